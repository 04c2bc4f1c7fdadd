"""A part's agreement calibrated on rendered scenes (service/vision/pipeline/calibration_scenes.py,
plane_calibration.py) and the verdict that reads it (estimate/verdict.py: material_free,
agreement_score, decide).

Scenes: the L-shaped block of tests/conftest.py among look-alike shapes, drawn by the project's rasteriser.
"""

from __future__ import annotations

import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from service.vision.estimate.verdict import (
    MIN_SCORE,
    PlaneAgreement,
    agreement_score,
    decide,
    distinct,
    material_free,
)
from service.vision.geometry.camera import project
from service.vision.geometry.frames import Rx, Rz
from service.vision.geometry.plane import Plane, R_cam_rest, rest_gap_mm
from service.vision.pipeline import estimate
from service.vision.pipeline.calibration_scenes import _part_alike, scene
from service.vision.pipeline.part import rest_family
from service.vision.pipeline.place import SAME_PLACE_IOU, outagreed, rivals_at
from service.vision.pipeline.plane_calibration import (
    ALONG_MIN_GAIN,
    MARGIN,
    MIN_RIGHT_PER_SCENE,
    MIN_WRONG_PER_REST_SCENE,
    MIN_WRONG_PER_SCENE,
    REFUSED_FOR_PLACE,
    RIGHT_PX,
    PlaneRecord,
    calibrated,
    place_point,
    plane_records,
)
from service.vision.pipeline.types import Checked

RESTING_MM = 1e-6  # a copy's lowest point lies on the table
UNREACHABLE = 2.0  # an agreement no pose reads
CONTRAST_GREY = 4.0  # a copy's pixels differ from the table's around it by more than the noise


@pytest.fixture(scope="module")
def bank(l_block_bank):
    return l_block_bank


def test_a_scene_is_drawn_again_from_the_same_seed(bank):
    a, b = scene(bank, np.random.default_rng([4, 2])), scene(bank, np.random.default_rng([4, 2]))
    assert np.array_equal(a.bgr, b.bgr) and len(a.poses) == len(b.poses) >= 2
    assert not np.array_equal(a.bgr, scene(bank, np.random.default_rng([4, 3])).bgr)


def test_copies_rest_on_the_table_or_on_objects_and_show_where_their_truth_projects(bank):
    sc = scene(bank, np.random.default_rng([1, 0]))
    assert sc.bgr.shape == (480, 640, 3)
    gaps = [rest_gap_mm(bank, pose, sc.plane) for pose in sc.poses]
    assert sum(abs(g) < RESTING_MM for g in gaps) >= 2  # on the table; any others lie on top of objects
    assert all(abs(g) < RESTING_MM or g > 0.0 for g in gaps)
    for pose, visible in zip(sc.poses, sc.visible, strict=True):
        assert 0.0 < visible <= 1.05  # (the whole silhouette is rendered once, without supersampling)
        uv = project(pose.apply(np.asarray(bank.centre_obj, float)[None]), sc.intr.K)[0]
        assert 0 <= uv[0] < 640 and 0 <= uv[1] < 480
    # the plane is the one the copies rest on, seen from above: its normal faces the camera
    assert sc.plane.d_mm < 0 and sc.plane.normal[2] < 0


def test_the_agreement_to_reach_lies_a_margin_above_the_highest_wrong_candidates():
    def rec(agreement, error_px, reason="low_score"):
        ev = {"edge_agreement": agreement, "polarity": 1.0, "distinct_px": 2.0}
        return PlaneRecord(error_px, reason, ev)

    wrong = [rec(0.3 + 0.001 * k, 50.0) for k in range(3 * MIN_WRONG_PER_SCENE)]
    plain = PlaneRecord(60.0, "low_score", {"edge_agreement": 0.95, "polarity": 1.0, "distinct_px": 0.5})
    records = [*wrong, rec(0.9, 100.0, "off_plane"), plain, rec(0.8, 2.0), rec(0.35, 1.0)]
    cal = calibrated(records, scenes=3)
    top = 0.3 + 0.001 * (3 * MIN_WRONG_PER_SCENE - 1)  # not the refused-for-its-place 0.9 nor the plain 0.95
    assert cal.agreement_min == pytest.approx(top + MARGIN) and cal.wrong_max == pytest.approx(top)
    assert (cal.right, cal.right_total, cal.wrong_total) == (1, 2, 3 * MIN_WRONG_PER_SCENE)
    assert calibrated(records[1:], scenes=3).agreement_min is None  # too few wrong candidates
    assert cal.agreement_along == "edge_agreement"  # records without an outline's agreement read 0 there
    assert cal.agreement == PlaneAgreement(cal.agreement_min, cal.agreement_floor, "edge_agreement")


