"""Pose refinement (improves on the paper's section II.C): robust least squares on image edges.

The paper refines with Levenberg-Marquardt on matched point pairs kept under a median threshold
(eq. 18), and its Table VIII shows rotation getting worse. Here:

- the model's **outer border at the current pose** (sub-pixel rim points with the 3D model point
  each came from, ``templates.border_at_pose``) is projected with the pose being refined; each
  point's image orientation is the projection of its 3D border tangent, so it moves continuously
  with the pose;
- **residual "dt"**: per border point, the directional chamfer distance read from
  DT3 of the image's LSD segments at the projected point, bilinear in the image and linear,
  cyclic across orientation channels (smooth and sub-pixel, analytic Jacobian);
- **residual "line"** (final iterations): the signed distance from the projected point to the
  line of the nearest LSD segment of matching orientation, matched afresh every outer iteration
  (point-to-line ICP). LSD endpoints are sub-pixel, so this is free of the DT's pixel
  quantisation; ``bench/refine_from_gt.py`` measures both;
- robust least squares (``lsq.least_squares``: scipy's "trf" trust region, without its wrapper) over
  6 DoF: a rotation increment (3-vector in the camera frame, exact SO(3) Jacobian) about the model's
  centre and the centre's translation in mm; for a part with continuous rotational symmetry the
  increment is perpendicular to the axis (the spin is unobservable) and the result is reported for
  the canonical spin; with ``distance_mm`` the object origin's camera z is held at that value; a
  part resting on a plane (``normal_cam``) is refined on it in 3 DoF (a spin about the normal and two
  slides along the plane), so its lowest point stays on the plane;
- robust loss (``soft_l1`` default, ``huber``, ``linear``) or the paper's eq. 18 median threshold
  (``loss="median"``, for comparison);
- the border is re-extracted when the pose has moved more than ~2 px / 1 deg from where it was
  extracted (outer loop);
- never worse: the refined pose is kept only when, on the same border points, its DT3 distances
  capped at ``score_px`` average no more than the start pose's and its verification score (fraction
  of border points within ``score_px`` of an edge of matching orientation) is at most
  ``SCORE_SLACK`` below the start pose's;
- lens distortion: LSD runs on the image as taken; segment endpoints (split into short pieces)
  are undistorted once and everything else works in the ideal pinhole camera.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numba as nb
import numpy as np

from service.vision import threads
from service.vision.bank import TemplateBank
from service.vision.estimate.chamfer import DistanceTensor, segment_distance_tensor
from service.vision.estimate.edges import Segments, detect_segments, undistort_segments
from service.vision.estimate.interior import unexplained_edge_ratio
from service.vision.estimate.lsq import LsqResult, least_squares
from service.vision.geometry.camera import Intrinsics, project_distorted
from service.vision.geometry.frames import Pose, canonical_spin, rotation_angle_deg
from service.vision.geometry.rotations import PoseParams
from service.vision.geometry.silhouette import Border, border_with_tangents

ROI_MARGIN_PX = 30  # edges are detected in the bbox of the projected model plus this margin
BORDER_SPACING_PX = 3.0  # spacing of the border points used in the residuals
# border_at_pose supersampling: the traced points are snapped onto the contour-generator edges, so
# 2x gave the line stage no measurable gain on the paper set (bench/accuracy.py) for ~8 ms per trace.
BORDER_SUPERSAMPLE = 1
TANGENT_STEP_MM = 1.0  # border tangent finite step (object frame) for the image orientation
REEXTRACT_PX = 2.0  # re-extract the border once any point has moved this far ...
REEXTRACT_DEG = 1.0  # ... or the rotation has changed this much since the extraction
# The interior check, started in the background at the DT stage's pose, stands for a final pose whose
# border lies within this of it (the check erodes the silhouette by interior.ERODE_PX = 5 px anyway).
INTERIOR_REUSE_PX = 1.5
DT_SCALE = 1.0  # DT3 grid per full-resolution pixel (exact distances to segments at pixel centres)
DT_TAU_PX = 12.0  # DT3 truncation for refinement (full-res px): the basin, not the coarse search
DT_F_SCALE_PX = 4.0  # robust-loss scale of the DT stage (smaller scales converge much slower)
DT_TOL = 1e-2  # least_squares ftol/xtol of the DT stage (the line stage polishes)
LINE_TOL = 1e-6  # ... of the line stage
LINE_MATCH_DEG = 20.0  # "line" residual: orientation gate between border point and LSD segment
LINE_GATE_PX = 3.0  # ... and distance gate (full-resolution px)
LINE_ROUNDS = 4  # line-stage rounds (match, solve, re-match ...)
MEDIAN_CONST_PX = 2.0  # eq. 18: tr = max(median(residual), tr_const)
# Never worse: the refined pose is kept when its DT3 distances, each capped at score_px, average no
# more than the start pose's, and its score (fraction within score_px) is at most this much lower. The
# score alone is a step function: moving sub-pixel it trades a border point across the 3 px line
# for many points drawn closer, and a strict "score >= start" rejected half the paper set's refinements.
SCORE_SLACK = 0.01
LOSSES = ("soft_l1", "huber", "linear", "cauchy", "median")


@dataclass(frozen=True)
class RefineResult:
    pose: Pose  # T_cam_obj (canonical spin for a symmetric part)
    cost: float  # mean |residual| of the inliers, full-resolution px
    score: float  # 0..1 fraction of border points within score_px of an edge of matching orientation
    iterations: int  # least-squares iterations (function evaluations' Jacobians), all stages
    inlier_ratio: float  # 0..1 fraction of border points counted as inliers at the end
    converged: bool  # the solver stopped on a tolerance and the refined pose was kept
    # image edges inside the returned pose's silhouette that the model does not explain, per unit of
    # perimeter (interior.unexplained_edge_ratio on the full-resolution ROI segments); nan with
    # ``refine_pose``'s ``interior_later``: ``unexplained_later()`` gives it then
    unexplained: float = 0.0
    unexplained_later: Callable[[], float] | None = field(default=None, repr=False, compare=False)


# --- border points at a pose --------------------------------------------------------------------


def border_points(bank: TemplateBank, pose: Pose, intr: Intrinsics, image_size, *,
                  spacing_px: float | None = None, supersample: int | None = None) -> Border:
    """The bank's mesh's outer border at ``pose`` with 3D tangents (``silhouette.border_with_tangents``)
    at the refinement's spacing and supersampling unless given."""
    spacing_px = BORDER_SPACING_PX if spacing_px is None else spacing_px
    supersample = BORDER_SUPERSAMPLE if supersample is None else supersample
    return border_with_tangents(bank.vertices_mm, bank.faces, pose, intr, image_size, spacing_px=spacing_px,
                                supersample=supersample)


