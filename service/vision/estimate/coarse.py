"""Coarse pose by directional chamfer matching over the whole image (paper section II.B).

Search, coarse to fine:
1. level A (DT3 min-pooled to ``level_scale``, 1/8): every out-of-plane view x in-plane rotation x
   distance is tried at every anchor (stride ``anchor_stride``) by a compiled scan with early
   termination (a template is abandoned once its partial sum exceeds the anchor's best so far, or
   its first points, taken in ``spread_order`` round the border, already average well above it);
   the image is split into tiles so each tile uses the template shape seen along its own viewing ray;
   anchors are scanned in bands of rows, a template's first points summed for a whole band at once
   from a DT3 laid out so that one point's costs along a row of anchors are contiguous (``_scan_bands``;
   exact);
2. level B (``fine_scale``, 1/2): around each distinct peak a compiled exhaustive scan of the
   nearby views, in-plane angles, depths and pixels (``local_scan``: level A says which basin to
   look in, not where in it; the same block bounds, ``_window_bounds``), then the best few are
   polished sub-pixel by a pattern search over (view, in-plane angle, distance, position) with exact
   perspective projection of the templates' 3D border points.

Peaks, level-B placements and polished hypotheses are ranked by cost over the local background's
(``bg_norm``, ``background_cost``): on texture every template is cheap, and an outline standing out
of plainer ground should outrank it. Level A keeps one template per anchor, and at a clutter peak near
the truth that one is often another rotation level B cannot turn back from: a second pass starts
level B from the first peaks' other distinct templates too (``templates_per_peak``, ``peak_starts``),
deferred by the pipeline until the first pass's candidates have all failed verification.

A hypothesis becomes a 6D pose without assuming the object sits on the optical axis: with the
reference point seen at pixel ``uv`` (viewing ray ``r``), ``R = R_between(e_z, r) @ Rz(phi) @ R_view``
and the reference point lies on ``r`` at depth ``z``, so the coarse rotation is right at the image
corners too.
"""

from __future__ import annotations

import concurrent.futures
import functools
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numba as nb
import numpy as np

from service.vision import threads
from service.vision.bank import (
    TemplateBank,
    border_triplets,
    spread_order,
    subsample_border,
    view_dirs_obj,
    view_neighbours,
    view_step_deg,
    views_within,
)
from service.vision.deadline import NO_DEADLINE, Deadline
from service.vision.estimate.chamfer import (
    DT_QUANT,
    DistanceTensor,
    pooled_and_quantised,
    quantised,
    sample,
    sample_mean,
)
from service.vision.geometry.camera import Intrinsics, project, ray_rotation, ray_rotations
from service.vision.geometry.frames import Rz
from service.vision.memo import Memo

# Early termination (``_scan``): a template is dropped once its first points, taken in spread order
# round its border, already average this many times the best mean so far ...
SENTINEL_RATIO = 1.2
LEVEL_A_SENTINEL_POINTS = 8  # ... judged on this many points at level A (32 per template)
LEVEL_B_SENTINEL_POINTS = 16  # ... and in level B's scans (80 and 160 per template)
# Level A keeps views at least this fraction of its view step apart (greedy on the view sphere).
LEVEL_A_VIEW_SPACING = 0.75
# Level A's edge count: a pixel is an edge pixel where some channel's DT3 is under this (level px) ...
EDGE_PIXEL_DT_PX = 0.75
EDGE_COUNT_EXTENT = 0.8  # ... counted within this fraction of the templates' extent round an anchor
PEAK_RADIUS_EXTENT = 0.25  # level-A peaks closer than this fraction of the template extent are one peak
MIN_PEAK_RADIUS_PX = 2.0  # ... and never closer than this (level px)
# Background normalisation (``SearchParams.bg_norm``): a placement's cost is divided by the mean over
# channels and pixels of the DT3 (truncated at tau) in a box of this fraction of the templates' extent
# round it -- what a template costs there by chance: textured floors and distractors, where every
# template is cheap, then rank below an outline standing out of a plainer neighbourhood.
BG_WINDOW_EXTENT = 0.5
# Level B's first block is re-centred (at most MAX_WALKS times) while its best lies on the block's
# edge: a view turned more than this fraction of local_view_deg, the first or last angle, the border.
WALK_VIEW_EDGE = 0.6
MAX_WALKS = 3
FINE_VIEW_STEPS = 1.5  # level B's fine block: bank views within this many grid steps of the best
# The fine block contains the first block's best, so it finds at least as good a placement unless the
# denser sampling raises that one's cost by more than this factor.
FINE_BLOCK_SLACK = 1.25
# With a deadline, level A's anchors are scanned in chunks of this many, checking the time between them
# (a chunk of a non-symmetric part's anchors with the most edges took ~0.2 s on 2 cores: 1/8 of them).
LEVEL_A_CHUNK_ANCHORS = 64
# ... and level A leaves this many times the caller's reserve: one for level B and the polish of the
# best peaks, one for verifying a candidate.
LEVEL_A_RESERVE_FACTOR = 2.0
# With several templates per peak (``peak_starts``), only templates costing less than the peak's level-A
# best plus this fraction of the truncation distance (and under ``accept_frac``) are ranked.
TEMPLATE_BOUND_MARGIN = 0.2


@dataclass(frozen=True)
class SearchParams:
    n_channels: int = 16
    level_scale: float = 0.125
    fine_scale: float = 0.5
    inplane_step_deg: float = 10.0
    view_step_deg: float = 6.0  # out-of-plane spacing used at level A for a revolved part (1 DoF)
    view_step_any_deg: float = 20.0  # ... and for any other part (2 DoF): level B covers +-local_view_deg
    depth_step: float = 0.15  # ratio between successive distances tried when the distance is not given
    anchor_stride: int = 2  # level-A pixels (16 full-res px: level B searches +-local_radius_px)
    points_per_template: int = 32
    fine_points: int = 160
    scan_points: int = 80  # level B's wide block: a placement's rank needs fewer points than its polish
    tiles: tuple[int, int] = (4, 3)
    n_peaks: int = 12
    n_polish: int = 4
    accept_frac: float = 0.5  # level A: a template must average under this fraction of tau
    min_edge_frac: float = 0.3  # level A: edge pixels near an anchor, as a fraction of a border's length
    score_px: float = 3.0  # full-resolution px: a border point is "supported" within this distance
    local_phi_step_deg: float = 2.0  # level B: in-plane steps of the local scan around each peak
    local_radius_px: float = 24.0  # level B: full-resolution px searched around each peak
    local_view_deg: float = 20.0  # level B: bank views within this angle of a peak's view are tried
    # Level B ranks by the DT3 mean truncated here (full-res px): a hidden border point then costs no
    # more than a badly placed one, so a 30 % occluded truth still beats a wrong pose on clutter.
    rank_tau_px: float = 8.0
    # Level B: a later peak's scan only accepts placements within this ratio of the best cost so far.
    peak_accept_ratio: float = 1.5
    # Rank level-A peaks, level-B scans and the polished hypotheses by cost over the local background
    # cost (``background_cost``) instead of by cost alone (issue #14: clutter).
    bg_norm: bool = True
    # Level B starts per level-A peak: its own level-A template (the first pass), then (a second pass,
    # ``coarse_search``) its best others, mutually distinct (rotations more than
    # ``distinct_template_deg`` apart), each the best over the peak's anchor and its neighbours within
    # ``template_anchor_reach`` anchor strides (1: the first pass only) ...
    templates_per_peak: int = 3
    distinct_template_deg: float = 30.0
    template_anchor_reach: int = 1
    # ... at the first this many peaks only: the second pass runs on every frame where nothing is found
    # (lmo_dev, every 16th query, whole estimate p50: 1407 ms without it, 1907 with all 12 peaks', 1581
    # with the first 4; the clutter2 part it finds came from the second peak)
    template_peaks: int = 4


@dataclass
class Hypothesis:
    view: int
    phi_deg: float
    z_mm: float  # depth (camera z) of the bank's reference point centre_obj
    uv: np.ndarray  # (2,) full-resolution pixel of the reference point
    cost: float = np.inf  # mean directional chamfer distance, full-resolution px
    score: float = 0.0
    rank_cost: float = np.inf  # what the search ranks by: ``cost``, or cost / background (bg_norm)


# --- geometry of a hypothesis ----------------------------------------------------------------------


# --- level A: exhaustive scan ----------------------------------------------------------------------


def _scan(dt, tau_q, off_u, off_v, chan, anchors_u, anchors_v, anchor_tile, accept, n_sentinel, shared):
    """``_scan_bounded`` without block bounds (see there)."""
    return _scan_bounded(dt, tau_q, off_u, off_v, chan, anchors_u, anchors_v, anchor_tile, accept, n_sentinel,
                         shared, _NO_BOUNDS, _NO_BLOCKS)


_NO_BOUNDS = np.zeros((0, 0, 0), np.int64)
_NO_BLOCKS = np.zeros(0, np.int32)


# With a shared bound, ``_scan_bounded`` scans its anchors in rounds of 1, 2, 4, ... anchors: each round's
# anchors prune against the best total of the rounds before it (its start), never against each other's.
SHARED_FIRST_ROUND = 1
# Rounds of at most this many anchors, and block-bound tables of at most ``SERIAL_BLOCKS`` blocks, run on
# the calling thread: with the OpenMP threads asleep between kernels (OMP_WAIT_POLICY, vision/__init__.py)
# a parallel region waits for a woken thread, longer when the other core runs the frame's background
# work, and a level-B window's rounds and tables are too small to pay for it. A level-B window (<= 169
# anchors: rounds up to 64; 16 blocks) thus runs serially; level A's one round of every anchor does not.
# Paper frames, one process alternating frame by frame (bench/launches.py --ab 5), coarse p50 serial vs
# parallel: distance given 17.6 vs 20.3 ms, 17.8 vs 19.9, 18.3 vs 21.2; not given 75.7 vs 84.5, 65.9 vs
# 68.4. Only small rounds (<= 16) serial gained about half as much (18.9 vs 20.1 ms).
SERIAL_ROUND = 64
SERIAL_BLOCKS = 16


