"""Plausibility bounds checked at estimate time, once the image's size is known: values that pass the
schema (fx > 0, distance > 0, finite) but cannot describe a real camera or scene are refused with a
422 that says what is wrong and the likely fix, instead of reaching the pipeline (fx = 1e15 or
cx = 1e300 made the coarse search fail with a 500).

=====================  ==============================  ===========================================
value                  plausible                       the usual mistake
=====================  ==============================  ===========================================
distance_mm, range     10 mm .. 20 m                   metres (or micrometres) instead of mm
fx, fy                 50 .. 1,000,000 px              millimetres instead of pixels
cx, cy                 inside the image                intrinsics of another resolution
dist coefficients      |k| <= 1,000                    not OpenCV's coefficients
roi                    within 1e6 px, covers a pixel   another resolution's coordinates
plane                  10 mm .. 20 m away, in view,    metres; a plane behind the camera
                       not all nearer than the range
the part's size at     clear of the camera, 8 px ..    a mesh in the wrong units; a distance or
the nearest distance   4 x shorter side (>= 1024 px)   fx far off
=====================  ==============================  ===========================================

The last row needs the loaded model (``check_apparent_size``): the coarse search's buffers are sized by
how large the part can appear, so it is checked before any of them is made.
"""

from __future__ import annotations

import math

import numpy as np

from service.errors import UnprocessableError
from service.schemas import Camera, Options
from service.vision.bank import TemplateBank
from service.vision.estimate.search import SearchParams
from service.vision.geometry.plane import depths_in_view_mm
from service.vision.pipeline import DEFAULT_DISTANCE_RANGE_MM

DISTANCE_MM = (10.0, 20_000.0)
FOCAL_PX = (50.0, 1_000_000.0)
MAX_ABS_DISTORTION = 1_000.0
MAX_ROI_PX = 1_000_000.0  # |u|, |v| of a roi corner: far outside any image, far inside int32 / 16


def _distance(name: str, value: float) -> None:
    lo, hi = DISTANCE_MM
    if value < lo:
        raise UnprocessableError(f"The options field {name} is {value:g}, under {lo:g} mm: distances are in "
                                 f"millimetres (did you send metres?); send a value from {lo:g} to {hi:g}")
    if value > hi:
        raise UnprocessableError(f"The options field {name} is {value:g}, over {hi / 1000:g} m: distances "
                                 f"are in millimetres; send a value from {lo:g} to {hi:g}")


def check_plausible(cam: Camera, opts: Options, image_size: tuple[int, int]) -> None:
    """422 for the first implausible value of ``cam`` / ``opts`` for an image of ``image_size`` (w, h)."""
    w, h = image_size
    lo, hi = FOCAL_PX
    for name in ("fx", "fy"):
        f = getattr(cam, name)
        if f < lo:
            raise UnprocessableError(f"The camera field {name} is {f:g} px, under {lo:g} px: focal lengths "
                                     "are in pixels (focal length in mm divided by the pixel pitch in mm), "
                                     "not millimetres; send the calibrated K matrix's value")
        if f > hi:
            raise UnprocessableError(f"The camera field {name} is {f:g} px, over {hi:,.0f} px, which no real "
                                     "lens gives; send the calibrated K matrix's value in pixels")
    for name, c, size in (("cx", cam.cx, w), ("cy", cam.cy, h)):
        if not -0.5 <= c <= size - 0.5:
            raise UnprocessableError(f"The camera field {name} is {c:g} px, outside this {w} x {h} image "
                                     f"(0 to {size - 1}): the principal point must lie in the image; send "
                                     "intrinsics calibrated at this resolution (scale fx, fy, cx, cy with "
                                     "the image if it was resized)")
    if cam.dist is not None and any(abs(k) > MAX_ABS_DISTORTION for k in cam.dist):
        raise UnprocessableError(f"The camera's dist coefficients {cam.dist} include a value over "
                                 f"{MAX_ABS_DISTORTION:g} in size; send OpenCV's [k1, k2, p1, p2[, k3[, k4, "
                                 "k5, k6]]] from the calibration")
    if opts.distance_mm is not None:
        _distance("distance_mm", opts.distance_mm)
    if opts.distance_range_mm is not None:
        for v in opts.distance_range_mm:
            _distance("distance_range_mm", v)
    if opts.plane is not None:
        _plane(opts, cam, w, h)
    poly = opts.roi_uv()
    if poly is not None:
        from service.vision.estimate.roi import roi_mask

        far = float(np.abs(poly).max())
        if far > MAX_ROI_PX:  # roi_mask rasterises in int32 sixteenths of a pixel
            raise UnprocessableError(f"The options field roi has a coordinate of {far:g} px, beyond "
                                     f"{MAX_ROI_PX:,.0f} px either way: roi is in pixels of this {w} x {h} "
                                     "image (origin at the top left); send a region inside it")
        if not roi_mask(poly, (h, w)).any():
            raise UnprocessableError(f"The options field roi covers no pixel of this {w} x {h} image: give a "
                                     f"region inside u 0 to {w - 1} and v 0 to {h - 1} (pixels, origin at "
                                     "the top left)")


