"""The search on a supporting plane: stable resting pose x spin about the plane normal x position on it.

A part lying on a known plane has 3 degrees of freedom left once its resting pose family is chosen
(``model/stable.py``, stored in the bank): the spin ``psi`` about the plane's normal and its position on
the plane. With the resting frame ``rest`` (+z = the plane's normal, towards the camera),
``R_cam_obj = R_cam_rest @ Rz(psi) @ R_rest_obj[s]`` is fixed by (s, psi), and the pixel ``uv`` where the
bank's reference point ``centre_obj`` is seen fixes the rest: that point lies on the viewing ray through
``uv`` at the height above the plane the resting pose gives it, so ``t_cam_obj`` follows.

Every (s, psi, uv) is therefore a full pose, scored against the image's directional distance tensor by
projecting the border points of the bank's template seen from the nearest direction (for a revolved
part the equivalent pose spun about its axis onto the template's half-plane, ``scoring_poses``).

Search, coarse to fine, like ``coarse.py`` but over 3 DoF instead of 6:
1. every family x spin (``inplane_step_deg``) x anchor (every ``PLANE_ANCHOR_STRIDE_PX`` pixels) on the
   min-pooled distance tensor (``level_scale``), ``points_per_template`` points each;
2. around each distinct peak, the peak's and the other families that scored near it, spins +-a step
   at ``local_phi_step_deg``, pixels within +-``LOCAL_RADIUS_PX`` every ``LOCAL_STRIDE_PX``, on the
   fine tensor;
3. a pattern search over (spin, u, v) with bilinear costs, ``fine_points`` points.

Frames: camera (OpenCV), mm. The plane and a resting part's geometry: ``geometry/plane.py``; the scoring of
poses: ``plane_scoring``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from service.vision.bank import TemplateBank
from service.vision.deadline import NO_DEADLINE, Deadline
from service.vision.estimate.chamfer import DT_QUANT, DistanceTensor, pooled_and_quantised, quantised
from service.vision.estimate.level_a import LEVEL_A_RESERVE_FACTOR, pick_peaks
from service.vision.estimate.plane_scoring import evaluate_poses, score_poses, scoring_poses
from service.vision.estimate.search import SearchParams
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Rz
from service.vision.geometry.plane import Plane, R_cam_rest, placements, rest_heights_mm

PLANE_TOLERANCE_MM = 5.0  # default: a found part's lowest point lies within this of the plane
PLANE_ANCHOR_STRIDE_PX = 16  # level A: full-resolution px between the anchors
LOCAL_RADIUS_PX = 16  # level B: full-resolution px searched round a peak (an anchor cell and a half)
LOCAL_STRIDE_PX = 4  # ... every this many px (the polish moves from there in 2 px steps)
LEVEL_B_PEAKS_PER_CALL = 8  # level B scores the scans round this many peaks in one call (a deadline unit)
LEVEL_B_FINE_STEPS = 2  # level B's second scan: this many full-grid steps round its first scan's best
# Level B also scans round a peak the families whose best placement at that anchor cost at most this
# ratio of the peak's (a part seen from above looks alike on some of its faces).
FAMILY_RATIO = 1.3
BLOCK_ANCHORS = 4  # level A first bounds each rotation on blocks of 4 x 4 anchors, placed at their centre
# ... on a floor reaching this far (full-resolution px): the block's farthest anchor (24 px each way) and
# what perspective moves a point more than the anchor across a block (a few px on 64 px blocks)
BLOCK_REACH_PX = 36.0
LEVEL_A_ROTATIONS_PER_CALL = 8  # rotations level A scores at every anchor per call (less per-call overhead)
PEAK_RADIUS_DIAMETERS = 0.15  # level-A peaks closer than this many projected diameters are one peak


@dataclass(frozen=True)
class Hypotheses:
    """Rotations of the search: family ``s[m]``, spin ``psi_deg[m]``, ``R[m] = R_cam_obj``, and the
    height of ``centre_obj`` above the plane when resting, ``h_mm[m]``."""

    s: np.ndarray  # (M,) int
    psi_deg: np.ndarray  # (M,)
    R: np.ndarray  # (M, 3, 3)
    h_mm: np.ndarray  # (M,)


def rotations(bank: TemplateBank, R_rest_obj: np.ndarray, plane: Plane, psi_step_deg: float) -> Hypotheses:
    """Every family x spin (0..360 by ``psi_step_deg``). A revolved part standing on its axis needs one
    spin only."""
    Rc = R_cam_rest(plane)
    h = rest_heights_mm(bank, R_rest_obj)
    s_out, psi_out, R_out = [], [], []
    for s in range(len(R_rest_obj)):
        psis = np.arange(0.0, 360.0, psi_step_deg)
        if bank.symmetry_axis_obj is not None and abs(float(R_rest_obj[s][2] @ bank.symmetry_axis_obj)) > \
                math.cos(math.radians(1.0)):
            psis = psis[:1]
        for p in psis:
            s_out.append(s)
            psi_out.append(p)
            R_out.append(Rc @ Rz(float(p)) @ R_rest_obj[s])
    s_arr = np.asarray(s_out, int)
    return Hypotheses(s_arr, np.asarray(psi_out, float), np.asarray(R_out).reshape(-1, 3, 3), h[s_arr])


@dataclass
class PlaneHypothesis:
    s: int  # resting family
    psi_deg: float  # spin about the plane normal
    uv: np.ndarray  # (2,) full-resolution pixel of centre_obj
    R: np.ndarray  # (3, 3) R_cam_obj
    t: np.ndarray  # (3,) t_cam_obj, mm
    cost: float = np.inf  # mean directional chamfer distance, full-resolution px (truncated at rank_tau_px)
    score: float = 0.0


def _poses(bank, R_rest_obj, plane, intr, s, psi, uv):
    """Poses of (family, spin, uv) triples: ((M, 3, 3) R, (M, 3) t, (M,) ok)."""
    s = np.asarray(s, int)
    a = np.radians(np.asarray(psi, float))
    c, si = np.cos(a), np.sin(a)
    Rzs = np.zeros((len(a), 3, 3))
    Rzs[:, 0, 0], Rzs[:, 0, 1], Rzs[:, 1, 0], Rzs[:, 1, 1], Rzs[:, 2, 2] = c, -si, si, c, 1.0
    R = R_cam_rest(plane) @ Rzs @ np.asarray(R_rest_obj, float)[s]
    t, ok = placements(R, rest_heights_mm(bank, R_rest_obj)[s], np.asarray(uv, float).reshape(-1, 2), bank,
                       intr, plane)
    return R, t, ok


def plane_search(bank: TemplateBank, R_rest_obj: np.ndarray, dtt_b: DistanceTensor, intr: Intrinsics,
                 image_shape: tuple[int, int], plane: Plane, p: SearchParams, *,
                 distance_range_mm: tuple[float, float] | None = None,
                 anchor_mask: np.ndarray | None = None, deadline: Deadline = NO_DEADLINE,
                 reserve_ms: float = 0.0) -> list[PlaneHypothesis]:
    """Ranked, polished hypotheses resting on ``plane`` (best first, at most ``p.n_polish``).

    ``dtt_b``: DT3 at ``p.fine_scale``; level A's is min-pooled from it. ``anchor_mask``
    (full-resolution (h, w) bool): only anchors there (a region of interest). ``distance_range_mm``:
    anchors whose reference point would lie outside this depth range are not searched.

    Anytime, as ``coarse.coarse_search``: level A goes rotation by rotation in ``coverage_order``
    (every family at coarse spins first), level B peak by peak, the polish hypothesis by hypothesis,
    each only while the ``deadline`` leaves the unit plus ``reserve_ms`` (level A: twice that)."""
    h_img, w_img = image_shape
    if len(R_rest_obj) == 0:
        return []
    # --- level A: families x spins x anchors on the pooled tensor -------------------------------------
    dtt_a, dt_qb, tau_qb = pooled_and_quantised(dtt_b, p.level_scale, p.rank_tau_px * dtt_b.scale)
    dt_qa, tau_qa = quantised(dtt_a, dtt_a.tau_px)
    hyp = rotations(bank, R_rest_obj, plane, p.inplane_step_deg)
    g = PLANE_ANCHOR_STRIDE_PX
    au, av = np.meshgrid(np.arange(g / 2 - 0.5, w_img, g), np.arange(g / 2 - 0.5, h_img, g))
    anchors = np.column_stack([au.ravel(), av.ravel()])
    if anchor_mask is not None:
        ui = np.clip(np.rint(anchors[:, 0]).astype(int), 0, w_img - 1)
        vi = np.clip(np.rint(anchors[:, 1]).astype(int), 0, h_img - 1)
        anchors = anchors[anchor_mask[vi, ui]]
    A, M = len(anchors), len(hyp.R)
    if A == 0:
        return []
    limit_q = p.accept_frac * tau_qa
    block_of, block_uv = anchor_blocks(anchors, g)
    dt_qblock = block_floor(dt_qa, dtt_a, BLOCK_REACH_PX)
    cost = np.full((M, A), np.inf)
    order = coverage_order(hyp.s, len(R_rest_obj))
    deadline.new_loop()
    for i in range(0, M, LEVEL_A_ROTATIONS_PER_CALL):
        if not deadline.allows_next(LEVEL_A_RESERVE_FACTOR * reserve_ms):
            break
        ms = order[i:i + LEVEL_A_ROTATIONS_PER_CALL]
        hopeful = hopeful_blocks(bank, hyp, ms, block_uv, dt_qblock, tau_qa, dtt_a, intr, plane, p, limit_q)
        # only the (rotation, anchor) pairs of hopeful blocks are placed, rotation-major
        sel = np.flatnonzero(hopeful[:, block_of].ravel())
        Rm = hyp.R[ms[sel // A]]
        t, ok = placements(Rm, hyp.h_mm[ms[sel // A]], anchors[sel % A], bank, intr, plane)
        if distance_range_mm is not None:
            z = (t + Rm @ bank.centre_obj)[:, 2]
            ok &= (z >= distance_range_mm[0]) & (z <= distance_range_mm[1])
        if ok.any():  # a template averaging over accept_frac x tau is no peak: abandoned
            c = np.full(len(ms) * A, np.inf)
            c[sel[ok]] = score_poses(bank, Rm[ok], t[ok], dt_qa, tau_qa, dtt_a, intr, p.points_per_template,
                                     limit_q=limit_q)
            cost[ms] = c.reshape(len(ms), A)
    cost = cost.T
    best_m = np.argmin(cost, axis=1)
    best = cost[np.arange(A), best_m]
    if not np.isfinite(best).any():
        return []
    # peaks: distinct anchors, lowest cost first
    rays = np.column_stack([(anchors[:, 0] - intr.cx) / intr.fx, (anchors[:, 1] - intr.cy) / intr.fy,
                            np.ones(A)])
    z_mid = float(np.median(np.abs(plane.d_mm) / np.maximum(-(rays @ plane.normal), 1e-3)))
    radius = max(PEAK_RADIUS_DIAMETERS * bank.diameter_mm * intr.fx / max(z_mid, 1.0), g * 0.75)
    peaks = pick_peaks(anchors[:, 0], anchors[:, 1], best, p.n_peaks, radius)
    # --- level B: round each peak on the fine tensor ---------------------------------------------------
    offs = np.arange(-LOCAL_RADIUS_PX, LOCAL_RADIUS_PX + 1e-9, LOCAL_STRIDE_PX)
    du, dv = (x.ravel() for x in np.meshgrid(offs, offs))
    near = np.argsort(du**2 + dv**2, kind="stable")  # near the peak first: a tight bound early
    du, dv = du[near], dv[near]
    dpsi = np.arange(-p.inplane_step_deg, p.inplane_step_deg + 1e-9, p.local_phi_step_deg)
    dpsi = dpsi[np.argsort(np.abs(dpsi), kind="stable")]
    stages = _level_b_stages(du, dv, dpsi)
    scanned: list[PlaneHypothesis] = []
    family_rotations = [np.flatnonzero(hyp.s == s) for s in range(len(R_rest_obj))]
    deadline.new_loop()
    for i in range(0, len(peaks), LEVEL_B_PEAKS_PER_CALL):
        if not deadline.allows_next(reserve_ms):
            break
        # each peak's families: each family's best at a peak between two copies may win there
        groups = []  # (peak, family, spin) in the order of the peaks, then of the families
        for a in peaks[i:i + LEVEL_B_PEAKS_PER_CALL]:
            for s, ms in enumerate(family_rotations):
                mb = ms[np.argmin(cost[a, ms])]
                if cost[a, mb] <= FAMILY_RATIO * best[a]:
                    groups.append((a, s, hyp.psi_deg[mb]))
        for h in _scan_round(bank, R_rest_obj, plane, intr, groups, anchors, stages, dt_qb, tau_qb, dtt_b,
                             p.scan_points):
            if h is not None and not any(x.s == h.s and x.psi_deg == h.psi_deg and np.array_equal(x.uv, h.uv)
                                         for x in scanned):  # two peaks' scans can end on one placement
                scanned.append(h)
    if not scanned:
        return []
    scanned.sort(key=lambda x: x.cost)
    out = polish(bank, R_rest_obj, scanned[:p.n_polish], dtt_b, intr, plane, p, deadline=deadline,
                 reserve_ms=reserve_ms)
    out.sort(key=lambda x: x.cost)
    return out


def anchor_blocks(anchors: np.ndarray, g: float) -> tuple[np.ndarray, np.ndarray]:
    """Anchors (full-resolution uv on a grid ``g`` px apart) grouped in blocks of BLOCK_ANCHORS x
    BLOCK_ANCHORS grid positions -> ((A,) block of each anchor, (B, 2) uv of each block's centre)."""
    cell = np.floor(anchors / (g * BLOCK_ANCHORS)).astype(int)
    keys, block_of = np.unique(cell, axis=0, return_inverse=True)
    centre = (keys + 0.5) * (g * BLOCK_ANCHORS) - 0.5
    return block_of.ravel(), centre


def block_floor(dt_q: np.ndarray, dtt: DistanceTensor, reach_px: float) -> np.ndarray:
    """(H, W, C) uint8: the least of ``dt_q`` over the channels either side and a square ``reach_px``
    (full-resolution) round each pixel: a template placed at a block's centre, scored on this, costs
    no more than at any anchor of the block whose points lie within that reach of the centre's."""
    least = np.minimum(dt_q, np.minimum(np.roll(dt_q, 1, axis=2), np.roll(dt_q, -1, axis=2)))
    k = 2 * int(math.ceil(reach_px * dtt.scale)) + 1
    kernel = np.ones((k, k), np.uint8)
    out = np.empty_like(least)
    for c in range(least.shape[2]):
        out[..., c] = cv2.erode(np.ascontiguousarray(least[..., c]), kernel, borderType=cv2.BORDER_REPLICATE)
    return out


def hopeful_blocks(bank: TemplateBank, hyp: Hypotheses, ms: np.ndarray, block_uv: np.ndarray,
                   dt_qblock: np.ndarray, tau_q: int, dtt: DistanceTensor, intr: Intrinsics, plane: Plane,
                   p: SearchParams, limit_q: float) -> np.ndarray:
    """(len(ms), B) whether rotation ms[j] placed at block b's centre can score under ``limit_q`` on the
    block floor (``block_floor``): where it cannot, no anchor of the block need be scored. A centre
    off the plane or the image bounds nothing (hopeful)."""
    nb_ = len(block_uv)
    Rb = np.repeat(hyp.R[ms], nb_, axis=0)
    t, ok = placements(Rb, np.repeat(hyp.h_mm[ms], nb_), np.tile(block_uv, (len(ms), 1)), bank, intr, plane)
    hopeful = np.ones(len(Rb), bool)
    if ok.any():
        c = score_poses(bank, Rb[ok], t[ok], dt_qblock, tau_q, dtt, intr, p.points_per_template,
                        limit_q=limit_q)
        hopeful[ok] = np.isfinite(c)
    return hopeful.reshape(len(ms), nb_)


def _scan_round(bank: TemplateBank, R_rest_obj: np.ndarray, plane: Plane, intr: Intrinsics, groups: list,
                anchors: np.ndarray, stages: list[tuple], dt_q: np.ndarray, tau_q: int, dtt: DistanceTensor,
                n_points: int) -> list[PlaneHypothesis | None]:
    """Level B's scans round peaks, one per (peak anchor, family, spin) of ``groups``: each stage of
    ``stages`` (``_level_b_stages``) scans its offsets round the scan's best so far (at first the peak's
    anchor and spin), all scans in one scoring call, each with its own running best (``_score``'s
    groups: the same placements as a call per scan). A scan ends where a stage finds nothing (no
    placement on the plane, or none finite) -> per group its best placement, or None."""
    out: list[PlaneHypothesis | None] = [None] * len(groups)
    if not groups:
        return out
    fam = np.array([g[1] for g in groups], int)
    centre_uv = anchors[[g[0] for g in groups]].astype(float)
    centre_psi = np.array([g[2] for g in groups], float)
    alive = np.ones(len(groups), bool)
    for ddu, ddv, dps in stages:
        live = np.flatnonzero(alive)
        if len(live) == 0:
            break
        n = len(ddu) * len(dps)
        off = np.column_stack([ddu, ddv])
        psi_all = np.concatenate([np.repeat(centre_psi[j] + dps, len(ddu)) for j in live])
        uv_all = np.concatenate([np.tile(centre_uv[j] + off, (len(dps), 1)) for j in live])
        R, t, ok = _poses(bank, R_rest_obj, plane, intr, np.repeat(fam[live], n), psi_all, uv_all)
        c = np.full(len(live) * n, np.inf)
        if ok.any():
            c[ok] = score_poses(bank, R[ok], t[ok], dt_q, tau_q, dtt, intr, n_points, best_only=True,
                                group=np.repeat(np.arange(len(live)), n)[ok])
        c = c.reshape(len(live), n)
        for r, j in enumerate(live):
            k = int(np.argmin(c[r]))
            if not np.isfinite(c[r, k]):  # nothing on the plane, or nothing finite: the scan ends
                alive[j] = False
                continue
            cost_k = float(c[r, k]) / DT_QUANT / dtt.scale
            h = out[j]
            if h is None or cost_k < h.cost:
                m = r * n + k
                out[j] = PlaneHypothesis(int(fam[j]), float(psi_all[m]), uv_all[m].copy(), R[m], t[m], cost_k)
                centre_uv[j], centre_psi[j] = uv_all[m], psi_all[m]
    return out


def _level_b_stages(du: np.ndarray, dv: np.ndarray, dpsi: np.ndarray) -> list[tuple]:
    """Level B's two scans round a peak, as (du, dv, dpsi) offsets: every other offset and spin of the
    full grid, then the full grid's steps within LEVEL_B_FINE_STEPS of the best of those (a fifth of the
    placements of scanning the full grid; on bench/plane.py the same recall)."""
    step_psi = float(np.min(np.abs(dpsi[dpsi != 0]))) if np.any(dpsi != 0) else 1.0
    even = (np.rint(du / LOCAL_STRIDE_PX) % 2 == 0) & (np.rint(dv / LOCAL_STRIDE_PX) % 2 == 0)
    coarse = (du[even], dv[even], dpsi[np.rint(dpsi / step_psi) % 2 == 0])
    reach = LEVEL_B_FINE_STEPS * LOCAL_STRIDE_PX
    near = (np.abs(du) <= reach) & (np.abs(dv) <= reach)
    fine = (du[near], dv[near], dpsi[np.abs(dpsi) <= LEVEL_B_FINE_STEPS * step_psi + 1e-9])
    return [coarse, fine]


def coverage_order(family: np.ndarray, n_families: int) -> np.ndarray:
    """Indices of level A's rotations (``family`` (M,) per rotation, its spins evenly spaced and in
    order within each) so that any prefix covers every family, at the coarsest spins first: within a
    family spins come farthest from those already taken first (0, 1/2, 1/4, 3/4 ... of the turn),
    and the families take turns."""
    rank = np.empty(len(family), float)
    for s in range(n_families):
        ms = np.flatnonzero(family == s)
        rank[ms[_farthest_first(len(ms))]] = np.arange(len(ms)) / max(len(ms), 1)
    return np.lexsort((family, rank))


def _farthest_first(n: int) -> np.ndarray:
    """0..n-1 round a circle of n evenly spaced spins, each next the one farthest from those taken (ties:
    the lowest)."""
    taken = [0]
    gap = np.minimum(np.arange(n), n - np.arange(n)).astype(float)  # circular distance to spin 0
    gap[0] = -1.0
    for _ in range(n - 1):
        k = int(np.argmax(gap))
        taken.append(k)
        d = np.abs(np.arange(n) - k)
        gap = np.minimum(gap, np.minimum(d, n - d))
        gap[taken] = -1.0
    return np.array(taken, int)


def polish(bank: TemplateBank, R_rest_obj: np.ndarray, hs: list[PlaneHypothesis], dtt: DistanceTensor,
           intr: Intrinsics, plane: Plane, p: SearchParams, *, min_step_px: float = 0.25, max_iter: int = 60,
           deadline: Deadline = NO_DEADLINE, reserve_ms: float = 0.0) -> list[PlaneHypothesis]:
    """A pattern search over (spin, u, v) on the plane from each hypothesis, bilinear costs
    (``evaluate_poses``): all hypotheses step together, one scoring call a step for all of them (each
    moves, or halves its steps, on its own six neighbours' costs alone). Anytime: a step starts only
    while the ``deadline`` leaves it and ``reserve_ms``; each hypothesis is then where it got to."""
    if not hs:
        return []

    def cost_of(s, psis, uvs):
        R, t, ok = _poses(bank, R_rest_obj, plane, intr, s, psis, uvs)
        views, R2, t2 = scoring_poses(bank, R, t)
        c, sc = evaluate_poses(bank, views, R2, t2, intr, dtt, p.fine_points, p.score_px, p.rank_tau_px)
        return np.where(ok, c, np.inf), sc, R, t

    n = len(hs)
    s = np.array([h.s for h in hs])
    psi = np.array([h.psi_deg for h in hs], float)
    uv = np.array([h.uv for h in hs], float)
    c, sc, R, t = cost_of(s, psi, uv)
    cost, score = c.copy(), sc.copy()
    step_psi = np.full(n, p.local_phi_step_deg / 2)
    step_uv = np.full(n, 1.0 / dtt.scale)
    active = np.ones(n, bool)
    d_psi = np.array([-1.0, 1.0, 0.0, 0.0, 0.0, 0.0])
    d_uv = np.array([[0, 0], [0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]], float)
    deadline.new_loop()
    for _ in range(max_iter):
        if not active.any() or not deadline.allows_next(reserve_ms):
            break
        k = np.flatnonzero(active)
        psis = (psi[k, None] + step_psi[k, None] * d_psi).ravel()
        uvs = (uv[k, None, :] + step_uv[k, None, None] * d_uv).reshape(-1, 2)
        c, sc, Rn, tn = cost_of(np.repeat(s[k], 6), psis, uvs)
        c = c.reshape(-1, 6)
        b = np.argmin(c, axis=1)
        better = c[np.arange(len(k)), b] < cost[k] - 1e-6
        for j, i in enumerate(k):
            if better[j]:
                m = 6 * j + b[j]
                psi[i], uv[i], cost[i], score[i] = psis[m], uvs[m], c[j, b[j]], sc[m]
                R[i], t[i] = Rn[m], tn[m]
            elif step_uv[i] <= min_step_px:
                active[i] = False
            else:
                step_psi[i] /= 2
                step_uv[i] /= 2
    return [PlaneHypothesis(h.s, float(psi[i]), uv[i].copy(), R[i], t[i], float(cost[i]), float(score[i]))
            for i, h in enumerate(hs)]
