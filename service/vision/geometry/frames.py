"""Frames, poses and rotation conventions: the one place they are stated.

Coordinate systems
------------------
- ``obj``: the CAD model's own frame after unit conversion, millimetres.
- ``cam``: OpenCV camera frame, x right, y down, z forward along the optical axis, millimetres.
- ``img``: pixels, ``uv`` with u = column, v = row; the centre of the top-left pixel is (0, 0).

A transform is named ``T_<to>_<from>``: ``p_cam = R_cam_obj @ p_obj + t_cam_obj_mm``, and inner
frames cancel: ``T_cam_obj = T_cam_tpl @ T_tpl_obj``.

Rotations
---------
``euler_xyz_deg = (rx, ry, rz)`` means ``R = Rx(rx) @ Ry(ry) @ Rz(rz)`` (the paper's eq. 3), which is
scipy's ``Rotation.from_euler("XYZ", ...)`` (UPPERCASE, intrinsic). Quaternions are ``quat_xyzw``
(scipy's order; trimesh uses wxyz).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

EULER_SEQ = "XYZ"


def Rx(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def Ry(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def Rz(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def R_from_euler_xyz_deg(euler_xyz_deg) -> np.ndarray:
    """(3,) degrees -> (3, 3) rotation, ``Rx @ Ry @ Rz``; batched input (N, 3) gives (N, 3, 3)."""
    return Rotation.from_euler(EULER_SEQ, np.asarray(euler_xyz_deg, float), degrees=True).as_matrix()


def euler_xyz_deg_from_R(R: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(np.asarray(R, float)).as_euler(EULER_SEQ, degrees=True)


def quat_xyzw_from_R(R: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(np.asarray(R, float)).as_quat()


def R_from_quat_xyzw(quat_xyzw) -> np.ndarray:
    return Rotation.from_quat(np.asarray(quat_xyzw, float)).as_matrix()


def R_from_rotvec(rotvec_rad) -> np.ndarray:
    return Rotation.from_rotvec(np.asarray(rotvec_rad, float)).as_matrix()


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` of two float64 3-vectors: the same products and differences, without its axis
    handling (~12 us on 3 numbers, called hundreds of times a frame)."""
    a0, a1, a2 = a.tolist()
    b0, b1, b2 = b.tolist()
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def R_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit direction ``a`` onto unit direction ``b``."""
    a = np.asarray(a, float) / np.linalg.norm(a)
    b = np.asarray(b, float) / np.linalg.norm(b)
    axis = cross3(a, b)
    s = np.linalg.norm(axis)
    c = float(np.clip(a @ b, -1.0, 1.0))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        # Antiparallel: turn half way round any axis perpendicular to a.
        perp = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(perp) < 1e-6:
            perp = np.cross(a, [0.0, 1.0, 0.0])
        return R_from_rotvec(np.pi * perp / np.linalg.norm(perp))
    return R_from_rotvec(axis / s * np.arctan2(s, c))


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Geodesic angle between two rotations, degrees."""
    cos = (np.trace(np.asarray(R_a).T @ np.asarray(R_b)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


@dataclass(frozen=True)
class Pose:
    """``T_cam_obj``: ``p_cam = R @ p_obj + t_mm``. R (3, 3) float64; t_mm (3,) float64, mm."""

    R: np.ndarray
    t_mm: np.ndarray

    @classmethod
    def from_euler_xyz_deg(cls, euler_xyz_deg, t_mm) -> Pose:
        return cls(R_from_euler_xyz_deg(euler_xyz_deg), np.asarray(t_mm, float))

    @classmethod
    def from_matrix(cls, T: np.ndarray) -> Pose:
        T = np.asarray(T, float)
        return cls(T[:3, :3].copy(), T[:3, 3].copy())

    def as_matrix(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.t_mm
        return T

    def euler_xyz_deg(self) -> np.ndarray:
        return euler_xyz_deg_from_R(self.R)

    def quat_xyzw(self) -> np.ndarray:
        return quat_xyzw_from_R(self.R)

    def compose(self, other: Pose) -> Pose:
        """``self @ other``: with self = T_a_b and other = T_b_c, returns T_a_c."""
        return Pose(self.R @ other.R, self.R @ other.t_mm + self.t_mm)

    def inverse(self) -> Pose:
        return Pose(self.R.T, -self.R.T @ self.t_mm)

    def apply(self, p: np.ndarray) -> np.ndarray:
        """(N, 3) points in the source frame -> (N, 3) in the target frame."""
        return np.asarray(p, float) @ self.R.T + self.t_mm


# --- continuous rotational symmetry -------------------------------------------------------------
# A revolved part's pose is reported for one canonical spin about its axis. With A the fixed
# rotation taking the model's axis onto +y, every pose is R = Rx(alpha) @ Rz(gamma) @ Ry(spin) @ A,
# and the canonical pose is the one with spin = 0 (for a +y axis: euler_xyz_deg = (alpha, 0, gamma)).


def R_align_axis_to_y(axis_obj: np.ndarray) -> np.ndarray:
    """``A`` with ``A @ axis_obj = +y``."""
    return R_between(axis_obj, [0.0, 1.0, 0.0])


def axis_alpha_gamma_deg(axis_cam: np.ndarray) -> tuple[float, float]:
    """Decompose a unit direction as ``Rx(alpha) @ Rz(gamma) @ e_y``; gamma in [-90, 90] degrees."""
    a = np.asarray(axis_cam, float) / np.linalg.norm(axis_cam)
    gamma = np.degrees(np.arcsin(np.clip(-a[0], -1.0, 1.0)))
    alpha = np.degrees(np.arctan2(a[2], a[1]))
    return float(alpha), float(gamma)


def canonical_spin(pose: Pose, axis_obj: np.ndarray | None, point_obj: np.ndarray | None = None) -> Pose:
    """The representative of ``pose`` (T_cam_obj) modulo spin about the symmetry axis ``axis_obj``
    (object frame) through ``point_obj`` (mm, object frame; the origin when None): spin = 0, see above.
    Spinning about that axis keeps ``point_obj`` where it was in the camera. ``axis_obj`` None (no
    continuous symmetry): ``pose`` itself."""
    if axis_obj is None:
        return pose
    axis = np.asarray(axis_obj, float) / np.linalg.norm(axis_obj)
    alpha, gamma = axis_alpha_gamma_deg(np.asarray(pose.R) @ axis)
    R = Rx(alpha) @ Rz(gamma) @ R_align_axis_to_y(axis)
    p0 = np.zeros(3) if point_obj is None else np.asarray(point_obj, float)
    return Pose(R, pose.R @ p0 + pose.t_mm - R @ p0)
