"""Pinhole intrinsics, projection and OpenCV lens distortion.

``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels; ``uv`` is (column, row) with the centre of
the top-left pixel at (0, 0). ``dist`` is OpenCV's ``[k1, k2, p1, p2[, k3[, k4, k5, k6]]]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] | None = None

    @classmethod
    def from_K(cls, K: np.ndarray, dist=None) -> Intrinsics:
        K = np.asarray(K, float)
        d = None if dist is None or not np.any(dist) else tuple(float(x) for x in dist)
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), d)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray | None:
        return None if self.dist is None else np.asarray(self.dist, float)

    def scaled(self, s: float) -> Intrinsics:
        """Intrinsics of the image resized by ``s`` (pixel centres stay pixel centres)."""
        return Intrinsics(self.fx * s, self.fy * s, (self.cx + 0.5) * s - 0.5, (self.cy + 0.5) * s - 0.5,
                          self.dist)

    def pinhole(self) -> Intrinsics:
        """The same camera without lens distortion: the ideal pinhole the image side is undistorted to."""
        return Intrinsics(self.fx, self.fy, self.cx, self.cy)

    def shifted(self, du: float, dv: float) -> Intrinsics:
        """Intrinsics of a crop whose top-left pixel is (du, dv) of this image."""
        return Intrinsics(self.fx, self.fy, self.cx - du, self.cy - dv, self.dist)


def as_intrinsics(K_or_intr) -> Intrinsics:
    """``Intrinsics`` or a (3, 3) ``K`` -> ``Intrinsics``."""
    return K_or_intr if isinstance(K_or_intr, Intrinsics) else Intrinsics.from_K(np.asarray(K_or_intr, float))


def project(p_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(..., 3) mm, camera frame -> (..., 2) uv pixels of the pinhole ``K`` (no distortion)."""
    p = np.asarray(p_cam, float)
    z = p[..., 2]
    return np.stack([K[0, 0] * p[..., 0] / z + K[0, 2], K[1, 1] * p[..., 1] / z + K[1, 2]], axis=-1)


def project_distorted(p_cam: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """(N, 3) mm, camera frame -> (N, 2) uv pixels through the lens model."""
    if intr.dist is None:
        return project(p_cam, intr.K)
    uv, _ = cv2.projectPoints(np.asarray(p_cam, np.float64).reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                              intr.K, intr.dist_coeffs)
    return uv.reshape(-1, 2)


def unproject(uv: np.ndarray, depth_mm: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N, 2) uv pixels and (N,) depth (z, mm) -> (N, 3) mm, camera frame."""
    uv = np.asarray(uv, float)
    z = np.asarray(depth_mm, float)
    x = (uv[:, 0] - K[0, 2]) / K[0, 0] * z
    y = (uv[:, 1] - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], axis=1)


def undistort_points(uv: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """(N, 2) distorted pixels -> (N, 2) pixels of the ideal pinhole camera ``intr.K``."""
    if intr.dist is None:
        return np.asarray(uv, float)
    # OpenCV's default stops after 5 fixed-point iterations (0.05 px off at the corners for k1=-0.2).
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    pts = np.asarray(uv, np.float64).reshape(-1, 1, 2)
    if hasattr(cv2, "undistortPointsIter"):
        out = cv2.undistortPointsIter(pts, intr.K, intr.dist_coeffs, None, intr.K, criteria)
    else:
        out = cv2.undistortPoints(pts, intr.K, intr.dist_coeffs, P=intr.K, criteria=criteria)
    return out.reshape(-1, 2)


def undistort_image(image: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """The image as the ideal pinhole camera ``intr.K`` would have taken it (the image itself when
    ``intr.dist`` is None): one remap per frame, for the checks that read pixels at projected poses."""
    if intr.dist is None:
        return image
    return cv2.undistort(np.asarray(image), intr.K, intr.dist_coeffs)


def ray_direction(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(N, 2) uv -> (N, 3) unit viewing rays, camera frame."""
    d = unproject(np.atleast_2d(uv), np.ones(len(np.atleast_2d(uv))), K)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def ray_rotations(uv: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3) unit viewing rays through pixels uv (M, 2) and (M, 3, 3) rotations taking e_z onto them.

    Rodrigues with k = e_z x d: R = I + [k]x + [k]x^2 / (1 + d_z); a ray never points backwards
    (d_z > 0), so the formula never divides by zero.
    """
    d = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    kx = np.zeros((len(d), 3, 3))
    kx[:, 0, 2], kx[:, 1, 2] = d[:, 0], d[:, 1]
    kx[:, 2, 0], kx[:, 2, 1] = -d[:, 0], -d[:, 1]
    R = np.eye(3) + kx + (kx @ kx) / (1.0 + d[:, 2])[:, None, None]
    return d, R


def ray_rotation(uv: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit viewing ray through pixel uv (2,) and the smallest rotation taking e_z onto it."""
    d, R = ray_rotations(np.asarray(uv, float)[None], K)
    return d[0], R[0]
