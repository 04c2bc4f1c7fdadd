"""The compiled scans both levels of the coarse search run: every template placement's directional
chamfer total over a quantised DT3, with early termination against the best so far and optional
lower bounds per block of anchors."""

from __future__ import annotations

import numba as nb
import numpy as np

# Early termination (``_scan``): a template is dropped once its first points, taken in spread order
# round its border, already average this many times the best mean so far ...
SENTINEL_RATIO = 1.2
LEVEL_A_SENTINEL_POINTS = 8  # ... judged on this many points at level A (32 per template)
LEVEL_B_SENTINEL_POINTS = 16  # ... and in level B's scans (80 and 160 per template)


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
# (Timings: docs/detection-history.md, bench/launches.py --ab.)
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