def test_each_resting_family_has_its_own_point_where_its_scenes_hold_enough_wrong_poses():
    def rec(agreement, error_px, rest):
        return PlaneRecord(error_px, "low_score", {"edge_agreement": agreement, "polarity": 1.0,
                                                   "distinct_px": 2.0}, rest)

    scenes = 2
    n = MIN_WRONG_PER_REST_SCENE * scenes
    # family 0's wrong poses read low, family 1's high; family 2 has one: too few to say
    wrong = ([rec(0.30, 50.0, 0) for _ in range(n)] + [rec(0.60, 50.0, 1) for _ in range(n)]
             + [rec(0.20, 50.0, 2)] + [rec(0.25, 50.0, 3) for _ in range(MIN_WRONG_PER_SCENE * scenes)])
    right = [rec(0.50, 2.0, 0), rec(0.50, 2.0, 2), rec(0.70, 2.0, 1)]
    cal = calibrated([*wrong, *right], scenes=scenes)
    assert cal.agreement_min == pytest.approx(0.60 + MARGIN)  # the part's: its highest wrong pose's
    assert cal.agreement_min_by_rest == pytest.approx((0.30 + MARGIN, 0.60 + MARGIN, None, 0.25 + MARGIN))
    assert cal.right == 2  # family 0's 0.5 reaches its 0.38; family 2's reads the part's 0.68
    at = cal.agreement
    assert at.at_rest(0).point == pytest.approx(0.30 + MARGIN) and at.at_rest(2).point == cal.agreement_min
    assert at.at_rest(7).point == at.at_rest(-1).point == cal.agreement_min  # no such family: the part's
    ev = {"edge_agreement": 0.5, "polarity": 1.0, "distinct_px": 2.0, "edge_support": 0.0, "unexplained": 1.0,
          "colour_edge": 0.0, "region_low": 0.0, "region_global": 0.0, "coherence": 0.0, "shading_r2": 0.0,
          "shading_std": 0.0, "generic": 1.0, "region": 0.0}
    on_plane = {"plane_gap_mm": 0.0, "plane_tolerance_mm": 5.0}
    assert decide(ev, **on_plane, agreement=at.at_rest(0)).found
    assert not decide(ev, **on_plane, agreement=at.at_rest(2)).found
    # records of no known family (-1) give no family a point
    assert calibrated([rec(r.evidence["edge_agreement"], r.error_px, -1) for r in [*wrong, *right]],
                      scenes=scenes).agreement_min_by_rest == ()


def _placed(agreement, error_px, scene, place, overlap):
    ev = {"edge_agreement": agreement, "polarity": 1.0, "distinct_px": 2.0}
    return PlaneRecord(error_px, "low_score", ev, 0, scene, place, overlap)


def test_the_place_point_reads_the_wrong_poses_away_from_every_copy():
    scenes = 2
    n = MIN_WRONG_PER_SCENE * scenes
    elsewhere = [_placed(0.40 + 0.001 * k, 80.0, k % scenes, -1, 0.0) for k in range(n)]
    # each copy's flips read 0.6 at its place, its truth 0.7 there
    flips = [_placed(0.60, 40.0, s, p, 0.6) for s in range(scenes) for p in range(2)]
    truths = [_placed(0.70, 1.0, s, p, 0.9) for s in range(scenes) for p in range(2)]
    records = [*elsewhere, *flips, *truths]
    top_elsewhere = 0.40 + 0.001 * (n - 1)
    assert place_point(records, MARGIN, "edge_agreement") == pytest.approx(top_elsewhere + MARGIN)
    cal = calibrated(records, scenes=scenes)
    assert cal.agreement_min == pytest.approx(0.60 + MARGIN)  # the flips set the full point
    assert cal.agreement_min_place == pytest.approx(top_elsewhere + MARGIN)
    assert cal.agreement.place_point == cal.agreement_min_place
    # one copy whose flip outagreed its truth there: no place point
    outagreeing = [*records, _placed(0.75, 40.0, 1, 1, 0.5)]
    assert place_point(outagreeing, MARGIN, "edge_agreement") is None
    assert calibrated(outagreeing, scenes=scenes).agreement_min_place is None
    # a flip under the place point is no reason to drop it; records that do not say where they lie give none
    assert place_point([*records, _placed(0.45, 40.0, 1, 1, 0.5)], MARGIN, "edge_agreement") is not None
    assert place_point([*records, PlaneRecord(80.0, "low_score", {"edge_agreement": 0.1})], MARGIN,
                       "edge_agreement") is None


