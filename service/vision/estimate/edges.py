"""Image edges: LSD line segments, binned by orientation.

Segments are in full-resolution pixels ``uv`` (centre of the top-left pixel at (0, 0)) whatever
resolution LSD ran at; orientations are undirected, ``theta_rad`` in [0, pi), measured from +u
towards +v (image rows grow downwards).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import cv2
import numpy as np

from service.vision import threads
from service.vision.geometry.camera import Intrinsics, undistort_points

DEFAULT_LSD_SCALE = 0.5  # LSD on the half-size image: ~2x faster, segments still sub-pixel
MIN_SEGMENT_PX = 4.0  # full-resolution length below which LSD segments are mostly noise
# A straight segment of the distorted image is a curve of the ideal one: it is undistorted in pieces
# at most this long, so every piece's chord stays on that curve to well under a pixel.
SPLIT_PX = 16.0
# ``detect_segments_in_bands``: the bands overlap by this (pixels of the image LSD runs on), so that a
# segment cut at one band's edge is whole enough in the other's
BAND_OVERLAP_PX = 16
# LSD resamples its image by 0.8 (4 rows of 5) before it looks for segments: a band starting on a multiple of
# 5 rows is resampled on the whole image's rows (another start found a sixth of its segments elsewhere)
LSD_RESAMPLING_PERIOD = 5


@dataclass(frozen=True)
class Segments:
    uv0: np.ndarray  # (S, 2) float32, full-resolution pixels
    uv1: np.ndarray  # (S, 2) float32
    theta_rad: np.ndarray  # (S,) float32 in [0, pi)
    image_shape: tuple[int, int]  # (h, w) of the full-resolution image

    @property
    def lengths_px(self) -> np.ndarray:
        return np.linalg.norm(self.uv1 - self.uv0, axis=1)

    def __len__(self) -> int:
        return int(len(self.uv0))

    def crop(self, u0: int, v0: int, w: int, h: int) -> Segments:
        """Segments touching the window [u0, u0 + w) x [v0, v0 + h), in the window's pixels."""
        lo = np.minimum(self.uv0, self.uv1)
        hi = np.maximum(self.uv0, self.uv1)
        keep = (hi[:, 0] >= u0 - 1) & (lo[:, 0] <= u0 + w) & (hi[:, 1] >= v0 - 1) & (lo[:, 1] <= v0 + h)
        shift = np.array([u0, v0], np.float32)
        return Segments(self.uv0[keep] - shift, self.uv1[keep] - shift, self.theta_rad[keep], (h, w))


def to_grey_u8(image: np.ndarray) -> np.ndarray:
    """(H, W[, 3|4]) uint8/uint16/float image -> (H, W) uint8 grey (BGR order for colour)."""
    img = np.asarray(image)
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code) if img.shape[2] in (3, 4) else img[..., 0]
    return stretch_u8(img)


def stretch_u8(img: np.ndarray) -> np.ndarray:
    """Any-depth image (any channels) -> uint8, all channels stretched alike (uint8 as it is)."""
    if img.dtype == np.uint8:
        return img
    if img.dtype == np.uint16:
        # Stretch what the sensor used, not the whole 16-bit range: 12-bit cameras store 0..4095.
        hi = max(int(img.max()), 1)
        return (img.astype(np.float32) * (255.0 / hi)).round().clip(0, 255).astype(np.uint8)
    f = img.astype(np.float32)
    lo, hi = float(f.min()), float(f.max())
    return ((f - lo) * (255.0 / max(hi - lo, 1e-6))).round().clip(0, 255).astype(np.uint8)


_LOCAL = threading.local()


def _lsd():
    # One detector per thread: sharing one across the API's threadpool corrupts OpenCV's heap.
    det = getattr(_LOCAL, "lsd", None)
    if det is None:
        det = _LOCAL.lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD)
    return det


def detect_segments(grey: np.ndarray, *, scale: float = DEFAULT_LSD_SCALE, blur_sigma: float = 0.0,
                    min_length_px: float = MIN_SEGMENT_PX, roi: tuple[int, int, int, int] | None = None
                    ) -> Segments:
    """LSD on ``grey`` (H, W) uint8 resized by ``scale``; ``roi = (u0, v0, w, h)`` restricts the
    detection to a window (coordinates stay those of the full image)."""
    h, w = grey.shape[:2]
    u0 = v0 = 0
    img = grey
    if roi is not None:
        u0, v0, rw, rh = roi
        img = grey[v0:v0 + rh, u0:u0 + rw]
    if blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
    if scale != 1.0:
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    lines = _lsd().detect(img)[0]
    return _segments(lines, scale, u0, v0, (h, w), min_length_px)


