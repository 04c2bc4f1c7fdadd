"""Borderline templates (the paper's section II.A): rotation grid, silhouette borders, the bank.

A template is the model seen from one orientation ``R_tpl_obj`` with its reference point
``centre_obj`` on the optical axis at ``reference_distance_mm`` (the *canonical view*), and its
borderline: the OUTER contour of the projected silhouette, resampled at about ``spacing_px``, each
point carrying

- ``xy_n``: normalised image coordinates ``((u - cx) / f, (v - cy) / f)`` of the canonical camera,
- ``theta_rad``: the undirected edge orientation in the image, [0, pi),
- ``p_obj``: the model point it came from (the paper's eq. 7), mm, object frame; projecting it with
  the template pose gives back ``xy_n`` (to float precision).

The border is traced on a supersampled silhouette (``cv2.findContours``, external contours only),
moved out by half a sub-pixel (the traced chain runs through the centres of the outermost covered
sub-pixels, the true edge lies half a sub-pixel further out), smoothed along the chain and resampled
by arc length. For a closed mesh (watertight, outward normals) each traced point is then snapped
onto the nearest projected contour-generator edge (an edge between a front and a back face): the
point, its orientation and its 3D point (on that edge, perspective-correct) are then exact, whatever
the supersampling. Otherwise ``p_obj`` is the point on the viewing ray at the depth of the nearest
covered sub-pixel. This replaces the paper's scan-line node procedure (kept, for reference and
tests, in ``scanline.py``), with the same border on the paper's cases.

Grid
----
- Continuously symmetric part (axis detected or given): ``R_tpl_obj[n] = Rx(tilt_n) @ A`` with
  ``A = frames.R_align_axis_to_y(axis)``, tilt over ``tilt_range_deg`` at ``tilt_step_deg`` (tilt of
  the axis towards the camera); ``view_params_deg[n] = (tilt, 0)``.
- Otherwise: viewpoints on a Fibonacci sphere about ``view_step_deg`` apart; the camera looks at the
  object centre from direction ``d`` (object frame) with the object's +z (or +y when looking along
  z) pointing up in the image; ``view_params_deg[n] = (azimuth, elevation)`` of ``d``.

In both cases the rotation about the optical axis is NOT in the grid: it leaves the silhouette's
shape unchanged (the paper's Table III), so the matcher rotates the contour at match time.
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np
import trimesh
from scipy.ndimage import gaussian_filter1d

from service.vision.bank import TemplateBank
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, R_align_axis_to_y, Rx
from service.vision.memo import Memo
from service.vision.geometry.render import as_intrinsics, rasterise_roi

GRID_DEFAULTS: dict = {
    # symmetric parts: tilt of the symmetry axis towards the camera, degrees
    "tilt_step_deg": 2.0,
    "tilt_range_deg": [-90.0, 90.0],
    # other parts: mean angular spacing of the viewpoints on the sphere, degrees
    "view_step_deg": 10.0,
    # canonical view: distance of the model's centre from the camera, mm. The default is raised to
    # 2.5 x the model diameter for large models; an explicit value must exceed 1.2 x the diameter.
    "reference_distance_mm": 600.0,
    # canonical view: the model's diameter spans about this many pixels
    "render_px": 400,
    # spacing of border points along the contour, canonical pixels
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
AUTO_DISTANCE_DIAMETERS = 2.5  # the default reference distance is at least this many diameters
MIN_DISTANCE_DIAMETERS = 1.2  # an explicit reference distance must be at least this many diameters
MIN_BLOB_AREA_FRACTION = 0.05  # external contours smaller than this fraction of the largest are dropped
SMOOTH_SIGMA_PX = 0.5  # Gaussian smoothing of the traced chain along its length, output pixels
SYMMETRY_CHOICES = ("auto", "none", "x", "y", "z")


# --- grid ---------------------------------------------------------------------------------------


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


def _n_views(g: dict, symmetric: bool) -> int:
    if symmetric:
        lo, hi = g["tilt_range_deg"]
        return int(math.floor((hi - lo) / g["tilt_step_deg"] + 1e-9)) + 1
    step = math.radians(g["view_step_deg"])
    return max(int(round(4.0 * math.pi / step**2)), 1)


def tilt_values_deg(g: dict) -> np.ndarray:
    lo, hi = g["tilt_range_deg"]
    return lo + g["tilt_step_deg"] * np.arange(_n_views(g, True))


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
    d = fibonacci_directions(_n_views(g, False))
    R = np.stack([look_from_R(x) for x in d])
    az = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
    el = np.degrees(np.arcsin(np.clip(d[:, 2], -1.0, 1.0)))
    return R, np.stack([az, el], axis=1)


# --- border extraction --------------------------------------------------------------------------


def _resample_closed(pts: np.ndarray, spacing: float) -> np.ndarray:
    """Closed polyline (n, 2) -> points every ``spacing`` along its length (at least 8)."""
    seg = np.linalg.norm(np.diff(pts, axis=0, append=pts[:1]), axis=1)
    total = float(seg.sum())
    if total <= 0.0:
        return pts[:1]
    m = max(int(round(total / spacing)), 8)
    s_knots = np.concatenate([[0.0], np.cumsum(seg)])
    closed = np.vstack([pts, pts[:1]])
    s = np.arange(m) * (total / m)
    return np.stack([np.interp(s, s_knots, closed[:, 0]), np.interp(s, s_knots, closed[:, 1])], axis=1)


def _contours_ss(mask: np.ndarray) -> list[np.ndarray]:
    """External contours (float64 (n, 2) uv in the mask's pixels) of the kept blobs."""
    cs, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not cs:
        return []
    areas = np.array([cv2.contourArea(c) + len(c) for c in cs], float)  # + len: lines have area 0
    keep = areas >= MIN_BLOB_AREA_FRACTION * areas.max()
    return [c.reshape(-1, 2).astype(np.float64) for c, k in zip(cs, keep, strict=True) if k and len(c) >= 3]


def extract_border(invz_ss: np.ndarray, fid_ss: np.ndarray, origin_ss: tuple[int, int], s: int,
                   intr: Intrinsics, pose: Pose, image_size, spacing_px: float,
                   sil_edges_cam: np.ndarray | None = None):
    """Border of a rasterised silhouette (see ``rasterise_roi``) in the image of ``intr``.

    invz_ss, fid_ss : the ROI buffers (inverse depth, face id) at s times the resolution
    (``intr.scaled(s)``), whose top-left sub-pixel is ``origin_ss`` of the supersampled image.
    Returns ``uv (M, 2)``, ``theta_rad (M,)``, ``p_obj (M, 3)`` (float64; pixels of ``intr``,
    radians, mm object frame). Points on the image frame (where the silhouette is cut by the image
    border) are dropped. With ``sil_edges_cam`` ((S, 2, 3) mm, camera frame: the mesh's contour
    generator edges, see ``MeshTopology``), each point is then moved onto the nearest projected edge
    (``snap_to_edges``): exact sub-pixel position and orientation, and a 3D point on the mesh.
    """
    empty = np.zeros((0, 2)), np.zeros(0), np.zeros((0, 3))
    if fid_ss.size == 0:
        return empty
    mask = fid_ss >= 0
    if not mask.any():
        return empty
    mask_p = np.pad(mask, 1)
    sigma = SMOOTH_SIGMA_PX * s
    uvs, thetas = [], []
    for c in _contours_ss(mask_p):
        c = c - 1.0  # undo the padding: ROI sub-pixel coords
        if len(c) >= 5:
            c = gaussian_filter1d(c, sigma, axis=0, mode="wrap")
        # Outward by half a sub-pixel along the normal.
        t = np.roll(c, -1, axis=0) - np.roll(c, 1, axis=0)
        tn = t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
        area2 = float(np.sum(c[:, 0] * np.roll(c[:, 1], -1) - np.roll(c[:, 0], -1) * c[:, 1]))
        sign = 1.0 if area2 > 0 else -1.0
        normal = sign * np.stack([tn[:, 1], -tn[:, 0]], axis=1)
        c = c + 0.5 * normal
        # ROI sub-pixels -> image pixels, then resample by arc length in image pixels.
        uv = (c + np.asarray(origin_ss, float) + 0.5) / s - 0.5
        uv = _resample_closed(uv, spacing_px)
        if len(uv) < 3:
            continue
        d = np.roll(uv, -1, axis=0) - np.roll(uv, 1, axis=0)
        thetas.append(np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi))
        uvs.append(uv)
    if not uvs:
        return empty
    uv = np.concatenate(uvs)
    theta = np.concatenate(thetas)
    w, h = int(image_size[0]), int(image_size[1])
    on_frame = (uv[:, 0] < 0.0) | (uv[:, 1] < 0.0) | (uv[:, 0] > w - 1.0) | (uv[:, 1] > h - 1.0)
    touches = (origin_ss[0] == 0 or origin_ss[1] == 0 or origin_ss[0] + mask.shape[1] >= w * s
               or origin_ss[1] + mask.shape[0] >= h * s)
    if touches:
        near = ((uv[:, 0] < 0.5) | (uv[:, 1] < 0.5) | (uv[:, 0] > w - 1.5) | (uv[:, 1] > h - 1.5))
        on_frame |= near
    uv, theta = uv[~on_frame], theta[~on_frame]
    # Depth of the nearest covered sub-pixel (5 x 5 window), then back along the ray (eq. 7).
    q = (uv + 0.5) * s - 0.5 - np.asarray(origin_ss, float)  # ROI sub-pixel coords
    base = np.rint(q).astype(np.int64)
    off = np.stack(np.meshgrid(np.arange(-2, 3), np.arange(-2, 3), indexing="xy"), axis=-1).reshape(-1, 2)
    cand = base[:, None, :] + off[None, :, :]  # (M, 25, 2) as (i, j) = (col, row)
    hh, ww = mask.shape
    inb = (cand[..., 0] >= 0) & (cand[..., 0] < ww) & (cand[..., 1] >= 0) & (cand[..., 1] < hh)
    ci = np.clip(cand[..., 0], 0, ww - 1)
    cj = np.clip(cand[..., 1], 0, hh - 1)
    covered = inb & mask[cj, ci]
    dist2 = ((cand - q[:, None, :]) ** 2).sum(axis=2)
    dist2 = np.where(covered, dist2, np.inf)
    best = np.argmin(dist2, axis=1)
    ok = np.isfinite(dist2[np.arange(len(q)), best])
    z = 1.0 / invz_ss[cj[np.arange(len(q)), best], ci[np.arange(len(q)), best]].astype(np.float64)
    uv, theta, z = uv[ok], theta[ok], z[ok]
    x = (uv[:, 0] - intr.cx) / intr.fx * z
    y = (uv[:, 1] - intr.cy) / intr.fy * z
    p_cam = np.stack([x, y, z], axis=1)
    if sil_edges_cam is not None and len(sil_edges_cam):
        uv, theta, p_cam = snap_to_edges(uv, theta, p_cam, sil_edges_cam, intr)
    p_obj = (p_cam - pose.t_mm) @ pose.R
    return uv, theta, p_obj


