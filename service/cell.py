"""Into the robot cell: camera extrinsics, robot-frame poses, grasp points, upload plausibility.

Plain numpy; no HTTP, pydantic or cache here (``service.api.cameras`` and ``service.api.grasps``
glue it to the API). Conventions as everywhere (API.md): millimetres, the OpenCV camera frame, a
transform ``T_<to>_<from>`` as a (4, 4) float64 matrix with ``p_to = T[:3, :3] @ p_from + T[:3, 3]``;
inner frames cancel (``T_base_obj = T_base_cam @ T_cam_obj``).

Frames of the cell::

    base    the robot's base frame (z up, as robot controllers have it)
    flange  the robot's tool flange; ``T_base_flange`` is the robot pose the controller reports
    cam     the camera (OpenCV: x right, y down, z along the optical axis)
    obj     the part's CAD frame (after unit conversion)
    grasp   a gripper pose relative to the part; its approach axis (default +z of the grasp frame)
            is the direction the gripper moves in to close on the part

A camera fixed in the cell (eye-to-hand) has ``T_base_cam``; a camera on the flange (eye-in-hand)
has ``T_flange_cam`` and every shot needs the robot's ``T_base_flange`` at the moment it was taken:
``T_base_cam = T_base_flange @ T_flange_cam``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

# A rotation sent by a client (a hand-eye result, a robot pose typed from a pendant, a dataset's ground
# truth) is accepted when it is this close to orthonormal, measured as max |R R^T - I| (the largest
# entry), and then snapped to the nearest rotation: Linemod-Occluded's published poses are off by up to
# ~0.009 in places, printed poses by ~1e-6. Beyond 1e-2 an axis is more than ~0.5 deg off square: a wrong
# or mistyped matrix rather than rounding, refused.
ROTATION_ATOL = 1e-2
# ... and snapped without a warning up to this (the rounding of a pose printed with 6 decimals).
ROTATION_SILENT = 1e-6
# Upload plausibility: a part outside these sizes (largest bounding-box side) was probably declared
# in the wrong unit. Typical parts sit well inside; the suggestion aims at TYPICAL_PART_MM.
PLAUSIBLE_EXTENT_MM = (1.0, 3000.0)
TYPICAL_PART_MM = 100.0
UNIT_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}

E_Z = np.array([0.0, 0.0, 1.0])
DOWN_BASE = np.array([0.0, 0.0, -1.0])  # straight down in the robot's base frame (base z is up)


def rigid(R, t_mm) -> np.ndarray:
    """(3, 3) rotation and (3,) translation, mm -> (4, 4) float64 homogeneous transform."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, float)
    T[:3, 3] = np.asarray(t_mm, float)
    return T


def inverse(T: np.ndarray) -> np.ndarray:
    """``T_a_b`` -> ``T_b_a`` for a rigid (4, 4) transform."""
    R, t = T[:3, :3], T[:3, 3]
    return rigid(R.T, -R.T @ t)


def rotation_error(R) -> float:
    """max |R R^T - I| of a 3x3 matrix ``R``: 0 for a rotation. Raises ValueError with a clause saying what
    is wrong when ``R`` is not a 3x3 matrix of finite numbers."""
    R = np.asarray(R, float)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError("R must be a 3x3 matrix of finite numbers")
    return float(np.max(np.abs(R @ R.T - np.eye(3))))


def nearest_rotation(R) -> np.ndarray:
    """The rotation closest to ``R`` (Frobenius norm): SVD, with det +1. Raises ValueError with a
    clause saying what is wrong when ``R`` is not a rotation within ``ROTATION_ATOL``."""
    err = rotation_error(R)
    R = np.asarray(R, float)
    if err > ROTATION_ATOL:
        raise ValueError(f"R is not a rotation matrix (R @ R^T differs from the identity by up to {err:.3g}; "
                         f"allowed {ROTATION_ATOL:g}): send the 3x3 rotation row by row")
    if np.linalg.det(R) < 0:
        raise ValueError("R is a reflection (determinant -1), not a rotation: check the sign of one axis")
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt


