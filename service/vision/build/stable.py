"""Stable resting poses of a part on a plane, grouped up to the part's symmetry.

``trimesh.poses.compute_stable_poses`` lists every face of the convex hull the centre of mass lies
over, with the probability that the part dropped at random comes to rest on it (the solid angle of
the face seen from the centre of mass). A revolved part lying on its side is one resting pose, yet
a tessellated one gives a hull face per facet (a 64-gon prism: 64 poses of 1.3 % each), and a box
resting on a face rests the same way on the opposite one. So poses are grouped into *families* that
are the same up to a rotation about the vertical (which the plane search tries anyway):

- with a continuous symmetry axis ``a`` (the bank's), two poses are one family when their up
  directions make the same angle with ``a`` (within ``GROUP_ANGLE_DEG``);
- any part: two poses are one family when the posed parts (resting on z = 0) are congruent up to a
  rotation about the vertical and a horizontal shift: their vertices coincide within
  ``CONGRUENT_FRACTION`` of the diameter (a box's opposite faces, a prism's facets).

A family keeps its most probable pose as representative and the sum of its members' probabilities;
families under ``MIN_PROBABILITY`` are dropped. Frames: ``R_rest_obj`` rotates the object frame into a
resting frame whose +z is the plane's normal (up) and in which the part rests on its lowest points;
the rotation about +z is arbitrary.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import trimesh

# A family resting less often than this when the part is dropped at random is not searched: 2 %
# keeps the three face families of a box with sides 1 : 2 : 4 (the smallest, on its 1 x 2 faces,
# 6.9 %) and every family of the L-bracket and T-LESS 06 (their smallest: 16.6 %, 6.2 %), and drops
# hull faces over edges and corners (the flange's: 1.1 % and less).
MIN_PROBABILITY = 0.02
GROUP_ANGLE_DEG = 2.0  # revolved part: poses whose up directions make angles with the axis this close
CONGRUENT_FRACTION = 0.005  # posed vertices within this fraction of the diameter: congruent
MAX_CHECK_POINTS = 512  # vertices compared per congruence test (seeded sample)
MAX_SPIN_CANDIDATES = 64  # spins tried per congruence test


@dataclass(frozen=True)
class StablePoses:
    R_rest_obj: np.ndarray  # (S, 3, 3) float64: object frame -> resting frame (+z up), one per family
    probability: np.ndarray  # (S,) float64: each family's share of random drops, most probable first


def _posed(V: np.ndarray, R: np.ndarray, com: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices rotated by R, shifted so the centre of mass is on the z axis and the lowest point at 0."""
    q = V @ R.T
    c = R @ com
    shift = np.array([c[0], c[1], q[:, 2].min()])
    return q - shift, c - shift


def _congruent(qa: np.ndarray, ca: np.ndarray, qb: np.ndarray, cb: np.ndarray, tol: float,
               sample: np.ndarray) -> bool:
    """Are the posed vertex sets ``qa`` and ``qb`` (centres of mass ``ca``, ``cb`` on the z axis) the
    same up to a rotation about z?"""
    from scipy.spatial import cKDTree

    if abs(ca[2] - cb[2]) > tol or abs(qa[:, 2].max() - qb[:, 2].max()) > tol:
        return False
    ra = np.hypot(qa[:, 0], qa[:, 1])
    rb = np.hypot(qb[:, 0], qb[:, 1])
    k = int(np.argmax(ra))  # the vertex farthest from the vertical through the centre of mass
    if ra[k] <= tol:
        return True  # every vertex on the axis: a needle, any spin does
    cand = np.flatnonzero((np.abs(rb - ra[k]) <= tol) & (np.abs(qb[:, 2] - qa[k, 2]) <= tol))
    if len(cand) == 0:
        return False
    tree_b, tree_a = cKDTree(qb), cKDTree(qa)
    pa, pb = qa[sample[sample < len(qa)]], qb[sample[sample < len(qb)]]
    for j in cand[:MAX_SPIN_CANDIDATES]:
        th = math.atan2(qb[j, 1], qb[j, 0]) - math.atan2(qa[k, 1], qa[k, 0])
        c, s = math.cos(th), math.sin(th)
        Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        if tree_b.query(pa @ Rz.T)[0].max() <= tol and tree_a.query(pb @ Rz)[0].max() <= tol:
            return True
    return False


def stable_poses(mesh: trimesh.Trimesh, *, axis_obj: np.ndarray | None = None,
                 diameter_mm: float | None = None, min_probability: float = MIN_PROBABILITY) -> StablePoses:
    """The part's resting pose families, most probable first (see the module docstring).

    mesh : mm, object frame. axis_obj : (3,) unit continuous symmetry axis or None. A mesh whose
    stable poses cannot be computed (degenerate, flat) has none: ``R_rest_obj`` is then (0, 3, 3).
    """
    V = np.asarray(mesh.vertices, float)
    none = StablePoses(np.zeros((0, 3, 3)), np.zeros(0))
    try:
        com = np.asarray(mesh.center_mass if mesh.is_watertight else mesh.convex_hull.center_mass, float)
        T, prob = trimesh.poses.compute_stable_poses(mesh, center_mass=com)
    except Exception:  # noqa: BLE001 - qhull or a degenerate hull: no resting poses to search
        return none
    if len(T) == 0:
        return none
    Rs = np.asarray(T, float)[:, :3, :3]
    prob = np.asarray(prob, float)
    diameter = diameter_mm if diameter_mm is not None else float(np.linalg.norm(np.ptp(V, axis=0)))
    tol = CONGRUENT_FRACTION * diameter
    sample = np.random.default_rng(0).permutation(len(V))[:MAX_CHECK_POINTS]
    a = None if axis_obj is None else np.asarray(axis_obj, float) / np.linalg.norm(axis_obj)
    fam_R: list[np.ndarray] = []
    fam_p: list[float] = []
    fam_posed: list[tuple[np.ndarray, np.ndarray]] = []
    fam_angle: list[float] = []
    for i in np.argsort(-prob, kind="stable"):
        R = Rs[i]
        up = R[2]  # the resting frame's +z in the object frame
        angle = math.degrees(math.acos(float(np.clip(up @ a, -1.0, 1.0)))) if a is not None else math.nan
        posed = _posed(V, R, com)
        for f in range(len(fam_R)):
            if (a is not None and abs(angle - fam_angle[f]) <= GROUP_ANGLE_DEG) or _congruent(
                    fam_posed[f][0], fam_posed[f][1], posed[0], posed[1], tol, sample):
                fam_p[f] += float(prob[i])
                break
        else:
            fam_R.append(R)
            fam_p.append(float(prob[i]))
            fam_posed.append(posed)
            fam_angle.append(angle)
    keep = [f for f in np.argsort(-np.asarray(fam_p), kind="stable") if fam_p[f] >= min_probability]
    if not keep:
        return none
    return StablePoses(np.stack([fam_R[f] for f in keep]), np.array([fam_p[f] for f in keep]))
