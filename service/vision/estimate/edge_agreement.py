"""Evidence that holds for metal, plastic and painted parts alike: do the image's gradients run along
the edges the CAD model shows at a pose?

Every visible edge of the posed model (``model/edge_points.visible_edges``: the outline, the part's own
occluding edges and its creases) is projected; a point agrees when, within ``TOLERANCE_PX``, the image
has a stable gradient orientation (``gradients.orientation_bits``) in the bin of the edge's normal
(a faint one too, where the table round it is quiet: ``agreeing_bits``).
The polarity is not read: a shiny part is brighter or darker than the table with the light. Each point
weighs 1 / (the points of its orientation bin), so a long straight side does not outvote the rest.

- ``edge_agreement``: the weighted share of all visible edge points that agree;
- ``outline_agreement``: the same over the outline only: a part whose creases seldom show (a smooth
  moulding, one light) reads its outline undiluted;
- ``inner_agreement``: the same over the inner edges (creases and self-occlusions inside the outline);
  a part showing fewer than ``MIN_INNER_POINTS`` of them reads its ``edge_agreement``. A wrong pose
  on another part's outline or on the table's texture can fit an outline, seldom the edges within it.
- ``edge_coverage`` and ``outline_coverage``: the same shares with each point weighing 1 / (the points
  of its orientation bin within ``COVERAGE_RADIUS_PX``): each stretch of edge counts by its extent, not
  by its points. An allen key's arm end is parallel to its other arm, so by orientation alone it weighs
  a few points among that arm's hundred; a longer key fits the shorter one's pose everywhere but there.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numba
import numpy as np

from service.vision.estimate.gradients import N_ORI, balanced_weights, quantise, spread
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose
from service.vision.model.edge_points import VisibleEdges, visible_edges

TOLERANCE_PX = 1  # an agreeing gradient lies within this many pixels of the projected edge
# A gradient from this Sobel magnitude, half the search's (``gradients.MAG_THRESHOLD``), also agrees where
# fewer than ``QUIET_SHARE`` of the pixels in the ``QUIET_WINDOW_PX`` square round it have one: a line
# 3 px wide across the square covers a fifth of it, a wood or cloth table's grain most of it (Blender
# piles held out: 66 -> 72 found right, no wrong; sygrid_synth, lmo_dev and the plane renders unchanged)
FAINT_MAG_THRESHOLD = 20.0
QUIET_WINDOW_PX = 15
QUIET_SHARE = 0.3
MIN_INNER_POINTS = 20
# an orientation's points within this of one another weigh as one stretch of edge (``coverage_weights``):
# a part's arm end counts like a stretch of its side this long (sygrid_synth's calibration scenes: more of
# an allen key's right poses reach its point at 32 px than at 8 or 16, and a clamp's and a spark plug key's
# as many as along the orientation-balanced agreement)
COVERAGE_RADIUS_PX = 32.0
TANGENT_STEP_MM = 0.5  # an edge's direction is read from its projection over this step


def agreeing_bits(bits: np.ndarray, faint: np.ndarray | None = None) -> np.ndarray:
    """The orientation bits spread over the tolerance: a point agrees where its own bin is set in this.
    ``faint``: the same image's bits from ``FAINT_MAG_THRESHOLD``, added where the table round them is
    quiet (``QUIET_SHARE``): a white part on a white table shows its outline a few grey levels deep, and
    a plain table has no such gradients round it, where grain has them everywhere."""
    if faint is not None:
        busy = cv2.blur((faint > 0).astype(np.float32), (QUIET_WINDOW_PX, QUIET_WINDOW_PX))
        bits = bits | np.where(busy < QUIET_SHARE, faint, 0).astype(np.uint8)
    return spread(bits, 2 * TOLERANCE_PX + 1)


def edge_agreement(vertices_mm: np.ndarray, faces: np.ndarray, creases: np.ndarray, pose: Pose,
                   intr: Intrinsics, agreeing: np.ndarray) -> dict[str, float]:
    """``edge_agreement`` and ``inner_agreement`` of ``pose`` on a frame's ``agreeing_bits``."""
    h, w = agreeing.shape
    return agreement_of_edges(visible_edges(vertices_mm, faces, creases, pose, intr, (w, h)), intr, agreeing)