def test_a_pose_reaching_only_the_place_point_is_found_unless_a_rival_at_its_place_agrees_more():
    at = PlaneAgreement(0.70, None, "edge_agreement", (), 0.50)
    ev = {"edge_agreement": 0.60, "polarity": 1.0, "distinct_px": 2.0, "edge_support": 0.0,
          "unexplained": 1.0, "colour_edge": 0.0, "region_low": 0.0, "region_global": 0.0, "coherence": 0.0,
          "shading_r2": 0.0, "shading_std": 0.0, "generic": 1.0, "region": 0.0}
    on_plane = {"plane_gap_mm": 0.0, "plane_tolerance_mm": 5.0}
    v = decide(ev, **on_plane, agreement=at)
    assert v.found and v.evidence["at_place_point"] == 1.0
    assert v.score == pytest.approx(agreement_score(ev, PlaneAgreement(0.50, None)))
    full = decide(ev | {"edge_agreement": 0.75}, **on_plane, agreement=at)
    assert full.found and "at_place_point" not in full.evidence  # found on its own point: no contest
    assert not decide(ev | {"edge_agreement": 0.45}, **on_plane, agreement=at).found
    assert "at_place_point" not in decide(ev, **on_plane, agreement=replace(at, place_point=None)).evidence

    def checked(verdict):
        return Checked(None, None, verdict)

    c = checked(v)
    assert outagreed(c, [checked(decide(ev | {"edge_agreement": 0.55}, **on_plane, agreement=at))],
                     "edge_agreement") is c
    lost = outagreed(c, [checked(decide(ev | {"edge_agreement": 0.65}, **on_plane, agreement=at))],
                     "edge_agreement")
    assert not lost.verdict.found and lost.verdict.reason == "rival_at_place"
    assert lost.verdict.evidence["rival_agreement"] == pytest.approx(0.65)
    # a pose found on its own point holds against any rival
    f = checked(full)
    assert outagreed(f, [checked(decide(ev | {"edge_agreement": 0.9}, **on_plane, agreement=at))],
                     "edge_agreement") is f


def test_a_pose_on_a_plane_is_in_the_resting_family_it_was_turned_from():
    plane = Plane(np.array([0.0, -0.5, -1.0]) / np.linalg.norm([0.0, -0.5, -1.0]), -400.0)
    # a cylinder along its object z: standing on either end, or lying (any roll about its axis)
    cylinder = SimpleNamespace(R_rest_obj=np.stack([np.eye(3), Rx(180.0), Rx(90.0)]),
                               symmetry_axis_obj=np.array([0.0, 0.0, 1.0]))
    box = SimpleNamespace(R_rest_obj=np.stack([np.eye(3), Rx(90.0), Rx(180.0), Rx(-90.0)]),
                          symmetry_axis_obj=None)
    for part in (cylinder, box):
        for s, R_rest_obj in enumerate(part.R_rest_obj):
            for spin in (0.0, 70.0, 200.0):
                R_cam_obj = R_cam_rest(plane) @ Rz(spin) @ R_rest_obj
                assert rest_family(part, R_cam_obj, plane.normal) == s
    # the lying cylinder rolled about its own axis is still lying; tilted 10 deg, still in its family
    lying = R_cam_rest(plane) @ Rz(30.0) @ Rx(90.0)
    for roll in (35.0, 120.0, 250.0):
        assert rest_family(cylinder, lying @ Rz(roll), plane.normal) == 2
    assert rest_family(cylinder, R_cam_rest(plane) @ Rx(10.0), plane.normal) == 0
    assert rest_family(SimpleNamespace(R_rest_obj=np.zeros((0, 3, 3)), symmetry_axis_obj=None),
                       np.eye(3), plane.normal) == -1


