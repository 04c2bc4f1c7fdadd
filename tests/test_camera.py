"""Conventions of geometry/camera.py: K, projection, pixel centres under resize and crop, distortion."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from service.vision.geometry.camera import (
    Intrinsics,
    project,
    project_distorted,
    ray_direction,
    undistort_points,
    unproject,
)
from tests.tolerances import DISTORTION_ROUND_TRIP_PX, RESIZE_CENTROID_PX, ROUND_TRIP_ATOL

SEED = 20240602
INTR = Intrinsics(fx=1100.0, fy=1090.0, cx=643.0, cy=477.0)
W, H = 1280, 960


def points_in_view(rng: np.random.Generator, n: int, intr: Intrinsics = INTR, margin_px: float = 0.0):
    """(n, 3) mm, camera frame: random depths 300..1500 mm, projecting inside the image."""
    u = rng.uniform(margin_px, W - 1 - margin_px, n)
    v = rng.uniform(margin_px, H - 1 - margin_px, n)
    z = rng.uniform(300.0, 1500.0, n)
    return unproject(np.stack([u, v], 1), z, intr.K)


def test_K_and_from_K():
    K = INTR.K
    np.testing.assert_array_equal(K, [[1100, 0, 643], [0, 1090, 477], [0, 0, 1]])
    assert Intrinsics.from_K(K) == INTR
    assert Intrinsics.from_K(K, dist=[0, 0, 0, 0]).dist is None  # all-zero distortion is none
    assert Intrinsics.from_K(K, dist=[-0.2, 0, 0, 0]).dist == (-0.2, 0.0, 0.0, 0.0)


@pytest.mark.parametrize("z_mm", [100.0, 500.0, 2000.0])
def test_origin_on_optical_axis_projects_to_principal_point(z_mm):
    # object origin under T_cam_obj = [I | (0, 0, z)] lands at (cx, cy)
    uv = project(np.array([[0.0, 0.0, z_mm]]), INTR.K)
    np.testing.assert_allclose(uv, [[INTR.cx, INTR.cy]], atol=ROUND_TRIP_ATOL)


def test_project_known_answer():
    # 10 mm right and 20 mm down at 500 mm: u = cx + fx * 10/500, v = cy + fy * 20/500
    uv = project(np.array([[10.0, 20.0, 500.0]]), INTR.K)
    np.testing.assert_allclose(uv, [[643.0 + 22.0, 477.0 + 43.6]], atol=ROUND_TRIP_ATOL)


def test_project_unproject_round_trip():
    rng = np.random.default_rng(SEED)
    p = rng.uniform([-300, -300, 100], [300, 300, 2000], size=(200, 3))
    uv = project(p, INTR.K)
    np.testing.assert_allclose(unproject(uv, p[:, 2], INTR.K), p, atol=1e-9)
    uv2 = rng.uniform([0, 0], [W, H], size=(200, 2))
    z = rng.uniform(100, 2000, 200)
    np.testing.assert_allclose(project(unproject(uv2, z, INTR.K), INTR.K), uv2, atol=1e-9)


def test_ray_direction_is_unit_and_through_pixel():
    rng = np.random.default_rng(SEED + 1)
    uv = rng.uniform([0, 0], [W, H], size=(50, 2))
    d = ray_direction(uv, INTR.K)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=ROUND_TRIP_ATOL)
    np.testing.assert_allclose(project(d * 700.0, INTR.K), uv, atol=1e-9)
    np.testing.assert_allclose(ray_direction(np.array([INTR.cx, INTR.cy]), INTR.K), [[0, 0, 1]],
                               atol=ROUND_TRIP_ATOL)


@pytest.mark.parametrize("s", [0.5, 0.25, 2.0, 0.8])
def test_scaled_pixel_centre_rule(s):
    rng = np.random.default_rng(SEED + 2)
    p = points_in_view(rng, 50)
    uv = project(p, INTR.K)
    uv_s = project(p, INTR.scaled(s).K)
    np.testing.assert_allclose(uv_s, (uv + 0.5) * s - 0.5, atol=1e-9)
    sc = INTR.scaled(s)
    assert (sc.fx, sc.fy) == pytest.approx((INTR.fx * s, INTR.fy * s))
    # scaling back returns the original
    back = sc.scaled(1.0 / s)
    assert (back.fx, back.fy, back.cx, back.cy) == pytest.approx((INTR.fx, INTR.fy, INTR.cx, INTR.cy))


def _blob(u0: float, v0: float, shape=(64, 64), sigma=3.0) -> np.ndarray:
    v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    return np.exp(-((u - u0) ** 2 + (v - v0) ** 2) / (2 * sigma**2))


def _centroid_uv(img: np.ndarray) -> np.ndarray:
    v, u = np.mgrid[0:img.shape[0], 0:img.shape[1]].astype(float)
    return np.array([(img * u).sum() / img.sum(), (img * v).sum() / img.sum()])


@pytest.mark.parametrize(("s", "interp"), [(0.5, cv2.INTER_AREA), (0.25, cv2.INTER_AREA),
                                           (2.0, cv2.INTER_LINEAR), (0.5, cv2.INTER_LINEAR)])
def test_scaled_matches_cv2_resize(s, interp):
    """The same rule as OpenCV's resize: a blob at (u, v) lands at ((u+0.5)s-0.5, (v+0.5)s-0.5)."""
    u0, v0 = 30.3, 27.8
    img = _blob(u0, v0, sigma=4.0 if s < 0.5 else 3.0)
    small = cv2.resize(img, None, fx=s, fy=s, interpolation=interp)
    expected = (np.array([u0, v0]) + 0.5) * s - 0.5
    np.testing.assert_allclose(_centroid_uv(small), expected, atol=RESIZE_CENTROID_PX)
    # and the pixel-centre rule is what Intrinsics.scaled encodes
    intr = Intrinsics(100.0, 100.0, u0, v0)
    sc = intr.scaled(s)
    np.testing.assert_allclose([sc.cx, sc.cy], expected, atol=ROUND_TRIP_ATOL)


