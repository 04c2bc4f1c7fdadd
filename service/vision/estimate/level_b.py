"""Level B of the coarse search (``coarse``): around a level-A peak, a compiled exhaustive scan of the
nearby views, in-plane angles, depths and pixels at ``fine_scale``, and the sub-pixel polish of the
best placements with exact perspective projection of the templates' 3D border points."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from service.vision.bank import (
    TemplateBank,
    border_triplets,
    spread_order,
    view_dirs_obj,
    view_step_deg,
    views_within,
)
from service.vision.estimate.chamfer import DistanceTensor, sample_mean
from service.vision.estimate.scan import (
    _NO_BLOCKS,
    _NO_BOUNDS,
    LEVEL_B_SENTINEL_POINTS,
    _block_lower_bounds,
    _pooled_region,
    _scan_bounded,
)
from service.vision.estimate.search import Hypothesis, SearchParams, poses_of
from service.vision.geometry.camera import project, ray_rotation
from service.vision.geometry.frames import Rz
from service.vision.memo import Memo

# Level B's first block is re-centred (at most MAX_WALKS times) while its best lies on the block's
# edge: a view turned more than this fraction of local_view_deg, the first or last angle, the border.
WALK_VIEW_EDGE = 0.6
MAX_WALKS = 3
FINE_VIEW_STEPS = 1.5  # level B's fine block: bank views within this many grid steps of the best
# The fine block contains the first block's best, so it finds at least as good a placement unless the
# denser sampling raises that one's cost by more than this factor.
FINE_BLOCK_SLACK = 1.25


def evaluate(bank: TemplateBank, views: np.ndarray, Rs: np.ndarray, ts: np.ndarray, K: np.ndarray,
             dtt: DistanceTensor, n_points: int, score_px: float, tau_px: float = np.inf
             ) -> tuple[np.ndarray, np.ndarray]:
    """Mean directional chamfer cost (full-res px, each point's truncated at ``tau_px``) and support
    score of M posed templates (``reference/evaluate.evaluate_numpy``'s bits)."""
    views = np.asarray(views, np.int64)
    # The points, their successors and predecessors in one matmul and one projection (each row's
    # product is the separate matmuls' bit for bit), the read-out and the means compiled (sample_mean).
    p_obj, tri = _evaluate_tables(bank, n_points)
    P = tri.shape[1] // 3
    uv = project(p_obj[tri[views]] @ Rs.transpose(0, 2, 1) + ts[:, None, :], K)
    d = uv[:, P:2 * P] - uv[:, 2 * P:]
    theta = np.mod(np.arctan2(d[..., 1], d[..., 0]), np.pi)
    return sample_mean(dtt, uv[:, :P], theta, tau_px=tau_px, score_px=score_px)
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
