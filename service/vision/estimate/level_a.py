"""Level A of the coarse search (``coarse``): every out-of-plane view x in-plane rotation x distance tried
at every anchor of DT3 min-pooled to ``level_scale``, its peaks, and the distinct templates a peak may
start level B from."""

from __future__ import annotations

import concurrent.futures
import math
import threading
from dataclasses import dataclass

import numba as nb
import numpy as np

from service.vision import threads
from service.vision.bank import TemplateBank, spread_order, subsample_border, view_dirs_obj
from service.vision.deadline import NO_DEADLINE, Deadline
from service.vision.estimate.chamfer import DT_QUANT, DistanceTensor, quantised
from service.vision.estimate.scan import LEVEL_A_SENTINEL_POINTS, SENTINEL_RATIO, _placement_total
from service.vision.estimate.search import Hypothesis, SearchParams
from service.vision.geometry.camera import Intrinsics, project, ray_rotation
from service.vision.geometry.frames import Rz
from service.vision.memo import Memo

# Level A keeps views at least this fraction of its view step apart (greedy on the view sphere).
LEVEL_A_VIEW_SPACING = 0.75
# Level A's edge count: a pixel is an edge pixel where some channel's DT3 is under this (level px) ...
EDGE_PIXEL_DT_PX = 0.75
EDGE_COUNT_EXTENT = 0.8  # ... counted within this fraction of the templates' extent round an anchor
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
                 reserve_ms: float = 0.0):
    """Level A's scan. ``anchor_mask``: (h, w) bool full-resolution, where the reference point may be
    placed (a region of interest): anchors elsewhere are not scanned at all. With a ``deadline`` the
    anchors are scanned in chunks of whole blocks (``_block_chunks``), the blocks with the most edge
    pixels round one of their anchors first, until it leaves
    less than ``LEVEL_A_RESERVE_FACTOR`` x ``reserve_ms``; unscanned anchors cost inf (each anchor's
    result does not depend on the others', so a scan that finishes is the unchunked one)."""
    C, hl, wl = dtt.dt.shape
    dt_q, tau_q = quantised(dtt, dtt.tau_px)
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
    scattered anchors would split ``_scan_bands``' bands into many short ones (a 450 ms deadline made
    level A 22 -> 33 ms a paper frame that way)."""
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
                image_shape, p: SearchParams) -> list[list[Hypothesis]]:
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
