"""Conventions of geometry/frames.py: eq. 3, euler/R/quaternion, poses, a revolved part's canonical spin."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.vision.geometry import frames
from service.vision.geometry.frames import (
    Pose,
    R_between,
    R_from_euler_xyz_deg,
    R_from_quat_xyzw,
    Rx,
    Ry,
    Rz,
    axis_alpha_gamma_deg,
    canonical_spin,
    euler_xyz_deg_from_R,
    quat_xyzw_from_R,
    rotation_angle_deg,
)
from tests.tolerances import DATASET_ANGLE_ATOL_DEG, ROUND_TRIP_ATOL

SEED = 20240601


def random_euler_deg(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3) degrees with ry away from the XYZ gimbal lock at +-90 (so the angles are unique)."""
    e = rng.uniform(-179.0, 179.0, size=(n, 3))
    e[:, 1] = rng.uniform(-85.0, 85.0, size=n)
    return e


def random_R(rng: np.random.Generator, n: int) -> np.ndarray:
    return Rotation.random(n, random_state=rng).as_matrix()


def spin(axis: np.ndarray, deg: float) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return Rotation.from_rotvec(np.deg2rad(deg) * axis).as_matrix()


# --- elementary rotations and eq. 3 -------------------------------------------------------------


def test_elementary_rotations_known_answers():
    # Right-handed, active: Rz(90) takes x to y, Rx(90) takes y to z, Ry(90) takes z to x.
    np.testing.assert_allclose(Rz(90) @ [1, 0, 0], [0, 1, 0], atol=ROUND_TRIP_ATOL)
    np.testing.assert_allclose(Rx(90) @ [0, 1, 0], [0, 0, 1], atol=ROUND_TRIP_ATOL)
    np.testing.assert_allclose(Ry(90) @ [0, 0, 1], [1, 0, 0], atol=ROUND_TRIP_ATOL)


def test_eq3_equals_R_from_euler_and_scipy_uppercase_XYZ():
    rng = np.random.default_rng(SEED)
    for rx, ry, rz in random_euler_deg(rng, 50):
        eq3 = Rx(rx) @ Ry(ry) @ Rz(rz)
        np.testing.assert_allclose(R_from_euler_xyz_deg([rx, ry, rz]), eq3, atol=ROUND_TRIP_ATOL)
        np.testing.assert_allclose(Rotation.from_euler("XYZ", [rx, ry, rz], degrees=True).as_matrix(), eq3,
                                   atol=ROUND_TRIP_ATOL)


def test_lowercase_xyz_is_a_different_matrix():
    # Lowercase (extrinsic) "xyz" is Rz @ Ry @ Rx: not eq. 3 in general ...
    rx, ry, rz = 30.0, 40.0, 50.0
    eq3 = Rx(rx) @ Ry(ry) @ Rz(rz)
    lower = Rotation.from_euler("xyz", [rx, ry, rz], degrees=True).as_matrix()
    np.testing.assert_allclose(lower, Rz(rz) @ Ry(ry) @ Rx(rx), atol=ROUND_TRIP_ATOL)
    assert np.max(np.abs(lower - eq3)) > 0.1
    # ... but the same as extrinsic "zyx" with the angles reversed.
    np.testing.assert_allclose(Rotation.from_euler("zyx", [rz, ry, rx], degrees=True).as_matrix(), eq3,
                               atol=ROUND_TRIP_ATOL)


def test_batched_euler():
    rng = np.random.default_rng(SEED + 1)
    e = random_euler_deg(rng, 7)
    Rs = R_from_euler_xyz_deg(e)
    assert Rs.shape == (7, 3, 3)
    for k in range(7):
        np.testing.assert_allclose(Rs[k], Rx(e[k, 0]) @ Ry(e[k, 1]) @ Rz(e[k, 2]), atol=ROUND_TRIP_ATOL)


# --- round trips ---------------------------------------------------------------------------------


def test_euler_R_round_trip():
    rng = np.random.default_rng(SEED + 2)
    for e in random_euler_deg(rng, 100):
        np.testing.assert_allclose(euler_xyz_deg_from_R(R_from_euler_xyz_deg(e)), e, atol=1e-7)
    for R in random_R(rng, 100):
        np.testing.assert_allclose(R_from_euler_xyz_deg(euler_xyz_deg_from_R(R)), R, atol=ROUND_TRIP_ATOL)


