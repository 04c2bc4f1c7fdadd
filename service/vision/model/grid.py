"""The rotation grid of a template bank: which orientations ``R_tpl_obj`` get a template.

- Continuously symmetric part (axis detected or given): ``R_tpl_obj[n] = Rx(tilt_n) @ A`` with
  ``A = frames.R_align_axis_to_y(axis)``, tilt over ``tilt_range_deg`` at ``tilt_step_deg`` (tilt of
  the axis towards the camera); ``view_params_deg[n] = (tilt, 0)``.
- Otherwise: viewpoints on a Fibonacci sphere about ``view_step_deg`` apart; the camera looks at the
  object centre from direction ``d`` (object frame) with the object's +z (or +y when looking along
  z) pointing up in the image; ``view_params_deg[n] = (azimuth, elevation)`` of ``d``.

In both cases the rotation about the optical axis is NOT in the grid: it leaves the silhouette's
shape unchanged (the paper's Table III), so the matcher rotates the contour at match time.

``GRID_DEFAULTS`` also holds the bank's other build options (template view distance, render size,
border spacing, supersampling): ``merge_grid`` validates all of them in one place.
"""

from __future__ import annotations

import math

import numpy as np

from service.vision.geometry.frames import R_align_axis_to_y, Rx

GRID_DEFAULTS: dict = {
    # symmetric parts: tilt of the symmetry axis towards the camera, degrees
    "tilt_step_deg": 2.0,
    "tilt_range_deg": [-90.0, 90.0],
    # other parts: mean angular spacing of the viewpoints on the sphere, degrees
    "view_step_deg": 10.0,
    # template view: distance of the model's centre from the camera, mm. The default is raised to
    # 2.5 x the model diameter for large models; an explicit value must exceed 1.2 x the diameter.
    "reference_distance_mm": 600.0,
    # template view: the model's diameter spans about this many pixels
    "render_px": 400,
    # spacing of border points along the contour, template-view pixels
    "spacing_px": 1.5,
    # silhouette supersampling for tracing the border (closed meshes then snap onto the exact edges)
    "supersample": 2,
}
_GRID_LIMITS = {  # key: (type, lo, hi)
    "tilt_step_deg": (float, 0.1, 90.0),
    "view_step_deg": (float, 1.0, 90.0),
    "reference_distance_mm": (float, 1.0, 1e6),
    "render_px": (int, 32, 2000),
    "spacing_px": (float, 0.25, 20.0),
    "supersample": (int, 1, 8),
}
MAX_VIEWS = 20_000  # a grid asking for more views than this is refused


def merge_grid(grid: dict | None) -> dict:
    """Defaults overridden by ``grid``, validated; raises ``ValueError`` with one sentence."""
    grid = dict(grid or {})
    unknown = sorted(set(grid) - set(GRID_DEFAULTS))
    if unknown:
        raise ValueError(f"unknown template grid option(s) {', '.join(map(repr, unknown))}; "
                         f"known: {', '.join(sorted(GRID_DEFAULTS))}.")
    out = dict(GRID_DEFAULTS)
    out["tilt_range_deg"] = list(GRID_DEFAULTS["tilt_range_deg"])
    for key, value in grid.items():
        if key == "tilt_range_deg":
            ok = isinstance(value, list | tuple) and len(value) == 2 and all(
                isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x) for x in value)
            if not ok or not (-180.0 <= value[0] <= value[1] <= 180.0):
                raise ValueError("tilt_range_deg must be two numbers [lo, hi] with -180 <= lo <= hi <= 180.")
            out[key] = [float(value[0]), float(value[1])]
            continue
        typ, lo, hi = _GRID_LIMITS[key]
        bad_type = isinstance(value, bool) or not isinstance(value, int | float) or (
            typ is int and not float(value).is_integer())
        if bad_type or not math.isfinite(value) or not (lo <= value <= hi):
            kind = "an integer" if typ is int else "a number"
            raise ValueError(f"{key} must be {kind} between {lo:g} and {hi:g}.")
        out[key] = typ(value)
    return out


def count_views(g: dict, symmetric: bool) -> int:
    if symmetric:
        lo, hi = g["tilt_range_deg"]
        return int(math.floor((hi - lo) / g["tilt_step_deg"] + 1e-9)) + 1
    step = math.radians(g["view_step_deg"])
    return max(int(round(4.0 * math.pi / step**2)), 1)


def tilt_values_deg(g: dict) -> np.ndarray:
    lo, hi = g["tilt_range_deg"]
    return lo + g["tilt_step_deg"] * np.arange(count_views(g, True))


def fibonacci_directions(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly on the sphere (Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def look_from_R(d_obj: np.ndarray) -> np.ndarray:
    """``R_cam_obj`` of a camera looking at the origin from direction ``d_obj`` (unit, object frame).

    The camera's z axis is ``-d``; the object's +z (or +y when ``d`` is within ~8 deg of the z axis)
    points up in the image (camera -y).
    """
    d = np.asarray(d_obj, float) / np.linalg.norm(d_obj)
    z_c = -d
    up = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    y_c = -(up - (up @ z_c) * z_c)
    y_c /= np.linalg.norm(y_c)
    x_c = np.cross(y_c, z_c)
    return np.stack([x_c, y_c, z_c])


def grid_rotations(g: dict, axis_obj: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3, 3) ``R_tpl_obj`` and (N, 2) ``view_params_deg`` of the grid (see the module docstring)."""
    if axis_obj is not None:
        A = R_align_axis_to_y(axis_obj)
        tilts = tilt_values_deg(g)
        R = np.stack([Rx(t) @ A for t in tilts])
        return R, np.stack([tilts, np.zeros_like(tilts)], axis=1)
    d = fibonacci_directions(count_views(g, False))
    R = np.stack([look_from_R(x) for x in d])
    az = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
    el = np.degrees(np.arcsin(np.clip(d[:, 2], -1.0, 1.0)))
    return R, np.stack([az, el], axis=1)