def _project_jac(pc: np.ndarray, intr: Intrinsics, Jp: np.ndarray | None = None):
    """Ideal pinhole: uv (M, 2) and, given d p_cam / dx (M, 3, n), d uv / dx (M, 2, n)."""
    x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
    iz = 1.0 / z
    uv = np.stack([intr.fx * x * iz + intr.cx, intr.fy * y * iz + intr.cy], 1)
    if Jp is None:
        return uv, None
    J = np.empty((len(pc), 2, Jp.shape[2]))
    J[:, 0] = (intr.fx * iz)[:, None] * Jp[:, 0] - (intr.fx * x * iz * iz)[:, None] * Jp[:, 2]
    J[:, 1] = (intr.fy * iz)[:, None] * Jp[:, 1] - (intr.fy * y * iz * iz)[:, None] * Jp[:, 2]
    return uv, J


def project_border(params: PoseParams, x: np.ndarray, border: Border, intr: Intrinsics,
                   with_jac: bool = True):
    """uv (M, 2), theta (M,) rad in [0, pi) and, with ``with_jac``, d uv / dx (M, 2, n) and
    d theta / dx (M, n). theta is the direction of the projected 3D border tangent."""
    h = TANGENT_STEP_MM
    P = border.p_obj
    M = len(P)
    allp = np.concatenate([P, P - h * border.tan_obj, P + h * border.tan_obj])
    pc, Jp = params.points(x, allp, with_jac)
    uv_all, J_all = _project_jac(pc, intr, Jp)
    uv, ua, ub = uv_all[:M], uv_all[M:2 * M], uv_all[2 * M:]
    d = ub - ua
    theta = np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi)
    if not with_jac:
        return uv, theta, None, None
    duv = J_all[:M]
    dd = J_all[2 * M:] - J_all[M:2 * M]
    n2 = np.maximum((d ** 2).sum(1), 1e-12)
    dth = (d[:, 0, None] * dd[:, 1] - d[:, 1, None] * dd[:, 0]) / n2[:, None]
    return uv, theta, duv, dth


