"""Scoring poses on a supporting plane (``plane``): each pose's border points, from the bank's template
seen from the nearest direction, projected and read off the directional distance tensor (quantised,
nearest pixel, early abandon) or bilinearly (``evaluate_poses``, the polish)."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from service.vision.bank import TemplateBank, border_triplets, spread_order, view_dirs_obj
from service.vision.estimate.chamfer import DistanceTensor
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import R_align_axis_to_y
from service.vision.memo import Memo


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
        return nearest_views(bank, dirs), R, t
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


@nb.njit(cache=True)
def _bin_edges(n_ch):
    """cos and sin of the orientation channels' upper edges (k + 1/2) pi / n_ch, k = 0 .. n_ch - 1."""
    b = (np.arange(n_ch) + 0.5) * (math.pi / n_ch)
    return np.cos(b), np.sin(b)


@nb.njit(inline="always")
def _channel(x, y, cos_b, sin_b):
    """The orientation channel of the direction (x, y): int(th n / pi + 1/2) mod n for th its angle
    modulo pi (atan2), as the number of channel edges at or below th, each told by the sign of
    y cos(b) - x sin(b) (th >= b for th, b in [0, pi]) instead of an atan2. The edges are counted, all
    n of them, rather than bisected: the signs run true then false along the edges (a rounding can flip
    only the one edge th lies on), so the count is where a bisection ends, and a loop of n comparisons
    has no branch to mispredict."""
    if y < 0.0:
        x, y = -x, -y
    n = cos_b.shape[0]
    below = 0
    for k in range(n):
        below += 1 if y * cos_b[k] - x * sin_b[k] >= 0.0 else 0
    return below if below < n else 0


@nb.njit(parallel=True, cache=True)
def _score(dt_q, tau_q, scale, ou, ov, fx, fy, cx, cy, p_mid, d_obj, views, R, t, n_ch, limit, shared, group,
           n_groups, centre, vz, vstart, vcand, vg):
    """Mean quantised DT3 (1/DT_QUANT grid px, nearest pixel) of M posed templates: view ``views[m]``'s
    points (N, P, 3) posed by ``R[m]``, ``t[m]``, each with the direction ``d_obj`` (N, P, 3) of the
    border through it (successor minus predecessor): its projected orientation is the derivative of
    the projection along it, one projection per point instead of three. dt_q: (H, W, C) uint8; a
    point outside costs ``tau_q``.

    A template is abandoned (inf) once its partial sum reaches ``limit`` x P (all terms are >= 0); with
    ``shared`` the limit drops to just above the best total reached so far (only the best matters: threads
    read it unsynchronised, and a stale, higher limit only prunes less). Totals are whole numbers, so every
    pose costing the best total stays finite: the caller's argmin picks the first of them, not the one a
    thread happened to finish first. ``group`` (M,) int64 in [0, n_groups) (or
    empty: one group): each group has its own best, as if scored by a call of its own.

    ``views`` empty: each pose's view is the one nearest the direction it sees ``centre`` (3,) from
    (``nearest_views`` with its table ``vz``, ``vstart``, ``vcand``, ``vg``; ``scoring_poses`` for a
    part without symmetry, the same arithmetic)."""
    M = R.shape[0]
    pick = views.shape[0] == 0
    P = p_mid.shape[1]
    H, W = dt_q.shape[0], dt_q.shape[1]
    out = np.full(M, np.inf)
    bound = np.full(max(n_groups, 1), limit * P)
    grouped = group.shape[0] > 0
    cos_b, sin_b = _bin_edges(n_ch)
    for m in nb.prange(M):
        if pick:
            c0 = R[m, 0, 0] * centre[0] + R[m, 0, 1] * centre[1] + R[m, 0, 2] * centre[2] + t[m, 0]
            c1 = R[m, 1, 0] * centre[0] + R[m, 1, 1] * centre[1] + R[m, 1, 2] * centre[2] + t[m, 1]
            c2 = R[m, 2, 0] * centre[0] + R[m, 2, 1] * centre[1] + R[m, 2, 2] * centre[2] + t[m, 2]
            nc = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
            c0, c1, c2 = c0 / nc, c1 / nc, c2 / nc
            n = _nearest_view(R[m, 0, 0] * c0 + R[m, 1, 0] * c1 + R[m, 2, 0] * c2,
                              R[m, 0, 1] * c0 + R[m, 1, 1] * c1 + R[m, 2, 1] * c2,
                              R[m, 0, 2] * c0 + R[m, 1, 2] * c1 + R[m, 2, 2] * c2, vz, vstart, vcand, vg)
        else:
            n = views[m]
        gi = group[m] if grouped else 0
        acc = 0.0
        ok = True
        r00, r01, r02 = R[m, 0, 0], R[m, 0, 1], R[m, 0, 2]
        r10, r11, r12 = R[m, 1, 0], R[m, 1, 1], R[m, 1, 2]
        r20, r21, r22 = R[m, 2, 0], R[m, 2, 1], R[m, 2, 2]
        t0, t1, t2 = t[m, 0], t[m, 1], t[m, 2]
        for i in range(P):
            q0, q1, q2 = p_mid[n, i, 0], p_mid[n, i, 1], p_mid[n, i, 2]
            X = r00 * q0 + r01 * q1 + r02 * q2 + t0
            Y = r10 * q0 + r11 * q1 + r12 * q2 + t1
            Z = max(r20 * q0 + r21 * q1 + r22 * q2 + t2, 1e-6)
            x = int(math.floor((fx * X / Z + cx - ou + 0.5) * scale))
            y = int(math.floor((fy * Y / Z + cy - ov + 0.5) * scale))
            if x < 0 or x >= W or y < 0 or y >= H:
                acc += tau_q
            else:
                d0, d1, d2 = d_obj[n, i, 0], d_obj[n, i, 1], d_obj[n, i, 2]
                dX = r00 * d0 + r01 * d1 + r02 * d2
                dY = r10 * d0 + r11 * d1 + r12 * d2
                dZ = r20 * d0 + r21 * d1 + r22 * d2
                c = _channel(fx * (dX * Z - X * dZ), fy * (dY * Z - Y * dZ), cos_b, sin_b)
                acc += dt_q[y, x, c]
            if acc >= bound[gi]:
                ok = False
                break
        if ok:
            out[m] = acc / P
            if shared and acc + 1 < bound[gi]:
                bound[gi] = acc + 1  # ties stay finite: which one reaches the bound first is the threads'
    return out


