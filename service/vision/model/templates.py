"""Borderline templates (the paper's section II.A): the bank of a mesh.

A template is the model seen from one orientation ``R_tpl_obj`` of the grid (``grid.py``) with its
reference point ``centre_obj`` on the optical axis at ``reference_distance_mm`` (the *template view*),
and its borderline (``geometry/silhouette.py``): the OUTER contour of the projected silhouette,
resampled at about ``spacing_px``, each point carrying

- ``xy_n``: normalised image coordinates ``((u - cx) / f, (v - cy) / f)`` of the template camera,
- ``theta_rad``: the undirected edge orientation in the image, [0, pi),
- ``p_obj``: the model point it came from (the paper's eq. 7), mm, object frame; projecting it with
  the template pose gives back ``xy_n`` (to float precision).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
import trimesh

from service.vision import threads
from service.vision.bank import TemplateBank
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose
from service.vision.geometry.render import rasterise_roi
from service.vision.geometry.silhouette import extract_border, mesh_topology
from service.vision.model.grid import MAX_VIEWS, count_views, grid_rotations, merge_grid

AUTO_DISTANCE_DIAMETERS = 2.5  # the default reference distance is at least this many diameters
MIN_DISTANCE_DIAMETERS = 1.2  # an explicit reference distance must be at least this many diameters
SYMMETRY_CHOICES = ("auto", "none", "x", "y", "z")


def model_diameter_mm(vertices_mm: np.ndarray) -> float:
    """Largest distance between two vertices, mm (over the convex hull's vertices)."""
    from scipy.spatial import ConvexHull
    from scipy.spatial.distance import pdist

    v = np.asarray(vertices_mm, float)
    with contextlib.suppress(Exception):  # flat or degenerate: keep all vertices
        v = v[ConvexHull(v).vertices]
    if len(v) < 2:
        return 0.0
    if len(v) <= 3000:
        return float(pdist(v).max())
    best = 0.0
    for i in range(0, len(v), 1000):
        d = np.linalg.norm(v[i:i + 1000, None, :] - v[None, :, :], axis=2)
        best = max(best, float(d.max()))
    return best


def _resolve_symmetry(mesh: trimesh.Trimesh, symmetry: str):
    if symmetry not in SYMMETRY_CHOICES:
        raise ValueError(f"symmetry must be one of {', '.join(SYMMETRY_CHOICES)}.")
    if symmetry == "none":
        return None, None
    if symmetry == "auto":
        from service.vision.model.symmetry import detect_symmetry

        found = detect_symmetry(mesh)
        return (None, None) if found is None else found
    axis = np.eye(3)[" xyz".index(symmetry) - 1]
    return axis, np.asarray(mesh.bounds, float).mean(axis=0)


def build_bank(mesh: trimesh.Trimesh, *, symmetry: str = "auto", grid: dict | None = None,
               progress: Callable[[float], None] | None = None) -> TemplateBank:
    """Mesh (mm, object frame) -> ``TemplateBank`` (see the module docstring for the grid).

    symmetry : "auto" (detect a continuous rotational symmetry axis), "none", or the model axis
        "x" | "y" | "z" (through the bounding-box centre). grid : overrides of ``GRID_DEFAULTS``;
        unknown keys or bad values raise ``ValueError``. progress : called with the fraction of
        views done (0..1). ``diameter_mm`` is the largest vertex-to-vertex distance; ``centre_obj``
        the bounding-box centre. The part's stable resting poses (``stable.py``) come with it.
    """
    explicit_distance = grid is not None and "reference_distance_mm" in grid
    g = merge_grid(grid)
    V = np.asarray(mesh.vertices, np.float64)
    F = np.asarray(mesh.faces, np.int32)
    if len(V) < 3 or len(F) < 1:
        raise ValueError("the mesh has no triangles.")
    axis, point = _resolve_symmetry(mesh, symmetry)
    n_views = count_views(g, axis is not None)
    if n_views > MAX_VIEWS:
        raise ValueError(f"the template grid asks for {n_views} views, more than the limit of {MAX_VIEWS}.")
    lo_b, hi_b = np.asarray(mesh.bounds, float)
    centre = (lo_b + hi_b) / 2.0
    extents = hi_b - lo_b
    diameter = model_diameter_mm(V)
    if diameter <= 0.0:
        raise ValueError("the mesh has zero size.")
    d_ref = g["reference_distance_mm"]
    if explicit_distance:
        if d_ref < MIN_DISTANCE_DIAMETERS * diameter:
            raise ValueError(f"reference_distance_mm must be at least {MIN_DISTANCE_DIAMETERS:g} x the model "
                             f"diameter ({diameter:.1f} mm).")
    else:
        d_ref = max(d_ref, AUTO_DISTANCE_DIAMETERS * diameter)
    g["reference_distance_mm"] = float(d_ref)
    f = g["render_px"] * d_ref / diameter
    size = canvas_px(V.astype(np.float32).astype(np.float64), centre, d_ref, f, g["render_px"])  # as stored
    c = (size - 1) / 2.0
    intr = Intrinsics(f, f, c, c)
    s = g["supersample"]
    intr_s = intr.scaled(s) if s > 1 else intr
    R_all, params = grid_rotations(g, axis)
    topo = mesh_topology(V, F)

    def one(R: np.ndarray):
        pose = Pose(R, np.array([0.0, 0.0, d_ref]) - R @ centre)
        front = topo.front_facing(pose) if topo.closed else None
        Fv = F if front is None else F[front]
        invz, fid, origin = rasterise_roi(V, Fv, pose, intr_s, (size * s, size * s), inverse_depth=True)
        edges = None if front is None else topo.contour_edges_cam(pose, front)
        uv, theta, p_obj = extract_border(invz, fid, origin, s, intr, pose, (size, size), g["spacing_px"],
                                          edges)
        xy = (uv - c) / f
        theta32 = theta.astype(np.float32)
        theta32[theta32 >= np.float32(np.pi)] = 0.0  # pi rounds up in float32; [0, pi) is undirected
        return xy.astype(np.float32), theta32, p_obj.astype(np.float32)

    results: list = [None] * len(R_all)
    done = 0
    with ThreadPoolExecutor(max_workers=threads.budget()) as ex:  # not the shared pool: it ends here
        futs = {ex.submit(one, R): k for k, R in enumerate(R_all)}
        from concurrent.futures import as_completed

        for fut in as_completed(futs):
            results[futs[fut]] = fut.result()
            done += 1
            if progress is not None:
                progress(done / len(R_all))
    from service.vision.model.mirror import mirror_planes
    from service.vision.model.stable import stable_poses

    stable = stable_poses(mesh, axis_obj=axis, diameter_mm=diameter)
    mirrors = mirror_planes(mesh, axis_obj=axis)
    counts = np.array([len(r[0]) for r in results], np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return TemplateBank(
        R_tpl_obj=R_all.astype(np.float64),
        view_params_deg=params.astype(np.float64),
        offsets=offsets,
        xy_n=np.concatenate([r[0] for r in results]).reshape(-1, 2),
        theta_rad=np.concatenate([r[1] for r in results]),
        p_obj=np.concatenate([r[2] for r in results]).reshape(-1, 3),
        centre_obj=centre,
        reference_distance_mm=float(d_ref),
        vertices_mm=V.astype(np.float32),
        faces=F,
        extents_mm=extents,
        diameter_mm=float(diameter),
        symmetry_axis_obj=None if axis is None else np.asarray(axis, float),
        symmetry_point_obj=None if point is None else np.asarray(point, float),
        grid=g,
        R_rest_obj=stable.R_rest_obj,
        rest_probability=stable.probability,
        mirror_normals_obj=mirrors.normals_obj,
        mirror_point_obj=mirrors.point_obj,
    )


def canvas_px(vertices_mm: np.ndarray, centre_obj: np.ndarray, d_ref: float, f: float, render_px: int) -> int:
    """Width = height of the template view's image: about 1.4 x ``render_px``, and large enough for the
    model in any orientation (the cone tangent to its bounding sphere about ``centre_obj``)."""
    r_b = float(np.linalg.norm(np.asarray(vertices_mm, float) - centre_obj, axis=1).max())
    half = f * r_b / math.sqrt(max(d_ref**2 - r_b**2, 1e-9)) + 4.0
    return int(max(math.ceil(1.4 * render_px), 2 * math.ceil(half) + 1))


def template_pose(bank: TemplateBank, k: int) -> Pose:
    """``T_cam_obj`` of template k's view."""
    R = np.asarray(bank.R_tpl_obj[k], float)
    return Pose(R, np.array([0.0, 0.0, bank.reference_distance_mm]) - R @ np.asarray(bank.centre_obj, float))


def template_camera(bank: TemplateBank) -> tuple[Intrinsics, tuple[int, int]]:
    """The camera the bank's templates were seen with, and its image size (w, h)."""
    g = bank.grid
    f = g["render_px"] * bank.reference_distance_mm / bank.diameter_mm
    size = canvas_px(np.asarray(bank.vertices_mm, float), np.asarray(bank.centre_obj, float),
                     bank.reference_distance_mm, f, g["render_px"])
    c = (size - 1) / 2.0
    return Intrinsics(f, f, c, c), (size, size)


# --- pictures -----------------------------------------------------------------------------------


def draw_template(bank: TemplateBank, k: int) -> np.ndarray:
    """(H, W, 3) uint8 BGR picture of template ``k``, laid out as the paper's Tables I-III.

    Left: the projected (Lambert-shaded) mesh in the template view; right: its extracted borderline,
    points joined along each contour and coloured by edge orientation (hue = theta over [0, pi)).
    A caption line above gives the view parameters and the number of points.
    """
    from service.vision.geometry.render import render_shaded

    if not 0 <= k < bank.n_templates:
        raise IndexError(f"template {k} out of range 0..{bank.n_templates - 1}.")
    intr, (w, h) = template_camera(bank)
    pose = template_pose(bank, k)
    left = render_shaded(np.asarray(bank.vertices_mm, float), np.asarray(bank.faces), pose, intr, (w, h),
                         background=40)
    left = cv2.cvtColor(left, cv2.COLOR_GRAY2BGR)
    right = np.full((h, w, 3), 20, np.uint8)
    sl = bank.points(k)
    xy = np.asarray(bank.xy_n[sl], float)
    uv = xy * [intr.fx, intr.fy] + [intr.cx, intr.cy]
    theta = np.asarray(bank.theta_rad[sl], float)
    hue = np.clip(theta / np.pi * 180.0, 0, 179).astype(np.uint8)
    colours = cv2.cvtColor(np.stack([hue, np.full_like(hue, 255), np.full_like(hue, 255)], axis=1)[None],
                           cv2.COLOR_HSV2BGR)[0]
    gap = 3.0 * float(bank.grid.get("spacing_px", 1.5))
    shift = 4
    pts = np.rint(uv * (1 << shift)).astype(np.int32)
    nxt = np.roll(np.arange(len(uv)), -1)
    for i in range(len(uv)):
        c = tuple(int(x) for x in colours[i])
        j = nxt[i]
        if np.linalg.norm(uv[j] - uv[i]) < gap:
            cv2.line(right, tuple(pts[i]), tuple(pts[j]), c, 1, cv2.LINE_AA, shift)
        else:
            cv2.circle(right, tuple(pts[i]), 1 << shift, c, -1, cv2.LINE_AA, shift)
    sep = np.full((h, 4, 3), 255, np.uint8)
    body = np.hstack([left, sep, right])
    a, b = bank.view_params_deg[k]
    view = (f"tilt {a:+.1f} deg" if bank.symmetry_axis_obj is not None
            else f"azimuth {a:+.1f} deg, elevation {b:+.1f} deg")
    caption = np.full((30, body.shape[1], 3), 255, np.uint8)
    cv2.putText(caption, f"template {k}: {view}, {sl.stop - sl.start} points", (8, 21),
                cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([caption, body])
