"""The anytime search (issue 19): ``deadline_ms`` bounds an estimate and the answer says when it did.

No wall-clock limits: a deadline that has passed before the search starts, a clock the test drives,
and a deadline so far away it never matters give answers known without timing anything.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import trimesh

from service.vision import pipeline
from service.vision.deadline import Deadline, RunningMean
from service.vision.estimate import level_a
from service.vision.estimate.chamfer import distance_tensor, pooled_distance_tensor
from service.vision.estimate.edges import detect_segments, to_grey_u8
from service.vision.estimate.evidence import colour_frame
from service.vision.estimate.search import depth_scales
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, Rx, Ry
from service.vision.geometry.render import render_shaded
from service.vision.pipeline import timing

with warnings.catch_warnings():  # starlette would like httpx2; the test extra installs httpx
    warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient`")
    from fastapi.testclient import TestClient

INTR = Intrinsics(600.0, 600.0, 319.5, 239.5)
SIZE = (640, 480)
TRUTH = Pose(Rx(40.0) @ Ry(25.0), np.array([30.0, -20.0, 450.0]))
PAST = 1e-6  # ms: gone before the edges are detected
NEVER = 1e9  # ms: 11 days


class TickingClock:
    """Advances ``tick_s`` every time it is read."""

    def __init__(self, tick_s: float):
        self.now, self.tick_s = 0.0, tick_s

    def __call__(self) -> float:
        self.now += self.tick_s
        return self.now


@pytest.fixture(scope="module")
def bank():
    mesh = trimesh.creation.box((80.0, 40.0, 20.0))
    return pipeline.build_templates(mesh, symmetry="none", grid={"view_step_deg": 20.0, "render_px": 128})


@pytest.fixture(scope="module")
def image(bank):
    grey = render_shaded(bank.vertices_mm, bank.faces, TRUTH, INTR.K, SIZE, background=60)
    return np.repeat(grey[..., None], 3, axis=2)


def test_deadline_counts_down_on_its_clock():
    clock = TickingClock(0.010)  # 10 ms per reading
    d = Deadline(25.0, clock=clock)  # start = 0.010
    assert d.left_ms() == pytest.approx(15.0)  # read at 0.020
    assert d.allows(0.0) and not d.hit  # 0.030: 5 ms left
    assert not d.allows(10.0) and d.hit  # 0.040: -5 ms left
    unbounded = Deadline(None, clock=clock)
    assert unbounded.left_ms() == float("inf") and unbounded.allows(1e12) and not unbounded.hit


def test_allows_next_budgets_the_last_unit_again():
    clock = TickingClock(0.010)
    d = Deadline(100.0, clock=clock)  # start 0.010, deadline 0.110
    d.checked()  # past the frame's first check, which every loop's first unit would otherwise be owed
    assert d.allows_next(0.0)  # first unit: no duration known yet (read 0.020, left read 0.030: 80 ms)
    # next call reads 0.040: the unit took 20 ms, 60 ms left at 0.050 >= 20 + 30 reserve
    assert d.allows_next(30.0)
    # reads 0.060 (unit 20 ms) and 0.070: 40 ms left < 20 + 30
    assert not d.allows_next(30.0) and d.hit


def test_until_the_first_check_every_loop_takes_its_first_unit():
    d = Deadline(PAST, clock=TickingClock(0.010))
    assert d.allows_next(1e9) and not d.hit  # the search's first unit, long past the deadline
    assert not d.allows_next(0.0) and d.hit  # its second is refused
    d.new_loop()
    assert d.allows_next(0.0) and d.allows_first(1e9)  # the next stage's first unit, the first check
    d.checked()
    d.new_loop()
    assert not d.allows_next(0.0) and not d.allows_first(0.0)


def test_a_passed_deadline_still_checks_the_best_proposal(bank, image):
    """A deadline bounds the search; it never refuses the first check: gone before the edges, the frame
    still gets its edges, each search stage's first unit and one checked proposal, the truth here."""
    free = pipeline.estimate(bank, image, INTR, distance_range_mm=(300.0, 700.0))
    out = pipeline.estimate(bank, image, INTR, distance_range_mm=(300.0, 700.0), deadline_ms=PAST)
    assert out.deadline_reached is True and out.deadline_stopped_in == "search"
    assert out.candidates and out.candidates_checked == 1
    assert out.found is True and out.verdict.reason == "found"
    np.testing.assert_allclose(out.refined.pose.t_mm, free.refined.pose.t_mm, atol=1.0)
    assert free.deadline_stopped_in is None and free.candidates_checked >= 1


