"""Continuous rotational symmetry: detect the axis of a revolved part.

Templates of a revolved part need no spin about its axis, so the bank only has to vary the tilt of
the axis (see ``templates``). What that needs is that spinning the part about the axis leaves its
SILHOUETTES unchanged, so that is what is measured here: the part is rendered from a few directions,
spun about the candidate axis by several angles that are not multiples of any small tessellation
period (``SPIN_ANGLES_DEG``), and the mean displacement of the silhouette border against the unspun
one (``|mask xor mask_spun| / perimeter``, pixels) is taken relative to the part's radius about the
candidate axis (so that long and short parts of the same cross-section score alike).

A surface test (nearest-sample distances after the spin) would be stricter than needed and rejects
real revolved parts whose surface is not exactly revolved: T-LESS 24 has a helical screw thread and
off-axis contacts inside, yet its silhouettes do not change when it spins.

Candidates: the principal axes of the surface's second moment (about its area-weighted centroid)
and the model axes x, y, z. The axis passes through the centre of the smallest circle enclosing the
vertices projected onto the plane normal to it (the outer envelope of a revolved part is a circle
about the axis). An axis within ``SNAP_DEG`` of a model axis is snapped onto it; its sign is chosen
so that its largest component is positive.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import trimesh

from service.vision.geometry.frames import Pose, R_align_axis_to_y, R_from_rotvec, Rx
from service.vision.geometry.render import rasterise_roi

SPIN_ANGLES_DEG = (37.0, 83.0, 131.0, 200.0)
VIEW_TILTS_DEG = (0.0, 35.0, 70.0)  # tilt of the axis towards the camera for the test renders
TEST_RENDER_PX = 300  # rendered diameter of the part in the test views, pixels
# Mean border displacement / radius about the axis below which the axis is accepted. Measured: a
# 32-gon prism 0.002, 12-gon 0.013, 8-gon 0.020, T-LESS 24 (flats on its thread) 0.034 | hexagonal
# prism 0.052, square 0.10, T-LESS 6 0.12, flange 0.12, L-bracket 0.17.
SYMMETRY_THRESHOLD = 0.042
SNAP_DEG = 1.0  # an axis within this angle of a model axis is snapped onto it


@dataclass(frozen=True)
class AxisScore:
    axis_obj: np.ndarray  # (3,) unit
    point_obj: np.ndarray  # (3,) mm, a point on the axis
    score: float  # worst (over views) mean border displacement / rendered diameter
    source: str  # "inertia" | "model-x" | "model-y" | "model-z"


def _canonical_sign(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, float) / np.linalg.norm(a)
    return a if a[np.argmax(np.abs(a))] > 0 else -a


def _snap(a: np.ndarray) -> np.ndarray:
    k = int(np.argmax(np.abs(a)))
    if np.degrees(np.arccos(np.clip(abs(a[k]), -1.0, 1.0))) <= SNAP_DEG:
        e = np.zeros(3)
        e[k] = 1.0
        return e
    return a


def axis_point(vertices_mm: np.ndarray, axis: np.ndarray, centroid: np.ndarray) -> np.ndarray:
    """Centre of the smallest circle enclosing the vertices projected on the plane normal to ``axis``,
    lifted to the plane through ``centroid`` (mm, object frame)."""
    A = R_align_axis_to_y(axis)  # axis -> +y; the plane normal to it is (x, z)
    q = np.asarray(vertices_mm, float) @ A.T
    (cx, cz), _ = cv2.minEnclosingCircle(q[:, [0, 2]].astype(np.float32))
    c_al = A @ np.asarray(centroid, float)
    return A.T @ np.array([cx, c_al[1], cz], float)


def surface_centroid_and_axes(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    tri = np.asarray(mesh.triangles, float)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    cent = tri.mean(axis=1)
    c = (area[:, None] * cent).sum(axis=0) / max(area.sum(), 1e-30)
    # Second moment of the surface (triangle covariance, exact for uniform density on each face).
    d = tri - c
    sd = d.sum(axis=1)
    cov = (np.einsum("f,fia,fib->ab", area, d, d) + np.einsum("f,fa,fb->ab", area, sd, sd)) / 12.0
    _, vec = np.linalg.eigh(cov)
    return c, vec.T


def silhouette_spin_score(vertices_mm: np.ndarray, faces: np.ndarray, axis: np.ndarray, point: np.ndarray,
                          diameter_mm: float) -> float:
    """Worst over ``VIEW_TILTS_DEG`` of the mean silhouette-border displacement caused by spinning the
    part about the axis (through ``point``) by ``SPIN_ANGLES_DEG``, relative to the part's radius about
    the axis (the largest distance of a vertex from it), both in pixels of the test renders."""
    V = np.asarray(vertices_mm, float)
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    point = np.asarray(point, float)
    d = V - point
    radius_mm = float(np.linalg.norm(d - np.outer(d @ axis, axis), axis=1).max())
    dist = 10.0 * diameter_mm
    f = TEST_RENDER_PX * dist / diameter_mm
    size = int(1.3 * TEST_RENDER_PX) + 8
    c = (size - 1) / 2.0
    K = np.array([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]])
    A = R_align_axis_to_y(axis)
    worst = 0.0
    for tilt in VIEW_TILTS_DEG:
        R0 = Rx(tilt) @ A
        masks = []
        for spin in (0.0, *SPIN_ANGLES_DEG):
            R = R0 @ R_from_rotvec(np.radians(spin) * axis)
            pose = Pose(R, np.array([0.0, 0.0, dist]) - R @ point)
            _, fid, (u0, v0) = rasterise_roi(V, faces, pose, K, (size, size), margin_px=0)
            m = np.zeros((size, size), bool)
            m[v0:v0 + fid.shape[0], u0:u0 + fid.shape[1]] = fid >= 0
            masks.append(m)
        m0 = masks[0]
        contours = cv2.findContours(m0.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)[0]
        perim = max(sum(float(cv2.arcLength(c, True)) for c in contours), 1.0)
        disp = np.mean([np.count_nonzero(m0 ^ m) / perim for m in masks[1:]])
        worst = max(worst, disp / (TEST_RENDER_PX * max(radius_mm, 1e-9) / diameter_mm))
    return float(worst)


def score_candidates(mesh: trimesh.Trimesh) -> list[AxisScore]:
    """Every candidate axis with its score, best first (see the module docstring)."""
    V = np.asarray(mesh.vertices, float)
    F = np.asarray(mesh.faces, np.int32)
    lo, hi = np.asarray(mesh.bounds, float)
    diameter = float(np.linalg.norm(hi - lo))
    centroid, axes = surface_centroid_and_axes(mesh)
    cands: list[tuple[np.ndarray, str]] = [(a, "inertia") for a in axes]
    cands += [(e, f"model-{n}") for e, n in zip(np.eye(3), "xyz", strict=True)]
    out: list[AxisScore] = []
    seen: list[np.ndarray] = []
    for a, src in cands:
        a = _canonical_sign(_snap(_canonical_sign(a)))
        if any(abs(a @ b) > np.cos(np.radians(0.01)) for b in seen):
            continue  # an inertia axis snapped onto a model axis: scored once
        seen.append(a)
        p = axis_point(V, a, centroid)
        out.append(AxisScore(a, p, silhouette_spin_score(V, F, a, p, diameter), src))
    return sorted(out, key=lambda s: s.score)


def detect_symmetry(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray] | None:
    """``(axis_obj (3,) unit, point_obj (3,) mm)`` of a continuous rotational symmetry, or None.

    The axis is accepted when spinning the part about it moves its silhouette borders by less than
    ``SYMMETRY_THRESHOLD`` of the diameter on average (see the module docstring).
    """
    best = score_candidates(mesh)[0]
    if best.score > SYMMETRY_THRESHOLD:
        return None
    return best.axis_obj, best.point_obj
