"""Pose errors as flat pure functions (BOP toolkit style), plus the paper's Table VI columns.

Every function takes an estimated and a ground-truth pose ``T_cam_obj`` as ``R`` (3, 3) float64 and
``t`` (3,) float64 in mm, OpenCV camera frame (``p_cam = R @ p_obj + t``); model points ``pts_obj`` are
(N, 3) float64, mm, object frame. Lower is better for every error.

Symmetry
--------
A continuous rotational symmetry (a revolved part) is an axis ``axis_obj`` (unit, object frame) through
a point ``point_obj`` (mm, object frame; the origin when None). Spinning the part by ``phi`` about it is
the rigid transform ``p -> S p + (c - S c)`` with ``S`` the rotation by ``phi`` about ``axis_obj`` and
``c = point_obj``. ``symmetry_rotations`` discretises those spins as ``(Rs, ts)`` pairs (BOP's
``{R, t}`` symmetry transformations) for the symmetry-aware errors ``mspd_px`` and ``mssd_mm``.

References: Hodan et al., "BOP challenge 2020 on 6D object localization" (MSSD, MSPD, recall);
Hinterstoisser et al., ACCV 2012 (ADD, ADD-S).
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence

import numpy as np
from scipy.spatial import ConvexHull, QhullError, cKDTree
from scipy.spatial.distance import pdist
from scipy.spatial.transform import Rotation

from service.vision.geometry.camera import project
from service.vision.geometry.frames import axis_alpha_gamma_deg, euler_xyz_deg_from_R, rotation_angle_deg

# A symmetry set: None (no symmetry), (M, 3, 3) rotations about the origin, or (Rs, ts) pairs.
Symmetries = None | np.ndarray | tuple[np.ndarray, np.ndarray]


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def wrap_deg(a):
    """Angles (any shape, degrees) wrapped to [-180, 180)."""
    return (np.asarray(a, float) + 180.0) % 360.0 - 180.0


# --- rotation and translation errors --------------------------------------------------------------


def te_mm(t_est, t_gt) -> float:
    """Translation error: ``||t_est - t_gt||``, mm."""
    return float(np.linalg.norm(np.asarray(t_est, float) - np.asarray(t_gt, float)))


def re_deg(R_est, R_gt) -> float:
    """Rotation error: geodesic angle of ``R_est^T R_gt``, degrees in [0, 180]."""
    return rotation_angle_deg(np.asarray(R_est, float), np.asarray(R_gt, float))


def axis_error_deg(R_est, R_gt, axis_obj) -> float:
    """Angle between the symmetry axis as estimated and as true, both in the camera frame, degrees.

    For a continuously symmetric part this is also the symmetry-aware rotation error
    ``min over spins S of re_deg(R_est, R_gt @ S)``: every rotation taking one axis direction onto
    the other turns by at least the angle between them, and the smallest one does exactly that.
    """
    a = _unit(axis_obj)
    ae = np.asarray(R_est, float) @ a
    ag = np.asarray(R_gt, float) @ a
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(ae, ag)), ae @ ag)))


# --- symmetries --------------------------------------------------------------------------------


def symmetry_rotations(axis_obj=None, point_obj=None, n: int = 360,
                       spins_deg=None) -> tuple[np.ndarray, np.ndarray]:
    """Discretised spins about a continuous symmetry axis as rigid transforms ``p -> R p + t``.

    axis_obj : (3,) direction in the object frame, or None for no symmetry (identity only).
    point_obj : (3,) mm, object frame, a point on the axis; None = the origin.
    n : number of spins, ``phi_k = 360 k / n`` degrees, k = 0..n-1 (k = 0 is the identity).
    spins_deg : (M,) degrees, explicit spins used instead of the ``n`` grid (e.g. a coarse grid plus a
        fine one around ``best_spin_deg``).
    Returns ``Rs`` (M, 3, 3) float64 and ``ts`` (M, 3) float64 mm, with M = n (1 without symmetry).
    """
    if axis_obj is None:
        return np.eye(3)[None], np.zeros((1, 3))
    a = _unit(axis_obj)
    if spins_deg is None:
        spins_deg = np.arange(n) * (360.0 / n)
    phis = np.deg2rad(np.asarray(spins_deg, float).ravel())
    Rs = Rotation.from_rotvec(phis[:, None] * a[None]).as_matrix()
    if point_obj is None:
        return Rs, np.zeros((len(Rs), 3))
    c = np.asarray(point_obj, float)
    return Rs, c[None] - Rs @ c


def best_spin_deg(R_est, R_gt, axis_obj) -> float:
    """The spin ``phi`` about ``axis_obj`` that brings ``R_gt @ S(phi)`` closest to ``R_est``, degrees.

    Closed form: ``trace(R_est^T R_gt S(phi)) = c + A cos(phi) + B sin(phi)`` (Rodrigues), maximised at
    ``atan2(B, A)``. Used to centre a fine spin grid for the symmetry-aware point errors.
    """
    a = _unit(axis_obj)
    M = np.asarray(R_est, float).T @ np.asarray(R_gt, float)
    ax = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    A = np.trace(M) - a @ M @ a
    B = np.trace(M @ ax)
    return float(np.degrees(np.arctan2(B, A)))


def pose_symmetries(R_est, R_gt, axis_obj=None, point_obj=None, n: int = 360, *,
                    fine_half_width_deg: float = 1.0,
                    fine_step_deg: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Spins for comparing one estimate: the ``n`` grid plus a fine grid around ``best_spin_deg``.

    Removes most of the grid's discretisation from MSPD/MSSD (a 0.5 deg spin moves a point 30 mm off
    the axis by 0.26 mm, about 1 px at 300 mm). Identity only without symmetry.
    """
    if axis_obj is None:
        return symmetry_rotations(None)
    phi = best_spin_deg(R_est, R_gt, axis_obj)
    fine = phi + np.arange(-fine_half_width_deg, fine_half_width_deg + fine_step_deg / 2, fine_step_deg)
    spins = np.concatenate([np.arange(n) * (360.0 / n), fine])
    return symmetry_rotations(axis_obj, point_obj, spins_deg=spins)