def _kernel_pose(params: PoseParams, x: np.ndarray, with_jac: bool):
    """The compiled residual loops' pose (``_point_uv``): (R, offset, centre, JB, dz_dr, TB), an object
    point p mapping to R (p - centre) + offset; with ``with_jac`` the rotation Jacobian's pieces of
    ``PoseParams._pose_jac``, else zeros (as ``PoseParams.points`` without a Jacobian: p R^T + t), and
    the translation parameters' camera-frame directions ``PoseParams.T``."""
    if with_jac:
        pose, JB, dz_dr = params._pose_jac(x)
        centre, offset = params.c, pose.R @ params.c + pose.t_mm
    else:
        pose = params.pose(x)
        centre, offset = np.zeros(3), pose.t_mm
        JB, dz_dr = np.zeros((3, params.nr)), np.zeros(params.nr)
    return (np.ascontiguousarray(pose.R, np.float64), np.asarray(offset, np.float64),
            np.asarray(centre, np.float64), np.ascontiguousarray(JB, np.float64),
            np.asarray(dz_dr, np.float64), np.ascontiguousarray(params.T, np.float64))


def dt_residuals(params: PoseParams, x: np.ndarray, border: Border, intr: Intrinsics, dtt: DistanceTensor,
                 with_jac: bool = True):
    """The "dt" residual: directional chamfer distance (full-res px) per border point, and
    its Jacobian (M, n): ``project_border`` and ``chamfer.sample_with_grad`` in one compiled loop (their
    numpy steps on a few hundred points cost ~0.25 ms an evaluation, mostly call overhead)."""
    r, J = _dt_kernel(np.ascontiguousarray(border.p_obj, np.float64),
                      np.ascontiguousarray(border.tan_obj, np.float64), TANGENT_STEP_MM,
                      *_kernel_pose(params, x, with_jac), params.n,
                      float(intr.fx), float(intr.fy), float(intr.cx), float(intr.cy), dtt.dt,
                      float(dtt.origin_uv[0]), float(dtt.origin_uv[1]), float(dtt.scale), float(dtt.tau_px),
                      with_jac)
    return r, (J if with_jac else None)


@nb.njit(cache=True, inline="always", error_model="numpy")
def _point_uv(p, R, offset, centre, JB, dz_dr, TB, n, fx, fy, cx, cy, with_jac, uv, duv):
    """One object point: its pixel into ``uv`` (2,) and, ``with_jac``, d uv / dx into ``duv`` (2, n)."""
    q0 = R[0, 0] * (p[0] - centre[0]) + R[0, 1] * (p[1] - centre[1]) + R[0, 2] * (p[2] - centre[2])
    q1 = R[1, 0] * (p[0] - centre[0]) + R[1, 1] * (p[1] - centre[1]) + R[1, 2] * (p[2] - centre[2])
    q2 = R[2, 0] * (p[0] - centre[0]) + R[2, 1] * (p[1] - centre[1]) + R[2, 2] * (p[2] - centre[2])
    x, y, z = q0 + offset[0], q1 + offset[1], q2 + offset[2]
    iz = 1.0 / z
    uv[0] = fx * x * iz + cx
    uv[1] = fy * y * iz + cy
    if not with_jac:
        return
    nr = JB.shape[1]
    au, av = fx * iz, fx * x * iz * iz
    bu, bv = fy * iz, fy * y * iz * iz
    for k in range(n):
        if k < nr:  # d(exp(w) v)/dw = -[v]x J_l: column k is (J_l B)[:, k] x q
            jx = JB[1, k] * q2 - JB[2, k] * q1
            jy = JB[2, k] * q0 - JB[0, k] * q2
            jz = JB[0, k] * q1 - JB[1, k] * q0 + dz_dr[k]
        else:
            jx, jy, jz = TB[0, k - nr], TB[1, k - nr], TB[2, k - nr]
        duv[0, k] = au * jx - av * jz
        duv[1, k] = bu * jy - bv * jz


