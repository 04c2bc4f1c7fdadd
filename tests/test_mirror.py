"""Mirror planes of a part and the outline twin they give a pose (model/mirror.py), and the estimate's
twin check, on constructed parts with known planes and rendered scenes with known poses."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from service.vision import pipeline
from service.vision.deadline import NO_DEADLINE, Deadline
from service.vision.estimate.evidence import colour_frame
from service.vision.estimate.plane import PLANE_TOLERANCE_MM
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, Rx, Ry, Rz, rotation_angle_deg
from service.vision.geometry.plane import Plane, rest_gap_mm
from service.vision.geometry.render import render, render_shaded
from service.vision.model.mirror import mirror_planes, twin_poses
from service.vision.pipeline import PoseCandidate
from service.vision.reference.metrics import mspd_px
from tests.scenes import l_block
from tests.tolerances import MIRROR_NORMAL_DEG, TWIN_OUTLINE_IOU, TWIN_RIGHT_PX

INTR = Intrinsics(600.0, 600.0, 319.5, 239.5)
SIZE = (640, 480)


def normals_match(found: np.ndarray, expected: list) -> bool:
    """Each expected normal is found once (up to sign), and nothing else."""
    if len(found) != len(expected):
        return False
    cos = np.cos(np.radians(MIRROR_NORMAL_DEG))
    return all(sum(abs(f @ np.asarray(e, float)) > cos for f in found) == 1 for e in expected)


def test_a_box_has_its_three_face_planes():
    assert normals_match(mirror_planes(trimesh.creation.box((80.0, 60.0, 40.0))).normals_obj, np.eye(3))


def test_an_extruded_l_has_only_its_mid_plane(l_block_bank):
    planes = mirror_planes(l_block())
    assert normals_match(planes.normals_obj, [(0.0, 0.0, 1.0)])
    assert abs(planes.point_obj[2]) < 1e-6  # the extrusion is centred on z = 0


def test_a_corner_boss_breaks_every_plane():
    box = trimesh.creation.box((80.0, 60.0, 40.0))
    boss = trimesh.creation.box((10.0, 10.0, 10.0))
    boss.apply_translation((30.0, 20.0, 25.0))  # on the top face, off both mid-planes
    assert len(mirror_planes(trimesh.util.concatenate([box, boss])).normals_obj) == 0


def test_a_cylinder_keeps_one_plane_through_its_axis_and_the_one_across():
    cyl = trimesh.creation.cylinder(radius=20.0, height=90.0, sections=64)  # axis z
    planes = mirror_planes(cyl, axis_obj=np.array([0.0, 0.0, 1.0]))
    assert len(planes.normals_obj) == 2
    assert sum(abs(n[2]) > np.cos(np.radians(MIRROR_NORMAL_DEG)) for n in planes.normals_obj) == 1
    assert sum(abs(n[2]) < np.sin(np.radians(MIRROR_NORMAL_DEG)) for n in planes.normals_obj) == 1


def test_an_oblique_revolved_axis_keeps_its_plane_through_the_axis():
    R = Rx(30.0) @ Rz(40.0)  # no model axis is perpendicular to this one
    cyl = trimesh.creation.cylinder(radius=20.0, height=90.0, sections=64)
    cyl.apply_transform(np.block([[R, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]))
    axis = R @ np.array([0.0, 0.0, 1.0])
    normals = mirror_planes(cyl, axis_obj=axis).normals_obj
    assert len(normals) == 2
    assert sum(abs(n @ axis) < np.sin(np.radians(MIRROR_NORMAL_DEG)) for n in normals) == 1


def silhouette(mesh, pose, K, size) -> np.ndarray:
    return render(np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32), pose, K, size,
                  supersample=1).coverage > 0.5


def test_the_twin_is_a_rotation_with_the_same_outline_and_centre():
    mesh = l_block()
    planes = mirror_planes(mesh)
    # Seen from 20 m the projection is nearly orthographic: the outline is the same, the pose is not.
    K = np.array([[40000.0, 0.0, 319.5], [0.0, 40000.0, 239.5], [0.0, 0.0, 1.0]])
    pose = Pose(Rx(35.0) @ Ry(-20.0) @ Rz(15.0), np.array([5.0, -3.0, 20000.0]))
    (twin,) = twin_poses(pose, planes)
    assert np.linalg.det(twin.R) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(twin.apply(planes.point_obj[None]), pose.apply(planes.point_obj[None]),
                               atol=1e-6)
    assert rotation_angle_deg(twin.R, pose.R) > 30.0
    a, b = silhouette(mesh, pose, K, SIZE), silhouette(mesh, twin, K, SIZE)
    assert np.count_nonzero(a & b) / np.count_nonzero(a | b) >= TWIN_OUTLINE_IOU


@pytest.fixture(scope="module")
def flipped_scene(l_block_bank):
    bank = l_block_bank
    truth = Pose(Rx(35.0) @ Ry(-20.0) @ Rz(15.0), np.array([10.0, -5.0, 430.0]))
    grey = render_shaded(bank.vertices_mm, bank.faces, truth, INTR.K, SIZE, background=70)
    img = np.repeat(grey[..., None], 3, axis=2)
    (flipped,) = twin_poses(truth, pipeline.mirror_planes_of(bank))
    return bank, img, truth, flipped


def check(bank, img, pose, *, twin_check: bool, monkeypatch, deadline=NO_DEADLINE):
    """``pose`` checked as an estimate checks a candidate; without ``twin_check``, its own check alone."""
    cand = PoseCandidate(pose, 0.0, 1.0)
    if not twin_check:
        checker = pipeline.Checker(bank, img[..., 0], colour_frame(img), INTR, None, 16,
                                   dict(distance_range_mm=(300.0, 600.0), min_score=0.0), deadline)
        return checker(cand, None)
    kw = dict(distance_mm=None, distance_range_mm=(300.0, 600.0), min_score=0.0, n_channels=16)
    return pipeline.check_candidate(bank, cand, img[..., 0], colour_frame(img), INTR, deadline=deadline, **kw)


def mspd(bank, a: Pose, b: Pose) -> float:
    return mspd_px(a.R, a.t_mm, b.R, b.t_mm, INTR.K, bank.vertices_mm.astype(float))


def test_a_flipped_start_is_turned_into_the_truth(flipped_scene, monkeypatch):
    bank, img, truth, flipped = flipped_scene
    # min_score 0: every checked pose is found, so the flipped pose's own check would be the answer ...
    alone = check(bank, img, flipped, twin_check=False, monkeypatch=monkeypatch)
    assert mspd(bank, alone.refined.pose, truth) > 20.0
    # ... and the twin check replaces it by its twin, the truth, which the shading prefers
    c = check(bank, img, flipped, twin_check=True, monkeypatch=monkeypatch)
    assert mspd(bank, c.refined.pose, truth) < TWIN_RIGHT_PX
    assert c.verdict.score > alone.verdict.score
    # the pose that lost is reported as the twin's score: the same check as the flipped start's own
    assert c.verdict.evidence["twin_score"] == pytest.approx(alone.verdict.score)


def test_no_twin_is_checked_past_the_deadline(flipped_scene, monkeypatch):
    bank, img, truth, flipped = flipped_scene
    fake_now = [0.0]
    past = Deadline(100.0, start=-1.0, clock=lambda: fake_now[0])  # started 1 s ago, 100 ms allowed
    c = check(bank, img, flipped, twin_check=True, monkeypatch=monkeypatch, deadline=past)
    assert mspd(bank, c.refined.pose, truth) > 20.0 and past.hit  # the flipped answer stands, and says so


def test_a_right_answer_is_kept(flipped_scene, monkeypatch):
    bank, img, truth, _ = flipped_scene
    c = check(bank, img, truth, twin_check=True, monkeypatch=monkeypatch)
    assert mspd(bank, c.refined.pose, truth) < TWIN_RIGHT_PX
    assert c.verdict.evidence["twin_score"] < c.verdict.score


def test_the_bank_carries_its_mirror_planes_and_an_older_bank_makes_them(l_block_bank):
    from service.vision.bank import TemplateBank

    bank = l_block_bank
    assert normals_match(bank.mirror_normals_obj, [(0.0, 0.0, 1.0)])
    arrays = bank.to_arrays()
    back = TemplateBank.from_arrays(arrays)
    np.testing.assert_array_equal(back.mirror_normals_obj, bank.mirror_normals_obj)
    old = {k: v for k, v in arrays.items() if k not in ("mirror_normals_obj", "mirror_point_obj")}
    old["format_version"] = np.int64(2)
    v2 = TemplateBank.from_arrays(old)
    assert v2.mirror_normals_obj is None and "mirror_normals_obj" not in v2.to_arrays()
    made = pipeline.mirror_planes_of(v2)
    assert normals_match(made.normals_obj, [(0.0, 0.0, 1.0)])
    np.testing.assert_allclose(made.point_obj, bank.mirror_point_obj, atol=1e-9)


def test_a_sphere_keeps_at_most_three_planes():
    # every plane through its centre is a mirror: the three best stand for them (one twin check each)
    planes = mirror_planes(trimesh.creation.icosphere(subdivisions=4, radius=50.0))
    assert len(planes.normals_obj) == 3


def test_on_a_plane_a_twin_that_does_not_rest_on_it_is_not_checked(flipped_scene):
    bank, img, truth, flipped = flipped_scene
    # a plane under the truth, across the L's mirror normal: the twin goes 17 mm through it
    normal = -truth.R[:, 2]
    plane = Plane(normal, float((truth.apply(bank.vertices_mm) @ normal).min()))
    assert rest_gap_mm(bank, truth, plane) == pytest.approx(0.0, abs=1e-9)
    assert rest_gap_mm(bank, flipped, plane) < -PLANE_TOLERANCE_MM
    kw = dict(distance_mm=None, distance_range_mm=(300.0, 600.0), min_score=0.0, n_channels=16)
    frame = colour_frame(img)
    on_plane = pipeline.check_candidate(bank, PoseCandidate(truth, 0.0, 1.0), img[..., 0], frame, INTR,
                                        plane=plane, **kw)
    free = pipeline.check_candidate(bank, PoseCandidate(truth, 0.0, 1.0), img[..., 0], frame, INTR, **kw)
    assert on_plane.verdict.found and "twin_score" not in on_plane.verdict.evidence
    assert "twin_score" in free.verdict.evidence