def _as_syms(syms: Symmetries) -> tuple[np.ndarray, np.ndarray]:
    if syms is None:
        return np.eye(3)[None], np.zeros((1, 3))
    if isinstance(syms, tuple):
        Rs, ts = syms
        return np.asarray(Rs, float).reshape(-1, 3, 3), np.asarray(ts, float).reshape(-1, 3)
    Rs = np.asarray(syms, float).reshape(-1, 3, 3)
    return Rs, np.zeros((len(Rs), 3))


def _transform(R, t, pts) -> np.ndarray:
    return np.asarray(pts, float) @ np.asarray(R, float).T + np.asarray(t, float)


def _gt_under_syms(R_g, t_g, pts_obj, syms: Symmetries) -> np.ndarray:
    """(M, N, 3) mm, camera frame: the gt model points under each symmetry transform."""
    Rs, ts = _as_syms(syms)
    R_g = np.asarray(R_g, float)
    R_sym = R_g[None] @ Rs  # (M, 3, 3)
    t_sym = ts @ R_g.T + np.asarray(t_g, float)  # (M, 3)
    pts = np.asarray(pts_obj, float)
    return np.matmul(pts[None], R_sym.transpose(0, 2, 1)) + t_sym[:, None, :]


# --- point-distance errors ---------------------------------------------------------------------


def mspd_px(R_e, t_e, R_g, t_g, K, pts_obj, syms: Symmetries = None) -> float:
    """Maximum Symmetry-aware Projection Distance (BOP), pixels.

    ``min over symmetries S of max over points p of ||proj(R_e p + t_e) - proj(R_g S p + t_g')||``.
    K : (3, 3) pinhole intrinsics. syms : see ``Symmetries`` (None = no symmetry). BOP scales the
    result by 640 / image width before thresholding; that is the caller's job.
    """
    K = np.asarray(K, float)
    uv_e = project(_transform(R_e, t_e, pts_obj), K)  # (N, 2)
    p_g = _gt_under_syms(R_g, t_g, pts_obj, syms)  # (M, N, 3)
    uv_g = project(p_g.reshape(-1, 3), K).reshape(p_g.shape[0], p_g.shape[1], 2)
    d2 = np.sum((uv_g - uv_e[None]) ** 2, axis=2)  # (M, N) squared pixel distances
    return float(np.sqrt(np.min(np.max(d2, axis=1))))


def mssd_mm(R_e, t_e, R_g, t_g, pts_obj, syms: Symmetries = None) -> float:
    """Maximum Symmetry-aware Surface Distance (BOP), mm: as ``mspd_px`` but 3D distances."""
    p_e = _transform(R_e, t_e, pts_obj)
    p_g = _gt_under_syms(R_g, t_g, pts_obj, syms)
    d2 = np.sum((p_g - p_e[None]) ** 2, axis=2)
    return float(np.sqrt(np.min(np.max(d2, axis=1))))


