"""Overlay: coarse contour dashed, refined contour solid, at the silhouette border's pixels."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose
from service.vision.geometry.render import render
from service.vision.overlay import COARSE_BGR, REFINED_BGR, draw_overlay, encode_png
from tests.tolerances import OVERLAY_ON_BORDER_PX

INTR = Intrinsics(fx=1100.0, fy=1100.0, cx=643.0, cy=477.0)
SIZE = (1280, 960)
REFINED = Pose.from_euler_xyz_deg((25.0, -35.0, 15.0), (40.0, -30.0, 500.0))
COARSE = Pose.from_euler_xyz_deg((25.0, -35.0, 15.0), (52.0, -30.0, 500.0))  # 12 mm ~ 26 px to the right


@pytest.fixture(scope="module")
def bank(tless06_mesh):
    from service.vision.build.templates import build_bank

    return build_bank(tless06_mesh, symmetry="none", grid={"render_px": 100, "supersample": 1,
                                                           "view_step_deg": 60.0})


def _pixels(img, bgr):
    return np.all(img == np.array(bgr, np.uint8), axis=2)


def _dilated(m):
    return cv2.dilate(m.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)


def _border_distance(bank, pose):
    m = render(bank.vertices_mm, bank.faces, pose, INTR, SIZE).mask.astype(np.uint8)
    border = m - cv2.erode(m, np.ones((3, 3), np.uint8))
    return cv2.distanceTransform((border == 0).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


def test_refined_contour_is_solid_on_the_silhouette_border(bank):
    grey = np.full((SIZE[1], SIZE[0]), 70, np.uint8)
    out = draw_overlay(grey, bank, INTR, COARSE, REFINED)
    assert out.shape == (SIZE[1], SIZE[0], 3) and out.dtype == np.uint8
    red = _pixels(out, REFINED_BGR)
    d = _border_distance(bank, REFINED)
    assert red.sum() > 200
    assert np.all(d[red] <= OVERLAY_ON_BORDER_PX)
    # Solid: the refined border is covered almost everywhere (the coarse one may cross it).
    near = d <= 0.5
    assert _dilated(red)[near].mean() > 0.97


def test_coarse_contour_is_dashed_on_its_own_border(bank):
    grey = np.full((SIZE[1], SIZE[0]), 70, np.uint8)
    out = draw_overlay(grey, bank, INTR, COARSE, None)
    green = _pixels(out, COARSE_BGR)
    d = _border_distance(bank, COARSE)
    assert green.sum() > 100
    assert np.all(d[green] <= OVERLAY_ON_BORDER_PX)
    covered = _dilated(green)[d <= 0.5].mean()
    assert 0.3 < covered < 0.75  # dashes: about half the border is drawn
    assert not _pixels(out, REFINED_BGR).any()


def test_colour_input_is_kept_and_png_round_trips(bank):
    bgr = np.zeros((SIZE[1], SIZE[0], 3), np.uint8)
    bgr[..., 0] = 200
    out = draw_overlay(bgr, bank, INTR, None, REFINED)
    assert out[0, 0].tolist() == [200, 0, 0]
    png = encode_png(out)
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    back = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    np.testing.assert_array_equal(back, out)


def test_nothing_to_draw_returns_the_image_in_bgr(bank):
    grey = np.arange(SIZE[0] * SIZE[1], dtype=np.uint32).reshape(SIZE[1], SIZE[0]).astype(np.uint8)
    out = draw_overlay(grey, bank, INTR, None, None)
    np.testing.assert_array_equal(out[..., 0], grey)
    np.testing.assert_array_equal(out[..., 2], grey)
