"""Photo-realistic piles of parts on a table, rendered with Blender (Cycles, CPU), with exact ground truth.

    python bench/blender_piles.py --out /work/gen/piles --n 60 --seed 0 [--models sprayer,lbracket,flange]
                                  [--samples 32] [--skip-existing] [--check 3 --check-dir /tmp/piles_check]

Writes ``OUT/images/NNNNNN.png`` (640 x 480, 8-bit RGB), ``OUT/scenes/NNNNNN.json`` (what Blender is
asked to render: world frame, mm), ``OUT/models/<model>.stl`` (the meshes, mm), ``OUT/gt.jsonl`` (one line
per copy, the format of ``../shared/data/sygrid_synth``) and ``OUT/meta.json``. Each scene json is
rendered by ``blender -b --factory-startup --python bench/blender_piles.py -- OUT/scenes/NNNNNN.json``:
this same file, run by Blender's Python, builds and renders the scene (only ``bpy`` there, no numpy).
Keep OUT outside the repository.

Scene model (image i is drawn from ``np.random.default_rng(seed + i)``; Cycles' seed is fixed per image,
so a set is reproducible and any one image can be rendered again alone):

- world: the table is the plane z = 0, z up; the camera's optical axis meets it at the origin;
- camera: 640 x 480, fx = fy in [550, 650], principal point (320, 240) (the centre of the top-left
  pixel is (0, 0)); 300-500 mm from the table along the optical axis, top-down (axis < 5 deg from
  the table normal) or oblique (20-35 deg), half each; any heading;
- one model per image, 3-6 copies, each resting on the table in one of the model's stable poses
  (``trimesh.poses.compute_stable_poses`` of the convex hull with the solid's centre of mass, drawn by
  probability), any spin about the normal, the whole copy inside the image; about 2/3 of the copies keep
  a gap of >= 15 mm to the others (footprints = convex hulls on the table), the others are put against a
  copy already placed (gap >= 1 mm, footprints never overlap); in about 1/3 of the images the last copy
  lies ON another one: a stable pose tilted 10-25 deg, over a copy, lowered vertically until it first
  touches a copy (exact meshes, subdivided; accepted only if it touches a copy before the table);
- appearance per image: the parts' material (all copies alike): metal (metallic 1, roughness
  0.15-0.4), white or coloured plastic (roughness 0.3-0.6) or dark plastic; the table plain or with a
  procedural texture (noise, wood, checker), random colours; one or two area lights and a world light.

Ground truth (``gt.jsonl``): ``R``, ``t_mm`` = T_cam_obj in the OpenCV camera frame (Blender's camera
looks down its -Z with +Y up: the OpenCV frame is it with Y and Z flipped), ``K``, ``plane`` (the table:
``n . p = d_mm`` in the camera frame, n towards the camera), ``visible_fraction`` = pixels where the
copy is the front-most of all copies / pixels of the copy rendered alone, both by the project's
rasteriser ``render`` at the pixel centres. The Blender camera reproduces ``K`` exactly (lens from fx,
sensor shift for the half-pixel between Blender's pixel-corner and our pixel-centre origin).

``--check N`` also renders, for the first N images, one flat-colour image per scene (emission only, one
colour per copy, one sample at each pixel's centre) into ``--check-dir`` and prints, per copy, the IoU
of Blender's visible mask with the rasteriser's, and the IoU of whole silhouettes for copies not hidden
at all; it draws the gt silhouettes in red over the first image into ``/tmp/piles_check.png``.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import struct
import subprocess
import sys
import time
from pathlib import Path

try:
    import bpy  # only when Blender runs this file
except ImportError:
    bpy = None

if bpy is None:
    import cv2
    import numpy as np
    import trimesh

    ROOT = Path(__file__).resolve().parents[1]
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from service.vision.geometry.frames import Pose, Rz
    from service.vision.geometry.render import render

MODELS_DIR = Path("/work/shared/data/models")
SYMMETRY = {"sprayer": "y", "lbracket": "none", "flange": "none"}  # the data README's
DEFAULT_MODELS = ("sprayer", "lbracket", "flange")
BLENDER = "blender"

# camera
WIDTH, HEIGHT = 640, 480
FX_RANGE = (550.0, 650.0)
DISTANCE_RANGE_MM = (300.0, 500.0)  # camera centre to the table along the optical axis
TOPDOWN_TILT_DEG = (0.0, 5.0)
OBLIQUE_TILT_DEG = (20.0, 35.0)
OBLIQUE_ROLL_DEG = 10.0  # oblique views: the far side of the table up, +- this roll
IMAGE_MARGIN_PX = 4.0  # every vertex of every copy projects this far inside the image

# copies
COPIES_RANGE = (3, 6)
ON_TOP_PROB = 1.0 / 3.0
CLOSE_PROB = 1.0 / 3.0  # share of table copies put against another copy
APART_GAP_MM = 15.0
CLOSE_GAP_MM = 1.0
TILT_ON_TOP_DEG = (10.0, 25.0)
ON_TOP_OFFSET = 0.35  # the on-top copy's centre within this share of the base copy's footprint radius
DROP_EDGE_MM = 3.0  # meshes subdivided to this edge length for the contact search
FOOTPRINT_GRID_MM = 1.0
PLACE_TRIES = 100  # draws per copy
LAYOUT_TRIES = 30  # cameras and layouts drawn per image until all its copies fit
SUPERSAMPLE = 1  # visible_fraction at pixel centres, the same rule as Blender's check render

# rendering
DEFAULT_SAMPLES = 32
MAX_BOUNCES, DIFFUSE_BOUNCES, GLOSSY_BOUNCES = 4, 2, 3  # light paths: enough for opaque parts on a table
SENSOR_WIDTH_MM = 36.0  # Blender's sensor width; any value, the lens is derived from fx with it
CHECK_PALETTE = ((1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, 0, 1), (0, 1, 1), (1, 1, 1))
MM_PER_M = 1000.0


# --------------------------------------------------------------------------------------------------
# Scene sampling (venv side: numpy, trimesh and the project's rasteriser)
# --------------------------------------------------------------------------------------------------


class Part:
    """One model: mesh (mm, object frame), its stable resting rotations and their probabilities."""

    def __init__(self, name: str, path: Path):
        mesh = trimesh.load(path, force="mesh")
        self.name, self.path = name, path
        self.V = np.asarray(mesh.vertices, float)
        self.F = np.asarray(mesh.faces, np.int64)
        T, prob = trimesh.poses.compute_stable_poses(mesh.convex_hull, center_mass=mesh.center_mass)
        self.R_rest = np.asarray(T)[:, :3, :3]
        self.prob = np.asarray(prob, float) / np.sum(prob)
        Vd, _ = trimesh.remesh.subdivide_to_size(self.V, self.F, max_edge=DROP_EDGE_MM, max_iter=20)
        self.V_drop = np.unique(np.asarray(Vd, float), axis=0)  # contact probes
        self.symmetry = SYMMETRY.get(name, "none")
        self.extents_mm = mesh.extents
        self.bounds_mm = mesh.bounds
        hull = np.asarray(mesh.convex_hull.vertices)
        self.diameter_mm = float(np.sqrt(((hull[:, None] - hull[None]) ** 2).sum(axis=2).max()))
        self.watertight = bool(mesh.is_watertight)


def look_down_camera(rng: np.random.Generator) -> dict:
    """K and T_world_cam (OpenCV camera frame, mm) of one view of the table (z = 0, origin under the axis)."""
    fx = rng.uniform(*FX_RANGE)
    K = np.array([[fx, 0.0, WIDTH / 2.0], [0.0, fx, HEIGHT / 2.0], [0.0, 0.0, 1.0]])
    oblique = bool(rng.random() < 0.5)
    tilt = rng.uniform(*(OBLIQUE_TILT_DEG if oblique else TOPDOWN_TILT_DEG))
    heading = rng.uniform(0.0, 360.0)
    roll = rng.uniform(-OBLIQUE_ROLL_DEG, OBLIQUE_ROLL_DEG) if oblique else 0.0
    dist = rng.uniform(*DISTANCE_RANGE_MM)
    t, h = np.radians(tilt), np.radians(heading)
    far = np.array([np.cos(h), np.sin(h), 0.0])  # horizontal direction the camera looks towards
    z_c = np.sin(t) * far - np.cos(t) * np.array([0.0, 0.0, 1.0])  # optical axis, world frame
    y_c = -(far - (far @ z_c) * z_c)  # image down = away from the far side
    y_c /= np.linalg.norm(y_c)
    x_c = np.cross(y_c, z_c)
    R_wc = np.stack([x_c, y_c, z_c], axis=1) @ Rz(roll)
    T_wc = np.eye(4)
    T_wc[:3, :3], T_wc[:3, 3] = R_wc, -dist * z_c
    return {"K": K, "T_world_cam": T_wc, "tilt_deg": tilt, "oblique": oblique, "distance_mm": dist}


def world_to_cam(cam: dict) -> tuple[np.ndarray, np.ndarray]:
    T = np.linalg.inv(cam["T_world_cam"])
    return T[:3, :3], T[:3, 3]


def in_view(P_world: np.ndarray, cam: dict) -> bool:
    """All points (N, 3, world, mm) in front of the camera and inside the image with the margin."""
    R, t = world_to_cam(cam)
    p = P_world @ R.T + t
    if (p[:, 2] <= 1.0).any():
        return False
    K = cam["K"]
    uv = p[:, :2] / p[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
    m = IMAGE_MARGIN_PX
    return bool((uv[:, 0] >= m).all() and (uv[:, 0] <= WIDTH - 1 - m).all()
                and (uv[:, 1] >= m).all() and (uv[:, 1] <= HEIGHT - 1 - m).all())


def table_point(uv: np.ndarray, cam: dict) -> np.ndarray:
    """World point (mm) of the table (z = 0) seen at pixel uv."""
    K = cam["K"]
    ray_cam = np.array([(uv[0] - K[0, 2]) / K[0, 0], (uv[1] - K[1, 2]) / K[1, 1], 1.0])
    ray = cam["T_world_cam"][:3, :3] @ ray_cam
    c = cam["T_world_cam"][:3, 3]
    return c + ray * (-c[2] / ray[2])


def T_of(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def resting(part: Part, R: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """T_world_obj of the part turned by R, its lowest point on the table, its footprint centred at xy."""
    q = part.V @ R.T
    c = 0.5 * (q[:, :2].min(axis=0) + q[:, :2].max(axis=0))
    return T_of(R, np.array([xy[0] - c[0], xy[1] - c[1], -q[:, 2].min()]))


class Footprints:
    """Occupancy of the table by the copies' footprints (convex hulls of the posed parts), 1 mm grid."""

    def __init__(self, half_mm: float):
        self.half = half_mm
        self.n = int(2 * half_mm / FOOTPRINT_GRID_MM) + 1
        self.occ = np.zeros((self.n, self.n), np.uint8)

    def _roi(self, P_world: np.ndarray, pad_mm: float) -> tuple[np.ndarray, tuple[slice, slice]] | None:
        """The footprint drawn in a window of the grid around it (padded) and that window."""
        g = (P_world[:, :2] + self.half) / FOOTPRINT_GRID_MM
        pad = int(np.ceil(pad_mm / FOOTPRINT_GRID_MM)) + 1
        lo = np.floor(g.min(axis=0)).astype(int) - pad
        hi = np.ceil(g.max(axis=0)).astype(int) + pad
        if lo.min() < 0 or hi.max() >= self.n:
            return None
        m = np.zeros((hi[1] - lo[1] + 1, hi[0] - lo[0] + 1), np.uint8)
        cv2.fillConvexPoly(m, cv2.convexHull(np.rint(g - lo).astype(np.int32)), 1)
        return m, (slice(lo[1], hi[1] + 1), slice(lo[0], hi[0] + 1))

    def free(self, P_world: np.ndarray, gap_mm: float) -> bool:
        roi = self._roi(P_world, gap_mm)
        if roi is None:
            return False
        m, win = roi
        r = int(np.ceil(gap_mm / FOOTPRINT_GRID_MM))
        m = cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
        return not (m & self.occ[win]).any()

    def add(self, P_world: np.ndarray) -> None:
        m, win = self._roi(P_world, 0.0)
        self.occ[win] |= m