def detect_segments_in_bands(grey: np.ndarray, *, scale: float = DEFAULT_LSD_SCALE,
                             min_length_px: float = MIN_SEGMENT_PX) -> Segments:
    """``detect_segments`` of the whole image, its top and bottom halves (overlapping by
    ``BAND_OVERLAP_PX`` or a little more) detected at once, the bottom on the background pool (OpenCV
    releases the GIL). LSD's standard refinement applies no NFA test, so a band finds what the whole
    image does but near its edges (and for the order its gradient bins seed regions in): segments
    crossing the middle come out in two pieces, the overlap twice; their distance transform is the
    same but near the pieces' ends."""
    h, w = grey.shape[:2]
    img = grey if scale == 1.0 else cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    mid = img.shape[0] // 2
    start = (mid - BAND_OVERLAP_PX) // LSD_RESAMPLING_PERIOD * LSD_RESAMPLING_PERIOD
    top, bottom = img[:mid + BAND_OVERLAP_PX], img[start:]
    fut = threads.background().submit(lambda: _lsd().detect(bottom)[0])
    a = _lsd().detect(top)[0]
    b = fut.result()
    parts = [x.reshape(-1, 4) for x in (a, b) if x is not None and len(x)]
    if b is not None and len(b):
        parts[-1] = parts[-1] + np.array([0, start, 0, start], np.float32)
    lines = np.concatenate(parts) if parts else None
    return _segments(lines, scale, 0, 0, (h, w), min_length_px)


def _segments(lines: np.ndarray | None, scale: float, u0: int, v0: int, shape_hw: tuple[int, int],
              min_length_px: float) -> Segments:
    """LSD's lines (pixels of the image it ran on: the window at ``scale``) -> Segments of the full image."""
    if lines is None or len(lines) == 0:
        z = np.zeros((0, 2), np.float32)
        return Segments(z, z.copy(), np.zeros(0, np.float32), shape_hw)
    xy = lines.reshape(-1, 4).astype(np.float32)
    # Pixel-centre convention: u_full = (u_scaled + 0.5) / scale - 0.5.
    p0 = (xy[:, :2] + 0.5) / scale - 0.5 + np.array([u0, v0], np.float32)
    p1 = (xy[:, 2:] + 0.5) / scale - 0.5 + np.array([u0, v0], np.float32)
    keep = np.linalg.norm(p1 - p0, axis=1) >= min_length_px
    p0, p1 = p0[keep], p1[keep]
    d = p1 - p0
    theta = np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi).astype(np.float32)
    return Segments(p0, p1, theta, shape_hw)


def channel_of(theta_rad: np.ndarray, n_channels: int) -> np.ndarray:
    """Orientation channel (bins centred on k * pi / C) of undirected angles, int64."""
    return np.mod(np.floor(np.asarray(theta_rad) * (n_channels / np.pi) + 0.5), n_channels).astype(np.int64)


def sample_segments(seg: Segments, *, step_px: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Points every ``step_px`` along every segment: ((M, 2) uv float32, (M,) segment index)."""
    n = np.maximum(np.ceil(seg.lengths_px / step_px).astype(np.int64), 1) + 1
    idx = np.repeat(np.arange(len(seg)), n)
    start = np.repeat(np.cumsum(n) - n, n)
    frac = ((np.arange(int(n.sum())) - start) / np.repeat(n - 1, n)).astype(np.float32)
    uv = seg.uv0[idx] + (seg.uv1[idx] - seg.uv0[idx]) * frac[:, None]
    return uv, idx


def edge_channels(seg: Segments, n_channels: int, shape_hw: tuple[int, int], *, scale: float = 1.0
                  ) -> np.ndarray:
    """Rasterise segments into per-channel edge masks at ``scale`` x the full resolution.

    Returns (C, H, W) uint8 with 1 on edge pixels; H, W = ``shape_hw`` (already scaled).
    """
    h, w = shape_hw
    out = np.zeros((n_channels, h, w), np.uint8)
    if len(seg) == 0:
        return out
    uv, idx = sample_segments(seg, step_px=0.5 / max(scale, 1e-6))
    uv_s = (uv + 0.5) * scale - 0.5
    u = np.rint(uv_s[:, 0]).astype(np.int64)
    v = np.rint(uv_s[:, 1]).astype(np.int64)
    c = channel_of(seg.theta_rad, n_channels)[idx]
    ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    out[c[ok], v[ok], u[ok]] = 1
    return out


def undistort_segments(seg: Segments, intr: Intrinsics, *, split_px: float = SPLIT_PX) -> Segments:
    """Segments of the distorted image -> segments of the ideal pinhole camera ``intr.K``.

    Each segment is split into pieces of at most ``split_px`` (a straight line of the distorted
    image is a curve of the ideal one) and the endpoints are undistorted once.
    """
    if intr.dist is None or len(seg) == 0:
        return seg
    L = seg.lengths_px
    k = np.maximum(np.ceil(L / split_px).astype(np.int64), 1)
    sid = np.repeat(np.arange(len(seg)), k)
    start = np.repeat(np.cumsum(k) - k, k)
    i = np.arange(int(k.sum())) - start
    kk = np.repeat(k, k)
    a = seg.uv0[sid] + (seg.uv1[sid] - seg.uv0[sid]) * (i / kk)[:, None]
    b = seg.uv0[sid] + (seg.uv1[sid] - seg.uv0[sid]) * ((i + 1) / kk)[:, None]
    ua = undistort_points(a, intr).astype(np.float32)
    ub = undistort_points(b, intr).astype(np.float32)
    d = ub - ua
    theta = np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi).astype(np.float32)
    return Segments(ua, ub, theta, seg.image_shape)
