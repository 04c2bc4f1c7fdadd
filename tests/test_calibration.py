"""Teach-time calibration of a taught part's operating point (``pipeline.calibrate_appearance``): each
reference photo searched, taught by the others, and every pose judged there away from the known one
counted as a wrong answer the cell can produce."""

from __future__ import annotations

import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from service.vision import pipeline
from service.vision.estimate.verdict import MIN_SCORE, Verdict
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, Rx, Ry, Rz
from service.vision.geometry.render import render
from service.vision.model.appearance import Appearance
from service.vision.pipeline import teach
from tests.test_appearance import (
    BOX,
    FLOOR_BGR,
    INTR_E2E,
    POSE_A,
    POSE_B,
    POSE_C,
    SIDE_BGR,
    SIZE_E2E,
    _side_of_face,
)

PX_TOL = 1e-6


def _part(mesh: trimesh.Trimesh, axis=None):
    return SimpleNamespace(vertices_mm=np.asarray(mesh.vertices, float), faces=np.asarray(mesh.faces),
                           symmetry_axis_obj=axis, symmetry_point_obj=None)


def test_the_error_of_a_pose_moved_sideways_is_the_nearest_corner_s_image_shift():
    """Moved dx mm along the camera's x, a point at depth z moves fx dx / z pixels along u: the largest
    shift is the nearest corner's, scaled to a 640 px wide image."""
    part = _part(trimesh.creation.box((60.0, 40.0, 30.0)))
    intr = Intrinsics(800.0, 800.0, 639.5, 479.5)
    truth = Pose(Rx(20.0) @ Ry(-30.0), np.array([10.0, 5.0, 500.0]))
    dx = 4.0
    moved = Pose(truth.R, truth.t_mm + np.array([dx, 0.0, 0.0]))
    z_near = truth.apply(part.vertices_mm)[:, 2].min()
    expected = 800.0 * dx / z_near * 640.0 / 1280
    assert abs(teach.pose_error_px(part, moved, truth, intr, 1280) - expected) < PX_TOL


def test_a_revolved_part_spun_about_its_axis_is_not_an_error_and_tilted_it_is():
    mesh = trimesh.creation.cylinder(radius=30.0, height=80.0, sections=48)
    part = _part(mesh, axis=np.array([0.0, 0.0, 1.0]))
    intr = Intrinsics(800.0, 800.0, 319.5, 239.5)
    truth = Pose(Rx(60.0) @ Ry(10.0), np.array([0.0, 0.0, 500.0]))
    spun = Pose(truth.R @ Rz(35.0), truth.t_mm)  # a multiple of the 5 degree spins the error tries
    tilted = Pose(truth.R @ Rx(35.0), truth.t_mm)
    assert teach.pose_error_px(part, spun, truth, intr, 640) < 1e-6
    assert teach.pose_error_px(part, tilted, truth, intr, 640) > pipeline.DEFAULT_POLICY.calibration_wrong_px


def _checked(reason: str, in_image: float = 1.0) -> pipeline.Checked:
    v = Verdict(reason == "found", 0.99, reason, {"in_image": in_image})
    return pipeline.Checked(None, None, v)


def test_the_calibration_counts_wrong_poses_the_cell_produces_even_where_the_verdict_refuses_them():
    """A wrong pose cut by a photo's border is refused there ("outside_image"), but half inside it is a
    score the part's other frames produce; a pose off the distance range or the plane is never returned."""
    assert teach._counts_as_met(_checked("found"))
    assert teach._counts_as_met(_checked("low_support"))
    half = pipeline.DEFAULT_POLICY.calibration_min_in_image
    assert teach._counts_as_met(_checked("outside_image", half))
    assert not teach._counts_as_met(_checked("outside_image", half - 0.01))
    assert not teach._counts_as_met(_checked("outside_distance_range"))
    assert not teach._counts_as_met(_checked("off_plane"))


def test_the_operating_point_lies_the_margin_above_the_highest_wrong_score_and_never_under_the_global_one():
    faces = np.zeros((1, 3), np.float32)
    assert pipeline.operating_point(None) is None
    assert pipeline.operating_point(Appearance(faces, 2)) is None  # not calibrated
    # calibrated, no wrong pose judged: the global operating point
    assert pipeline.operating_point(Appearance(faces, 2, wrong_score=-math.inf)) is None
    assert pipeline.operating_point(Appearance(faces, 2, wrong_score=0.5)) == MIN_SCORE
    doubling = replace(pipeline.DEFAULT_POLICY, calibration_margin=math.log(2.0))
    # wrong odds 0.99 / 0.01 = 99 doubled: 198 / 199
    point = pipeline.operating_point(Appearance(faces, 2, wrong_score=0.99), doubling)
    assert abs(point - 198.0 / 199.0) < 1e-12