def _vertical_extremes(xy: np.ndarray, tri: np.ndarray, block: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """Highest and lowest z of the triangles (M, 3, 3) straight above or below each xy (N, 2);
    -inf / +inf where no triangle covers the point."""
    hi = np.full(len(xy), -np.inf)
    lo = np.full(len(xy), np.inf)
    t_min, t_max = tri[:, :, :2].min(axis=1), tri[:, :, :2].max(axis=1)
    order = np.argsort(xy[:, 0])
    for s in range(0, len(order), block):
        idx = order[s:s + block]
        p = xy[idx]
        pmin, pmax = p.min(axis=0), p.max(axis=0)
        sel = np.nonzero((t_min <= pmax).all(axis=1) & (t_max >= pmin).all(axis=1))[0]
        for c in range(0, len(sel), 4096):
            tr = tri[sel[c:c + 4096]]
            a, b, cc = tr[:, 0], tr[:, 1], tr[:, 2]
            e1, e2 = b[:, :2] - a[:, :2], cc[:, :2] - a[:, :2]
            det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
            ok = np.abs(det) > 1e-12
            if not ok.any():
                continue
            a, b, cc, e1, e2, det = a[ok], b[ok], cc[ok], e1[ok], e2[ok], det[ok]
            d = p[:, None, :] - a[None, :, :2]
            w1 = (d[..., 0] * e2[:, 1] - d[..., 1] * e2[:, 0]) / det
            w2 = (e1[:, 0] * d[..., 1] - e1[:, 1] * d[..., 0]) / det
            inside = (w1 >= -1e-9) & (w2 >= -1e-9) & (w1 + w2 <= 1 + 1e-9)
            z = a[:, 2] + w1 * (b[:, 2] - a[:, 2]) + w2 * (cc[:, 2] - a[:, 2])
            hi[idx] = np.maximum(hi[idx], np.where(inside, z, -np.inf).max(axis=1))
            lo[idx] = np.minimum(lo[idx], np.where(inside, z, np.inf).min(axis=1))
    return hi, lo


def drop(part: Part, T: np.ndarray, others: list[np.ndarray]) -> tuple[np.ndarray, int]:
    """Lower the copy at T (above everything) straight down until it first touches the table or a copy.

    others: T_world_obj of the copies in place. Returns the new T and what it touches (-1: the table,
    k: copy k). Vertex-face contacts both ways: the vertices of the mesh subdivided to DROP_EDGE_MM
    against the other's own triangles (an edge-edge contact between them can sink by a fraction of a mm).
    """
    def posed(V, To):
        return V @ To[:3, :3].T + To[:3, 3]

    P, P_tri = posed(part.V_drop, T), posed(part.V, T)[part.F]
    best, hit = P[:, 2].min(), -1
    for k, To in enumerate(others):
        Q = posed(part.V_drop, To)
        apart = (Q[:, :2].max(axis=0) < P[:, :2].min(axis=0)) | (Q[:, :2].min(axis=0) > P[:, :2].max(axis=0))
        if apart.any():
            continue
        hi, _ = _vertical_extremes(P[:, :2], posed(part.V, To)[part.F])
        _, lo = _vertical_extremes(Q[:, :2], P_tri)
        gap = min(np.min(P[:, 2] - hi), np.min(lo - Q[:, 2]))
        if gap < best:
            best, hit = gap, k
    out = T.copy()
    out[2, 3] -= best
    return out, hit


def place_copies(rng: np.random.Generator, part: Part, cam: dict, n: int, on_top: bool) -> list[dict]:
    """n copies of the part on the table, the last one on top of another if on_top: T_world_obj, how
    placed. Fewer when one does not fit in PLACE_TRIES draws."""
    fp = Footprints(half_mm=2.0 * DISTANCE_RANGE_MM[1])
    copies: list[dict] = []
    for _ in range(n - 1 if on_top else n):
        close = bool(copies) and rng.random() < CLOSE_PROB
        for _try in range(PLACE_TRIES):
            R = Rz(rng.uniform(0.0, 360.0)) @ part.R_rest[rng.choice(len(part.prob), p=part.prob)]
            if close:
                base = copies[int(rng.integers(len(copies)))]
                r = (base["radius_mm"] + 0.5 * part.diameter_mm) * rng.uniform(0.35, 1.0)
                a = rng.uniform(0.0, 2 * np.pi)
                T = resting(part, R, base["centre_xy"] + r * np.array([np.cos(a), np.sin(a)]))
            else:
                uv = rng.uniform([0.1 * WIDTH, 0.1 * HEIGHT], [0.9 * WIDTH, 0.9 * HEIGHT])
                T = resting(part, R, table_point(uv, cam)[:2])
            P = part.V @ T[:3, :3].T + T[:3, 3]
            if in_view(P, cam) and fp.free(P, CLOSE_GAP_MM if close else APART_GAP_MM):
                fp.add(P)
                centre = 0.5 * (P[:, :2].min(axis=0) + P[:, :2].max(axis=0))
                radius = float(np.linalg.norm(P[:, :2] - centre, axis=1).max())
                copies.append({"T_world_obj": T, "placed": "close" if close else "apart", "on": -1,
                               "centre_xy": centre, "radius_mm": radius})
                break
    if on_top and copies:
        for _try in range(PLACE_TRIES):
            k = int(rng.integers(len(copies)))
            base = copies[k]
            axis = rng.uniform(0.0, 2 * np.pi)
            tilt = np.radians(rng.uniform(*TILT_ON_TOP_DEG))
            R_tilt = trimesh.transformations.rotation_matrix(tilt, [np.cos(axis), np.sin(axis), 0.0])[:3, :3]
            R = R_tilt @ Rz(rng.uniform(0.0, 360.0)) @ part.R_rest[rng.choice(len(part.prob), p=part.prob)]
            off = ON_TOP_OFFSET * base["radius_mm"] * np.sqrt(rng.random())
            a = rng.uniform(0.0, 2 * np.pi)
            T = resting(part, R, base["centre_xy"] + off * np.array([np.cos(a), np.sin(a)]))
            top = max(float((part.V @ c["T_world_obj"][:3, :3].T + c["T_world_obj"][:3, 3])[:, 2].max())
                      for c in copies)
            P = part.V @ T[:3, :3].T + T[:3, 3]
            T[2, 3] += top + 10.0
            # the drop is slow: first check the copy is in view at both ends of its way down (the
            # image of a straight path is straight, the image convex: then it is all the way)
            if not (in_view(P, cam) and in_view(P + [0.0, 0.0, top + 10.0], cam)):
                continue
            T, hit = drop(part, T, [c["T_world_obj"] for c in copies])
            if hit >= 0:
                copies.append({"T_world_obj": T, "placed": "on_top", "on": hit,
                               "tilt_deg": float(np.degrees(tilt))})
                break
    return copies


def srgb_to_linear(c) -> list[float]:
    return [x / 12.92 if x <= 0.04045 else ((x + 0.055) / 1.055) ** 2.4 for x in c]


def hsv(rng: np.random.Generator, h, s, v) -> list[float]:
    """A linear RGB colour drawn from (lo, hi) ranges of sRGB hue, saturation and value."""
    import colorsys

    return srgb_to_linear(colorsys.hsv_to_rgb(rng.uniform(*h) % 1.0, rng.uniform(*s), rng.uniform(*v)))


def appearance(rng: np.random.Generator) -> dict:
    """Material of the parts, table, lights and world light of one image (Blender units: m, W)."""
    kind = str(rng.choice(["metal", "white_plastic", "plastic", "dark_plastic"], p=[0.4, 0.2, 0.25, 0.15]))
    if kind == "metal":
        mat = {"color": hsv(rng, (0.55, 0.65), (0.0, 0.12), (0.6, 0.85)), "metallic": 1.0,
               "roughness": rng.uniform(0.15, 0.4)}
    elif kind == "white_plastic":
        mat = {"color": hsv(rng, (0.0, 1.0), (0.0, 0.06), (0.82, 0.95)), "metallic": 0.0,
               "roughness": rng.uniform(0.3, 0.6)}
    elif kind == "plastic":
        mat = {"color": hsv(rng, (0.0, 1.0), (0.5, 0.9), (0.35, 0.85)), "metallic": 0.0,
               "roughness": rng.uniform(0.3, 0.6)}
    else:
        mat = {"color": hsv(rng, (0.0, 1.0), (0.0, 0.3), (0.05, 0.14)), "metallic": 0.0,
               "roughness": rng.uniform(0.3, 0.6)}
    mat["kind"] = kind
    tkind = str(rng.choice(["plain", "noise", "wood", "checker"]))
    if tkind == "wood":
        c1 = hsv(rng, (0.05, 0.11), (0.35, 0.7), (0.35, 0.8))
        c2 = [x * rng.uniform(0.45, 0.75) for x in c1]
    else:
        c1 = hsv(rng, (0.0, 1.0), (0.0, 0.5), (0.2, 0.9))
        c2 = hsv(rng, (0.0, 1.0), (0.0, 0.5), (0.1, 0.9))
    table = {"kind": tkind, "color1": c1, "color2": c2, "roughness": rng.uniform(0.35, 0.9),
             "scale": {"plain": 1.0, "noise": rng.uniform(8.0, 40.0), "wood": rng.uniform(2.0, 6.0),
                       "checker": rng.uniform(8.0, 30.0)}[tkind],
             "detail": rng.uniform(2.0, 8.0), "distortion": rng.uniform(2.0, 8.0),
             "rotation_deg": rng.uniform(0.0, 360.0)}
    lights = []
    for j in range(int(rng.integers(1, 3))):
        az, el = rng.uniform(0.0, 2 * np.pi), np.radians(rng.uniform(45.0, 80.0))
        d = rng.uniform(0.6, 1.2)
        loc = d * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        lights.append({"location_m": loc.tolist(), "size_m": rng.uniform(0.15, 0.6),
                       "power_w": rng.uniform(45.0, 130.0) * d * d * (1.0 if j == 0 else 0.5),
                       "color": hsv(rng, (0.05, 0.6), (0.0, 0.12), (1.0, 1.0))})
    world = {"color": hsv(rng, (0.0, 1.0), (0.0, 0.1), (0.8, 1.0)), "strength": rng.uniform(0.15, 0.6)}
    return {"material": mat, "table": table, "lights": lights, "world": world}


def ground_truth(part: Part, cam: dict, copies: list[dict], image: str) -> tuple[list[dict], list]:
    """gt.jsonl lines of the copies and their visible masks (h, w bool: the copy is the front-most)."""
    R_cw, t_cw = world_to_cam(cam)
    poses = [Pose(R_cw @ c["T_world_obj"][:3, :3], R_cw @ c["T_world_obj"][:3, 3] + t_cw) for c in copies]
    solo = [render(part.V, part.F, p, cam["K"], (WIDTH, HEIGHT), supersample=SUPERSAMPLE) for p in poses]
    depth = np.stack([r.depth_mm for r in solo])
    owner = np.argmin(depth, axis=0)
    visible = [r.mask & (owner == k) for k, r in enumerate(solo)]
    n = R_cw @ np.array([0.0, 0.0, 1.0])
    plane = {"normal": n.tolist(), "d_mm": float(n @ t_cw)}
    lines = [{"image": image, "model": part.name, "K": cam["K"].tolist(), "width": WIDTH, "height": HEIGHT,
              "R": p.R.tolist(), "t_mm": p.t_mm.tolist(), "symmetry": part.symmetry,
              "visible_fraction": round(float(v.sum()) / max(float(r.mask.sum()), 1.0), 4),
              "plane": plane, "plane_rms_mm": 0.0}
             for p, r, v in zip(poses, solo, visible, strict=True)]
    return lines, visible


def make_scene(rng: np.random.Generator, parts: dict[str, Part], index: int) -> tuple[dict, Part, list[dict]]:
    """The scene description Blender renders (world frame, mm; paths relative to the set) and its copies."""
    part = parts[str(rng.choice(sorted(parts)))]
    n = int(rng.integers(COPIES_RANGE[0], COPIES_RANGE[1] + 1))
    on_top = bool(rng.random() < ON_TOP_PROB)
    best: tuple[dict, list[dict]] | None = None
    for _ in range(LAYOUT_TRIES):  # a long part may not fit n times in a near camera's view
        cam = look_down_camera(rng)
        copies = place_copies(rng, part, cam, n, on_top)
        if best is None or len(copies) > len(best[1]):
            best = cam, copies
        if len(copies) == n:
            break
    cam, copies = best
    look = appearance(rng)
    scene = {"index": index, "image": f"images/{index:06d}.png", "mesh": f"models/{part.name}.stl",
             "model": part.name, "width": WIDTH, "height": HEIGHT, "K": cam["K"].tolist(),
             "T_world_cam": cam["T_world_cam"].tolist(), "camera": {k: cam[k] for k in
                                                                     ("tilt_deg", "oblique", "distance_mm")},
             "copies": [{"T_world_obj": c["T_world_obj"].tolist(), "placed": c["placed"], "on": c["on"]}
                        for c in copies], **look}
    return scene, part, cam


def run_blender(scene_path: Path, samples: int, check_path: Path | None = None) -> float:
    """Render one scene json with Blender; returns the wall time, s."""
    cmd = [BLENDER, "-b", "--factory-startup", "-noaudio", "--python-exit-code", "1",
           "--python", str(Path(__file__).resolve()), "--", str(scene_path), str(samples)]
    if check_path is not None:
        cmd.append(str(check_path))
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"blender failed on {scene_path}:\n{res.stdout[-3000:]}\n{res.stderr[-3000:]}")
    return time.perf_counter() - t0


