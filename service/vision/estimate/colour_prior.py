"""How part-coloured each pixel of a frame is, from a taught part's colours (issue #14: proposals).

On lmo_dev the region hierarchy (``regions.py``) holds a node matching the true part's visible pixels
(IoU >= 0.6) on 67 queries where none of the first proposals is right: the proposals are ranked by
silhouette fit alone, and a distractor's region fits a silhouette as well as the part's. A taught part
(``model/appearance.py``) also says which colours it is made of: the likelihood ratio of a pixel's
colour under the part's colours (its taught faces, weighted by area) against the frame's own colours
(Swain and Ballard's histogram back-projection) says how much a region looks like the part, whatever
the pose. Colours are binned in Lab with a coarse L (the light varies across the part and the scene)
and smoothed over neighbouring bins (a face's median colour stands for a spread of pixel colours).
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter

BINS = (6, 16, 16)  # L, a, b bins over OpenCV's 8-bit Lab (0..255 each)
SMOOTH_BINS = 1.0  # Gaussian sigma of the histograms, bins
# The part's share of a pixel's colour is never taken as certain either way: a colour the part and the
# frame share about equally reads 0.5.
FLOOR = 1e-4


def lab_bins(bgr: np.ndarray) -> np.ndarray:
    """(...,) flat Lab bin index of each BGR colour (uint8 or float 0..255, last axis 3)."""
    px = np.clip(np.asarray(bgr, np.float32).reshape(-1, 1, 3), 0, 255).astype(np.uint8)
    lab = cv2.cvtColor(px, cv2.COLOR_BGR2LAB).reshape(-1, 3).astype(np.int64)
    b = [np.minimum(lab[:, k] * n // 256, n - 1) for k, n in enumerate(BINS)]
    return ((b[0] * BINS[1] + b[1]) * BINS[2] + b[2]).reshape(np.shape(bgr)[:-1])


def density(bins: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """(BINS) the smoothed, normalised histogram of ``lab_bins`` indices (each counted once, or by its
    weight)."""
    w = None if weights is None else np.asarray(weights, float).ravel()
    h = np.bincount(bins.ravel(), w, minlength=int(np.prod(BINS))).astype(float).reshape(BINS)
    h = gaussian_filter(h, SMOOTH_BINS, mode="constant")
    return h / max(float(h.sum()), 1e-12)


def part_density(face_bgr: np.ndarray, face_area: np.ndarray) -> np.ndarray:
    """(BINS) the part's colour density: its taught faces' colours weighted by their areas (faces no
    photo saw are left out)."""
    known = np.isfinite(face_bgr[:, 0])
    return density(lab_bins(face_bgr[known]), np.asarray(face_area, float)[known])


def likelihood(image_bgr: np.ndarray, part: np.ndarray) -> np.ndarray:
    """(h, w) float32 in [0, 1]: p_part / (p_part + p_frame) of each pixel's colour, the frame's density
    made from the image itself (a colour everywhere in the frame is weak evidence for the part)."""
    bins = lab_bins(image_bgr)
    frame = density(bins)
    pf, pb = part.ravel()[bins] + FLOOR / part.size, frame.ravel()[bins] + FLOOR / part.size
    return (pf / (pf + pb)).astype(np.float32)