def test_quat_R_round_trip_and_order_xyzw():
    rng = np.random.default_rng(SEED + 3)
    for R in random_R(rng, 100):
        q = quat_xyzw_from_R(R)
        assert q.shape == (4,)
        np.testing.assert_allclose(np.linalg.norm(q), 1.0, atol=ROUND_TRIP_ATOL)
        np.testing.assert_allclose(R_from_quat_xyzw(q), R, atol=ROUND_TRIP_ATOL)
    # Known answer: 90 deg about z is (x, y, z, w) = (0, 0, sin 45, cos 45); w is LAST.
    q = quat_xyzw_from_R(Rz(90))
    q = q * np.sign(q[3])
    np.testing.assert_allclose(q, [0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=ROUND_TRIP_ATOL)


def test_trimesh_quaternion_is_wxyz_not_ours():
    transformations = pytest.importorskip("trimesh.transformations")
    rng = np.random.default_rng(SEED + 4)
    for R in random_R(rng, 20):
        T = np.eye(4)
        T[:3, :3] = R
        q_wxyz = transformations.quaternion_from_matrix(T)
        q_xyzw = quat_xyzw_from_R(R)
        # The same rotation, components rolled by one (and possibly of opposite sign).
        rolled = np.roll(q_wxyz, -1)
        assert min(np.max(np.abs(rolled - q_xyzw)), np.max(np.abs(rolled + q_xyzw))) < 1e-9
    # Fed to scipy as if it were xyzw, trimesh's quaternion gives a different rotation.
    T = np.eye(4)
    T[:3, :3] = Rz(90)
    wrong = R_from_quat_xyzw(transformations.quaternion_from_matrix(T))
    assert rotation_angle_deg(wrong, Rz(90)) > 1.0


def test_pose_euler_and_matrix_constructors():
    p = Pose.from_euler_xyz_deg([10, 20, 30], [1, 2, 3])
    np.testing.assert_allclose(p.R, Rx(10) @ Ry(20) @ Rz(30), atol=ROUND_TRIP_ATOL)
    np.testing.assert_allclose(p.euler_xyz_deg(), [10, 20, 30], atol=1e-9)
    T = p.as_matrix()
    np.testing.assert_allclose(T[3], [0, 0, 0, 1])
    q = Pose.from_matrix(T)
    np.testing.assert_allclose(q.R, p.R)
    np.testing.assert_allclose(q.t_mm, [1, 2, 3])


def test_pose_apply_known_answer():
    # p_cam = R @ p_obj + t: 90 deg about z then 500 mm forward.
    T_cam_obj = Pose(Rz(90), np.array([0.0, 0.0, 500.0]))
    np.testing.assert_allclose(T_cam_obj.apply(np.array([[10.0, 0.0, 0.0]])), [[0.0, 10.0, 500.0]],
                               atol=ROUND_TRIP_ATOL)


def test_pose_compose_inverse_apply_round_trips():
    rng = np.random.default_rng(SEED + 5)
    Rs = random_R(rng, 30)
    ts = rng.uniform(-500, 500, size=(30, 3))
    pts = rng.uniform(-100, 100, size=(25, 3))
    for k in range(10):
        T_a_b = Pose(Rs[3 * k], ts[3 * k])
        T_b_c = Pose(Rs[3 * k + 1], ts[3 * k + 1])
        T_a_c = T_a_b.compose(T_b_c)
        # compose = matrix product, and applying it = applying the two in turn (inner frames cancel)
        np.testing.assert_allclose(T_a_c.as_matrix(), T_a_b.as_matrix() @ T_b_c.as_matrix(), atol=1e-9)
        np.testing.assert_allclose(T_a_c.apply(pts), T_a_b.apply(T_b_c.apply(pts)), atol=1e-9)
        # inverse undoes apply, and T @ T^-1 = identity
        np.testing.assert_allclose(T_a_b.inverse().apply(T_a_b.apply(pts)), pts, atol=1e-9)
        ident = T_a_b.compose(T_a_b.inverse())
        np.testing.assert_allclose(ident.R, np.eye(3), atol=ROUND_TRIP_ATOL)
        np.testing.assert_allclose(ident.t_mm, np.zeros(3), atol=1e-9)
        # (T_a_b T_b_c)^-1 = T_b_c^-1 T_a_b^-1
        np.testing.assert_allclose(T_a_c.inverse().as_matrix(),
                                   T_b_c.inverse().compose(T_a_b.inverse()).as_matrix(), atol=1e-9)


def test_rotation_angle_deg_known_answers():
    assert rotation_angle_deg(np.eye(3), Rz(90)) == pytest.approx(90.0)
    assert rotation_angle_deg(Rx(10), Rx(-20)) == pytest.approx(30.0)
    assert rotation_angle_deg(np.eye(3), Ry(180)) == pytest.approx(180.0)
    assert rotation_angle_deg(Rz(33), Rz(33)) == pytest.approx(0.0, abs=1e-6)


# --- R_between ------------------------------------------------------------------------------------


def test_R_between_random_pairs():
    rng = np.random.default_rng(SEED + 6)
    for _ in range(50):
        a, b = rng.normal(size=(2, 3))
        R = R_between(a, b)
        ua, ub = a / np.linalg.norm(a), b / np.linalg.norm(b)
        np.testing.assert_allclose(R @ ua, ub, atol=ROUND_TRIP_ATOL)
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=ROUND_TRIP_ATOL)
        assert np.linalg.det(R) == pytest.approx(1.0)
        # the smallest such rotation: its angle is the angle between a and b
        angle = np.degrees(np.arccos(np.clip(ua @ ub, -1, 1)))
        assert rotation_angle_deg(np.eye(3), R) == pytest.approx(angle, abs=1e-7)


