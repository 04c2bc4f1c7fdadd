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
MAX_SPIN_CANDIDATES = 16  # spins tried per congruence test
# Only the most probable poses are grouped: past them each pose rests less than 1/64 of drops, and a
# ball's thousands of hull faces would cost millions of congruence tests (a revolved part's facets are
# grouped by the axis first, so a 128-gon lying on its side still sums to one family).
MAX_POSES = 64
# Stable poses depend only on the convex hull and the centre of mass, and compute_stable_poses costs
# ~10 ms per hull face (a 16,000-face ball: 47 s): a hull of more faces is simplified to about this many
# first (quadric decimation, then its hull again), which moves its faces by a fraction of a millimetre.
MAX_HULL_FACES = 2000
# a hull facet whose up direction lies within about 1 deg of a pose trimesh found is that pose
MISSED_FACET_COS = math.cos(math.radians(1.0))
HEIGHT_QUANTILES = 16  # a congruence test first compares this many quantiles of the vertex heights


@dataclass(frozen=True)
class StablePoses:
    R_rest_obj: np.ndarray  # (S, 3, 3) float64: object frame -> resting frame (+z up), one per family
    probability: np.ndarray  # (S,) float64: each family's share of random drops, most probable first


def _posed(V: np.ndarray, R: np.ndarray, com: np.ndarray) -> _Posed:
    """Vertices rotated by R, shifted so the centre of mass is on the z axis and the lowest point at 0."""
    q = V @ R.T
    c = R @ com
    shift = np.array([c[0], c[1], q[:, 2].min()])
    q = q - shift
    return _Posed(q, c - shift, np.quantile(q[:, 2], np.linspace(0.0, 1.0, HEIGHT_QUANTILES)))


@dataclass
class _Posed:
    q: np.ndarray  # (V, 3) posed vertices (centre of mass on the z axis, lowest point at z = 0)
    c: np.ndarray  # (3,) posed centre of mass
    heights: np.ndarray  # (HEIGHT_QUANTILES,) quantiles of q[:, 2]: invariant to spin and shift
    _tree: object = None

    def tree(self):
        from scipy.spatial import cKDTree

        if self._tree is None:
            self._tree = cKDTree(self.q)
        return self._tree


def _congruent(a: _Posed, b: _Posed, tol: float, sample: np.ndarray) -> bool:
    """Are the posed vertex sets of ``a`` and ``b`` (centres of mass on the z axis) the same up to a
    rotation about z?"""
    qa, ca, qb, cb = a.q, a.c, b.q, b.c
    if abs(ca[2] - cb[2]) > tol or np.abs(a.heights - b.heights).max() > tol:
        return False
    ra = np.hypot(qa[:, 0], qa[:, 1])
    rb = np.hypot(qb[:, 0], qb[:, 1])
    k = int(np.argmax(ra))  # the vertex farthest from the vertical through the centre of mass
    if ra[k] <= tol:
        return True  # every vertex on the axis: a needle, any spin does
    cand = np.flatnonzero((np.abs(rb - ra[k]) <= tol) & (np.abs(qb[:, 2] - qa[k, 2]) <= tol))
    if len(cand) == 0:
        return False
    tree_b, tree_a = b.tree(), a.tree()
    pa, pb = qa[sample[sample < len(qa)]], qb[sample[sample < len(qb)]]
    for j in cand[:MAX_SPIN_CANDIDATES]:
        th = math.atan2(qb[j, 1], qb[j, 0]) - math.atan2(qa[k, 1], qa[k, 0])
        c, s = math.cos(th), math.sin(th)
        Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        if tree_b.query(pa @ Rz.T)[0].max() <= tol and tree_a.query(pb @ Rz)[0].max() <= tol:
            return True
    return False