def _scene(poses: list[Pose], seed: int) -> np.ndarray:
    """The painted box at each pose (the nearer surface wins) on a grey floor with sensor noise."""
    w, h = SIZE_E2E
    img = np.empty((h, w, 3))
    img[:] = FLOOR_BGR
    depth = np.full((h, w), np.inf)
    for pose in poses:
        r = render(BOX.vertices_mm, BOX.faces, pose, INTR_E2E.K, SIZE_E2E)
        on = (r.face_id >= 0) & (r.depth_mm < depth)
        img[on] = SIDE_BGR[_side_of_face(BOX)[r.face_id[on]]]
        depth[on] = r.depth_mm[on]
    img += np.random.default_rng(seed).normal(0.0, 1.0, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


# A second box, painted the same, beside the one whose pose each photo gives: a look-alike in the cell.
LOOK_ALIKE = Pose(Rx(-50.0) @ Ry(25.0) @ Rz(15.0), np.array([-90.0, 20.0, 450.0]))


@pytest.fixture(scope="module")
def box_bank():
    mesh = trimesh.Trimesh(BOX.vertices_mm, BOX.faces, process=False)
    return pipeline.build_templates(mesh, symmetry="none", grid={"view_step_deg": 15.0, "render_px": 160})


def _photos(with_look_alike: bool) -> list[tuple]:
    shifted = [Pose(p.R, p.t_mm + np.array([60.0, -20.0, 0.0])) for p in (POSE_A, POSE_C, POSE_B)]
    return [(_scene([p, LOOK_ALIKE] if with_look_alike else [p], seed=20 + i), INTR_E2E, p)
            for i, p in enumerate(shifted)]


def test_a_look_alike_in_the_reference_photos_raises_the_part_s_operating_point_over_its_score(box_bank):
    """Alone in its photos the box's searches judge no wrong pose near the global operating point. With a
    second box painted the same in every photo, that box is a wrong answer (the photo's pose is the
    other one) that verifies: the part's operating point rises over its score, and a frame showing both
    is found only over it."""
    alone = pipeline.teach_appearance(box_bank, _photos(False), calibrate=True)
    assert alone.used and alone.calibrated_photos == 3
    assert not alone.wrong_score >= MIN_SCORE, alone.wrong_score
    assert (pipeline.operating_point(alone) or MIN_SCORE) == MIN_SCORE

    crowded = pipeline.teach_appearance(box_bank, _photos(True), calibrate=True)
    assert crowded.used and crowded.wrong_score >= MIN_SCORE, crowded.wrong_score
    bar = pipeline.operating_point(crowded)
    assert bar is not None and bar >= crowded.wrong_score

    frame = _photos(True)[1][0]  # a frame of the cell: both boxes
    at_global = pipeline.estimate(box_bank, frame, INTR_E2E, appearance=alone)
    assert at_global.verdict.found, at_global.verdict  # either box verifies at the global operating point
    out = pipeline.estimate(box_bank, frame, INTR_E2E, appearance=crowded)
    assert out.verdict.found == (out.verdict.score >= bar), (out.verdict, bar)
    assert bar > at_global.verdict.score or out.verdict.found


def test_photos_that_agree_less_are_used_only_once_calibrated():
    from service.vision.model.appearance import MIN_AGREEMENT, MIN_AGREEMENT_CALIBRATED

    faces = np.full((1, 3), 100.0, np.float32)
    between = 0.5 * (MIN_AGREEMENT + MIN_AGREEMENT_CALIBRATED)
    taught = Appearance(faces, 3, agreement=between)
    assert taught.calibratable and not taught.used
    assert Appearance(faces, 3, agreement=between, wrong_score=0.5, calibrated_photos=3).used
    below = Appearance(faces, 3, agreement=MIN_AGREEMENT_CALIBRATED - 0.01, calibrated_photos=3)
    assert not below.calibratable and not below.used
    plain = Appearance(faces, 3, reference_shading_r2=0.95, hue_share=0.0, agreement=0.9, calibrated_photos=3)
    assert plain.plain and not plain.calibratable and not plain.used


def test_a_part_calibrated_on_enough_photos_is_also_searched_with_the_colour_sweep():
    faces = np.full((1, 3), 100.0, np.float32)
    policy = pipeline.DEFAULT_POLICY
    assert pipeline.taught_search(None) is None
    assert pipeline.taught_search(Appearance(faces, 6)) is policy.taught_search  # not calibrated
    fewer = policy.sweep_min_photos - 1
    calibrated = pipeline.taught_search(Appearance(faces, fewer, calibrated_photos=fewer))
    assert calibrated is policy.calibrated_search
    assert not policy.calibrated_search.colour_sweep
    enough = policy.sweep_min_photos
    swept = pipeline.taught_search(Appearance(faces, enough, calibrated_photos=enough))
    assert swept.colour_sweep and swept == replace(policy.calibrated_search, colour_sweep=True)