@nb.njit(cache=True, error_model="numpy", nogil=True)
def _dt_kernel(P, T, h, R, offset, centre, JB, dz_dr, TB, n, fx, fy, cx, cy, dt, ou, ov, scale, tau,
               with_jac):
    M = P.shape[0]
    C, H, W = dt.shape
    r = np.empty(M)
    J = np.zeros((M, n)) if with_jac else np.zeros((0, n))
    uv, ua, ub = np.empty(2), np.empty(2), np.empty(2)
    duv, dua, dub = np.zeros((2, n)), np.zeros((2, n)), np.zeros((2, n))
    pa, pb = np.empty(3), np.empty(3)
    for i in range(M):
        for k in range(3):
            pa[k] = P[i, k] - h * T[i, k]
            pb[k] = P[i, k] + h * T[i, k]
        _point_uv(P[i], R, offset, centre, JB, dz_dr, TB, n, fx, fy, cx, cy, with_jac, uv, duv)
        _point_uv(pa, R, offset, centre, JB, dz_dr, TB, n, fx, fy, cx, cy, with_jac, ua, dua)
        _point_uv(pb, R, offset, centre, JB, dz_dr, TB, n, fx, fy, cx, cy, with_jac, ub, dub)
        d0, d1 = ub[0] - ua[0], ub[1] - ua[1]
        theta = np.arctan2(d1, d0) % np.pi
        # chamfer.sample_with_grad at the grid point
        gu = (uv[0] - ou + 0.5) * scale - 0.5
        gv = (uv[1] - ov + 0.5) * scale - 0.5
        if not (gu >= 0 and gu <= W - 1 and gv >= 0 and gv <= H - 1):
            r[i] = tau / scale
            continue  # zero gradient outside the grid
        uc, vc = min(gu, W - 1.0001), min(gv, H - 1.0001)
        u0, v0 = int(np.floor(uc)), int(np.floor(vc))
        fu, fv = uc - u0, vc - v0
        cf = (theta * (C / np.pi)) % C
        c0 = int(np.floor(cf)) % C
        c1 = (c0 + 1) % C
        fc = cf - np.floor(cf)
        a, b = np.float64(dt[c0, v0, u0]), np.float64(dt[c0, v0, u0 + 1])
        c, d = np.float64(dt[c0, v0 + 1, u0]), np.float64(dt[c0, v0 + 1, u0 + 1])
        A0 = (1 - fv) * ((1 - fu) * a + fu * b) + fv * ((1 - fu) * c + fu * d)
        Au0 = (1 - fv) * (b - a) + fv * (d - c)
        Av0 = (1 - fu) * (c - a) + fu * (d - b)
        a, b = np.float64(dt[c1, v0, u0]), np.float64(dt[c1, v0, u0 + 1])
        c, d = np.float64(dt[c1, v0 + 1, u0]), np.float64(dt[c1, v0 + 1, u0 + 1])
        A1 = (1 - fv) * ((1 - fu) * a + fu * b) + fv * ((1 - fu) * c + fu * d)
        Au1 = (1 - fv) * (b - a) + fv * (d - c)
        Av1 = (1 - fu) * (c - a) + fu * (d - b)
        r[i] = ((1 - fc) * A0 + fc * A1) / scale
        if not with_jac:
            continue
        g_u = (1 - fc) * Au0 + fc * Au1
        g_v = (1 - fc) * Av0 + fc * Av1
        g_th = (A1 - A0) * (C / np.pi) / scale
        n2 = max(d0 * d0 + d1 * d1, 1e-12)
        for k in range(n):
            dth = (d0 * (dub[1, k] - dua[1, k]) - d1 * (dub[0, k] - dua[0, k])) / n2
            # d grid / d uv = scale; r = val / scale
            J[i, k] = g_u * duv[0, k] + g_v * duv[1, k] + g_th * dth
    return r, J


# --- point-to-LSD-line residual -----------------------------------------------------------------


@dataclass(frozen=True)
class LineMatch:
    idx: np.ndarray  # (K,) border point indices with a matched segment
    normal: np.ndarray  # (K, 2) unit normal of the matched segment's line
    offset: np.ndarray  # (K,) normal . point_on_line


