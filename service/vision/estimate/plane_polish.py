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
from service.vision.geometry.plane import Plane, R_cam_rest, touching
from service.vision.model.edge_points import EdgePoints

STEPS = (4.0, 2.0)  # the first spin step (deg) and slide step (px at the part's depth), halved together
HALVINGS = 4


def spun_and_slid(R: np.ndarray, centre_obj: np.ndarray, t_mm: np.ndarray, plane: Plane, x: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) spun by ``x[0]`` deg about the plane's normal through the part's centre, the centre slid
    ``x[1]``, ``x[2]`` mm along the plane's axes (the object origin follows)."""
    Rc = R_cam_rest(plane)
    R2 = R_from_rotvec(Rc[:, 2] * np.radians(x[0])) @ R
    c_cam = R @ centre_obj + t_mm + Rc[:, 0] * x[1] + Rc[:, 1] * x[2]
    return R2, c_cam - R2 @ centre_obj


def polish_on_plane(vertices_mm: np.ndarray, centre_obj: np.ndarray, edges: EdgePoints, pose: Pose,
                    plane: Plane, intr: Intrinsics, agreeing: np.ndarray) -> tuple[Pose, float, float]:
    """The pose near ``pose`` on the plane whose edge points agree best (``agreeing``: a frame's
    ``agreeing_bits``) -> (that pose, its agreement, ``pose``'s own). ``edges``: the part's visible edge
    points at ``pose`` (object frame)."""
    V = np.asarray(vertices_mm, float)
    R0, t0 = np.asarray(pose.R, float), np.asarray(pose.t_mm, float)
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
                    R, t = spun_and_slid(R0, centre_obj, t0, plane, x2)
                    t = touching(V, centre_obj, R, t, plane)
                    if t is None:
                        continue
                    score = agreement_on_plane(edges, R, t, intr, agreeing)
                    if score > best + 1e-9:
                        best, x, R_best, t_best, improved = score, x2, R, t, True
        steps = steps / 2
    return Pose(R_best, t_best), best, start