def agreement_of_edges(e: VisibleEdges | None, intr: Intrinsics, agreeing: np.ndarray) -> dict[str, float]:
    """``edge_agreement`` of the edges ``e`` a pose shows (``visible_edges`` in the image of ``agreeing``)."""
    if e is None:
        return dict.fromkeys(("edge_agreement", "outline_agreement", "inner_agreement", "edge_coverage",
                              "outline_coverage"), 0.0)
    unit = e.tangent_cam / np.maximum(np.linalg.norm(e.tangent_cam, axis=1), 1e-9)[:, None]
    ori = quantise(edge_normals_px(e.p_cam, unit, intr)[1])
    every = share_agreeing(e.uv, ori, agreeing)
    inner = ~e.outline & _inside(e.uv, agreeing.shape)
    out = e.outline
    return {"edge_agreement": every,
            "outline_agreement": share_agreeing(e.uv[out], ori[out], agreeing),
            "inner_agreement": share_agreeing(e.uv[inner], ori[inner], agreeing)
            if inner.sum() >= MIN_INNER_POINTS else every,
            "edge_coverage": share_agreeing(e.uv, ori, agreeing, coverage_weights),
            "outline_coverage": share_agreeing(e.uv[out], ori[out], agreeing, coverage_weights)}


def edge_normals_px(p_cam: np.ndarray, tangent_cam: np.ndarray, intr: Intrinsics
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame edge points and their unit tangents -> (P, 2) pixels and (P,) directions (rad) of the
    projected edges' normals: the tangent is projected from both ends of a ``TANGENT_STEP_MM`` step, so a
    point's rounding to a pixel does not turn it."""
    f = np.array([intr.fx, intr.fy])
    c = np.array([intr.cx, intr.cy])
    uv = p_cam[:, :2] / p_cam[:, 2:3] * f + c
    q = p_cam + TANGENT_STEP_MM * tangent_cam
    d = q[:, :2] / q[:, 2:3] * f + c - uv
    return uv, np.arctan2(d[:, 0], -d[:, 1])


def coverage_weights(uv: np.ndarray, ori: np.ndarray) -> np.ndarray:
    """Weights of points at pixels ``uv`` with orientation bins ``ori``: 1 / (the points of the same bin
    within ``COVERAGE_RADIUS_PX``, itself included), summing to 1."""
    order = np.argsort(ori, kind="stable")
    starts = np.searchsorted(ori[order], np.arange(N_ORI + 1))
    n = np.empty(len(uv))
    n[order] = _neighbours_in_bin(np.ascontiguousarray(uv[order], np.float64), starts,
                                  COVERAGE_RADIUS_PX ** 2)
    w = 1.0 / n
    return w / w.sum()


@numba.njit(cache=True)
def _neighbours_in_bin(uv, starts, r2):  # pragma: no cover - compiled
    """Points sorted by bin (bin b: ``starts[b]:starts[b + 1]``) -> each one's points of its bin within
    sqrt(r2), itself included."""
    out = np.zeros(uv.shape[0])
    for b in range(starts.shape[0] - 1):
        for i in range(starts[b], starts[b + 1]):
            c = 0
            for j in range(starts[b], starts[b + 1]):
                du = uv[i, 0] - uv[j, 0]
                dv = uv[i, 1] - uv[j, 1]
                if du * du + dv * dv <= r2:
                    c += 1
            out[i] = c
    return out


def share_agreeing(uv: np.ndarray, ori: np.ndarray, agreeing: np.ndarray,
                   weights: Callable[..., np.ndarray] | None = None) -> float:
    """The weighted share of the points at pixels ``uv`` inside the image whose orientation bin ``ori`` is
    set in ``agreeing`` (a frame's ``agreeing_bits``); 0 with none. ``weights(uv, ori)`` of the points
    inside (None: ``gradients.balanced_weights`` of their bins)."""
    iu, iv = _pixels(uv)
    inside = _within(iu, iv, agreeing.shape)
    if not inside.any():
        return 0.0
    agree = (agreeing[iv[inside], iu[inside]] >> ori[inside]) & 1
    w = balanced_weights(ori[inside]) if weights is None else weights(uv[inside], ori[inside])
    return float((w * agree).sum())


def _inside(uv: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    return _within(*_pixels(uv), shape)


def _pixels(uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)


def _within(iu: np.ndarray, iv: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    return (iu >= 0) & (iu < shape[1]) & (iv >= 0) & (iv < shape[0])