def nearest_views(bank: TemplateBank, dirs: np.ndarray) -> np.ndarray:
    """(M,) the bank view nearest each unit viewing direction of ``dirs`` (M, 3), object frame (largest
    dot product, the lowest index among equals): as a scan of every view, but each direction is
    compared only with the views that can be nearest anywhere in its cell of a cube map."""
    z = view_dirs_obj(bank)
    start, cand = _VIEWS.get(bank, VIEW_TABLE_CELLS, lambda: view_table(z, VIEW_TABLE_CELLS))
    return _nearest_in_table(np.ascontiguousarray(dirs, np.float64), np.ascontiguousarray(z, np.float64),
                             start, cand, VIEW_TABLE_CELLS)
VIEW_TABLE_CELLS = 32  # cells along a cube face's side in the nearest-view table (~2.8 deg each)
_VIEWS = Memo(8)


def view_table(z: np.ndarray, g: int) -> tuple[np.ndarray, np.ndarray]:
    """Per cell of a cube map with g x g cells a face (``_cell``), the views that can be nearest to some
    direction in it, in index order (CSR: ``cand[start[c]:start[c + 1]]``). Every direction in a cell
    lies within its corners' largest angle rho of the cell's centre direction c, so a view further than
    angle(c, nearest view of c) + 2 rho from c is never the nearest there."""
    cells = 6 * g * g
    k = np.arange(cells)
    face, i, j = k // (g * g), (k // g) % g, k % g
    edges = np.linspace(-1.0, 1.0, g + 1)
    corners = [_face_dirs(face, edges[i + di], edges[j + dj]) for di in (0, 1) for dj in (0, 1)]
    centre = _face_dirs(face, 0.5 * (edges[i] + edges[i + 1]), 0.5 * (edges[j] + edges[j + 1]))
    rho = np.max([np.arccos(np.clip(np.sum(centre * c, axis=1), -1.0, 1.0)) for c in corners], axis=0)
    ang = np.arccos(np.clip(centre @ z.T, -1.0, 1.0))  # (cells, N)
    keep = ang <= (ang.min(axis=1) + 2.0 * rho + 1e-9)[:, None]
    start = np.concatenate([[0], np.cumsum(keep.sum(axis=1))]).astype(np.int64)
    return start, np.nonzero(keep)[1].astype(np.int64)


