"""The search on a supporting plane: stable resting pose x spin about the plane normal x position on it.

A part lying on a known plane has 3 degrees of freedom left once its resting pose family is chosen
(``build/stable.py``, stored in the bank): the spin ``psi`` about the plane's normal and its position on
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

Frames: camera (OpenCV), mm. The plane: points p with ``n . p = d_mm``, ``n`` unit, towards the camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from service.vision.bank import TemplateBank, border_triplets, spread_order, view_dirs_obj
from service.vision.deadline import NO_DEADLINE, Deadline
from service.vision.estimate.chamfer import DT_QUANT, DistanceTensor, pooled_and_quantised, quantised
from service.vision.estimate.coarse import LEVEL_A_RESERVE_FACTOR, SearchParams, evaluate, pick_peaks
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, R_align_axis_to_y, Rz
from service.vision.memo import Memo

PLANE_TOLERANCE_MM = 5.0  # default: a found part's lowest point lies within this of the plane
PLANE_ANCHOR_STRIDE_PX = 16  # level A: full-resolution px between the anchors
LOCAL_RADIUS_PX = 16  # level B: full-resolution px searched round a peak (an anchor cell and a half)
LOCAL_STRIDE_PX = 4  # ... every this many px (the polish moves from there in 2 px steps)
# Level B also scans round a peak the families whose best placement at that anchor cost at most this
# ratio of the peak's (a part seen from above looks alike on some of its faces).
FAMILY_RATIO = 1.3
PEAK_RADIUS_DIAMETERS = 0.15  # level-A peaks closer than this many projected diameters are one peak
MIN_RAY_COS = 0.05  # rays meeting the plane at less than ~3 deg are not searched (the far horizon)


@dataclass(frozen=True)
class Plane:
    """A plane in the camera frame: points p (mm) with ``normal . p = d_mm``; ``normal`` (3,) unit,
    pointing out of the surface towards the camera (``d_mm < 0`` for a surface in front of it)."""

    normal: np.ndarray
    d_mm: float

    def height_mm(self, p_cam: np.ndarray) -> np.ndarray:
        """(N, 3) camera-frame points -> (N,) signed heights above the plane, mm."""
        return np.asarray(p_cam, float) @ self.normal - self.d_mm


def rest_gap_mm(bank: TemplateBank, pose: Pose, plane: Plane) -> float:
    """Height of the posed part's lowest point above the plane, mm: 0 resting on it, > 0 floating,
    < 0 going through it."""
    return float(plane.height_mm(pose.apply(np.asarray(bank.vertices_mm, float))).min())


def centre_height_mm(bank: TemplateBank, pose: Pose, plane: Plane) -> float:
    """Height of the part's reference point ``centre_obj`` above the plane, mm (``sort: height``)."""
    return float(plane.height_mm(pose.apply(np.asarray(bank.centre_obj, float)[None]))[0])


def R_cam_rest(plane: Plane) -> np.ndarray:
    """A rotation whose third column is the plane's normal (the resting frame's +z), camera frame."""
    n = np.asarray(plane.normal, float)
    e = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = e - (e @ n) * n
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(n, x), n])


@dataclass(frozen=True)
class Hypotheses:
    """Rotations of the search: family ``s[m]``, spin ``psi_deg[m]``, ``R[m] = R_cam_obj``, and the
    height of ``centre_obj`` above the plane when resting, ``h_mm[m]``."""

    s: np.ndarray  # (M,) int
    psi_deg: np.ndarray  # (M,)
    R: np.ndarray  # (M, 3, 3)
    h_mm: np.ndarray  # (M,)


def rest_heights_mm(bank: TemplateBank, R_rest_obj: np.ndarray) -> np.ndarray:
    """(S,) height of ``centre_obj`` above the plane for each resting rotation (its lowest vertex at 0)."""
    V = np.asarray(bank.vertices_mm, float)
    up = np.asarray(R_rest_obj, float)[:, 2, :]  # (S, 3) the resting frame's +z in the object frame
    return up @ np.asarray(bank.centre_obj, float) - (V @ up.T).min(axis=0)


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