def strip_png(path: Path) -> None:
    """Write the PNG again without Cycles' metadata (render times): the same scene gives the same bytes."""
    cv2.imwrite(str(path), cv2.imread(str(path), cv2.IMREAD_COLOR))


def check_ids(check_png: Path, n_copies: int) -> list[np.ndarray]:
    """Per-copy masks (h, w bool) decoded from a flat-colour check render (CHECK_PALETTE, black = none)."""
    bgr = cv2.imread(str(check_png), cv2.IMREAD_COLOR)
    rgb = (bgr[..., ::-1] >= 128).astype(np.int32)
    code = rgb[..., 0] * 4 + rgb[..., 1] * 2 + rgb[..., 2]
    return [code == (c[0] * 4 + c[1] * 2 + c[2]) for c in CHECK_PALETTE[:n_copies]]


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum()) / max(float((a | b).sum()), 1.0)


def overlay(image_png: Path, lines: list[dict], part: Part, out_png: Path) -> None:
    """The image with every copy's gt silhouette outlined in red."""
    img = cv2.imread(str(image_png), cv2.IMREAD_COLOR)
    for ln in lines:
        m = render(part.V, part.F, Pose(np.array(ln["R"]), np.array(ln["t_mm"])), np.array(ln["K"]),
                   (WIDTH, HEIGHT)).mask
        contours, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(img, contours, -1, (0, 0, 255), 1)
    cv2.imwrite(str(out_png), img)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--n", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--models", default=",".join(DEFAULT_MODELS))
    ap.add_argument("--samples", type=int, default=DEFAULT_SAMPLES)
    ap.add_argument("--skip-existing", action="store_true", help="do not render images already there")
    ap.add_argument("--check", type=int, default=0, help="check the first N images against the rasteriser")
    ap.add_argument("--check-dir", type=Path, default=Path("/tmp/piles_check"))
    args = ap.parse_args(argv)
    if shutil.which(BLENDER) is None:
        sys.exit("blender not found: apt-get install -y blender")
    out = args.out
    for sub in ("images", "scenes", "models"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    parts = {}
    for name in args.models.split(","):
        src = MODELS_DIR / f"{name}.stl"
        shutil.copyfile(src, out / "models" / src.name)
        parts[name] = Part(name, out / "models" / src.name)
    if args.check:
        args.check_dir.mkdir(parents=True, exist_ok=True)
    all_lines, times, checks = [], [], []
    n_on_top = 0
    for i in range(args.n):
        rng = np.random.default_rng(args.seed + i)
        scene, part, cam = make_scene(rng, parts, i)
        scene["cycles_seed"] = args.seed + i
        scene_path = out / "scenes" / f"{i:06d}.json"
        scene_path.write_text(json.dumps(scene, indent=1))
        lines, visible = ground_truth(part, cam, [{"T_world_obj": np.array(c["T_world_obj"])}
                                                  for c in scene["copies"]], scene["image"])
        n_on_top += sum(c["placed"] == "on_top" for c in scene["copies"])
        image_png = out / scene["image"]
        check_png = args.check_dir / f"{i:06d}_ids.png" if i < args.check else None
        if not (args.skip_existing and image_png.exists() and check_png is None):
            times.append(run_blender(scene_path, args.samples, check_png))
            strip_png(image_png)
            print(f"{i:4d} {part.name:9s} copies {len(lines)} on_top "
                  f"{sum(c['placed'] == 'on_top' for c in scene['copies'])} "
                  f"{'oblique' if scene['camera']['oblique'] else 'top-down'} {times[-1]:.1f} s", flush=True)
        all_lines += lines
        if check_png is not None:
            got = check_ids(check_png, len(lines))
            for k, ln in enumerate(lines):
                solo = render(part.V, part.F, Pose(np.array(ln["R"]), np.array(ln["t_mm"])), cam["K"],
                              (WIDTH, HEIGHT)).mask
                full = iou(got[k], solo) if ln["visible_fraction"] >= 1.0 else float("nan")
                checks.append((i, k, ln["visible_fraction"], iou(got[k], visible[k]), full))
                print(f"  check image {i} copy {k}: visible {ln['visible_fraction']:.3f} "
                      f"IoU visible {checks[-1][3]:.4f} IoU whole {full:.4f}", flush=True)
            if i == 0:
                overlay(image_png, lines, part, Path("/tmp/piles_check.png"))
        (out / "gt.jsonl").write_text("".join(json.dumps(ln) + "\n" for ln in all_lines))
    meta = {"set": out.name, "generator": "bench/blender_piles.py", "n_images": args.n, "seed": args.seed,
            "samples": args.samples, "width": WIDTH, "height": HEIGHT, "n_lines": len(all_lines),
            "n_on_top": n_on_top,
            "render_s_per_image": {"mean": round(float(np.mean(times)), 2) if times else None,
                                   "max": round(float(np.max(times)), 2) if times else None,
                                   "each": [round(t, 2) for t in times]},
            "models": {p.name: {"file": f"{p.name}.stl", "symmetry": p.symmetry, "vertices": len(p.V),
                                "faces": len(p.F), "extents_mm": np.round(p.extents_mm, 3).tolist(),
                                "bounds_mm": np.round(p.bounds_mm, 3).tolist(),
                                "diameter_mm": round(p.diameter_mm, 2), "watertight": p.watertight}
                       for p in parts.values()}}
    (out / "meta.json").write_text(json.dumps(meta, indent=1))
    if checks:
        c = np.array(checks, float)
        full = c[~np.isnan(c[:, 4]), 4]
        print(f"check: {len(c)} copies, IoU visible min {c[:, 3].min():.4f} mean {c[:, 3].mean():.4f}; "
              f"{len(full)} fully visible, IoU whole min {full.min() if len(full) else float('nan'):.4f}")
    rs = meta["render_s_per_image"]
    print(f"{args.n} images, {len(all_lines)} copies, {n_on_top} on top; render mean {rs['mean']} s, "
          f"max {rs['max']} s per image -> {out}")


# --------------------------------------------------------------------------------------------------
# Blender side (run by Blender's own Python: bpy and mathutils only)
# --------------------------------------------------------------------------------------------------


def bl_read_stl(path: Path) -> tuple[list, list]:
    """Vertices (mm) and triangles of an STL file, shared vertices merged (binary or ASCII)."""
    data = path.read_bytes()
    index: dict = {}
    verts: list = []
    tris: list = []

    def vid(v):
        if v not in index:
            index[v] = len(verts)
            verts.append(v)
        return index[v]

    n = struct.unpack_from("<I", data, 80)[0] if len(data) >= 84 else -1
    if len(data) == 84 + 50 * n:
        for i in range(n):
            f = struct.unpack_from("<9f", data, 84 + 50 * i + 12)
            tris.append((vid(f[0:3]), vid(f[3:6]), vid(f[6:9])))
    else:
        vs = [tuple(float(x) for x in ln.split()[1:4]) for ln in data.decode().splitlines()
              if ln.strip().startswith("vertex")]
        tris = [(vid(vs[i]), vid(vs[i + 1]), vid(vs[i + 2])) for i in range(0, len(vs), 3)]
    return verts, tris


def bl_matrix_m(T_mm, scale: float):
    """mathutils 4x4 of a mm transform for Blender's metres: rotation part times scale, translation / 1000."""
    from mathutils import Matrix

    M = Matrix([list(r) for r in T_mm])
    for r in range(3):
        for c in range(3):
            M[r][c] *= scale
        M[r][3] /= MM_PER_M
    return M


def bl_principled(name: str, color, metallic: float, roughness: float):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    bsdf = mat.node_tree.nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    bsdf.inputs["Metallic"].default_value = metallic
    bsdf.inputs["Roughness"].default_value = roughness
    return mat, bsdf


def bl_table_material(t: dict):
    mat, bsdf = bl_principled("table", t["color1"], 0.0, t["roughness"])
    if t["kind"] == "plain":
        return mat
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    coord = nodes.new("ShaderNodeTexCoord")
    mapping = nodes.new("ShaderNodeMapping")
    mapping.inputs["Rotation"].default_value = (0.0, 0.0, math.radians(t["rotation_deg"]))
    links.new(coord.outputs["Object"], mapping.inputs["Vector"])
    if t["kind"] == "checker":
        tex = nodes.new("ShaderNodeTexChecker")
        tex.inputs["Scale"].default_value = t["scale"]
        tex.inputs["Color1"].default_value = (*t["color1"], 1.0)
        tex.inputs["Color2"].default_value = (*t["color2"], 1.0)
        links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
        links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
        return mat
    if t["kind"] == "wood":
        tex = nodes.new("ShaderNodeTexWave")
        tex.wave_type, tex.bands_direction = "BANDS", "X"
        tex.inputs["Distortion"].default_value = t["distortion"]
        tex.inputs["Detail"].default_value = t["detail"]
        tex.inputs["Detail Scale"].default_value = 1.5
        mapping.inputs["Scale"].default_value = (1.0, 8.0, 1.0)  # grain runs along y
    else:
        tex = nodes.new("ShaderNodeTexNoise")
        tex.inputs["Detail"].default_value = t["detail"]
    tex.inputs["Scale"].default_value = t["scale"]
    ramp = nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].color = (*t["color1"], 1.0)
    ramp.color_ramp.elements[1].color = (*t["color2"], 1.0)
    links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
    links.new(tex.outputs["Fac"], ramp.inputs["Fac"])
    links.new(ramp.outputs["Color"], bsdf.inputs["Base Color"])
    return mat