@nb.njit(parallel=True, cache=True, nogil=True)
def _scan_bounded(dt, tau_q, off_u, off_v, chan, anchors_u, anchors_v, anchor_tile, accept, n_sentinel,
                  shared, lower, anchor_block, serial_round=SERIAL_ROUND):
    """For every anchor, the best (template, scale) by mean DT3 over template points.

    dt: (H, W, C) uint8 (DT3 in 1/DT_QUANT pixels, pixel-major so a template's neighbouring points
    share cache lines); a point outside it costs ``tau_q``; off_u/off_v: (J, D, T, P) int16 offsets in
    level pixels of template t at scale d in tile j; chan: (T, P) int32.
    Returns best mean cost (A,), template (A,), scale index (A,). A template is abandoned as soon as
    its partial sum reaches the anchor's best total (all terms are >= 0), or when its first
    ``n_sentinel`` points already average ``SENTINEL_RATIO`` times the best mean. With ``shared`` only
    the overall best matters (a local search): anchors go in rounds of ``SHARED_FIRST_ROUND``, then
    twice as many each round, and an anchor starts from the best total of the rounds before its own;
    anchors that cannot beat it report inf. The bound an anchor prunes against is thus fixed by the
    anchors' order, never by which thread got where first: the sentinel and ties make the overall best
    depend on that bound, and a bound read as the threads ran made the same frame's answer differ from
    run to run. With ``n_sentinel = 0`` the overall best is exact. The sentinel is a heuristic:
    points come in ``spread_order``, so the first ones are a fair sample of the border.

    ``lower`` (B, D, T) int64 and ``anchor_block`` (A,) int32 (or empty: none): a lower bound, per
    block of anchors, of every template's sum over its first ``n_sentinel`` points (``_window_bounds``).
    A template whose bound already fails the partial-sum or the sentinel test is skipped without
    reading the tensor: the test would fail on its own sum too, so the result is exactly the
    unbounded scan's (same best, same ties), only cheaper.

    A round of at most ``serial_round`` anchors runs serially: an anchor's result depends only on its
    round's start, so the answer is the same.
    """
    A = anchors_u.shape[0]
    P = off_u.shape[3]
    best_sum = np.empty(A, np.int64)
    best_t = np.full(A, -1, np.int32)
    best_d = np.full(A, -1, np.int32)
    bound = accept * P
    start = 0
    size = SHARED_FIRST_ROUND if shared else A
    while start < A:
        stop = min(A, start + size)
        if stop - start <= serial_round:
            for a in range(start, stop):
                best_sum[a], best_t[a], best_d[a] = _scan_anchor(dt, tau_q, off_u, off_v, chan, anchors_u[a],
                                                                 anchors_v[a], anchor_tile[a], bound,
                                                                 n_sentinel, lower, anchor_block, a)
        else:
            for a in nb.prange(start, stop):
                best_sum[a], best_t[a], best_d[a] = _scan_anchor(dt, tau_q, off_u, off_v, chan, anchors_u[a],
                                                                 anchors_v[a], anchor_tile[a], bound,
                                                                 n_sentinel, lower, anchor_block, a)
        for a in range(start, stop):  # the next round's bound, from this round's anchors in order
            if best_t[a] >= 0 and best_sum[a] < bound:
                bound = best_sum[a]
        start = stop
        size *= 2
    best_cost = np.full(A, np.inf, np.float64)
    for a in range(A):
        if best_t[a] >= 0:
            best_cost[a] = best_sum[a] / P
    return best_cost, best_t, best_d


@nb.njit(cache=True, inline="always")
def _placement_total(dt, tau_q, off_u, off_v, chan, j, d, t, ua, va, best, n_sentinel):
    """Template ``t`` at scale ``d`` (tile ``j``'s offsets) placed at anchor (``ua``, ``va``): its total
    over all points (``tau_q`` for a point off the image), or -1 as soon as the partial total reaches
    ``best`` or, at point ``n_sentinel`` (0: no test), is over the sentinel's share of it."""
    H = dt.shape[0]
    W = dt.shape[1]
    P = off_u.shape[3]
    acc = 0
    for i in range(P):
        y = va + off_v[j, d, t, i]
        x = ua + off_u[j, d, t, i]
        if y >= 0 and y < H and x >= 0 and x < W:
            acc += dt[y, x, chan[t, i]]
        else:
            acc += tau_q
        if acc >= best:
            return -1
        if i + 1 == n_sentinel and acc * P > best * n_sentinel * SENTINEL_RATIO:
            return -1
    return acc


@nb.njit(cache=True, nogil=True)
def _scan_anchor(dt, tau_q, off_u, off_v, chan, ua, va, j, start, n_sentinel, lower, anchor_block, a):
    """``_scan_bounded`` at one anchor (``ua``, ``va``; tile ``j``; index ``a`` into ``anchor_block``),
    from the best total ``start`` -> (best total, its template, its scale index; -1, -1 when nothing
    beats ``start``)."""
    D = off_u.shape[1]
    T = off_u.shape[2]
    P = off_u.shape[3]
    bounded = lower.shape[0] > 0
    best = start
    bt = -1
    bd = -1
    for t in range(T):
        for d in range(D):
            if bounded:
                lo = lower[anchor_block[a], d, t]
                if lo >= best or (0 < n_sentinel <= P and lo * P > best * n_sentinel * SENTINEL_RATIO):
                    continue
            acc = _placement_total(dt, tau_q, off_u, off_v, chan, j, d, t, ua, va, best, n_sentinel)
            if acc >= 0:
                best = acc
                bt = t
                bd = d
    return best, bt, bd


@nb.njit(parallel=True, cache=True, nogil=True)
def _block_lower_bounds(pooled, pu0, pv0, off_u, off_v, chan, block_u, block_v, n_points,
                        serial_blocks=SERIAL_BLOCKS):
    """(B, D, T) int64: per block of anchors and template, the sum over its first ``n_points`` points of
    ``pooled`` (the DT3 min-pooled over the block's anchor offsets, region origin (pu0, pv0)). At most
    ``serial_blocks`` blocks run on the calling thread (see ``SERIAL_ROUND``)."""
    n_blocks = block_u.shape[0]
    out = np.empty((n_blocks, off_u.shape[1], off_u.shape[2]), np.int64)
    if n_blocks <= serial_blocks:
        for b in range(n_blocks):
            _block_bound(pooled, pu0, pv0, off_u, off_v, chan, block_u[b], block_v[b], n_points, out[b])
    else:
        for b in nb.prange(n_blocks):
            _block_bound(pooled, pu0, pv0, off_u, off_v, chan, block_u[b], block_v[b], n_points, out[b])
    return out


@nb.njit(cache=True, inline="always")
def _block_bound(pooled, pu0, pv0, off_u, off_v, chan, bu, bv, n_points, out):
    """``_block_lower_bounds`` for one block (anchor origin (``bu``, ``bv``)) into ``out`` (D, T)."""
    for d in range(off_u.shape[1]):
        for t in range(off_u.shape[2]):
            acc = 0
            for i in range(n_points):
                acc += pooled[bv + off_v[0, d, t, i] - pv0, bu + off_u[0, d, t, i] - pu0, chan[t, i]]
            out[d, t] = acc


def _pooled_region(dt, tau_q, u0, v0, u1, v1, shift, n_shift):
    """dt[v0:v1, u0:u1] (tau_q outside the image) min-pooled over offsets {0, shift, .., (n_shift - 1)
    shift} in u and v (``n_shift`` a power of 2): (v1 - v0, u1 - u0, C) uint8, element (y, x) the min
    over dt[v0 + y + j shift, u0 + x + i shift]."""
    H, W, C = dt.shape
    ext = shift * (n_shift - 1)
    reg = np.full((v1 - v0 + ext, u1 - u0 + ext, C), tau_q, np.uint8)
    a0, a1, b0, b1 = max(v0, 0), min(v1 + ext, H), max(u0, 0), min(u1 + ext, W)
    if a1 > a0 and b1 > b0:
        reg[a0 - v0:a1 - v0, b0 - u0:b1 - u0] = dt[a0:a1, b0:b1]
    m = reg
    k = 1
    while k < n_shift:  # doubling: min over {0, s} then {0, s, 2s, 3s} ...
        step = shift * k
        m = np.minimum(m[:, :-step], m[:, step:])
        m = np.minimum(m[:-step], m[step:])
        k *= 2
    return m[:v1 - v0, :u1 - u0]


@dataclass(frozen=True)
class LevelATemplates:
    views: np.ndarray  # (Tv,) bank view index per level-A view
    phis_deg: np.ndarray  # (Tp,)
    off_u: np.ndarray  # (J, T, P) float32 level px, T = Tv * Tp (view-major)
    off_v: np.ndarray
    chan: np.ndarray  # (T, P) int32
    z_ref_mm: np.ndarray  # (J, T) depth of the reference point the offsets were projected at
    tile_uv: np.ndarray  # (J, 2) full-res px
    extent_px: float  # largest |offset| at scale 1, level px
    perimeter_px: float  # median template border length at scale 1, level px


def _level_a_views(bank: TemplateBank, view_step_deg: float) -> np.ndarray:
    """A subset of the bank's views spaced about ``view_step_deg`` apart (greedy on the sphere); for a
    revolved part only one of each mirror pair (see ``views_within``: level B tries both)."""
    z = view_dirs_obj(bank)
    chosen: list[int] = []
    cos_min = math.cos(math.radians(view_step_deg) * LEVEL_A_VIEW_SPACING)
    candidates = range(len(z))
    if bank.symmetry_axis_obj is not None:
        candidates = np.flatnonzero(z @ np.asarray(bank.symmetry_axis_obj, float) >= -1e-6)
    for n in candidates:
        if not chosen or np.max(z[chosen] @ z[n]) < cos_min:
            chosen.append(n)
    return np.array(chosen, np.int64)