def test_a_part_is_calibrated_along_the_edges_that_let_more_right_candidates_reach_their_point():
    def rec(edges, outline, error_px):
        return PlaneRecord(error_px, "low_score", {"edge_agreement": edges, "outline_agreement": outline,
                                                   "polarity": 1.0, "distinct_px": 2.0})

    n = MIN_WRONG_PER_SCENE
    m = 0.12  # the margin these agreements are laid out around
    # creases that seldom show: the right poses' outlines agree, their edges much less
    wrong = [rec(0.4, 0.6, 50.0) for _ in range(n)]
    right = [rec(0.45, 0.9, 2.0), rec(0.5, 0.95, 1.0), rec(0.6, 0.7, 3.0)]
    cal = calibrated([*wrong, *right], scenes=1, margin=m)
    assert cal.agreement_along == "outline_agreement"
    assert cal.agreement_min == pytest.approx(0.6 + m) and cal.right == 2
    assert cal.agreement_floor == pytest.approx(0.7 - m)  # the floor reads the same agreement
    assert calibrated([*wrong, *right], scenes=1, margin=m, along=("edge_agreement",)).right == 1
    # look-alike outlines: the edges tell them apart
    wrong = [rec(0.4, 0.95, 50.0) for _ in range(n)]
    assert calibrated([*wrong, *right], scenes=1, margin=m).agreement_along == "edge_agreement"
    # a tie keeps every edge's agreement
    wrong = [rec(0.4, 0.6, 50.0) for _ in range(n)]
    tie = [rec(0.9, 0.9, 2.0)]
    assert calibrated([*wrong, *tie], scenes=1, margin=m).agreement_along == "edge_agreement"
    # ... as does one more of many: the scenes' noise (``ALONG_MIN_GAIN``)
    many = [rec(0.6, 0.9, 2.0) for _ in range(11)] + [rec(0.45, 0.9, 2.0)]
    assert ALONG_MIN_GAIN * len(many) > 1
    assert calibrated([*wrong, *many], scenes=1, margin=m).agreement_along == "edge_agreement"


def test_the_least_agreement_found_lies_a_margin_below_the_lowest_right_candidates():
    def rec(agreement, error_px, distinct_px=2.0):
        return PlaneRecord(error_px, "low_score", {"edge_agreement": agreement, "polarity": 1.0,
                                                   "distinct_px": distinct_px})

    # the lowest right one has an outline a plain shape has too: the floor holds for it as well
    records = [rec(0.2, 50.0), rec(0.8, 2.0), rec(0.6, 4.9), rec(0.45, 1.0, distinct_px=0.5), rec(0.1, 5.0)]
    assert calibrated(records, scenes=1).agreement_floor == pytest.approx(0.45 - MARGIN)
    assert calibrated(records[:1], scenes=1).agreement_floor is None  # no right candidate: no floor
    # 3 right candidates in 4 scenes say too little of how low a right pose reads
    assert MIN_RIGHT_PER_SCENE * 4 > 3 and calibrated(records, scenes=4).agreement_floor is None


def test_the_material_free_score_is_held_down_by_polarity_and_reaches_the_operating_point_at_its_agreement():
    assert material_free({"edge_agreement": 0.8, "polarity": 0.6}) == 0.6
    assert material_free({"edge_agreement": 0.8, "outline_agreement": 0.5, "polarity": 0.6},
                         "outline_agreement") == 0.5
    def ev(agreement, distinct_px=2.0):
        return {"edge_agreement": agreement, "polarity": 1.0, "distinct_px": distinct_px}

    at = PlaneAgreement(0.7, None)
    assert agreement_score(ev(0.7), at) == pytest.approx(MIN_SCORE)
    assert agreement_score(ev(0.72), at) > MIN_SCORE
    assert agreement_score(ev(0.68), at) < MIN_SCORE
    assert agreement_score(ev(0.99, distinct_px=0.9), at) == 0.0
    assert agreement_score(ev(0.99), PlaneAgreement(None, 0.3)) == 0.0  # not calibrated


def test_a_calibrated_part_on_a_plane_is_found_on_its_agreement_and_only_there():
    ev = {"edge_support": 0.5, "unexplained": 0.3, "colour_edge": 0.9, "polarity": 0.95, "region": 0.5,
          "region_low": 0.5, "region_global": 0.3, "coherence": 0.5, "shading_r2": 0.2, "shading_std": 9.0,
          "generic": 0.5, "distinct_px": 2.0, "edge_agreement": 0.9, "inner_agreement": 0.8}
    assert not decide(ev, plane_gap_mm=0.0, plane_tolerance_mm=5.0).found  # the material-bound score
    on_plane = {"plane_gap_mm": 0.0, "plane_tolerance_mm": 5.0}
    found = decide(ev, **on_plane, agreement=PlaneAgreement(0.85, None))
    assert found.found and found.reason == "found" and found.score > MIN_SCORE
    assert not decide(ev, **on_plane, agreement=PlaneAgreement(0.95, None)).found
    assert decide(ev, plane_gap_mm=9.0, plane_tolerance_mm=5.0,
                  agreement=PlaneAgreement(0.85, None)).reason == "off_plane"
    assert not decide(ev, agreement=PlaneAgreement(0.85, None)).found  # without a plane it is not read
    plain = ev | {"distinct_px": 0.5}  # an outline a plain shape has too: edges alone do not tell
    assert not decide(plain, **on_plane, agreement=PlaneAgreement(0.85, None)).found
    # a part calibrated along its outline reads that agreement, not every edge's
    outline = ev | {"edge_agreement": 0.6, "outline_agreement": 0.9}
    assert decide(outline, **on_plane, agreement=PlaneAgreement(0.85, None, "outline_agreement")).found
    assert not decide(outline, **on_plane, agreement=PlaneAgreement(0.85, None)).found