def _face_dirs(face: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Unit directions of the cube-map points (a, b) in [-1, 1]^2 on faces 0-5 (+x, -x, +y, -y, +z, -z)."""
    axis, sign = face // 2, np.where(face % 2 == 0, 1.0, -1.0)
    v = np.empty((len(face), 3))
    for ax in range(3):
        u_ax, w_ax = (ax + 1) % 3, (ax + 2) % 3
        sel = axis == ax
        v[sel, ax] = sign[sel]
        v[sel, u_ax] = a[sel]
        v[sel, w_ax] = b[sel]
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@nb.njit(inline="always")
def _cell(x, y, z, g):
    """The cube-map cell (``_face_dirs``' layout) of the direction (x, y, z)."""
    ax, ay, az = abs(x), abs(y), abs(z)
    if ax >= ay and ax >= az:
        face, m, a, b = (0 if x > 0 else 1), ax, y, z
    elif ay >= az:
        face, m, a, b = (2 if y > 0 else 3), ay, z, x
    else:
        face, m, a, b = (4 if z > 0 else 5), az, x, y
    i = min(int((a / m + 1.0) * 0.5 * g), g - 1)
    j = min(int((b / m + 1.0) * 0.5 * g), g - 1)
    return (face * g + i) * g + j


@nb.njit(inline="always")
def _nearest_view(x, y, w, z, start, cand, g):
    """The view of ``z`` nearest the unit direction (x, y, w) by ``view_table``'s candidates."""
    c = _cell(x, y, w, g)
    best = -2.0
    bi = 0
    for k in range(start[c], start[c + 1]):
        n = cand[k]
        d = x * z[n, 0] + y * z[n, 1] + w * z[n, 2]
        if d > best:
            best = d
            bi = n
    return bi


@nb.njit(parallel=True, cache=True)
def _nearest_in_table(dirs, z, start, cand, g):
    M = dirs.shape[0]
    out = np.empty(M, np.int64)
    for m in nb.prange(M):
        out[m] = _nearest_view(dirs[m, 0], dirs[m, 1], dirs[m, 2], z, start, cand, g)
    return out


@nb.njit(inline="always")
def _project_point(p_obj, k, R, t, m, fx, fy, cx, cy):
    """Pixel (u, v) of model point ``p_obj[k]`` at pose m (``camera.project`` of ``p @ R.T + t``)."""
    q0, q1, q2 = float(p_obj[k, 0]), float(p_obj[k, 1]), float(p_obj[k, 2])
    X = q0 * R[m, 0, 0] + q1 * R[m, 0, 1] + q2 * R[m, 0, 2] + t[m, 0]
    Y = q0 * R[m, 1, 0] + q1 * R[m, 1, 1] + q2 * R[m, 1, 2] + t[m, 1]
    Z = q0 * R[m, 2, 0] + q1 * R[m, 2, 1] + q2 * R[m, 2, 2] + t[m, 2]
    return fx * X / Z + cx, fy * Y / Z + cy


@nb.njit(parallel=True, cache=True)
def _evaluate(p_obj, idx, prv, nxt, views, R, t, fx, fy, cx, cy, dt, ou, ov, scale, dt_tau_px, tau_px,
              score_px):
    """``coarse.evaluate`` compiled (its arithmetic, one pose per thread): mean directional chamfer cost
    (full-resolution px, each point's truncated at ``tau_px``) and support score of M posed templates,
    bilinear in space and linear across channels (``chamfer.sample``) on ``dt`` (C, H, W) float32 whose
    pixel (0, 0) lies at full-resolution ``(ou, ov)`` (``DistanceTensor.to_grid``); ``dt_tau_px``
    outside it (the tensor's own tau)."""
    M = views.shape[0]
    P = idx.shape[1]
    C, H, W = dt.shape
    cost = np.empty(M)
    score = np.empty(M)
    for m in nb.prange(M):
        n = views[m]
        acc = 0.0
        hits = 0
        for i in range(P):
            u_p, v_p = _project_point(p_obj, idx[n, i], R, t, m, fx, fy, cx, cy)
            u_n, v_n = _project_point(p_obj, nxt[n, i], R, t, m, fx, fy, cx, cy)
            u_b, v_b = _project_point(p_obj, prv[n, i], R, t, m, fx, fy, cx, cy)
            th = math.atan2(v_n - v_b, u_n - u_b) % math.pi
            u = (u_p - ou + 0.5) * scale - 0.5
            v = (v_p - ov + 0.5) * scale - 0.5
            if u >= 0 and u <= W - 1 and v >= 0 and v <= H - 1:
                uc = min(max(u, 0.0), W - 1.0001)
                vc = min(max(v, 0.0), H - 1.0001)
                u0 = int(math.floor(uc))
                v0 = int(math.floor(vc))
                fu, fv = uc - u0, vc - v0
                cf = (th * (C / math.pi)) % C
                c0 = int(math.floor(cf)) % C
                c1 = (c0 + 1) % C
                fc = cf - math.floor(cf)
                b0 = ((1 - fv) * ((1 - fu) * dt[c0, v0, u0] + fu * dt[c0, v0, u0 + 1])
                      + fv * ((1 - fu) * dt[c0, v0 + 1, u0] + fu * dt[c0, v0 + 1, u0 + 1]))
                b1 = ((1 - fv) * ((1 - fu) * dt[c1, v0, u0] + fu * dt[c1, v0, u0 + 1])
                      + fv * ((1 - fu) * dt[c1, v0 + 1, u0] + fu * dt[c1, v0 + 1, u0 + 1]))
                val = ((1 - fc) * b0 + fc * b1) / scale
            else:
                val = dt_tau_px / scale
            acc += min(val, tau_px)
            if val <= score_px:
                hits += 1
        cost[m] = acc / P
        score[m] = hits / P
    return cost, score


def evaluate_poses(bank: TemplateBank, views: np.ndarray, R: np.ndarray, t: np.ndarray, intr: Intrinsics,
                   dtt: DistanceTensor, n_points: int, score_px: float, tau_px: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``coarse.evaluate(bank, views, R, t, intr.K, dtt, n_points, score_px, tau_px)`` by ``_evaluate``."""
    idx, prv, nxt = border_triplets(bank, n_points)
    ou, ov = (float(x) for x in dtt.origin_uv)
    return _evaluate(np.asarray(bank.p_obj), idx, prv, nxt, np.asarray(views, np.int64),
                     np.ascontiguousarray(R), np.ascontiguousarray(t), intr.fx, intr.fy, intr.cx, intr.cy,
                     dtt.dt, ou, ov, float(dtt.scale), float(dtt.tau_px), float(tau_px), float(score_px))


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
                best_only: bool = False, group: np.ndarray | None = None) -> np.ndarray:
    """(M,) mean directional chamfer cost of M poses, px of ``dtt``'s grid x DT_QUANT (nearest pixel);
    inf where it reaches ``limit_q`` (and, with ``best_only``, where it cannot beat the best; of its
    ``group`` (M,) int >= 0, if given)."""
    if len(R) == 0:
        return np.zeros(0)
    z = view_dirs_obj(bank)
    start, cand = _VIEWS.get(bank, VIEW_TABLE_CELLS, lambda: view_table(z, VIEW_TABLE_CELLS))
    if bank.symmetry_axis_obj is None:  # the kernel picks each pose's view, as scoring_poses would
        views, R2, t2 = _NO_GROUP, R, t
    else:
        views, R2, t2 = scoring_poses(bank, R, t)
    mid, direction = _points(bank, n_points)
    return _score(dt_q, tau_q, dtt.scale, dtt.origin_uv[0], dtt.origin_uv[1], intr.fx, intr.fy, intr.cx,
                  intr.cy, mid, direction, views.astype(np.int64), np.ascontiguousarray(R2, np.float64),
                  np.ascontiguousarray(t2, np.float64), dtt.n_channels, float(limit_q), best_only,
                  _NO_GROUP if group is None else np.ascontiguousarray(group, np.int64),
                  0 if group is None or len(group) == 0 else int(np.max(group)) + 1,
                  np.asarray(bank.centre_obj, np.float64), np.ascontiguousarray(z, np.float64), start, cand,
                  VIEW_TABLE_CELLS)
_NO_GROUP = np.zeros(0, np.int64)
