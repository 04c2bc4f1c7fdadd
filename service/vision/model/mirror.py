"""Mirror planes of a part, and the outline twin they give every pose.

A part that is its own mirror image about a plane (normal ``n_obj`` through ``point_obj``) has, from
any view, a second pose with nearly the same outline: reflect the part through that plane (it does not
change) and then through the plane across the line of sight at its centre (the outline does not change
under orthographic projection). The two reflections make a proper rotation,

    R_twin = D_ray @ R @ S_n,   D_ray = I - 2 r r^T (r: unit ray to the centre),  S_n = I - 2 n n^T,

so the twin is a real pose of the part, seen with its near and far faces swapped. A silhouette-driven
search and refinement cannot tell the two apart (a flat L-shaped block lying on a real copy, seen
flipped, in the instance and plane benchmarks); shading and region evidence can, so the estimate
checks the twin of a found pose and keeps whichever verifies better (``pipeline.check_candidate``).

Detection: surface samples reflected through a candidate plane must land on the surface: the
``MIRROR_QUANTILE`` of their distances to an independent sample of the surface may exceed that of the
unreflected samples (the sampling's own spacing) by at most ``MIRROR_TOLERANCE`` of the diameter.
Candidate normals: the principal axes of the surface's second moment and the model axes, through the
surface centroid (every mirror plane contains it). A revolved part has every plane through its axis as
a mirror: one of them (normal perpendicular to the axis) stands for all, as their twins differ only by a
spin about the axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from service.vision.geometry.frames import Pose
from service.vision.model.symmetry import surface_centroid_and_axes

MIRROR_TOLERANCE = 0.01  # of the diameter: a tessellation's facets, not a lug or a boss
# A quantile, not the mean: a boss on one side is a few per cent of the surface, but far off.
MIRROR_QUANTILE = 0.99
SAMPLES = 4000  # surface points per sample set (two independent sets)
SAME_NORMAL_DEG = 10.0  # passing normals closer than this are one plane (the better one is kept)
# A box-like part passes up to six candidates (its principal axes then fall anywhere); each plane costs a
# twin check per found frame, and its three best are the ones a box has.
MAX_PLANES = 3


@dataclass(frozen=True)
class MirrorPlanes:
    normals_obj: np.ndarray  # (M, 3) unit, object frame; M = 0: no mirror plane
    point_obj: np.ndarray  # (3,) mm, object frame: a point every plane contains (the surface centroid)


def mirror_planes(mesh: trimesh.Trimesh, *, axis_obj: np.ndarray | None = None) -> MirrorPlanes:
    """The part's mirror planes (see the module docstring). ``axis_obj``: a revolved part's axis."""
    centroid, axes = surface_centroid_and_axes(mesh)
    lo, hi = np.asarray(mesh.bounds, float)
    diameter = float(np.linalg.norm(hi - lo))
    a = np.asarray(trimesh.sample.sample_surface(mesh, SAMPLES, seed=1)[0], float)
    b = np.asarray(trimesh.sample.sample_surface(mesh, SAMPLES, seed=2)[0], float)
    tree = cKDTree(b)
    floor_mm = float(np.quantile(tree.query(a)[0], MIRROR_QUANTILE))
    passing = []
    for n in _candidate_normals(axes, axis_obj):
        reflected = a - 2.0 * np.outer((a - centroid) @ n, n)
        gap_mm = float(np.quantile(tree.query(reflected)[0], MIRROR_QUANTILE)) - floor_mm
        if gap_mm <= MIRROR_TOLERANCE * diameter:
            passing.append((gap_mm, n))
    normals: list[np.ndarray] = []
    for _, n in sorted(passing, key=lambda g: g[0]):
        if len(normals) < MAX_PLANES and not any(_one_plane(n, m, axis_obj) for m in normals):
            normals.append(n)
    return MirrorPlanes(np.array(normals, float).reshape(-1, 3), centroid)


def _one_plane(n: np.ndarray, m: np.ndarray, axis_obj: np.ndarray | None) -> bool:
    """Whether normals ``n`` and ``m`` give the same twins: within ``SAME_NORMAL_DEG``, or, for a revolved
    part, both planes through its axis (their twins differ by a spin about it)."""
    if abs(n @ m) >= np.cos(np.radians(SAME_NORMAL_DEG)):
        return True
    if axis_obj is None:
        return False
    axis = np.asarray(axis_obj, float) / np.linalg.norm(axis_obj)
    return max(abs(n @ axis), abs(m @ axis)) < np.sin(np.radians(1.0))


def _candidate_normals(axes: np.ndarray, axis_obj: np.ndarray | None) -> list[np.ndarray]:
    cands = [np.asarray(v, float) / np.linalg.norm(v) for v in (*axes, *np.eye(3))]
    if axis_obj is None:
        return cands
    axis = np.asarray(axis_obj, float) / np.linalg.norm(axis_obj)
    # Planes through the axis (normals perpendicular to it: the candidates that are, and one made so) and
    # the plane across it (normal along it); ``mirror_planes`` keeps one of the first kind.
    made = np.cross(axis, np.eye(3)[int(np.argmin(np.abs(axis)))])
    through = [c for c in cands if abs(c @ axis) < np.sin(np.radians(1.0))] + [made / np.linalg.norm(made)]
    return [*through, axis]


def twin_poses(pose: Pose, planes: MirrorPlanes) -> list[Pose]:
    """The outline twin of ``pose`` for each mirror plane (module docstring): same centre point, the
    part's near and far sides swapped."""
    c = np.asarray(planes.point_obj, float)
    p_cam = pose.R @ c + pose.t_mm
    r = p_cam / np.linalg.norm(p_cam)
    D_ray = np.eye(3) - 2.0 * np.outer(r, r)
    out = []
    for n in planes.normals_obj:
        R = D_ray @ pose.R @ (np.eye(3) - 2.0 * np.outer(n, n))
        out.append(Pose(R, p_cam - R @ c))
    return out