SNAP_MAX_PX = 0.75  # a border point further than this from every contour-generator edge is kept as traced
SNAP_MAX_DEPTH_FRACTION = 0.05  # ... and so is one whose edge point is this much (of z) off the z-buffer
SNAP_SAMPLE_PX = 2.0  # edges are sampled this often to find the candidates (the 6 nearest samples' edges)


def snap_to_edges(uv: np.ndarray, theta: np.ndarray, p_cam: np.ndarray, edges_cam: np.ndarray,
                  intr: Intrinsics):
    """Move traced border points onto the nearest projected contour-generator edge.

    uv (M, 2), theta (M,), p_cam (M, 3) as traced (p_cam's depth from the z-buffer); edges_cam
    (S, 2, 3) mm, camera frame. A point within ``SNAP_MAX_PX`` of an edge's projection takes the
    closest point of that projection, the edge's image direction, and the 3D point of the edge that
    projects there (perspective-correct), unless that point's depth disagrees with the z-buffer's by
    more than ``SNAP_MAX_DEPTH_FRACTION`` (an occluded edge). Returns new (uv, theta, p_cam).
    """
    from scipy.spatial import cKDTree

    P0, P1 = edges_cam[:, 0], edges_cam[:, 1]
    ok_z = (P0[:, 2] > 1e-3) & (P1[:, 2] > 1e-3)
    P0, P1 = P0[ok_z], P1[ok_z]
    if len(P0) == 0 or len(uv) == 0:
        return uv, theta, p_cam
    a = np.stack([intr.fx * P0[:, 0] / P0[:, 2] + intr.cx, intr.fy * P0[:, 1] / P0[:, 2] + intr.cy], axis=1)
    b = np.stack([intr.fx * P1[:, 0] / P1[:, 2] + intr.cx, intr.fy * P1[:, 1] / P1[:, 2] + intr.cy], axis=1)
    # Keep only edges near the border's bounding box, then sample them for the candidate search.
    lo, hi = uv.min(axis=0) - 2.0, uv.max(axis=0) + 2.0
    near = ~((np.maximum(a, b) < lo).any(axis=1) | (np.minimum(a, b) > hi).any(axis=1))
    a, b, P0, P1 = a[near], b[near], P0[near], P1[near]
    if len(a) == 0:
        return uv, theta, p_cam
    length = np.linalg.norm(b - a, axis=1)
    n = np.minimum(np.ceil(length / SNAP_SAMPLE_PX).astype(np.int64), 4096) + 1
    seg = np.repeat(np.arange(len(a)), n)
    start = np.repeat(np.cumsum(n) - n, n)
    t = (np.arange(len(seg)) - start) / np.maximum(n[seg] - 1, 1)
    samples = a[seg] + t[:, None] * (b - a)[seg]
    k = min(6, len(samples))
    _, idx = cKDTree(samples, balanced_tree=False, compact_nodes=False).query(uv, k=k)
    cand = seg[np.asarray(idx).reshape(len(uv), k)]  # (M, k) segment ids
    ab = (b - a)[cand]  # (M, k, 2)
    den = np.maximum((ab**2).sum(axis=2), 1e-18)
    tt = np.clip(((uv[:, None, :] - a[cand]) * ab).sum(axis=2) / den, 0.0, 1.0)
    q = a[cand] + tt[..., None] * ab
    d = np.linalg.norm(q - uv[:, None, :], axis=2)
    j = np.argmin(d, axis=1)
    rows = np.arange(len(uv))
    dmin, best, tb = d[rows, j], cand[rows, j], tt[rows, j]
    z0, z1 = P0[best, 2], P1[best, 2]
    lam = tb * z0 / np.maximum((1.0 - tb) * z1 + tb * z0, 1e-12)
    p_snap = P0[best] + lam[:, None] * (P1[best] - P0[best])
    depth_ok = np.abs(p_snap[:, 2] - p_cam[:, 2]) <= SNAP_MAX_DEPTH_FRACTION * p_cam[:, 2]
    use = (dmin <= SNAP_MAX_PX) & depth_ok & (np.linalg.norm(b[best] - a[best], axis=1) > 1e-9)
    uv = uv.copy()
    theta = theta.copy()
    p_cam = p_cam.copy()
    # uv from the 3D point (consistent to float precision with its projection)
    ps = p_snap[use]
    uv[use] = np.stack([intr.fx * ps[:, 0] / ps[:, 2] + intr.cx, intr.fy * ps[:, 1] / ps[:, 2] + intr.cy],
                       axis=1)
    dirs = (b - a)[best[use]]
    theta[use] = np.mod(np.arctan2(dirs[:, 1], dirs[:, 0]), np.pi)
    p_cam[use] = ps
    return uv, theta, p_cam