@pytest.mark.parametrize("a", [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 2, 3]])
def test_R_between_parallel_and_antiparallel(a):
    a = np.asarray(a, float)
    np.testing.assert_allclose(R_between(a, 3 * a), np.eye(3), atol=ROUND_TRIP_ATOL)
    R = R_between(a, -a)
    np.testing.assert_allclose(R @ (a / np.linalg.norm(a)), -a / np.linalg.norm(a), atol=ROUND_TRIP_ATOL)
    assert np.linalg.det(R) == pytest.approx(1.0)


# --- continuous symmetry: alpha/gamma and the canonical pose -------------------------------------


def test_axis_alpha_gamma_known_answers_and_round_trip():
    assert axis_alpha_gamma_deg([0, 1, 0]) == pytest.approx((0.0, 0.0))
    # Rx(90) e_y = e_z: alpha 90; Rz(30) e_y = (-sin 30, cos 30, 0): gamma 30.
    assert axis_alpha_gamma_deg([0, 0, 1]) == pytest.approx((90.0, 0.0))
    assert axis_alpha_gamma_deg(Rz(30) @ [0, 1, 0]) == pytest.approx((0.0, 30.0))
    rng = np.random.default_rng(SEED + 7)
    for _ in range(100):
        a = rng.normal(size=3)
        a /= np.linalg.norm(a)
        alpha, gamma = axis_alpha_gamma_deg(a)
        assert -90.0 <= gamma <= 90.0
        np.testing.assert_allclose(Rx(alpha) @ Rz(gamma) @ [0, 1, 0], a, atol=ROUND_TRIP_ATOL)


def _canonical_R(R, axis_obj) -> np.ndarray:
    return canonical_spin(Pose(np.asarray(R, float), np.zeros(3)), axis_obj).R


@pytest.mark.parametrize("axis_obj", [[0, 1, 0], [0, 0, 1], [1, 0, 0], [0, -1, 0], [1, 2, -2]])
def test_canonical_spin_properties(axis_obj):
    axis_obj = np.asarray(axis_obj, float) / np.linalg.norm(axis_obj)
    rng = np.random.default_rng(SEED + 8)
    for R in random_R(rng, 30):
        C = _canonical_R(R, axis_obj)
        np.testing.assert_allclose(C.T @ C, np.eye(3), atol=ROUND_TRIP_ATOL)
        assert np.linalg.det(C) == pytest.approx(1.0)
        # maps the axis to the same camera direction as R
        np.testing.assert_allclose(C @ axis_obj, R @ axis_obj, atol=ROUND_TRIP_ATOL)
        # C differs from R by a spin about the axis only: C = R @ S with S @ axis = axis
        S = R.T @ C
        np.testing.assert_allclose(S @ axis_obj, axis_obj, atol=ROUND_TRIP_ATOL)
        # invariant to spinning the input about the axis
        for phi in (17.0, 90.0, -123.0, 180.0):
            np.testing.assert_allclose(_canonical_R(R @ spin(axis_obj, phi), axis_obj), C,
                                       atol=ROUND_TRIP_ATOL)


