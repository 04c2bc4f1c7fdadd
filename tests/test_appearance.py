"""Taught appearance: reference photos of a painted part give its colours back, and the evidence tells
the part's colour pattern from another pattern of the same outline."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from service.vision.estimate.evidence import ColourFrame, evidence
from service.vision.estimate.verdict import (
    APPEARANCE_WEIGHTS,
    TYPICAL_RIGHT,
    WEIGHTS,
    rejection_reason,
    weights_for,
)
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, Rx, Ry, Rz
from service.vision.geometry.render import render
from service.vision.model.appearance import SPIN_VIEWS, ReferenceView, spun, teach, vertex_normals

# One colour per side of the box (+x, -x, +y, -y, +z, -z), BGR, far apart.
SIDE_BGR = np.array([[200, 40, 40], [40, 200, 40], [40, 40, 200], [200, 200, 40], [200, 40, 200],
                     [40, 200, 200]], float)
FLOOR_BGR = (110.0, 110.0, 110.0)
INTR = Intrinsics(500.0, 500.0, 159.5, 119.5)
SIZE = (320, 240)
COLOUR_TOL = 3.0  # grey levels: the rendered colours are exact, the photo's pixels are rounded
DEPTH_TOL = 0.01  # a rendered outline is known to half a pixel: on a box ~150 px across, a depth to ~0.7 %


def _box():
    mesh = trimesh.creation.box((60.0, 40.0, 30.0))
    for _ in range(3):  # interior vertices: their colour is one side's, not a mix across an edge
        mesh = mesh.subdivide()
    return SimpleNamespace(vertices_mm=np.asarray(mesh.vertices, float), faces=np.asarray(mesh.faces))


BOX = _box()


def _side_of_face(part) -> np.ndarray:
    """(F,) index into SIDE_BGR of each face's side (its normal's axis and sign)."""
    v, f = part.vertices_mm, part.faces
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    axis = np.argmax(np.abs(n), axis=1)
    return 2 * axis + (n[np.arange(len(n)), axis] < 0)


def _photo(pose: Pose, side_bgr=SIDE_BGR, gain: float = 1.0, offset: float = 0.0, seed: int = 0,
           intr: Intrinsics = INTR, size=SIZE):
    """The painted box at ``pose`` on a grey floor with sensor noise, its colours mapped by gain and
    offset (another light): (H, W, 3) uint8, and the render."""
    r = render(BOX.vertices_mm, BOX.faces, pose, intr.K, size)
    img = np.empty((size[1], size[0], 3))
    img[:] = FLOOR_BGR
    on = r.face_id >= 0
    img[on] = gain * np.asarray(side_bgr, float)[_side_of_face(BOX)[r.face_id[on]]] + offset
    img += np.random.default_rng(seed).normal(0.0, 1.0, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), r


POSE_A = Pose(Rx(-35.0) @ Ry(30.0), np.array([0.0, 0.0, 400.0]))  # sees +z, -y... three sides
POSE_B = Pose(Rx(140.0) @ Ry(-40.0) @ Rz(20.0), np.array([10.0, -5.0, 420.0]))  # the other three
POSE_C = Pose(Rx(-30.0) @ Ry(-35.0) @ Rz(10.0), np.array([-8.0, 6.0, 380.0]))


def _interior_faces() -> np.ndarray:
    """Faces all of whose vertices lie inside one side (their normals are the side's): no colour edge."""
    vn = vertex_normals(BOX.vertices_mm, BOX.faces)
    flat = np.abs(vn).max(axis=1) > 0.999
    return flat[BOX.faces].all(axis=1)


def test_one_photo_teaches_the_colour_of_every_side_it_shows_and_nothing_else():
    img, r = _photo(POSE_A)
    app = teach(BOX.vertices_mm, BOX.faces, [ReferenceView(img, INTR, POSE_A)])
    side = _side_of_face(BOX)
    seen_sides = np.unique(side[r.face_id[r.face_id >= 0]])
    assert len(seen_sides) == 3
    known = np.isfinite(app.face_bgr[:, 0])
    interior = _interior_faces()
    for s in range(6):
        faces = interior & (side == s)
        if s in seen_sides:
            # Most of a side seen face-on is read; what is read is the side's colour.
            assert known[faces].mean() > 0.8, s
            err = np.abs(app.face_bgr[faces & known] - SIDE_BGR[s]).max()
            assert err < COLOUR_TOL, (s, err)
        else:
            assert not known[faces].any(), s  # a side the photo does not show stays unknown


def test_hidden_pixels_are_not_read_and_the_median_outvotes_a_covered_photo():
    img, r = _photo(POSE_A)
    covered = img.copy()
    cover = np.zeros(r.mask.shape, bool)
    cover[:, : SIZE[0] // 2] = True
    covered[cover] = (30, 160, 90)  # something in front of the left half, the part's pose unchanged
    side = _side_of_face(BOX)
    interior = _interior_faces()
    hid = teach(BOX.vertices_mm, BOX.faces, [ReferenceView(covered, INTR, POSE_A, hidden=cover)])
    known = np.isfinite(hid.face_bgr[:, 0]) & interior
    assert known.any()
    assert np.abs(hid.face_bgr[known] - SIDE_BGR[side[known]]).max() < COLOUR_TOL
    # Not marked hidden: one covered photo among three is outvoted vertex by vertex.
    other, _ = _photo(POSE_A, seed=1)
    third, _ = _photo(POSE_A, seed=2)
    views = [ReferenceView(covered, INTR, POSE_A), ReferenceView(other, INTR, POSE_A),
             ReferenceView(third, INTR, POSE_A)]
    app = teach(BOX.vertices_mm, BOX.faces, views)
    known = np.isfinite(app.face_bgr[:, 0]) & interior
    assert np.abs(app.face_bgr[known] - SIDE_BGR[side[known]]).max() < COLOUR_TOL
    assert app.n_views == 3


def _taught():
    views = [ReferenceView(_photo(p)[0], INTR, p) for p in (POSE_A, POSE_B)]
    return teach(BOX.vertices_mm, BOX.faces, views)


def test_appearance_is_high_at_the_truth_under_another_light_and_low_for_another_pattern():
    app = _taught()
    # Two photos show all six sides; the vertices along the outline each photo sees are not read.
    assert app.known_fraction > 0.75
    for gain, offset in ((1.0, 0.0), (0.6, 30.0)):  # an affine change of light is no evidence against
        img, _ = _photo(POSE_C, gain=gain, offset=offset, seed=3)
        ev = evidence(BOX, POSE_C, INTR, ColourFrame(img), face_bgr=app.face_bgr)
        assert ev.appearance > 0.95, (gain, ev.appearance)
        assert ev.appearance_known > 0.85
    # The same outline painted with the sides' colours swapped: the silhouette's edges and regions are
    # as good as the truth's, the colour pattern is not the part's.
    swapped, _ = _photo(POSE_C, side_bgr=SIDE_BGR[[3, 5, 1, 0, 2, 4]], seed=3)
    ev = evidence(BOX, POSE_C, INTR, ColourFrame(swapped), face_bgr=app.face_bgr)
    assert ev.appearance < 0.3, ev.appearance
    # Without taught colours the evidence has none of it.
    plain = evidence(BOX, POSE_C, INTR, ColourFrame(swapped))
    assert plain.appearance is None and "appearance" not in plain.as_dict()


def test_an_occluder_covering_a_fifth_of_the_part_barely_lowers_the_appearance():
    app = _taught()
    img, r = _photo(POSE_C, seed=4)
    cols = np.nonzero(r.mask.any(axis=0))[0]
    counts = np.cumsum(r.mask.sum(axis=0))
    cut = int(np.searchsorted(counts, 0.2 * counts[-1]))
    img[:, cols[0]:cut + 1] = (30, 160, 90)
    ev = evidence(BOX, POSE_C, INTR, ColourFrame(img), face_bgr=app.face_bgr)
    assert ev.appearance > 0.9, ev.appearance


def test_untaught_faces_lower_the_known_share_by_their_pixels():
    one = teach(BOX.vertices_mm, BOX.faces, [ReferenceView(_photo(POSE_A)[0], INTR, POSE_A)])
    img, r = _photo(POSE_B, seed=5)  # the sides POSE_A did not show
    ev = evidence(BOX, POSE_B, INTR, ColourFrame(img), face_bgr=one.face_bgr)
    assert ev.appearance_known < 0.1
    assert ev.appearance == 0.0  # too few known pixels to correlate: no evidence for the pose


def test_taught_evidence_switches_the_score_and_names_the_appearance_when_it_fails():
    typical = {"edge_support": 0.9, "unexplained": 0.1, "colour_edge": 0.95, "region_global": 0.85,
               "shading_r2": 0.9, "generic": 0.5}
    assert weights_for(typical) is WEIGHTS
    taught = typical | {"appearance": 0.05, "appearance_known": 0.9}
    assert weights_for(taught) is APPEARANCE_WEIGHTS
    # Everything but the appearance looks like a true pose's: the appearance is the reason.
    assert rejection_reason(taught) == "appearance_mismatch"
    # The untextured shading model is no reason for a taught part.
    assert rejection_reason(taught | {"shading_r2": 0.0, "appearance": TYPICAL_RIGHT["appearance"]}) != (
        "shading_mismatch")


@pytest.mark.parametrize("k", ["appearance", "appearance_known", "region_global"])
def test_appearance_weights_never_lower_the_score_for_better_evidence(k):
    assert APPEARANCE_WEIGHTS[k] > 0


POSE_T = Pose(Rx(-50.0) @ Ry(25.0) @ Rz(15.0), np.array([12.0, -8.0, 450.0]))
TAUGHT_FOUND_ROT_DEG = 3.0  # a found pose is the painted truth, not one of its silhouette's other poses
INTR_E2E = Intrinsics(800.0, 800.0, 319.5, 239.5)  # the search needs the box larger than at INTR
SIZE_E2E = (640, 480)


def _rot_deg(Ra, Rb) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1))))