def _plane(opts: Options, cam: Camera, w: int, h: int) -> None:
    """The plane is 10 mm .. 20 m from the camera and some pixel's viewing ray meets it in front."""
    import numpy as np

    from service.vision.geometry.plane import MIN_RAY_COS

    lo, hi = DISTANCE_MM
    dist = -opts.plane.d_mm  # the camera's height above the plane (unit normal, d_mm < 0)
    if dist < lo:
        raise UnprocessableError(f"The options field plane is {dist:g} mm from the camera, under {lo:g} mm: "
                                 "d_mm is in millimetres (did you send metres?)")
    if dist > hi:
        raise UnprocessableError(f"The options field plane is {dist / 1000:g} m from the camera, over "
                                 f"{hi / 1000:g} m: d_mm is in millimetres")
    u = np.array([-0.5, w - 0.5, w - 0.5, -0.5, (w - 1) / 2])
    v = np.array([-0.5, -0.5, h - 0.5, h - 0.5, (h - 1) / 2])
    rays = np.column_stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones(5)])
    cos = rays @ np.asarray(opts.plane.normal, float) / np.linalg.norm(rays, axis=1)
    if not (cos < -MIN_RAY_COS).any():
        raise UnprocessableError("The options field plane is not in view: no pixel of this image looks onto "
                                 "it (it lies behind the camera, or the camera looks along it); send the "
                                 "plane in the camera frame (OpenCV: x right, y down, z forward) with its "
                                 "normal pointing towards the camera")


# How large the part may appear at the nearest distance the search places it (its bounding sphere's
# extent in px, anywhere in the image). Level A pads its DT3 by the largest template offset before the
# scan (``coarse._level_a_layout``: (h/8 + 2m) x (w/8 + 2m) x 16 channels, m ~ apparent size / 16), so
# the buffer follows the apparent size, and a part reaching the camera's plane projects to no finite
# size at all (distance_mm 50 on the 200 mm sprayer asked for 86 TiB). At 4 x the image's shorter side
# the padded layout is at most (1 + 4)^2 / 4 ~ 6 bytes per image pixel, under the 16 of the fine distance
# tensor every image already costs (so POSE_MAX_IMAGE_PIXELS bounds both); the shorter side, not the
# diagonal, because a 20000 x 32 image would otherwise allow a padding thousands of rows deep. A part that
# large shows at most a quarter of its outline, which level A's whole-outline templates cannot rank.
MAX_APPARENT_SHORT_SIDES = 4.0
# ... but never under this, for small images: 1024 px pads at most ~264 bytes per image column (and
# 0.25 MB), under the 512 of the fine tensor of an image's 32 rows at least (decode.MIN_IMAGE_SIDE_PX).
APPARENT_FLOOR_PX = 1024.0
# ... and at least one level-A pixel: smaller, every template point falls on the same coarse cell and the
# part cannot be told from a speck of noise.
MIN_APPARENT_PX = 1.0 / SearchParams.level_scale


def apparent_size_px(radius_mm: float, depth_mm: float, cam: Camera, image_size: tuple[int, int]) -> float:
    """Largest extent, px, of a sphere of ``radius_mm`` whose centre lies at camera depth ``depth_mm`` on
    the viewing ray of any pixel of an ``image_size`` (w, h) image (the corners see it most stretched):
    ``f (tan(a + b) - tan(a - b))`` for a ray ``a`` off the optical axis and the sphere's half-angle ``b``;
    inf when the sphere reaches the camera's plane z = 0 (``depth_mm <= radius_mm``)."""
    if depth_mm <= radius_mm:
        return math.inf
    w, h = image_size
    u, v = np.array([-0.5, w - 0.5]), np.array([-0.5, h - 0.5])
    tan_a = float(np.hypot(np.abs((u - cam.cx) / cam.fx).max(), np.abs((v - cam.cy) / cam.fy).max()))
    a = math.atan(tan_a)
    b = math.asin(radius_mm * math.cos(a) / depth_mm)  # depth > radius: a + b < 90 deg
    return max(cam.fx, cam.fy) * (math.tan(a + b) - math.tan(a - b))


