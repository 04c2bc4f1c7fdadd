"""Image edges: undistorting LSD segments against the geometry of the lens (known answers); LSD in
two bands against LSD on the whole image."""

from __future__ import annotations

import cv2
import numpy as np

from service.vision.estimate.edges import (
    Segments,
    detect_segments,
    detect_segments_in_bands,
    sample_segments,
    undistort_segments,
)
from service.vision.geometry.camera import Intrinsics, undistort_points
from tests.lens import distort_image
from tests.tolerances import (
    BANDS_COVER_DEG,
    BANDS_COVER_PX,
    BANDS_COVER_SHARE,
    ROUND_TRIP_ATOL,
    UNDISTORTED_EDGE_BIAS_PX,
    UNDISTORTED_EDGE_NEAR_PX,
)

W, H = 1280, 960
LENS = Intrinsics(1100.0, 1100.0, 643.0, 477.0, (-0.2, 0.0, 0.0, 0.0))


def test_without_distortion_the_segments_are_returned_as_they_are():
    seg = Segments(np.array([[10.0, 20.0]], np.float32), np.array([[110.0, 20.0]], np.float32),
                   np.zeros(1, np.float32), (H, W))
    assert undistort_segments(seg, Intrinsics(1100.0, 1100.0, 643.0, 477.0)) is seg


def test_pieces_are_the_undistorted_points_of_the_segment_in_order():
    """Brute force: a 100 px segment comes back as ceil(100 / split_px) contiguous pieces whose ends are
    undistort_points of the evenly spaced points of the distorted segment."""
    uv0, uv1 = np.array([30.0, 40.0]), np.array([90.0, 120.0])  # 100 px long, in the distorted corner
    seg = Segments(uv0[None].astype(np.float32), uv1[None].astype(np.float32), np.zeros(1, np.float32),
                   (H, W))
    out = undistort_segments(seg, LENS, split_px=16.0)
    assert len(out) == 7  # ceil(100 / 16)
    knots = undistort_points(uv0 + (uv1 - uv0) * (np.arange(8) / 7.0)[:, None], LENS)
    np.testing.assert_allclose(out.uv0, knots[:-1], atol=1e-3)  # float32 pixels
    np.testing.assert_allclose(out.uv1, knots[1:], atol=1e-3)
    d = knots[1:] - knots[:-1]
    np.testing.assert_allclose(out.theta_rad, np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi), atol=1e-5)
    assert out.image_shape == (H, W)
    np.testing.assert_allclose(out.uv0[1:], out.uv1[:-1], atol=ROUND_TRIP_ATOL)


def test_a_straight_edge_seen_through_the_lens_is_straight_again():
    """A straight step edge of the ideal image is a curve in the distorted one, and LSD fits long
    straight segments to it (their middles bulge off the curve, their ends fall short of it). The
    undistorted segments must lie on the ideal line without a bias to either side; undistorting only
    the endpoints and joining them puts the whole segment on one side by the fit's offset at its ends."""
    s = 4
    normal = np.array([1.0, -0.1]) / np.hypot(1.0, 0.1)  # the line u = 150 + 0.1 v, near the left border
    c = normal @ np.array([150.0, 0.0])
    vv, uu = np.mgrid[0:H * s, 0:W * s]
    side = ((uu + 0.5) / s - 0.5) * normal[0] + ((vv + 0.5) / s - 0.5) * normal[1] < c
    ideal = cv2.resize(np.where(side, 200.0, 60.0).astype(np.float32), (W, H), interpolation=cv2.INTER_AREA)
    img = np.clip(distort_image(ideal, LENS), 0, 255).astype(np.uint8)
    seg = undistort_segments(detect_segments(img, scale=1.0), LENS)
    uv, _ = sample_segments(seg, step_px=1.0)
    offset = uv.astype(np.float64) @ normal - c  # signed distance from the ideal line, px
    on_line = np.abs(offset) <= UNDISTORTED_EDGE_NEAR_PX
    assert on_line.mean() > 0.9
    assert abs(offset[on_line].mean()) <= UNDISTORTED_EDGE_BIAS_PX


def _covered(a: Segments, b: Segments) -> float:
    """Share of the points along ``a``'s segments (every px) within BANDS_COVER_PX of a segment of ``b``
    whose orientation is within BANDS_COVER_DEG (brute force over b's sampled points)."""
    from scipy.spatial import cKDTree

    pa, ia = sample_segments(a, step_px=1.0)
    pb, ib = sample_segments(b, step_px=0.25)  # 0.25 px apart: a point's nearest sample is its foot +-0.125
    near = cKDTree(pb).query_ball_point(pa, BANDS_COVER_PX)
    ok = 0
    for k, js in enumerate(near):
        d = np.abs(b.theta_rad[ib[js]] - a.theta_rad[ia[k]])
        ok += bool(np.any(np.minimum(d, np.pi - d) <= np.radians(BANDS_COVER_DEG)))
    return ok / len(pa)


def test_lsd_in_two_bands_finds_the_whole_images_segments(data_dir):
    """A cluttered render (hundreds of segments, many across the middle row): each detection's segments
    lie on the other's."""
    grey = cv2.imread(str(data_dir / "clutter" / "images" / "0002.png"), cv2.IMREAD_GRAYSCALE)
    whole, bands = detect_segments(grey), detect_segments_in_bands(grey)
    assert bands.image_shape == whole.image_shape == grey.shape
    middle = grey.shape[0] / 2
    crossing = (np.minimum(whole.uv0[:, 1], whole.uv1[:, 1]) < middle - 20) & (
        np.maximum(whole.uv0[:, 1], whole.uv1[:, 1]) > middle + 20)
    assert crossing.sum() >= 5  # the seam is exercised
    assert _covered(whole, bands) >= BANDS_COVER_SHARE
    assert _covered(bands, whole) >= BANDS_COVER_SHARE
