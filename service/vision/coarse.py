"""Coarse pose by directional chamfer matching over the whole image (paper section II.B).

Search, coarse to fine:
1. level A (the image at ``level_scale``, e.g. 1/4): every out-of-plane view x in-plane rotation x
   distance is tried at every anchor (stride ``anchor_stride``) by a compiled scan with early
   termination (a template is abandoned once its partial sum exceeds the anchor's best so far); the
   image is split into tiles so each tile uses the template shape seen along its own viewing ray;
2. level B (``fine_scale``, e.g. 1/2): the best distinct peaks are polished by a local pattern
   search over (view, in-plane angle, distance, position) with exact perspective projection of the
   templates' 3D border points.

A hypothesis becomes a 6D pose without assuming the object sits on the optical axis: with the
reference point seen at pixel ``uv`` (viewing ray ``r``), ``R = R_between(e_z, r) @ Rz(phi) @ R_view``
and the reference point lies on ``r`` at depth ``z``, so the coarse rotation is right at the image
corners too.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, replace

import numba as nb
import numpy as np

from service.vision.bank import TemplateBank
from service.vision.camera import Intrinsics
from service.vision.chamfer import DistanceTensor, sample
from service.vision.frames import Pose, R_between, Rz

E_Z = np.array([0.0, 0.0, 1.0])
DT_QUANT = 8  # level-A DT3 stored as uint8 in 1/8 px: 4x less memory traffic than float32


@dataclass(frozen=True)
class SearchParams:
    n_channels: int = 16
    level_scale: float = 0.25
    fine_scale: float = 0.5
    inplane_step_deg: float = 10.0
    view_step_deg: float = 6.0  # out-of-plane spacing used at level A (the bank may be finer)
    depth_step: float = 0.08  # ratio between successive distances tried at level A
    anchor_stride: int = 2  # level-A pixels
    points_per_template: int = 48
    fine_points: int = 160
    tiles: tuple[int, int] = (4, 3)
    n_peaks: int = 12
    n_polish: int = 4
    accept_frac: float = 0.5  # level A: a template must average under this fraction of tau
    unknown_depth_step: float = 0.15  # ratio between distances tried when the distance is not given
    min_edge_frac: float = 0.3  # level A: edge pixels near an anchor, as a fraction of a border's length
    score_px: float = 3.0  # full-resolution px: a border point is "supported" within this distance


@dataclass
class Hypothesis:
    view: int
    phi_deg: float
    z_mm: float  # depth (camera z) of the bank's reference point centre_obj
    uv: np.ndarray  # (2,) full-resolution pixel of the reference point
    cost: float = np.inf  # mean directional chamfer distance, full-resolution px
    score: float = 0.0


# --- geometry of a hypothesis ----------------------------------------------------------------------


def ray_rotation(uv: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit viewing ray through pixel uv and the smallest rotation taking e_z onto it."""
    d = np.array([(uv[0] - K[0, 2]) / K[0, 0], (uv[1] - K[1, 2]) / K[1, 1], 1.0])
    d /= np.linalg.norm(d)
    return d, R_between(E_Z, d)


def depth_for_distance(bank: TemplateBank, R: np.ndarray, distance_mm: float) -> float:
    """Depth of centre_obj when the object origin is at camera z = distance_mm."""
    return float(distance_mm + (R @ bank.centre_obj)[2])


def subsample_border(bank: TemplateBank, n: int, count: int) -> np.ndarray:
    """Indices of ``count`` points spread evenly along template n's border."""
    s = bank.points(n)
    m = s.stop - s.start
    if m <= count:
        return np.arange(s.start, s.stop)
    return s.start + np.linspace(0, m, count, endpoint=False).astype(np.int64)


