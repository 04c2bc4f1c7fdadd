"""Rendered test scenes of the L-shaped block (no symmetry), built on the service's own rasteriser.

The plane scenes: a camera (640 x 480, f = 600 px) looks down 40 deg from straight down at a plain
plane 450 mm along its axis; copies of the block rest on it in their stable families, spun about its
normal. (The benchmarks keep their own copy of the block in ``bench/lib/scenes.py``: the tests import
nothing from the benchmarks.)
"""

from __future__ import annotations

import numpy as np
import trimesh

from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, Rz
from service.vision.geometry.plane import Plane
from service.vision.geometry.render import render, render_shaded

INTR = Intrinsics(600.0, 600.0, 319.5, 239.5)
SIZE = (640, 480)
L_BLOCK_GRID = {"view_step_deg": 15.0, "render_px": 160}  # the coarse grid the instance and plane tests use
TILT_DEG, AXIS_DIST_MM = 40.0, 450.0


def l_block() -> trimesh.Trimesh:
    """An L-shaped block, 80 x 60 x 40 mm, arms of unequal length: no symmetry."""
    a = trimesh.creation.box((80.0, 20.0, 40.0))
    b = trimesh.creation.box((20.0, 40.0, 40.0))
    b.apply_translation((-30.0, 30.0, 0.0))
    return trimesh.util.concatenate([a, b])


def _camera() -> tuple[np.ndarray, np.ndarray]:
    """(R_cam_world, t_cam_world): world = plane frame (z up, plane z = 0), the optical axis 40 deg
    from straight down, meeting the plane at the world origin 450 mm away."""
    a = np.radians(TILT_DEG)
    z_c = np.array([0.0, np.sin(a), -np.cos(a)])
    x_c = np.array([1.0, 0.0, 0.0])
    R = np.stack([x_c, np.cross(z_c, x_c), z_c])
    return R, R @ (AXIS_DIST_MM * z_c)  # t = -R @ C with C = -450 z_c


R_CW, T_CW = _camera()
PLANE = Plane(R_CW[:, 2], float(R_CW[:, 2] @ T_CW))


def resting(bank, s: int, spin_deg: float, x_mm: float, y_mm: float, lift_mm: float = 0.0) -> Pose:
    """The part in family s, spun about the plane normal, its bounding-box centre above (x, y) of the
    plane frame, its lowest point ``lift_mm`` above the plane: T_cam_obj."""
    R_wo = Rz(spin_deg) @ bank.R_rest_obj[s]
    q = np.asarray(bank.vertices_mm, float) @ R_wo.T
    c = R_wo @ bank.centre_obj
    t_wo = np.array([x_mm - c[0], y_mm - c[1], lift_mm - q[:, 2].min()])
    return Pose(R_CW @ R_wo, R_CW @ t_wo + T_CW)


def copies(bank, poses) -> tuple[np.ndarray, np.ndarray]:
    """The copies at ``poses`` as one mesh in the camera frame: (vertices, faces), copy k's faces k-th."""
    V = np.asarray(bank.vertices_mm, float)
    F = np.asarray(bank.faces)
    Fs = np.concatenate([F + k * len(V) for k in range(len(poses))])
    return np.concatenate([p.apply(V) for p in poses]), Fs


def scene(bank, poses) -> np.ndarray:
    """The copies at ``poses``, Lambert-shaded on a plain grey plane: (H, W, 3) uint8."""
    Vs, Fs = copies(bank, poses)
    eye = Pose(np.eye(3), np.zeros(3))
    shaded = render_shaded(Vs, Fs, eye, INTR.K, SIZE, background=0).astype(float)
    cov = render(Vs, Fs, eye, INTR.K, SIZE, supersample=2).coverage
    grey = np.clip(np.rint(70.0 * (1 - cov) + shaded), 0, 255).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=2)


def visible_fraction(bank, poses, k: int) -> float:
    """Share of copy k's silhouette that the others (rendered together, z-buffered) leave visible."""
    n_faces = len(bank.faces)
    r = render(*copies(bank, poses), Pose(np.eye(3), np.zeros(3)), INTR.K, SIZE, supersample=2)
    own = r.mask & (r.face_id >= k * n_faces) & (r.face_id < (k + 1) * n_faces)
    return float(own.sum()) / float(render(bank.vertices_mm, bank.faces, poses[k], INTR.K, SIZE,
                                           supersample=2).mask.sum())