def axes_moved_deg(R, Q) -> float:
    """The largest angle, deg, between a column (axis) of ``R`` and the same column of ``Q``."""
    R, Q = np.asarray(R, float), np.asarray(Q, float)
    cos = np.sum(R * Q, axis=0) / (np.linalg.norm(R, axis=0) * np.linalg.norm(Q, axis=0))
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).max())


def snap_warning(what: str, R_sent, R_snapped) -> str | None:
    """The warning for a rotation ``what`` snapped from ``R_sent`` (None when it was within
    ``ROTATION_SILENT`` of a rotation)."""
    err = rotation_error(R_sent)
    if err <= ROTATION_SILENT:
        return None
    return (f"{what}'s R was off orthonormal by {err:.2g} (max |R R^T - I|, accepted up to "
            f"{ROTATION_ATOL:g}) and was snapped to the nearest rotation, turning its axes by up to "
            f"{axes_moved_deg(R_sent, R_snapped):.2g} deg; send an orthonormal R to silence this")


def base_from_cam(T_base_cam: np.ndarray | None, T_flange_cam: np.ndarray | None,
                  T_base_flange: np.ndarray | None) -> np.ndarray | None:
    """``T_base_cam`` of one shot: the fixed one (eye-to-hand), or ``T_base_flange @ T_flange_cam``
    (eye-in-hand, needs the shot's robot pose), or None when the camera has no extrinsics."""
    if T_base_cam is not None:
        return T_base_cam
    if T_flange_cam is not None and T_base_flange is not None:
        return T_base_flange @ T_flange_cam
    return None


# --- grasps ------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Grasp:
    """A named gripper pose in the model frame: ``T_obj_grasp`` (4, 4), mm; ``approach`` (3,) unit
    vector in the grasp frame (the direction the gripper moves in to close on the part)."""

    name: str
    T_obj_grasp: np.ndarray
    approach: np.ndarray = field(default_factory=lambda: E_Z.copy())


@dataclass(frozen=True)
class PlacedGrasp:
    """A grasp where the part was found. ``T_cam_grasp`` always; ``T_base_grasp`` when the camera's
    extrinsics are known. ``approach_angle_deg``: angle between the approach direction and the
    reference (straight down in the base frame when known, else the camera's viewing direction +z).
    ``spin_deg``: how far the grasp was turned about a revolved part's axis (0 for other parts)."""

    name: str
    T_cam_grasp: np.ndarray
    T_base_grasp: np.ndarray | None
    approach_angle_deg: float
    spin_deg: float


