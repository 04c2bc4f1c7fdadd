"""Coarse pose known answers: render a mesh at a known pose with the project's rasteriser, estimate
without refinement, compare within named tolerances; blank and unrelated images are not found."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numba
import numpy as np
import pytest

from service.vision import pipeline
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, Rx, Rz, rotation_angle_deg
from service.vision.geometry.render import render, render_shaded
from tests.lens import distort_image
from tests.tolerances import (
    COARSE_AXIS_DEG,
    COARSE_FREE_AXIS_DEG,
    COARSE_FREE_DEPTH_MM,
    COARSE_OCCLUDED_AXIS_DEG,
    COARSE_OCCLUDED_XY_MM,
    COARSE_ROT_DEG_NONSYM,
    COARSE_T_MM_NONSYM,
    COARSE_XY_MM,
)

W, H = 1280, 960
INTR = Intrinsics(1100.0, 1100.0, 643.0, 477.0)


@pytest.fixture(scope="module")
def sprayer_bank(sprayer_mesh):
    return pipeline.build_templates(sprayer_mesh, symmetry="y")


def _noisy(img: np.ndarray, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.clip(img.astype(np.float32) + rng.normal(0, 3.0, img.shape), 0, 255).astype(np.uint8)


def _axis_err_deg(R_a, R_b) -> float:
    return float(np.degrees(np.arccos(np.clip(R_a[:, 1] @ R_b[:, 1], -1, 1))))


KNOWN_MISS = pytest.mark.xfail(reason=(
    "known weakness: with 30 % of the border hidden, level A's peaks are all tilted >20 deg from the "
    "truth and the local scans do not reach it"))


@pytest.mark.parametrize(("alpha", "gamma", "t_mm"), [
    (20.0, 35.0, (40.0, -60.0, 620.0)),  # the view stopped moving after the first polish round: 3.6 deg
    (10.0, -70.0, (0.0, 0.0, 520.0)),
    (-25.0, 100.0, (-60.0, 40.0, 700.0)),
])
def test_sprayer_coarse_pose_distance_estimated(sprayer_bank, alpha, gamma, t_mm):
    truth = Pose(Rx(alpha) @ Rz(gamma), np.array(t_mm))
    img = _noisy(render_shaded(sprayer_bank.vertices_mm, sprayer_bank.faces, truth, INTR.K, (W, H)), 0)
    out = pipeline.estimate(sprayer_bank, img, INTR, refine=False)
    assert out.found
    est = out.coarse.pose
    assert _axis_err_deg(est.R, truth.R) <= COARSE_FREE_AXIS_DEG
    assert np.all(np.abs(est.t_mm[:2] - truth.t_mm[:2]) <= COARSE_XY_MM)
    assert abs(est.t_mm[2] - truth.t_mm[2]) <= COARSE_FREE_DEPTH_MM


@pytest.mark.parametrize(("alpha", "gamma", "t_mm"), [
    (20.0, 35.0, (40.0, -60.0, 500.0)),  # level A prefers a template tilted 30 deg too far here
    (-45.0, -10.0, (-90.0, 30.0, 500.0)),  # partly outside the image; level A picks the mirror tilt
    (60.0, 50.0, (190.0, 120.0, 500.0)),  # near the bottom-right corner: the ray is ~26 deg off axis
])
def test_sprayer_coarse_pose_distance_given(sprayer_bank, alpha, gamma, t_mm):
    truth = Pose(Rx(alpha) @ Rz(gamma), np.array(t_mm))
    img = _noisy(render_shaded(sprayer_bank.vertices_mm, sprayer_bank.faces, truth, INTR.K, (W, H)), 1)
    out = pipeline.estimate(sprayer_bank, img, INTR, distance_mm=t_mm[2], refine=False)
    assert out.found
    est = out.coarse.pose
    assert _axis_err_deg(est.R, truth.R) <= COARSE_AXIS_DEG
    assert np.all(np.abs(est.t_mm[:2] - truth.t_mm[:2]) <= COARSE_XY_MM)
    assert est.t_mm[2] == pytest.approx(t_mm[2])
    # canonical spin: the reported rotation has no spin about the axis (euler ry = 0 for +y)
    assert abs(est.euler_xyz_deg()[1]) < 1e-6


def test_lens_distortion_k1_minus_0_2_coarse_pose(sprayer_bank):
    """The coarse search works on the undistorted segments (the refinement's own use of
    undistort_segments is tested in test_refine.py)."""
    import cv2

    lens = Intrinsics(INTR.fx, INTR.fy, INTR.cx, INTR.cy, (-0.2, 0.0, 0.0, 0.0))
    truth = Pose(Rx(60.0) @ Rz(50.0), np.array([190.0, 120.0, 500.0]))  # near a corner: ~10 px of distortion
    fine = INTR.scaled(2)
    big = render_shaded(sprayer_bank.vertices_mm, sprayer_bank.faces, truth, fine.K, (2 * W, 2 * H))
    big = distort_image(big, Intrinsics(fine.fx, fine.fy, fine.cx, fine.cy, lens.dist))
    img = _noisy(cv2.resize(big, (W, H), interpolation=cv2.INTER_AREA), 7)
    out = pipeline.estimate(sprayer_bank, img, lens, distance_mm=500.0, refine=False)
    assert out.found
    assert _axis_err_deg(out.coarse.pose.R, truth.R) <= COARSE_AXIS_DEG
    assert np.all(np.abs(out.coarse.pose.t_mm[:2] - truth.t_mm[:2]) <= COARSE_XY_MM)
    # Ignoring the lens loses the part (the check above is not vacuous).
    assert not pipeline.estimate(sprayer_bank, img, INTR, distance_mm=500.0, refine=False).found


@KNOWN_MISS
def test_sprayer_coarse_pose_with_30_percent_occluded_synthetic(sprayer_bank):
    truth = Pose(Rx(15.0) @ Rz(-30.0), np.array([-40.0, 20.0, 500.0]))
    img = render_shaded(sprayer_bank.vertices_mm, sprayer_bank.faces, truth, INTR.K, (W, H))
    mask = render(sprayer_bank.vertices_mm, sprayer_bank.faces, truth, INTR.K, (W, H)).mask
    vs, us = np.nonzero(mask)
    # hide the object's top 30 % of rows with background
    cut = np.quantile(vs, 0.30)
    img[: int(cut), us.min() - 5: us.max() + 5] = 70
    out = pipeline.estimate(sprayer_bank, _noisy(img, 2), INTR, distance_mm=500.0, refine=False)
    assert out.found
    assert _axis_err_deg(out.coarse.pose.R, truth.R) <= COARSE_OCCLUDED_AXIS_DEG
    assert np.all(np.abs(out.coarse.pose.t_mm[:2] - truth.t_mm[:2]) <= COARSE_OCCLUDED_XY_MM)


def _paper_case(data_dir, i):
    import json

    import cv2

    g = json.loads((data_dir / "paper" / "gt.jsonl").read_text().splitlines()[i])
    img = cv2.imread(str(data_dir / "paper" / g["image"]), cv2.IMREAD_GRAYSCALE)
    return img, Intrinsics.from_K(np.array(g["K"])), Pose(np.array(g["R"]), np.array(g["t_mm"]))


@pytest.mark.parametrize("i", [0, 3, 9])
def test_paper_render_coarse_pose_distance_given(sprayer_bank, data_dir, i):
    img, intr, truth = _paper_case(data_dir, i)
    out = pipeline.estimate(sprayer_bank, img, intr, distance_mm=500.0, refine=False)
    assert out.found
    assert _axis_err_deg(out.coarse.pose.R, truth.R) <= COARSE_AXIS_DEG
    assert np.all(np.abs(out.coarse.pose.t_mm[:2] - truth.t_mm[:2]) <= COARSE_XY_MM)


@KNOWN_MISS
def test_paper_render_coarse_pose_with_30_percent_occluded(sprayer_bank, data_dir):
    img, intr, truth = _paper_case(data_dir, 1)
    size = (img.shape[1], img.shape[0])
    mask = render(sprayer_bank.vertices_mm, sprayer_bank.faces, truth, intr.K, size).mask
    vs, us = np.nonzero(mask)
    cut = int(np.quantile(vs, 0.30))
    img = img.copy()
    img[:cut, us.min() - 5: us.max() + 5] = int(np.median(img[~mask]))
    out = pipeline.estimate(sprayer_bank, img, intr, distance_mm=500.0, refine=False)
    # The pose is right; the found verdict is not asserted: with 30 % of
    # the border gone the score sits at ~0.6, where one cluttered absent scene also lands.
    best = out.candidates[0]
    assert _axis_err_deg(best.pose.R, truth.R) <= COARSE_OCCLUDED_AXIS_DEG
    assert np.all(np.abs(best.pose.t_mm[:2] - truth.t_mm[:2]) <= COARSE_OCCLUDED_XY_MM)


def test_blank_image_is_not_found(sprayer_bank):
    img = _noisy(np.full((H, W), 90, np.uint8), 3)
    out = pipeline.estimate(sprayer_bank, img, INTR, distance_mm=500.0)
    assert not out.found
    assert out.coarse is None and out.refined is None


def test_unrelated_image_is_not_found(sprayer_bank):
    """Boxes and discs scattered over the image: plenty of edges, none of them a sprayer."""
    import cv2

    rng = np.random.default_rng(4)
    img = np.full((H, W), 80, np.uint8)
    for _ in range(25):
        x, y = int(rng.integers(0, W)), int(rng.integers(0, H))
        if rng.random() < 0.5:
            cv2.rectangle(img, (x, y), (x + int(rng.integers(20, 200)), y + int(rng.integers(20, 200))),
                          int(rng.integers(120, 240)), -1)
        else:
            cv2.circle(img, (x, y), int(rng.integers(10, 90)), int(rng.integers(120, 240)), -1)
    out = pipeline.estimate(sprayer_bank, _noisy(img, 5), INTR, distance_mm=500.0)
    assert not out.found


@pytest.fixture(scope="module")
def tless06_bank(tless06_mesh):
    return pipeline.build_templates(tless06_mesh, symmetry="none")  # the default grid, as users get it


FLIP = pytest.mark.xfail(reason=(
    "known weakness: this near-symmetric part's 180 deg flip has almost the same silhouette; the search "
    "returns the flip (position right)"))


@pytest.mark.slow
@pytest.mark.parametrize("truth", [
    Pose(Rx(-120.0) @ Rz(25.0) @ Rx(10.0), np.array([30.0, -20.0, 400.0])),
    pytest.param(Pose(Rx(40.0) @ Rz(-70.0), np.array([-60.0, 40.0, 550.0])), marks=FLIP),
])
def test_tless06_coarse_pose_non_symmetric(tless06_bank, truth):
    bank = tless06_bank
    img = _noisy(render_shaded(bank.vertices_mm, bank.faces, truth, INTR.K, (W, H)), 6)
    out = pipeline.estimate(bank, img, INTR, distance_mm=float(truth.t_mm[2]), refine=False)
    assert out.found
    assert rotation_angle_deg(out.coarse.pose.R, truth.R) <= COARSE_ROT_DEG_NONSYM
    assert np.linalg.norm(out.coarse.pose.t_mm - truth.t_mm) <= COARSE_T_MM_NONSYM


def _brute_best(dt, tau_q, off_u, off_v, chan, au, av):
    best = (np.inf, -1)
    H, W, _ = dt.shape
    for a in range(len(au)):
        for t in range(off_u.shape[2]):
            y, x = av[a] + off_v[0, 0, t], au[a] + off_u[0, 0, t]
            inside = (y >= 0) & (y < H) & (x >= 0) & (x < W)
            vals = np.where(inside, dt[np.clip(y, 0, H - 1), np.clip(x, 0, W - 1), chan[t]], tau_q)
            best = min(best, (vals.mean(), t))
    return best


def test_scan_with_a_shared_bound_finds_the_brute_force_best():
    """The local scans prune every anchor against the best any anchor has reached; the overall best
    must be exactly the brute-force one, also with template points falling outside the image."""
    from service.vision.estimate.scan import _scan

    rng = np.random.default_rng(7)
    H, W, C, T, P = 30, 40, 4, 9, 12
    tau_q = 60
    dt = rng.integers(0, tau_q + 1, (H, W, C)).astype(np.uint8)
    off_u = rng.integers(-8, 9, (1, 1, T, P)).astype(np.int16)
    off_v = rng.integers(-8, 9, (1, 1, T, P)).astype(np.int16)
    chan = rng.integers(0, C, (T, P)).astype(np.int32)
    au = rng.integers(-3, W + 3, 200).astype(np.int32)
    av = rng.integers(-3, H + 3, 200).astype(np.int32)
    for shared in (False, True):
        cost, t, _ = _scan(dt, tau_q, off_u, off_v, chan, au, av, np.zeros(200, np.int32), np.int64(tau_q),
                           0, shared)
        a = int(np.argmin(cost))
        want_cost, want_t = _brute_best(dt, tau_q, off_u, off_v, chan, au, av)
        assert cost[a] == pytest.approx(want_cost)
        assert _brute_best(dt, tau_q, off_u[:, :, t[a]:t[a] + 1], off_v[:, :, t[a]:t[a] + 1],
                           chan[t[a]:t[a] + 1], au[a:a + 1], av[a:a + 1])[0] == pytest.approx(want_cost)


def _window_case(seed, tau_q=32, T=40, P=24, r=12, stride=2, near_image_edge=False):
    rng = np.random.default_rng(seed)
    H, W, C = 60, 70, 4
    # smooth-ish costs (a real DT3 is 1-Lipschitz) with a few cheap templates, capped at tau_q
    yy, xx = np.mgrid[0:H, 0:W]
    dt = np.stack([np.minimum(np.abs(np.sin(0.2 * xx + c) * np.cos(0.15 * yy - c)) * 3 * tau_q, tau_q)
                   for c in range(C)], -1).astype(np.uint8)
    off_u = rng.integers(-15, 16, (1, 1, T, P)).astype(np.int16)
    off_v = rng.integers(-15, 16, (1, 1, T, P)).astype(np.int16)
    chan = rng.integers(0, C, (T, P)).astype(np.int32)
    g = np.arange(-r, r + 1, stride)
    gu, gv = (x.ravel() for x in np.meshgrid(g, g))
    order = np.argsort(gu ** 2 + gv ** 2, kind="stable")
    gu, gv = gu[order], gv[order]
    c0 = (3, 4) if near_image_edge else (W // 2, H // 2)
    au, av = (c0[0] + gu).astype(np.int32), (c0[1] + gv).astype(np.int32)
    return dt, tau_q, off_u, off_v, chan, au, av, gu, gv, stride


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("near_image_edge", [False, True])
def test_window_block_bounds_are_lower_bounds_and_change_no_result(seed, near_image_edge):
    """Level B's block bounds: for every anchor of a block and template, the bound is at most the
    anchor's own sum over the first LEVEL_B_SENTINEL_POINTS points (tau_q outside the image), and the
    bounded scan returns exactly what the unbounded one does, at any accept threshold."""
    from service.vision.estimate.level_b import _window_bounds
    from service.vision.estimate.scan import LEVEL_B_SENTINEL_POINTS, _scan, _scan_bounded

    dt, tau_q, off_u, off_v, chan, au, av, gu, gv, stride = _window_case(seed,
                                                                         near_image_edge=near_image_edge)
    lower, block = _window_bounds(dt, tau_q, off_u, off_v, chan, au, av, gu, gv, stride)
    assert len(block) == len(au) and lower.shape[1:] == (1, off_u.shape[2])
    H, W, _ = dt.shape
    n = LEVEL_B_SENTINEL_POINTS
    for a in range(len(au)):
        y, x = av[a] + off_v[0, 0, :, :n], au[a] + off_u[0, 0, :, :n]
        inside = (y >= 0) & (y < H) & (x >= 0) & (x < W)
        own = np.where(inside, dt[np.clip(y, 0, H - 1), np.clip(x, 0, W - 1), chan[:, :n]], tau_q).sum(1)
        assert np.all(lower[block[a], 0] <= own)
    assert (lower > 8 * n * 1.2).any()  # the bounds reject some templates at accept 8
    # One thread: with several, which anchors report inf depends on when each saw the shared bound (for
    # the bounded and the unbounded scan alike).
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        for accept in (4, 8, 16, tau_q):
            got = _scan_bounded(dt, tau_q, off_u, off_v, chan, au, av, np.zeros(len(au), np.int32),
                                np.int64(accept), n, True, lower, block)
            want = _scan(dt, tau_q, off_u, off_v, chan, au, av, np.zeros(len(au), np.int32), np.int64(accept),
                         n, True)
            for g_, w_ in zip(got, want, strict=True):
                np.testing.assert_array_equal(g_, w_)
    finally:
        numba.set_num_threads(threads)


def _shared_scan_reference(dt, tau_q, off_u, off_v, chan, au, av, accept, n_sentinel):
    """``_scan_bounded`` with a shared bound as its docstring specifies it, serially in Python: anchors in
    rounds of SHARED_FIRST_ROUND, 2x, 4x, ..., each starting from the best total of the rounds before."""
    from service.vision.estimate.scan import SENTINEL_RATIO, SHARED_FIRST_ROUND

    H, W, _ = dt.shape
    _, D, T, P = off_u.shape
    A = len(au)
    cost, bt, bd = np.full(A, np.inf), np.full(A, -1, np.int32), np.full(A, -1, np.int32)
    bound, start, size = int(accept) * P, 0, SHARED_FIRST_ROUND
    while start < A:
        stop = min(A, start + size)
        for a in range(start, stop):
            best = bound
            for t in range(T):
                for d in range(D):
                    y, x = av[a] + off_v[0, d, t], au[a] + off_u[0, d, t]
                    inside = (y >= 0) & (y < H) & (x >= 0) & (x < W)
                    acc = np.cumsum(np.where(inside, dt[np.clip(y, 0, H - 1), np.clip(x, 0, W - 1), chan[t]],
                                             tau_q).astype(np.int64))
                    if acc[-1] >= best or (0 < n_sentinel <= P
                                           and acc[n_sentinel - 1] * P > best * n_sentinel * SENTINEL_RATIO):
                        continue
                    best, bt[a], bd[a] = int(acc[-1]), t, d
            if bt[a] >= 0:
                cost[a] = best / P
        finite = cost[start:stop][np.isfinite(cost[start:stop])]
        bound = min([bound, *(int(round(c * P)) for c in finite)])
        start, size = stop, 2 * size
    return cost, bt, bd


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_shared_bound_scan_does_not_depend_on_the_threads(seed):
    """Level B's scan with a shared bound returns exactly the serial reference's costs, templates and
    scales, with one thread and with every thread numba has: the bound an anchor prunes against (and so
    its sentinel tests and ties) follows from the anchors' order, never from the threads' timing (a bound
    read as the threads ran changed clutter 0002's candidates from run to run)."""
    from service.vision.estimate.level_b import _window_bounds
    from service.vision.estimate.scan import LEVEL_B_SENTINEL_POINTS, _scan_bounded

    dt, tau_q, off_u, off_v, chan, au, av, gu, gv, stride = _window_case(seed)
    # two depths: the scale index is part of the answer
    off_u = np.concatenate([off_u, (off_u * 1.1).astype(np.int16)], axis=1)
    off_v = np.concatenate([off_v, (off_v * 1.1).astype(np.int16)], axis=1)
    lower, block = _window_bounds(dt, tau_q, off_u, off_v, chan, au, av, gu, gv, stride)
    n = LEVEL_B_SENTINEL_POINTS
    threads = numba.get_num_threads()
    reported = []
    try:
        for accept in (8, 16, tau_q):
            want = _shared_scan_reference(dt, tau_q, off_u, off_v, chan, au, av, accept, n)
            reported.append(int(np.isfinite(want[0]).sum()))
            for k in sorted({1, numba.config.NUMBA_NUM_THREADS}):
                numba.set_num_threads(k)
                for _ in range(3):
                    got = _scan_bounded(dt, tau_q, off_u, off_v, chan, au, av, np.zeros(len(au), np.int32),
                                        np.int64(accept), n, True, lower, block)
                    for g_, w_ in zip(got, want, strict=True):
                        np.testing.assert_array_equal(g_, w_)
    finally:
        numba.set_num_threads(threads)
    assert max(reported) > 1  # later rounds beat earlier ones: the bound moved between rounds


@pytest.mark.parametrize("seed", [0, 1])
def test_serial_rounds_and_blocks_give_the_parallel_kernels_answer(seed):
    """The small rounds and block tables that run on the calling thread (no parallel region to start)
    give exactly the answer of the same kernel run all in parallel, and of the serial reference."""
    from service.vision.estimate.level_b import _window_bounds
    from service.vision.estimate.scan import LEVEL_B_SENTINEL_POINTS, _block_lower_bounds, _scan_bounded

    dt, tau_q, off_u, off_v, chan, au, av, gu, gv, stride = _window_case(seed)
    n = LEVEL_B_SENTINEL_POINTS
    bounds = [(np.zeros((0, 0, 0), np.int64), np.zeros(0, np.int32)),
              _window_bounds(dt, tau_q, off_u, off_v, chan, au, av, gu, gv, stride)]
    for accept in (8, tau_q):
        want = _shared_scan_reference(dt, tau_q, off_u, off_v, chan, au, av, accept, n)
        for (lower, block), serial_round in itertools.product(bounds, (0, 4, len(au))):
            got = _scan_bounded(dt, tau_q, off_u, off_v, chan, au, av, np.zeros(len(au), np.int32),
                                np.int64(accept), n, True, lower, block, serial_round)
            for g_, w_ in zip(got, want, strict=True):
                np.testing.assert_array_equal(g_, w_)
    rng = np.random.default_rng(seed)
    pooled = rng.integers(0, 256, (80, 90, chan.max() + 1)).astype(np.uint8)
    bu, bv = rng.integers(20, 60, 6).astype(np.int32), rng.integers(20, 50, 6).astype(np.int32)
    pu0, pv0 = -3, -5  # the region's origin: offsets index pooled relative to it
    y = bv[:, None, None, None] + off_v[0][None, :, :, :n] - pv0  # (B, D, T, n)
    x = bu[:, None, None, None] + off_u[0][None, :, :, :n] - pu0
    want = pooled[y, x, chan[None, None, :, :n]].astype(np.int64).sum(-1)
    for serial_blocks in (0, len(bu)):
        got = _block_lower_bounds(pooled, pu0, pv0, off_u, off_v, chan, bu, bv, n, serial_blocks)
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("seed,stride", [(0, 2), (1, 2), (2, 1), (3, 3)])
def test_level_a_block_scan_equals_the_anchor_scan(seed, stride):
    """Level A's banded scan (tiles, several scales, any subset of the stride grid, anchors near and past
    the image border) returns exactly ``_scan``'s per-anchor best."""
    from service.vision.estimate.level_a import _scan_level_a_bands
    from service.vision.estimate.scan import LEVEL_A_SENTINEL_POINTS, _scan

    rng = np.random.default_rng(seed)
    H, W, C, J, D, T, P = 40, 56, 4, 2, 3, 30, 32
    tau_q = 32
    yy, xx = np.mgrid[0:H, 0:W]
    dt = np.stack([np.minimum(np.abs(np.sin(0.3 * xx + c) * np.cos(0.25 * yy - c)) * 3 * tau_q, tau_q)
                   for c in range(C)], -1).astype(np.uint8)
    off_u = rng.integers(-10, 11, (J, D, T, P)).astype(np.int16)
    off_v = rng.integers(-10, 11, (J, D, T, P)).astype(np.int16)
    chan = rng.integers(0, C, (T, P)).astype(np.int32)
    grid = np.meshgrid(np.arange(0, W, stride), np.arange(0, H, stride))
    au, av = (x.ravel().astype(np.int32) for x in grid)
    keep = rng.random(len(au)) < 0.7
    au, av = au[keep], av[keep]
    tile = (au >= W // 2).astype(np.int32)
    found = []
    for accept in (6, 12, tau_q // 2, tau_q):
        got = _scan_level_a_bands(dt, tau_q, off_u, off_v, chan, au, av, tile, np.int64(accept), stride)
        want = _scan(dt, tau_q, off_u, off_v, chan, au, av, tile, np.int64(accept), LEVEL_A_SENTINEL_POINTS,
                     False)
        for g_, w_ in zip(got, want, strict=True):
            np.testing.assert_array_equal(g_, w_)
        found.append(np.isfinite(want[0]).mean())
    assert 0 < found[-1] <= 1 and found[0] < 1


def test_level_a_scan_of_scattered_blocks_equals_the_anchor_scan():
    """A deadline scans level A in chunks of whole blocks in edge-count order, not in rows: a chunk of
    scattered blocks (gaps inside a band) still gets exactly ``_scan``'s per-anchor best."""
    from service.vision.estimate.level_a import LEVEL_A_BLOCK_ANCHORS, _scan_level_a_bands
    from service.vision.estimate.scan import LEVEL_A_SENTINEL_POINTS, _scan

    rng = np.random.default_rng(7)
    H, W, C, J, D, T, P, stride = 48, 96, 3, 1, 2, 20, 32, 2
    tau_q = 24
    dt = rng.integers(0, tau_q + 1, (H, W, C)).astype(np.uint8)
    off_u = rng.integers(-12, 13, (J, D, T, P)).astype(np.int16)
    off_v = rng.integers(-12, 13, (J, D, T, P)).astype(np.int16)
    chan = rng.integers(0, C, (T, P)).astype(np.int32)
    grid = np.meshgrid(np.arange(0, W, stride), np.arange(0, H, stride))
    au, av = (x.ravel().astype(np.int32) for x in grid)
    span = stride * LEVEL_A_BLOCK_ANCHORS
    block_col = au // span
    chosen = (block_col % 3 == 0) | ((block_col == 4) & (av < span))  # gaps of one and two blocks
    au, av = au[chosen], av[chosen]
    tile = np.zeros(len(au), np.int32)
    got = _scan_level_a_bands(dt, tau_q, off_u, off_v, chan, au, av, tile, np.int64(tau_q // 2), stride)
    want = _scan(dt, tau_q, off_u, off_v, chan, au, av, tile, np.int64(tau_q // 2), LEVEL_A_SENTINEL_POINTS,
                 False)
    for g_, w_ in zip(got, want, strict=True):
        np.testing.assert_array_equal(g_, w_)
    assert np.isfinite(want[0]).any()


def test_views_within_adds_a_revolved_parts_mirror_tilt(sprayer_bank):
    from service.vision.bank import views_within

    tilt = sprayer_bank.view_params_deg[:, 0]
    v30 = int(np.argmin(np.abs(tilt - 30.0)))
    near = set(np.round(tilt[views_within(sprayer_bank, v30, 5.0)]).astype(int))
    assert {26, 28, 30, 32, 34} <= near and {-26, -28, -30, -32, -34} <= near
    assert not any(abs(abs(x) - 30) > 5 for x in near)


@pytest.mark.parametrize("count", [16, 48, 80, 160])
def test_spread_order_is_a_permutation_whose_prefixes_cover_the_border_evenly(count):
    from service.vision.bank import spread_order

    order = spread_order(count)
    assert sorted(order.tolist()) == list(range(count))
    for k in (4, 8, 16):
        pos = np.sort(order[:k])
        gaps = np.diff(np.r_[pos, pos[0] + count])  # cyclic: the border is closed
        assert gaps.max() <= int(np.ceil(count / k)) + 1


def test_window_offsets_equal_the_projected_posed_border(sprayer_bank):
    """The compiled window templates against an independent path: poses_of (ray, in-plane angle,
    bank view, known distance) then the pinhole projection of the same 3D border points."""
    from service.vision.bank import border_triplets
    from service.vision.estimate.level_b import Window, _window_offsets
    from service.vision.estimate.search import Hypothesis, poses_of
    from service.vision.geometry.camera import ray_rotation

    bank = sprayer_bank
    win = Window(np.array([3, 17, 40]), np.array([-12.0, 0.0, 33.0]), np.array([1.0, 1.07]),
                 np.array([1010.3, 170.8]), 4, 2)
    scale, distance = 0.5, 480.0
    idx = border_triplets(bank, 40)[0][win.views]
    d, R_ray = ray_rotation(win.centre, INTR.K)
    Rphi = np.stack([Rz(f) for f in win.phis_deg])[:, None]
    Rv = (R_ray @ Rphi @ bank.R_tpl_obj[win.views][None]).reshape(-1, 3, 3)
    zc = distance + (Rv @ bank.centre_obj)[:, 2]
    c0 = np.rint((win.centre + 0.5) * scale - 0.5)
    off_u, off_v, _ = _window_offsets(bank.p_obj[idx].astype(np.float64) - bank.centre_obj,
                                      bank.theta_rad[idx].astype(np.float64), Rv, zc, win.depth_f, d / d[2],
                                      INTR.fx, INTR.fy, INTR.cx, INTR.cy, scale, c0[0], c0[1],
                                      np.deg2rad(win.phis_deg), 16)
    K = INTR.K
    for t in range(len(Rv)):
        iv, iphi = t % len(win.views), t // len(win.views)
        h = Hypothesis(int(win.views[iv]), float(win.phis_deg[iphi]), 0.0, win.centre.copy())
        R, t_mm = (x[0] for x in poses_of(bank, [h], K, distance))
        q = bank.p_obj[idx[iv]] @ R.T + t_mm
        uv = (K @ (q / q[:, 2:3]).T).T[:, :2]
        want = np.rint((uv + 0.5) * scale - 0.5 - c0)
        assert np.array_equal(off_u[0, 0, t], want[:, 0]) and np.array_equal(off_v[0, 0, t], want[:, 1])
        # the second depth factor: the reference point slides along the same ray
        z = t_mm + (R @ bank.centre_obj)
        q2 = bank.p_obj[idx[iv]] @ R.T + t_mm + z * (1.07 - 1.0)
        uv2 = (K @ (q2 / q2[:, 2:3]).T).T[:, :2]
        assert np.abs(off_u[0, 1, t] - np.rint((uv2[:, 0] + 0.5) * scale - 0.5 - c0[0])).max() <= 1


def test_min_pool_is_the_cell_minimum_in_coarser_pixels():
    from service.vision.estimate.chamfer import DistanceTensor, pooled_distance_tensor

    rng = np.random.default_rng(5)
    dt = rng.uniform(0, 10, (3, 23, 37)).astype(np.float32)
    pooled = pooled_distance_tensor(DistanceTensor(dt, 0.5, (0.0, 0.0), 10.0, 1.0), 0.125)
    want = dt[:, :20, :36].reshape(3, 5, 4, 9, 4).min(axis=(2, 4)) / 4
    np.testing.assert_allclose(pooled.dt, want, rtol=1e-6)
    assert pooled.scale == 0.125 and pooled.tau_px == 2.5


def test_scaled_offsets_are_the_rounded_products_and_are_made_once():
    from service.vision.estimate.level_a import LevelATemplates, scaled_offsets

    rng = np.random.default_rng(2)
    off_u = rng.uniform(-40, 40, (3, 5, 7)).astype(np.float32)
    off_v = rng.uniform(-40, 40, (3, 5, 7)).astype(np.float32)
    tpl = LevelATemplates(np.arange(5), np.zeros(1), off_u, off_v, np.zeros((5, 7), np.int32),
                          np.zeros((3, 5)), np.zeros((3, 2)), 40.0, 100.0)
    scales = np.array([0.5, 1.0, 1.15, 2.3])
    u, v = scaled_offsets(tpl, scales)
    np.testing.assert_array_equal(u, np.rint(off_u[:, None] * scales[None, :, None, None]).astype(np.int16))
    np.testing.assert_array_equal(v, np.rint(off_v[:, None] * scales[None, :, None, None]).astype(np.int16))
    assert scaled_offsets(tpl, scales)[0] is u  # the next frame reuses them


def test_background_normalised_cost_ranks_a_partial_outline_above_dense_texture():
    """Known answer (issue #14): a square template on dense random texture (every orientation nearby)
    costs less than on its own outline with one of its four sides missing (occluded), so ranking by
    cost picks the texture; over the local background cost (``background_cost``: what any template
    costs there) the outline, standing out of plain ground, ranks first."""
    from service.vision.estimate.chamfer import distance_tensor_from_edges, quantised
    from service.vision.estimate.level_a import background_cost, pick_peaks
    from service.vision.estimate.scan import _scan

    C, H, W, half = 8, 64, 160, 8
    rng = np.random.default_rng(3)
    edges = np.zeros((C, H, W), np.uint8)
    tex = rng.random((H, W // 2)) < 0.35  # the left half: dense texture of random orientations
    ch = rng.integers(0, C, (H, W // 2))
    for c in range(C):
        edges[c, :, :W // 2] = tex & (ch == c)
    cu, cv = 120, 32  # the right half: the square's outline less its bottom side (channel 0: horizontal)
    edges[0, cv - half, cu - half:cu + half + 1] = 1
    edges[C // 2, cv - half:cv + half + 1, cu - half] = 1
    edges[C // 2, cv - half:cv + half + 1, cu + half] = 1
    dtt = distance_tensor_from_edges(edges, tau_px=10.0)
    s = np.arange(-half, half + 1)
    pts = np.concatenate([np.stack([s, np.full_like(s, -half)], 1), np.stack([s, np.full_like(s, half)], 1),
                          np.stack([np.full_like(s, -half), s], 1), np.stack([np.full_like(s, half), s], 1)])
    chan = np.array([0] * (2 * len(s)) + [C // 2] * (2 * len(s)), np.int32)[None]
    off_u = pts[:, 0].astype(np.int16)[None, None, None]
    off_v = pts[:, 1].astype(np.int16)[None, None, None]
    dt_q, tau_q = quantised(dtt, dtt.tau_px)
    gu, gv = np.meshgrid(np.arange(half, W - half, 2), np.arange(half, H - half, 2))
    au, av = gu.ravel().astype(np.int32), gv.ravel().astype(np.int32)
    cost, _, _ = _scan(dt_q, tau_q, off_u, off_v, chan, au, av, np.zeros(len(au), np.int32),
                       np.int64(tau_q * off_u.shape[-1]), 0, False)
    outline = int(np.flatnonzero((au == cu) & (av == cv))[0])
    on_texture = au < W // 2 - half
    assert cost[on_texture].min() < cost[outline]  # raw chamfer cost: the texture wins
    bg = background_cost(dtt, half)
    rank = cost / bg[av, au]
    assert rank[outline] < rank[on_texture].min()  # over the background: the outline wins
    assert pick_peaks(au, av, rank, 1, 4.0) == [outline]


def _decoy_scene(bank, dist: float, uv: np.ndarray, *, decoy: bool = True, phi_deg: float = 94.0):
    """The part (the L block) rendered at ``uv`` (3 px off a level-A anchor's pixel ``uv - 3``, 4 deg off
    level A's in-plane grid) and, with ``decoy``, its outline at another rotation (118 deg away) drawn
    as two parallel contours 5 px either side of it, which level A's 1/8 min-pooled grid cannot tell
    from an outline itself -> (grey image, R_part, t_part)."""
    import cv2

    from service.vision.estimate import level_a
    from service.vision.estimate.search import Hypothesis, poses_of

    tpl = level_a._cached_level_a(bank, INTR, (H, W), pipeline.DEFAULT_POLICY.search_params, dist, dist)
    h_decoy = Hypothesis(int(tpl.views[0]), 0.0, dist, uv - 3)
    h_part = Hypothesis(int(tpl.views[20]), phi_deg, dist, uv)
    (R_decoy, R_part), (t_decoy, t_part) = poses_of(bank, [h_decoy, h_part], INTR.K, dist)
    assert rotation_angle_deg(R_decoy, R_part) > 100
    img = render_shaded(bank.vertices_mm, bank.faces, Pose(R_part, t_part), INTR.K, (W, H))
    if decoy:
        mask = render(bank.vertices_mm, bank.faces, Pose(R_decoy, t_decoy), INTR.K, (W, H)).mask
        mask = mask.astype(np.uint8)
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (11, 11))
        for m in (cv2.dilate(mask, disc), cv2.erode(mask, disc)):
            contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
            cv2.drawContours(img, contours, -1, 255, 1)
    return img, R_part, t_part


def _is_pose(R_part, t_part):
    def right(pose) -> bool:
        return (rotation_angle_deg(pose.R, R_part) <= COARSE_ROT_DEG_NONSYM
                and np.linalg.norm(pose.t_mm - t_part) <= COARSE_T_MM_NONSYM)
    return right


def test_second_distinct_template_at_a_peak_is_proposed(l_block_bank):
    """Level A keeps an anchor's single best template. Here that one is a decoy's (``_decoy_scene``) at
    the very place of the part. Level B finds the decoy 5 px off everywhere, but from the decoy's
    template it cannot turn to the part. With one peak, only ``templates_per_peak`` > 1 starts level B
    from the part's template too (the second distinct one there, the search's deferred second pass)
    and proposes it."""
    bank, dist = l_block_bank, 500.0
    p = replace(pipeline.DEFAULT_POLICY.search_params, n_peaks=1, bg_norm=False, templates_per_peak=1)
    img, R_part, t_part = _decoy_scene(bank, dist, np.array([8 * 80 + 6.5, 8 * 60 + 6.5]))
    right = _is_pose(R_part, t_part)
    single = pipeline.propose(bank, img, INTR, distance_mm=dist, params=p)[0]
    assert single and not any(right(c.pose) for c in single)  # the single best template leads elsewhere
    later: list = []
    first = pipeline.propose(bank, img, INTR, distance_mm=dist, params=replace(p, templates_per_peak=3),
                             deferred=later)[0]
    assert not any(right(c.pose) for c in first) and len(later) == 1  # the first pass: as with one ...
    assert any(right(c.pose) for c in later[0]())  # ... the second, the peak's other templates: the part


def test_estimate_runs_the_second_pass_only_when_the_first_candidates_fail(l_block_bank, monkeypatch):
    """The search's second pass (the peaks' other templates) costs level-B scans: ``estimate`` runs it
    only when none of the first pass's candidates is found. On a clean render of the part (on level
    A's in-plane grid) it is found at once and the pass never runs; with the decoy on it
    (``_decoy_scene``) the first candidate is the decoy's rotation, rejected, and the second pass runs
    and proposes the part."""
    from service.vision.estimate import coarse

    calls: list[int] = []
    peak_starts = coarse.peak_starts  # as the search calls it
    monkeypatch.setattr(coarse, "peak_starts", lambda *a, **k: calls.append(1) or peak_starts(*a, **k))
    bank, dist = l_block_bank, 500.0
    p = replace(pipeline.DEFAULT_POLICY.search_params, n_peaks=1, templates_per_peak=3)
    uv = np.array([8 * 80 + 6.5, 8 * 60 + 6.5])
    img, R_part, t_part = _decoy_scene(bank, dist, uv, decoy=False, phi_deg=90.0)
    out = pipeline.estimate(bank, img, INTR, distance_mm=dist, params=p)
    assert out.found and _is_pose(R_part, t_part)(out.refined.pose) and not calls
    img, R_part, t_part = _decoy_scene(bank, dist, uv)
    right = _is_pose(R_part, t_part)
    out = pipeline.estimate(bank, img, INTR, distance_mm=dist, params=p)
    assert not right(out.candidates[0].pose) and calls == [1]
    assert any(right(c.pose) for c in out.candidates[1:])


def test_background_norm_and_templates_per_peak_together_propose_the_part_beside_texture(l_block_bank):
    """Known answer for the two mechanisms together (issue #14). The part sits at one place with a
    decoy outline (its outline at another rotation, 118 deg away, drawn as two contours 5 px either
    side) on it, as in ``test_second_distinct_template_at_a_peak_is_proposed``; the left 480 px of the
    frame are dense texture (random short segments of every orientation). With one peak: by chamfer
    cost level A picks the texture, with or without extra templates; over the background it picks the
    part's anchor, but there its single best template is the decoy's; only both together start level B
    from the part's own rotation there and propose it."""
    import cv2

    from service.vision.estimate import coarse, level_a
    from service.vision.estimate.chamfer import distance_tensor
    from service.vision.estimate.edges import Segments, detect_segments
    from service.vision.estimate.search import Hypothesis, poses_of

    bank, dist = l_block_bank, 500.0
    p = replace(pipeline.DEFAULT_POLICY.search_params, n_peaks=1, bg_norm=False, templates_per_peak=1)
    tpl = level_a._cached_level_a(bank, INTR, (H, W), p, dist, dist)
    uv = np.array([8 * 100 + 3.5, 8 * 60 + 3.5])  # a level-A anchor's pixel, right of the texture
    decoy = Hypothesis(int(tpl.views[0]), 0.0, dist, uv)
    part = Hypothesis(int(tpl.views[20]), 94.0, dist, uv + 3)
    (R_decoy, R_part), (t_decoy, t_part) = poses_of(bank, [decoy, part], INTR.K, dist)
    img = render_shaded(bank.vertices_mm, bank.faces, Pose(R_part, t_part), INTR.K, (W, H))
    mask = render(bank.vertices_mm, bank.faces, Pose(R_decoy, t_decoy), INTR.K, (W, H)).mask.astype(np.uint8)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (11, 11))
    for m in (cv2.dilate(mask, disc), cv2.erode(mask, disc)):
        contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(img, contours, -1, 255, 1)
    seg = detect_segments(img)
    rng = np.random.default_rng(5)
    n = 6000
    c = np.column_stack([rng.uniform(0, 480, n), rng.uniform(0, H, n)])
    th = rng.uniform(0, np.pi, n)
    d = np.column_stack([np.cos(th), np.sin(th)]) * rng.uniform(8, 20, n)[:, None] / 2
    seg = Segments(np.concatenate([seg.uv0, c - d]).astype(np.float32),
                   np.concatenate([seg.uv1, c + d]).astype(np.float32),
                   np.concatenate([seg.theta_rad, th]).astype(np.float32), (H, W))
    dtt = distance_tensor(seg, n_channels=p.n_channels, scale=p.fine_scale)

    def search(**kw):
        hs = coarse.coarse_search(bank, dtt, INTR, (H, W), replace(p, **kw), distance_mm=dist,
                                  distance_range_mm=(300.0, 1200.0))
        Rs, ts = poses_of(bank, hs, INTR.K, dist)
        return hs, [rotation_angle_deg(R, R_part) <= COARSE_ROT_DEG_NONSYM
                    and np.linalg.norm(t - t_part) <= COARSE_T_MM_NONSYM for R, t in zip(Rs, ts, strict=True)]

    hs, right = search()
    assert hs and hs[0].uv[0] < 480 and not any(right)  # by cost: the texture
    hs, right = search(templates_per_peak=3)
    assert hs and hs[0].uv[0] < 480 and not any(right)  # ... extra templates there do not help
    hs, right = search(bg_norm=True)
    assert hs and hs[0].uv[0] > 480 and not any(right)  # over the background: the place, not the rotation
    hs, right = search(bg_norm=True, templates_per_peak=3)
    assert right[0]  # both: the part, first


def test_level_a_tables_the_deadline_leaves_no_time_for_are_made_in_the_background(sprayer_bank, monkeypatch):
    # Making level A's templates (per bank, camera, image size and distance) is in no unit of work the
    # deadline checks: with no time left the search answers at once, and a later frame finds them made.
    import threading

    from service.vision.deadline import Deadline
    from service.vision.estimate import level_a

    gate = threading.Event()
    real = level_a._cached_level_a

    def slow(*args):
        assert gate.wait(30)  # hang guard: the test opens the gate
        return real(*args)

    monkeypatch.setattr(level_a, "_cached_level_a", slow)
    p = pipeline.DEFAULT_POLICY.search_params
    intr = Intrinsics(1234.0, 1234.0, 640.0, 480.0)  # a camera no other test made tables for
    args = (sprayer_bank, intr, (H, W), p, 500.0, 500.0, np.array([1.0]))
    deadline = Deadline(100.0, clock=lambda: 0.0)  # 100 ms left, and they stay left
    deadline.checked()  # past the frame's first check, which would be owed the tables whatever the time
    assert level_a._level_a_in_time(*args, deadline, reserve_ms=100.0) is None
    assert deadline.hit
    gate.set()
    later = Deadline(60_000.0, clock=lambda: 0.0)  # a hang guard, not a speed assert
    tpl = level_a._level_a_in_time(*args, later, reserve_ms=0.0)  # waits for the one being made
    assert tpl is not None and not later.hit
    want = level_a.level_a_templates(sprayer_bank, intr, (H, W), p, distance_mm=500.0, z_ref_mm=500.0)
    np.testing.assert_array_equal(tpl.off_u, want.off_u)
    np.testing.assert_array_equal(tpl.chan, want.chan)
    again = Deadline(100.0, clock=lambda: 0.0)
    assert level_a._level_a_in_time(*args, again, reserve_ms=100.0) is tpl  # made once, no wait
    assert not again.hit


@pytest.mark.parametrize("distance_range_mm", [(300.0, 1200.0), (150.0, 400.0)])
def test_level_a_padding_covers_every_scaled_offset(sprayer_bank, distance_range_mm):
    """Level A's banded scan reads its padded DT3 without bounds tests: the padding it is given from the
    templates' extent (``scan_level_a``) must cover every scaled offset it will read."""
    from service.vision.estimate import level_a, search

    intr = Intrinsics.from_K(np.array([[1100.0, 0, 643.0], [0, 1100.0, 477.0], [0, 0, 1]]))
    p = search.SearchParams()
    z_ref, scales = search.depth_scales(distance_range_mm, p.depth_step)
    tpl = level_a.level_a_templates(sprayer_bank, intr, (960, 1280), p, distance_mm=None, z_ref_mm=z_ref)
    off_u, off_v = level_a.scaled_offsets(tpl, scales)
    reach = int(np.ceil(tpl.extent_px * float(scales.max()))) + 1
    assert max(np.abs(off_u).max(), np.abs(off_v).max()) <= reach
