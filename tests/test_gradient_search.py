"""The gradient search of a part on a plane (service/vision/estimate/gradients.py, plane_match.py,
edge_agreement.py, model/edge_points.py): orientations of known edges, scores against brute force, edge
points on the model's edges, and copies found at their rendered placements.

Scenes: tests/scenes.py's L-shaped block resting on a plane seen 40 deg from straight down, rendered by
the project's rasteriser at 640 x 480.
"""

from __future__ import annotations

import numba
import numpy as np
import pytest

from service.vision.estimate.edge_agreement import (
    COVERAGE_RADIUS_PX,
    FAINT_MAG_THRESHOLD,
    agreeing_bits,
    coverage_weights,
    edge_agreement,
    share_agreeing,
)
from service.vision.estimate.evidence import colour_frame
from service.vision.estimate.gradients import (
    N_ORI,
    best_in_window,
    best_on_grid,
    orientation_bits,
    response_maps,
    score_at,
)
from service.vision.estimate.plane import PlaneHypothesis
from service.vision.estimate.plane_match import (
    GradientSearch,
    best_at_each_place,
    gradient_search,
    matches_as_hypotheses,
    polish_on_gradients,
)
from service.vision.geometry.camera import Intrinsics, project
from service.vision.geometry.frames import Pose
from service.vision.model.edge_points import edge_points_at, visible_edges
from service.vision.pipeline.part import crease_edges_of
from tests.scenes import INTR, PLANE, SIZE, resting, scene

# a placement's anchor (the projected centre_obj) is found to within the search grid's half step (8 px
# for a part this large) plus a pixel, and polished to within a pixel
FOUND_PX = 5.0
POLISHED_PX = 1.0
POLISHED_DEG = 2.0
# the model's edges at the true pose agree with a clean render's gradients on most of their length
TRUE_AGREEMENT = 0.8
SHIFTED_AGREEMENT = 0.4  # ... and 12 px away on few
ON_SURFACE_MM = 0.5


@pytest.fixture(scope="module")
def bank(l_block_bank):
    return l_block_bank