def match_lines(uv: np.ndarray, theta: np.ndarray, seg: Segments, *, gate_px: float = LINE_GATE_PX,
                gate_deg: float = LINE_MATCH_DEG) -> LineMatch:
    """Nearest segment (point-to-segment distance, endpoints extended by 1 px) of orientation
    within ``gate_deg`` and distance within ``gate_px`` for each border point."""
    if len(seg) == 0 or len(uv) == 0:
        return LineMatch(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0))
    p0 = seg.uv0.astype(np.float64)
    p1 = seg.uv1.astype(np.float64)
    d = p1 - p0
    L = np.maximum(np.linalg.norm(d, axis=1), 1e-9)
    dirn = d / L[:, None]
    st = np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi)
    cos_gate = math.cos(math.radians(gate_deg))
    # Each segment's box, widened by its 1 px extension and the gate (and a pixel to spare): a point only
    # compares the segments whose box holds it; the others lie beyond its gate.
    reach = gate_px + 2.0
    lo = np.minimum(p0, p1) - reach
    hi = np.maximum(p0, p1) + reach
    best_i = _nearest_segments(np.ascontiguousarray(uv, np.float64), np.asarray(theta, np.float64), p0, dirn,
                               L, st, lo, hi, cos_gate, float(gate_px))
    idx = np.flatnonzero(best_i >= 0)
    j = best_i[idx]
    nrm = np.stack([-dirn[j, 1], dirn[j, 0]], 1)
    off = np.einsum("ij,ij->i", nrm, p0[j])
    return LineMatch(idx, nrm, off)


@nb.njit(cache=True, error_model="numpy", nogil=True)
def _nearest_segments(uv, theta, p0, dirn, L, st, lo, hi, cos_gate, gate_px):
    """Per point, the index of the nearest segment within the gates (the first of equals), or -1."""
    out = np.full(len(uv), -1, np.int64)
    for m in range(len(uv)):
        u, v = uv[m, 0], uv[m, 1]
        best = np.inf
        for k in range(len(p0)):
            if not (hi[k, 0] >= u and lo[k, 0] <= u and hi[k, 1] >= v and lo[k, 1] <= v):
                continue
            if abs(math.cos(theta[m] - st[k])) < cos_gate:  # |cos| of the undirected difference
                continue
            r0, r1 = u - p0[k, 0], v - p0[k, 1]
            t = min(max(r0 * dirn[k, 0] + r1 * dirn[k, 1], -1.0), L[k] + 1.0)
            e0, e1 = r0 - t * dirn[k, 0], r1 - t * dirn[k, 1]
            dist = math.sqrt(e0 * e0 + e1 * e1)
            if dist < best:
                best = dist
                if dist <= gate_px:
                    out[m] = k
        if best > gate_px:
            out[m] = -1
    return out


def line_residuals(params: PoseParams, x: np.ndarray, border: Border, intr: Intrinsics, match: LineMatch,
                   with_jac: bool = True):
    """Signed distance (full-res px) of each matched border point to its segment's line (one compiled
    loop, as ``dt_residuals``)."""
    P = np.ascontiguousarray(border.p_obj[match.idx], np.float64)
    r, J = _line_kernel(P, *_kernel_pose(params, x, with_jac), params.n,
                        float(intr.fx), float(intr.fy), float(intr.cx), float(intr.cy),
                        np.ascontiguousarray(match.normal, np.float64), np.asarray(match.offset, np.float64),
                        with_jac)
    return r, (J if with_jac else None)


@nb.njit(cache=True, error_model="numpy", nogil=True)
def _line_kernel(P, R, offset, centre, JB, dz_dr, TB, n, fx, fy, cx, cy, normal, line_offset, with_jac):
    M = P.shape[0]
    r = np.empty(M)
    J = np.zeros((M, n)) if with_jac else np.zeros((0, n))
    uv, duv = np.empty(2), np.zeros((2, n))
    for i in range(M):
        _point_uv(P[i], R, offset, centre, JB, dz_dr, TB, n, fx, fy, cx, cy, with_jac, uv, duv)
        r[i] = (normal[i, 0] * uv[0] + normal[i, 1] * uv[1]) - line_offset[i]
        if with_jac:
            for k in range(n):
                J[i, k] = normal[i, 0] * duv[0, k] + normal[i, 1] * duv[1, k]
    return r, J


# --- image side ---------------------------------------------------------------------------------


