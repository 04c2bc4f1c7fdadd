"""Every visible CAD edge of a part at a pose: the points a gradient template is projected from
(``estimate/plane_match.py``) and the edges a pose's agreement is read on (``estimate/edge_agreement.py``).

The part is rendered by the project's rasteriser, and two kinds of edge are sampled:

- **occluding edges**: pixels where the z-buffer jumps (``_near_side_of_jumps``: the outline on the
  background and the part's own overhangs), each lifted to the 3D surface point it shows, its tangent
  the direction along the jump (normal to the depth gradient);
- **crease edges**: mesh edges whose faces turn by more than ``CREASE_DEG`` (the hexagon of a nut, the
  step of a nozzle, the bevels of a spanner), sampled along their length and kept where the z-buffer
  shows them, their tangent the edge's direction.

A template keeps at most ``MAX_POINTS`` of them spread evenly over the view (``edge_points_at``), each
with its object-frame point ``p_obj`` and unit tangent ``tangent_obj``: it is projected with any
position on a plane, and the edge's image orientation read from the projected tangent.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np
import trimesh

from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose
from service.vision.geometry.render import rasterise_roi

CREASE_DEG = 30.0  # faces meeting at a sharper turn than this make a visible edge
DEPTH_JUMP_MM = 2.0  # a z-buffer step larger than this is an occluding edge ...
SLOPE_RATIO = 3.0  # ... if also this many times larger than the steps beside it
VISIBLE_TOL_MM = 1.0  # a crease sample is visible when the z-buffer next to it is not nearer than this
MAX_POINTS = 128  # points a template keeps
WINDOW_PAD_PX = 8  # the render's window round the part: wider than the depth's smoothing kernel (sigma 1)


@dataclass(frozen=True)
class EdgePoints:
    """The edge points of one view of the part: object frame, mm."""

    p_obj: np.ndarray  # (P, 3) float64
    tangent_obj: np.ndarray  # (P, 3) float64, unit
    crease: np.ndarray  # (P,) bool: from a crease edge (else an occluding edge)


EMPTY_EDGES = EdgePoints(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, bool))


def crease_edges(vertices_mm: np.ndarray, faces: np.ndarray, crease_deg: float = CREASE_DEG) -> np.ndarray:
    """(E, 2, 3) mesh edges whose faces turn by more than ``crease_deg``, object frame, mm."""
    mesh = trimesh.Trimesh(np.asarray(vertices_mm, float), np.asarray(faces))  # merged: shared edges
    sharp = np.degrees(mesh.face_adjacency_angles) > crease_deg
    return np.asarray(mesh.vertices, float)[mesh.face_adjacency_edges[sharp]]


@dataclass(frozen=True)
class VisibleEdges:
    """The edges a render of the part shows: pixels, camera-frame points and tangents, and their kind."""

    uv: np.ndarray  # (P, 2) float64 pixels
    p_cam: np.ndarray  # (P, 3) mm
    tangent_cam: np.ndarray  # (P, 3), not normalised
    crease: np.ndarray  # (P,) bool: a crease edge (else an occluding edge)
    outline: np.ndarray  # (P,) bool: on the outline against the background (else an inner edge)


def visible_edges(V: np.ndarray, F: np.ndarray, creases: np.ndarray, pose: Pose, intr: Intrinsics,
                  size: tuple[int, int]) -> VisibleEdges | None:
    """The occluding and crease edges the part shows at ``pose``; None when it covers under 4 pixels."""
    mask, depth, (u0, v0) = _window(V, F, pose, intr, size)
    if mask.sum() < 4:
        return None
    far = float(depth[mask].max()) + 10.0 * DEPTH_JUMP_MM
    depth = np.where(mask, depth, far).astype(np.float32)
    jump = _near_side_of_jumps(depth)
    smooth = cv2.GaussianBlur(depth, (0, 0), 1.0)
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3)
    jv, ju = np.nonzero(jump)
    z = depth[jv, ju].astype(float)
    ju_img, jv_img = ju + u0, jv + v0
    p_cam = np.stack([(ju_img - intr.cx) / intr.fx * z, (jv_img - intr.cy) / intr.fy * z, z], 1)
    tan_cam = np.stack([-gy[jv, ju], gx[jv, ju], np.zeros(len(jv), np.float32)], 1).astype(float)
    near_background = cv2.dilate((~mask).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    p_cr, t_cr, uv_cr = _visible_creases(creases, pose, intr, depth, jump, (u0, v0), size)
    return VisibleEdges(np.concatenate([np.stack([ju_img, jv_img], 1).astype(float), uv_cr]),
                        np.concatenate([p_cam, p_cr]), np.concatenate([tan_cam, t_cr]),
                        np.concatenate([np.zeros(len(p_cam), bool), np.ones(len(p_cr), bool)]),
                        np.concatenate([near_background[jv, ju], np.zeros(len(p_cr), bool)]))


def _window(V: np.ndarray, F: np.ndarray, pose: Pose, intr: Intrinsics, size: tuple[int, int]
            ) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """(mask, depth mm, (u0, v0)) of the part rendered at ``pose`` in the window of its projection grown by
    ``WINDOW_PAD_PX`` within the image: beyond the depth's smoothing kernel every pixel reads the
    background, as in the whole image, and the window costs a fraction of it."""
    d_roi, f_roi, (ru, rv) = rasterise_roi(V, F, pose, intr.K, size)
    w, h = size
    rh, rw = f_roi.shape
    u0, v0 = max(ru - WINDOW_PAD_PX, 0), max(rv - WINDOW_PAD_PX, 0)
    u1, v1 = min(ru + rw + WINDOW_PAD_PX, w), min(rv + rh + WINDOW_PAD_PX, h)
    mask = np.zeros((max(v1 - v0, 0), max(u1 - u0, 0)), bool)
    depth = np.full(mask.shape, np.inf, np.float32)
    mask[rv - v0:rv - v0 + rh, ru - u0:ru - u0 + rw] = f_roi >= 0
    depth[rv - v0:rv - v0 + rh, ru - u0:ru - u0 + rw] = d_roi
    return mask, depth, (u0, v0)


def edge_points_at(V: np.ndarray, F: np.ndarray, creases: np.ndarray, pose: Pose, intr: Intrinsics,
                   size: tuple[int, int], *, seed: int = 0) -> EdgePoints:
    """The edges the part shows at ``pose``, at most ``MAX_POINTS`` of them spread evenly, object frame."""
    return edge_points_of(visible_edges(V, F, creases, pose, intr, size), pose, seed=seed)


def edge_points_of(e: VisibleEdges | None, pose: Pose, *, seed: int = 0) -> EdgePoints:
    """``edge_points_at`` of the edges ``e`` the part shows at ``pose`` (``visible_edges``)."""
    rng = np.random.default_rng(seed)
    if e is None:
        return EMPTY_EDGES
    norm = np.linalg.norm(e.tangent_cam, axis=1)
    ok = norm > 1e-9
    keep = np.flatnonzero(ok)[_spread_pick(e.uv[ok], MAX_POINTS, rng)]
    p_obj = (e.p_cam[keep] - pose.t_mm) @ pose.R
    t_obj = (e.tangent_cam[keep] / norm[keep, None]) @ pose.R
    return EdgePoints(p_obj, t_obj, e.crease[keep])


def _near_side_of_jumps(depth: np.ndarray) -> np.ndarray:
    """Pixels on the near side of a z-buffer step to a 4-neighbour larger than ``DEPTH_JUMP_MM`` and than
    ``SLOPE_RATIO`` times the steps beside it: a face seen at a grazing angle steps as much from pixel
    to pixel all along, an occluding edge steps once."""
    jump = np.zeros(depth.shape, bool)
    for ax in (0, 1):
        dd = np.diff(depth, axis=ax)
        size = np.abs(dd)
        beside = _larger_beside(size) if ax == 0 else _larger_beside(size.T).T
        step = (size > DEPTH_JUMP_MM) & (size > SLOPE_RATIO * beside)
        first_nearer = step & (dd > 0)
        second_nearer = step & (dd < 0)
        if ax == 0:
            jump[:-1] |= first_nearer
            jump[1:] |= second_nearer
        else:
            jump[:, :-1] |= first_nearer
            jump[:, 1:] |= second_nearer
    return jump


def _larger_beside(size: np.ndarray) -> np.ndarray:
    """Per row of ``size``, the larger of the rows before and after it (the first and last repeated at the
    ends, as np.pad's "edge" mode, whose bookkeeping cost more than the maximum)."""
    before, after = np.empty_like(size), np.empty_like(size)
    before[0], before[1:] = size[0], size[:-1]
    after[-1], after[:-1] = size[-1], size[1:]
    return np.maximum(before, after)


def _visible_creases(creases: np.ndarray, pose: Pose, intr: Intrinsics, depth: np.ndarray,
                     jump: np.ndarray, origin: tuple[int, int], size: tuple[int, int]
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Crease samples (one per pixel) the z-buffer shows and no occluding edge already covers:
    camera-frame points, tangents and pixels. ``depth`` and ``jump``: the window at pixel ``origin`` of
    an image of ``size`` (w, h) that holds the part's projection."""
    empty = np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 2))
    if not len(creases):
        return empty
    P = creases @ pose.R.T + pose.t_mm
    step_mm = 0.7 * float(np.median(P[:, :, 2])) / intr.fx
    length = np.linalg.norm(P[:, 1] - P[:, 0], axis=1)
    k = np.maximum(1, np.ceil(length / step_mm).astype(int))
    seg = np.repeat(np.arange(len(P)), k)
    first_of = np.repeat(np.cumsum(k) - k, k)
    frac = (np.arange(len(seg)) - first_of + 0.5) / np.repeat(k, k)
    pts = P[seg, 0] + (P[seg, 1] - P[seg, 0]) * frac[:, None]
    uv = np.stack([pts[:, 0] / pts[:, 2] * intr.fx + intr.cx, pts[:, 1] / pts[:, 2] * intr.fy + intr.cy], 1)
    w, h = size
    iu, iv = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
    inside = (iu >= 1) & (iu < w - 1) & (iv >= 1) & (iv < h - 1)
    iu, iv = np.clip(iu, 1, w - 2), np.clip(iv, 1, h - 2)
    # window pixels: the window holds every sample in the image and the pixels round it
    wu, wv = iu - origin[0], iv - origin[1]
    farthest = np.full(len(pts), -np.inf)
    for dv in (-1, 0, 1):
        for du in (-1, 0, 1):
            farthest = np.maximum(farthest, depth[wv + dv, wu + du])
    ok = inside & (farthest >= pts[:, 2] - VISIBLE_TOL_MM) & ~jump[wv, wu]
    key = iv * w + iu
    ok_idx = np.flatnonzero(ok)
    _, first = np.unique(key[ok_idx], return_index=True)
    sel = ok_idx[first]
    tangent = P[seg[sel], 1] - P[seg[sel], 0]
    return pts[sel], tangent, np.stack([iu[sel], iv[sel]], 1).astype(float)


def _spread_pick(uv: np.ndarray, n_max: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of at most ``n_max`` points of ``uv`` spread evenly (greedy, the spacing relaxed until
    about that many are kept)."""
    if len(uv) <= n_max:
        return np.arange(len(uv))
    perm = rng.permutation(len(uv))
    spacing = max(1.0, len(uv) / n_max)
    keep = np.arange(0)
    for _ in range(30):
        keep = _greedy_min_dist(uv[perm], spacing * spacing)
        if len(keep) >= 0.8 * n_max or spacing <= 1.0:
            break
        spacing = max(1.0, spacing * 0.85)
    return np.sort(perm[keep][:n_max])


@numba.njit(cache=True)
def _greedy_min_dist(uv, d2):  # pragma: no cover - compiled
    out = np.empty(len(uv), np.int64)
    n = 0
    for i in range(len(uv)):
        ok = True
        for j in range(n):
            k = out[j]
            if (uv[i, 0] - uv[k, 0]) ** 2 + (uv[i, 1] - uv[k, 1]) ** 2 < d2:
                ok = False
                break
        if ok:
            out[n] = i
            n += 1
    return out[:n]
