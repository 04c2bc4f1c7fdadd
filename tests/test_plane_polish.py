"""A refined pose polished again on the plane (service/vision/estimate/plane_polish.py): the polished pose
touches the plane, a spin keeps its height, and a start turned and shifted off a rendered copy is brought
back onto it.

Scenes: tests/scenes.py's L-shaped block on a plane seen 40 deg from straight down.
"""

from __future__ import annotations

import numpy as np
import pytest

from service.vision.estimate.edge_agreement import agreeing_bits
from service.vision.estimate.gradients import orientation_bits
from service.vision.estimate.plane_polish import polish_on_plane, spun_and_slid
from service.vision.geometry.camera import project
from service.vision.geometry.frames import Pose, R_from_rotvec, rotation_angle_deg
from service.vision.geometry.plane import lowest_mm, rest_gap_mm, touching
from service.vision.model.edge_points import edge_points_at
from service.vision.pipeline.part import crease_edges_of
from tests.scenes import INTR, PLANE, SIZE, resting, scene

ON_PLANE_MM = 1e-6
# the polish ends within these of the copy, as the search's polish does (test_gradient_search): the
# agreement's 1 px tolerance leaves a pixel, and at the block's 40 mm arm ends 450 mm away 1.5 deg, flat
POLISHED_DEG = 2.0
POLISHED_PX = 1.5


@pytest.fixture(scope="module")
def bank(l_block_bank):
    return l_block_bank


def test_a_pose_turned_off_the_plane_is_moved_along_its_centre_s_line_of_sight_onto_it(bank):
    pose = resting(bank, 0, 20.0, 10.0, -5.0)
    R = R_from_rotvec(np.array([0.2, -0.1, 0.05])) @ pose.R
    low = lowest_mm(np.asarray(bank.vertices_mm, float), bank.centre_obj, R, PLANE)
    t = touching(low, bank.centre_obj, R, pose.t_mm, PLANE)
    assert abs(rest_gap_mm(bank, Pose(R, t), PLANE)) < ON_PLANE_MM
    before, after = R @ bank.centre_obj + pose.t_mm, R @ bank.centre_obj + t
    assert np.linalg.norm(np.cross(before, after)) / np.linalg.norm(before) / np.linalg.norm(after) < 1e-12


def test_a_spin_and_a_slide_keep_a_resting_pose_on_the_plane(bank):
    pose = resting(bank, 1, -40.0, 0.0, 0.0)
    R, t = spun_and_slid(pose.R, bank.centre_obj, pose.t_mm, PLANE, np.array([33.0, 4.0, -2.0]))
    assert abs(rest_gap_mm(bank, Pose(R, t), PLANE)) < 1e-6
    assert rotation_angle_deg(R, R_from_rotvec(PLANE.normal * np.radians(33.0)) @ pose.R) < 1e-6


def test_a_start_turned_and_shifted_off_a_copy_is_polished_back_onto_it(bank):
    truth = resting(bank, 0, 25.0, 0.0, 0.0)
    agreeing = agreeing_bits(orientation_bits(scene(bank, [truth])))
    R, t = spun_and_slid(truth.R, bank.centre_obj, truth.t_mm, PLANE, np.array([5.0, 2.5, -2.0]))
    start = Pose(R, t)
    edges = edge_points_at(bank.vertices_mm, bank.faces, crease_edges_of(bank), start, INTR, SIZE)
    found, agrees, before = polish_on_plane(bank.vertices_mm, bank.centre_obj, edges, start, PLANE, INTR,
                                            agreeing)
    assert agrees > before
    assert rotation_angle_deg(found.R, truth.R) < POLISHED_DEG
    centre = [p.apply(bank.centre_obj[None]) for p in (found, truth)]
    assert np.linalg.norm(project(centre[0], INTR.K) - project(centre[1], INTR.K)) < POLISHED_PX
    assert abs(rest_gap_mm(bank, found, PLANE)) < ON_PLANE_MM