def test_the_outline_and_the_shading_fit_cannot_tell_a_turned_box_the_taught_colours_can():
    """A box's silhouette is the same turned 180 degrees about its axis, and a quadratic in the normals
    fits any three side colours: untaught, both poses verify. Taught, only the painted truth does."""
    from service.vision.estimate.verdict import MIN_SCORE
    from service.vision.pipeline import unrefined_score

    app = _taught()
    img, _ = _photo(POSE_T, seed=8)
    turned = Pose(POSE_T.R @ Rz(180.0), POSE_T.t_mm)
    same = render(BOX.vertices_mm, BOX.faces, turned, INTR.K, SIZE).mask
    truth = render(BOX.vertices_mm, BOX.faces, POSE_T, INTR.K, SIZE).mask
    assert (same & truth).sum() / (same | truth).sum() > 0.99
    frame = ColourFrame(img)
    for pose in (POSE_T, turned):
        assert unrefined_score(BOX, pose, frame, INTR, None) >= MIN_SCORE
    assert unrefined_score(BOX, POSE_T, frame, INTR, None, app) >= MIN_SCORE
    assert unrefined_score(BOX, turned, frame, INTR, None, app) < MIN_SCORE


@pytest.fixture(scope="module")
def box_bank():
    from service.vision import pipeline

    mesh = trimesh.Trimesh(BOX.vertices_mm, BOX.faces, process=False)
    return pipeline.build_templates(mesh, symmetry="none", grid={"view_step_deg": 15.0, "render_px": 160})