def test_a_square_has_the_orientations_of_its_sides():
    img = np.zeros((60, 60), np.uint8)
    img[20:40, 20:40] = 200
    bits = orientation_bits(img)
    # the left and right sides' gradient runs along u (bin 0), the top and bottom's along v (bin N/2)
    assert bits[30, 19] & 1 and bits[30, 40] & 1
    assert bits[19, 30] & (1 << (N_ORI // 2)) and bits[40, 30] & (1 << (N_ORI // 2))
    assert bits[30, 30] == 0 and bits[5, 5] == 0  # flat inside and outside


def test_a_template_scores_as_the_share_of_its_points_that_agree():
    rng = np.random.default_rng(3)
    bits = (1 << rng.integers(0, N_ORI, (48, 64))).astype(np.uint8) * (rng.random((48, 64)) < 0.5)
    t = 4
    rm = response_maps(bits, t, 8)
    dx = rng.integers(-10, 10, 30).astype(np.int32)
    dy = rng.integers(-10, 10, 30).astype(np.int32)
    ori = rng.integers(0, N_ORI, 30).astype(np.int32)
    wt = np.full(30, 1 / 30, np.float32)
    u, v = 30, 22
    # brute force: 1 where the point's bin is set within its t x t neighbourhood, 1/4 where a
    # neighbouring bin is, else 0 (LINE-2D's response)
    expected = 0.0
    for k in range(30):
        pu, pv = u + dx[k], v + dy[k]
        win = bits[max(pv - t // 2, 0):max(pv - t // 2 + t, 0), max(pu - t // 2, 0):max(pu - t // 2 + t, 0)]
        ored = int(np.bitwise_or.reduce(win.ravel())) if win.size else 0
        near = (1 << ((ori[k] + 1) % N_ORI)) | (1 << ((ori[k] - 1) % N_ORI))
        expected += (1.0 if ored >> ori[k] & 1 else 0.25 if ored & near else 0.0) / 30
    assert score_at(rm.lin, rm.pad, t, dx, dy, ori, wt, 30, u, v) == pytest.approx(expected, abs=1e-6)


def test_edge_points_lie_on_the_surface_and_crease_points_on_the_model_edges(bank):
    # the L-block is the union of two axis-aligned boxes: a point on its surface lies in one box with a
    # coordinate on that box's faces (the z-buffer's pixel puts it within about a pixel, ~0.3 mm here), a
    # crease point with two
    boxes = [((-40.0, -10.0, -20.0), (40.0, 10.0, 20.0)), ((-40.0, 10.0, -20.0), (-20.0, 50.0, 20.0))]
    poses = [resting(bank, s, 30.0, 0.0, 0.0) for s in range(len(bank.R_rest_obj))]
    creases = crease_edges_of(bank)
    edges = [edge_points_at(bank.vertices_mm, bank.faces, creases, p, INTR, SIZE) for p in poses]
    assert sum(e.crease.sum() for e in edges) > 10
    for e in edges:
        assert len(e.p_obj) > 50
        faces_on = np.zeros(len(e.p_obj), int)
        for lo, hi in boxes:
            lo, hi = np.array(lo), np.array(hi)
            inside = np.all((e.p_obj > lo - ON_SURFACE_MM) & (e.p_obj < hi + ON_SURFACE_MM), axis=1)
            on = (np.abs(e.p_obj - lo) < ON_SURFACE_MM) | (np.abs(e.p_obj - hi) < ON_SURFACE_MM)
            faces_on = np.maximum(faces_on, np.where(inside, on.sum(axis=1), 0))
        assert (faces_on >= 1).mean() > 0.95
        assert (faces_on[e.crease] >= 2).all()
        np.testing.assert_allclose(np.linalg.norm(e.tangent_obj, axis=1), 1.0, atol=1e-9)


@pytest.mark.parametrize("s, spin, x, y", [(0, 30.0, 0.0, 0.0), (1, 200.0, 60.0, -40.0)])
def test_a_rendered_copy_is_found_at_its_placement_and_polished(bank, s, spin, x, y):
    pose = resting(bank, s, spin, x, y)
    frame = colour_frame(scene(bank, [pose]))
    rest = bank.R_rest_obj
    matches, tpl = gradient_search(bank, crease_edges_of(bank), rest, frame.orientations, INTR, PLANE,
                                   GradientSearch())
    truth_uv = project(pose.apply(bank.centre_obj[None]), INTR.K)[0]
    best = matches[0]
    assert np.linalg.norm(np.array(best.uv) - truth_uv) < FOUND_PX
    assert tpl.family[best.template] == s
    polished = polish_on_gradients(bank, tpl, rest, matches_as_hypotheses(matches[:1], tpl), INTR,
                                   PLANE, frame.agreeing)[0]
    assert np.linalg.norm(polished.uv - truth_uv) < POLISHED_PX
    angle = np.degrees(np.arccos(np.clip((np.trace(polished.R.T @ pose.R) - 1) / 2, -1, 1)))
    assert angle < POLISHED_DEG


def test_edges_agree_at_the_true_pose_and_not_beside_it(bank):
    pose = resting(bank, 0, 30.0, 0.0, 0.0)
    agreeing = agreeing_bits(orientation_bits(scene(bank, [pose])))
    creases = crease_edges_of(bank)
    at = edge_agreement(bank.vertices_mm, bank.faces, creases, pose, INTR, agreeing)
    beside = edge_agreement(bank.vertices_mm, bank.faces, creases,
                            Pose(pose.R, pose.t_mm + np.array([12.0 * pose.t_mm[2] / INTR.fx, 0.0, 0.0])),
                            INTR, agreeing)
    for k in ("edge_agreement", "inner_agreement", "outline_agreement", "edge_coverage", "outline_coverage"):
        assert at[k] > TRUE_AGREEMENT
    for k in ("edge_agreement", "outline_agreement", "edge_coverage", "outline_coverage"):
        assert beside[k] < SHIFTED_AGREEMENT


def test_coverage_weighs_each_stretch_of_an_orientation_once_however_many_its_points():
    # three stretches of one orientation, of 1, 5 and 50 points within 3 px each, far apart (> 2 radii),
    # and one stretch of another orientation beside the first: each weighs a quarter
    rng = np.random.default_rng(3)
    centres = np.array([[0.0, 0.0], [200.0, 0.0], [0.0, 200.0], [5.0, 0.0]])
    sizes, bins = [1, 5, 50, 7], [2, 2, 2, 6]
    uv = np.concatenate([c + rng.uniform(-1.5, 1.5, (n, 2)) for c, n in zip(centres, sizes, strict=True)])
    ori = np.repeat(bins, sizes)
    w = coverage_weights(uv, ori)
    ends = np.cumsum([0, *sizes])
    np.testing.assert_allclose([w[a:b].sum() for a, b in zip(ends[:-1], ends[1:], strict=True)], 0.25)
    # brute force on random points: 1 / (same-bin points within the radius, itself included)
    uv, ori = rng.uniform(0.0, 120.0, (300, 2)), rng.integers(0, N_ORI, 300)
    d = np.linalg.norm(uv[:, None] - uv[None], axis=2)
    n = ((d <= COVERAGE_RADIUS_PX) & (ori[:, None] == ori[None])).sum(axis=1)
    np.testing.assert_allclose(coverage_weights(uv, ori), (1.0 / n) / (1.0 / n).sum())


def test_a_longer_look_alike_differs_at_an_arm_end_which_coverage_weighs_as_a_stretch_of_side():
    # An L of 6 px wide arms, 200 px along u and 100 px along v, posed on a longer L that has no edge at
    # the long arm's end: that end's normal is the short arm's sides', 6 points among its 200
    h, w = 160, 260
    x0, y0, wid = 20, 130, 6
    pts, ori = [], []
    def side(us, vs, b):
        pts.extend(zip(us, vs, strict=True))
        ori.extend([b] * len(us))
    u = np.arange(x0, x0 + 200.0)
    side(u, np.full(200, y0), 4)  # long arm, its two sides (normal along v: bin 4 of 0..7 over 180 deg)
    side(u, np.full(200, y0 + wid), 4)
    v = np.arange(y0 - 100.0, y0)
    side(np.full(100, x0), v, 0)  # short arm, its two sides (normal along u: bin 0)
    side(np.full(100, x0 + wid), v, 0)
    side(np.full(wid, x0 + 200.0), np.arange(y0, y0 + wid, dtype=float), 0)  # the long arm's end
    side(np.arange(x0, x0 + wid, dtype=float), np.full(wid, y0 - 100.0), 4)  # the short arm's end
    uv, ori = np.array(pts, float), np.array(ori)
    agreeing = np.zeros((h, w), np.uint8)
    iu, iv = uv[:, 0].astype(int), uv[:, 1].astype(int)
    np.bitwise_or.at(agreeing, (iv, iu), (1 << ori).astype(np.uint8))  # every point agrees ...
    agreeing[y0:y0 + wid, x0 + 200] = 0  # ... but at the end: the look-alike's arm goes on
    by_orientation, by_extent = share_agreeing(uv, ori, agreeing), share_agreeing(uv, ori, agreeing,
                                                                                  coverage_weights)
    assert by_orientation == pytest.approx(1.0 - 0.5 * 6 / 206)
    assert by_extent < by_orientation - 0.1


def test_a_faint_edge_agrees_on_a_quiet_table_and_not_in_grain():
    # A vertical step of 8 grey levels, under the search's magnitude and over the faint one; its lower
    # half crosses horizontal grain of the same depth (8 levels, 8 px period) whose gradients are faint
    # too, and dense: there the step's orientation is not added, on the plain upper half it is.
    img = np.full((120, 160), 120.0)
    img[:, 80:] += 8.0
    img[60:] += 8.0 * np.sin(2 * np.pi * np.arange(60, 120) / 8.0)[:, None]
    bgr = np.repeat(img.astype(np.uint8)[..., None], 3, axis=2)
    bits, faint = orientation_bits(bgr), orientation_bits(bgr, mag_threshold=FAINT_MAG_THRESHOLD)
    plain, read = agreeing_bits(bits), agreeing_bits(bits, faint)
    step = 1  # bin 0: the gradient along +u
    assert not (plain[10:50, 79:81] & step).any()  # the search's magnitude misses the step
    assert (read[10:50, 79:81] & step).all()  # on the quiet half it agrees
    assert np.mean(faint[75:105] > 0) > 0.5  # the grain is dense with faint gradients ...
    np.testing.assert_array_equal(read[75:105], plain[75:105])  # ... and none of them is added


def test_a_frame_reads_both_magnitudes_off_one_gradient_as_if_apart(bank):
    img = scene(bank, [resting(bank, 0, 30.0, 0.0, 0.0)])
    frame = colour_frame(img)
    bits = orientation_bits(img)
    np.testing.assert_array_equal(frame.orientations, bits)
    np.testing.assert_array_equal(
        frame.agreeing, agreeing_bits(bits, orientation_bits(img, mag_threshold=FAINT_MAG_THRESHOLD)))


def test_the_best_in_a_window_is_the_brute_force_best_over_its_cells():
    rng = np.random.default_rng(5)
    bits = (1 << rng.integers(0, N_ORI, (48, 64))).astype(np.uint8) * (rng.random((48, 64)) < 0.4)
    t = 4
    rm = response_maps(bits, t, 8)
    M, P = 5, 20
    dx = rng.integers(-12, 12, (M, P)).astype(np.int32)
    dy = rng.integers(-12, 12, (M, P)).astype(np.int32)
    ori = rng.integers(0, N_ORI, (M, P)).astype(np.int32)
    wt = np.full((M, P), 1 / P, np.float32)
    n_pts = np.array([20, 15, 20, 8, 20], np.int32)
    ids = np.array([4, 1, 3], np.int64)
    scores, at = best_in_window(rm.lin, rm.pad, t, dx, dy, ori, wt, n_pts, ids, 2, 3, 9, 8)
    for k, m in enumerate(ids):
        n = int(n_pts[m])
        brute = {(gx, gy): score_at(rm.lin, rm.pad, t, dx[m], dy[m], ori[m], wt[m], n, gx * t, gy * t)
                 for gx in range(2, 9) for gy in range(3, 8)}
        assert scores[k] == pytest.approx(max(brute.values()), abs=1e-5)
        assert brute[tuple(at[k])] == pytest.approx(scores[k], abs=1e-5)


def _random_templates(rng, M, P):
    dx = rng.integers(-12, 12, (M, P)).astype(np.int32)
    dy = rng.integers(-12, 12, (M, P)).astype(np.int32)
    # coarse orientations and equal weights: many templates tie at a cell, where the first must win
    ori = rng.integers(0, 2, (M, P)).astype(np.int32)
    wt = np.full((M, P), 1 / P, np.float32)
    return dx, dy, ori, wt, rng.integers(4, P + 1, M).astype(np.int32)


@pytest.mark.parametrize("n_threads", [1, 2])
def test_the_grid_keeps_each_cells_brute_force_best_template_the_first_on_a_tie(n_threads):
    rng = np.random.default_rng(8)
    bits = (1 << rng.integers(0, 2, (48, 64))).astype(np.uint8) * (rng.random((48, 64)) < 0.5)
    t = 4
    rm = response_maps(bits, t, 8)
    gh, gw = rm.grid_shape
    M, P = 40, 12
    dx, dy, ori, wt, n_pts = _random_templates(rng, M, P)
    g0, h0 = rng.integers(0, gw // 2, M), rng.integers(0, gh // 2, M)
    cells = np.stack([g0, h0, g0 + rng.integers(1, gw // 2, M), h0 + rng.integers(1, gh // 2, M)], 1)
    cells = cells.astype(np.int64)
    best, best_m = np.full((gh, gw), -1.0, np.float32), np.full((gh, gw), -1, np.int64)
    numba.set_num_threads(n_threads)
    try:
        best_on_grid(rm.lin, rm.pad, t, dx, dy, ori, wt, n_pts, cells, best, best_m)
    finally:
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    for gy in range(gh):
        for gx in range(gw):
            here = [m for m in range(M)
                    if cells[m, 0] <= gx < cells[m, 2] and cells[m, 1] <= gy < cells[m, 3]]
            s = [score_at(rm.lin, rm.pad, t, dx[m], dy[m], ori[m], wt[m], int(n_pts[m]), gx * t, gy * t)
                 for m in here]
            if not here:
                assert best_m[gy, gx] == -1
                continue
            top = max(s)
            first = here[int(np.flatnonzero(np.isclose(s, top, atol=1e-6))[0])]
            assert best[gy, gx] == pytest.approx(top, abs=1e-5) and best_m[gy, gx] == first


def test_a_window_reads_the_same_best_templates_on_one_thread_as_on_two():
    rng = np.random.default_rng(9)
    bits = (1 << rng.integers(0, N_ORI, (48, 64))).astype(np.uint8) * (rng.random((48, 64)) < 0.4)
    t = 4
    rm = response_maps(bits, t, 8)
    dx, dy, ori, wt, n_pts = _random_templates(rng, 30, 12)
    ids = rng.permutation(30)[:25].astype(np.int64)
    assert numba.config.NUMBA_NUM_THREADS >= 2, "the machine has a second core to split over"
    read = []
    for n in (1, 2):
        numba.set_num_threads(n)
        try:
            read.append(best_in_window(rm.lin, rm.pad, t, dx, dy, ori, wt, n_pts, ids, 1, 2, 10, 9))
        finally:
            numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    np.testing.assert_array_equal(read[0][0], read[1][0])
    np.testing.assert_array_equal(read[0][1], read[1][1])


# Family 2 spun 90 deg shows, from this camera, the outline of family 3 at the same place: the grid
# scores family 3 best there, and only the edges inside the outline tell them apart.
AMBIGUOUS = (2, 90.0)


def test_a_rotation_sharing_the_outline_is_proposed_at_its_place_and_polished_first(bank):
    pose = resting(bank, *AMBIGUOUS, 0.0, 0.0)
    frame = colour_frame(scene(bank, [pose]))
    rest = bank.R_rest_obj
    truth_uv = project(pose.apply(bank.centre_obj[None]), INTR.K)[0]
    creases = crease_edges_of(bank)

    def right(s, uv):
        return s == AMBIGUOUS[0] and np.linalg.norm(np.asarray(uv) - truth_uv) < FOUND_PX

    alone, tpl = gradient_search(bank, creases, rest, frame.orientations, INTR, PLANE,
                                 GradientSearch(rivals=0))
    assert not any(right(tpl.family[x.template], x.uv) for x in alone)  # the scene is ambiguous
    settings = GradientSearch()
    assert settings.rivals
    matches, tpl = gradient_search(bank, creases, rest, frame.orientations, INTR, PLANE, settings)
    first = [x for x in matches if x.place == 0]
    assert len(first) > 1 and any(right(tpl.family[x.template], x.uv) for x in first[1:])
    polished = polish_on_gradients(bank, tpl, rest, matches_as_hypotheses(matches, tpl), INTR, PLANE,
                                   frame.agreeing)
    best = best_at_each_place(polished, [x.place for x in matches], settings.rival_margin)[0]
    assert best.s == AMBIGUOUS[0] and np.linalg.norm(best.uv - truth_uv) < POLISHED_PX


def _hypothesis(score: float) -> PlaneHypothesis:
    return PlaneHypothesis(0, 0.0, np.zeros(2), np.eye(3), np.zeros(3), score=score)


def test_each_place_comes_best_first_without_those_far_below_its_best():
    hs = [_hypothesis(s) for s in (0.7, 0.9, 0.5, 0.88, 0.6, 0.2)]
    places = [0, 0, 1, 0, 1, 2]
    out = best_at_each_place(hs, places, 0.05)
    assert [h.score for h in out] == [0.9, 0.88, 0.6, 0.2]


def test_visible_edges_move_with_the_image_round_them(bank):
    # the edges are read in a window round the part: the same view in an image 100 px larger each side
    # (the principal point moved with it) shows the same edges, 100 px further right and down
    pose = resting(bank, 1, 200.0, 60.0, -40.0)
    creases = crease_edges_of(bank)
    a = visible_edges(bank.vertices_mm, bank.faces, creases, pose, INTR, SIZE)
    big = Intrinsics(INTR.fx, INTR.fy, INTR.cx + 100, INTR.cy + 100)
    b = visible_edges(bank.vertices_mm, bank.faces, creases, pose, big, (SIZE[0] + 200, SIZE[1] + 200))
    assert len(a.uv) > 100
    np.testing.assert_allclose(b.uv - 100, a.uv, atol=1e-9)
    np.testing.assert_allclose(b.p_cam, a.p_cam, atol=1e-6)
    np.testing.assert_array_equal(b.crease, a.crease)
    np.testing.assert_array_equal(b.outline, a.outline)
