"""Frame math of the cell (service/cell.py): compositions, the revolved part's grasp spin, the sort
rule, and the upload plausibility warning, against closed forms and brute force."""

from __future__ import annotations

import numpy as np
import pytest

from service.cell import (
    Grasp,
    axis_rotation,
    base_from_cam,
    best_spin_rad,
    extent_warnings,
    inverse,
    nearest_rotation,
    place_grasps,
    rigid,
)
from service.vision.geometry.frames import R_from_euler_xyz_deg, Rx, rotation_angle_deg
from tests.tolerances import CELL_EXACT_ATOL, CELL_SPIN_GRID_DEG

RNG_SEED = 20261123


def random_T(rng) -> np.ndarray:
    return rigid(R_from_euler_xyz_deg(rng.uniform(-180, 180, 3)), rng.uniform(-500, 500, 3))


def test_inverse_and_composition_cancel_inner_frames():
    rng = np.random.default_rng(RNG_SEED)
    for _ in range(20):
        T_a_b, T_b_c = random_T(rng), random_T(rng)
        np.testing.assert_allclose(inverse(T_a_b) @ T_a_b, np.eye(4), atol=CELL_EXACT_ATOL)
        p_c = rng.uniform(-100, 100, 3)
        p_a = (T_a_b @ T_b_c @ np.r_[p_c, 1.0])[:3]
        np.testing.assert_allclose(p_a, T_a_b[:3, :3] @ (T_b_c[:3, :3] @ p_c + T_b_c[:3, 3]) + T_a_b[:3, 3],
                                   atol=CELL_EXACT_ATOL)


def test_base_from_cam_eye_to_hand_eye_in_hand_and_unknown():
    # camera 1 m above the base origin looking straight down: the camera's origin in base is (0, 0, 1000)
    # and a point 1000 mm in front of it (camera z) is the base origin.
    T_base_cam = rigid(Rx(180.0), [0.0, 0.0, 1000.0])
    np.testing.assert_allclose((T_base_cam @ [0.0, 0.0, 1000.0, 1.0])[:3], [0.0, 0.0, 0.0],
                               atol=CELL_EXACT_ATOL)
    assert base_from_cam(T_base_cam, None, None) is T_base_cam
    T_flange_cam = rigid(np.eye(3), [0.0, 0.0, 50.0])  # camera 50 mm along the flange's z
    T_base_flange = rigid(Rx(180.0), [400.0, 0.0, 600.0])  # flange pointing down at 600 mm
    T = base_from_cam(None, T_flange_cam, T_base_flange)
    np.testing.assert_allclose(T[:3, 3], [400.0, 0.0, 550.0], atol=CELL_EXACT_ATOL)  # 50 mm below the flange
    assert base_from_cam(None, T_flange_cam, None) is None
    assert base_from_cam(None, None, T_base_flange) is None


def test_nearest_rotation_snaps_small_errors_and_refuses_others():
    R = R_from_euler_xyz_deg([10.0, 20.0, 30.0])
    noisy = np.round(R, 4)  # a hand-eye result printed with 4 decimals
    snapped = nearest_rotation(noisy)
    np.testing.assert_allclose(snapped @ snapped.T, np.eye(3), atol=CELL_EXACT_ATOL)
    assert rotation_angle_deg(snapped, R) < 0.01
    with pytest.raises(ValueError, match="not a rotation matrix"):
        nearest_rotation(2.0 * R)
    with pytest.raises(ValueError, match="reflection"):
        nearest_rotation(np.diag([1.0, 1.0, -1.0]))


def test_grasps_without_extrinsics_sort_by_the_cameras_viewing_direction():
    T_cam_obj = rigid(np.eye(3), [0.0, 0.0, 500.0])
    along = Grasp("along", rigid(np.eye(3), [0.0, 0.0, -20.0]))  # approach +z_obj = +z_cam: 0 deg
    across = Grasp("across", rigid(R_from_euler_xyz_deg([0.0, 90.0, 0.0]), [20.0, 0.0, 0.0]))  # +x: 90 deg
    placed = place_grasps(T_cam_obj, [across, along])
    assert [p.name for p in placed] == ["along", "across"]
    assert placed[0].approach_angle_deg == pytest.approx(0.0, abs=1e-6)
    assert placed[1].approach_angle_deg == pytest.approx(90.0, abs=1e-6)
    np.testing.assert_allclose(placed[0].T_cam_grasp[:3, 3], [0.0, 0.0, 480.0], atol=CELL_EXACT_ATOL)
    assert placed[0].T_base_grasp is None