def project_border(bank: TemplateBank, idx: np.ndarray, pose: Pose, K: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Border points ``idx`` at ``pose``: (M, 2) uv full-res px and (M,) image orientation rad.

    The orientation comes from projecting each point's neighbours along the template border, so it
    follows perspective and off-axis placement exactly.
    """
    p = bank.p_obj[idx].astype(np.float64) @ pose.R.T + pose.t_mm
    uv = np.stack([K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2], K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]], 1)
    theta = border_orientation(bank, idx, pose, K)
    return uv, theta


def border_orientation(bank: TemplateBank, idx: np.ndarray, pose: Pose, K: np.ndarray) -> np.ndarray:
    view = np.searchsorted(bank.offsets, idx, side="right") - 1
    lo, hi = bank.offsets[view], bank.offsets[view + 1]
    prev = np.where(idx - 1 >= lo, idx - 1, hi - 1)
    nxt = np.where(idx + 1 < hi, idx + 1, lo)
    a = bank.p_obj[prev].astype(np.float64) @ pose.R.T + pose.t_mm
    b = bank.p_obj[nxt].astype(np.float64) @ pose.R.T + pose.t_mm
    du = K[0, 0] * (b[:, 0] / b[:, 2] - a[:, 0] / a[:, 2])
    dv = K[1, 1] * (b[:, 1] / b[:, 2] - a[:, 1] / a[:, 2])
    return np.mod(np.arctan2(dv, du), np.pi)


# --- level A: exhaustive scan ----------------------------------------------------------------------


@nb.njit(parallel=True, cache=True)
def _scan(dt, pad, off_u, off_v, chan, anchors_u, anchors_v, anchor_tile, accept, n_sentinel):
    """For every anchor, the best (template, scale) by mean DT3 over template points.

    dt: (Hp, Wp, C) uint8 (DT3 in 1/DT_QUANT pixels, pixel-major so a template's neighbouring points
    share cache lines) padded by ``pad`` on every side; off_u/off_v: (J, D, T, P) int16 offsets in
    level pixels of template t at scale d in tile j; chan: (T, P) int32.
    Returns best mean cost (A,), template (A,), scale index (A,). A template is abandoned as soon as
    its partial sum reaches the anchor's best total (all terms are >= 0), or when its first
    ``n_sentinel`` points already average 1.5x the best mean.
    """
    A = anchors_u.shape[0]
    D = off_u.shape[1]
    T = off_u.shape[2]
    P = off_u.shape[3]
    best_cost = np.full(A, np.inf, np.float64)
    best_t = np.full(A, -1, np.int32)
    best_d = np.full(A, -1, np.int32)
    for a in nb.prange(A):
        ua = anchors_u[a] + pad
        va = anchors_v[a] + pad
        j = anchor_tile[a]
        best = accept * P
        bt = -1
        bd = -1
        for t in range(T):
            for d in range(D):
                acc = 0
                ok = True
                for i in range(P):
                    acc += dt[va + off_v[j, d, t, i], ua + off_u[j, d, t, i], chan[t, i]]
                    if acc >= best:
                        ok = False
                        break
                    if i + 1 == n_sentinel and acc * P > best * n_sentinel * 1.5:
                        ok = False
                        break
                if ok:
                    best = acc
                    bt = t
                    bd = d
        if bt >= 0:
            best_cost[a] = best / P
            best_t[a] = bt
            best_d[a] = bd
    return best_cost, best_t, best_d


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
    """A subset of the bank's views spaced about ``view_step_deg`` apart (greedy on the sphere)."""
    z = bank.R_tpl_obj.transpose(0, 2, 1) @ E_Z  # viewing direction in the object frame
    chosen: list[int] = []
    cos_min = math.cos(math.radians(view_step_deg) * 0.75)
    for n in range(len(z)):
        if not chosen or np.max(z[chosen] @ z[n]) < cos_min:
            chosen.append(n)
    return np.array(chosen, np.int64)


def level_a_templates(bank: TemplateBank, intr: Intrinsics, image_shape: tuple[int, int], p: SearchParams,
                      *, distance_mm: float | None, z_ref_mm: float) -> LevelATemplates:
    from service.vision.edges import channel_of

    K = intr.K
    h, w = image_shape
    views = _level_a_views(bank, p.view_step_deg)
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
        q = pc + centre[:, None, :]
        u = K[0, 0] * q[..., 0] / q[..., 2] + K[0, 2]
        v = K[1, 1] * q[..., 1] / q[..., 2] + K[1, 2]
        off_u[j] = (u - uv[0]) * p.level_scale
        off_v[j] = (v - uv[1]) * p.level_scale
        z_ref[j] = zc
    extent = float(max(np.abs(off_u).max(), np.abs(off_v).max()))
    step = np.hypot(np.diff(off_u[0], axis=1), np.diff(off_v[0], axis=1))
    perimeter = float(np.median(step.sum(axis=1) * P / (P - 1)))
    return LevelATemplates(views, phis, off_u, off_v, chan, z_ref, tile_uv, extent, perimeter)


def scan_level_a(dtt: DistanceTensor, tpl: LevelATemplates, scales: np.ndarray, image_shape, p: SearchParams):
    C, hl, wl = dtt.dt.shape
    pad = int(math.ceil(tpl.extent_px * float(scales.max()))) + 2
    tau_q = int(round(dtt.tau_px * DT_QUANT))
    dt_pad = np.full((hl + 2 * pad, wl + 2 * pad, C), tau_q, np.uint8)
    dt_pad[pad:pad + hl, pad:pad + wl] = np.rint(dtt.dt.transpose(1, 2, 0) * DT_QUANT).astype(np.uint8)
    au, av = np.meshgrid(np.arange(0, wl, p.anchor_stride), np.arange(0, hl, p.anchor_stride))
    au, av = au.ravel().astype(np.int32), av.ravel().astype(np.int32)
    # An anchor can only win if the image has about as many edge pixels around it as a template has
    # border pixels: counting them (integral image) discards empty background before the scan.
    edges = (dtt.dt.min(axis=0) < 0.75).astype(np.int32)
    ii = np.pad(edges.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    r = max(int(tpl.extent_px * float(scales.min()) * 0.8), 1)
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
    off_u = np.rint(tpl.off_u[:, None] * scales[None, :, None, None]).astype(np.int16)
    off_v = np.rint(tpl.off_v[:, None] * scales[None, :, None, None]).astype(np.int16)
    cost, t, d = _scan(dt_pad, pad, off_u, off_v, tpl.chan, au, av, tile,
                       np.int64(p.accept_frac * tau_q), 8)
    return au, av, tile, cost / DT_QUANT, t, d


def distance_tensor_from_edges_scaled(dtt: DistanceTensor, scale: float) -> DistanceTensor:
    """A coarser DT3 by min-pooling (an edge anywhere in a cell counts), distances rescaled."""
    f = int(round(dtt.scale / scale))
    if f <= 1:
        return dtt
    C, h, w = dtt.dt.shape
    hh, ww = h // f, w // f
    pooled = dtt.dt[:, :hh * f, :ww * f].reshape(C, hh, f, ww, f).min(axis=(2, 4)) / f
    return DistanceTensor(np.ascontiguousarray(pooled, np.float32), scale, dtt.origin_uv, dtt.tau_px / f,
                          dtt.lambda_px / f)


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


# --- level B: local polish -------------------------------------------------------------------------


def _border_triplets(bank: TemplateBank, view: int, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    idx = subsample_border(bank, view, count)
    if len(idx) < count:
        idx = np.resize(idx, count)
    lo, hi = bank.offsets[view], bank.offsets[view + 1]
    prev = np.where(idx - 1 >= lo, idx - 1, hi - 1)
    nxt = np.where(idx + 1 < hi, idx + 1, lo)
    return idx, prev, nxt


def poses_of(bank: TemplateBank, hs: list[Hypothesis], K: np.ndarray, distance_mm: float | None
             ) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3, 3) R and (M, 3) t of hypotheses; with a known distance the depth follows from it."""
    Rs = np.empty((len(hs), 3, 3))
    ts = np.empty((len(hs), 3))
    for i, h in enumerate(hs):
        d, R_ray = ray_rotation(h.uv, K)
        R = R_ray @ Rz(h.phi_deg) @ bank.R_tpl_obj[h.view]
        z = depth_for_distance(bank, R, distance_mm) if distance_mm is not None else h.z_mm
        Rs[i] = R
        ts[i] = d / d[2] * z - R @ bank.centre_obj
    return Rs, ts


def evaluate(bank: TemplateBank, views: np.ndarray, Rs: np.ndarray, ts: np.ndarray, K: np.ndarray,
             dtt: DistanceTensor, n_points: int, score_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean directional chamfer cost (full-res px) and support score of M posed templates."""
    trip = [_border_triplets(bank, int(v), n_points) for v in views]
    idx = np.stack([t[0] for t in trip])
    prev = np.stack([t[1] for t in trip])
    nxt = np.stack([t[2] for t in trip])

    def proj(ii):
        q = np.einsum("mij,mpj->mpi", Rs, bank.p_obj[ii].astype(np.float64)) + ts[:, None, :]
        u = K[0, 0] * q[..., 0] / q[..., 2] + K[0, 2]
        return np.stack([u, K[1, 1] * q[..., 1] / q[..., 2] + K[1, 2]], -1)

    uv = proj(idx)
    d = proj(nxt) - proj(prev)
    theta = np.mod(np.arctan2(d[..., 1], d[..., 0]), np.pi)
    val = sample(dtt, dtt.to_grid(uv), theta) / dtt.scale
    return val.mean(axis=1), (val <= score_px).mean(axis=1)


def view_neighbours(bank: TemplateBank, k: int = 6) -> np.ndarray:
    """(N, k) the k nearest other views by viewing direction (object frame)."""
    z = bank.R_tpl_obj.transpose(0, 2, 1) @ E_Z
    sim = z @ z.T
    np.fill_diagonal(sim, -np.inf)
    k = min(k, len(z) - 1)
    return np.argsort(-sim, axis=1)[:, :k]


def polish(bank: TemplateBank, h: Hypothesis, dtt: DistanceTensor, K: np.ndarray, p: SearchParams, *,
           distance_mm: float | None, neighbours: np.ndarray, min_step_px: float = 0.25,
           max_iter: int = 60) -> Hypothesis:
    """Pattern search over (view, phi, z, u, v) from ``h`` on the distance tensor ``dtt``."""
    step_phi = p.inplane_step_deg / 2
    step_uv = 1.0 / p.level_scale
    step_z = p.depth_step / 2
    cur = h
    Rs, ts = poses_of(bank, [cur], K, distance_mm)
    cur.cost, cur.score = (float(x[0]) for x in evaluate(bank, np.array([cur.view]), Rs, ts, K, dtt,
                                                         p.fine_points, p.score_px))
    view_moves = True
    for _ in range(max_iter):
        moves: list[Hypothesis] = []
        for dp in (-step_phi, step_phi):
            moves.append(Hypothesis(cur.view, cur.phi_deg + dp, cur.z_mm, cur.uv))
        for du, dv in ((step_uv, 0), (-step_uv, 0), (0, step_uv), (0, -step_uv)):
            moves.append(Hypothesis(cur.view, cur.phi_deg, cur.z_mm, cur.uv + np.array([du, dv])))
        if distance_mm is None:
            for f in (1 + step_z, 1 / (1 + step_z)):
                moves.append(Hypothesis(cur.view, cur.phi_deg, cur.z_mm * f, cur.uv))
        if view_moves:
            for n in neighbours[cur.view]:
                moves.append(Hypothesis(int(n), cur.phi_deg, cur.z_mm, cur.uv))
        Rs, ts = poses_of(bank, moves, K, distance_mm)
        cost, score = evaluate(bank, np.array([m.view for m in moves]), Rs, ts, K, dtt, p.fine_points,
                               p.score_px)
        b = int(np.argmin(cost))
        if cost[b] < cur.cost - 1e-6:
            cur = moves[b]
            cur.cost, cur.score = float(cost[b]), float(score[b])
            continue
        if step_uv <= min_step_px:
            break
        step_phi /= 2
        step_uv /= 2
        step_z /= 2
        view_moves = step_phi >= 0.5  # past that, neighbouring views are coarser than the angle steps
    return cur


def coarse_search(bank: TemplateBank, dtt_a: DistanceTensor, dtt_b: DistanceTensor, intr: Intrinsics,
                  image_shape: tuple[int, int], p: SearchParams, *, distance_mm: float | None,
                  distance_range_mm: tuple[float, float]) -> list[Hypothesis]:
    """Ranked, polished, mutually distinct hypotheses (best first)."""
    K = intr.K
    if distance_mm is None:
        # Every distance multiplies the scan: run it on a coarser grid, with fewer, smaller templates.
        p = replace(p, level_scale=p.level_scale / 2, anchor_stride=1, points_per_template=32,
                    depth_step=p.unknown_depth_step)
        dtt_a = distance_tensor_from_edges_scaled(dtt_a, p.level_scale)
    if distance_mm is not None:
        scales = np.array([1.0])
        z_ref = distance_mm
    else:
        lo, hi = distance_range_mm
        n = max(int(math.ceil(math.log(hi / lo) / math.log(1 + p.depth_step))), 1)
        zs = lo * (1 + p.depth_step) ** (np.arange(n + 1))
        z_ref = float(math.sqrt(lo * hi))
        scales = z_ref / zs
    tpl = _cached_level_a(bank, intr, image_shape, p, distance_mm, z_ref)
    au, av, tile, cost, t, d = scan_level_a(dtt_a, tpl, scales, image_shape, p)
    radius = 0.25 * tpl.extent_px * float(np.median(scales))
    peaks = pick_peaks(au, av, cost, p.n_peaks, max(radius, 2.0))
    n_phi = len(tpl.phis_deg)
    neighbours = view_neighbours(bank)
    starts: list[Hypothesis] = []
    for a in peaks:
        ti = int(t[a])
        view = int(tpl.views[ti // n_phi])
        phi = float(tpl.phis_deg[ti % n_phi])
        uv = np.array([(au[a] + 0.5) / p.level_scale - 0.5, (av[a] + 0.5) / p.level_scale - 0.5])
        z = float(tpl.z_ref_mm[tile[a], ti] / scales[d[a]])
        starts.append(Hypothesis(view, phi, z, uv))
    if not starts:
        return []
    # Level-A ranks are coarse: re-rank every peak on the finer grid, polish only the best few.
    Rs, ts = poses_of(bank, starts, K, distance_mm)
    views = np.array([h.view for h in starts])
    cost_b, _ = evaluate(bank, views, Rs, ts, K, dtt_b, p.fine_points, p.score_px)
    order = np.argsort(cost_b)[:p.n_polish]
    out = [polish(bank, starts[i], dtt_b, K, p, distance_mm=distance_mm, neighbours=neighbours)
           for i in order]
    out.sort(key=lambda h: h.cost)
    return out


_LEVEL_A_CACHE: OrderedDict = OrderedDict()


def _cached_level_a(bank, intr, image_shape, p, distance_mm, z_ref) -> LevelATemplates:
    """Level-A templates depend only on the bank, the camera, the image size and the distance: a
    cell's camera and distance rarely change between frames, so they are made once per camera."""
    key = (id(bank), intr, tuple(image_shape), p, distance_mm, z_ref)
    hit = _LEVEL_A_CACHE.get(key)
    if hit is not None and hit[0] is bank:
        _LEVEL_A_CACHE.move_to_end(key)
        return hit[1]
    tpl = level_a_templates(bank, intr, image_shape, p, distance_mm=distance_mm, z_ref_mm=z_ref)
    _LEVEL_A_CACHE[key] = (bank, tpl)
    while len(_LEVEL_A_CACHE) > 8:
        _LEVEL_A_CACHE.popitem(last=False)
    return tpl
