"""Colour edges (Canny on the colour image, for the proposal engine): known answers."""

from __future__ import annotations

import numpy as np
import pytest

from service.vision.estimate.colour_edges import canny_tensor
from service.vision.estimate.edges import detect_segments, to_grey_u8

# BGR colours of equal grey level (0.114 B + 0.587 G + 0.299 R = 100): the rectangle has no grey edge.
FLOOR_BGR, PART_BGR = (100, 100, 100), (95, 50, 200)


def _isoluminant_rectangle() -> np.ndarray:
    img = np.zeros((200, 200, 3), np.uint8)
    img[:] = FLOOR_BGR
    img[80:120, 60:140] = PART_BGR  # rows v 80..119, columns u 60..139
    return img


def test_isoluminant_rectangle_has_no_grey_edge():
    grey = to_grey_u8(_isoluminant_rectangle())
    assert int(grey.max()) - int(grey.min()) <= 1
    assert len(detect_segments(grey)) == 0


def test_canny_tensor_finds_the_colour_outline_in_its_orientation_channel():
    dtt = canny_tensor(_isoluminant_rectangle(), n_channels=16, scale=1.0)
    # The top and bottom sides (v = 79.5, 119.5) are horizontal: channel 0; the left and right sides
    # (u = 59.5, 139.5) vertical: channel 8 of 16.
    assert min(dtt.dt[0, 79, 100], dtt.dt[0, 80, 100]) <= 1.0
    assert min(dtt.dt[0, 119, 100], dtt.dt[0, 120, 100]) <= 1.0
    assert min(dtt.dt[8, 100, 59], dtt.dt[8, 100, 60]) <= 1.0
    assert min(dtt.dt[8, 100, 139], dtt.dt[8, 100, 140]) <= 1.0
    # Far from the outline (the floor's corner) only the truncation.
    assert dtt.dt[:, 5, 5].min() == pytest.approx(dtt.tau_px)


def test_canny_tensor_reads_sixteen_bit_and_bgra_images_as_their_eight_bit_colour():
    img = _isoluminant_rectangle()
    ref = canny_tensor(img, scale=1.0).dt
    bgra = np.concatenate([img, np.full(img.shape[:2] + (1,), 255, np.uint8)], axis=2)
    np.testing.assert_array_equal(canny_tensor(bgra, scale=1.0).dt, ref)
    sixteen = img.astype(np.uint16) * 4  # a 10-bit sensor's levels: stretched back to 0..255 by its max
    assert canny_tensor(sixteen, scale=1.0).dt[8, 100, 59:61].min() <= 1.0


def test_canny_tensor_box_keeps_only_the_edges_inside():
    dtt = canny_tensor(_isoluminant_rectangle(), n_channels=16, scale=1.0,
                       box_uv=(np.array([0.0, 0.0]), np.array([100.0, 199.0])))
    assert min(dtt.dt[8, 100, 59], dtt.dt[8, 100, 60]) <= 1.0  # the left side is in the box
    assert dtt.dt[8, 100, 139] > 10.0  # the right side (u = 139.5) is not
