"""The supporting plane (service/vision/estimate/plane.py and its use in the pipeline): placements that
rest on it by construction, the off_plane verdict, sort by height, and rendered copies resting on it.

Scenes: an L-shaped block (no symmetry) resting on a plane 450 mm along the optical axis of a camera
looking down 40 deg from straight down, rendered with the project's rasteriser at 640 x 480.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from service.vision import pipeline
from service.vision.estimate.evidence import colour_frame
from service.vision.estimate.plane import _poses
from service.vision.estimate.refine import refine_pose
from service.vision.estimate.verdict import decide
from service.vision.geometry.camera import Intrinsics, project
from service.vision.geometry.frames import Pose, rotation_angle_deg
from service.vision.geometry.plane import (
    Plane,
    R_cam_rest,
    centre_height_mm,
    depths_in_view_mm,
    rest_gap_mm,
    rest_heights_mm,
)
from service.vision.pipeline import (
    DEFAULT_DISTANCE_RANGE_MM,
    DEFAULT_POLICY,
    Checked,
    PoseCandidate,
    RefinedPose,
    sort_instances,
)
from service.vision.pipeline.estimate import plane_range
from service.vision.pipeline.instances import paint_depth
from tests.scenes import (
    AXIS_DIST_MM,
    INTR,
    PLANE,
    SIZE,
    TILT_DEG,
    resting,
    scene,
    visible_fraction,
)
from tests.tolerances import (
    PLANE_FOUND_T_MM,
    PLANE_REST_TOL_MM,
    REFINE_ANGLE_DEG,
    REFINE_TRANS_MM,
    ROUND_TRIP_ATOL,
)


@pytest.fixture(scope="module")
def bank(l_block_bank):
    return l_block_bank


def test_the_test_plane_is_in_the_conventions():
    # the normal points towards the camera (at the origin), d < 0, and the axis' foot point is on it
    assert PLANE.d_mm == pytest.approx(-AXIS_DIST_MM * np.cos(np.radians(TILT_DEG)))
    assert PLANE.height_mm(np.array([[0.0, 0.0, AXIS_DIST_MM]]))[0] == pytest.approx(0.0, abs=1e-9)
    Rc = R_cam_rest(PLANE)
    np.testing.assert_allclose(Rc.T @ Rc, np.eye(3), atol=ROUND_TRIP_ATOL)
    np.testing.assert_allclose(Rc[:, 2], PLANE.normal, atol=ROUND_TRIP_ATOL)


def test_every_placement_of_the_search_rests_on_the_plane_with_its_centre_at_the_pixel(bank):
    rng = np.random.default_rng(15)
    S = len(bank.R_rest_obj)
    s = rng.integers(0, S, 20)
    psi = rng.uniform(0, 360, 20)
    uv = rng.uniform([100, 150], [540, 460], (20, 2))
    R, t, ok = _poses(bank, bank.R_rest_obj, PLANE, INTR, s, psi, uv)
    assert ok.all()
    for k in range(20):
        pose = Pose(R[k], t[k])
        assert rest_gap_mm(bank, pose, PLANE) == pytest.approx(0.0, abs=PLANE_REST_TOL_MM)
        np.testing.assert_allclose(project(pose.apply(bank.centre_obj[None]), INTR.K)[0], uv[k], atol=1e-6)
        h = rest_heights_mm(bank, bank.R_rest_obj)[s[k]]
        assert centre_height_mm(bank, pose, PLANE) == pytest.approx(h, abs=PLANE_REST_TOL_MM)


def test_the_verdict_rejects_a_pose_off_the_plane():
    ev = {"edge_support": 1.0, "unexplained": 0.0, "colour_edge": 1.0, "polarity": 1.0, "region": 1.0,
          "region_low": 1.0, "region_global": 1.0, "coherence": 1.0, "shading_r2": 1.0, "shading_std": 10.0,
          "generic": 0.8}
    assert decide(ev).found
    assert decide(ev, plane_gap_mm=4.0, plane_tolerance_mm=5.0).found
    for gap in (50.0, -10.0):  # floating, or through the surface
        v = decide(ev, plane_gap_mm=gap, plane_tolerance_mm=5.0)
        assert not v.found and v.reason == "off_plane" and v.evidence["plane_gap_mm"] == gap


def test_the_plane_rejects_a_part_floating_50_mm_above_it(bank):
    floating = resting(bank, 0, 30.0, 0.0, 0.0, lift_mm=50.0)
    img = scene(bank, [floating])
    grey = img[..., 0]
    frame = colour_frame(img)
    cand = PoseCandidate(floating, 0.0, 1.0)
    kw = dict(distance_mm=None, distance_range_mm=(300.0, 1200.0), min_score=None, n_channels=16)
    free = pipeline.check_candidate(bank, cand, grey, frame, INTR, **kw)
    assert free.verdict.found  # the image supports it ...
    on = pipeline.check_candidate(bank, cand, grey, frame, INTR, plane=PLANE, plane_tolerance_mm=5.0, **kw)
    assert not on.verdict.found and on.verdict.reason == "off_plane"  # ... but it does not rest on the plane
    assert on.verdict.evidence["plane_gap_mm"] == pytest.approx(50.0, abs=5.0)


def test_sort_height_puts_the_highest_centre_first(bank):
    # family heights differ (the L-block lying flat vs on its side); sorted highest centre first
    h = rest_heights_mm(bank, bank.R_rest_obj)
    order = np.argsort(-h)
    assert h[order[0]] > h[order[-1]] + 5.0
    families = [int(order[-1]), int(order[0]), int(order[len(order) // 2])]  # lowest, highest, between
    checked = []
    for k, s in enumerate(families):
        pose = resting(bank, s, 10.0 * k, 60.0 * k - 60.0, 0.0)
        c = PoseCandidate(pose, 1.0, 1.0)
        checked.append(Checked(c, RefinedPose(pose, 1.0, 1.0), decide(None)))
    got = sort_instances(checked, bank, "height", PLANE)
    assert [c.refined.pose for c in got] == [checked[1].refined.pose, checked[2].refined.pose,
                                             checked[0].refined.pose]
    assert [centre_height_mm(bank, c.refined.pose, PLANE) for c in got] == pytest.approx(
        sorted(h[families], reverse=True), abs=PLANE_REST_TOL_MM)
    with pytest.raises(ValueError, match="needs a plane"):
        sort_instances(checked, bank, "height")


@pytest.mark.slow
@pytest.mark.parametrize("n", [2, 4])
def test_copies_resting_on_the_plane_come_back_as_that_many_instances(bank, n):
    spots = [(-70.0, -40.0), (60.0, -30.0), (-40.0, 60.0), (70.0, 70.0)]
    truth = [resting(bank, k % len(bank.R_rest_obj), 40.0 * k + 15.0, *spots[k]) for k in range(n)]
    out = pipeline.estimate(bank, scene(bank, truth), INTR, max_instances=n, plane=PLANE, sort="height")
    assert len(out.instances) == n
    matched = []
    for inst in out.instances:
        d = [np.linalg.norm(inst.refined.pose.t_mm - p.t_mm) for p in truth]
        assert min(d) <= PLANE_FOUND_T_MM, d
        assert abs(inst.verdict.evidence["plane_gap_mm"]) <= 5.0
        matched.append(int(np.argmin(d)))
    assert sorted(matched) == list(range(n))
    heights = [centre_height_mm(bank, i.refined.pose, PLANE) for i in out.instances]
    assert heights == sorted(heights, reverse=True)


def test_coverage_order_looks_at_every_family_at_the_coarsest_spins_first():
    from service.vision.estimate.plane import coverage_order

    family = np.repeat([0, 1, 2], 36)  # 3 families x 36 spins of 10 deg, spins in order within each
    spin_deg = np.tile(np.arange(36) * 10.0, 3)
    order = coverage_order(family, 3)
    assert sorted(order.tolist()) == list(range(len(family)))  # a permutation
    first = order[:6]  # two spins of each family: 0 and 180 deg
    assert sorted(family[first].tolist()) == [0, 0, 1, 1, 2, 2]
    assert set(spin_deg[first].tolist()) == {0.0, 180.0}
    first = order[:12]  # four of each: every 90 deg
    assert set(spin_deg[first].tolist()) == {0.0, 90.0, 180.0, 270.0}
    assert np.bincount(family[first]).tolist() == [4, 4, 4]


def test_the_plane_search_is_anytime(bank):
    truth = [resting(bank, 0, 25.0, 10.0, -20.0)]
    img = scene(bank, truth)
    free = pipeline.estimate(bank, img, INTR, plane=PLANE)
    bounded = pipeline.estimate(bank, img, INTR, plane=PLANE, deadline_ms=1e9)  # never comes
    assert free.found and bounded.found and not bounded.deadline_reached
    np.testing.assert_array_equal(bounded.refined.pose.t_mm, free.refined.pose.t_mm)
    gone = pipeline.estimate(bank, img, INTR, plane=PLANE, deadline_ms=1e-6)  # passed before the search
    # a deadline never refuses the first check: the search's first units, its best proposal checked
    assert gone.deadline_reached and gone.deadline_stopped_in == "search" and gone.candidates_checked == 1
    assert gone.candidates


@pytest.mark.slow
def test_a_copy_40_percent_hidden_behind_another_is_found(bank):
    # The tallest resting family in front, 46 mm nearer the camera, hides 42 % of a flat copy behind it.
    # Alone, neither passes: the front one's outside band holds the back one's pixels, the back one's
    # inside the front one's; judged with each other explaining those pixels both are found.
    tall = int(np.argmax(rest_heights_mm(bank, bank.R_rest_obj)))
    truth = [resting(bank, tall, 0.0, 0.0, -15.0), resting(bank, 0, 30.0, 0.0, 31.0)]
    assert 0.55 <= visible_fraction(bank, truth, 1) <= 0.6 and visible_fraction(bank, truth, 0) >= 0.95
    out = pipeline.estimate(bank, scene(bank, truth), INTR, max_instances=2, plane=PLANE)
    assert len(out.instances) == 2
    d = [[np.linalg.norm(i.refined.pose.t_mm - p.t_mm) for p in truth] for i in out.instances]
    assert sorted(int(np.argmin(x)) for x in d) == [0, 1]
    assert max(min(x) for x in d) <= PLANE_FOUND_T_MM


def test_a_found_neighbour_explains_its_pixels_in_the_evidence(bank):
    from service.vision.estimate.evidence import evidence

    tall = int(np.argmax(rest_heights_mm(bank, bank.R_rest_obj)))
    front, back = resting(bank, tall, 0.0, 0.0, -15.0), resting(bank, 0, 30.0, 0.0, 40.0)
    alone = evidence(bank, front, INTR, colour_frame(scene(bank, [front])))
    pair = colour_frame(scene(bank, [front, back]))
    back_depth = np.full((SIZE[1], SIZE[0]), np.inf, np.float32)
    paint_depth(back_depth, bank, back, INTR)
    among = evidence(bank, front, INTR, pair)
    explained = evidence(bank, front, INTR, pair, back_depth)
    # The back copy's pixels in the front one's outside band look like its inside: explained, the
    # band is the plain floor again, as with the front copy alone (up to anti-aliased pixels).
    assert among.region_global < alone.region_global - 0.1
    assert explained.region_global == pytest.approx(alone.region_global, abs=0.03)
    # Where the back copy covers a sliver of the front one it is left out of the shading fit, which then
    # reads the front copy's own pixels only: as alone.
    assert explained.shading_r2 == pytest.approx(alone.shading_r2, abs=0.005)


def test_the_nearest_view_table_agrees_with_a_scan_of_every_view(bank):
    from service.vision.bank import view_dirs_obj
    from service.vision.estimate.plane_scoring import nearest_views

    rng = np.random.default_rng(3)
    dirs = rng.normal(size=(20000, 3))
    z = view_dirs_obj(bank)
    dirs = np.concatenate([dirs, z, -z, np.eye(3), -np.eye(3)])  # the views themselves, the cube's axes
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    np.testing.assert_array_equal(nearest_views(bank, dirs), np.argmax(dirs @ z.T, axis=1))


def test_the_block_floor_is_the_least_over_its_reach_and_the_channels_either_side():
    from service.vision.estimate.chamfer import DistanceTensor
    from service.vision.estimate.plane import block_floor

    rng = np.random.default_rng(8)
    dt_q = rng.integers(0, 40, (12, 14, 6)).astype(np.uint8)
    dtt = DistanceTensor(np.zeros((6, 12, 14), np.float32), 0.125, (0.0, 0.0), 2.0, 0.5)
    got = block_floor(dt_q, dtt, 16.0)  # 16 full-res px = 2 grid px
    for y, x, c in [(0, 0, 0), (5, 7, 3), (11, 13, 5), (6, 0, 2), (3, 9, 1)]:
        win = dt_q[max(y - 2, 0):y + 3, max(x - 2, 0):x + 3][..., [(c - 1) % 6, c, (c + 1) % 6]]
        assert got[y, x, c] == win.min()


@pytest.mark.parametrize("n_ch", [16, 12, 8, 1])
def test_the_channel_by_bisection_is_the_rounded_atan2_modulo_pi(n_ch):
    import math

    from service.vision.estimate.plane_scoring import _bin_edges, _channel

    def rounded(x, y):
        th = math.atan2(y, x)
        return int((th + math.pi if th < 0.0 else th) * n_ch / math.pi + 0.5) % n_ch

    rng = np.random.default_rng(n_ch)
    xy = rng.normal(size=(20000, 2)) * 10.0 ** rng.uniform(-3, 3, (20000, 1))
    axes = [(1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0), (-1.0, -0.0), (1.0, -0.0), (0.0, 0.0)]
    cos_b, sin_b = _bin_edges(n_ch)
    for x, y in [*xy, *axes]:
        assert _channel(x, y, cos_b, sin_b) == rounded(x, y), (x, y)
    # on a channel edge itself (to rounding) either side is the rounded atan2
    for k in range(n_ch):
        for s in (1.0, -1.0):
            got = _channel(s * cos_b[k], s * sin_b[k], cos_b, sin_b)
            assert got in ((k + 1) % n_ch, k), (k, s)


def test_the_compiled_polish_cost_is_coarse_evaluate(bank):
    from service.vision.estimate.chamfer import distance_tensor
    from service.vision.estimate.edges import detect_segments, to_grey_u8
    from service.vision.estimate.level_b import evaluate
    from service.vision.estimate.plane_scoring import evaluate_poses, scoring_poses

    img = scene(bank, [resting(bank, 0, 25.0, 10.0, -20.0), resting(bank, 1, 100.0, -60.0, 30.0)])
    dtt = distance_tensor(detect_segments(to_grey_u8(img)), n_channels=16, scale=0.5)
    rng = np.random.default_rng(4)
    n = 200  # round the copies, and some partly or wholly off the image
    s = rng.integers(0, len(bank.R_rest_obj), n)
    uv = np.column_stack([rng.uniform(-100, SIZE[0] + 100, n), rng.uniform(-100, SIZE[1] + 100, n)])
    R, t, ok = _poses(bank, bank.R_rest_obj, PLANE, INTR, s, rng.uniform(0, 360, n), uv)
    views, R2, t2 = scoring_poses(bank, R[ok], t[ok])
    want = evaluate(bank, views, R2, t2, INTR.K, dtt, 160, 3.0, 8.0)
    got = evaluate_poses(bank, views, R2, t2, INTR, dtt, 160, 3.0, 8.0)
    assert np.isfinite(want[0]).all() and (want[0] < 8.0).any()
    np.testing.assert_allclose(got[0], want[0], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(got[1], want[1])


def test_the_scoring_kernel_picks_the_views_scoring_poses_would(bank):
    from service.vision.estimate.chamfer import distance_tensor, quantised
    from service.vision.estimate.edges import detect_segments, to_grey_u8
    from service.vision.estimate.plane_scoring import _points, _score, score_poses, scoring_poses

    img = scene(bank, [resting(bank, 0, 25.0, 10.0, -20.0)])
    dtt = distance_tensor(detect_segments(to_grey_u8(img)), n_channels=16, scale=0.5)
    dt_q, tau_q = quantised(dtt, dtt.tau_px)
    rng = np.random.default_rng(6)
    n = 3000
    s = rng.integers(0, len(bank.R_rest_obj), n)
    uv = np.column_stack([rng.uniform(0, SIZE[0], n), rng.uniform(0, SIZE[1], n)])
    R, t, ok = _poses(bank, bank.R_rest_obj, PLANE, INTR, s, rng.uniform(0, 360, n), uv)
    R, t = R[ok], t[ok]
    views, R2, t2 = scoring_poses(bank, R, t)
    assert len(np.unique(views)) > 20
    mid, direction = _points(bank, 32)
    none = np.zeros(0, np.int64)
    want = _score(dt_q, tau_q, dtt.scale, dtt.origin_uv[0], dtt.origin_uv[1], INTR.fx, INTR.fy, INTR.cx,
                  INTR.cy, mid, direction, views.astype(np.int64), R2, t2, 16, np.inf, False, none, 0,
                  np.zeros(3), np.zeros((1, 3)), none, none, 1)
    np.testing.assert_array_equal(score_poses(bank, R, t, dt_q, tau_q, dtt, INTR, 32), want)


@pytest.mark.parametrize("spin_deg, slide_mm", [(4.0, 3.0), (-6.0, -4.0)])
def test_a_pose_resting_on_the_plane_is_refined_on_it(bank, spin_deg, slide_mm):
    # spun and slid on the plane from the truth, it is spun and slid back, its lowest point kept on it
    truth = resting(bank, 0, 25.0, 10.0, -20.0)
    start = resting(bank, 0, 25.0 + spin_deg, 10.0 + slide_mm, -20.0 + 0.5 * slide_mm)
    img = scene(bank, [truth])
    r = refine_pose(bank, start, img[..., 0], INTR, normal_cam=PLANE.normal)
    assert r.converged
    assert rotation_angle_deg(r.pose.R, truth.R) <= REFINE_ANGLE_DEG
    assert np.abs(r.pose.t_mm - truth.t_mm).max() <= REFINE_TRANS_MM
    assert rest_gap_mm(bank, r.pose, PLANE) == pytest.approx(0.0, abs=PLANE_REST_TOL_MM)


def test_the_plane_s_depths_in_view_are_where_the_corner_rays_meet_it():
    intr = Intrinsics(600.0, 600.0, 319.5, 239.5)
    n = np.array([0.0, np.sin(np.radians(50.0)), -np.cos(np.radians(50.0))])  # tilted 50 deg
    plane = Plane(n, -400.0)
    near, far = depths_in_view_mm(plane, intr, (640, 480))
    corners = np.array([[-0.5, -0.5], [639.5, -0.5], [639.5, 479.5], [-0.5, 479.5]])
    rays = np.column_stack([(corners - [intr.cx, intr.cy]) / [intr.fx, intr.fy], np.ones(4)])
    depths = plane.d_mm / (rays @ n)  # z of each corner ray's point on the plane (its ray has z = 1)
    assert near == pytest.approx(depths.min()) and far == pytest.approx(depths.max())
    # tilted so far that the horizon is in view: the plane reaches infinitely far
    steep = Plane(np.array([0.0, np.sin(np.radians(80.0)), -np.cos(np.radians(80.0))]), -400.0)
    assert depths_in_view_mm(steep, intr, (640, 480))[1] == math.inf


def test_a_plane_without_a_range_is_searched_to_its_far_end_in_view(l_block_bank):
    intr = Intrinsics(600.0, 600.0, 319.5, 239.5)
    top_down = Plane(np.array([0.0, 0.0, -1.0]), -500.0)
    assert plane_range(l_block_bank, top_down, intr, (640, 480)) == DEFAULT_DISTANCE_RANGE_MM
    oblique = Plane(np.array([0.0, np.sin(np.radians(50.0)), -np.cos(np.radians(50.0))]), -700.0)
    far = depths_in_view_mm(oblique, intr, (640, 480))[1]
    assert far > DEFAULT_DISTANCE_RANGE_MM[1]
    assert plane_range(l_block_bank, oblique, intr, (640, 480)) == (DEFAULT_DISTANCE_RANGE_MM[0], far)
    steep = Plane(np.array([0.0, np.sin(np.radians(80.0)), -np.cos(np.radians(80.0))]), -400.0)
    smallest = intr.fx * l_block_bank.diameter_mm / DEFAULT_POLICY.plane_smallest_part_px
    assert plane_range(l_block_bank, steep, intr, (640, 480))[1] == pytest.approx(smallest)
