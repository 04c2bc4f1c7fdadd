"""Edges of the colour image for the proposal engine: a part whose grey level matches its
surroundings (a dark blue part on a brown table) has an outline only in colour.

Two sources, each giving what ``chamfer`` needs for the coarse search:

- ``channel_segments``: LSD on each of the B, G, R channels, the segments pooled;
- ``canny_tensor``: Canny on the colour image (OpenCV takes, per pixel, the channel with the
  strongest gradient), each edge pixel put in the orientation channel of that gradient, and the
  DT3 of those masks.
"""

from __future__ import annotations

import cv2
import numpy as np

from service.vision.estimate.chamfer import DEFAULT_TAU_PX, DistanceTensor, distance_tensor_from_edges
from service.vision.estimate.edges import DEFAULT_LSD_SCALE, Segments, channel_of, detect_segments, stretch_u8

CANNY_LOW, CANNY_HIGH = 20, 40  # hysteresis thresholds on the L2 gradient of 8-bit channels (Sobel 3x3)


def channel_segments(image: np.ndarray, *, scale: float = DEFAULT_LSD_SCALE) -> Segments:
    """LSD on each colour channel of a BGR (H, W, 3) uint8 image, pooled (a grey image: LSD on it)."""
    if image.ndim == 2:
        return detect_segments(image, scale=scale)
    segs = [detect_segments(np.ascontiguousarray(image[..., c]), scale=scale) for c in range(3)]
    return Segments(np.concatenate([s.uv0 for s in segs]), np.concatenate([s.uv1 for s in segs]),
                    np.concatenate([s.theta_rad for s in segs]), segs[0].image_shape)


def colour_u8(image: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, 3) uint8 from a grey, BGR or BGRA image of any depth (``edges.to_grey_u8``'s
    ``stretch_u8``: 16-bit to the range the sensor used, float to its own range)."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = img[..., :3] if img.shape[2] >= 3 else img[..., 0]
    return np.ascontiguousarray(stretch_u8(img))


def canny_edges(image: np.ndarray, *, scale: float = 1.0, low: float = CANNY_LOW, high: float = CANNY_HIGH
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Canny edge pixels of a grey (H, W) or colour (H, W, 3|4) image (``colour_u8``) resized by ``scale``:
    (v, u) int arrays on the resized grid and the undirected edge orientation ``theta_rad`` there
    (perpendicular to the strongest channel's gradient, [0, pi), from +u towards +v)."""
    image = colour_u8(image)
    img = image if scale == 1.0 else cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    v, u = np.nonzero(cv2.Canny(img, low, high, L2gradient=True))
    if img.ndim == 2:
        img = img[..., None]
    gx = np.stack([cv2.Sobel(img[..., c], cv2.CV_32F, 1, 0, ksize=3)[v, u] for c in range(img.shape[2])])
    gy = np.stack([cv2.Sobel(img[..., c], cv2.CV_32F, 0, 1, ksize=3)[v, u] for c in range(img.shape[2])])
    k = np.argmax(gx * gx + gy * gy, axis=0)[None]
    gx, gy = np.take_along_axis(gx, k, 0)[0], np.take_along_axis(gy, k, 0)[0]
    theta = np.mod(np.arctan2(gy, gx) + np.pi / 2, np.pi)
    return v, u, theta


def canny_tensor(image: np.ndarray, *, n_channels: int = 16, scale: float = 1.0,
                 low: float = CANNY_LOW, high: float = CANNY_HIGH,
                 box_uv: tuple[np.ndarray, np.ndarray] | None = None) -> DistanceTensor:
    """DT3 (``chamfer.distance_tensor``'s grid, truncation and relaxation) of the Canny edges of
    ``image`` at ``scale`` x its resolution; ``box_uv = (lo, hi)`` (full-resolution uv corners) keeps
    only the edges inside that box (a region of interest grown by the part's reach)."""
    v, u, theta = canny_edges(image, scale=scale, low=low, high=high)
    if box_uv is not None:
        uf, vf = (u + 0.5) / scale - 0.5, (v + 0.5) / scale - 0.5
        (u0, v0), (u1, v1) = box_uv
        keep = (uf >= u0) & (uf <= u1) & (vf >= v0) & (vf <= v1)
        v, u, theta = v[keep], u[keep], theta[keep]
    h, w = image.shape[:2]
    shape = (max(int(round(h * scale)), 1), max(int(round(w * scale)), 1))
    masks = np.zeros((n_channels,) + shape, np.uint8)
    masks[channel_of(theta, n_channels), v, u] = 1
    return distance_tensor_from_edges(masks, tau_px=DEFAULT_TAU_PX * scale, scale=scale)
