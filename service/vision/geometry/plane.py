"""A supporting plane in the camera frame and the geometry of a part resting on it: how high its lowest
point and its reference point lie, the resting frame, and where a viewing ray puts a resting part.

Frames: camera (OpenCV), mm. The plane: points p with ``n . p = d_mm``, ``n`` unit, towards the camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, cross3


class Part(Protocol):
    """What the plane's geometry reads of a part (a ``TemplateBank`` is one): its mesh's vertices (V, 3)
    and its reference point ``centre_obj`` (3,), mm, object frame."""

    vertices_mm: np.ndarray
    centre_obj: np.ndarray

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


def rest_gap_mm(bank: Part, pose: Pose, plane: Plane) -> float:
    """Height of the posed part's lowest point above the plane, mm: 0 resting on it, > 0 floating,
    < 0 going through it."""
    return float(plane.height_mm(pose.apply(np.asarray(bank.vertices_mm, float))).min())


def lowest_mm(vertices_mm: np.ndarray, centre_obj: np.ndarray, R: np.ndarray, plane: Plane) -> float:
    """Height of the part's lowest point above its centre ``centre_obj`` along the plane's normal at rotation
    R, mm (<= 0): where the part at R touches the plane does not depend on where it is."""
    n = np.asarray(plane.normal, float)
    return float(((vertices_mm - centre_obj) @ R.T @ n).min())


def touching(low_mm: float, centre_obj: np.ndarray, R: np.ndarray, t_mm: np.ndarray, plane: Plane
             ) -> np.ndarray | None:
    """The translation putting the part at (R, ``t_mm``) moved along its centre's line of sight until its
    lowest point (``low_mm``: its ``lowest_mm`` at R) lies on the plane; None where that line runs along
    the plane or behind the camera."""
    n = np.asarray(plane.normal, float)
    c_cam = R @ centre_obj + t_mm
    along = float(n @ c_cam)
    if abs(along) < 1e-9:
        return None
    s = (plane.d_mm - low_mm) / along
    return s * c_cam - R @ centre_obj if s > 0 else None


def centre_height_mm(bank: Part, pose: Pose, plane: Plane) -> float:
    """Height of the part's reference point ``centre_obj`` above the plane, mm (``sort: height``)."""
    return float(plane.height_mm(pose.apply(np.asarray(bank.centre_obj, float)[None]))[0])


def R_cam_rest(plane: Plane) -> np.ndarray:
    """A rotation whose third column is the plane's normal (the resting frame's +z), camera frame."""
    n = np.asarray(plane.normal, float)
    e = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = e - (e @ n) * n
    x /= np.linalg.norm(x)
    return np.column_stack([x, cross3(n, x), n])


def rest_heights_mm(bank: Part, R_rest_obj: np.ndarray) -> np.ndarray:
    """(S,) height of ``centre_obj`` above the plane for each resting rotation (its lowest vertex at 0)."""
    V = np.asarray(bank.vertices_mm, float)
    up = np.asarray(R_rest_obj, float)[:, 2, :]  # (S, 3) the resting frame's +z in the object frame
    return up @ np.asarray(bank.centre_obj, float) - (V @ up.T).min(axis=0)


def placements(R: np.ndarray, h_mm: np.ndarray, uv: np.ndarray, bank: Part, intr: Intrinsics,
               plane: Plane) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3, 3) rotations with centre heights (M,) placed at pixels uv (M, 2) -> ((M, 3) t_cam_obj, (M,)
    bool: the ray meets the plane in front of the camera). The reference point ``centre_obj`` lies on
    the ray through uv at height ``h_mm`` above the plane."""
    # filled in place and its norm summed directly: the search and its polish place one pose at a time
    r = np.empty((len(uv), 3))
    r[:, 0], r[:, 1], r[:, 2] = (uv[:, 0] - intr.cx) / intr.fx, (uv[:, 1] - intr.cy) / intr.fy, 1.0
    nr = r @ plane.normal
    ok = nr < -MIN_RAY_COS * np.sqrt(np.add.reduce(r * r, axis=1))
    lam = (plane.d_mm + h_mm) / np.where(ok, nr, -1.0)
    ok &= lam > 0
    c_cam = lam[:, None] * r
    return c_cam - R @ np.asarray(bank.centre_obj, float), ok


def depths_in_view_mm(plane: Plane, intr: Intrinsics, image_size: tuple[int, int]) -> tuple[float, float]:
    """Depths, mm, of the plane's nearest and farthest points in the image of ``image_size`` (w, h) (inf:
    its horizon is in view; nan, nan: it is not in view). Both lie at image corners: a pixel ray's depth
    to the plane is d / (n . ray), and n . ray is linear in the pixel."""
    w, h = image_size
    u, v = np.array([-0.5, w - 0.5, w - 0.5, -0.5]), np.array([-0.5, -0.5, h - 0.5, h - 0.5])
    facing = -(np.column_stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones(4)]) @ plane.normal)
    if facing.max() <= 0:
        return math.nan, math.nan
    height = -plane.d_mm
    return float(height / facing.max()), float(height / facing.min()) if facing.min() > 0 else math.inf