def border_at_pose(vertices_mm, faces, pose: Pose, intr_or_K, image_size, *, spacing_px: float = 1.0,
                   supersample: int = 2, snap: bool = True):
    """Outer silhouette border of the mesh at ``pose`` (T_cam_obj) in a real (pinhole) camera.

    Returns ``uv (M, 2)`` pixels, ``theta_rad (M,)`` in [0, pi), ``p_obj (M, 3)`` mm object frame,
    all float64; empty arrays when nothing is visible. Only the ROI of the projected mesh is
    rasterised. Lens distortion is ignored (``intr_or_K``'s pinhole part is used). For a closed mesh
    (``MeshTopology``, cached per mesh) back faces are skipped and, with ``snap``, the traced points
    are moved onto the projected contour-generator edges (``snap_to_edges``).
    """
    intr = as_intrinsics(intr_or_K)
    s = int(supersample)
    w, h = int(image_size[0]), int(image_size[1])
    intr_s = intr.scaled(s) if s > 1 else intr
    topo = mesh_topology(vertices_mm, faces)
    front = topo.front_facing(pose) if topo.closed else None
    F = topo.faces if front is None else topo.faces[front]
    invz, fid, origin = rasterise_roi(topo.vertices, F, pose, intr_s, (w * s, h * s), inverse_depth=True)
    edges = topo.contour_edges_cam(pose, front) if (snap and front is not None) else None
    return extract_border(invz, fid, origin, s, intr, pose, (w, h), spacing_px, edges)