def level_a_templates(bank: TemplateBank, intr: Intrinsics, image_shape: tuple[int, int], p: SearchParams,
                      *, distance_mm: float | None, z_ref_mm: float) -> LevelATemplates:
    from service.vision.estimate.edges import channel_of

    K = intr.K
    h, w = image_shape
    views = _level_a_views(bank, p.view_step_deg if bank.symmetry_axis_obj is not None
                           else p.view_step_any_deg)
    phis = np.arange(0.0, 360.0, p.inplane_step_deg)
    nj_u, nj_v = p.tiles
    tu = (np.arange(nj_u) + 0.5) * w / nj_u - 0.5
    tv = (np.arange(nj_v) + 0.5) * h / nj_v - 0.5
    tile_uv = np.array([(u, v) for v in tv for u in tu])
    P = p.points_per_template
    idx = np.stack([subsample_border(bank, int(n), P) for n in views])  # (Tv, P') may be < P
    if idx.shape[1] < P:
        idx = np.stack([np.resize(i, P) for i in idx])
    p_rel = (bank.p_obj[idx].astype(np.float64) - bank.centre_obj)  # (Tv, P, 3)
    Rv = np.einsum("fij,vjk->fvik", np.stack([Rz(f) for f in phis]), bank.R_tpl_obj[views])  # (Tp,Tv,3,3)
    Rv = Rv.transpose(1, 0, 2, 3).reshape(-1, 3, 3)  # (T, 3, 3) view-major
    p_cam0 = np.einsum("tij,tpj->tpi", Rv, np.repeat(p_rel, len(phis), axis=0))  # (T, P, 3)
    theta0 = np.mod(np.repeat(bank.theta_rad[idx], len(phis), 0)
                    + np.tile(np.deg2rad(phis), len(views))[:, None], np.pi)
    chan = channel_of(theta0, p.n_channels).astype(np.int32)
    J, T = len(tile_uv), len(Rv)
    off_u = np.empty((J, T, P), np.float32)
    off_v = np.empty((J, T, P), np.float32)
    z_ref = np.empty((J, T))
    for j, uv in enumerate(tile_uv):
        d, R_ray = ray_rotation(uv, K)
        pc = p_cam0 @ R_ray.T  # (T, P, 3) relative to the reference point
        if distance_mm is not None:
            c_rot = (R_ray @ Rv @ bank.centre_obj)[:, 2]  # (T,)
            zc = distance_mm + c_rot
        else:
            zc = np.full(T, z_ref_mm)
        centre = d[None, :] / d[2] * zc[:, None]  # (T, 3)
        uv_pts = project(pc + centre[:, None, :], K)
        off_u[j] = (uv_pts[..., 0] - uv[0]) * p.level_scale
        off_v[j] = (uv_pts[..., 1] - uv[1]) * p.level_scale
        z_ref[j] = zc
    extent = float(max(np.abs(off_u).max(), np.abs(off_v).max()))
    step = np.hypot(np.diff(off_u[0], axis=1), np.diff(off_v[0], axis=1))
    perimeter = float(np.median(step.sum(axis=1) * P / (P - 1)))
    order = spread_order(P)
    return LevelATemplates(views, phis, np.ascontiguousarray(off_u[..., order]),
                           np.ascontiguousarray(off_v[..., order]), np.ascontiguousarray(chan[:, order]),
                           z_ref, tile_uv, extent, perimeter)


