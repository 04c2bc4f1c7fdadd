"""Plausibility bounds checked at estimate time, once the image's size is known: values that pass the
schema (fx > 0, distance > 0, finite) but cannot describe a real camera or scene are refused with a
422 that says what is wrong and the likely fix, instead of reaching the pipeline (fx = 1e15 or
cx = 1e300 made the coarse search fail with a 500).

=====================  ==========================  ===========================================
value                  plausible                   the usual mistake
=====================  ==========================  ===========================================
distance_mm, range     10 mm .. 20 m               metres (or micrometres) instead of mm
fx, fy                 50 .. 1,000,000 px          millimetres instead of pixels
cx, cy                 inside the image            intrinsics of another resolution
dist coefficients      |k| <= 1,000                not OpenCV's coefficients
roi                    covers a pixel of the image  another resolution's coordinates
plane                  10 mm .. 20 m away, in view  metres; a plane behind the camera
=====================  ==========================  ===========================================
"""

from __future__ import annotations

from service.errors import UnprocessableError
from service.schemas import Camera, Options

DISTANCE_MM = (10.0, 20_000.0)
FOCAL_PX = (50.0, 1_000_000.0)
MAX_ABS_DISTORTION = 1_000.0


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

        if not roi_mask(poly, (h, w)).any():
            raise UnprocessableError(f"The options field roi covers no pixel of this {w} x {h} image: give a "
                                     f"region inside u 0 to {w - 1} and v 0 to {h - 1} (pixels, origin at "
                                     "the top left)")


def _plane(opts: Options, cam: Camera, w: int, h: int) -> None:
    """The plane is 10 mm .. 20 m from the camera and some pixel's viewing ray meets it in front."""
    import numpy as np

    from service.vision.estimate.plane import MIN_RAY_COS

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