def test_estimate_with_taught_colours_finds_the_painted_pose(box_bank):
    """End to end: taught from three photos at other poses (``pipeline.teach_appearance``), the estimate
    reports the taught evidence and finds the box at the painted truth."""
    from service.vision import pipeline

    photos = [(_photo(p, seed=7, intr=INTR_E2E, size=SIZE_E2E)[0], INTR_E2E, p)
              for p in (POSE_A, POSE_C, POSE_B)]
    app = pipeline.teach_appearance(box_bank, photos)
    assert app.used and app.agreement > 0.95
    img, _ = _photo(POSE_T, seed=8, intr=INTR_E2E, size=SIZE_E2E)
    out = pipeline.estimate(box_bank, img, INTR_E2E, distance_range_mm=(350.0, 550.0), appearance=app)
    assert out.found and out.verdict.reason == "found", out.verdict
    assert out.verdict.evidence["appearance"] > 0.9
    assert _rot_deg(out.refined.pose.R, POSE_T.R) < TAUGHT_FOUND_ROT_DEG
    assert np.linalg.norm(out.refined.pose.t_mm - POSE_T.t_mm) < 5.0


def test_a_taught_pass_ends_at_its_first_found_candidate(box_bank):
    """Two candidates at one place, the box turned 180 degrees about its axis first (the same outline, other
    colours), then the painted truth, with an operating point both pass: the first found candidate ends
    the pass, though the taught colours tell the two apart."""
    from service.vision import pipeline
    from service.vision.estimate.edges import to_grey_u8
    from service.vision.estimate.evidence import colour_frame

    photos = [(_photo(p, seed=7, intr=INTR_E2E, size=SIZE_E2E)[0], INTR_E2E, p)
              for p in (POSE_A, POSE_C, POSE_B)]
    app = pipeline.teach_appearance(box_bank, photos)
    img, _ = _photo(POSE_T, seed=8, intr=INTR_E2E, size=SIZE_E2E)
    turned = Pose(POSE_T.R @ Rz(180.0), POSE_T.t_mm)
    frame = colour_frame(img)
    s_turned = pipeline.unrefined_score(box_bank, turned, frame, INTR_E2E, None, app)
    s_truth = pipeline.unrefined_score(box_bank, POSE_T, frame, INTR_E2E, None, app)
    assert s_turned < s_truth - 0.05  # the taught colours tell them apart
    cands = [pipeline.PoseCandidate(pose, 0.0, 0.0) for pose in (turned, POSE_T)]
    checked = pipeline.verify_candidates(box_bank, cands, to_grey_u8(img), frame, INTR_E2E,
                                         distance_mm=None, distance_range_mm=(350.0, 550.0),
                                         min_score=s_turned - 0.1, n_channels=16, appearance=app)
    assert checked[0].verdict.found
    best_rot = _rot_deg(checked[0].refined.pose.R, POSE_T.R)
    assert best_rot >= TAUGHT_FOUND_ROT_DEG, best_rot
    assert len(checked) == 1


