"""A refined pose on the plane polished again on its own visible edges: spun about the plane's normal and
slid along it, its lowest point kept on the plane.

The search's polish (``plane_match.polish_on_gradients``) scores a proposal's template, the edge points of
its family at the nearest template spin; the refinement then moves it on the image's segments, which a
pile's other parts pull at. A pose refined so and refused is polished once more from where it ended, on
the agreement of the edge points it shows there: a pattern search over the spin and the slide (4 deg and
2 px steps, halved four times), each pose moved along its centre's line of sight until its lowest point
touches the plane.
"""

from __future__ import annotations

import numpy as np

from service.vision.estimate.plane_match import agreement_on_plane
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, R_from_rotvec
from service.vision.geometry.plane import Plane, R_cam_rest, lowest_mm, touching
from service.vision.model.edge_points import EdgePoints

STEPS = (4.0, 2.0)  # the first spin step (deg) and slide step (px at the part's depth), halved together
HALVINGS = 4


def spun_and_slid(R: np.ndarray, centre_obj: np.ndarray, t_mm: np.ndarray, plane: Plane, x: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) spun by ``x[0]`` deg about the plane's normal through the part's centre, the centre slid
    ``x[1]``, ``x[2]`` mm along the plane's axes (the object origin follows)."""
    Rc = R_cam_rest(plane)
    R2 = _spun(R, Rc, x[0])
    return R2, _slid(R @ centre_obj + t_mm, Rc, x) - R2 @ centre_obj


def _spun(R: np.ndarray, Rc: np.ndarray, spin_deg: float) -> np.ndarray:
    return R_from_rotvec(Rc[:, 2] * np.radians(spin_deg)) @ R


def _slid(c_cam: np.ndarray, Rc: np.ndarray, x: np.ndarray) -> np.ndarray:
    return c_cam + Rc[:, 0] * x[1] + Rc[:, 1] * x[2]


class _Moves:
    """``polish_on_plane``'s poses: ``pose`` spun and slid by x (``spun_and_slid``), then moved onto the
    plane (``touching``). Each spin is tried with many slides: its rotation and the lowest point under it
    are found once."""

    def __init__(self, vertices_mm: np.ndarray, centre_obj: np.ndarray, pose: Pose, plane: Plane):
        self.V, self.centre_obj, self.R0, self.plane = vertices_mm, centre_obj, pose.R, plane
        self.Rc = R_cam_rest(plane)
        self.c_cam = pose.R @ centre_obj + pose.t_mm
        self.spins: dict[float, tuple[np.ndarray, np.ndarray, float]] = {}

    def at(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """(R, t touching the plane, or None: ``touching``) of ``pose`` moved by x."""
        spin = float(x[0])
        if spin not in self.spins:
            R = _spun(self.R0, self.Rc, x[0])
            self.spins[spin] = R, R @ self.centre_obj, lowest_mm(self.V, self.centre_obj, R, self.plane)
        R, Rc_obj, low = self.spins[spin]
        return R, touching(low, self.centre_obj, R, _slid(self.c_cam, self.Rc, x) - Rc_obj, self.plane)


def polish_on_plane(vertices_mm: np.ndarray, centre_obj: np.ndarray, edges: EdgePoints, pose: Pose,
                    plane: Plane, intr: Intrinsics, agreeing: np.ndarray) -> tuple[Pose, float, float]:
    """The pose near ``pose`` on the plane whose edge points agree best (``agreeing``: a frame's
    ``agreeing_bits``) -> (that pose, its agreement, ``pose``'s own). ``edges``: the part's visible edge
    points at ``pose`` (object frame)."""
    R0, t0 = np.asarray(pose.R, float), np.asarray(pose.t_mm, float)
    moves = _Moves(np.asarray(vertices_mm, float), centre_obj, Pose(R0, t0), plane)
    mm_per_px = float(t0[2]) / intr.fx
    steps = np.array([STEPS[0], STEPS[1] * mm_per_px, STEPS[1] * mm_per_px])
    start = agreement_on_plane(edges, R0, t0, intr, agreeing)
    best, x, R_best, t_best = start, np.zeros(3), R0, t0
    for _ in range(HALVINGS + 1):
        improved = True
        while improved:
            improved = False
            for k in range(3):
                for sign in (1.0, -1.0):
                    x2 = x.copy()
                    x2[k] += sign * steps[k]
                    R, t = moves.at(x2)
                    if t is None:
                        continue
                    score = agreement_on_plane(edges, R, t, intr, agreeing)
                    if score > best + 1e-9:
                        best, x, R_best, t_best, improved = score, x2, R, t, True
        steps = steps / 2
    return Pose(R_best, t_best), best, start