def _roi(bank: TemplateBank, pose: Pose, intr: Intrinsics, image_size, margin: int, *, distorted: bool):
    w, h = int(image_size[0]), int(image_size[1])
    pc = pose.apply(bank.vertices_mm)
    pc = pc[pc[:, 2] > 1e-3]
    if len(pc) == 0:
        return None
    uv = project_distorted(pc, intr) if distorted else project_distorted(
        pc, intr.pinhole())
    u0 = max(int(np.floor(uv[:, 0].min())) - margin, 0)
    v0 = max(int(np.floor(uv[:, 1].min())) - margin, 0)
    u1 = min(int(np.ceil(uv[:, 0].max())) + margin, w - 1)
    v1 = min(int(np.ceil(uv[:, 1].max())) + margin, h - 1)
    if u1 - u0 < 8 or v1 - v0 < 8:
        return None
    return (u0, v0, u1 - u0 + 1, v1 - v0 + 1)


# --- the refinement -----------------------------------------------------------------------------


def _rho(loss: str):
    return "linear" if loss == "median" else loss


class _Views:
    """Border points seen by the ideal camera (fx x / z, fy y / z) at poses, each (points, pose) pair
    projected once: a refinement compares each new pose with the one before and with its border's."""

    def __init__(self, intr: Intrinsics):
        self.intr = intr
        self.seen: dict[tuple[int, int], tuple[np.ndarray, Pose, np.ndarray]] = {}

    def of(self, p_obj: np.ndarray, pose: Pose) -> np.ndarray:
        key = (id(p_obj), id(pose))
        if key not in self.seen:  # the entry holds both objects: their ids stay theirs
            a = pose.apply(p_obj)
            uv = np.stack([self.intr.fx * a[:, 0] / a[:, 2], self.intr.fy * a[:, 1] / a[:, 2]], 1)
            self.seen[key] = (p_obj, pose, uv)
        return self.seen[key][2]

    def moved_px(self, p_obj: np.ndarray, a: Pose, b: Pose) -> float:
        """Largest image displacement (px) of the points from pose ``a`` to pose ``b``."""
        if not len(p_obj):
            return 0.0
        return float(np.max(np.linalg.norm(self.of(p_obj, a) - self.of(p_obj, b), axis=1)))


def verify(border: Border, pose: Pose, intr: Intrinsics, dtt: DistanceTensor, *, score_px: float
           ) -> tuple[float, float, float]:
    """(score, cost, capped) of ``border`` projected at ``pose``: the fraction of border points within
    ``score_px`` of an image edge of matching orientation (DT3 read-out, full-res px), the mean DT3
    distance of those points, and the mean over all points of the distance capped at ``score_px``."""
    if len(border.p_obj) == 0:
        return 0.0, float("inf"), float(score_px)
    params = PoseParams(pose, np.zeros(3))
    r, _ = dt_residuals(params, np.zeros(params.n), border, intr, dtt, with_jac=False)
    ok = r <= score_px
    cost = float(r[ok].mean()) if ok.any() else float(dtt.tau_px / dtt.scale)
    return float(ok.mean()), cost, float(np.minimum(r, score_px).mean())


def _solve(fun_jac, params: PoseParams, loss: str, f_scale: float, max_nfev: int, tol: float) -> LsqResult:
    # Parameters scaled so that a unit step moves the model by ~1 px-ish amounts alike:
    # 0.01 rad about the centre and 1 mm.
    x_scale = np.r_[np.full(params.nr, 0.01), np.ones(params.n - params.nr)]
    return least_squares(fun_jac, np.zeros(params.n), x_scale=x_scale, loss=loss, f_scale=f_scale,
                         max_nfev=max_nfev, xtol=tol, ftol=tol, gtol=1e-8)


def _dt_stage(border, pose, bank, distance_mm, ideal, dtt, loss, f_scale, max_iter, normal_cam=None):
    params = PoseParams(pose, bank.centre_obj, bank.symmetry_axis_obj, distance_mm, normal_cam)
    sub, thr = border, None
    if loss == "median":  # eq. 18: keep the points under tr = max(median, tr_const), then LSQ
        r0, _ = dt_residuals(params, np.zeros(params.n), border, ideal, dtt, with_jac=False)
        thr = max(float(np.median(r0)), MEDIAN_CONST_PX)
        keep = r0 <= thr
        sub = Border(border.p_obj[keep], border.tan_obj[keep], border.pose)
    res = _solve(lambda x: dt_residuals(params, x, sub, ideal, dtt), params, _rho(loss), f_scale, max_iter,
                 DT_TOL)
    return params.pose(res.x), res, thr


