"""A lens for synthetic images: what a camera with distortion would take of an ideal pinhole picture."""

from __future__ import annotations

import cv2
import numpy as np

from service.vision.geometry.camera import Intrinsics, undistort_points


def distort_image(img: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """The picture the lens ``intr.dist`` would take of the ideal pinhole picture ``img`` (h, w)."""
    h, w = img.shape
    vv, uu = np.mgrid[0:h, 0:w]
    src = undistort_points(np.stack([uu.ravel(), vv.ravel()], 1).astype(np.float64), intr)
    mx = src[:, 0].reshape(h, w).astype(np.float32)
    my = src[:, 1].reshape(h, w).astype(np.float32)
    return cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
