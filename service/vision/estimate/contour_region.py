"""A pose's outline moved to where the part's own colours end (issue #14: the depth of real photos).

On real photos the edge refinement (``refine.py``) keeps most of a start pose's depth error: a printed
or painted part has edges just inside its rim, and a silhouette a few percent too small settles on them
(lmo_dev, 50 truths started at x 1.06 their depth: refined x 1.028 at the median, 16 % within 2 %;
``bench/depth_from_gt.py``). Region-based trackers (PWP3D, RBOT, SRT3D) find the outline instead where
the colours inside the silhouette give way to those around it. Here, per round: the colours of a band
inside the silhouette and of a band outside it are binned (``colour_prior``'s Lab bins), each pixel's
log-odds of belonging to the inside band is read along every border point's outward normal, the point is
matched to the step where part-coloured pixels end (the inside mean above ``MIN_LOG_ODDS``, the outside
mean below minus it, else unmatched), and the pose is solved for the border points to reach their steps
(the line stage's point-to-line residual, ``refine.line_residuals``). No colour of the CAD model is
needed: the colours are the frame's own at the current pose.
"""

from __future__ import annotations

import cv2
import numpy as np

from service.vision.estimate import refine as rf
from service.vision.estimate.colour_prior import density, lab_bins
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose
from service.vision.geometry.render import rasterise_roi
from service.vision.geometry.rotations import PoseParams

REACH_PX = 8.0  # a border point's step is looked for this far each way along its normal
BAND_PX = 10  # width of the inside and outside bands whose colours are compared
ROUNDS = 4  # match, solve, match again ...
F_SCALE_PX = 1.5  # robust-loss scale of the solve
MIN_LOG_ODDS = 0.3  # a step counts when the inside side is this part-coloured on average, the outside not
LOG_ODDS_CLIP = 3.0
MIN_MATCHED = 0.2  # share of border points that must find a step, else the pose is left as it is
MAX_ITER = 30


def region_contour_refine(bank, pose: Pose, image_bgr: np.ndarray, intr: Intrinsics, *,
                          distance_mm: float | None = None, rounds: int = ROUNDS) -> Pose:
    """``pose`` (T_cam_obj) moved so that its outline lies where the colours inside it give way to the
    colours around it; ``pose`` itself when too few border points find such a step."""
    ideal = intr.pinhole()
    H, W = image_bgr.shape[:2]
    for _ in range(rounds):
        border = rf.border_points(bank, pose, ideal, (W, H))
        if len(border.p_obj) < 6:
            return pose
        window = _window(bank, pose, ideal, (W, H))
        if window is None:
            return pose
        mask, (u0, v0) = window
        h, w = mask.shape
        L = _inside_log_odds(image_bgr[v0:v0 + h, u0:u0 + w], mask)
        if L is None:
            return pose
        params = PoseParams(pose, bank.centre_obj, bank.symmetry_axis_obj, distance_mm)
        uv, theta, _, _ = rf.project_border(params, np.zeros(params.n), border, ideal, with_jac=False)
        origin = np.array([u0, v0], float)
        normal, target, good = steps_along_normals(L, mask, uv - origin, theta)
        idx = np.flatnonzero(good)
        if len(idx) < max(6, MIN_MATCHED * len(uv)):
            return pose
        offset = np.einsum("ij,ij->i", normal[idx], target[idx] + origin)
        pose = _solved(params, border, ideal, rf.LineMatch(idx, normal[idx], offset))
    return pose


def _solved(params: PoseParams, border, intr: Intrinsics, match: rf.LineMatch) -> Pose:
    res = rf._solve(lambda x: rf.line_residuals(params, x, border, intr, match), params, "soft_l1",
                    F_SCALE_PX, MAX_ITER, rf.LINE_TOL)
    return params.pose(res.x)


def _window(bank, pose: Pose, intr: Intrinsics, size: tuple[int, int]):
    """(silhouette mask of a window holding the outline's bands and reach, its (u0, v0)), or None."""
    W, H = size
    _, face, (fu, fv) = rasterise_roi(bank.vertices_mm, bank.faces, pose, intr.K, size)
    fh, fw = face.shape
    if fh == 0 or fw == 0:
        return None
    m = int(BAND_PX + REACH_PX + 2)
    u0, v0 = max(fu - m, 0), max(fv - m, 0)
    u1, v1 = min(fu + fw + m, W), min(fv + fh + m, H)
    mask = np.zeros((v1 - v0, u1 - u0), np.uint8)
    mask[fv - v0:fv - v0 + fh, fu - u0:fu - u0 + fw] = face >= 0
    return mask, (u0, v0)


def _inside_log_odds(bgr: np.ndarray, mask: np.ndarray) -> np.ndarray | None:
    """(h, w) float32 log-odds of each pixel's colour under the inside band's colours against the outside
    band's (clipped to +-LOG_ODDS_CLIP), or None if a band is empty."""
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * BAND_PX + 1, 2 * BAND_PX + 1))
    inside = (mask > 0) & (cv2.erode(mask, k, borderType=cv2.BORDER_CONSTANT, borderValue=0) == 0)
    outside = (cv2.dilate(mask, k) > 0) & (mask == 0)
    if not inside.any() or not outside.any():
        return None
    bins = lab_bins(bgr)
    p_in, p_out = density(bins[inside]), density(bins[outside])
    floor = 1e-6
    lo = np.log(p_in.ravel()[bins] + floor) - np.log(p_out.ravel()[bins] + floor)
    return np.clip(lo, -LOG_ODDS_CLIP, LOG_ODDS_CLIP).astype(np.float32)


def steps_along_normals(L: np.ndarray, mask: np.ndarray, uv: np.ndarray, theta: np.ndarray):
    """Per border point (``uv`` in ``L``'s pixels, ``theta`` its outline's direction): the outward unit
    normal (M, 2), the point on it where part-coloured pixels end (M, 2), and whether that step is real."""
    h, w = L.shape
    normal = np.stack([-np.sin(theta), np.cos(theta)], 1)
    probe = np.round(uv + 2.0 * normal).astype(int)
    on = (probe[:, 0] >= 0) & (probe[:, 0] < w) & (probe[:, 1] >= 0) & (probe[:, 1] < h)
    flip = np.zeros(len(uv), bool)
    flip[on] = mask[probe[on, 1], probe[on, 0]] > 0  # 2 px along it is still inside: it points in
    normal[flip] *= -1.0
    s = np.arange(-REACH_PX, REACH_PX + 0.5)
    pts = (uv[:, None, :] + s[None, :, None] * normal[:, None, :]).astype(np.float32)
    vals = cv2.remap(L, pts[..., 0], pts[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=0.0)
    c = np.cumsum(vals, 1)
    total = c[:, -1:]
    split = c[:, :-1] - (total - c[:, :-1])  # inside (samples <= j) minus outside (> j)
    j = np.argmax(split, 1)
    rows = np.arange(len(uv))
    n_in = j + 1
    mean_in = c[rows, j] / n_in
    mean_out = (total[:, 0] - c[rows, j]) / (len(s) - n_in)
    good = (mean_in > MIN_LOG_ODDS) & (mean_out < -MIN_LOG_ODDS)
    target = uv + (s[j] + 0.5)[:, None] * normal
    return normal, target, good