def axis_rotation(axis, angle_rad: float) -> np.ndarray:
    """(3, 3) rotation by ``angle_rad`` about the unit ``axis`` (right hand; Rodrigues)."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle_rad) * K + (1.0 - np.cos(angle_rad)) * (K @ K)


def best_spin_rad(a_obj: np.ndarray, ref_obj: np.ndarray, axis_obj: np.ndarray) -> float:
    """The spin ``s`` about ``axis_obj`` that turns direction ``a_obj`` closest to ``ref_obj``
    (maximises ``ref . Rot(axis, s) a``), all in the model frame; 0 when every spin is as good.

    Rodrigues: ``ref . Rot(s) a = A cos s + B sin s + C`` with ``A = a.ref - (k.a)(k.ref)`` and
    ``B = (k x a).ref``, so the best spin is ``atan2(B, A)``."""
    k = np.asarray(axis_obj, float) / np.linalg.norm(axis_obj)
    A = float(a_obj @ ref_obj - (k @ a_obj) * (k @ ref_obj))
    B = float(np.cross(k, a_obj) @ ref_obj)
    if np.hypot(A, B) < 1e-9:
        return 0.0
    return float(np.arctan2(B, A))


def place_grasps(T_cam_obj: np.ndarray, grasps: Sequence[Grasp], T_base_cam: np.ndarray | None = None, *,
                 symmetry_axis_obj=None, symmetry_point_obj=None) -> list[PlacedGrasp]:
    """The grasps of a part found at ``T_cam_obj``, most reachable first.

    Order: by ``approach_angle_deg`` (approach closest to straight down in the base frame when
    ``T_base_cam`` is known, else closest to the camera's viewing direction), ties in the given order.
    A revolved part (``symmetry_axis_obj`` through ``symmetry_point_obj``, model frame) looks the same
    at any spin about its axis, so each grasp is turned about that axis to the spin whose approach is
    closest to the reference: the grasp a robot can best reach among its equivalent ones.
    """
    ref_cam = E_Z if T_base_cam is None else T_base_cam[:3, :3].T @ DOWN_BASE
    R_cam_obj = T_cam_obj[:3, :3]
    out = []
    for g in grasps:
        T_obj_grasp = np.asarray(g.T_obj_grasp, float)
        approach = np.asarray(g.approach, float) / np.linalg.norm(g.approach)
        spin = 0.0
        if symmetry_axis_obj is not None:
            a_obj = T_obj_grasp[:3, :3] @ approach
            spin = best_spin_rad(a_obj, R_cam_obj.T @ ref_cam, np.asarray(symmetry_axis_obj, float))
            p0 = np.zeros(3) if symmetry_point_obj is None else np.asarray(symmetry_point_obj, float)
            S = axis_rotation(symmetry_axis_obj, spin)
            # spin about the axis through p0: p -> S (p - p0) + p0
            T_obj_grasp = rigid(S, p0 - S @ p0) @ T_obj_grasp
        T_cam_grasp = T_cam_obj @ T_obj_grasp
        a_cam = T_cam_grasp[:3, :3] @ approach
        angle = float(np.degrees(np.arccos(np.clip(a_cam @ ref_cam, -1.0, 1.0))))
        T_base_grasp = None if T_base_cam is None else T_base_cam @ T_cam_grasp
        spin_deg = float(np.degrees(spin))
        out.append(PlacedGrasp(g.name, T_cam_grasp, T_base_grasp, angle, spin_deg))
    return sorted(out, key=lambda p: p.approach_angle_deg)  # stable: ties keep the given order


# --- upload plausibility -----------------------------------------------------------------------------

def extent_warnings(extents_mm: Sequence[float], units: str) -> list[str]:
    """Warnings (sentences) about a mesh's size: a largest side outside ``PLAUSIBLE_EXTENT_MM``
    means the mesh was probably declared in the wrong unit; the unit that would make it a typical
    part is suggested. ``extents_mm``: bounding-box sides after converting from ``units``."""
    ext = [float(x) for x in extents_mm]
    size = max(ext) if ext else 0.0
    lo, hi = PLAUSIBLE_EXTENT_MM
    if lo <= size <= hi or size <= 0 or units not in UNIT_MM:
        return []
    raw = size / UNIT_MM[units]  # the size in the file's own numbers
    plausible = [u for u, f in UNIT_MM.items() if lo <= raw * f <= hi and u != units]
    sides = " x ".join(f"{x:.0f}" if x >= 10 else f"{x:.3g}" for x in ext)
    if plausible:
        best = min(plausible, key=lambda u: abs(np.log(raw * UNIT_MM[u] / TYPICAL_PART_MM)))
        hint = f"did you mean units={best}?"
    else:
        hint = "check the mesh's unit and scale"
    side = "larger than 3 m" if size > hi else "smaller than 1 mm"
    return [f"extents {sides} mm: {hint} (read with units={units}, the part is {side}; poses of a part "
            "that size are unlikely to be found)"]


def watertight_warnings(watertight: bool | None, open_edges: int = 0,
                        nonmanifold_edges: int = 0) -> list[str]:
    """Warnings (sentences) about a mesh that is not closed (``decode.MeshFacts``): a hole shows in its
    templates' silhouettes and edges as an outline the real part does not have, so an estimate may
    miss the part for reasons that look like the scene's. ``watertight`` None (a model recorded
    before this was checked): nothing is said."""
    if watertight is None or watertight:
        return []
    what = []
    if open_edges:
        what.append(f"{open_edges:,} open edge{'s' if open_edges != 1 else ''}")
    if nonmanifold_edges:
        what.append(f"{nonmanifold_edges:,} edge{'s' if nonmanifold_edges != 1 else ''} shared by more than "
                    "two faces")
    detail = f" ({', '.join(what)})" if what else ""
    return [f"The mesh is not watertight{detail}: its silhouettes and edges may be wrong and the part may "
            "not be found; upload a closed mesh (fill the holes in the CAD export)"]