def _line_stage(border, pose, bank, distance_mm, ideal, seg, loss, f_scale, max_iter, gate_px,
                normal_cam=None):
    params = PoseParams(pose, bank.centre_obj, bank.symmetry_axis_obj, distance_mm, normal_cam)
    uv, th, _, _ = project_border(params, np.zeros(params.n), border, ideal, with_jac=False)
    match = match_lines(uv, th, seg, gate_px=gate_px)
    thr = None
    if loss == "median" and len(match.idx):
        r0, _ = line_residuals(params, np.zeros(params.n), border, ideal, match, with_jac=False)
        thr = max(float(np.median(np.abs(r0))), MEDIAN_CONST_PX / 2)
        keep = np.abs(r0) <= thr
        match = LineMatch(match.idx[keep], match.normal[keep], match.offset[keep])
    if len(match.idx) < max(6, 0.2 * len(border.p_obj)):
        return None
    res = _solve(lambda x: line_residuals(params, x, border, ideal, match), params, _rho(loss), f_scale,
                 max_iter, LINE_TOL)
    return params.pose(res.x), res, thr


def _image_side(bank, pose0, grey, intr, seg, n_channels, dt_scale, tau_px):
    """ROI (ideal camera), its segments (ideal camera, full image coords) and DT3, or None."""
    H, W = grey.shape[:2]
    size = (W, H)
    distorted = intr.dist is not None
    roi_img = _roi(bank, pose0, intr, size, ROI_MARGIN_PX, distorted=distorted)
    if roi_img is None:
        return None
    if seg is None:
        seg = detect_segments(grey, scale=1.0, roi=roi_img)
    if distorted:
        seg = undistort_segments(seg, intr)
        roi = _roi(bank, pose0, intr, size, ROI_MARGIN_PX, distorted=False) or roi_img
    else:
        roi = roi_img
    c = seg.crop(*roi)
    off = np.array(roi[:2], np.float32)
    seg_roi = Segments(c.uv0 + off, c.uv1 + off, c.theta_rad, seg.image_shape)
    dtt = segment_distance_tensor(seg_roi, roi, n_channels=n_channels, scale=dt_scale,
                                  tau_px=tau_px * dt_scale)
    return roi, seg_roi, dtt