def placements(R: np.ndarray, h_mm: np.ndarray, uv: np.ndarray, bank: TemplateBank, intr: Intrinsics,
               plane: Plane) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3, 3) rotations with centre heights (M,) placed at pixels uv (M, 2) -> ((M, 3) t_cam_obj, (M,)
    bool: the ray meets the plane in front of the camera). The reference point ``centre_obj`` lies on
    the ray through uv at height ``h_mm`` above the plane."""
    r = np.stack([(uv[:, 0] - intr.cx) / intr.fx, (uv[:, 1] - intr.cy) / intr.fy, np.ones(len(uv))], 1)
    nr = r @ plane.normal
    ok = nr < -MIN_RAY_COS * np.linalg.norm(r, axis=1)
    lam = (plane.d_mm + h_mm) / np.where(ok, nr, -1.0)
    ok &= lam > 0
    c_cam = lam[:, None] * r
    return c_cam - R @ np.asarray(bank.centre_obj, float), ok


def scoring_poses(bank: TemplateBank, R: np.ndarray, t: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For M poses: the bank view to score each with, (M,) int, and the pose to project that view's
    border points with ((M, 3, 3), (M, 3)). The view is the nearest by viewing direction (object frame);
    for a revolved part the nearest by tilt of the axis, with the pose spun about the axis so the
    camera sees it from that template's side (the same silhouette)."""
    c = R @ np.asarray(bank.centre_obj, float) + t
    dirs = np.einsum("mji,mj->mi", R, c / np.linalg.norm(c, axis=1, keepdims=True))  # R^T c_hat
    z = view_dirs_obj(bank)
    if bank.symmetry_axis_obj is None:
        return _nearest_views(np.ascontiguousarray(dirs), np.ascontiguousarray(z)), R, t
    a = np.asarray(bank.symmetry_axis_obj, float)
    p_s = np.asarray(bank.symmetry_point_obj, float)
    views = np.argmin(np.abs((dirs @ a)[:, None] - (z @ a)[None, :]), axis=1)
    w = R_align_axis_to_y(a)[2]  # the templates' side: z_n = sin(tilt) a + cos(tilt) w
    perp = dirs - np.outer(dirs @ a, a)
    beta = np.arctan2(np.cross(perp, np.broadcast_to(w, perp.shape)) @ a, perp @ w)  # perp -> w about a
    beta = np.where(np.linalg.norm(perp, axis=1) > 1e-9, beta, 0.0)
    Ka = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    S_T = (np.eye(3) - np.sin(beta)[:, None, None] * Ka
           + (1.0 - np.cos(beta))[:, None, None] * (Ka @ Ka))  # Rot(a, beta)^T, Rodrigues
    R2 = R @ S_T
    return views, R2, t + R @ p_s - R2 @ p_s


@nb.njit(parallel=True, cache=True)
def _score(dt_q, tau_q, scale, ou, ov, fx, fy, cx, cy, p_mid, d_obj, views, R, t, n_ch, limit, shared):
    """Mean quantised DT3 (1/DT_QUANT grid px, nearest pixel) of M posed templates: view ``views[m]``'s
    points (N, P, 3) posed by ``R[m]``, ``t[m]``, each with the direction ``d_obj`` (N, P, 3) of the
    border through it (successor minus predecessor): its projected orientation is the derivative of
    the projection along it, one projection per point instead of three. dt_q: (H, W, C) uint8; a
    point outside costs ``tau_q``.

    A template is abandoned (inf) once its partial sum reaches ``limit`` x P (all terms are >= 0); with
    ``shared`` the limit drops to the best total reached so far (only the best matters: threads read it
    unsynchronised, and a stale, higher limit only prunes less)."""
    M = views.shape[0]
    P = p_mid.shape[1]
    H, W = dt_q.shape[0], dt_q.shape[1]
    out = np.full(M, np.inf)
    bound = np.full(1, limit * P)
    for m in nb.prange(M):
        n = views[m]
        acc = 0.0
        ok = True
        for i in range(P):
            q = p_mid[n, i]
            d = d_obj[n, i]
            X = R[m, 0, 0] * q[0] + R[m, 0, 1] * q[1] + R[m, 0, 2] * q[2] + t[m, 0]
            Y = R[m, 1, 0] * q[0] + R[m, 1, 1] * q[1] + R[m, 1, 2] * q[2] + t[m, 1]
            Z = max(R[m, 2, 0] * q[0] + R[m, 2, 1] * q[1] + R[m, 2, 2] * q[2] + t[m, 2], 1e-6)
            x = int(np.floor((fx * X / Z + cx - ou + 0.5) * scale))
            y = int(np.floor((fy * Y / Z + cy - ov + 0.5) * scale))
            if x < 0 or x >= W or y < 0 or y >= H:
                acc += tau_q
            else:
                dX = R[m, 0, 0] * d[0] + R[m, 0, 1] * d[1] + R[m, 0, 2] * d[2]
                dY = R[m, 1, 0] * d[0] + R[m, 1, 1] * d[1] + R[m, 1, 2] * d[2]
                dZ = R[m, 2, 0] * d[0] + R[m, 2, 1] * d[1] + R[m, 2, 2] * d[2]
                th = math.atan2(fy * (dY * Z - Y * dZ), fx * (dX * Z - X * dZ)) % math.pi
                c = int(math.floor(th * (n_ch / math.pi) + 0.5)) % n_ch
                acc += dt_q[y, x, c]
            if acc >= bound[0]:
                ok = False
                break
        if ok:
            out[m] = acc / P
            if shared and acc < bound[0]:
                bound[0] = acc
    return out


