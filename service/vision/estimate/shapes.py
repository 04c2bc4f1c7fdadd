"""Silhouettes compared in a canonical frame, and the generic shapes any everyday object shows.

A silhouette is moved to a ``CANON_PX`` square (centroid at the centre, principal axis on x, area a
fixed share of the square), so two silhouettes compare by one IoU whatever their position, scale and
in-plane angle. The region proposals (``regions``) compare image regions with the bank's templates
this way; both they and the verdict's evidence (``evidence``) compare a silhouette with a family of
generic shapes (ellipses, rectangles, cylinder and box views): a silhouette that one of them fits
closely says little about which object made it (a white bowl fits a duck's or a bottle's outline
seen from some sides), so evidence gathered along it is weaker evidence for the part.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

CANON_PX, CANON_AREA = 48, 0.2  # silhouettes are compared on this square, at this share of its area
ROUND_ELONG = 0.75  # a silhouette rounder than this is tried at 12 in-plane turns, not 2
SCALES = (1.0, 1.25)  # template area / region area tried (a partly hidden part's region is smaller)
MIN_SILHOUETTE_PX = 12  # a silhouette smaller than this says nothing about its shape


def principal_axis(mo: dict) -> tuple[float, float]:
    """(angle of the major axis in rad, elongation sqrt(minor / major) in 0..1) from cv2 moments."""
    a, b, c = mo["mu20"], mo["mu11"], mo["mu02"]
    ang = 0.5 * math.atan2(2 * b, a - c)
    d = math.sqrt(max((a - c) ** 2 + 4 * b * b, 0.0))
    l1, l2 = (a + c + d) / 2, (a + c - d) / 2
    return ang, math.sqrt(max(l2, 0.0) / l1) if l1 > 0 else 1.0


def canonical(mask: np.ndarray, mo: dict, angle_rad: float, area_scale: float = 1.0,
              out: np.ndarray | None = None) -> np.ndarray:
    """``mask`` moved to a ``CANON_PX`` square: its centroid at the centre, its axis at ``angle_rad``
    turned onto x, its area scaled to ``CANON_AREA`` x ``area_scale`` of the square (float 0..1; written
    into ``out``, (G, G) float32, when given). ``mask`` may already be float32."""
    G = CANON_PX
    s = math.sqrt(CANON_AREA * area_scale * G * G / mo["m00"])
    cx, cy = mo["m10"] / mo["m00"], mo["m01"] / mo["m00"]
    c, sn = math.cos(-angle_rad), math.sin(-angle_rad)
    A = s * np.array([[c, -sn], [sn, c]])
    off = np.array([G / 2 - 0.5, G / 2 - 0.5]) - A @ np.array([cx, cy])
    src = mask if mask.dtype == np.float32 else mask.astype(np.float32)
    return cv2.warpAffine(src, np.hstack([A, off[:, None]]), (G, G), dst=out, flags=cv2.INTER_LINEAR)


def canonical_turns(mask_f: np.ndarray, mo: dict, angles_rad: list[float], out: np.ndarray) -> None:
    """``canonical(mask_f, mo, a)`` for each of ``angles_rad`` into the rows of ``out`` (T, G^2) float32:
    the same affine maps (the matrix products batched, which numpy computes as one at a time), one
    ``warpAffine`` each."""
    G = CANON_PX
    s = math.sqrt(CANON_AREA * 1.0 * G * G / mo["m00"])
    cx, cy = mo["m10"] / mo["m00"], mo["m01"] / mo["m00"]
    cs = [(math.cos(-a), math.sin(-a)) for a in angles_rad]
    A = s * np.array([[[c, -sn], [sn, c]] for c, sn in cs])  # (T, 2, 2)
    off = np.array([G / 2 - 0.5, G / 2 - 0.5]) - A @ np.array([cx, cy])
    M = np.concatenate([A, off[:, :, None]], axis=2)
    for i in range(len(angles_rad)):
        cv2.warpAffine(mask_f, M[i], (G, G), dst=out[i].reshape(G, G), flags=cv2.INTER_LINEAR)


def _poly_mask(pts: np.ndarray, size: int = 256) -> np.ndarray:
    """The convex hull of ``pts`` (M, 2) filled on a ``size`` square (scaled to fit with a margin)."""
    pts = np.asarray(pts, float)
    pts = pts - (pts.max(0) + pts.min(0)) / 2
    pts = pts * (0.4 * size / max(np.abs(pts).max(), 1e-9)) + size / 2
    m = np.zeros((size, size), np.uint8)
    cv2.fillConvexPoly(m, cv2.convexHull(np.round(pts * 16).astype(np.int32)), 1, cv2.LINE_8, 4)
    return m


def generic_shapes() -> list[np.ndarray]:
    """The look-alike gate's family of generic silhouettes, binary masks (each shape's scale, position
    and in-plane angle do not matter: they are compared in the canonical frame). Everything a plain
    everyday object shows from any side, all convex: ellipses (a ball, a disc, a can seen end-on
    obliquely) and rectangles (a slab face-on) over aspect ratios 0.1 .. 1; cylinder views (two
    elliptical caps of semi-axes r and r |cos theta| joined by their hull: the axis tilted theta from
    the line of sight) over length / diameter 0.25 .. 6 and theta 0 .. 90 deg, the far cap 1, 0.85 or
    0.7 times the near one (a cylinder near the camera, seen in perspective, tapers; so does a cup); box
    views (the hull of a box's 8 corners, orthographic) over 6 proportions x 16 orientations (a fixed
    pseudo-random set).
    ~310 masks: a few per cent of a bank's templates, so the gate costs little."""
    out = []
    t = np.linspace(0, 2 * np.pi, 96, endpoint=False)
    circle = np.stack([np.cos(t), np.sin(t)], 1)
    for a in np.linspace(0.1, 1.0, 12):
        out.append(_poly_mask(circle * [1.0, a]))  # ellipse
        out.append(_poly_mask(np.array([[-1, -a], [1, -a], [1, a], [-1, a]], float)))  # rectangle
    for ld in (0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0):  # cylinder: length / diameter
        for th in np.radians([0, 15, 30, 45, 60, 75, 90]):  # axis tilt from the line of sight
            half = ld * math.sin(th)  # projected half-length in radii (length 2 ld r)
            cap = circle * [abs(math.cos(th)), 1.0]  # along the axis (x): r |cos th|, across: r
            for rho in (1.0, 0.85, 0.7):  # far cap / near cap: perspective (or a frustum: a cup)
                out.append(_poly_mask(np.concatenate([cap + [half, 0], rho * cap - [half, 0]])))
    rng = np.random.default_rng(13)
    corners = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
    for dims in ((1, 1, 1), (1, 1, 0.5), (1, 0.5, 0.25), (1, 1, 0.2), (1, 0.6, 0.6), (1, 0.3, 0.3)):
        for _ in range(16):
            q = rng.normal(size=4)
            w, x, y, z = q / np.linalg.norm(q)
            R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                          [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)]])
            out.append(_poly_mask((corners * dims) @ R.T))
    return out