@dataclass(frozen=True)
class MeshTopology:
    """What border extraction needs about a mesh besides its triangles (built once per mesh).

    closed: watertight, consistently wound, outward normals (``is_closed_outward``); only then are
    back faces culled and contour generators defined. edges (E, 2): each undirected edge once;
    edge_faces (E, 2): its two faces (closed meshes only).
    """

    vertices: np.ndarray  # (V, 3) float64, mm
    faces: np.ndarray  # (F, 3) int32
    closed: bool
    face_normals: np.ndarray  # (F, 3) float64, unnormalised (right-hand rule)
    edges: np.ndarray  # (E, 2) int64
    edge_faces: np.ndarray  # (E, 2) int64

    def front_facing(self, pose: Pose) -> np.ndarray:
        """(F,) bool: faces whose outward normal points towards the camera."""
        cam_obj = -np.asarray(pose.R, float).T @ np.asarray(pose.t_mm, float)
        v0 = self.vertices[self.faces[:, 0]]
        return np.einsum("ij,ij->i", self.face_normals, cam_obj - v0) > 0.0

    def contour_edges_cam(self, pose: Pose, front: np.ndarray) -> np.ndarray:
        """(S, 2, 3) mm, camera frame: edges between a front and a back face (contour generators)."""
        sel = front[self.edge_faces[:, 0]] != front[self.edge_faces[:, 1]]
        e = self.edges[sel]
        p = self.vertices[e.reshape(-1)] @ np.asarray(pose.R, float).T + np.asarray(pose.t_mm, float)
        return p.reshape(-1, 2, 3)