def scan_level_a(dtt: DistanceTensor, tpl: LevelATemplates, scales: np.ndarray, image_shape, p: SearchParams,
                 anchor_mask: np.ndarray | None = None, deadline: Deadline = NO_DEADLINE,
                 reserve_ms: float = 0.0, level_a_cost: Callable | None = None):
    """Level A's scan. ``anchor_mask``: (h, w) bool full-resolution, where the reference point may be
    placed (a region of interest): anchors elsewhere are not scanned at all. With a ``deadline`` the
    anchors are scanned in chunks of whole blocks (``_block_chunks``), the blocks with the most edge
    pixels round one of their anchors first, until it leaves
    less than ``LEVEL_A_RESERVE_FACTOR`` x ``reserve_ms``; unscanned anchors cost inf (each anchor's
    result does not depend on the others', so a scan that finishes is the unchunked one).
    ``level_a_cost``: (quantised DT3, tau_q) -> the (H, W, C) uint8 tensor scanned instead (a blend with
    other evidence, ``contrast.py``); the edge count still reads the DT3."""
    C, hl, wl = dtt.dt.shape
    dt_q, tau_q = quantised(dtt, dtt.tau_px)
    if level_a_cost is not None:
        dt_q = level_a_cost(dt_q, tau_q)
    au, av = np.meshgrid(np.arange(0, wl, p.anchor_stride), np.arange(0, hl, p.anchor_stride))
    au, av = au.ravel().astype(np.int32), av.ravel().astype(np.int32)
    if anchor_mask is not None:
        mh, mw = anchor_mask.shape
        ui = np.clip(np.rint((au + 0.5) / p.level_scale - 0.5).astype(np.int64), 0, mw - 1)
        vi = np.clip(np.rint((av + 0.5) / p.level_scale - 0.5).astype(np.int64), 0, mh - 1)
        inside = anchor_mask[vi, ui]
        au, av = au[inside], av[inside]
    # An anchor can only win if the image has about as many edge pixels around it as a template has
    # border pixels: counting them (integral image) discards empty background before the scan.
    edges = (dtt.dt.min(axis=0) < EDGE_PIXEL_DT_PX).astype(np.int32)
    ii = np.pad(edges.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    r = max(int(tpl.extent_px * float(scales.min()) * EDGE_COUNT_EXTENT), 1)
    u0, u1 = np.clip(au - r, 0, wl), np.clip(au + r + 1, 0, wl)
    v0, v1 = np.clip(av - r, 0, hl), np.clip(av + r + 1, 0, hl)
    count = ii[v1, u1] - ii[v0, u1] - ii[v1, u0] + ii[v0, u0]
    keep = count >= p.min_edge_frac * tpl.perimeter_px * float(scales.min())
    au, av = au[keep], av[keep]
    h, w = image_shape
    nj_u, nj_v = p.tiles
    uf = (au + 0.5) / p.level_scale - 0.5
    vf = (av + 0.5) / p.level_scale - 0.5
    tile = (np.minimum((vf / h * nj_v).astype(np.int32), nj_v - 1) * nj_u
            + np.minimum((uf / w * nj_u).astype(np.int32), nj_u - 1)).astype(np.int32)
    off_u, off_v = scaled_offsets(tpl, scales)
    accept = np.int64(p.accept_frac * tau_q)
    # |rint(offset x scale)| <= ceil(extent x largest scale): the padding every placement stays within
    layout = _level_a_layout(dt_q, tau_q, int(math.ceil(tpl.extent_px * float(scales.max()))) + 1,
                             p.anchor_stride)
    if deadline.ms is None:
        cost, t, d = _scan_level_a_bands(dt_q, tau_q, off_u, off_v, tpl.chan, au, av, tile, accept,
                                          p.anchor_stride, layout)
        return au, av, tile, cost / DT_QUANT, t, d
    cost = np.full(len(au), np.inf)
    t = np.full(len(au), -1, np.int32)
    d = np.full(len(au), -1, np.int32)
    deadline.new_loop()
    for chunk in _block_chunks(au, av, tile, count[keep], p.anchor_stride):
        if not deadline.allows_next(LEVEL_A_RESERVE_FACTOR * reserve_ms):
            break
        cost[chunk], t[chunk], d[chunk] = _scan_level_a_bands(
            dt_q, tau_q, off_u, off_v, tpl.chan, au[chunk], av[chunk], tile[chunk], accept, p.anchor_stride,
            layout)
    return au, av, tile, cost / DT_QUANT, t, d


LEVEL_A_BLOCK_ANCHORS = 4  # a deadline's level-A chunks are whole blocks of 4 x 4 anchors of one tile
# Level A scans bands of this many anchor rows of one tile (``_scan_bands``). Clutter frames, level A
# total: 2 rows 7.2 s, 4 rows 5.8-6.4 s, 8 rows 4.8-5.6 s, 16 rows 4.6-5.4 s (2 threads, 16 frames); taller
# bands leave fewer bands to share between threads and waste more where a deadline's chunk skips blocks.
LEVEL_A_BAND_ROWS = 8


@nb.njit(cache=True, inline="always")
def _pass_limit(best, P, n_sentinel, sentinel):
    """The largest sum of a template's first ``n_sentinel`` points that still passes ``_placement_total``'s
    tests against the best total ``best``: partial sums only grow, so a sum passes iff it is at most this."""
    lim = min(best - 1, int(best * n_sentinel * SENTINEL_RATIO / P) + 1) if sentinel else best - 1
    while lim >= 0 and (lim >= best or (sentinel and lim * P > best * n_sentinel * SENTINEL_RATIO)):
        lim -= 1
    return lim


@nb.njit(cache=True, inline="always")
def _dtx_at(c, y, e, gx, s, Hp, Q):
    """Index in ``_level_a_layout``'s flattened DT3 of channel ``c``, padded row ``y``, padded column
    ``e`` + ``s`` x ``gx`` (stride ``s``: column x lies at x % s, x // s)."""
    return ((c * Hp + y) * s + e % s) * Q + e // s + gx


@nb.njit(parallel=True, cache=True, nogil=True)
def _scan_bands(dtx, Hp, Q, s, m, off_u, off_v, chan, band_tile, band_gy0, band_gx0, band_rows, band_cols,
                band_start, anchor_cell, accept, n_sentinel):
    """``_scan`` without a shared bound (each anchor its own best), anchors grouped in bands: anchors
    ``band_start[k]:band_start[k + 1]`` lie in tile ``band_tile[k]`` at cell ``anchor_cell`` of the
    ``band_rows[k]`` x ``band_cols[k]`` grid of stride-``s`` anchors from grid position (``band_gx0[k]``,
    ``band_gy0[k]``). ``dtx``: ``_level_a_layout``'s DT3 (padding ``m``, (C, Hp, s, Q) flattened), where
    one template point's costs at a row of grid anchors are contiguous: each template's first
    ``n_sentinel`` points are summed for the whole band a row at a time (vector instructions, no bounds
    tests), and only anchors whose sum passes read the rest. Each anchor sees the templates in ``_scan``'s
    order and keeps its own best, so the result is exactly ``_scan``'s."""
    A = anchor_cell.shape[0]
    D = off_u.shape[1]
    T = off_u.shape[2]
    P = off_u.shape[3]
    n_lb = min(n_sentinel, P)
    sentinel = 0 < n_sentinel <= P
    best_sum = np.full(A, accept * P, np.int64)
    best_t = np.full(A, -1, np.int32)
    best_d = np.full(A, -1, np.int32)
    limit = np.full(A, _pass_limit(accept * P, P, n_sentinel, sentinel), np.int64)
    for k in nb.prange(band_tile.shape[0]):
        j = band_tile[k]
        rows = band_rows[k]
        cols = band_cols[k]
        gy0 = band_gy0[k]
        gx0 = band_gx0[k]
        a0 = band_start[k]
        a1 = band_start[k + 1]
        first = np.empty(rows * cols, np.int16)  # n_lb <= LEVEL_A_SENTINEL_POINTS uint8 costs: no overflow
        for t in range(T):
            for d in range(D):
                first[:] = 0
                for i in range(n_lb):
                    row0 = _dtx_at(chan[t, i], m + off_v[j, d, t, i] + gy0 * s, m + off_u[j, d, t, i], gx0,
                                   s, Hp, Q)
                    for r in range(rows):
                        src = row0 + r * s * s * Q
                        dst = r * cols
                        # unsigned indices: numba's negative-index wrap would keep LLVM from vectorising
                        for c in range(cols):
                            first[np.uint64(dst + c)] += dtx[np.uint64(src + c)]
                for a in range(a0, a1):
                    acc = np.int64(first[np.uint64(anchor_cell[a])])
                    if acc > limit[a]:
                        continue
                    best = best_sum[a]
                    gy = gy0 + anchor_cell[a] // cols
                    gx = gx0 + anchor_cell[a] % cols
                    for i in range(n_lb, P):
                        acc += dtx[_dtx_at(chan[t, i], m + off_v[j, d, t, i] + gy * s, m + off_u[j, d, t, i],
                                           gx, s, Hp, Q)]
                        if acc >= best:
                            break
                    if acc < best:
                        best_sum[a] = acc
                        best_t[a] = t
                        best_d[a] = d
                        limit[a] = _pass_limit(acc, P, n_sentinel, sentinel)
    best_cost = np.full(A, np.inf, np.float64)
    for a in range(A):
        if best_t[a] >= 0:
            best_cost[a] = best_sum[a] / P
    return best_cost, best_t, best_d


def _scan_level_a_bands(dt_q, tau_q, off_u, off_v, chan, au, av, tile, accept, stride, layout=None):
    """``_scan(dt_q, tau_q, off_u, off_v, chan, au, av, tile, accept, LEVEL_A_SENTINEL_POINTS, False)``
    by ``_scan_bands``: the anchors (any subset of level A's stride grid) grouped per tile in bands of
    LEVEL_A_BAND_ROWS anchor rows, split where whole blocks of LEVEL_A_BLOCK_ANCHORS columns are missing
    (a deadline's chunks). Same result as the block-bounded scan it replaced; level A of the 16 clutter
    frames (1280 x 960) 16.9 -> ~5 s, of real photos (640 x 480) 2.2 x faster, of a paper frame with the
    distance given unchanged (~4 ms). ``layout``: ``_level_a_layout`` (made here when None)."""
    A = len(au)
    if A == 0:
        return np.full(0, np.inf), np.full(0, -1, np.int32), np.full(0, -1, np.int32)
    if layout is None:
        reach = int(max(np.abs(off_u).max(initial=0), np.abs(off_v).max(initial=0)))
        layout = _level_a_layout(dt_q, tau_q, reach, stride)
    dtx, Hp, Q, m = layout
    assert min(LEVEL_A_SENTINEL_POINTS, off_u.shape[3]) * 255 < 2 ** 15  # _scan_bands' int16 first sums
    gx, gy = (np.asarray(au, np.int64) // stride), (np.asarray(av, np.int64) // stride)
    band = gy // LEVEL_A_BAND_ROWS
    order = np.lexsort((gy, gx, band, tile))
    t_o, b_o, x_o, y_o = tile[order], band[order], gx[order], gy[order]
    col_block = x_o // LEVEL_A_BLOCK_ANCHORS
    cut = np.flatnonzero((np.diff(t_o) != 0) | (np.diff(b_o) != 0) | (np.diff(col_block) > 1)) + 1
    start = np.concatenate([[0], cut, [A]]).astype(np.int64)
    gx0, gy0 = np.minimum.reduceat(x_o, start[:-1]), np.minimum.reduceat(y_o, start[:-1])
    cols = np.maximum.reduceat(x_o, start[:-1]) - gx0 + 1
    rows = np.maximum.reduceat(y_o, start[:-1]) - gy0 + 1
    of = np.repeat(np.arange(len(gx0)), np.diff(start))
    cell = (y_o - gy0[of]) * cols[of] + x_o - gx0[of]
    band_tile = t_o[start[:-1]].astype(np.int32)
    c, t, d = _scan_bands(dtx, Hp, Q, stride, m, off_u, off_v, chan, band_tile, gy0, gx0, rows, cols, start,
                          cell, accept, LEVEL_A_SENTINEL_POINTS)
    cost = np.empty(A)
    ti = np.empty(A, np.int32)
    di = np.empty(A, np.int32)
    cost[order], ti[order], di[order] = c, t, d
    return cost, ti, di


def _block_ids(tile: np.ndarray, bv: np.ndarray, bu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(np.stack([tile, bv, bu], 1), axis=0, return_inverse=True)`` of non-negative integers
    (the distinct (tile, block row, block column) triples in lexicographic order, (B, 3) int64, and each
    anchor's index among them): one integer key per anchor instead of numpy's row sort (~1 ms a frame)."""
    t, v, u = (np.asarray(x, np.int64) for x in (tile, bv, bu))
    nv, nu = int(v.max()) + 1, int(u.max()) + 1
    keys, inverse = np.unique((t * nv + v) * nu + u, return_inverse=True)
    return np.stack([keys // (nv * nu), keys // nu % nv, keys % nu], 1), inverse.ravel()


def _level_a_layout(dt_q, tau_q, reach, stride) -> tuple[np.ndarray, int, int, int]:
    """(dtx, Hp, Q, m): the (H, W, C) DT3 padded by ``m`` (at least ``reach``, the largest |offset| of a
    template point: every point of an anchor on the image lands inside; padding costs ``tau_q``, as a
    point off the image does) and laid out (C, Hp, stride, Q) with x = stride * q + x % stride, flattened:
    the costs at one row of stride-grid anchors are then contiguous for every template point."""
    H, W, C = dt_q.shape
    m = int(reach) + stride
    Hp, Wp = H + 2 * m, -(-(W + 2 * m) // stride) * stride
    padded = np.full((Hp, Wp, C), tau_q, np.uint8)
    padded[m:m + H, m:m + W] = dt_q
    dtx = np.ascontiguousarray(padded.reshape(Hp, Wp // stride, stride, C).transpose(3, 0, 2, 1)).ravel()
    return dtx, Hp, Wp // stride, m


def _block_chunks(au, av, tile, count, stride) -> list[np.ndarray]:
    """Level A's anchors (indices) in chunks of whole blocks (``_scan_level_a_bands``'s) of at least
    LEVEL_A_CHUNK_ANCHORS anchors, the blocks with the most edge pixels round an anchor first: chunks of
    scattered anchors would split ``_scan_bands``' bands into many short ones (with session 23's block
    bounds a 450 ms deadline made level A 22 -> 33 ms a paper frame that way)."""
    if len(au) == 0:
        return []
    span = stride * LEVEL_A_BLOCK_ANCHORS
    _, block = _block_ids(tile, av // span, au // span)
    top = np.zeros(int(block.max()) + 1, count.dtype)
    np.maximum.at(top, block, count)
    # blocks by their best anchor's count, then each block's anchors by count: the old per-anchor order
    # within a block, and the same anchors first at block granularity
    order = np.lexsort((-count, block, -top[block]))
    ends = np.flatnonzero(np.diff(block[order])) + 1  # block boundaries in that order
    chunks, start = [], 0
    for e in [*ends.tolist(), len(order)]:
        if e - start >= LEVEL_A_CHUNK_ANCHORS or e == len(order):
            chunks.append(order[start:e])
            start = e
    return chunks


_SCALED = Memo(4)


def scaled_offsets(tpl: LevelATemplates, scales: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(J, D, T, P) int16 level-A offsets at each of the ``scales``, made once per (templates, scales):
    for a non-symmetric part searched over distance they are 2 x 16 M numbers (numpy took 0.6 s per
    frame to remake them), and a cell's camera, image size and distance range do not change."""
    sc = np.asarray(scales, np.float64)
    return _SCALED.get(tpl, tuple(sc.tolist()),
                       lambda: (_scale_offsets(tpl.off_u, sc), _scale_offsets(tpl.off_v, sc)))


@nb.njit(parallel=True, cache=True, nogil=True)
def _scale_offsets(off, scales):
    J, T, P = off.shape
    D = scales.shape[0]
    out = np.empty((J, D, T, P), np.int16)
    for j in nb.prange(J):
        for d in range(D):
            for t in range(T):
                for i in range(P):
                    out[j, d, t, i] = np.int16(np.rint(off[j, t, i] * scales[d]))
    return out


def background_cost(dtt_a: DistanceTensor, radius_lvl: int) -> np.ndarray:
    """(h, w) float64, level px: the mean over channels and over the (2 radius + 1)^2 box round each
    level-A pixel (clipped at the image border) of the DT3 truncated at its tau: the expected cost of a
    template point placed there at random, in any orientation. Low on texture, high on plain ground."""
    m = np.minimum(dtt_a.dt, dtt_a.tau_px).mean(axis=0, dtype=np.float64)
    hl, wl = m.shape
    ii = np.pad(m.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    r = max(int(radius_lvl), 1)
    v, u = np.arange(hl), np.arange(wl)
    v0, v1 = np.clip(v - r, 0, hl)[:, None], np.clip(v + r + 1, 0, hl)[:, None]
    u0, u1 = np.clip(u - r, 0, wl)[None], np.clip(u + r + 1, 0, wl)[None]
    box = ii[v1, u1] - ii[v0, u1] - ii[v1, u0] + ii[v0, u0]
    # never zero: a box inside a dense edge field still divides sensibly
    return np.maximum(box / ((v1 - v0) * (u1 - u0)), 1.0 / DT_QUANT)


def _bg_at(bg: np.ndarray, uv: np.ndarray, level_scale: float) -> np.ndarray:
    """``background_cost`` at full-resolution pixels ``uv`` (M, 2) (nearest level pixel)."""
    uv = np.atleast_2d(np.asarray(uv, float))
    u = np.clip(np.rint((uv[:, 0] + 0.5) * level_scale - 0.5).astype(np.int64), 0, bg.shape[1] - 1)
    v = np.clip(np.rint((uv[:, 1] + 0.5) * level_scale - 0.5).astype(np.int64), 0, bg.shape[0] - 1)
    return bg[v, u]


def pick_peaks(au, av, cost, n_peaks: int, radius_lvl: float) -> list[int]:
    """Indices of the lowest-cost anchors, greedily suppressing neighbours within ``radius_lvl``."""
    order = np.argsort(cost)
    order = order[np.isfinite(cost[order])]
    chosen: list[int] = []
    for a in order:
        if len(chosen) >= n_peaks:
            break
        if all((au[a] - au[b]) ** 2 + (av[a] - av[b]) ** 2 > radius_lvl ** 2 for b in chosen):
            chosen.append(int(a))
    return chosen


@nb.njit(parallel=True, cache=True, nogil=True)
def _scan_templates(dt, tau_q, off_u, off_v, chan, anchors_u, anchors_v, anchor_tile, bound_q):
    """Every template's cost at each anchor, not only the best one's (``_scan``'s arguments).

    Returns (A, T) the mean cost (1/DT_QUANT level px) of each template at its best scale and (A, T)
    int32 that scale's index; inf and -1 where no scale's total is under ``bound_q[a]`` (a template
    is abandoned once its partial sum reaches the bound or its own best total at an earlier scale)."""
    A = anchors_u.shape[0]
    D = off_u.shape[1]
    T = off_u.shape[2]
    P = off_u.shape[3]
    cost = np.full((A, T), np.inf, np.float64)
    best_d = np.full((A, T), -1, np.int32)
    for a in nb.prange(A):
        ua = anchors_u[a]
        va = anchors_v[a]
        j = anchor_tile[a]
        for t in range(T):
            best = bound_q[a]
            for d in range(D):
                acc = _placement_total(dt, tau_q, off_u, off_v, chan, j, d, t, ua, va, best, 0)
                if acc >= 0:
                    best = acc
                    cost[a, t] = acc / P
                    best_d[a, t] = d
    return cost, best_d


def template_axes(bank: TemplateBank, tpl: LevelATemplates) -> np.ndarray:
    """(T, 3, 3) rotation of each level-A template about its own viewing ray (``Rz(phi) @ R_view``,
    view-major like the templates); for a revolved part (T, 1, 3): only where its axis points."""
    Rp = np.stack([Rz(f) for f in tpl.phis_deg])
    Rv = (Rp[None] @ bank.R_tpl_obj[tpl.views][:, None]).reshape(-1, 3, 3)  # (Tv * Tp, 3, 3)
    if bank.symmetry_axis_obj is not None:
        return (Rv @ np.asarray(bank.symmetry_axis_obj, float))[:, None, :]
    return Rv


def distinct_templates(order: np.ndarray, axes: np.ndarray, k: int, min_deg: float,
                       taken: tuple[int, ...] = ()) -> list[int]:
    """The first ``k`` of the templates ``order`` (best first) whose rotations (``template_axes``) are
    more than ``min_deg`` from every one taken before (greedy), ``taken`` counting as taken already."""
    cos_min = math.cos(math.radians(min_deg))
    chosen: list[int] = [int(t) for t in taken]
    for t in order:
        if len(chosen) >= k + len(taken):
            break
        if axes.shape[1] == 1:  # a revolved part: the angle between the axes
            near = any(float(axes[t, 0] @ axes[c, 0]) > cos_min for c in chosen)
        else:  # the rotation angle of R_t R_c^T: trace = 1 + 2 cos(angle)
            near = any((float(np.sum(axes[t] * axes[c])) - 1) / 2 > cos_min for c in chosen)
        if not near:
            chosen.append(int(t))
    return chosen[len(taken):]


def peak_starts(bank: TemplateBank, tpl: LevelATemplates, scales: np.ndarray, dtt_a: DistanceTensor,
                au: np.ndarray, av: np.ndarray, cost_a: np.ndarray, t_a: np.ndarray, peaks: list[int],
                image_shape, p: SearchParams, level_a_cost: Callable | None = None) -> list[list[Hypothesis]]:
    """Per level-A peak, level B's extra starts: its best ``templates_per_peak - 1`` templates distinct
    from each other and from the peak's own level-A template ``t_a[peak]`` (``distinct_templates``),
    each scored at the peak's anchor and the anchors within ``template_anchor_reach`` strides of it and
    placed at the one where it costs least. Level A keeps each anchor's single best template only, and
    at a clutter peak near the truth that one is often another rotation (a view 60-160 degrees off)
    that level B's local scan cannot turn back from."""
    if not peaks or p.templates_per_peak <= 1:
        return [[] for _ in peaks]
    C, hl, wl = dtt_a.dt.shape
    dt_q, tau_q = quantised(dtt_a, dtt_a.tau_px)
    if level_a_cost is not None:  # the templates ranked as ``scan_level_a`` ranked them (``cost_a``)
        dt_q = level_a_cost(dt_q, tau_q)
    off_u, off_v = scaled_offsets(tpl, scales)
    r = p.template_anchor_reach * p.anchor_stride
    g = np.arange(-r, r + 1, p.anchor_stride)
    du, dv = (x.ravel() for x in np.meshgrid(g, g))
    nu = np.concatenate([np.clip(au[a] + du, 0, wl - 1) for a in peaks]).astype(np.int32)
    nv = np.concatenate([np.clip(av[a] + dv, 0, hl - 1) for a in peaks]).astype(np.int32)
    h, w = image_shape
    nj_u, nj_v = p.tiles
    uf = (nu + 0.5) / p.level_scale - 0.5
    vf = (nv + 0.5) / p.level_scale - 0.5
    tile = (np.minimum((vf / h * nj_v).astype(np.int32), nj_v - 1) * nj_u
            + np.minimum((uf / w * nj_u).astype(np.int32), nj_u - 1)).astype(np.int32)
    P = off_u.shape[3]
    # A template costing more than the peak's best + TEMPLATE_BOUND_MARGIN x tau is not ranked.
    bound = np.minimum(p.accept_frac * tau_q * P,
                       np.repeat([(cost_a[a] * DT_QUANT + TEMPLATE_BOUND_MARGIN * tau_q) * P for a in peaks],
                                 len(du)))
    cost, dk = _scan_templates(dt_q, tau_q, off_u, off_v, tpl.chan, nu, nv, tile, bound.astype(np.int64))
    axes = template_axes(bank, tpl)
    n_phi = len(tpl.phis_deg)
    out = []
    m = len(du)
    for i, pk in enumerate(peaks):
        c = cost[i * m:(i + 1) * m]  # (m, T)
        best_a = np.argmin(c, axis=0)
        c_t = c[best_a, np.arange(c.shape[1])]
        order = np.argsort(c_t, kind="stable")
        order = order[np.isfinite(c_t[order])]
        starts = []
        for ti in distinct_templates(order, axes, p.templates_per_peak - 1, p.distinct_template_deg,
                                     (int(t_a[pk]),)):
            a = i * m + int(best_a[ti])
            uv = np.array([uf[a], vf[a]])
            z = float(tpl.z_ref_mm[tile[a], ti] / scales[dk[a, ti]])
            starts.append(Hypothesis(int(tpl.views[ti // n_phi]), float(tpl.phis_deg[ti % n_phi]), z, uv))
        out.append(starts)
    return out


# --- level B: local scans around the peaks, then a sub-pixel polish --------------------------------


def poses_of(bank: TemplateBank, hs: list[Hypothesis], K: np.ndarray, distance_mm: float | None
             ) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3, 3) R and (M, 3) t of hypotheses; with a known distance the depth follows from it."""
    if not hs:
        return np.zeros((0, 3, 3)), np.zeros((0, 3))
    d, R_ray = ray_rotations(np.array([h.uv for h in hs], float), K)
    Rs = R_ray @ np.stack([Rz(h.phi_deg) for h in hs]) @ bank.R_tpl_obj[[h.view for h in hs]]
    c_rot = Rs @ bank.centre_obj  # (M, 3)
    z = (distance_mm + c_rot[:, 2]) if distance_mm is not None else np.array([h.z_mm for h in hs])
    return Rs, d / d[:, 2:3] * z[:, None] - c_rot


def evaluate(bank: TemplateBank, views: np.ndarray, Rs: np.ndarray, ts: np.ndarray, K: np.ndarray,
             dtt: DistanceTensor, n_points: int, score_px: float, tau_px: float = np.inf
             ) -> tuple[np.ndarray, np.ndarray]:
    """Mean directional chamfer cost (full-res px, each point's truncated at ``tau_px``) and support
    score of M posed templates."""
    views = np.asarray(views, np.int64)
    if not FAST_EVALUATE:
        idx_all, prev_all, nxt_all = border_triplets(bank, n_points)

        def proj(ii):
            # matmul: 10x faster than einsum here
            return project(bank.p_obj[ii].astype(np.float64) @ Rs.transpose(0, 2, 1) + ts[:, None, :], K)

        uv = proj(idx_all[views])
        d = proj(nxt_all[views]) - proj(prev_all[views])
        theta = np.mod(np.arctan2(d[..., 1], d[..., 0]), np.pi)
        val = sample(dtt, dtt.to_grid(uv), theta) / dtt.scale
        return np.minimum(val, tau_px).mean(axis=1), (val <= score_px).mean(axis=1)
    # The points, their successors and predecessors in one matmul and one projection (each row's
    # product is the separate matmuls' bit for bit), the read-out and the means compiled (sample_mean).
    p_obj, tri = _evaluate_tables(bank, n_points)
    P = tri.shape[1] // 3
    uv = project(p_obj[tri[views]] @ Rs.transpose(0, 2, 1) + ts[:, None, :], K)
    d = uv[:, P:2 * P] - uv[:, 2 * P:]
    theta = np.mod(np.arctan2(d[..., 1], d[..., 0]), np.pi)
    return sample_mean(dtt, uv[:, :P], theta, tau_px=tau_px, score_px=score_px)


FAST_EVALUATE = True
_EVALUATE_TABLES = Memo(8)


def _evaluate_tables(bank: TemplateBank, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """The bank's border points as float64 (V, 3) and, per template, ``border_triplets``' points, then
    their successors, then their predecessors: (N, 3 * n_points). Made once per bank and count."""
    def make():
        idx, prv, nxt = border_triplets(bank, n_points)
        return bank.p_obj.astype(np.float64), np.ascontiguousarray(np.concatenate([idx, nxt, prv], axis=1))

    return _EVALUATE_TABLES.get(bank, n_points, make)


@dataclass(frozen=True)
class Window:
    """A block of the local search: these views x in-plane angles x depth factors, at every
    ``stride``-th fine-grid pixel within ``radius`` (fine-grid px) of ``centre`` (full-res uv)."""

    views: np.ndarray
    phis_deg: np.ndarray
    depth_f: np.ndarray
    centre: np.ndarray
    radius: int
    stride: int


@nb.njit(cache=True, nogil=True)
def _window_offsets(p_rel, theta, Rv, zc, depth_f, ray, fx, fy, cx, cy, s, c0u, c0v, phis_rad, n_channels):
    """Templates of a local-scan window: (1, D, T, P) int16 fine-grid offsets from the window centre
    (c0u, c0v) and (T, P) int32 channels, for the Tv views' points ``p_rel`` (relative to the
    reference point) rotated by ``Rv`` (T = Tp * Tv, phi-major) and placed at depth ``zc * depth_f``
    on the unit-z ray ``ray``. Compiled: numpy's temporaries cost more than the scan itself."""
    Tv, P = theta.shape[0], theta.shape[1]
    T, D = Rv.shape[0], depth_f.shape[0]
    off_u = np.empty((1, D, T, P), np.int16)
    off_v = np.empty((1, D, T, P), np.int16)
    chan = np.empty((T, P), np.int32)
    for t in range(T):
        iv = t % Tv
        phi = phis_rad[t // Tv]
        R = Rv[t]
        for i in range(P):
            x, y, z = p_rel[iv, i, 0], p_rel[iv, i, 1], p_rel[iv, i, 2]
            qx = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z
            qy = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z
            qz = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z
            for k in range(D):
                zk = zc[t] * depth_f[k]
                X, Y, Z = qx + ray[0] * zk, qy + ray[1] * zk, qz + zk
                off_u[0, k, t, i] = np.int16(np.rint((fx * X / Z + cx + 0.5) * s - 0.5 - c0u))
                off_v[0, k, t, i] = np.int16(np.rint((fy * Y / Z + cy + 0.5) * s - 0.5 - c0v))
            a = (theta[iv, i] + phi) % np.pi
            chan[t, i] = np.int32(np.floor(a * (n_channels / np.pi) + 0.5)) % n_channels
    return off_u, off_v, chan


BLOCK_ANCHORS = 4  # level B's block bounds: blocks of 4 x 4 anchors (2 x 2 and 8 x 8 measured slower)


def _window_bounds(dt_q, tau_q, off_u, off_v, chan, au, av, gu, gv, stride):
    """``_scan_bounded``'s bounds for a local-scan window: the anchors (``au``, ``av``; grid offsets
    ``gu``, ``gv`` from the window centre, ``stride`` apart) in blocks of BLOCK_ANCHORS x BLOCK_ANCHORS,
    and per block the sum of each template's first LEVEL_B_SENTINEL_POINTS points over the DT3
    min-pooled across the block's anchor offsets: at most any of its anchors' own sums. A failing
    peak's window (nothing within the accept threshold) thus costs one read per point per block
    instead of one per anchor: level B 21 -> 10 ms a paper frame, the same placements."""
    nb_ = BLOCK_ANCHORS
    if nb_ <= 1 or off_u.shape[3] < LEVEL_B_SENTINEL_POINTS:
        return _NO_BOUNDS, _NO_BLOCKS
    iu = (gu - gu.min()) // stride // nb_
    iv = (gv - gv.min()) // stride // nb_
    nbu = int(iu.max()) + 1
    block = (iv * nbu + iu).astype(np.int32)
    nblk = int(block.max()) + 1
    bu = np.zeros(nblk, np.int32)
    bv = np.zeros(nblk, np.int32)
    bu[block] = au - (gu - gu.min()) % (stride * nb_)
    bv[block] = av - (gv - gv.min()) % (stride * nb_)
    n = LEVEL_B_SENTINEL_POINTS
    ou, ov = off_u[0, :, :, :n], off_v[0, :, :, :n]
    u0, u1 = int(bu.min()) + int(ou.min()), int(bu.max()) + int(ou.max()) + 1
    v0, v1 = int(bv.min()) + int(ov.min()), int(bv.max()) + int(ov.max()) + 1
    pooled = _pooled_region(dt_q, tau_q, u0, v0, u1, v1, stride, nb_)
    return _block_lower_bounds(pooled, u0, v0, off_u, off_v, chan, bu, bv, n), block


_WINDOW_TABLES = Memo(8)


def _window_tables(bank: TemplateBank, n_points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per bank and point count, made once: each template's ``border_triplets`` points in
    ``spread_order`` (N, P), and the bank's border points relative to its centre (V, 3) and their
    orientations (V,), float64 (what ``_window_offsets`` reads, gathered per window)."""
    def make():
        idx = border_triplets(bank, n_points)[0]
        return (np.ascontiguousarray(idx[:, spread_order(idx.shape[1])]),
                bank.p_obj.astype(np.float64) - bank.centre_obj, bank.theta_rad.astype(np.float64))

    return _WINDOW_TABLES.get(bank, n_points, make)


@functools.lru_cache(maxsize=16)
def _window_grid(radius: int, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """A window's grid offsets (du, dv) from its centre, ``stride`` apart within ``radius``, nearest the
    centre first (a tight bound early; ties in row order); made once per radius and stride (read-only)."""
    g = np.arange(-radius, radius + 1, stride)
    gu, gv = np.meshgrid(g, g)
    near_first = np.argsort(gu.ravel() ** 2 + gv.ravel() ** 2, kind="stable")
    gu, gv = gu.ravel()[near_first], gv.ravel()[near_first]
    gu.flags.writeable = gv.flags.writeable = False
    return gu, gv


def _scan_window(bank: TemplateBank, win: Window, z_mm: float, dt_q: np.ndarray, tau_q: int,
                 accept_q: int, dtt: DistanceTensor, K: np.ndarray, n_points: int, *,
                 distance_mm: float | None) -> tuple[Hypothesis | None, float, tuple[int, int, int, int]]:
    """The best placement in ``win`` by the compiled scan: (hypothesis, mean cost in 1/DT_QUANT
    fine-grid px, (view index, phi index, du, dv) within the window) or (None, inf, ...) when nothing
    beats ``accept_q``. Templates are projected exactly along the window centre's viewing ray."""
    views, phis = win.views, win.phis_deg
    spread, p_rel, theta = _window_tables(bank, n_points)
    idx = spread[views]  # (Tv, P)
    d, R_ray = ray_rotation(win.centre, K)
    Rv = (R_ray @ np.stack([Rz(f) for f in phis])[:, None] @ bank.R_tpl_obj[views][None]).reshape(-1, 3, 3)
    zc = (distance_mm + (Rv @ bank.centre_obj)[:, 2]) if distance_mm is not None else np.full(len(Rv), z_mm)
    s = dtt.scale
    c0 = np.rint((win.centre + 0.5) * s - 0.5)  # the window centre on the fine grid
    off_u, off_v, chan = _window_offsets(
        p_rel[idx], theta[idx], Rv, zc,
        np.asarray(win.depth_f, np.float64), d / d[2], K[0, 0], K[1, 1], K[0, 2], K[1, 2], s, c0[0], c0[1],
        np.deg2rad(np.asarray(phis, np.float64)), dtt.n_channels)
    gu, gv = _window_grid(win.radius, win.stride)
    au = (c0[0] + gu).astype(np.int32)
    av = (c0[1] + gv).astype(np.int32)
    lower, block = _window_bounds(dt_q, tau_q, off_u, off_v, chan, au, av, gu, gv, win.stride)
    cost, t, dk = _scan_bounded(dt_q, tau_q, off_u, off_v, chan, au, av, np.zeros(len(au), np.int32),
                                np.int64(accept_q), LEVEL_B_SENTINEL_POINTS, True, lower, block)
    a = int(np.argmin(cost))
    if not np.isfinite(cost[a]):
        return None, np.inf, (0, 0, 0, 0)
    ti = int(t[a])
    iv, iphi = ti % len(views), ti // len(views)
    uv = np.array([(au[a] + 0.5) / s - 0.5, (av[a] + 0.5) / s - 0.5])
    hyp = Hypothesis(int(views[iv]), float(phis[iphi]), float(zc[ti] * win.depth_f[dk[a]]), uv)
    return hyp, float(cost[a]), (iv, iphi, int(au[a] - c0[0]), int(av[a] - c0[1]))


def local_scan(bank: TemplateBank, h: Hypothesis, dt_q: np.ndarray, tau_q: int, dtt: DistanceTensor,
               K: np.ndarray, p: SearchParams, *, distance_mm: float | None, accept_q: int,
               max_walks: int = MAX_WALKS) -> tuple[Hypothesis | None, float]:
    """Exhaustive search around a level-A peak on the finer grid, in two blocks.

    Level A only says which basin to look in: its angle and placement can be off by half a step, which
    moves the ends of a long part by many pixels, and a shaded part's interior edges can make a
    template tilted tens of degrees too far win there. So first every bank view within
    ``local_view_deg`` of the peak's (and of its mirror for a revolved part), in-plane angles
    +-``inplane_step_deg`` and pixels within ``local_radius_px`` are tried at double steps; the block
    is re-centred while its best lies on its edge. Then the best's immediate neighbourhood is tried
    at single steps, abandoning any template that cannot beat the first block's best. Both blocks drop a
    template whose first ``LEVEL_B_SENTINEL_POINTS`` (spread) points already average ``SENTINEL_RATIO``
    times the best. Returns the
    best and its mean cost (1/DT_QUANT fine-grid px), or (None, inf) when nothing beats ``accept_q``.
    """
    s = dtt.scale
    depth_f = np.array([1.0]) if distance_mm is not None else np.array(
        [1.0, 1 + p.depth_step / 2, 1 / (1 + p.depth_step / 2)])
    step2 = p.local_phi_step_deg  # a long part's ends move fast with the angle: full angle steps here
    r = int(math.ceil(p.local_radius_px * s))
    best, best_q = h, np.inf
    z_dirs = view_dirs_obj(bank)
    for _ in range(max_walks):
        win = Window(views_within(bank, best.view, p.local_view_deg),
                     best.phi_deg + np.arange(-p.inplane_step_deg, p.inplane_step_deg + 1e-9, step2),
                     depth_f, best.uv, r, 2)
        hyp, q, (iv, iphi, du, dv) = _scan_window(bank, win, best.z_mm, dt_q, tau_q, accept_q, dtt, K,
                                                   p.scan_points, distance_mm=distance_mm)
        if hyp is None:
            break
        centre_view = best.view
        best, best_q = hyp, q
        turn = math.degrees(math.acos(min(float(z_dirs[hyp.view] @ z_dirs[centre_view]), 1.0)))
        on_edge = (turn > WALK_VIEW_EDGE * p.local_view_deg or iphi in (0, len(win.phis_deg) - 1)
                   or max(abs(du), abs(dv)) >= r - 1)
        if not on_edge:
            break
    if not np.isfinite(best_q):
        return None, np.inf
    # Fine block: neighbouring bank views, single angle and pixel steps, depth half-steps.
    near = views_within(bank, best.view, FINE_VIEW_STEPS * view_step_deg(bank))
    win = Window(near, best.phi_deg + np.arange(-step2, step2 + 1e-9, p.local_phi_step_deg / 2),
                 np.array([1.0]) if distance_mm is not None else np.array([1.0, 1 + p.depth_step / 4,
                                                                          1 / (1 + p.depth_step / 4)]),
                 best.uv, 2, 1)
    hyp, q, _ = _scan_window(bank, win, best.z_mm, dt_q, tau_q, int(math.ceil(best_q * FINE_BLOCK_SLACK)) + 1,
                             dtt, K, p.fine_points, distance_mm=distance_mm)
    return (hyp, q) if hyp is not None else (best, best_q)


def polish(bank: TemplateBank, h: Hypothesis, dtt: DistanceTensor, K: np.ndarray, p: SearchParams, *,
           distance_mm: float | None, neighbours: np.ndarray, step_phi_deg: float, step_uv_px: float,
           step_z: float, min_step_px: float = 0.25, max_iter: int = 60) -> Hypothesis:
    """Pattern search over (view, phi, z, u, v) from ``h`` on the distance tensor ``dtt``, with
    bilinear, channel-interpolated costs: sub-pixel where the scans are whole-pixel."""
    cur = h
    Rs, ts = poses_of(bank, [cur], K, distance_mm)
    cur.cost, cur.score = (float(x[0]) for x in evaluate(bank, np.array([cur.view]), Rs, ts, K, dtt,
                                                         p.fine_points, p.score_px, p.rank_tau_px))
    view_moves = True
    for _ in range(max_iter):
        moves: list[Hypothesis] = []
        for dp in (-step_phi_deg, step_phi_deg):
            moves.append(Hypothesis(cur.view, cur.phi_deg + dp, cur.z_mm, cur.uv))
        for du, dv in ((step_uv_px, 0), (-step_uv_px, 0), (0, step_uv_px), (0, -step_uv_px)):
            moves.append(Hypothesis(cur.view, cur.phi_deg, cur.z_mm, cur.uv + np.array([du, dv])))
        if distance_mm is None:
            for f in (1 + step_z, 1 / (1 + step_z)):
                moves.append(Hypothesis(cur.view, cur.phi_deg, cur.z_mm * f, cur.uv))
        if view_moves:
            for n in neighbours[cur.view]:
                moves.append(Hypothesis(int(n), cur.phi_deg, cur.z_mm, cur.uv))
        Rs, ts = poses_of(bank, moves, K, distance_mm)
        cost, score = evaluate(bank, np.array([m.view for m in moves]), Rs, ts, K, dtt, p.fine_points,
                               p.score_px, p.rank_tau_px)
        b = int(np.argmin(cost))
        if cost[b] < cur.cost - 1e-6:
            cur = moves[b]
            cur.cost, cur.score = float(cost[b]), float(score[b])
            continue
        if step_uv_px <= min_step_px:
            break
        step_phi_deg /= 2
        step_uv_px /= 2
        step_z /= 2
        # With the distance given the scans already chose the view: past the first round only fine moves.
        # Without it, tilt and depth trade off (a revolved part tilted towards the camera looks like
        # one further away) and settle together only at the fine steps: views keep moving. Paper
        # renders, distance estimated: coarse Rx 4.8 -> 2.6 deg, tz 4.8 -> 3.2 mm.
        view_moves = distance_mm is None
    return cur


def depth_scales(distance_range_mm: tuple[float, float], depth_step: float) -> tuple[float, np.ndarray]:
    """Level A's reference depth for a searched distance range (its geometric middle) and the scale
    factors of the depths tried, ``depth_step`` apart from the near end to past the far end."""
    lo, hi = distance_range_mm
    n = max(int(math.ceil(math.log(hi / lo) / math.log(1 + depth_step))), 1)
    z_ref = float(math.sqrt(lo * hi))
    return z_ref, z_ref / (lo * (1 + depth_step) ** np.arange(n + 1))


def coarse_search(bank: TemplateBank, dtt_b: DistanceTensor, intr: Intrinsics,
                  image_shape: tuple[int, int], p: SearchParams, *, distance_mm: float | None,
                  distance_range_mm: tuple[float, float], anchor_mask: np.ndarray | None = None,
                  deadline: Deadline = NO_DEADLINE, reserve_ms: float = 0.0,
                  deferred: list[Callable[[], list[Hypothesis]]] | None = None,
                  contrast=None, extra_peaks: int = 0) -> list[Hypothesis]:
    """Ranked, polished, mutually distinct hypotheses (best first). ``dtt_b`` is the DT3 at
    ``fine_scale``; level A's grid is min-pooled from it. ``anchor_mask`` (full-resolution (h, w)
    bool): level A places the reference point only there (``scan_level_a``).

    Two passes: level B from each level-A peak's own template, then (``templates_per_peak`` > 1) from
    its other distinct templates (``peak_starts``), each pass polishing its best ``n_polish``. With a
    ``deferred`` list the second pass is not run here: a callable running it (and returning its
    hypotheses, ranked) is appended to the list, for a caller that needs it only when the first
    pass's hypotheses all fail verification (``pipeline.estimate``); without, both passes' hypotheses
    are returned together, ranked.

    Anytime: each unit of work (a chunk of level-A anchors, a peak's local scan, a polish) starts only
    while the ``deadline`` leaves more than ``reserve_ms`` (the caller's time to verify a result); what
    was reached by then is returned, hypotheses left unpolished with their level-B costs.

    ``contrast`` (``contrast.Contrast``): level A scans its blend of DT3 and oriented contrast instead
    of the DT3, and level B its blend at ``fine_scale`` (``weight_b`` > 0). With ``extra_peaks`` > 0
    the first pass is unchanged and the second pass adds ``_contrast_pass``'s hypotheses."""
    K = intr.K
    dtt_a, dt_q, tau_q = pooled_and_quantised(dtt_b, p.level_scale, p.rank_tau_px * dtt_b.scale)
    z_ref, scales = (distance_mm, np.array([1.0])) if distance_mm is not None else \
        depth_scales(distance_range_mm, p.depth_step)
    if deadline.ms is None:
        tpl = _cached_level_a(bank, intr, image_shape, p, distance_mm, z_ref)
    else:
        tpl = _level_a_in_time(bank, intr, image_shape, p, distance_mm, z_ref, scales, deadline,
                               LEVEL_A_RESERVE_FACTOR * reserve_ms)
        if tpl is None:
            return []
    r_bg = int(BG_WINDOW_EXTENT * tpl.extent_px * float(np.median(scales)))
    lac = None if contrast is None else (lambda q, tq: contrast.level_a(q, tq, r_bg))
    au, av, tile, cost, t, d = scan_level_a(dtt_a, tpl, scales, image_shape, p, anchor_mask, deadline,
                                            reserve_ms, None if extra_peaks else lac)
    radius = max(PEAK_RADIUS_EXTENT * tpl.extent_px * float(np.median(scales)), MIN_PEAK_RADIUS_PX)
    bg = background_cost(dtt_a, r_bg) if p.bg_norm else None
    rank_a = cost / bg[av, au] if bg is not None else cost
    peaks = pick_peaks(au, av, rank_a, p.n_peaks, radius)
    n_phi = len(tpl.phis_deg)

    def start_of(a, t, d) -> Hypothesis:
        ti = int(t[a])
        uv = np.array([(au[a] + 0.5) / p.level_scale - 0.5, (av[a] + 0.5) / p.level_scale - 0.5])
        return Hypothesis(int(tpl.views[ti // n_phi]), float(tpl.phis_deg[ti % n_phi]),
                          float(tpl.z_ref_mm[tile[a], ti] / scales[d[a]]), uv)

    starts = [start_of(a, t, d) for a in peaks]
    if not starts:
        return []
    if contrast is not None and not extra_peaks and contrast.weight_b > 0:
        # level B on the blend too (its own tensors: the DT3 itself stays what refinement reads)
        dtt_b = contrast.fine_tensor(dtt_b, p.rank_tau_px * dtt_b.scale, r_bg / p.level_scale)
        dt_q, tau_q = quantised(dtt_b, p.rank_tau_px * dtt_b.scale)
    state = _LevelB(bank, dtt_b, dt_q, tau_q, K, p, distance_mm, bg, deadline, reserve_ms)
    out = state.run(starts)
    if p.templates_per_peak <= 1 and not (extra_peaks and lac is not None):
        return out

    def second() -> list[Hypothesis]:
        found: list[Hypothesis] = []
        if extra_peaks and lac is not None:
            found = _contrast_pass(bank, dtt_b, dtt_a, tpl, scales, image_shape, K, p, distance_mm,
                                   anchor_mask, deadline, reserve_ms, contrast, lac, bg, peaks, au, av,
                                   radius, r_bg, extra_peaks, start_of)
        more: list[Hypothesis] = []
        if p.templates_per_peak > 1:
            # Each peak's second distinct template first, then each one's third, ...: the deadline
            # reaches every peak's best alternative before any peak's next.
            extra = peak_starts(bank, tpl, scales, dtt_a, au, av, cost, t, peaks[:p.template_peaks],
                                image_shape, p)
            for rank in range(p.templates_per_peak - 1):
                more += [s[rank] for s in extra if len(s) > rank]
        return sorted(found + state.run(more), key=lambda h: h.rank_cost)

    if deferred is not None:
        deferred.append(second)
        return out
    return sorted(out + second(), key=lambda h: h.rank_cost)


# Each contrast peak's other distinct templates start level B too (``peak_starts`` on the blend): clutter2
# truth in the proposals 4 -> 6 of 30 with them, 4 without (``bench/stages.py --contrast-extra 12``).
CONTRAST_TEMPLATES = True


def _contrast_pass(bank, dtt_b, dtt_a, tpl, scales, image_shape, K, p, distance_mm, anchor_mask, deadline,
                   reserve_ms, contrast, lac, bg, peaks, au, av, radius, r_bg, n_extra, start_of
                   ) -> list[Hypothesis]:
    """Level A rescanned on ``lac``'s blend of DT3 and contrast: its best ``n_extra`` peaks farther than
    ``radius`` from every one of ``peaks`` (the anchors are the first scan's: the edge count that
    selects them reads the DT3 alone), each searched by level B on the blend at ``fine_scale``
    (``contrast.fine_tensor``) in a level B of their own: not gated by the first pass's best cost."""
    au2, av2, _, cost2, t2, d2 = scan_level_a(dtt_a, tpl, scales, image_shape, p, anchor_mask, deadline,
                                              reserve_ms, lac)
    assert np.array_equal(au2, au) and np.array_equal(av2, av)
    rank2 = cost2 / bg[av, au] if bg is not None else cost2
    taken = np.array([[au[a], av[a]] for a in peaks], float).reshape(-1, 2)
    far = np.all(np.hypot(au[:, None] - taken[None, :, 0], av[:, None] - taken[None, :, 1]) > radius, axis=1)
    extra = pick_peaks(au, av, np.where(far, rank2, np.inf), n_extra, radius)
    if not extra:
        return []
    tau_fine = p.rank_tau_px * dtt_b.scale
    dtt_c = contrast.fine_tensor(dtt_b, tau_fine, r_bg / p.level_scale) if contrast.weight_b > 0 else dtt_b
    dt_qc, tau_qc = quantised(dtt_c, tau_fine)
    state = _LevelB(bank, dtt_c, dt_qc, tau_qc, K, p, distance_mm, bg, deadline, reserve_ms)
    starts = [start_of(a, t2, d2) for a in extra]
    if CONTRAST_TEMPLATES:
        others = peak_starts(bank, tpl, scales, dtt_a, au, av, cost2, t2, extra, image_shape, p, lac)
        for rank in range(p.templates_per_peak - 1):
            starts += [o[rank] for o in others if len(o) > rank]
    return state.run(starts)


class _LevelB:
    """Level B of one frame's search, run on batches of starts (``coarse_search``'s passes): each
    start's local scan, accepted within ``peak_accept_ratio`` of the best so far over all batches
    (over its background with ``bg_norm``), then the batch's best ``n_polish`` polished."""

    def __init__(self, bank, dtt_b, dt_q, tau_q, K, p: SearchParams, distance_mm, bg, deadline: Deadline,
                 reserve_ms: float):
        self.bank, self.dtt_b, self.dt_q, self.tau_q, self.K, self.p = bank, dtt_b, dt_q, tau_q, K, p
        self.distance_mm, self.bg, self.deadline, self.reserve_ms = distance_mm, bg, deadline, reserve_ms
        self.best_q = np.inf  # the best cost so far (over its background with bg_norm)

    def bg_of(self, hs: list[Hypothesis]) -> np.ndarray:
        if self.bg is None or not hs:
            return np.ones(len(hs))
        return _bg_at(self.bg, np.array([x.uv for x in hs]), self.p.level_scale)

    def run(self, starts: list[Hypothesis]) -> list[Hypothesis]:
        p, bank, K, dtt_b, deadline = self.p, self.bank, self.K, self.dtt_b, self.deadline
        scanned: list[Hypothesis] = []
        deadline.new_loop()
        for h in starts:
            if not deadline.allows_next(self.reserve_ms):
                break
            # A peak whose neighbourhood cannot come near the best so far would never be reported first.
            accept = int(min(self.tau_q, p.peak_accept_ratio * self.best_q * float(self.bg_of([h])[0])))
            hyp, q = local_scan(bank, h, self.dt_q, self.tau_q, dtt_b, K, p, distance_mm=self.distance_mm,
                                accept_q=accept)
            if hyp is not None:
                scanned.append(hyp)
                self.best_q = min(self.best_q, q / float(self.bg_of([hyp])[0]))
        if not scanned:
            return []
        Rs, ts = poses_of(bank, scanned, K, self.distance_mm)
        cost_b, score_b = evaluate(bank, np.array([h.view for h in scanned]), Rs, ts, K, dtt_b, p.fine_points,
                                   p.score_px, p.rank_tau_px)
        order = np.argsort(cost_b / self.bg_of(scanned))[:p.n_polish]
        neighbours = view_neighbours(bank)
        out = []
        deadline.new_loop()
        for i in order:
            if deadline.allows_next(self.reserve_ms):
                out.append(polish(bank, scanned[i], dtt_b, K, p, distance_mm=self.distance_mm,
                                  neighbours=neighbours, step_phi_deg=p.local_phi_step_deg / 2,
                                  step_uv_px=1.0 / dtt_b.scale, step_z=p.depth_step / 4))
            else:
                h = scanned[i]
                h.cost, h.score = float(cost_b[i]), float(score_b[i])
                out.append(h)
        for h, b in zip(out, self.bg_of(out), strict=True):
            h.rank_cost = h.cost / float(b)
        out.sort(key=lambda h: h.rank_cost)
        return out


_LEVEL_A = Memo(8)
_MAKING: dict = {}  # level-A tables being made in the background, by their memo key
_MAKING_LOCK = threading.Lock()


def _level_a_in_time(bank, intr, image_shape, p, distance_mm, z_ref, scales, deadline: Deadline,
                     reserve_ms: float) -> LevelATemplates | None:
    """The level-A templates and their ``scaled_offsets`` (made once per bank, camera, image size and
    distance: ~50-150 ms, in no unit of work the deadline checks), or None when the ``deadline``, less
    ``reserve_ms``, comes first (never before the frame's first check): they are then made in the
    background, waited for until then, and ready for a later frame (the deadline is marked hit)."""
    key = _level_a_key(intr, image_shape, p, distance_mm, z_ref)
    tpl = _LEVEL_A.peek(bank, key)
    sc = tuple(np.asarray(scales, np.float64).tolist())
    if tpl is not None and _SCALED.peek(tpl, sc) is not None:
        return tpl

    def make() -> LevelATemplates:
        try:
            tables = _cached_level_a(bank, intr, image_shape, p, distance_mm, z_ref)
            scaled_offsets(tables, scales)
            return tables
        finally:
            with _MAKING_LOCK:
                _MAKING.pop((id(bank), key, sc), None)

    with _MAKING_LOCK:
        fut = _MAKING.get((id(bank), key, sc))
        if fut is None:
            fut = _MAKING[(id(bank), key, sc)] = threads.background().submit(make)
    if deadline.checks == 0:  # the first proposal is owed whatever the time (``Deadline.allows_first``)
        return fut.result()
    try:
        return fut.result(timeout=max(deadline.left_ms() - reserve_ms, 0.0) / 1000.0)
    except concurrent.futures.TimeoutError:
        deadline.mark_hit()
        return None


def _level_a_key(intr, image_shape, p, distance_mm, z_ref) -> tuple:
    # Keyed on the fields level_a_templates reads: a region of interest or more instances change only
    # the peak and polish counts, and must not make the templates again.
    fields = (p.n_channels, p.level_scale, p.inplane_step_deg, p.view_step_deg, p.view_step_any_deg, p.tiles,
              p.points_per_template)
    return (intr, tuple(image_shape), fields, distance_mm, z_ref)


def _cached_level_a(bank, intr, image_shape, p, distance_mm, z_ref) -> LevelATemplates:
    """Level-A templates depend only on the bank, the camera, the image size and the distance: a
    cell's camera and distance rarely change between frames, so they are made once per camera."""
    return _LEVEL_A.get(bank, _level_a_key(intr, image_shape, p, distance_mm, z_ref),
                        lambda: level_a_templates(bank, intr, image_shape, p, distance_mm=distance_mm,
                                                  z_ref_mm=z_ref))