_GENERIC: dict = {}


def canonical_generic() -> np.ndarray:
    """(len(SCALES), M, CANON_PX^2) float32 the generic shapes in the canonical frame, per area scale (as
    ``canonical_templates``), made once per process."""
    return generic_family()[0]


def generic_family() -> tuple[np.ndarray, np.ndarray]:
    """(``canonical_generic``, its masks' areas (len(SCALES), M))."""
    key = (CANON_PX, CANON_AREA, SCALES)
    if key not in _GENERIC:
        shapes = generic_shapes()
        out = np.zeros((len(SCALES), len(shapes), CANON_PX * CANON_PX), np.float32)
        for n, m in enumerate(shapes):
            mo = cv2.moments(m, True)
            ang, _ = principal_axis(mo)
            for k, s_a in enumerate(SCALES):
                out[k, n] = canonical(m, mo, ang, s_a).ravel() > 0.5
        _GENERIC[key] = (out, out.sum(2))
    return _GENERIC[key]


def best_iou_rows(rows: np.ndarray, canon: np.ndarray, canon_area: np.ndarray | None = None, *,
                  blas: bool = True) -> np.ndarray:
    """(T,) each of ``rows``' (T, G^2) float 0..1 (canonical masks) largest IoU with any of ``canon``
    (S, M, G^2) (canonical silhouettes per area scale; ``canon_area`` (S, M) their sums, when known): one
    matrix product for all scales (``blas`` False: numpy's own loop, for a few rows)."""
    S, M, G2 = canon.shape
    area = canon.sum(2) if canon_area is None else canon_area
    flat = canon.reshape(S * M, G2)
    inter = rows @ flat.T if blas else np.einsum("tj,kj->tk", rows, flat)  # (T, S M)
    return (inter / (rows.sum(1)[:, None] + area.reshape(1, S * M) - inter + 1e-9)).max(1)


def best_iou(rows: np.ndarray, canon: np.ndarray) -> float:
    """The largest IoU of any of ``rows`` (a region's canonical turns) with any of ``canon``."""
    return float(best_iou_rows(rows, canon).max())


def turns_of(mask: np.ndarray) -> tuple[dict, float, tuple]:
    """A silhouette's moments, principal axis angle and the in-plane turns (deg) to try it at: its axis
    either way round; a roundish silhouette every 30 degrees (its axis says little)."""
    mo = cv2.moments(mask, True)
    ang, el = principal_axis(mo)
    return mo, ang, (0.0, 180.0) if el < ROUND_ELONG else tuple(range(0, 360, 30))


def genericity(mask: np.ndarray) -> float:
    """The largest IoU of a silhouette ((H, W) 0/1 or bool) with any generic shape, over its turns and
    ``SCALES``: 1.0 where a plain ellipse, rectangle, cylinder or box view is exactly that outline (and
    for an empty or speck mask, which says nothing either)."""
    m8 = np.ascontiguousarray(mask, np.uint8)
    mo, ang, turns = turns_of(m8)
    if mo["m00"] < MIN_SILHOUETTE_PX:
        return 1.0
    rows = np.empty((len(turns), CANON_PX * CANON_PX), np.float32)
    canonical_turns(m8.astype(np.float32), mo, [ang + math.radians(t) for t in turns], rows)
    generic, area = generic_family()
    # A few rows against the family: numpy's own loop, not BLAS, whose threads cost 10-100x the product
    # itself on a loaded 2-core machine (measured: 0.3-0.6 ms against 3.5-66 ms CPU).
    return float(best_iou_rows(rows, generic, area, blas=False).max())


def distinct_px(mask: np.ndarray, generic: float) -> float:
    """How far, in pixels, the silhouette's outline lies from the best plain shape's on average, given its
    ``genericity``: (1 - generic) x area / perimeter. Two nearly equal outlines differ by a thin band, its
    area the mean width times the perimeter, so 1 - IoU is that width times perimeter over area. Under a
    pixel, no image of the part can tell it from a plain object of that outline."""
    m8 = np.ascontiguousarray(mask, np.uint8)
    area = cv2.countNonZero(m8)
    if area == 0:
        return 0.0
    contours = cv2.findContours(m8, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)[0]
    perimeter = sum(cv2.arcLength(c, True) for c in contours)
    return float((1.0 - generic) * area / max(perimeter, 1.0))