def test_a_timing_model_fed_one_minute_long_sample_recovers():
    """One kernel compile or a stalled machine (a 60 s check) counts for at most MAX_SAMPLE_RATIO means:
    ordinary samples bring the mean back, so no deadline is locked into refusing."""
    m = RunningMean(35.0)
    m.add(60_000.0)
    assert m.value == pytest.approx(35.0 + m.alpha * (m.MAX_SAMPLE_RATIO * 35.0 - 35.0))
    for _ in range(30):
        m.add(30.0)
    assert m.value == pytest.approx(30.0, abs=0.1) and m.high < 35.0


def test_the_warm_up_teaches_no_timing_model():
    from service.vision.deadline import timing_paused

    m = RunningMean(35.0)
    with timing_paused():
        m.add(5_000.0)
    assert (m.value, m.spread) == (35.0, 0.25 * 35.0)
    m.add(45.0)  # outside the block it learns again
    assert m.value == pytest.approx(37.0)


def test_a_deadline_that_never_comes_changes_nothing(bank, image):
    free = pipeline.estimate(bank, image, INTR, distance_range_mm=(300.0, 700.0))
    bounded = pipeline.estimate(bank, image, INTR, distance_range_mm=(300.0, 700.0), deadline_ms=NEVER)
    assert free.found and bounded.found and not bounded.deadline_reached
    assert bounded.verdict.reason == "found"
    np.testing.assert_array_equal(bounded.refined.pose.R, free.refined.pose.R)
    np.testing.assert_array_equal(bounded.refined.pose.t_mm, free.refined.pose.t_mm)
    assert [c.cost for c in bounded.candidates] == [c.cost for c in free.candidates]


def test_level_a_scans_the_anchors_with_most_edges_first(bank, image):
    grey = to_grey_u8(image)
    p = pipeline.DEFAULT_POLICY.search_params
    dtt_a = pooled_distance_tensor(distance_tensor(detect_segments(grey), n_channels=p.n_channels,
                                                   scale=p.fine_scale), p.level_scale)
    z_ref, scales = depth_scales((300.0, 700.0), p.depth_step)
    tpl = level_a.level_a_templates(bank, INTR, grey.shape, p, distance_mm=None, z_ref_mm=z_ref)
    full = level_a.scan_level_a(dtt_a, tpl, scales, grey.shape, p)
    # Chunked and run to the end: every anchor's result is the unchunked scan's.
    whole = level_a.scan_level_a(dtt_a, tpl, scales, grey.shape, p, deadline=Deadline(NEVER))
    for a, b in zip(full, whole, strict=True):
        np.testing.assert_array_equal(a, b)
    # A clock that ticks 10 ms per reading and a 45 ms budget: the first chunk is scanned, then the
    # next would not fit (allows_next reads the clock twice per chunk).
    part = level_a.scan_level_a(dtt_a, tpl, scales, grey.shape, p,
                               deadline=Deadline(45.0, clock=TickingClock(0.010)))
    np.testing.assert_array_equal(part[0], full[0])
    # The chunks, recounted here: whole blocks of anchors, ordered by the most edge pixels round one of
    # their anchors, most first.
    edges = (dtt_a.dt.min(axis=0) < level_a.EDGE_PIXEL_DT_PX).astype(np.int32)
    r = max(int(tpl.extent_px * float(scales.min()) * level_a.EDGE_COUNT_EXTENT), 1)
    counts = np.array([edges[max(v - r, 0):v + r + 1, max(u - r, 0):u + r + 1].sum()
                       for u, v in zip(part[0], part[1], strict=True)])
    chunks = level_a._block_chunks(part[0], part[1], part[2], counts, p.anchor_stride)
    assert len(chunks) > 1 and len(chunks[0]) >= level_a.LEVEL_A_CHUNK_ANCHORS
    assert counts[chunks[0]].max() == counts.max()
    first = chunks[0]
    rest = np.concatenate(chunks[1:])
    np.testing.assert_array_equal(part[3][first], full[3][first])
    np.testing.assert_array_equal(part[4][first], full[4][first])
    assert np.all(np.isinf(part[3][rest])) and np.all(part[4][rest] == -1)
    assert len(rest) > 0  # the cut-off left anchors unscanned


