"""Several instances and a region of interest, on constructed scenes with known answers.

Copies of an L-shaped block (no symmetry) are rendered with the project's rasteriser at known poses
and composited on a plain floor at 640 x 480; each found instance must be one of them, each copy
found once.
"""

from __future__ import annotations

import numpy as np
import pytest

from service.vision import pipeline
from service.vision.estimate.roi import rect_polygon
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, Rx, Ry, Rz
from service.vision.geometry.render import render_shaded
from tests.tolerances import FOUND_POSE_T_MM

INTR = Intrinsics(600.0, 600.0, 319.5, 239.5)
SIZE = (640, 480)
RANGE = (300.0, 600.0)
R15, R105 = Rx(35.0) @ Ry(-20.0) @ Rz(15.0), Rx(35.0) @ Ry(-20.0) @ Rz(105.0)
POSES = [Pose(R15, np.array([90.0, -60.0, 430.0])), Pose(R105, np.array([-90.0, 60.0, 430.0])),
         Pose(R15, np.array([90.0, 55.0, 430.0])), Pose(R105, np.array([0.0, -10.0, 430.0]))]


@pytest.fixture(scope="module")
def bank(l_block_bank):
    return l_block_bank


def scene(bank, poses) -> np.ndarray:
    grey = np.full((SIZE[1], SIZE[0]), 70, np.uint8)
    for p in poses:  # the parts are brighter than the floor and do not overlap
        grey = np.maximum(grey, render_shaded(bank.vertices_mm, bank.faces, p, INTR.K, SIZE, background=70))
    return np.repeat(grey[..., None], 3, axis=2)


def match(found, truth) -> list[int]:
    """For each found instance the index of the rendered copy it is within tolerance of."""
    out = []
    for inst in found:
        d = [np.linalg.norm(inst.refined.pose.t_mm - p.t_mm) for p in truth]
        assert min(d) <= FOUND_POSE_T_MM, (inst.refined.pose.t_mm, d)
        out.append(int(np.argmin(d)))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("n", [2, 4])
def test_copies_come_back_as_that_many_instances(bank, n):
    out = pipeline.estimate(bank, scene(bank, POSES[:n]), INTR, distance_range_mm=RANGE, max_instances=n)
    assert len(out.instances) == n
    assert sorted(match(out.instances, POSES[:n])) == list(range(n))
    scores = [i.verdict.score for i in out.instances]
    assert scores == sorted(scores, reverse=True)  # sort "score"
    assert out.found and out.refined.pose is out.instances[0].refined.pose


@pytest.mark.slow
def test_sort_by_distance_puts_the_nearest_first(bank):
    near = Pose(R105, np.array([-90.0, 60.0, 400.0]))
    truth = [POSES[0], near]
    out = pipeline.estimate(bank, scene(bank, truth), INTR, distance_range_mm=RANGE, max_instances=2,
                            sort="distance")
    assert match(out.instances, truth) == [1, 0]


def test_roi_excludes_a_copy_outside_it(bank):
    img = scene(bank, POSES[:2])
    roi = rect_polygon(320.0, 0.0, 320.0, 240.0)  # the top-right quarter: POSES[0] only
    out = pipeline.estimate(bank, img, INTR, distance_range_mm=RANGE, max_instances=2, roi_uv=roi)
    assert match(out.instances, POSES[:2]) == [0]


def test_one_instance_answers_as_before(bank):
    img = scene(bank, POSES[:2])
    a = pipeline.estimate(bank, img, INTR, distance_range_mm=RANGE)
    b = pipeline.estimate(bank, img, INTR, distance_range_mm=RANGE, max_instances=1)
    assert a.found and b.instances and len(b.instances) == 1
    assert np.array_equal(a.refined.pose.R, b.refined.pose.R) and np.array_equal(a.refined.pose.t_mm,
                                                                                b.refined.pose.t_mm)
    assert b.instances[0].refined.pose is b.refined.pose and b.verdict == b.instances[0].verdict
    match(b.instances, POSES[:2])


def test_nothing_found_has_no_instances(bank):
    out = pipeline.estimate(bank, np.full((SIZE[1], SIZE[0], 3), 90, np.uint8), INTR, max_instances=3)
    assert not out.found and out.instances == [] and out.verdict.reason == "no_candidate"


def test_silhouette_iou_known_answers(bank):
    p = POSES[0]
    assert pipeline.silhouette_iou(bank, p, p, INTR, SIZE) == pytest.approx(1.0)
    assert pipeline.silhouette_iou(bank, p, POSES[1], INTR, SIZE) == 0.0
