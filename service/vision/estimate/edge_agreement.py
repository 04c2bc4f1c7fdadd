"""Evidence that holds for metal, plastic and painted parts alike: do the image's gradients run along
the edges the CAD model shows at a pose?

Every visible edge of the posed model (``model/edge_points.visible_edges``: the outline, the part's own
occluding edges and its creases) is projected; a point agrees when, within ``TOLERANCE_PX``, the image
has a stable gradient orientation (``gradients.orientation_bits``) in the bin of the edge's normal.
The polarity is not read: a shiny part is brighter or darker than the table with the light. Each point
weighs 1 / (the points of its orientation bin), so a long straight side does not outvote the rest.

- ``edge_agreement``: the weighted share of all visible edge points that agree;
- ``inner_agreement``: the same over the inner edges (creases and self-occlusions inside the outline);
  a part showing fewer than ``MIN_INNER_POINTS`` of them reads its ``edge_agreement``. A wrong pose
  on another part's outline or on the table's texture can fit an outline, seldom the edges within it.
"""

from __future__ import annotations

import numpy as np

from service.vision.estimate.gradients import N_ORI, quantise, spread
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose
from service.vision.model.edge_points import visible_edges

TOLERANCE_PX = 1  # an agreeing gradient lies within this many pixels of the projected edge
MIN_INNER_POINTS = 20
TANGENT_STEP_MM = 0.5


def agreeing_bits(bits: np.ndarray) -> np.ndarray:
    """The orientation bits spread over the tolerance: a point agrees where its own bin is set in this."""
    return spread(bits, 2 * TOLERANCE_PX + 1)


def edge_agreement(vertices_mm: np.ndarray, faces: np.ndarray, creases: np.ndarray, pose: Pose,
                   intr: Intrinsics, agreeing: np.ndarray) -> dict[str, float]:
    """``edge_agreement`` and ``inner_agreement`` of ``pose`` on a frame's ``agreeing_bits``."""
    h, w = agreeing.shape
    e = visible_edges(vertices_mm, faces, creases, pose, intr, (w, h))
    if e is None:
        return {"edge_agreement": 0.0, "inner_agreement": 0.0}
    unit = e.tangent_cam / np.maximum(np.linalg.norm(e.tangent_cam, axis=1), 1e-9)[:, None]
    q = e.p_cam + TANGENT_STEP_MM * unit
    f = np.array([intr.fx, intr.fy])
    d = (q[:, :2] / q[:, 2:3] - e.p_cam[:, :2] / e.p_cam[:, 2:3]) * f
    ori = quantise(np.arctan2(d[:, 0], -d[:, 1]))
    iu, iv = np.rint(e.uv[:, 0]).astype(int), np.rint(e.uv[:, 1]).astype(int)
    inside = (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
    agree = np.zeros(len(ori), bool)
    agree[inside] = (agreeing[iv[inside], iu[inside]] >> ori[inside]) & 1 == 1
    every = _weighted_share(agree[inside], ori[inside])
    inner = inside & ~e.outline
    return {"edge_agreement": every,
            "inner_agreement": _weighted_share(agree[inner], ori[inner]) if inner.sum() >= MIN_INNER_POINTS
            else every}


def _weighted_share(agree: np.ndarray, ori: np.ndarray) -> float:
    """The share of agreeing points, each weighing 1 / (points of its bin, at least n / (2 N_ORI))."""
    n = len(ori)
    if n == 0:
        return 0.0
    count = np.bincount(ori, minlength=N_ORI).astype(float)
    wt = 1.0 / np.maximum(count[ori], n / (2.0 * N_ORI))
    return float((wt * agree).sum() / wt.sum())