def _build_topology(V: np.ndarray, F: np.ndarray) -> MeshTopology:
    tri = V[F]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    closed = is_closed_outward(V, F)
    edges = np.zeros((0, 2), np.int64)
    edge_faces = np.zeros((0, 2), np.int64)
    if closed:
        d = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]).astype(np.int64)
        face_of = np.tile(np.arange(len(F)), 3)
        key = np.sort(d, axis=1)
        order = np.lexsort((key[:, 1], key[:, 0]))
        # Closed: every undirected edge occurs exactly twice, so sorted pairs are adjacent.
        first, second = order[0::2], order[1::2]
        edges = key[first]
        edge_faces = np.stack([face_of[first], face_of[second]], axis=1)
    return MeshTopology(V, F, closed, normals, edges, edge_faces)


_TOPOLOGY_BY_ARRAY = Memo(8)
_TOPOLOGY_BY_CONTENT = Memo(8)
_CONTENT = object()  # owner of the content-keyed entries: their key (a digest) says everything


def mesh_topology(vertices_mm, faces) -> MeshTopology:
    """``MeshTopology`` of the mesh, cached by content (a few recent meshes); the same array objects
    (a bank's, on every refinement step) skip even the content hash (~1 ms for a 16 k-face mesh)."""
    faces_seen, topo = _TOPOLOGY_BY_ARRAY.get(vertices_mm, id(faces),
                                              lambda: (faces, _topology_by_content(vertices_mm, faces)))
    return topo if faces_seen is faces else _topology_by_content(vertices_mm, faces)


def _topology_by_content(vertices_mm, faces) -> MeshTopology:
    V = np.ascontiguousarray(vertices_mm, np.float64)
    F = np.ascontiguousarray(faces, np.int32)
    key = hashlib.blake2b(V.tobytes() + b"|" + F.tobytes(), digest_size=16).digest()
    return _TOPOLOGY_BY_CONTENT.get(_CONTENT, key, lambda: _build_topology(V, F))


