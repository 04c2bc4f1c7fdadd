"""The verdict's known answers on constructed scenes: found means right, and every no says why.

Scenes are rendered with the project's rasteriser at 640 x 480: a box-shaped part (no symmetry) on a
plain floor (found, at its pose), a checkerboard without the part (not found), the part beyond the
requested distance range (never returned), an empty image (no candidate).
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from service.vision import pipeline
from service.vision.estimate import verdict
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, Rx, Ry, Rz
from service.vision.geometry.render import render_shaded
from tests.tolerances import FOUND_POSE_T_MM

INTR = Intrinsics(600.0, 600.0, 319.5, 239.5)
SIZE = (640, 480)
POSE = Pose(Rx(35.0) @ Ry(-20.0) @ Rz(15.0), np.array([12.0, -8.0, 420.0]))
REJECTIONS = set(verdict.REASONS) - {"found"}


@pytest.fixture(scope="module")
def part_bank():
    # An L-shaped block: two boxes joined, no symmetry, creases a real part would have.
    a = trimesh.creation.box((80.0, 20.0, 40.0))
    b = trimesh.creation.box((20.0, 60.0, 40.0))
    b.apply_translation((-30.0, 40.0, 0.0))
    mesh = trimesh.util.concatenate([a, b])
    return pipeline.build_templates(mesh, symmetry="none", grid={"view_step_deg": 15.0, "render_px": 160})


def _colour(grey: np.ndarray, bgr_gain=(1.0, 1.0, 1.0)) -> np.ndarray:
    return np.clip(grey[..., None].astype(np.float64) * np.asarray(bgr_gain), 0, 255).astype(np.uint8)


def _checkerboard(period_px: int = 36, lo: int = 60, hi: int = 190) -> np.ndarray:
    v, u = np.mgrid[0:SIZE[1], 0:SIZE[0]]
    return np.where(((u // period_px) + (v // period_px)) % 2 == 0, lo, hi).astype(np.uint8)


def test_part_on_a_plain_floor_is_found_at_its_pose(part_bank):
    img = _colour(render_shaded(part_bank.vertices_mm, part_bank.faces, POSE, INTR.K, SIZE, background=70))
    out = pipeline.estimate(part_bank, img, INTR, distance_range_mm=(300.0, 600.0))
    assert out.found and out.verdict.found and out.verdict.reason == "found"
    assert out.verdict.score >= verdict.MIN_SCORE
    assert np.linalg.norm(out.refined.pose.t_mm - POSE.t_mm) <= FOUND_POSE_T_MM
    assert set(verdict.FEATURES) - set(verdict.TAUGHT_FEATURES) - set(verdict.PLANE_FEATURES) <= set(
            out.verdict.evidence)


def test_checkerboard_without_the_part_is_not_found_and_says_why(part_bank):
    out = pipeline.estimate(part_bank, _colour(_checkerboard()), INTR, distance_range_mm=(300.0, 600.0),
                            overlay=True)
    assert not out.found and out.coarse is None and out.refined is None
    assert out.verdict.reason in REJECTIONS
    assert out.overlay_png is not None


def test_operating_point_is_the_integrators_to_move(part_bank):
    img = _colour(render_shaded(part_bank.vertices_mm, part_bank.faces, POSE, INTR.K, SIZE, background=70))
    strict = pipeline.estimate(part_bank, img, INTR, distance_range_mm=(300.0, 600.0), min_score=1.0)
    assert not strict.found and strict.verdict.reason != "found"
    assert strict.verdict.score < 1.0


def test_a_pose_outside_the_requested_range_is_never_returned(part_bank):
    far = Pose(POSE.R, np.array([0.0, 0.0, 900.0]))
    img = _colour(render_shaded(part_bank.vertices_mm, part_bank.faces, far, INTR.K, SIZE, background=70))
    rng = (300.0, 600.0)
    out = pipeline.estimate(part_bank, img, INTR, distance_range_mm=rng)
    assert not out.found
    assert out.verdict.reason in REJECTIONS
    for c in out.candidates:  # what is listed may be anywhere; what is reported is not
        assert c is not None
    assert out.refined is None and out.coarse is None


def test_empty_image_has_no_candidate(part_bank):
    out = pipeline.estimate(part_bank, np.full((SIZE[1], SIZE[0], 3), 90, np.uint8), INTR)
    assert not out.found and out.verdict.reason == "no_candidate" and out.verdict.score == 0.0


# --- the decision on given evidence: each reason from a constructed case ----------------------------

TRUE_LIKE = {"edge_support": 0.98, "unexplained": 0.0, "colour_edge": 1.0, "polarity": 1.0, "region": 0.95,
             "region_low": 0.9, "region_global": 0.95, "coherence": 0.95, "shading_r2": 0.95,
             "shading_std": 20.0, "in_image": 1.0, "generic": 0.85}


def test_true_like_evidence_is_found():
    v = verdict.decide(TRUE_LIKE, z_mm=500.0, distance_range_mm=(300.0, 1200.0))
    assert v.found and v.reason == "found"


@pytest.mark.parametrize("change, reason", [
    ({"edge_support": 0.2, "region_global": 0.5, "shading_r2": 0.6}, "low_support"),
    ({"unexplained": 6.0, "region_global": 0.5, "shading_r2": 0.6}, "interior_edges"),
    ({"region": 0.05, "region_low": 0.0, "region_global": 0.0, "colour_edge": 0.3, "polarity": 0.3,
      "coherence": 0.0}, "region_mismatch"),
    ({"shading_r2": 0.0, "region_global": 0.6}, "shading_mismatch"),
    ({"in_image": 0.2}, "outside_image"),
    ({"in_image": 0.7}, "outside_image"),  # a pose cut by the border: its cut-off part is not checked
    # fair region and shading evidence along an outline an ellipse or a cylinder view has as well
    ({"region_global": 0.8, "shading_r2": 0.82, "generic": 0.99},
     "generic_outline"),
])
def test_each_rejection_names_its_evidence(change, reason):
    v = verdict.decide(TRUE_LIKE | change, z_mm=500.0, distance_range_mm=(300.0, 1200.0))
    assert not v.found and v.reason == reason


def test_a_pose_cut_by_the_border_is_judged_only_when_nearly_all_its_outline_is_inside():
    below, at = verdict.MIN_IN_IMAGE - 0.01, verdict.MIN_IN_IMAGE
    assert verdict.decide(TRUE_LIKE | {"in_image": below}).reason == "outside_image"
    assert verdict.decide(TRUE_LIKE | {"in_image": at}).found


def test_distance_outside_range_is_rejected_whatever_the_evidence():
    v = verdict.decide(TRUE_LIKE, z_mm=1300.0, distance_range_mm=(300.0, 1200.0))
    assert not v.found and v.reason == "outside_distance_range" and v.evidence["z_mm"] == 1300.0


def test_a_pose_with_no_pixel_in_the_image_is_judged_not_found():
    from service.vision.estimate.evidence import NO_EVIDENCE

    v = verdict.decide(NO_EVIDENCE.as_dict() | {"edge_support": 0.0, "unexplained": 0.0})
    assert not v.found and v.score < 0.5


def test_no_hypothesis_is_no_candidate():
    v = verdict.decide(None)
    assert not v.found and v.reason == "no_candidate"