def refine_pose(bank: TemplateBank, pose0: Pose, grey: np.ndarray, intr: Intrinsics,
                seg: Segments | None = None, *, distance_mm: float | None = None, n_channels: int = 16,
                score_px: float = 3.0, loss: str = "soft_l1", max_iter: int = 30, residual: str = "dt+line",
                dt_scale: float = DT_SCALE, tau_px: float = DT_TAU_PX, f_scale_px: float = 0.5,
                dt_f_scale_px: float = DT_F_SCALE_PX, interior_later: bool = False,
                normal_cam: np.ndarray | None = None) -> RefineResult:
    """Refine ``pose0`` (T_cam_obj) against the edges of ``grey`` (H, W) uint8.

    ``seg``: LSD segments of the image at full resolution (None: detected here on the ROI around
    the projected model). ``distance_mm``: hold the object origin's camera z at this value.
    ``loss``: soft_l1 | huber | cauchy | linear | median (the paper's eq. 18 threshold).
    ``residual``: "dt" (directional chamfer only), "line" (point-to-LSD-line only) or "dt+line"
    (dt to convergence, then line for the final iterations). ``max_iter``: function evaluations
    per least-squares run. The pose returned is ``pose0`` (canonicalised) with ``converged=False``
    when the refined pose does not keep the verification score.

    ``normal_cam``: a plane's unit normal (camera frame) the part rests on at ``pose0``: the pose is
    refined on the plane, spun about its normal and slid along it (3 DoF, ``PoseParams``): in a pile the
    other parts' edges pull a free refinement off the plane (docs/method.md).

    ``interior_later``: the interior check (``unexplained``, running on the background pool) is not
    waited for: ``unexplained`` is nan and ``unexplained_later()`` waits for it (the caller's evidence
    runs meanwhile instead of the calling thread idling; the same value).
    """
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}.")
    if residual not in ("dt", "line", "dt+line"):
        raise ValueError("residual must be 'dt', 'line' or 'dt+line'.")
    H, W = grey.shape[:2]
    size = (W, H)

    def reported(p: Pose) -> Pose:  # a revolved part's pose with spin 0 about its axis
        return canonical_spin(p, bank.symmetry_axis_obj, bank.symmetry_point_obj)

    ideal = intr.pinhole()
    # A background thread overlaps the border rasterisation with LSD + DT, and the interior check
    # (unexplained_edge_ratio) with the line stage.
    fut = threads.background().submit(border_points, bank, pose0, ideal, size)
    img = _image_side(bank, pose0, grey, intr, seg, n_channels, dt_scale, tau_px)
    border = fut.result()
    if img is None or len(border.p_obj) < 6:
        return RefineResult(reported(pose0), float("inf"), 0.0, 0, 0.0, False)
    roi, seg_roi, dtt = img
    if len(seg_roi) == 0:  # nothing to refine against
        return RefineResult(reported(pose0), float("inf"), 0.0, 0, 0.0, False)
    pose, iterations, converged, thr, last = pose0, 0, False, None, None
    kind = "dt"

    views = _Views(ideal)

    def maybe_reextract(border, pose):
        if (views.moved_px(border.p_obj, border.pose, pose) > REEXTRACT_PX
                or rotation_angle_deg(border.pose.R, pose.R) > REEXTRACT_DEG):
            return border_points(bank, pose, ideal, size), True
        return border, False

    if residual in ("dt", "dt+line"):
        for _ in range(3):
            pose, res, thr = _dt_stage(border, pose, bank, distance_mm, ideal, dtt, loss, dt_f_scale_px,
                                       max_iter, normal_cam)
            iterations += int(res.njev or 0)
            converged, last = res.status > 0, res
            if residual == "dt+line":  # the line stage re-extracts if the pose moved
                break
            border, moved = maybe_reextract(border, pose)
            if not moved:
                break
        interior_pose = pose
        interior = threads.background().submit(unexplained_edge_ratio, bank, pose, ideal, seg_roi, size)
    else:
        interior_pose = interior = None

    def interior_at(p: Pose) -> float:
        if interior is not None and views.moved_px(border.p_obj, interior_pose, p) <= INTERIOR_REUSE_PX:
            return interior.result()
        return unexplained_edge_ratio(bank, p, ideal, seg_roi, size)

    def result(p: Pose, cost: float, score: float, iters: int, inliers: float, conv: bool) -> RefineResult:
        if interior_later:
            return RefineResult(reported(p), cost, score, iters, inliers, conv, float("nan"),
                                lambda: interior_at(p))
        return RefineResult(reported(p), cost, score, iters, inliers, conv, interior_at(p))

    if residual in ("line", "dt+line"):
        kind = "line"
        gate = LINE_GATE_PX if residual == "dt+line" else max(LINE_GATE_PX, 2 * score_px)
        border, _ = maybe_reextract(border, pose)
        for k in range(LINE_ROUNDS):
            out = _line_stage(border, pose, bank, distance_mm, ideal, seg_roi, loss, f_scale_px,
                              max_iter, gate, normal_cam)
            if out is None:
                break
            pose_new, res, thr = out
            iterations += int(res.njev or 0)
            converged, last = res.status > 0, res
            step_px = views.moved_px(border.p_obj, pose, pose_new)
            pose = pose_new
            border, moved = maybe_reextract(border, pose)
            if step_px < 0.05 and not moved and k >= 1:
                break

    score1, cost1, capped1 = verify(border, pose, ideal, dtt, score_px=score_px)
    # Both poses are judged on the same 3D border points (re-extracted at the refined pose): borders
    # sampled at different densities score a few tenths of a percent apart.
    score0, cost0, capped0 = verify(border, pose0, ideal, dtt, score_px=score_px)
    if last is None or score1 <= 0.0 or score1 < score0 - SCORE_SLACK or capped1 > capped0 + 1e-9:
        return result(pose0, cost0, score0, iterations, score0, False)
    r = np.abs(last.fun)
    inl_thr = thr if thr is not None else (score_px if kind == "dt" else 1.0)
    inl = r <= inl_thr
    inlier_ratio = float(min(inl.sum() / len(border.p_obj), 1.0))
    cost = float(r[inl].mean()) if inl.any() else cost1
    # The interior check reads the pose as refined: spinning a revolved part changes no pixel of it,
    # but moves the border points that interior_at compares.
    return result(pose, cost, score1, iterations, inlier_ratio, bool(converged))