def _depth_for(size_px: float, radius_mm: float, cam: Camera, image_size: tuple[int, int]) -> float:
    """The depth, mm, at which ``apparent_size_px`` is ``size_px`` (it falls as the depth grows)."""
    lo, hi = radius_mm, max(2.0 * radius_mm, 1.0)
    while apparent_size_px(radius_mm, hi, cam, image_size) > size_px:
        hi *= 2.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if apparent_size_px(radius_mm, mid, cam, image_size) > size_px else (lo, mid)
    return hi


def check_apparent_size(bank: TemplateBank, cam: Camera, opts: Options, image_size: tuple[int, int], *,
                        units: str = "mm") -> None:
    """422 when the part, at the nearest distance the search places it, would reach the camera or appear
    larger than ``MAX_APPARENT_SHORT_SIDES`` x the image's shorter side (``APPARENT_FLOOR_PX`` at least), or
    smaller than ``MIN_APPARENT_PX``. Run after ``check_plausible``, before the search makes a buffer.

    The nearest distance of the bank's reference point ``centre_obj``: ``distance_mm`` (the object
    origin's) less the reference point's distance from the origin; else the low end of
    ``distance_range_mm`` (or of ``pipeline.DEFAULT_DISTANCE_RANGE_MM``), or with a ``plane`` the plane's
    nearest point in view when that is farther (the plane search places nothing nearer than either).
    The part is its bounding sphere round ``centre_obj`` (half its bounding box's diagonal)."""
    w, h = image_size
    radius = 0.5 * float(np.linalg.norm(bank.extents_mm))
    offset = 0.0  # what the fix's distance adds to the reference point's depth
    if opts.distance_mm is not None and opts.plane is None:
        offset = float(np.linalg.norm(bank.centre_obj))
        depth, field = opts.distance_mm - offset, "distance_mm"
        where = f"options.distance_mm ({opts.distance_mm:g} mm)"
    else:
        field = "distance_range_mm"
        depth = (opts.distance_range_mm or DEFAULT_DISTANCE_RANGE_MM)[0]
        where = (f"the low end of options.distance_range_mm ({depth:g} mm)" if opts.distance_range_mm else
                 f"the low end of the default distance range ({depth:g} mm)")
        # (``check_plausible``'s ``_plane`` has made sure some pixel sees the plane)
        near, far = depths_in_view_mm(opts.plane.to_plane(), cam.to_intrinsics(), (w, h)) \
            if opts.plane is not None else (-math.inf, math.inf)
        if far < depth:  # a resting part's centre is nearer than the plane under it: nothing is searched
            raise UnprocessableError(
                f"The options field plane is at most {far:.0f} mm from the camera in this image, nearer than "
                f"{where} where the search starts placing the part; check the plane's d_mm (millimetres, "
                "camera frame) or send options.distance_range_mm")
        if near > depth:
            depth, field = near, "plane"
            where = f"options.plane's nearest point in view ({near:.0f} mm)"

    def fix(size_px: float, bound: str) -> str:
        d = _depth_for(size_px, radius, cam, image_size) + offset
        if not DISTANCE_MM[0] <= d <= DISTANCE_MM[1]:
            lo, hi = DISTANCE_MM
            return (f"no distance from {lo:g} mm to {hi / 1000:g} m fits it, so upload the model again with "
                    f"its true units (it was read in {units}) or check fx and fy (pixels)")
        send = {"distance_mm": f"send a distance_mm of {bound} {d:.0f} mm (millimetres to the object origin)",
                "distance_range_mm": f"send options.distance_range_mm with a low end of {bound} {d:.0f} "
                                     "mm (or distance_mm)",
                "plane": "check options.plane's d_mm (millimetres, camera frame)"}[field]
        return (f"{send}, check fx and fy (pixels), or upload the model again with its true units (it was "
                f"read in {units})")

    part = f"The part ({bank.diameter_mm:.4g} mm across)"
    size = apparent_size_px(radius, depth, cam, image_size)
    most = max(MAX_APPARENT_SHORT_SIDES * min(w, h), APPARENT_FLOOR_PX)
    if math.isinf(size):
        raise UnprocessableError(f"{part} would reach the camera at {where}; {fix(most, 'at least')}")
    if size > most:
        raise UnprocessableError(
            f"{part} would appear {size:.0f} px across at {where} with fx {cam.fx:g} px, more than the "
            f"{most:.0f} px the search allows in this {w} x {h} image ({MAX_APPARENT_SHORT_SIDES:g} x its "
            f"shorter side, at least {APPARENT_FLOOR_PX:g}); {fix(most, 'at least')}")
    if size < MIN_APPARENT_PX:
        raise UnprocessableError(
            f"{part} would appear only {size:.2g} px across at {where} with fx {cam.fx:g} px, under the "
            f"{MIN_APPARENT_PX:g} px the search can see; {fix(MIN_APPARENT_PX, 'at most')}")
