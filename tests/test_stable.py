"""Stable resting poses (service/vision/model/stable.py): known answers from boxes and a prism."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import trimesh

from service.vision.model.stable import MIN_PROBABILITY, _with_missed_facets, stable_poses
from tests.tolerances import STABLE_ATOL


def _face_down_axes(sp) -> list[int]:
    """For each family, the object axis (0 x, 1 y, 2 z) that points up (or down) while resting."""
    return [int(np.argmax(np.abs(R[2]))) for R in sp.R_rest_obj]


def test_a_box_rests_on_its_6_faces_3_distinct_up_to_symmetry():
    raw, p = trimesh.poses.compute_stable_poses(trimesh.creation.box((80.0, 60.0, 40.0)))
    assert len(raw) == 6  # its 6 faces ...
    sp = stable_poses(trimesh.creation.box((80.0, 60.0, 40.0)))
    assert len(sp.R_rest_obj) == 3  # ... 3 distinct: each face and its opposite are one family
    # Most probable first: on the largest face (80 x 60, the z axis up), then 80 x 40 (y), then 60 x 40 (x).
    assert _face_down_axes(sp) == [2, 1, 0]
    assert sp.probability.sum() == pytest.approx(1.0, abs=STABLE_ATOL)
    np.testing.assert_allclose(np.sort(sp.probability)[::-1], sp.probability)
    for R in sp.R_rest_obj:  # proper rotations with an object axis straight up
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=STABLE_ATOL)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=STABLE_ATOL)
        assert np.abs(R[2]).max() == pytest.approx(1.0, abs=STABLE_ATOL)


def test_a_cube_rests_one_way():
    sp = stable_poses(trimesh.creation.box((50.0, 50.0, 50.0)))
    assert len(sp.R_rest_obj) == 1 and sp.probability[0] == pytest.approx(1.0, abs=STABLE_ATOL)


def test_a_revolved_part_on_its_side_is_one_family_not_one_per_facet():
    mesh = trimesh.creation.cylinder(radius=20.0, height=60.0, sections=64)  # axis z
    raw, _ = trimesh.poses.compute_stable_poses(mesh)
    assert len(raw) == 66  # 64 side facets and 2 ends
    sp = stable_poses(mesh, axis_obj=np.array([0.0, 0.0, 1.0]))
    assert len(sp.R_rest_obj) == 2  # on its side (axis horizontal) and on an end (the two ends are congruent)
    side, end = sp.R_rest_obj
    assert abs(side[2, 2]) < 1e-6 and abs(end[2, 2]) == pytest.approx(1.0, abs=STABLE_ATOL)
    assert sp.probability.sum() == pytest.approx(1.0, abs=1e-6)


def test_a_facet_trimesh_missed_is_added_at_its_solid_angle():
    # From a cube's centre each face subtends exactly 4 pi / 6 of the sphere: a face left out of the list
    # comes back at probability 1/6, resting on it (its outward normal straight down), and nothing else.
    cube = trimesh.creation.box((50.0, 50.0, 50.0))
    T, p = trimesh.poses.compute_stable_poses(cube)
    Rs = np.asarray(T)[:, :3, :3]
    left_out = int(np.argmin(Rs[:, 2, 2]))  # the pose resting on the +z face: up is -z
    keep = np.arange(len(Rs)) != left_out
    R, prob = _with_missed_facets(cube.convex_hull, np.zeros(3), Rs[keep], np.asarray(p)[keep])
    assert len(R) == len(Rs)
    np.testing.assert_allclose(R[-1][2], [0.0, 0.0, -1.0], atol=STABLE_ATOL)
    np.testing.assert_allclose(R[-1] @ R[-1].T, np.eye(3), atol=STABLE_ATOL)
    assert prob[-1] == pytest.approx(1.0 / 6.0, abs=STABLE_ATOL)
    # given every face, it adds none
    R_all, _ = _with_missed_facets(cube.convex_hull, np.zeros(3), Rs, np.asarray(p))
    assert len(R_all) == len(Rs)


def test_a_flat_spanner_rests_on_both_faces(data_dir):
    # A 4 mm plate, symmetric through its mid-plane: it lies on either face about equally often, and the
    # two are not congruent (its outline is not mirror-symmetric), yet trimesh 4 may list only one of them
    # (its toppling graph loses the other where the centre of mass falls on an edge between triangles:
    # on some machines, not on others, by the rounding of that test).
    # The service runs with numpy's warnings shown, not raised, and so does this: raised (the suite's
    # setting), a failed square root inside trimesh makes it take another path that keeps both.
    mesh = trimesh.load(data_dir / "sygrid_synth" / "models" / "sygrid_spanner.stl", force="mesh")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        sp = stable_poses(mesh)
    flat = [(R[2, 2], q) for R, q in zip(sp.R_rest_obj, sp.probability, strict=True) if abs(R[2, 2]) > 0.99]
    assert sorted(np.sign(up) for up, _ in flat) == [-1.0, 1.0]
    assert flat[0][1] == pytest.approx(flat[1][1], abs=0.01)


def test_negligible_families_are_dropped():
    # A thin slab: resting on an edge face (0.5 x 80) is rare, on the 80 x 80 faces almost always.
    sp = stable_poses(trimesh.creation.box((80.0, 80.0, 0.5)))
    assert all(p >= MIN_PROBABILITY for p in sp.probability)
    assert _face_down_axes(sp)[0] == 2
    everything = stable_poses(trimesh.creation.box((80.0, 80.0, 0.5)), min_probability=0.0)
    assert len(everything.R_rest_obj) == 2 and len(sp.R_rest_obj) == 1


def test_the_bank_carries_its_stable_poses_and_a_version_1_bank_loads_without_them():
    from service.vision.bank import BANK_FORMAT_VERSION, TemplateBank
    from service.vision.pipeline import build_templates

    bank = build_templates(trimesh.creation.box((80.0, 60.0, 40.0)), symmetry="none",
                           grid={"view_step_deg": 45.0, "render_px": 64})
    assert bank.R_rest_obj.shape == (3, 3, 3) and bank.rest_probability.shape == (3,)
    arrays = bank.to_arrays()
    assert int(arrays["format_version"]) == BANK_FORMAT_VERSION == 3
    back = TemplateBank.from_arrays(arrays)
    np.testing.assert_array_equal(back.R_rest_obj, bank.R_rest_obj)
    old = {k: v for k, v in arrays.items() if k not in ("R_rest_obj", "rest_probability")}
    old["format_version"] = np.int64(1)
    v1 = TemplateBank.from_arrays(old)
    assert v1.R_rest_obj is None and v1.rest_probability is None
    assert "R_rest_obj" not in v1.to_arrays()