def test_a_revolved_part_is_taught_at_every_spin_about_its_axis():
    """The spins turn the part about its own axis: the axis's points stay where the pose puts them, and
    spin k is k steps of a full turn (about y here: R @ Ry)."""
    axis, p0 = np.array([0.0, 1.0, 0.0]), np.array([5.0, 0.0, -3.0])
    pose = Pose(Rx(30.0), np.array([1.0, 2.0, 400.0]))
    spins = spun(pose, axis, p0)
    assert len(spins) == SPIN_VIEWS
    axis_point = p0 + [0.0, 50.0, 0.0]
    for k, p in enumerate(spins):
        np.testing.assert_allclose(p.apply(axis_point[None])[0], pose.apply(axis_point[None])[0], atol=1e-9)
        np.testing.assert_allclose(p.apply(p0[None])[0], pose.apply(p0[None])[0], atol=1e-9)
        turn = Ry(360.0 * k / SPIN_VIEWS)
        np.testing.assert_allclose(np.asarray(p.R), np.asarray(pose.R) @ turn, atol=1e-9)


@pytest.mark.parametrize("repainted, used", [((0, 1, 2, 3, 4, 5), True), ((3, 5, 1, 0, 2, 4), False)])
def test_photos_are_used_only_if_each_agrees_with_what_the_others_teach(repainted, used):
    """Three photos of one paint agree (each one's colours, as the other two teach them, correlate
    perfectly); the same three with each painted another way (a different part, or shading that moves
    with the pose) disagree, and their colours are not used. One photo alone cannot be checked."""
    from service.vision import pipeline

    part = SimpleNamespace(vertices_mm=BOX.vertices_mm, faces=BOX.faces, symmetry_axis_obj=None,
                           symmetry_point_obj=None)
    perms = [np.arange(6), np.asarray(repainted), np.asarray(repainted)[np.asarray(repainted)]]
    photos = [(_photo(p, SIDE_BGR[perm], seed=7, intr=INTR_E2E, size=SIZE_E2E)[0], INTR_E2E, p)
              for perm, p in zip(perms, (POSE_A, POSE_C, POSE_B), strict=True)]
    app = pipeline.teach_appearance(part, photos)
    assert app.used == used and not app.plain
    assert (app.agreement > 0.95) if used else (app.agreement < 0.0)
    one = pipeline.teach_appearance(part, photos[:1])
    assert np.isnan(one.agreement) and not one.used