def test_api_deadline_option(tmp_path, sprayer_bytes, frame):
    from service.main import create_app
    from service.settings import Settings
    from tests.api_helpers import wait_built

    image_bytes, camera = frame
    settings = Settings(cache_dir=tmp_path, template_grid={"tilt_step_deg": 15, "view_step_deg": 45})
    with TestClient(create_app(settings)) as c:
        mid = c.post("/models", files={"file": ("sprayer.stl", sprayer_bytes)}).json()["id"]
        assert wait_built(c, mid)["status"] == "ready"

        def post(options):
            return c.post(f"/models/{mid}/estimate", files={"image": ("image", image_bytes)},
                          data={"camera": json.dumps(camera), "options": json.dumps(options)})

        r = post({"distance_mm": 500, "deadline_ms": PAST})
        assert r.status_code == 200, r.text
        res = r.json()  # past before it started: still the best proposal checked, and found
        assert res["found"] is True and res["deadline_reached"] is True
        assert res["candidates_checked"] == 1 and res["deadline_stopped_in"] == "search"
        r = post({"distance_mm": 500, "deadline_ms": 600_000})  # the largest accepted: 10 min
        assert r.status_code == 200 and r.json()["found"] is True and r.json()["deadline_reached"] is False
        assert r.json()["deadline_stopped_in"] is None and r.json()["candidates_checked"] >= 1
        for bad in (0, -5, 1e7):
            r = post({"distance_mm": 500, "deadline_ms": bad})
            assert r.status_code == 422, (bad, r.text)
            assert "deadline_ms" in r.text


def test_service_default_deadline_applies(tmp_path, sprayer_bytes, frame, monkeypatch):
    from service.main import create_app
    from service.settings import Settings
    from tests.api_helpers import wait_built

    image_bytes, camera = frame
    grid = {"tilt_step_deg": 15, "view_step_deg": 45}
    assert Settings(cache_dir=tmp_path).deadline_ms == 0  # none unless one is asked for
    monkeypatch.setenv("POSE_DEADLINE_MS", str(PAST))
    settings = Settings(cache_dir=tmp_path, template_grid=grid)
    assert settings.deadline_ms == PAST
    with TestClient(create_app(settings)) as c:
        mid = c.post("/models", files={"file": ("sprayer.stl", sprayer_bytes)}).json()["id"]
        assert wait_built(c, mid)["status"] == "ready"
        r = c.post(f"/models/{mid}/estimate", files={"image": ("image", image_bytes)},
                   data={"camera": json.dumps(camera), "options": json.dumps({"distance_mm": 500})})
        assert r.status_code == 200 and r.json()["deadline_reached"] is True
        assert r.json()["candidates_checked"] == 1


def test_running_mean_and_its_high_estimate_by_hand():
    m = RunningMean(40.0, alpha=0.5)  # spread starts at 10
    assert m.high == pytest.approx(40.0 + 2 * 10.0)
    m.add(60.0)  # deviation 20: spread 10 + 0.5 * (20 - 10) = 15; mean 50
    assert (m.value, m.spread) == pytest.approx((50.0, 15.0))
    m.add(50.0)  # deviation 0: spread 7.5; mean stays 50
    assert (m.value, m.spread) == pytest.approx((50.0, 7.5))
    assert m.high == pytest.approx(50.0 + m.HIGH_SPREADS * 7.5)


def test_a_check_after_the_first_starts_only_when_the_deadline_leaves_its_high_estimate(bank, image,
                                                                                      monkeypatch):
    # Checks took 10 ms on average but spread 20 ms: a deadline leaving 30 ms (more than the mean, less
    # than the high estimate 10 + 2 x 20) starts no check but the first.
    def checks_took_10_ms_spread_20():  # afresh before each frame: a check made teaches the mean
        check = RunningMean(10.0)
        check.spread = 20.0
        monkeypatch.setattr(timing, "CHECK_MS", check)

    grey = to_grey_u8(image)
    cands, _, _ = pipeline.propose(bank, grey, INTR, distance_range_mm=(300.0, 700.0))
    assert cands
    frame = colour_frame(image)
    kw = dict(distance_mm=None, distance_range_mm=(300.0, 700.0), min_score=None,
              n_channels=pipeline.DEFAULT_POLICY.search_params.n_channels)
    checks_took_10_ms_spread_20()
    first = Deadline(30.0, clock=lambda: 0.0)
    assert len(pipeline.verify_candidates(bank, cands, grey, frame, INTR, deadline=first, **kw)) == 1
    assert first.checks >= 1
    checks_took_10_ms_spread_20()
    tight = Deadline(30.0, clock=lambda: 0.0)
    tight.checked()  # this frame's first check is made
    assert pipeline.verify_candidates(bank, cands, grey, frame, INTR, deadline=tight, **kw) == []
    assert tight.hit and tight.stopped_in == "edges"
    checks_took_10_ms_spread_20()
    roomy = Deadline(50.0, clock=lambda: 0.0)
    roomy.checked()
    assert len(pipeline.verify_candidates(bank, cands, grey, frame, INTR, deadline=roomy, **kw)) >= 1
