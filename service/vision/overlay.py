"""Result overlay like the paper's Tables IV, V and VII, made to be read by a person at full frame:
the coarse pose's silhouette border dashed (yellow), the refined pose's solid (magenta), the reported
pose's object axes (x red, y green, z blue, as arrows from the model origin) and a banner with the
verdict and the score, all drawn on the input image (in colour when it is colour). With several found
instances each is drawn solid with its axes and numbered as in the result's ``instances`` (1 first).
Lines, dashes and text scale with the image (``line_thickness_px``), so a 4K frame gets lines as
visible as a VGA one.

Contours are the outer border of the rasterised silhouette (``render.render`` of the bank's mesh)
in the ideal pinhole camera; with lens distortion the contour and axis points are distorted onto the
image.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from service.vision.bank import TemplateBank
from service.vision.geometry.camera import Intrinsics, project_distorted
from service.vision.geometry.frames import Pose
from service.vision.geometry.render import render

COARSE_BGR = (0, 220, 255)  # yellow, dashed
REFINED_BGR = (255, 0, 255)  # magenta, solid
REJECTED_BGR = (0, 140, 255)  # orange, dotted: the best candidate the verdict rejected
DOT_PX = 2  # dot and gap length along the contour at thickness 1, px (scaled with the thickness)
AXES_BGR = ((0, 0, 255), (0, 200, 0), (255, 80, 0))  # x red, y green, z blue
FOUND_BGR = (0, 160, 0)  # banner text: found
ABSENT_BGR = (0, 0, 220)  # banner text: not found
BANNER_BG_BGR = (255, 255, 255)
DASH_PX = 8  # dash and gap length along the contour at thickness 1, px (scaled with the thickness)
THICKNESS_PX = 1  # the thinnest line drawn
LINE_PX_PER_IMAGE_PX = 1.0 / 400.0  # line thickness per pixel of the image's longer side: 1280 px -> 3 px
AXIS_LENGTH_DIAMETERS = 0.5  # axis arrows as long as half the model's diameter


def line_thickness_px(image_size) -> int:
    """Line thickness for ``image_size`` = (w, h) pixels: 2 px at VGA, 3 at 1280 x 960, 10 at 4K."""
    return max(2 * THICKNESS_PX, int(round(max(image_size) * LINE_PX_PER_IMAGE_PX)))


def to_bgr(image: np.ndarray) -> np.ndarray:
    """(H, W) grey or (H, W, 3|4) colour, any of uint8/uint16/float -> (H, W, 3) uint8 BGR copy
    (colour stays colour: deeper images are stretched to 8 bits like the grey the search reads)."""
    from service.vision.estimate.edges import stretch_u8, to_grey_u8

    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        return np.ascontiguousarray(stretch_u8(img[..., :3])).copy()
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
                 refined_pose: Pose | None, *, dash_px: int | None = None, thickness: int | None = None,
                 found: bool | None = None, score: float | None = None, axes: bool = True,
                 rejected: Pose | None = None, instances: Sequence[Pose] = ()) -> np.ndarray:
    """(H, W) grey or (H, W, 3) BGR image -> (H, W, 3) uint8 BGR with the coarse border dashed
    (``COARSE_BGR``), the refined border solid (``REFINED_BGR``, drawn on top), the object axes of the
    reported pose (the refined one, else the coarse one) when ``axes``, and, when ``found`` is given,
    a banner saying FOUND or NOT FOUND with ``score``. ``thickness`` defaults to
    ``line_thickness_px`` of the image, ``dash_px`` to ``DASH_PX`` times the thickness. When nothing was
    found, ``rejected`` (the best candidate the verdict turned down) is drawn dotted (``REJECTED_BGR``).
    ``instances``: the other found instances' reported poses (``instances[1:]`` of the result), each
    drawn solid with its axes; then every instance, the reported one too, is labelled with its number
    (1 for the reported one), as the result lists them."""
    out = to_bgr(image)
    h, w = out.shape[:2]
    t = line_thickness_px((w, h)) if thickness is None else int(thickness)
    dash = DASH_PX * t if dash_px is None else int(dash_px)
    if rejected is not None:
        for c in silhouette_contours(bank, rejected, intr, (w, h)):
            _dashed(out, c, REJECTED_BGR, DOT_PX * t, t)
    if coarse_pose is not None:
        for c in silhouette_contours(bank, coarse_pose, intr, (w, h)):
            _dashed(out, c, COARSE_BGR, dash, t)
    if refined_pose is not None:
        for c in silhouette_contours(bank, refined_pose, intr, (w, h)):
            cv2.polylines(out, [c.reshape(-1, 1, 2)], True, REFINED_BGR, t, cv2.LINE_8)
    reported = refined_pose if refined_pose is not None else coarse_pose
    if axes and reported is not None:
        draw_axes(out, reported, intr, AXIS_LENGTH_DIAMETERS * bank.diameter_mm, t)
    outlines = []  # of every instance, in the result's order, for the numbers
    if instances and reported is not None:
        outlines.append(silhouette_contours(bank, reported, intr, (w, h)))
    for pose in instances:
        outlines.append(silhouette_contours(bank, pose, intr, (w, h)))
        for c in outlines[-1]:
            cv2.polylines(out, [c.reshape(-1, 1, 2)], True, REFINED_BGR, t, cv2.LINE_8)
        if axes:
            draw_axes(out, pose, intr, AXIS_LENGTH_DIAMETERS * bank.diameter_mm, t)
    if len(outlines) > 1:  # one instance needs no number; drawn last, so no line hides one
        for k, cs in enumerate(outlines, start=1):
            if cs:
                draw_number(out, k, np.vstack(cs), t)
    if found is not None:
        draw_banner(out, found, score, t)
    return out


def axis_endpoints_uv(pose: Pose, intr: Intrinsics, length_mm: float) -> np.ndarray | None:
    """(4, 2) float64 pixels (as taken, distorted when ``intr.dist``) of the model origin and the tips of
    its x, y, z axes ``length_mm`` long at ``pose`` (``T_cam_obj``); None if any lies behind the camera."""
    p_cam = pose.apply(np.vstack([np.zeros(3), length_mm * np.eye(3)]))
    if np.any(p_cam[:, 2] <= 1e-6):
        return None
    return project_distorted(p_cam / p_cam[:, 2:3], intr)


def draw_axes(img: np.ndarray, pose: Pose, intr: Intrinsics, length_mm: float, thickness: int) -> None:
    """Arrows from the model origin along its x (red), y (green) and z (blue) axes, in place."""
    uv = axis_endpoints_uv(pose, intr, length_mm)
    if uv is None or not np.all(np.isfinite(uv)) or np.abs(uv).max() > 1e6:
        return
    o = tuple(int(round(v)) for v in uv[0])
    for k in (2, 1, 0):  # z first, so x and y are drawn over it
        tip = tuple(int(round(v)) for v in uv[k + 1])
        cv2.arrowedLine(img, o, tip, AXES_BGR[k], thickness, cv2.LINE_AA, tipLength=0.15)


def draw_banner(img: np.ndarray, found: bool, score: float | None, thickness: int) -> None:
    """The verdict, the score and a legend, top left on a light box, in place (text scales with
    the line thickness)."""
    scale = 0.3 * thickness
    verdict = "FOUND" if found else "NOT FOUND"
    if score is not None:
        verdict += f"  score {score:.2f}" if found else f"  (best candidate score {score:.2f})"
    lines = [(verdict, FOUND_BGR if found else ABSENT_BGR, scale, max(1, thickness - 1)),
             ("refined: magenta  coarse: yellow dashed  axes: x red, y green, z blue", (40, 40, 40),
              0.5 * scale, max(1, thickness // 2))]
    pad = 4 * thickness
    sizes = [cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, s, th) for text, _, s, th in lines]
    width = max(sz[0][0] for sz in sizes) + 2 * pad
    height = sum(sz[0][1] + sz[1] for sz in sizes) + (len(lines) + 1) * pad
    cv2.rectangle(img, (0, 0), (min(width, img.shape[1] - 1), min(height, img.shape[0] - 1)), BANNER_BG_BGR,
                  cv2.FILLED)
    y = pad
    for (text, color, s, th), ((_, th_px), base) in zip(lines, sizes, strict=True):
        y += th_px
        cv2.putText(img, text, (pad, y), cv2.FONT_HERSHEY_SIMPLEX, s, color, th, cv2.LINE_AA)
        y += base + pad


def draw_number(img: np.ndarray, number: int, outline_uv: np.ndarray, thickness: int) -> None:
    """``number`` on a light box just above the top left of ``outline_uv`` ((n, 2) pixels), in place;
    kept inside the image so a part at the border is still numbered."""
    scale = 0.3 * thickness
    text = str(number)
    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, max(1, thickness - 1))
    pad = 2 * thickness
    bw, bh = tw + 2 * pad, th + base + 2 * pad
    u0 = int(np.clip(outline_uv[:, 0].min(), 0, max(img.shape[1] - bw, 0)))
    v0 = int(np.clip(outline_uv[:, 1].min() - bh - thickness, 0, max(img.shape[0] - bh, 0)))
    cv2.rectangle(img, (u0, v0), (u0 + bw, v0 + bh), BANNER_BG_BGR, cv2.FILLED)
    cv2.rectangle(img, (u0, v0), (u0 + bw, v0 + bh), REFINED_BGR, max(1, thickness // 2))
    cv2.putText(img, text, (u0 + pad, v0 + pad + th), cv2.FONT_HERSHEY_SIMPLEX, scale, (40, 40, 40),
                max(1, thickness - 1), cv2.LINE_AA)


def encode_png(img: np.ndarray) -> bytes:
    """(H, W[, 3]) uint8 -> PNG bytes."""
    ok, buf = cv2.imencode(".png", np.asarray(img))
    if not ok:  # pragma: no cover - cv2 fails only on unsupported dtypes
        raise ValueError("could not encode the overlay as PNG.")
    return buf.tobytes()