def _with_missed_facets(hull: trimesh.Trimesh, com: np.ndarray, Rs: np.ndarray, prob: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """``compute_stable_poses``' rotations and probabilities, with every hull facet it missed that the part
    rests on (the centre of mass over it), at the probability of its own solid angle seen from the centre
    of mass (its basin's least). Where the centre of mass projects onto a shared edge of a facet's coplanar
    triangles, trimesh's toppling graph can lose the facet: a flat spanner's second face."""
    ups = Rs[:, 2, :] if len(Rs) else np.zeros((0, 3))
    groups = [list(f) for f in hull.facets]
    grouped = set(i for g in groups for i in g)
    groups += [[i] for i in range(len(hull.faces)) if i not in grouped]
    added_R, added_p = [], []
    for g in groups:
        n = hull.face_normals[g[0]]
        if len(ups) and np.max(ups @ -n) >= MISSED_FACET_COS:
            continue
        tri = hull.triangles[g] - com  # (k, 3, 3) about the centre of mass
        foot = -(tri[0, 0] @ n) * n  # the centre of mass's foot on the facet's plane
        with np.errstate(all="ignore"):  # a sliver triangle's coordinates are NaN: not inside
            bary = trimesh.triangles.points_to_barycentric(tri, np.repeat(foot[None], len(tri), 0))
        if not np.any(np.all(bary >= -1e-9, axis=1)):
            continue
        added_R.append(_resting_rotation(-n))
        added_p.append(float(sum(_solid_angle(t) for t in tri)) / (4.0 * math.pi))
    if not added_R:
        return Rs, prob
    return np.concatenate([Rs.reshape(-1, 3, 3), np.array(added_R)]), np.concatenate([prob, added_p])


def _solid_angle(tri: np.ndarray) -> float:
    """The solid angle of a triangle seen from the origin (Van Oosterom and Strackee)."""
    a, b, c = tri
    la, lb, lc = np.linalg.norm(a), np.linalg.norm(b), np.linalg.norm(c)
    num = abs(float(a @ np.cross(b, c)))
    den = la * lb * lc + (a @ b) * lc + (a @ c) * lb + (b @ c) * la
    return 2.0 * math.atan2(num, den)


def _resting_rotation(up: np.ndarray) -> np.ndarray:
    """A rotation whose third row is ``up`` (the resting frame's +z in the object frame), built as
    trimesh builds its stable poses' (its spin about +z is arbitrary)."""
    x = np.array([-up[1], up[0], 0.0])
    x = np.array([1.0, 0.0, 0.0]) if np.linalg.norm(x) == 0.0 else x / np.linalg.norm(x)
    y = np.cross(up, x)
    return np.array([x, y / np.linalg.norm(y), up])


def stable_poses(mesh: trimesh.Trimesh, *, axis_obj: np.ndarray | None = None,
                 diameter_mm: float | None = None, min_probability: float = MIN_PROBABILITY) -> StablePoses:
    """The part's resting pose families, most probable first (see the module docstring).

    mesh : mm, object frame. axis_obj : (3,) unit continuous symmetry axis or None. A mesh whose
    stable poses cannot be computed (degenerate, flat) has none: ``R_rest_obj`` is then (0, 3, 3).
    """
    V = np.asarray(mesh.vertices, float)
    none = StablePoses(np.zeros((0, 3, 3)), np.zeros(0))
    try:
        hull = mesh.convex_hull
        com = np.asarray(mesh.center_mass if mesh.is_watertight else hull.center_mass, float)
        if len(hull.faces) > MAX_HULL_FACES:
            import fast_simplification

            v, f = fast_simplification.simplify(np.asarray(hull.vertices, float), np.asarray(hull.faces),
                                                target_reduction=1.0 - MAX_HULL_FACES / 2 / len(hull.faces))
            hull = trimesh.Trimesh(v, f).convex_hull
        T, prob = trimesh.poses.compute_stable_poses(hull, center_mass=com)
        Rs, prob = _with_missed_facets(hull, com, np.asarray(T, float).reshape(-1, 4, 4)[:, :3, :3],
                                       np.asarray(prob, float))
    except Exception:  # noqa: BLE001 - qhull or a degenerate hull: no resting poses to search
        return none
    if len(Rs) == 0:
        return none
    diameter = diameter_mm if diameter_mm is not None else float(np.linalg.norm(np.ptp(V, axis=0)))
    tol = CONGRUENT_FRACTION * diameter
    sample = np.random.default_rng(0).permutation(len(V))[:MAX_CHECK_POINTS]
    a = None if axis_obj is None else np.asarray(axis_obj, float) / np.linalg.norm(axis_obj)
    fam_R: list[np.ndarray] = []
    fam_p: list[float] = []
    fam_posed: list[_Posed] = []
    fam_angle: list[float] = []
    for rank, i in enumerate(np.argsort(-prob, kind="stable")):
        R = Rs[i]
        up = R[2]  # the resting frame's +z in the object frame
        if a is not None:
            angle = math.degrees(math.acos(float(np.clip(up @ a, -1.0, 1.0))))
            f = next((f for f in range(len(fam_R)) if abs(angle - fam_angle[f]) <= GROUP_ANGLE_DEG), None)
            if f is not None:
                fam_p[f] += float(prob[i])
                continue
        else:
            angle = math.nan
        if rank >= MAX_POSES:
            continue  # rests less than 1 / MAX_POSES of drops and is not a revolved part's facet
        posed = _posed(V, R, com)
        f = next((f for f in range(len(fam_R)) if _congruent(fam_posed[f], posed, tol, sample)), None)
        if f is not None:
            fam_p[f] += float(prob[i])
            continue
        fam_R.append(R)
        fam_p.append(float(prob[i]))
        fam_posed.append(posed)
        fam_angle.append(angle)
    keep = [f for f in np.argsort(-np.asarray(fam_p), kind="stable") if fam_p[f] >= min_probability]
    if not keep:
        return none
    return StablePoses(np.stack([fam_R[f] for f in keep]), np.array([fam_p[f] for f in keep]))