def test_shifted_is_a_crop():
    rng = np.random.default_rng(SEED + 3)
    p = points_in_view(rng, 50)
    du, dv = 123.0, 45.0
    np.testing.assert_allclose(project(p, INTR.shifted(du, dv).K), project(p, INTR.K) - [du, dv], atol=1e-9)
    # known answer with a real crop: a pixel marked at (u, v) is at (u - du, v - dv) in img[dv:, du:]
    img = np.zeros((H, W), np.uint8)
    img[300, 700] = 255  # img[v, u]
    crop = img[45:, 123:]
    vv, uu = np.nonzero(crop)
    assert (uu[0], vv[0]) == (700 - 123, 300 - 45)


def test_shifted_then_scaled_composes():
    # crop then resize: the composition is still a pinhole with the expected principal point
    sc = INTR.shifted(100, 50).scaled(0.5)
    assert sc.cx == pytest.approx((INTR.cx - 100 + 0.5) * 0.5 - 0.5)
    assert sc.cy == pytest.approx((INTR.cy - 50 + 0.5) * 0.5 - 0.5)


DIST_INTR = Intrinsics(fx=1100.0, fy=1100.0, cx=643.0, cy=477.0, dist=(-0.2, 0.0, 0.0, 0.0))


def test_distortion_known_direction():
    # barrel distortion (k1 < 0) pulls off-centre points towards the principal point; centre is fixed
    p = np.array([[0.0, 0.0, 500.0], [150.0, 100.0, 500.0]])
    ideal = project(p, DIST_INTR.K)
    dist = project_distorted(p, DIST_INTR)
    np.testing.assert_allclose(dist[0], ideal[0], atol=ROUND_TRIP_ATOL)
    c = np.array([DIST_INTR.cx, DIST_INTR.cy])
    assert np.linalg.norm(dist[1] - c) < np.linalg.norm(ideal[1] - c)
    # OpenCV's model: x_d = x (1 + k1 r^2)
    x, y = 150.0 / 500.0, 100.0 / 500.0
    f = 1 + -0.2 * (x * x + y * y)
    np.testing.assert_allclose(dist[1], [643.0 + 1100.0 * x * f, 477.0 + 1100.0 * y * f], atol=1e-9)


def test_no_distortion_is_pinhole():
    rng = np.random.default_rng(SEED + 4)
    p = points_in_view(rng, 20)
    np.testing.assert_allclose(project_distorted(p, INTR), project(p, INTR.K), atol=ROUND_TRIP_ATOL)
    uv = project(p, INTR.K)
    np.testing.assert_allclose(undistort_points(uv, INTR), uv, atol=ROUND_TRIP_ATOL)


def test_distortion_round_trip_k1_minus_0p2():
    """undistort_points(project_distorted(p)) gives back the pinhole projection over the whole image."""
    rng = np.random.default_rng(SEED + 5)
    p = points_in_view(rng, 300, DIST_INTR)
    # and the four image corners, where the distortion is largest
    corners = unproject(np.array([[0.0, 0.0], [W - 1, 0], [0, H - 1], [W - 1, H - 1]]), np.full(4, 600.0),
                        DIST_INTR.K)
    p = np.vstack([p, corners])
    ideal = project(p, DIST_INTR.K)
    back = undistort_points(project_distorted(p, DIST_INTR), DIST_INTR)
    np.testing.assert_allclose(back, ideal, atol=DISTORTION_ROUND_TRIP_PX)


def test_ray_rotations_take_the_optical_axis_onto_each_pixel_ray():
    from service.vision.geometry.camera import ray_rotations

    uv = np.array([[643.0, 477.0], [0.0, 0.0], [1279.0, 959.0], [100.0, 900.0]])
    d, R = ray_rotations(uv, INTR.K)
    for k in range(len(uv)):
        assert R[k] @ np.array([0.0, 0.0, 1.0]) == pytest.approx(d[k], abs=1e-12)
        assert R[k] @ R[k].T == pytest.approx(np.eye(3), abs=1e-12)
        assert np.linalg.det(R[k]) == pytest.approx(1.0)
        # the ray really passes through the pixel
        assert (INTR.K @ d[k])[:2] / d[k][2] == pytest.approx(uv[k], abs=1e-9)
    assert R[0] == pytest.approx(np.eye(3), abs=1e-12)


def test_project_takes_any_batch_shape_and_pinhole_drops_only_the_lens():
    rng = np.random.default_rng(3)
    p = rng.uniform([-100, -100, 300], [100, 100, 900], (4, 5, 3))
    uv = project(p, INTR.K)
    assert uv.shape == (4, 5, 2)
    np.testing.assert_allclose(uv.reshape(-1, 2), project(p.reshape(-1, 3), INTR.K), atol=ROUND_TRIP_ATOL)
    # the origin on the optical axis projects to the principal point
    np.testing.assert_allclose(project(np.array([0.0, 0.0, 500.0]), INTR.K), [INTR.cx, INTR.cy])
    lens = Intrinsics(INTR.fx, INTR.fy, INTR.cx, INTR.cy, (-0.2, 0.0, 0.0, 0.0))
    assert lens.pinhole() == Intrinsics(INTR.fx, INTR.fy, INTR.cx, INTR.cy)
