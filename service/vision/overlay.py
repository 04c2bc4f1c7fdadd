"""Result overlay like the paper's Tables IV, V and VII: the coarse pose's silhouette border dashed
(green), the refined pose's solid (red), drawn on the input image.

Contours are the outer border of the rasterised silhouette (``render.render`` of the bank's mesh)
in the ideal pinhole camera; with lens distortion the contour points are distorted onto the image.
"""

from __future__ import annotations

import cv2
import numpy as np

from service.vision.bank import TemplateBank
from service.vision.geometry.camera import Intrinsics, project_distorted
from service.vision.geometry.frames import Pose
from service.vision.geometry.render import render

COARSE_BGR = (0, 200, 0)  # green, dashed
REFINED_BGR = (0, 0, 255)  # red, solid
DASH_PX = 8  # dash and gap length along the contour, px
THICKNESS_PX = 1


def to_bgr(image: np.ndarray) -> np.ndarray:
    """(H, W) grey or (H, W, 3|4) colour, any of uint8/uint16/float -> (H, W, 3) uint8 BGR copy."""
    from service.vision.estimate.edges import to_grey_u8

    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (3, 4) and img.dtype == np.uint8:
        return np.ascontiguousarray(img[..., :3]).copy()
    return cv2.cvtColor(to_grey_u8(img), cv2.COLOR_GRAY2BGR)


def silhouette_contours(bank: TemplateBank, pose: Pose, intr: Intrinsics, image_size) -> list[np.ndarray]:
    """Outer borders of the model's silhouette at ``pose``: a list of (n, 2) int32 uv pixel
    polylines (closed) in the image as taken (distorted when ``intr.dist`` is set)."""
    ideal = Intrinsics(intr.fx, intr.fy, intr.cx, intr.cy)
    r = render(bank.vertices_mm, bank.faces, pose, ideal, image_size)
    cs, _ = cv2.findContours(r.mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    out = []
    for c in cs:
        c = c.reshape(-1, 2).astype(np.float64)
        if intr.dist is not None:
            c = _distort(c, intr)
        out.append(np.rint(c).astype(np.int32))
    return out


def _distort(uv: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Ideal pinhole pixels -> pixels of the distorted image (inverse of ``undistort_points``)."""
    xy = np.stack([(uv[:, 0] - intr.cx) / intr.fx, (uv[:, 1] - intr.cy) / intr.fy, np.ones(len(uv))], 1)
    return project_distorted(xy, intr)


def _dashed(img: np.ndarray, poly: np.ndarray, color, dash_px: int, thickness: int) -> None:
    """Draw a closed polyline dashed: ``dash_px`` on, ``dash_px`` off, by arc length."""
    pts = np.vstack([poly, poly[:1]]).astype(np.float64)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    on = (np.floor(s[:-1] / dash_px).astype(np.int64) % 2) == 0
    for i in np.flatnonzero(on):
        a = tuple(int(x) for x in pts[i])
        b = tuple(int(x) for x in pts[i + 1])
        cv2.line(img, a, b, color, thickness, cv2.LINE_8)


def draw_overlay(image: np.ndarray, bank: TemplateBank, intr: Intrinsics, coarse_pose: Pose | None,
                 refined_pose: Pose | None, *, dash_px: int = DASH_PX, thickness: int = THICKNESS_PX
                 ) -> np.ndarray:
    """(H, W) grey or (H, W, 3) BGR image -> (H, W, 3) uint8 BGR with the coarse border dashed
    (``COARSE_BGR``) and the refined border solid (``REFINED_BGR``, drawn on top)."""
    out = to_bgr(image)
    h, w = out.shape[:2]
    if coarse_pose is not None:
        for c in silhouette_contours(bank, coarse_pose, intr, (w, h)):
            _dashed(out, c, COARSE_BGR, dash_px, thickness)
    if refined_pose is not None:
        for c in silhouette_contours(bank, refined_pose, intr, (w, h)):
            cv2.polylines(out, [c.reshape(-1, 1, 2)], True, REFINED_BGR, thickness, cv2.LINE_8)
    return out


def encode_png(img: np.ndarray) -> bytes:
    """(H, W[, 3]) uint8 -> PNG bytes."""
    ok, buf = cv2.imencode(".png", np.asarray(img))
    if not ok:  # pragma: no cover - cv2 fails only on unsupported dtypes
        raise ValueError("could not encode the overlay as PNG.")
    return buf.tobytes()