def test_canonical_spin_keeps_the_axis_point_and_forgets_the_spin():
    """The axis through point_obj stays where it was; spinning the part about it changes nothing."""
    rng = np.random.default_rng(SEED + 10)
    axis, point = np.array([1.0, 2.0, -2.0]) / 3.0, np.array([5.0, -7.0, 11.0])
    for R in random_R(rng, 20):
        pose = Pose(R, rng.uniform(-100, 100, 3) + [0, 0, 600])
        C = canonical_spin(pose, axis, point)
        np.testing.assert_allclose(C.apply(point[None]), pose.apply(point[None]), atol=1e-9)
        np.testing.assert_allclose(C.R @ axis, pose.R @ axis, atol=ROUND_TRIP_ATOL)
        S = spin(axis, 40.0)  # the part spun by 40 deg about the axis through point
        spun = pose.compose(Pose(S, point - S @ point))
        C2 = canonical_spin(spun, axis, point)
        np.testing.assert_allclose(C2.R, C.R, atol=ROUND_TRIP_ATOL)
        np.testing.assert_allclose(C2.t_mm, C.t_mm, atol=1e-9)
    assert canonical_spin(pose, None) is pose


def test_canonical_spin_for_y_axis_has_zero_ry():
    rng = np.random.default_rng(SEED + 9)
    for R in random_R(rng, 50):
        C = _canonical_R(R, [0, 1, 0])
        rx, ry, rz = euler_xyz_deg_from_R(C)
        assert ry == pytest.approx(0.0, abs=1e-7)
        alpha, gamma = axis_alpha_gamma_deg(R @ [0, 1, 0])
        assert (rx, rz) == pytest.approx((alpha, gamma), abs=1e-7)


def test_R_align_axis_to_y():
    for axis in ([1, 0, 0], [0, 0, -1], [0, -1, 0], [3, 1, 2]):
        A = frames.R_align_axis_to_y(np.asarray(axis, float))
        np.testing.assert_allclose(A @ (np.asarray(axis, float) / np.linalg.norm(axis)), [0, 1, 0],
                                   atol=ROUND_TRIP_ATOL)


def _gt_lines(path):
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def test_dataset_alpha_gamma_and_euler_match_frames(data_dir):
    """Every line of paper/gt.jsonl: our conventions reproduce its axis_alpha_gamma_deg and euler_xyz_deg."""
    lines = _gt_lines(data_dir / "paper" / "gt.jsonl")
    assert lines
    for g in lines:
        R = np.asarray(g["R"], float)
        assert g["symmetry"] == "y"
        axis_cam = R @ [0.0, 1.0, 0.0]
        np.testing.assert_allclose(axis_alpha_gamma_deg(axis_cam), g["axis_alpha_gamma_deg"],
                                   atol=DATASET_ANGLE_ATOL_DEG, err_msg=g["image"])
        np.testing.assert_allclose(euler_xyz_deg_from_R(R), g["euler_xyz_deg"], atol=DATASET_ANGLE_ATOL_DEG,
                                   err_msg=g["image"])
        # the canonical pose of the gt: euler (alpha, 0, gamma), same axis direction
        C = _canonical_R(R, [0.0, 1.0, 0.0])
        np.testing.assert_allclose(euler_xyz_deg_from_R(C),
                                   [g["axis_alpha_gamma_deg"][0], 0.0, g["axis_alpha_gamma_deg"][1]],
                                   atol=DATASET_ANGLE_ATOL_DEG, err_msg=g["image"])
        # and the spin the dataset reports is the one that takes the canonical pose to R (about +y)
        if "spin_deg" in g:
            np.testing.assert_allclose(C @ Ry(g["spin_deg"]), R, atol=1e-9, err_msg=g["image"])