def is_closed_outward(vertices_mm, faces) -> bool:
    """True when every edge is shared by exactly two faces traversing it in opposite directions
    and the enclosed volume is positive (normals point out): back faces can then be skipped."""
    F = np.asarray(faces, np.int64)
    if len(F) == 0:
        return False
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    n = int(F.max()) + 1
    fwd = e[:, 0] * n + e[:, 1]
    rev = e[:, 1] * n + e[:, 0]
    if len(np.unique(fwd)) != len(fwd):  # an edge used twice in the same direction
        return False
    if not np.array_equal(np.sort(fwd), np.sort(rev)):  # an edge without its opposite
        return False
    tri = np.asarray(vertices_mm, float)[F]
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0
    return bool(volume > 0.0)


# --- the bank -----------------------------------------------------------------------------------


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
        from service.vision.build.symmetry import detect_symmetry

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
        the bounding-box centre.
    """
    explicit_distance = grid is not None and "reference_distance_mm" in grid
    g = merge_grid(grid)
    V = np.asarray(mesh.vertices, np.float64)
    F = np.asarray(mesh.faces, np.int32)
    if len(V) < 3 or len(F) < 1:
        raise ValueError("the mesh has no triangles.")
    axis, point = _resolve_symmetry(mesh, symmetry)
    n_views = _n_views(g, axis is not None)
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
    workers = max(1, min(2, os.cpu_count() or 1))
    done = 0
    with ThreadPoolExecutor(max_workers=workers) as ex:
        futs = {ex.submit(one, R): k for k, R in enumerate(R_all)}
        from concurrent.futures import as_completed

        for fut in as_completed(futs):
            results[futs[fut]] = fut.result()
            done += 1
            if progress is not None:
                progress(done / len(R_all))
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
    )


def canvas_px(vertices_mm: np.ndarray, centre_obj: np.ndarray, d_ref: float, f: float, render_px: int) -> int:
    """Width = height of the canonical image: about 1.4 x ``render_px``, and large enough for the
    model in any orientation (the cone tangent to its bounding sphere about ``centre_obj``)."""
    r_b = float(np.linalg.norm(np.asarray(vertices_mm, float) - centre_obj, axis=1).max())
    half = f * r_b / math.sqrt(max(d_ref**2 - r_b**2, 1e-9)) + 4.0
    return int(max(math.ceil(1.4 * render_px), 2 * math.ceil(half) + 1))


def canonical_pose(bank: TemplateBank, k: int) -> Pose:
    """``T_cam_obj`` of template k's canonical view."""
    R = np.asarray(bank.R_tpl_obj[k], float)
    return Pose(R, np.array([0.0, 0.0, bank.reference_distance_mm]) - R @ np.asarray(bank.centre_obj, float))


def canonical_intrinsics(bank: TemplateBank) -> tuple[Intrinsics, tuple[int, int]]:
    """The canonical camera of the bank and its image size (w, h)."""
    g = bank.grid
    f = g["render_px"] * bank.reference_distance_mm / bank.diameter_mm
    size = canvas_px(np.asarray(bank.vertices_mm, float), np.asarray(bank.centre_obj, float),
                     bank.reference_distance_mm, f, g["render_px"])
    c = (size - 1) / 2.0
    return Intrinsics(f, f, c, c), (size, size)


# --- pictures -----------------------------------------------------------------------------------


def draw_template(bank: TemplateBank, k: int) -> np.ndarray:
    """(H, W, 3) uint8 BGR picture of template ``k``, laid out as the paper's Tables I-III.

    Left: the projected (Lambert-shaded) mesh in the canonical view; right: its extracted borderline,
    points joined along each contour and coloured by edge orientation (hue = theta over [0, pi)).
    A caption line above gives the view parameters and the number of points.
    """
    from service.vision.geometry.render import render_shaded

    if not 0 <= k < bank.n_templates:
        raise IndexError(f"template {k} out of range 0..{bank.n_templates - 1}.")
    intr, (w, h) = canonical_intrinsics(bank)
    pose = canonical_pose(bank, k)
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