def test_a_pose_whose_edges_disagree_is_not_found_on_a_plane_however_its_shading_reads():
    ev = {"edge_support": 0.97, "unexplained": 0.0, "colour_edge": 0.95, "polarity": 0.95, "region": 0.9,
          "region_low": 0.9, "region_global": 0.9, "coherence": 0.95, "shading_r2": 0.95, "shading_std": 9.0,
          "generic": 0.1, "distinct_px": 0.5, "edge_agreement": 0.2, "inner_agreement": 0.2}
    on_plane = {"plane_gap_mm": 0.0, "plane_tolerance_mm": 5.0}
    assert decide(ev, **on_plane).found  # the material-bound score alone finds it
    refused = decide(ev, **on_plane, agreement=PlaneAgreement(None, 0.3))
    assert not refused.found and refused.reason == "edges_disagree"
    assert refused.score == decide(ev, **on_plane).score  # the score is reported as it was
    assert decide(ev, **on_plane, agreement=PlaneAgreement(None, 0.15)).found
    assert decide(ev, agreement=PlaneAgreement(None, 0.3)).found  # without a plane it is not read


def test_calibration_records_the_copies_it_finds_as_right_and_the_estimate_reads_its_agreement(bank):
    records = plane_records(bank, n_scenes=1, seed=7)
    assert records and all(math.isfinite(r.error_px) for r in records)
    assert all(0 <= r.rest < len(bank.R_rest_obj) for r in records)  # each in a resting family of the part
    right = [r for r in records if r.error_px < RIGHT_PX]
    assert right, "the calibration scene's copies are among the checked candidates"
    # a right pose covers the copy it is right for: the record says which, and by how much
    assert all(r.scene == 0 and r.place >= 0 and r.overlap >= SAME_PLACE_IOU for r in right)
    # the same scene, estimated with the lowest agreement a right candidate read: it is found there
    sc = scene(bank, np.random.default_rng([7, 0]))
    a = min(material_free(r.evidence) for r in right)
    out = estimate(bank, sc.bgr, sc.intr, plane=sc.plane, max_instances=len(sc.poses),
                   agreement=PlaneAgreement(a, None))
    assert out.found
    # the same read as a place point only (the part's own point out of reach): what is found there is the
    # best-agreeing candidate at its place, each rival there checked and refused
    out = estimate(bank, sc.bgr, sc.intr, plane=sc.plane, max_instances=len(sc.poses),
                   agreement=PlaneAgreement(UNREACHABLE, None, place_point=a))
    at_place = [c for c in out.checked if c.verdict.found and "at_place_point" in c.verdict.evidence]
    assert at_place, "a copy is found at the place point alone"
    size, memo = (sc.bgr.shape[1], sc.bgr.shape[0]), {}
    for c in at_place:
        for r in rivals_at(bank, c, out.checked, sc.intr, size, memo):
            assert not r.verdict.found
            assert material_free(r.verdict.evidence) <= material_free(c.verdict.evidence) or not distinct(
                r.verdict.evidence) or r.verdict.reason in REFUSED_FOR_PLACE


@pytest.mark.parametrize("up_axis", [2, 0])
def test_a_stretched_look_alike_is_stretched_along_the_table_so_its_outline_from_above_differs(up_axis):
    # a 60 x 30 x 4 mm plate resting with its object axis ``up_axis`` along the table's normal
    plate = trimesh.creation.box([60.0, 30.0, 4.0])
    R_rest = np.eye(3) if up_axis == 2 else np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    part = SimpleNamespace(vertices_mm=np.asarray(plate.vertices, float), faces=np.asarray(plate.faces),
                           rest_probability=[1.0], R_rest_obj=R_rest[None])
    footprint = np.ptp(part.vertices_mm @ R_rest.T, axis=0)
    for i in range(60):
        V = _part_alike(np.random.default_rng([7, i]), part, stretched=True).vertices_mm
        ratio = np.ptp(V, axis=0) / footprint
        assert ratio[2] == pytest.approx(1.0)  # its height is the part's
        # stretched by 0.5-0.75 or 1.3-2 along the table: its outline from above is not the part's
        assert min(abs(np.log(ratio[:2]))) == pytest.approx(0.0, abs=1e-9)
        assert max(abs(np.log(ratio[:2]))) >= math.log(1.3) - 1e-9
