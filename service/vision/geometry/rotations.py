"""Rotations as a least-squares solver moves them: the cross-product matrix, SO(3)'s exponential with its
left Jacobian, and a pose parametrised about a start pose (rotation vector and centre shift).

Frames: ``R`` is R_cam_obj and ``t`` t_cam_obj (mm), as in ``frames.Pose``.
"""

from __future__ import annotations

import math

import numpy as np

from service.vision.geometry.frames import Pose, cross3


def skew(v: np.ndarray) -> np.ndarray:
    """(3,) -> (3, 3) cross-product matrix."""
    x, y, z = np.asarray(v, float).tolist()
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
_I3 = np.eye(3)


def exp_so3(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation exp([w]x) and the left Jacobian J_l(w) (d exp(w) v = -[exp(w) v]x J_l dw)."""
    th = math.sqrt(float(w.dot(w)))  # np.linalg.norm's own sum for a vector, without its dispatch
    W = skew(w)
    WW = W @ W
    if th < 1e-8:
        return _I3 + W + 0.5 * WW, _I3 + 0.5 * W + WW / 6.0
    a = math.sin(th) / th
    b = (1 - math.cos(th)) / th ** 2
    c = (th - math.sin(th)) / th ** 3
    return _I3 + a * W + b * WW, _I3 + b * W + c * WW


# A symmetry axis this close to a resting part's plane normal (|cos|) makes its spin on the plane the
# unobservable one: nothing of the rotation is left to refine.
_SPIN_ON_AXIS_COS = 0.999


class PoseParams:
    """x -> pose about the start pose: R = exp([B x_r]) R0, centre c moves by ``T`` x_t.

    ``B`` is (3, 3) (free rotation), (3, 2) (perpendicular to a symmetry axis, camera frame), or on a
    plane (``normal_cam``, the plane's unit normal in the camera frame) (3, 1): the spin about the
    normal, which keeps every point's height above the plane (none for a part whose symmetry axis is the
    normal). Translation parameters are the centre's camera-frame shift in mm: (dx, dy, dz) (``T`` the
    identity), (dx, dy) with the object origin's camera z held at ``distance_mm``, or on a plane two
    shifts along it (``T``'s columns span the plane).
    """

    def __init__(self, pose0: Pose, centre_obj: np.ndarray, axis_obj: np.ndarray | None = None,
                 distance_mm: float | None = None, normal_cam: np.ndarray | None = None):
        self.R0 = np.asarray(pose0.R, float)
        self.t0 = np.asarray(pose0.t_mm, float)
        self.c = np.asarray(centre_obj, float)
        self.c0 = self.R0 @ self.c + self.t0
        a = None if axis_obj is None else self.R0 @ (np.asarray(axis_obj, float) / np.linalg.norm(axis_obj))
        if normal_cam is not None:
            if distance_mm is not None:
                raise ValueError("a pose held on a plane cannot also hold its distance.")
            nrm = np.asarray(normal_cam, float) / np.linalg.norm(normal_cam)
            spun = a is None or abs(float(a @ nrm)) < _SPIN_ON_AXIS_COS
            self.B = nrm[:, None] if spun else np.zeros((3, 0))
            self.T = _perpendicular_basis(nrm)
        else:
            self.B = np.eye(3) if a is None else _perpendicular_basis(a)
            self.T = _translation_basis(distance_mm)
        self.nr = self.B.shape[1]
        self.distance_mm = distance_mm
        self.n = self.nr + self.T.shape[1]

    def pose(self, x: np.ndarray) -> Pose:
        return self._pose_jac(x)[0]

    def _pose_jac(self, x: np.ndarray):
        """Pose at x; and, for the Jacobian, ``dR`` pieces: J_l @ B and the centre shift."""
        x = np.asarray(x, float)
        w = self.B @ x[:self.nr]
        E, Jl = exp_so3(w)
        R = E @ self.R0
        JB = Jl @ self.B  # (3, nr)
        c_cam = self.c0 + self.T @ x[self.nr:]
        Rc = R @ self.c
        dz_dr = np.zeros(self.nr)
        if self.distance_mm is not None:
            c_cam[2] = self.distance_mm + Rc[2]
            dz_dr = (-skew(Rc) @ JB)[2]
        t = c_cam - Rc
        return Pose(R, t), JB, dz_dr

    def points(self, x: np.ndarray, p_obj: np.ndarray, with_jac: bool):
        """Camera-frame points (M, 3) and, with ``with_jac``, d p_cam / d x (M, 3, n), else None."""
        if with_jac:
            return self.points_and_jac(x, p_obj)
        pose = self.pose(x)
        return p_obj @ pose.R.T + pose.t_mm, None

    def points_and_jac(self, x: np.ndarray, p_obj: np.ndarray):
        """Camera-frame points (M, 3) and d p_cam / d x (M, 3, n)."""
        pose, JB, dz_dr = self._pose_jac(x)
        q = (p_obj - self.c) @ pose.R.T  # R (p - c)
        pc = q + (pose.R @ self.c + pose.t_mm)
        J = np.zeros((len(p_obj), 3, self.n))
        # d(exp(w) v)/dw = -[v]x J_l: column k is (J_l B)[:, k] x q, written out (np.cross's axis
        # shuffling cost more than the products, ~3 ms a frame).
        a0, a1, a2 = JB[0][None, :], JB[1][None, :], JB[2][None, :]
        q0, q1, q2 = q[:, 0:1], q[:, 1:2], q[:, 2:3]
        J[:, 0, :self.nr] = a1 * q2 - a2 * q1
        J[:, 1, :self.nr] = a2 * q0 - a0 * q2
        J[:, 2, :self.nr] = a0 * q1 - a1 * q0
        J[:, 2, :self.nr] += dz_dr
        J[:, :, self.nr:] = self.T[None]
        return pc, J


def _perpendicular_basis(a: np.ndarray) -> np.ndarray:
    """(3, 2): two unit vectors perpendicular to the unit vector ``a`` and to each other."""
    e = np.eye(3)[int(np.argmin(np.abs(a)))]
    b1 = cross3(a, e)
    b1 /= np.linalg.norm(b1)
    return np.stack([b1, cross3(a, b1)], 1)


def _translation_basis(distance_mm: float | None) -> np.ndarray:
    """The centre's free camera-frame shifts: all three, or x and y with the distance held."""
    return np.eye(3) if distance_mm is None else np.eye(3)[:, :2]