@nb.njit(parallel=True, cache=True)
def _nearest_views(dirs, z):
    """(M,) index of the row of z (N, 3) nearest to each row of dirs (M, 3) (largest dot product)."""
    M, N = dirs.shape[0], z.shape[0]
    out = np.empty(M, np.int64)
    for m in nb.prange(M):
        best = -2.0
        bi = 0
        for n in range(N):
            d = dirs[m, 0] * z[n, 0] + dirs[m, 1] * z[n, 1] + dirs[m, 2] * z[n, 2]
            if d > best:
                best = d
                bi = n
        out[m] = bi
    return out


def _points(bank: TemplateBank, count: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, count, 3) border points of every view in ``spread_order`` (early ones spread round the
    border: a fair sample for the early abandon), and the border's direction through each (its
    successor minus its predecessor, object frame)."""

    def make():
        idx, prev, nxt = border_triplets(bank, count)
        order = spread_order(idx.shape[1])
        p = np.asarray(bank.p_obj, np.float64)
        return (np.ascontiguousarray(p[idx[:, order]]),
                np.ascontiguousarray(p[nxt[:, order]] - p[prev[:, order]]))

    return _POINTS.get(bank, count, make)


_POINTS = Memo(8)


def score_poses(bank: TemplateBank, R: np.ndarray, t: np.ndarray, dt_q: np.ndarray, tau_q: int,
                dtt: DistanceTensor, intr: Intrinsics, n_points: int, *, limit_q: float = np.inf,
                best_only: bool = False) -> np.ndarray:
    """(M,) mean directional chamfer cost of M poses, px of ``dtt``'s grid x DT_QUANT (nearest pixel);
    inf where it reaches ``limit_q`` (and, with ``best_only``, where it cannot beat the best)."""
    if len(R) == 0:
        return np.zeros(0)
    views, R2, t2 = scoring_poses(bank, R, t)
    mid, direction = _points(bank, n_points)
    return _score(dt_q, tau_q, dtt.scale, dtt.origin_uv[0], dtt.origin_uv[1], intr.fx, intr.fy, intr.cx,
                  intr.cy, mid, direction, views.astype(np.int64), np.ascontiguousarray(R2),
                  np.ascontiguousarray(t2), dtt.n_channels, float(limit_q), best_only)


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
    cost = np.full((A, M), np.inf)
    deadline.new_loop()
    for m in coverage_order(hyp.s, len(R_rest_obj)):
        if not deadline.allows_next(LEVEL_A_RESERVE_FACTOR * reserve_ms):
            break
        t, ok = placements(np.broadcast_to(hyp.R[m], (A, 3, 3)), np.full(A, hyp.h_mm[m]), anchors, bank, intr,
                           plane)
        if distance_range_mm is not None:
            z = (t + hyp.R[m] @ bank.centre_obj)[:, 2]
            ok &= (z >= distance_range_mm[0]) & (z <= distance_range_mm[1])
        if ok.any():  # a template averaging over accept_frac x tau is no peak: abandoned
            Rm = np.broadcast_to(hyp.R[m], (int(ok.sum()), 3, 3))
            cost[ok, m] = score_poses(bank, Rm, t[ok], dt_qa, tau_qa, dtt_a, intr, p.points_per_template,
                                      limit_q=p.accept_frac * tau_qa)
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
    scanned: list[PlaneHypothesis] = []
    deadline.new_loop()
    for a in peaks:
        if not deadline.allows_next(reserve_ms):
            break
        s_list, psi_list = [], []
        for s in range(len(R_rest_obj)):
            ms = np.flatnonzero(hyp.s == s)
            mb = ms[np.argmin(cost[a, ms])]
            if cost[a, mb] <= FAMILY_RATIO * best[a]:
                s_list.append(s)
                psi_list.append(hyp.psi_deg[mb])
        S_, P_, U_ = [], [], []
        for s, psi0 in zip(s_list, psi_list, strict=True):
            for d in dpsi:
                S_.append(np.full(len(du), s))
                P_.append(np.full(len(du), psi0 + d))
                U_.append(anchors[a] + np.column_stack([du, dv]))
        s_all, psi_all, uv_all = np.concatenate(S_), np.concatenate(P_), np.concatenate(U_)
        R, t, ok = _poses(bank, R_rest_obj, plane, intr, s_all, psi_all, uv_all)
        if not ok.any():
            continue
        c = np.full(len(R), np.inf)
        c[ok] = score_poses(bank, R[ok], t[ok], dt_qb, tau_qb, dtt_b, intr, p.scan_points, best_only=True)
        k = int(np.argmin(c))
        scanned.append(PlaneHypothesis(int(s_all[k]), float(psi_all[k]), uv_all[k].copy(), R[k], t[k],
                                       float(c[k]) / DT_QUANT / dtt_b.scale))
    if not scanned:
        return []
    scanned.sort(key=lambda x: x.cost)
    out = []
    deadline.new_loop()
    for h in scanned[:p.n_polish]:
        go = deadline.allows_next(reserve_ms)
        out.append(polish(bank, R_rest_obj, h, dtt_b, intr, plane, p) if go else h)
    out.sort(key=lambda x: x.cost)
    return out


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


def polish(bank: TemplateBank, R_rest_obj: np.ndarray, h: PlaneHypothesis, dtt: DistanceTensor,
           intr: Intrinsics, plane: Plane, p: SearchParams, *, min_step_px: float = 0.25,
           max_iter: int = 60) -> PlaneHypothesis:
    """Pattern search over (spin, u, v) on the plane from ``h``, bilinear costs (``coarse.evaluate``)."""

    def cost_of(psis, uvs):
        R, t, ok = _poses(bank, R_rest_obj, plane, intr, np.full(len(psis), h.s), psis, uvs)
        views, R2, t2 = scoring_poses(bank, R, t)
        c, sc = evaluate(bank, views, R2, t2, intr.K, dtt, p.fine_points, p.score_px, p.rank_tau_px)
        return np.where(ok, c, np.inf), sc, R, t

    c, sc, R, t = cost_of(np.array([h.psi_deg]), h.uv[None])
    cur = PlaneHypothesis(h.s, h.psi_deg, h.uv, R[0], t[0], float(c[0]), float(sc[0]))
    step_psi, step_uv = p.local_phi_step_deg / 2, 1.0 / dtt.scale
    for _ in range(max_iter):
        psis = cur.psi_deg + np.array([-step_psi, step_psi, 0, 0, 0, 0])
        uvs = cur.uv + np.array([[0, 0], [0, 0], [step_uv, 0], [-step_uv, 0], [0, step_uv], [0, -step_uv]])
        c, sc, R, t = cost_of(psis, uvs)
        b = int(np.argmin(c))
        if c[b] < cur.cost - 1e-6:
            cur = PlaneHypothesis(h.s, float(psis[b]), uvs[b], R[b], t[b], float(c[b]), float(sc[b]))
            continue
        if step_uv <= min_step_px:
            break
        step_psi /= 2
        step_uv /= 2
    return cur
