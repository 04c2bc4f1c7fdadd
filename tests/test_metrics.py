"""Known-answer tests of service/vision/reference/metrics.py."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.vision.geometry.frames import Pose, Rx, Ry, Rz, canonical_spin
from service.vision.reference import metrics as m
from tests.tolerances import METRIC_ATOL, ROUND_TRIP_ATOL, SYM_DISCRETISATION_DEG

SEED = 20240603
K = np.array([[1000.0, 0.0, 640.0], [0.0, 1000.0, 480.0], [0.0, 0.0, 1.0]])
Y = np.array([0.0, 1.0, 0.0])


def cylinder_points(n_ring: int = 72, radius: float = 30.0, height: float = 200.0, centre=(0.0, 0.0, 0.0)):
    """(N, 3) mm: rings of a cylinder about +y through ``centre`` (symmetric for spins of 360/n_ring)."""
    phi = np.deg2rad(np.arange(n_ring) * 360.0 / n_ring)
    ys = np.linspace(0.0, height, 11)
    pts = np.array([[radius * np.cos(p), y, radius * np.sin(p)] for y in ys for p in phi])
    return pts + np.asarray(centre, float)


def box_points():
    """(8, 3) mm: corners of an asymmetric box."""
    return np.array([[x, y, z] for x in (0.0, 100.0) for y in (0.0, 60.0) for z in (0.0, 30.0)])


def spin(axis, deg):
    return Rotation.from_rotvec(np.deg2rad(deg) * np.asarray(axis, float) / np.linalg.norm(axis)).as_matrix()


T0 = np.array([10.0, -20.0, 500.0])


# --- te, re, axis ---------------------------------------------------------------------------------


def test_te_known_answers():
    assert m.te_mm(T0 + [1.0, 0, 0], T0) == pytest.approx(1.0)
    assert m.te_mm(T0 + [3.0, 4.0, 0], T0) == pytest.approx(5.0)
    assert m.te_mm(T0, T0) == 0.0


def test_re_known_answers():
    assert m.re_deg(Rz(90), np.eye(3)) == pytest.approx(90.0)
    assert m.re_deg(Rx(30) @ Ry(10), Rx(30) @ Ry(10)) == pytest.approx(0.0, abs=1e-6)
    assert m.re_deg(Ry(-170), Ry(170)) == pytest.approx(20.0)
    assert m.re_deg(np.eye(3), Rx(180)) == pytest.approx(180.0)


def test_axis_error_known_answers():
    # spinning about the axis leaves it; tilting the axis by 25 deg gives 25
    R = Rx(20) @ Rz(-35)
    assert m.axis_error_deg(R @ spin(Y, 77), R, Y) == pytest.approx(0.0, abs=1e-6)
    assert m.axis_error_deg(Rx(25) @ R, R, Y) == pytest.approx(m.axis_error_deg(Rx(25), np.eye(3), R @ Y))
    assert m.axis_error_deg(Rz(25), np.eye(3), Y) == pytest.approx(25.0)
    assert m.axis_error_deg(Rz(25), np.eye(3), [0, 0, 1]) == pytest.approx(0.0, abs=1e-6)


def test_axis_error_is_the_symmetry_aware_rotation_error():
    rng = np.random.default_rng(SEED)
    Rs, _ = m.symmetry_rotations(Y, n=3600)
    for R_e, R_g in Rotation.random(10, random_state=rng).as_matrix().reshape(5, 2, 3, 3):
        brute = min(m.re_deg(R_e, R_g @ S) for S in Rs)
        assert m.axis_error_deg(R_e, R_g, Y) == pytest.approx(brute, abs=SYM_DISCRETISATION_DEG / 10)


# --- symmetry transforms ----------------------------------------------------------------------------


def test_symmetry_rotations_none_is_identity():
    Rs, ts = m.symmetry_rotations(None)
    np.testing.assert_array_equal(Rs, np.eye(3)[None])
    np.testing.assert_array_equal(ts, np.zeros((1, 3)))


def test_symmetry_rotations_about_axis_through_point():
    c = np.array([5.0, 0.0, -7.0])
    Rs, ts = m.symmetry_rotations([0, 2, 0], point_obj=c, n=8)
    assert Rs.shape == (8, 3, 3) and ts.shape == (8, 3)
    np.testing.assert_allclose(Rs[0], np.eye(3), atol=ROUND_TRIP_ATOL)
    np.testing.assert_allclose(Rs[2], Ry(90), atol=ROUND_TRIP_ATOL)
    for R, t in zip(Rs, ts, strict=True):
        # points on the axis stay put; the axis direction is kept
        for s in (0.0, 10.0, -50.0):
            np.testing.assert_allclose(R @ (c + s * Y) + t, c + s * Y, atol=1e-9)
        np.testing.assert_allclose(R @ Y, Y, atol=ROUND_TRIP_ATOL)
    # the off-axis cylinder is mapped onto itself (as a point set) by every spin of 45 deg
    pts = cylinder_points(n_ring=8, centre=c)
    for R, t in zip(Rs, ts, strict=True):
        moved = pts @ R.T + t
        d = np.min(np.linalg.norm(moved[:, None] - pts[None], axis=2), axis=1)
        assert d.max() < 1e-9


def test_best_spin_deg_recovers_a_spin():
    rng = np.random.default_rng(SEED + 3)
    for R_g in Rotation.random(10, random_state=rng).as_matrix():
        for phi in (0.0, 12.345, -170.0, 95.5):
            assert m.best_spin_deg(R_g @ spin(Y, phi), R_g, Y) == pytest.approx(phi, abs=1e-7)
    # with the axis also off by a tilt, it is still the minimiser of the geodesic error
    R_g = Rx(20) @ Rz(10)
    R_e = Rx(23) @ R_g @ spin(Y, 40.0)
    phis = np.arange(0.0, 80.0, 0.01)
    brute = phis[np.argmin([m.re_deg(R_e, R_g @ spin(Y, p)) for p in phis])]
    assert m.best_spin_deg(R_e, R_g, Y) == pytest.approx(brute, abs=0.01)


def test_pose_symmetries_make_an_off_grid_spin_exact():
    pts = cylinder_points(n_ring=72)
    R_g, t_g = Rx(-30) @ Rz(40), np.array([20.0, -10.0, 300.0])
    R_e = R_g @ spin(Y, 37.4321)  # off the 1 deg grid
    coarse = m.symmetry_rotations(Y, n=360)
    fine = m.pose_symmetries(R_e, R_g, Y)
    assert m.mspd_px(R_e, t_g, R_g, t_g, K, pts, coarse) > 0.05
    assert m.mspd_px(R_e, t_g, R_g, t_g, K, pts, fine) < 0.01
    assert m.mssd_mm(R_e, t_g, R_g, t_g, pts, fine) < 0.01
    Rs, ts = m.pose_symmetries(R_e, R_g, None)
    assert Rs.shape == (1, 3, 3)


# --- MSPD, MSSD, ADD, ADD-S ---------------------------------------------------------------------------


def test_identical_poses_give_zero_everywhere():
    pts = box_points()
    R = Rx(10) @ Rz(20)
    assert m.mspd_px(R, T0, R, T0, K, pts) == pytest.approx(0.0, abs=METRIC_ATOL)
    assert m.mssd_mm(R, T0, R, T0, pts) == pytest.approx(0.0, abs=METRIC_ATOL)
    assert m.add_mm(R, T0, R, T0, pts) == pytest.approx(0.0, abs=METRIC_ATOL)
    assert m.add_s_mm(R, T0, R, T0, pts) == pytest.approx(0.0, abs=METRIC_ATOL)


def test_pure_translation_known_answers():
    pts = box_points()
    R = Rx(10) @ Rz(20)
    shift = np.array([1.0, 0.0, 0.0])
    assert m.te_mm(T0 + shift, T0) == pytest.approx(1.0)
    assert m.add_mm(R, T0 + shift, R, T0, pts) == pytest.approx(1.0)
    assert m.mssd_mm(R, T0 + shift, R, T0, pts) == pytest.approx(1.0)
    assert m.mssd_mm(R, T0 + [0, 2.0, 0], R, T0, pts, syms=m.symmetry_rotations(None)) == pytest.approx(2.0)


def test_mspd_of_a_known_pixel_shift():
    """A fronto-parallel planar object shifted by d mm at depth z moves every point by fx d / z px."""
    pts = np.array([[x, y, 0.0] for x in (-50.0, 0.0, 50.0) for y in (-30.0, 30.0)])
    t_g = np.array([0.0, 0.0, 500.0])
    t_e = t_g + [2.0, 0.0, 0.0]  # 2 mm at 500 mm with fx = 1000: 4 px
    assert m.mspd_px(np.eye(3), t_e, np.eye(3), t_g, K, pts) == pytest.approx(4.0)
    t_e = t_g + [0.0, -1.5, 0.0]  # 3 px upwards
    assert m.mspd_px(np.eye(3), t_e, np.eye(3), t_g, K, pts) == pytest.approx(3.0)
    # a 3D part moved parallel to the image: the nearest points move most (max over points)
    pts3 = box_points()
    R = Rx(15) @ Ry(-25)
    t_e = T0 + [1.0, 0, 0]
    z_min = (pts3 @ R.T + T0)[:, 2].min()
    assert m.mspd_px(R, t_e, R, T0, K, pts3) == pytest.approx(1000.0 * 1.0 / z_min)


def test_ninety_degree_rotation():
    pts = box_points()
    assert m.re_deg(Rz(90), np.eye(3)) == pytest.approx(90.0)
    # ADD of a 90 deg rotation about z (through the origin) of a point at radius r moves it r * sqrt(2)
    p = np.array([[100.0, 0.0, 0.0]])
    assert m.add_mm(Rz(90), T0, np.eye(3), T0, p) == pytest.approx(100.0 * np.sqrt(2))
    assert m.add_mm(Rz(90), T0, np.eye(3), T0, pts) > 10.0


@pytest.mark.parametrize("centre", [(0.0, 0.0, 0.0), (12.0, 0.0, -8.0)])
def test_spinning_a_symmetric_part(centre):
    """Spin about the axis: MSPD, MSSD, ADD-S ~ 0 with the symmetry; ADD and plain MSPD are not."""
    pts = cylinder_points(n_ring=72, centre=centre)
    syms = m.symmetry_rotations(Y, point_obj=np.asarray(centre), n=360)
    R_g = Rx(-30) @ Rz(40)
    t_g = np.array([20.0, -10.0, 600.0])
    S, s_t = syms[0][37], syms[1][37]  # a 37 deg spin about the axis through ``centre``
    R_e, t_e = R_g @ S, R_g @ s_t + t_g
    assert m.mspd_px(R_e, t_e, R_g, t_g, K, pts, syms) == pytest.approx(0.0, abs=METRIC_ATOL)
    assert m.mssd_mm(R_e, t_e, R_g, t_g, pts, syms) == pytest.approx(0.0, abs=METRIC_ATOL)
    # 37 deg is not a multiple of the 5 deg ring spacing: ADD-S is small but not exactly 0
    assert m.add_s_mm(R_e, t_e, R_g, t_g, pts) < 30.0 * np.deg2rad(2.5)
    assert m.add_mm(R_e, t_e, R_g, t_g, pts) > 10.0
    assert m.mspd_px(R_e, t_e, R_g, t_g, K, pts) > 10.0  # without the symmetry it is a large error
    # a spin that is a multiple of the ring spacing maps the sampled points onto themselves
    S, s_t = syms[0][40], syms[1][40]
    assert m.add_s_mm(R_g @ S, R_g @ s_t + t_g, R_g, t_g, pts) == pytest.approx(0.0, abs=METRIC_ATOL)


def test_mspd_symmetric_with_pure_rotation_array():
    pts = cylinder_points()
    Rs, _ = m.symmetry_rotations(Y, n=360)
    R_g = Rx(20)
    assert m.mspd_px(R_g @ Ry(90), T0, R_g, T0, K, pts, Rs) == pytest.approx(0.0, abs=METRIC_ATOL)


def test_add_s_at_most_add():
    rng = np.random.default_rng(SEED + 1)
    pts = rng.uniform(-50, 50, (300, 3))
    for R in Rotation.random(5, random_state=rng).as_matrix():
        t = T0 + rng.normal(0, 5, 3)
        assert m.add_s_mm(R, t, np.eye(3), T0, pts) <= m.add_mm(R, t, np.eye(3), T0, pts) + 1e-12


def test_diameter_and_recall():
    assert m.diameter_mm(box_points()) == pytest.approx(np.sqrt(100**2 + 60**2 + 30**2))
    assert m.diameter_mm(np.array([[0.0, 0, 0], [3.0, 4.0, 0]])) == pytest.approx(5.0)
    assert m.recall([1.0, 4.9, 5.0, 7.0], 5.0) == pytest.approx(0.5)  # strictly below
    assert m.recall([1.0, np.nan, np.inf], 5.0) == pytest.approx(1 / 3)
    assert np.isnan(m.recall([], 5.0))


# --- the paper's Table VI columns ---------------------------------------------------------------------


def test_paper_errors_translation():
    e = m.paper_errors(np.eye(3), T0 + [-1.0, 2.0, -3.0], np.eye(3), T0, Y)
    assert (e["tx_mm"], e["ty_mm"], e["tz_mm"]) == pytest.approx((1.0, 2.0, 3.0))


def test_paper_errors_symmetric_alpha_gamma():
    # the axis written as Rx(alpha) Rz(gamma) e_y: errors are the differences of alpha and of gamma
    R_g = Rx(10.0) @ Rz(20.0)
    R_e = Rx(12.5) @ Rz(19.0) @ Ry(123.0)  # any spin about the axis: no effect
    e = m.paper_errors(R_e, T0, R_g, T0, Y)
    assert e["symmetric"] is True
    assert (e["rx_deg"], e["rz_deg"]) == pytest.approx((2.5, 1.0))
    assert np.isnan(e["ry_deg"])
    assert e["re_deg"] == pytest.approx(m.axis_error_deg(R_e, R_g, Y))
    # alpha wraps across +-180
    e = m.paper_errors(Rx(179.0), T0, Rx(-179.0), T0, Y)
    assert e["rx_deg"] == pytest.approx(2.0)


def test_paper_errors_symmetric_is_spin_invariant():
    rng = np.random.default_rng(SEED + 2)
    for R_e, R_g in Rotation.random(20, random_state=rng).as_matrix().reshape(10, 2, 3, 3):
        e1 = m.paper_errors(R_e, T0, R_g, T0, Y)
        e2 = m.paper_errors(R_e @ spin(Y, 71.0), T0, canonical_spin(Pose(R_g, np.zeros(3)), Y).R, T0, Y)
        for k in ("rx_deg", "rz_deg", "re_deg"):
            assert e1[k] == pytest.approx(e2[k], abs=1e-7)


def test_paper_errors_symmetric_axis_off_origin():
    # spinning about an axis through c changes t but not the error measured at c
    c = np.array([10.0, 0.0, 0.0])
    syms = m.symmetry_rotations(Y, point_obj=c, n=4)
    S, s_t = syms[0][1], syms[1][1]
    R_g = Rx(10)
    e = m.paper_errors(R_g @ S, R_g @ s_t + T0, R_g, T0, Y, point_obj=c)
    assert max(e["tx_mm"], e["ty_mm"], e["tz_mm"], e["rx_deg"], e["rz_deg"]) == pytest.approx(0.0, abs=1e-9)


def test_paper_errors_non_symmetric_euler():
    R_g = Rx(10.0) @ Ry(20.0) @ Rz(30.0)
    R_e = Rx(11.0) @ Ry(20.0) @ Rz(28.0)
    e = m.paper_errors(R_e, T0, R_g, T0)
    assert e["symmetric"] is False
    assert (e["rx_deg"], e["ry_deg"], e["rz_deg"]) == pytest.approx((1.0, 0.0, 2.0), abs=1e-7)
    assert e["re_deg"] == pytest.approx(m.re_deg(R_e, R_g))
    # rz wraps across +-180
    e = m.paper_errors(Rz(-178.0), T0, Rz(178.0), T0)
    assert e["rz_deg"] == pytest.approx(4.0)
    assert e["re_deg"] == pytest.approx(4.0)


def test_wrap_deg():
    np.testing.assert_allclose(m.wrap_deg([0.0, 190.0, -190.0, 360.0, 540.0]),
                               [0.0, -170.0, 170.0, 0.0, -180.0])