def test_the_taught_colours_polish_a_pose_a_few_millimetres_off_back_onto_the_truth():
    """Started 3 mm off the painted truth along x, the polish's 1 mm steps walk back onto it: the
    colours fit best at the truth, and the score rises."""
    from service.vision.pipeline import polish_appearance, unrefined_score

    app = _taught()
    img, _ = _photo(POSE_T, seed=9)
    frame = ColourFrame(img)
    off = Pose(POSE_T.R, POSE_T.t_mm + np.array([3.0, 0.0, 0.0]))
    polished = polish_appearance(BOX, off, frame, INTR, app, None)
    np.testing.assert_allclose(polished.t_mm, POSE_T.t_mm, atol=1e-9)
    np.testing.assert_allclose(polished.R, POSE_T.R, atol=1e-12)
    before = unrefined_score(BOX, off, frame, INTR, None, app)
    assert unrefined_score(BOX, polished, frame, INTR, None, app) > before


def test_a_found_answer_keeps_its_colour_outline_depth_where_the_edges_disagree(box_bank):
    """The grey image's edges drawn 3 % too far (as printed edges inside a real part's rim pull the edge
    refinement, ``bench/depth_from_gt.py``), the colours and the found answer's start at the truth x 1.06:
    held at its colours' outline's depth (``Checker.outlined_on_colours``), the answer keeps the truth's
    depth."""
    ratio = _outlined_against_edges(box_bank, 1.03).refined.pose.t_mm[2] / POSE_T.t_mm[2]
    assert abs(ratio - 1.0) < DEPTH_TOL


def test_a_held_answer_the_edges_turn_is_not_taken(box_bank):
    """The edges drawn 6 % too far: held at the outline's depth, the refinement can only meet them by
    turning the pose, and the turned pose is not the found one (``same_place_but_depth``): the found
    answer stands as it was."""
    found = _found_at(Pose(POSE_T.R, POSE_T.t_mm * 1.06))
    assert _outlined_against_edges(box_bank, 1.06, found) is found


def test_a_pose_moved_along_its_line_of_sight_is_the_same_place_but_for_its_depth(box_bank):
    """Known answers (``Policy.hold_same_place_px``, 3 px; the box's corners 450 mm away at f = 800 px):
    the pose scaled along its line of sight is the same place, and so is it turned 2 deg about the optical
    axis (1.4 px on average); turned 5 deg (3.6 px) or moved 3 mm sideways (5.3 px) it is not."""
    from service.vision.pipeline import same_place_but_depth as _same_place_but_depth

    K = INTR_E2E.K
    assert _same_place_but_depth(box_bank, POSE_T, Pose(POSE_T.R, POSE_T.t_mm * 1.07), K)
    assert _same_place_but_depth(box_bank, POSE_T, Pose(Rz(2.0) @ POSE_T.R, POSE_T.t_mm * 1.07), K)
    assert not _same_place_but_depth(box_bank, POSE_T, Pose(Rz(5.0) @ POSE_T.R, POSE_T.t_mm), K)
    assert not _same_place_but_depth(box_bank, POSE_T, Pose(POSE_T.R, POSE_T.t_mm + [3.0, 0.0, 0.0]), K)


def _found_at(pose: Pose):
    from dataclasses import replace

    from service.vision.estimate.verdict import decide

    return _checked(pose, replace(decide(None), found=True, reason="found"))


def _outlined_against_edges(box_bank, edges_scale: float, found=None):
    """A found answer at the truth x 1.06 moved to its colours' outline, the colours at the truth and the
    grey image's edges at the truth x ``edges_scale``."""
    from service.vision import pipeline
    from service.vision.estimate.edges import to_grey_u8
    from service.vision.estimate.evidence import colour_frame

    photos = [(_photo(p, seed=7, intr=INTR_E2E, size=SIZE_E2E)[0], INTR_E2E, p)
              for p in (POSE_A, POSE_C, POSE_B)]
    app = pipeline.teach_appearance(box_bank, photos)
    colours, _ = _photo(POSE_T, seed=8, intr=INTR_E2E, size=SIZE_E2E)
    edges, _ = _photo(Pose(POSE_T.R, POSE_T.t_mm * edges_scale), seed=8, intr=INTR_E2E, size=SIZE_E2E)
    check = pipeline.Checker(box_bank, to_grey_u8(edges), colour_frame(colours), INTR_E2E, None, 16,
                             dict(distance_range_mm=(350.0, 550.0), min_score=0.0, appearance=app))
    return check.outlined_on_colours(found or _found_at(Pose(POSE_T.R, POSE_T.t_mm * 1.06)), None)


