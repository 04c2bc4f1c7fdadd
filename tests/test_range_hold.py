"""The searched distance range bounds the refinement (``Policy.range_hold_max``): a candidate whose refinement
ends a little beyond it is refined again with its depth held at the bound it passed, so the answer lies in
the range and no further from a truth inside it; without the hold it is refused as outside the range."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from service.vision import pipeline
from service.vision.estimate.evidence import colour_frame
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, Rx, Ry, Rz
from service.vision.geometry.render import render_shaded
from service.vision.pipeline import PoseCandidate

INTR = Intrinsics(600.0, 600.0, 319.5, 239.5)
SIZE = (640, 480)
TRUTH = Pose(Rx(35.0) @ Ry(-20.0) @ Rz(15.0), np.array([10.0, -5.0, 470.0]))
# A clean render: the edge refinement reaches the truth's depth to a fraction of a percent.
DEPTH_TOL = 0.01


@pytest.fixture(scope="module")
def scene(l_block_bank):
    grey = render_shaded(l_block_bank.vertices_mm, l_block_bank.faces, TRUTH, INTR.K, SIZE, background=70)
    return np.repeat(grey[..., None], 3, axis=2)


def check(bank, img, start: Pose, distance_range_mm, *, hold: bool, monkeypatch):
    """``start`` checked; without ``hold``, at a policy that holds no refinement (no slack past a bound)."""
    policy = pipeline.DEFAULT_POLICY if hold else replace(pipeline.DEFAULT_POLICY, range_hold_max=0.0)
    return pipeline.check_candidate(bank, PoseCandidate(start, 0.0, 1.0), img[..., 0], colour_frame(img),
                                    INTR, distance_mm=None, distance_range_mm=distance_range_mm,
                                    min_score=0.0, n_channels=16, policy=policy)


def test_a_refinement_past_the_far_bound_is_held_at_it(l_block_bank, scene, monkeypatch):
    bound = 450.0  # the truth lies 4.4 % beyond it
    start = Pose(TRUTH.R, TRUTH.t_mm * (440.0 / TRUTH.t_mm[2]))  # inside the range
    free = check(l_block_bank, scene, start, (300.0, bound), hold=False, monkeypatch=monkeypatch)
    assert abs(free.refined.pose.t_mm[2] / TRUTH.t_mm[2] - 1.0) < DEPTH_TOL  # the refinement leaves the range
    assert free.verdict.reason == "outside_distance_range"
    held = check(l_block_bank, scene, start, (300.0, bound), hold=True, monkeypatch=monkeypatch)
    assert held.refined.pose.t_mm[2] == pytest.approx(bound, abs=1e-6)
    assert held.verdict.reason != "outside_distance_range"


def test_a_refinement_past_the_near_bound_is_held_at_it(l_block_bank, scene, monkeypatch):
    bound = 490.0
    start = Pose(TRUTH.R, TRUTH.t_mm * (500.0 / TRUTH.t_mm[2]))
    held = check(l_block_bank, scene, start, (bound, 900.0), hold=True, monkeypatch=monkeypatch)
    assert held.refined.pose.t_mm[2] == pytest.approx(bound, abs=1e-6)


def test_a_start_outside_the_range_is_held_too(l_block_bank, scene, monkeypatch):
    """Proposals lie past the range too (a colour region's depth): the bound holds whatever the start."""
    bound = 450.0
    start = Pose(TRUTH.R, TRUTH.t_mm * (460.0 / TRUTH.t_mm[2]))
    c = check(l_block_bank, scene, start, (300.0, bound), hold=True, monkeypatch=monkeypatch)
    assert c.refined.pose.t_mm[2] == pytest.approx(bound, abs=1e-6)


def test_far_beyond_the_bound_is_not_held(l_block_bank, scene, monkeypatch):
    """A refinement that ends more than ``range_hold_max`` past the bound found something else than a part in
    the range: it is refused, not held."""
    bound = 400.0  # the truth 17.5 % beyond it
    start = Pose(TRUTH.R, TRUTH.t_mm * (395.0 / TRUTH.t_mm[2]))
    assert TRUTH.t_mm[2] > bound * (1 + pipeline.DEFAULT_POLICY.range_hold_max)
    c = check(l_block_bank, scene, start, (300.0, bound), hold=True, monkeypatch=monkeypatch)
    assert c.verdict.reason == "outside_distance_range"