def add_mm(R_e, t_e, R_g, t_g, pts_obj) -> float:
    """ADD: mean distance between corresponding model points, mm."""
    d = _transform(R_e, t_e, pts_obj) - _transform(R_g, t_g, pts_obj)
    return float(np.mean(np.linalg.norm(d, axis=1)))


def add_s_mm(R_e, t_e, R_g, t_g, pts_obj) -> float:
    """ADD-S (ADI): mean over gt points of the distance to the closest estimated point, mm."""
    p_e = _transform(R_e, t_e, pts_obj)
    p_g = _transform(R_g, t_g, pts_obj)
    d, _ = cKDTree(p_e).query(p_g, k=1)
    return float(np.mean(d))


def diameter_mm(pts_obj) -> float:
    """Largest distance between two model points, mm (BOP's object diameter)."""
    pts = np.asarray(pts_obj, float)
    if len(pts) > 4:
        with contextlib.suppress(QhullError):  # degenerate (flat) point sets: use all points
            pts = pts[ConvexHull(pts).vertices]
    return float(pdist(pts).max()) if len(pts) > 1 else 0.0


def recall(errors: Sequence[float] | np.ndarray, threshold: float) -> float:
    """Fraction of errors strictly below ``threshold`` (BOP's ``e < th``); NaN/inf count as misses.

    An empty sequence gives NaN.
    """
    e = np.asarray(errors, float)
    if e.size == 0:
        return float("nan")
    return float(np.mean(np.where(np.isfinite(e), e, np.inf) < threshold))


# --- the paper's Table VI columns ------------------------------------------------------------------


def paper_errors(R_e, t_e, R_g, t_g, axis_obj=None, point_obj=None) -> dict[str, float | bool]:
    """Absolute per-component errors as in the paper's Table VI.

    Returns a dict:
    - ``tx_mm``, ``ty_mm``, ``tz_mm``: ``|t_e - t_g|`` per camera axis, mm. For a symmetric part whose
      axis does not pass through the origin, measured at ``point_obj`` (``R @ c + t``), which does
      not depend on the spin.
    - symmetric part (``axis_obj`` given): the axis in the camera frame written as
      ``a = Rx(alpha) @ Rz(gamma) @ e_y`` (``frames.axis_alpha_gamma_deg``); ``rx_deg = |alpha_e - alpha_g|``
      (wrapped to [-180, 180]), ``rz_deg = |gamma_e - gamma_g|``; ``ry_deg`` is NaN (the spin is free);
      ``re_deg`` is the symmetry-aware rotation error, which equals ``axis_error_deg``.
    - non-symmetric part: ``rx_deg``, ``ry_deg``, ``rz_deg`` are the wrapped absolute differences of
      ``euler_xyz_deg``; ``re_deg`` the geodesic rotation error.
    - ``symmetric``: whether the symmetric formulas were used.
    """
    R_e = np.asarray(R_e, float)
    R_g = np.asarray(R_g, float)
    t_e = np.asarray(t_e, float)
    t_g = np.asarray(t_g, float)
    if axis_obj is not None and point_obj is not None:
        c = np.asarray(point_obj, float)
        dt = np.abs((R_e @ c + t_e) - (R_g @ c + t_g))
    else:
        dt = np.abs(t_e - t_g)
    out: dict[str, float | bool] = {"tx_mm": float(dt[0]), "ty_mm": float(dt[1]), "tz_mm": float(dt[2])}
    if axis_obj is not None:
        a = _unit(axis_obj)
        al_e, ga_e = axis_alpha_gamma_deg(R_e @ a)
        al_g, ga_g = axis_alpha_gamma_deg(R_g @ a)
        out.update(rx_deg=float(abs(wrap_deg(al_e - al_g))), ry_deg=float("nan"),
                   rz_deg=float(abs(ga_e - ga_g)), re_deg=axis_error_deg(R_e, R_g, a), symmetric=True)
    else:
        d = np.abs(wrap_deg(euler_xyz_deg_from_R(R_e) - euler_xyz_deg_from_R(R_g)))
        out.update(rx_deg=float(d[0]), ry_deg=float(d[1]), rz_deg=float(d[2]), re_deg=re_deg(R_e, R_g),
                   symmetric=False)
    return out
