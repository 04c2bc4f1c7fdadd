"""A region of interest: the image polygon the part's projected centre must lie in.

The search is restricted, not filtered afterwards: level A only scans anchors inside the polygon
(``coarse.scan_level_a``), and only the edge segments near it (within the part's largest projected
radius of its bounding box) enter the distance tensor. A rectangle is the polygon of its 4 corners.
"""

from __future__ import annotations

import cv2
import numpy as np

from service.vision.estimate.edges import Segments


def rect_polygon(x: float, y: float, w: float, h: float) -> np.ndarray:
    """(4, 2) float64 uv corners of the rectangle with top-left pixel (x, y), w x h pixels."""
    return np.array([[x, y], [x + w, y], [x + w, y + h], [x, y + h]], float)


def roi_mask(poly_uv: np.ndarray, image_shape: tuple[int, int]) -> np.ndarray:
    """(h, w) bool, True at the pixels whose centres lie in the polygon (``image_shape`` = (h, w))."""
    h, w = image_shape
    mask = np.zeros((h, w), np.uint8)
    pts = np.rint(np.asarray(poly_uv, float) * 16).astype(np.int32)  # 4 fractional bits
    cv2.fillPoly(mask, [pts], 1, lineType=cv2.LINE_8, shift=4)
    return mask.astype(bool)


def inside(poly_uv: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(N,) bool: the points ``uv`` (N, 2) inside (or on) the polygon."""
    c = np.asarray(poly_uv, np.float32).reshape(-1, 1, 2)
    return np.array([cv2.pointPolygonTest(c, (float(u), float(v)), False) >= 0 for u, v in np.asarray(uv)],
                    bool)


def crop_segments(seg: Segments, poly_uv: np.ndarray, margin_px: float) -> Segments:
    """The segments with a point within the polygon's bounding box grown by ``margin_px``."""
    lo = np.asarray(poly_uv, float).min(axis=0) - margin_px
    hi = np.asarray(poly_uv, float).max(axis=0) + margin_px
    a, b = seg.uv0.astype(np.float64), seg.uv1.astype(np.float64)
    # Segment against box: keep when the segment's bounding box overlaps the grown box (cheap, conservative).
    keep = np.all((np.minimum(a, b) <= hi) & (np.maximum(a, b) >= lo), axis=1)
    return Segments(seg.uv0[keep], seg.uv1[keep], seg.theta_rad[keep], seg.image_shape)


def segments_cross(p: np.ndarray) -> bool:
    """True when two non-adjacent edges of the closed polygon ``p`` (N, 2) intersect."""
    p = np.asarray(p, float)
    n = len(p)

    def orient(a, b, c):
        return np.sign((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))

    def on(a, b, c):  # c on segment ab, given collinear
        return min(a[0], b[0]) <= c[0] <= max(a[0], b[0]) and min(a[1], b[1]) <= c[1] <= max(a[1], b[1])

    for i in range(n):
        a, b = p[i], p[(i + 1) % n]
        for j in range(i + 1, n):
            if j == i or (j + 1) % n == i or j == (i + 1) % n:
                continue
            c, d = p[j], p[(j + 1) % n]
            o1, o2, o3, o4 = orient(a, b, c), orient(a, b, d), orient(c, d, a), orient(c, d, b)
            if o1 != o2 and o3 != o4:
                return True
            if (o1 == 0 and on(a, b, c)) or (o2 == 0 and on(a, b, d)) or (o3 == 0 and on(c, d, a)) \
                    or (o4 == 0 and on(c, d, b)):
                return True
    return False


def polygon_area(p: np.ndarray) -> float:
    """Unsigned shoelace area of the polygon (N, 2), px^2."""
    p = np.asarray(p, float)
    return float(abs(np.dot(p[:, 0], np.roll(p[:, 1], -1)) - np.dot(p[:, 1], np.roll(p[:, 0], -1))) / 2)