def bl_render(scene, path: Path) -> None:
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)


def blender_main(scene_path: Path, samples: int, check_path: Path | None) -> None:
    """Build the scene described by scene_path (see make_scene) and render it; with check_path also a
    flat-colour image: copy k in CHECK_PALETTE[k], one sample at each pixel's centre, black elsewhere."""
    from mathutils import Matrix, Vector

    sc = json.loads(scene_path.read_text())
    set_dir = scene_path.resolve().parents[1]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    w, h = sc["width"], sc["height"]
    r = scene.render
    r.engine = "CYCLES"
    r.resolution_x, r.resolution_y, r.resolution_percentage = w, h, 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    r.dither_intensity = 0.0
    im = r.image_settings
    im.file_format, im.color_mode, im.color_depth = "PNG", "RGB", "8"
    cy = scene.cycles
    cy.device = "CPU"
    cy.samples = samples
    cy.seed, cy.use_animated_seed = sc["cycles_seed"], False
    cy.max_bounces, cy.diffuse_bounces, cy.glossy_bounces = MAX_BOUNCES, DIFFUSE_BOUNCES, GLOSSY_BOUNCES
    cy.transmission_bounces, cy.transparent_max_bounces, cy.volume_bounces = 0, 2, 0
    cy.caustics_reflective = cy.caustics_refractive = False
    cy.blur_glossy, cy.sample_clamp_indirect = 1.0, 8.0
    try:
        import _cycles

        cy.use_denoising = bool(getattr(_cycles, "with_openimagedenoise", False))
    except ImportError:
        cy.use_denoising = False
    scene.view_settings.view_transform, scene.view_settings.look = "Filmic", "None"

    # camera: K exactly (lens from fx; shift puts the principal point at our pixel-centre coordinates)
    K = sc["K"]
    cam_data = bpy.data.cameras.new("cam")
    cam_data.sensor_fit, cam_data.sensor_width = "HORIZONTAL", SENSOR_WIDTH_MM
    cam_data.lens = K[0][0] * SENSOR_WIDTH_MM / w
    # without shift the axis meets the image at pixel (w / 2 - 0.5, h / 2 - 0.5) in our pixel-centre
    # coordinates; a positive shift_x (y) moves the picture left (down), in units of the sensor width
    cam_data.shift_x = -(K[0][2] + 0.5 - w / 2.0) / w
    cam_data.shift_y = (K[1][2] + 0.5 - h / 2.0) / w
    cam_data.clip_start, cam_data.clip_end = 0.01, 20.0
    cam = bpy.data.objects.new("cam", cam_data)
    scene.collection.objects.link(cam)
    cv_to_blender = Matrix(((1, 0, 0, 0), (0, -1, 0, 0), (0, 0, -1, 0), (0, 0, 0, 1)))
    cam.matrix_world = bl_matrix_m(sc["T_world_cam"], 1.0) @ cv_to_blender
    scene.camera = cam

    # table: the plane z = 0, large
    half = 3.0
    tmesh = bpy.data.meshes.new("table")
    tmesh.from_pydata([(-half, -half, 0), (half, -half, 0), (half, half, 0), (-half, half, 0)], [],
                      [(0, 1, 2, 3)])
    table = bpy.data.objects.new("table", tmesh)
    table.data.materials.append(bl_table_material(sc["table"]))
    scene.collection.objects.link(table)

    # parts
    verts, tris = bl_read_stl(set_dir / sc["mesh"])
    m = sc["material"]
    mat, _ = bl_principled("part", m["color"], m["metallic"], m["roughness"])
    parts = []
    for k, c in enumerate(sc["copies"]):
        mesh = bpy.data.meshes.new(f"part{k}")
        mesh.from_pydata(verts, [], tris)
        mesh.polygons.foreach_set("use_smooth", [True] * len(mesh.polygons))
        mesh.use_auto_smooth, mesh.auto_smooth_angle = True, math.radians(30.0)
        mesh.materials.append(mat)
        ob = bpy.data.objects.new(f"part{k}", mesh)
        ob.matrix_world = bl_matrix_m(c["T_world_obj"], 1.0 / MM_PER_M)
        scene.collection.objects.link(ob)
        parts.append(ob)

    # lights
    lights = []
    for j, li in enumerate(sc["lights"]):
        ld = bpy.data.lights.new(f"light{j}", "AREA")
        ld.shape, ld.size, ld.energy, ld.color = "DISK", li["size_m"], li["power_w"], li["color"]
        lo = bpy.data.objects.new(f"light{j}", ld)
        lo.location = Vector(li["location_m"])
        lo.rotation_euler = (-lo.location).to_track_quat("-Z", "Y").to_euler()
        scene.collection.objects.link(lo)
        lights.append(lo)
    world = bpy.data.worlds.new("world")
    world.use_nodes = True
    bg = world.node_tree.nodes["Background"]
    bg.inputs["Color"].default_value = (*sc["world"]["color"], 1.0)
    bg.inputs["Strength"].default_value = sc["world"]["strength"]
    scene.world = world

    bl_render(scene, set_dir / sc["image"])
    if check_path is None:
        return
    table.hide_render = True
    for lo in lights:
        lo.hide_render = True
    bg.inputs["Strength"].default_value = 0.0
    for k, ob in enumerate(parts):
        flat = bpy.data.materials.new(f"flat{k}")
        flat.use_nodes = True
        nodes = flat.node_tree.nodes
        nodes.remove(nodes["Principled BSDF"])
        em = nodes.new("ShaderNodeEmission")
        em.inputs["Color"].default_value = (*CHECK_PALETTE[k], 1.0)
        flat.node_tree.links.new(em.outputs["Emission"], nodes["Material Output"].inputs["Surface"])
        ob.data.materials[0] = flat
    scene.view_settings.view_transform = "Standard"
    cy.samples, cy.use_adaptive_sampling, cy.use_denoising = 1, False, False
    cy.pixel_filter_type, cy.filter_width = "BOX", 0.01
    cy.max_bounces = 0
    bl_render(scene, check_path)


if __name__ == "__main__":
    if bpy is not None:
        args = sys.argv[sys.argv.index("--") + 1:]
        blender_main(Path(args[0]), int(args[1]), Path(args[2]) if len(args) > 2 else None)
    else:
        main()