def test_the_polish_never_steps_out_of_the_searched_distance_range():
    """The truth 8 mm beyond the range's far bound, a start 8 mm inside it: unbounded, the polish's 4 mm
    depth steps walk to the truth; bounded, the polish ends within the range (the depth at most the bound:
    the closest the steps come to the truth), its lateral position unchanged."""
    from service.vision.pipeline import polish_appearance

    app = _taught()
    img, _ = _photo(POSE_T, seed=9)
    frame = ColourFrame(img)
    z = float(POSE_T.t_mm[2])
    start = Pose(POSE_T.R, POSE_T.t_mm - np.array([0.0, 0.0, 16.0]))
    free = polish_appearance(BOX, start, frame, INTR, app, None)
    assert abs(free.t_mm[2] - z) < 4.0  # the 4 mm steps reach the truth's depth unbounded
    bounded = polish_appearance(BOX, start, frame, INTR, app, None, distance_range_mm=(z - 40.0, z - 8.0))
    assert z - 16.0 <= bounded.t_mm[2] <= z - 8.0
    assert bounded.t_mm[2] == pytest.approx(z - 8.0)
    np.testing.assert_allclose(bounded.t_mm[:2], POSE_T.t_mm[:2], atol=1.0)


def test_no_polish_step_is_taken_past_the_deadline():
    import time

    from service.vision.deadline import Deadline
    from service.vision.pipeline import polish_appearance

    app = _taught()
    img, _ = _photo(POSE_T, seed=9)
    off = Pose(POSE_T.R, POSE_T.t_mm + np.array([3.0, 0.0, 0.0]))
    spent = Deadline(1.0, start=time.perf_counter() - 1.0)
    assert polish_appearance(BOX, off, ColourFrame(img), INTR, app, None, spent) is off


def test_a_taught_found_answer_too_far_is_moved_to_its_colours_outline(box_bank):
    """A found answer 6 % too far (as region proposals on real photos end, ``bench/depth_from_gt.py``) is
    moved to where the box's colours end and refined again: its depth comes back to the painted truth's
    (``Checker.outlined_on_colours``)."""
    from dataclasses import replace

    from service.vision import pipeline
    from service.vision.estimate.edges import to_grey_u8
    from service.vision.estimate.evidence import colour_frame
    from service.vision.estimate.verdict import decide

    photos = [(_photo(p, seed=7, intr=INTR_E2E, size=SIZE_E2E)[0], INTR_E2E, p)
              for p in (POSE_A, POSE_C, POSE_B)]
    app = pipeline.teach_appearance(box_bank, photos)
    img, _ = _photo(POSE_T, seed=8, intr=INTR_E2E, size=SIZE_E2E)
    check = pipeline.Checker(box_bank, to_grey_u8(img), colour_frame(img), INTR_E2E, None, 16,
                             dict(distance_range_mm=(350.0, 550.0), min_score=0.0, appearance=app))
    far = Pose(POSE_T.R, POSE_T.t_mm * 1.06)
    found = pipeline.Checked(pipeline.PoseCandidate(far, 0.0, 0.0), pipeline.RefinedPose(far, 0.0, 0.0),
                             replace(decide(None), found=True, reason="found"))
    out = check.outlined_on_colours(found, None)
    assert out.verdict.found
    assert abs(out.refined.pose.t_mm[2] / POSE_T.t_mm[2] - 1.0) < DEPTH_TOL
    assert _rot_deg(out.refined.pose.R, POSE_T.R) < TAUGHT_FOUND_ROT_DEG


def _checked(pose: Pose, verdict):
    """A check whose candidate and refined pose are ``pose``."""
    from service.vision import pipeline

    return pipeline.Checked(pipeline.PoseCandidate(pose, 0.0, 0.0), pipeline.RefinedPose(pose, 0.0, 0.0),
                            verdict)