def test_grasps_with_extrinsics_sort_by_straight_down_in_the_base_frame():
    # camera looking horizontally along base +x (camera z = base x, camera y = base -z)
    R_base_cam = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    T_base_cam = rigid(R_base_cam, [0.0, 0.0, 300.0])
    T_cam_obj = rigid(np.eye(3), [0.0, 0.0, 500.0])
    along = Grasp("along-view", rigid(np.eye(3), [0.0, 0.0, 0.0]))  # approach = base +x: 90 deg from down
    down = Grasp("down", rigid(np.eye(3), [0.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))  # cam +y = base -z
    placed = place_grasps(T_cam_obj, [along, down], T_base_cam)
    assert [p.name for p in placed] == ["down", "along-view"]
    assert placed[0].approach_angle_deg == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(placed[0].T_base_grasp[:3, 3], [500.0, 0.0, 300.0], atol=CELL_EXACT_ATOL)


@pytest.mark.parametrize("seed", range(5))
def test_revolved_part_grasp_is_spun_to_the_most_vertical_approach(seed):
    """Closed-form best spin against a brute-force scan of spins; the spun grasp is the same grasp
    of the part (its position stays on the same circle about the axis, its distance to the axis kept)."""
    rng = np.random.default_rng(RNG_SEED + seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    p0 = rng.uniform(-20, 20, 3)
    T_cam_obj, T_base_cam = random_T(rng), random_T(rng)
    g = Grasp("g", random_T(rng))
    [placed] = place_grasps(T_cam_obj, [g], T_base_cam, symmetry_axis_obj=axis, symmetry_point_obj=p0)

    def down_angle(spin_deg: float) -> float:
        S = axis_rotation(axis, np.radians(spin_deg))
        T = T_base_cam @ T_cam_obj @ rigid(S, p0 - S @ p0) @ g.T_obj_grasp
        return float(np.degrees(np.arccos(np.clip(T[:3, 2] @ [0.0, 0.0, -1.0], -1, 1))))

    spins = np.arange(-180.0, 180.0, CELL_SPIN_GRID_DEG)
    brute = min(down_angle(s) for s in spins)
    assert placed.approach_angle_deg <= brute + 1e-6
    assert placed.approach_angle_deg == pytest.approx(down_angle(placed.spin_deg), abs=1e-6)
    # the spun grasp lies as far from the axis, and at the same height along it, as the registered one
    T_obj_spun = inverse(T_cam_obj) @ inverse(T_base_cam) @ placed.T_base_grasp

    def radial_and_height(p):
        d = p - p0
        return np.linalg.norm(d - (d @ axis) * axis), d @ axis

    np.testing.assert_allclose(radial_and_height(T_obj_spun[:3, 3]), radial_and_height(g.T_obj_grasp[:3, 3]),
                               atol=1e-6)


def test_best_spin_is_zero_when_every_spin_is_as_good():
    # approach along the axis itself: spinning does not move it
    y = np.array([0.0, 1.0, 0.0])
    assert best_spin_rad(y, np.array([0.3, 0.9, 0.1]), y) == 0.0


@pytest.mark.parametrize(("extents_mm", "units", "suggestion"), [
    ((200000.0, 50000.0, 50000.0), "m", "units=mm"),  # a 200 mm part declared in metres
    ((2540.0, 2540.0, 1270.0), "in", None),  # 2.5 m: plausible, no warning
    ((5080.0, 2540.0, 1270.0), "in", "units=mm"),  # 200 "inches" = 200 mm more likely than 5 m
    ((0.2, 0.1, 0.1), "mm", "units=m"),  # 0.2 m written in metres, declared mm
    ((80.0, 40.0, 10.0), "mm", None),
])
def test_extent_warnings_suggest_the_unit_that_makes_a_typical_part(extents_mm, units, suggestion):
    w = extent_warnings(extents_mm, units)
    if suggestion is None:
        assert w == []
    else:
        assert len(w) == 1 and f"did you mean {suggestion}?" in w[0]
        assert w[0].startswith("extents ")


# Linemod-Occluded's published ground truth (lmo_dev/gt.jsonl, images/000047.png, lmo_08, the driller):
# max |R R^T - I| = 0.0020, a 422 while rotations were held to 1e-3.
LMO_R = [[0.77882393, 0.62415451, 0.07664882],
         [0.46645237, -0.49163726, -0.73663738],
         [-0.42164912, 0.60878461, -0.67337539]]


def test_a_published_ground_truth_off_orthonormal_is_snapped_with_a_warning():
    from scipy.spatial.transform import Rotation

    from service.cell import ROTATION_ATOL, axes_moved_deg, rotation_error, snap_warning

    R = np.asarray(LMO_R)
    err = rotation_error(R)
    assert 1e-3 < err < ROTATION_ATOL
    snapped = nearest_rotation(R)
    np.testing.assert_allclose(snapped @ snapped.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(snapped) == pytest.approx(1.0, abs=1e-9)
    # the known answer: the closest rotation in the Frobenius norm, as scipy's from_matrix finds it
    np.testing.assert_allclose(snapped, Rotation.from_matrix(R).as_matrix(), atol=1e-9)
    # R ~ Q (I + S), S symmetric, |S| ~ err / 2: no axis turns by more than ~err rad
    moved = axes_moved_deg(R, snapped)
    assert 0.0 < moved < np.degrees(err)
    warning = snap_warning("pose", R, snapped)
    assert warning.startswith("pose's R was off orthonormal by 0.002 (max |R R^T - I|, accepted up to 0.01)")
    assert snap_warning("pose", snapped, snapped) is None


def test_beyond_the_tolerance_a_rotation_is_still_refused():
    R = np.asarray(LMO_R) @ np.diag([1.0, 1.0, 1.01])  # max |R R^T - I| = 0.0128
    with pytest.raises(ValueError, match=r"differs from the identity by up to 0.01\d+; allowed 0.01"):
        nearest_rotation(R)
