"""Seeded generator of cluttered test scenes with exact ground truth, in the data sets' format.

    python bench/synth_scenes.py OUT_DIR --n 300 --seed 7 [--size 1280x960|640x480] [--absent-frac 0.25]
                                 [--models sprayer,lbracket,flange] [--min-visible 0.5]

Writes ``OUT_DIR/images/NNNN.png``, ``OUT_DIR/models/<model>.stl``, ``OUT_DIR/meta.json`` and
``OUT_DIR/gt.jsonl`` exactly like ``../shared/data/clutter`` (present) and ``.../absent`` (absent lines
have ``"absent": true``, ``"visible_fraction": 0.0`` and no ``R`` / ``t_mm``). Keep OUT_DIR outside the
repository (e.g. /tmp/synth); ``bench/out/`` is git-ignored if you must write inside it.

Scene model (every image is drawn from ``np.random.default_rng([seed, index])``, so a set is
reproducible and any one image can be regenerated alone):

- camera: the pinhole ``K`` of the clutter set (fx 1020-1240 at 1280 x 960, principal point within
  a few % of the centre; scaled for other sizes) or, at 640 x 480, Linemod-Occluded's (fx ~ 572);
- floor: a textured plane behind everything (1250-1750 mm, tilted up to 40 deg, so its texture is
  perspective-foreshortened), textured with one of: checkerboard, (wavy) stripes, wood grain, smooth
  fractal noise, printed matter (blocks, discs, lines, text-like marks) or plain with a mild
  gradient; plus a mild large-scale unevenness; sometimes (60 % of printed floors, 12 % of the others)
  a flat, shaded, poster-sized *picture of a part* (most often the model asked about) is printed on
  it -- it is floor, never ground truth, and casts no shadow;
- 2-6 distractors at 300-1200 mm with random full rotations: boxes, cylinders, spheres and,
  sometimes, one of the other CAD parts (never the target's model); one is sometimes put in front
  of the target on purpose to occlude it;
- the target part at a random full 6D pose: rotation uniform on SO(3), distance 300-1200 mm, the
  model's bounding-box centre projected inside the image with a 12 % margin; its colour is random,
  or close to the floor's mean colour, or of the floor's lightness (Lab L) with another hue;
- shading: Lambert with ambient + a weak Blinn-Phong highlight, one random light direction from
  the camera's side per image, flat per face, anti-aliased (2 x 2 supersampling of the project's
  rasteriser ``render``); objects are composited by depth (per-pixel z-test on ``depth_mm``);
- soft cast shadows of every object on the floor (its silhouette shifted along the light and
  blurred), a global gain, a linear light gradient and a soft dark blob, then sometimes a slight
  Gaussian blur, Gaussian sensor noise (sigma 1-4 levels) and sometimes JPEG (quality 70-92;
  decoded again and saved as PNG).

Ground truth: ``R``, ``t_mm`` (T_cam_obj, p_cam = R @ p_obj + t, OpenCV frame, mm), ``K``;
``visible_fraction`` = (target pixels not behind a nearer distractor) / (target pixels of the part
rendered alone), both counted INSIDE the image (the rasteriser never writes outside it) with the
renderer's own mask at ``supersample=2`` (coverage >= 0.5: at least 2 of a pixel's 2 x 2 sub-sample
centres inside the projected mesh); a present scene is redrawn with new distractors until
``visible_fraction >= --min-visible`` (default 0.5, like clutter / lmo_dev).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # `python bench/synth_scenes.py`
try:  # the geometry modules are moving to service/vision/geometry/: accept both layouts
    from service.vision.geometry.camera import Intrinsics  # noqa: E402
    from service.vision.geometry.frames import Pose, axis_alpha_gamma_deg  # noqa: E402
    from service.vision.geometry.render import render  # noqa: E402
except ImportError:
    from service.vision.camera import Intrinsics  # noqa: E402
    from service.vision.frames import Pose, axis_alpha_gamma_deg  # noqa: E402
    from service.vision.render import render  # noqa: E402

from bench import synth_light  # noqa: E402
from bench.synth_light import Look, ShadowMap, sample_look  # noqa: E402

DATA_DIR = Path(os.environ.get("POSE_DATA_DIR", ROOT.parent / "shared" / "data"))
MODELS_DIR = DATA_DIR / "models"
SYMMETRY = {"sprayer": "y", "lbracket": "none", "flange": "none"}
DEFAULT_MODELS = ("sprayer", "lbracket", "flange")

DIST_RANGE_MM = (300.0, 1200.0)
FLOOR_DIST_MM = (1250.0, 1750.0)
FLOOR_MAX_TILT_DEG = 40.0
CENTRE_MARGIN = 0.12  # fraction of the image size kept free around the target's projected centre
N_DISTRACTORS = (2, 6)
SUPERSAMPLE = 2
MAX_TRIES = 12  # distractor redraws to reach --min-visible
FLOOR_KINDS = ("checker", "stripes", "wood", "noise", "printed", "plain")
FLOOR_P = (0.22, 0.16, 0.16, 0.18, 0.18, 0.10)


# --- meshes -------------------------------------------------------------------------------------

@dataclass
class Mesh:
    V: np.ndarray  # (V, 3) float64 mm
    F: np.ndarray  # (F, 3) int32
    centre: np.ndarray  # bounding-box centre, mm
    diameter: float


_MESHES: dict[str, Mesh] = {}


def _mesh(V, F) -> Mesh:
    V = np.asarray(V, float)
    lo, hi = V.min(axis=0), V.max(axis=0)
    return Mesh(V, np.ascontiguousarray(F, np.int32), (lo + hi) / 2, float(np.linalg.norm(hi - lo)))


def load_model(name: str, models_dir: Path | None = None) -> Mesh:
    models_dir = MODELS_DIR if models_dir is None else models_dir
    key = f"{models_dir}/{name}"
    if key not in _MESHES:
        import trimesh

        m = trimesh.load(models_dir / f"{name}.stl", force="mesh")
        _MESHES[key] = _mesh(m.vertices, m.faces)
    return _MESHES[key]


def primitive(kind: str) -> Mesh:
    """Unit primitives (scaled per instance): box of extents 1, cylinder r = 1 h = 1, sphere r = 1."""
    if kind not in _MESHES:
        import trimesh

        m = {"box": lambda: trimesh.creation.box(extents=(1.0, 1.0, 1.0)),
             "cylinder": lambda: trimesh.creation.cylinder(radius=1.0, height=1.0, sections=48),
             "sphere": lambda: trimesh.creation.icosphere(subdivisions=3, radius=1.0)}[kind]()
        _MESHES[kind] = _mesh(m.vertices, m.faces)
    return _MESHES[kind]


# --- camera -------------------------------------------------------------------------------------

def sample_K(rng, w: int, h: int) -> np.ndarray:
    """Linemod-Occluded-like at 640 x 480, else the clutter set's (1280 x 960) scaled to the width."""
    if (w, h) == (640, 480):
        fx = rng.uniform(562.0, 582.0)
        fy = fx * 1.002
        cx, cy = 325.26 + rng.uniform(-4, 4), 242.05 + rng.uniform(-4, 4)
    else:
        s = w / 1280.0
        fx = rng.uniform(1020.0, 1240.0) * s
        fy = fx * (1.0 + rng.uniform(-0.004, 0.004))
        cx = (w - 1) / 2 + rng.uniform(-0.016, 0.019) * w
        cy = (h - 1) / 2 + rng.uniform(-0.026, 0.021) * h
    return Intrinsics(fx, fy, cx, cy).K


def random_rotation(rng) -> np.ndarray:
    return Rotation.random(random_state=rng).as_matrix()


def pose_at_pixel(mesh: Mesh, R: np.ndarray, uv, z: float, K: np.ndarray) -> Pose:
    """Pose whose bounding-box centre lies at depth z on the ray through pixel uv."""
    ray = np.linalg.solve(K, np.array([uv[0], uv[1], 1.0]))
    return Pose(R, ray * z - R @ mesh.centre)


# --- colours ------------------------------------------------------------------------------------

def hsv_bgr(h: float, s: float, v: float) -> np.ndarray:
    px = np.uint8([[[int(h) % 180, int(np.clip(s * 255, 0, 255)), int(np.clip(v * 255, 0, 255))]]])
    return cv2.cvtColor(px, cv2.COLOR_HSV2BGR)[0, 0].astype(float)


def random_colour(rng, s=(0.05, 0.75), v=(0.3, 0.95)) -> np.ndarray:
    return hsv_bgr(rng.uniform(0, 180), rng.uniform(*s), rng.uniform(*v))


def lab(bgr) -> np.ndarray:
    return cv2.cvtColor(np.float32(bgr).reshape(1, 1, 3) / 255.0, cv2.COLOR_BGR2Lab)[0, 0]


def from_lab(L_ab) -> np.ndarray:
    px = cv2.cvtColor(np.float32(L_ab).reshape(1, 1, 3), cv2.COLOR_Lab2BGR)[0, 0]
    return np.clip(px * 255.0, 0, 255).astype(float)


def part_colour(rng, floor_mean: np.ndarray) -> tuple[np.ndarray, str]:
    """Random (55 %), near the floor's mean colour (20 %), the floor's lightness in another hue (25 %)."""
    u = rng.uniform()
    if u < 0.55:
        return random_colour(rng), "random"
    if u < 0.75:
        return np.clip(floor_mean + rng.normal(0, 14, 3), 0, 255), "near_floor"
    L = lab(floor_mean)[0]
    ang = rng.uniform(0, 2 * np.pi)
    rad = rng.uniform(25, 60)
    for _ in range(8):  # shrink the chroma until the colour is in gamut (same lightness)
        c = from_lab([L, rad * np.cos(ang), rad * np.sin(ang)])
        if abs(lab(c)[0] - L) < 2.0:
            break
        rad *= 0.7
    return c, "floor_lightness"


# --- floor --------------------------------------------------------------------------------------

def fbm(rng, shape, cell: float, octaves: int = 4, gain: float = 0.5) -> np.ndarray:
    """Smooth fractal noise in [0, 1], (h, w) float32, features ~ ``cell`` pixels."""
    h, w = shape
    out = np.zeros(shape, np.float32)
    amp, tot, c = 1.0, 0.0, float(cell)
    for _ in range(octaves):
        gh, gw = max(int(h / c) + 2, 2), max(int(w / c) + 2, 2)
        g = rng.random((gh, gw)).astype(np.float32)
        out += amp * cv2.resize(g, (w, h), interpolation=cv2.INTER_CUBIC)
        tot += amp
        amp *= gain
        c /= 2.0
        if c < 1.5:
            break
    out /= tot
    lo, hi = float(out.min()), float(out.max())
    return (out - lo) / max(hi - lo, 1e-6)


def mix(c0, c1, t) -> np.ndarray:
    t = np.asarray(t, np.float32)[..., None]
    return (1 - t) * np.float32(c0) + t * np.float32(c1)


def floor_geometry(rng, K: np.ndarray, w: int, h: int):
    """Per-pixel plane coordinates (a, b) mm of an oblique floor plane, and its depth map."""
    Zf = rng.uniform(*FLOOR_DIST_MM)
    tilt = rng.uniform(0, FLOOR_MAX_TILT_DEG)
    az = rng.uniform(0, 2 * np.pi)
    Rf = Rotation.from_rotvec(np.radians(tilt) * np.array([np.cos(az), np.sin(az), 0.0])).as_matrix()
    Rf = Rf @ Rotation.from_euler("z", rng.uniform(0, 360), degrees=True).as_matrix()
    e1, e2, n = Rf[:, 0], Rf[:, 1], Rf[:, 2]
    P0 = np.array([0.0, 0.0, Zf])
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    Ki = np.linalg.inv(K)
    dx, dy = Ki[0, 0] * u + Ki[0, 2], Ki[1, 1] * v + Ki[1, 2]
    s = (n @ P0) / (n[0] * dx + n[1] * dy + n[2])
    X = np.stack([s * dx - P0[0], s * dy - P0[1], s - P0[2]], axis=-1)
    a = X @ e1
    b = X @ e2
    return a.astype(np.float32), b.astype(np.float32), s.astype(np.float32), Zf


def text_marks(rng, tex, n, mpp):
    chars = "ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789 abcdefghijklmnopqrstuvwxyz-./"
    H, W = tex.shape[:2]
    ink = random_colour(rng, v=(0.0, 0.4)) if rng.uniform() < 0.7 else random_colour(rng)
    for _ in range(n):
        s = "".join(rng.choice(list(chars), size=int(rng.integers(3, 16))))
        scale = rng.uniform(6, 25) / mpp / 22.0
        org = (int(rng.uniform(0, W)), int(rng.uniform(0, H)))
        cv2.putText(tex, s, org, int(rng.choice([0, 1, 2, 3, 4, 6, 7])), max(scale, 0.2), ink.tolist(),
                    max(int(scale * 2), 1), cv2.LINE_AA)


def printed_part(rng, tex, mesh: Mesh, size_tpx: float, at_tpx, colour, light) -> None:
    """Paste a flat shaded picture of ``mesh`` (random view) into the floor texture at ``at_tpx``."""
    n = int(np.clip(size_tpx, 16, 0.8 * min(tex.shape[:2])))
    z = 5.0 * mesh.diameter
    f = 0.85 * n * z / mesh.diameter
    K = np.array([[f, 0, (n - 1) / 2], [0, f, (n - 1) / 2], [0, 0, 1.0]])
    R = random_rotation(rng)
    layer = shade_layer(mesh, Pose(R, np.array([0, 0, z]) - R @ mesh.centre), K, n, n, colour, light,
                        ambient=rng.uniform(0.3, 0.5), spec=0.1)
    if layer is None:
        return
    pic, cov = np.zeros((n, n, 3), np.float32), np.zeros((n, n), np.float32)
    (v0, u0), (bh, bw) = layer["origin"], layer["cov"].shape
    pic[v0:v0 + bh, u0:u0 + bw], cov[v0:v0 + bh, u0:u0 + bw] = layer["colour"], layer["cov"]
    if rng.uniform() < 0.4:  # a printed frame around it
        cv2.rectangle(tex, (int(at_tpx[0] - n / 2 - 4), int(at_tpx[1] - n / 2 - 4)),
                      (int(at_tpx[0] + n / 2 + 4), int(at_tpx[1] + n / 2 + 4)), (235, 235, 235), -1)
    x0, y0 = int(at_tpx[0] - n / 2), int(at_tpx[1] - n / 2)
    H, W = tex.shape[:2]
    xs, ys = slice(max(x0, 0), min(x0 + n, W)), slice(max(y0, 0), min(y0 + n, H))
    if xs.stop <= xs.start or ys.stop <= ys.start:
        return
    ps = (slice(ys.start - y0, ys.stop - y0), slice(xs.start - x0, xs.stop - x0))
    c = cov[ps][..., None]
    tex[ys, xs] = tex[ys, xs] * (1 - c) + pic[ps] * c


def make_floor(rng, K, w, h, models: list[str], light, target: str) -> tuple[np.ndarray, np.ndarray, dict]:
    """(h, w, 3) float32 BGR floor, its depth (h, w) and a description; a printed picture on it shows
    ``target`` (the model asked about, present or not) more often than the other models."""
    a, b, depth, Zf = floor_geometry(rng, K, w, h)
    amin, amax, bmin, bmax = float(a.min()), float(a.max()), float(b.min()), float(b.max())
    mpp = max(Zf / K[0, 0], max(amax - amin, bmax - bmin) / 2000.0)  # texture mm per texel
    W, H = int((amax - amin) / mpp) + 3, int((bmax - bmin) / mpp) + 3
    ta, tb = np.meshgrid(amin + mpp * np.arange(W, dtype=np.float32),
                         bmin + mpp * np.arange(H, dtype=np.float32))
    kind = str(rng.choice(FLOOR_KINDS, p=FLOOR_P))
    c0, c1 = random_colour(rng), random_colour(rng)
    desc = {"kind": kind, "dist_mm": round(Zf, 1)}
    if kind == "checker":
        p = rng.uniform(12, 90)
        if rng.uniform() < 0.5:  # low contrast
            c1 = np.clip(c0 + rng.normal(0, 30, 3), 0, 255)
        t = ((np.floor(ta / p) + np.floor(tb / p)) % 2).astype(np.float32)
        tex = mix(c0, c1, cv2.GaussianBlur(t, (0, 0), 0.6))
        desc["period_mm"] = round(p, 1)
    elif kind == "stripes":
        p, th = rng.uniform(8, 60), rng.uniform(0, np.pi)
        q, amp = rng.uniform(40, 300), rng.uniform(0, 0.5) * p
        x = ta * np.cos(th) + tb * np.sin(th)
        y = -ta * np.sin(th) + tb * np.cos(th)
        ph = 2 * np.pi * (x + amp * np.sin(2 * np.pi * y / q)) / p
        sharp = rng.uniform(1, 8)
        tex = mix(c0, c1, 0.5 + 0.5 * np.tanh(sharp * np.sin(ph)))
        desc["period_mm"] = round(p, 1)
    elif kind == "wood":
        base = hsv_bgr(rng.uniform(5, 22), rng.uniform(0.35, 0.75), rng.uniform(0.45, 0.85))
        dark = base * rng.uniform(0.45, 0.75)
        th = rng.uniform(0, np.pi)
        x = ta * np.cos(th) + tb * np.sin(th)
        y = -ta * np.sin(th) + tb * np.cos(th)
        n = fbm(rng, ta.shape, cell=max(150 / mpp, 4), octaves=3)
        p = rng.uniform(4, 14)
        rings = np.sin(2 * np.pi * (y + 6 * p * n + 3 * np.sin(x / rng.uniform(80, 400))) / p)
        t = 0.5 + 0.5 * rings
        t = t ** 3 * 0.8 + 0.2 * fbm(rng, ta.shape, cell=max(8 / mpp, 2), octaves=3)
        tex = mix(base, dark, t)
        if rng.uniform() < 0.5:  # planks
            pw = rng.uniform(80, 200)
            seam = np.abs(((y / pw) % 1.0) - 0.5) > 0.49
            tex[seam] *= 0.55
        c0 = base
    elif kind == "noise":
        cell = max(rng.uniform(20, 200) / mpp, 3)
        n = fbm(rng, ta.shape, cell=cell, octaves=5, gain=rng.uniform(0.4, 0.65))
        if rng.uniform() < 0.5:
            c1 = np.clip(c0 * rng.uniform(0.5, 0.8) + rng.normal(0, 15, 3), 0, 255)
        tex = mix(c0, c1, n)
    elif kind == "printed":
        paper = hsv_bgr(rng.uniform(0, 180), rng.uniform(0, 0.15), rng.uniform(0.75, 0.97))
        tex = np.empty(ta.shape + (3,), np.uint8)  # cv2 draws text on 8-bit images only
        tex[:] = np.uint8(np.rint(paper))
        c0 = paper
        for _ in range(int(rng.integers(4, 30))):
            col = random_colour(rng).tolist()
            cx, cy = rng.uniform(0, W), rng.uniform(0, H)
            r = rng.uniform(8, 120) / mpp
            shape = rng.integers(0, 4)
            if shape == 0:
                p0, p1 = (int(cx - r), int(cy - r * rng.uniform(0.3, 1.5))), (int(cx + r), int(cy + r))
                thick = -1 if rng.uniform() < 0.7 else max(int(3 / mpp), 1)
                cv2.rectangle(tex, p0, p1, col, thick, cv2.LINE_AA)
            elif shape == 1:
                cv2.circle(tex, (int(cx), int(cy)), int(r), col, -1 if rng.uniform() < 0.7 else 2,
                           cv2.LINE_AA)
            elif shape == 2:
                p1 = (int(cx + rng.normal(0, 3 * r)), int(cy + rng.normal(0, 3 * r)))
                cv2.line(tex, (int(cx), int(cy)), p1, col, max(int(rng.uniform(1, 6) / mpp), 1), cv2.LINE_AA)
            else:
                pts = (np.array([cx, cy]) + rng.normal(0, r, (int(rng.integers(3, 7)), 2))).astype(np.int32)
                cv2.fillPoly(tex, [pts], col, cv2.LINE_AA)
        text_marks(rng, tex, int(rng.integers(3, 25)), mpp)
        tex = tex.astype(np.float32)
    else:  # plain
        tex = np.empty(ta.shape + (3,), np.float32)
        tex[:] = c0
    desc["printed_part"] = None
    if rng.uniform() < (0.6 if kind == "printed" else 0.12):  # a flat picture of a part: floor, not truth
        name = target if target in models and rng.uniform() < 0.6 else str(rng.choice(models))
        mesh = load_model(name)
        uv = (rng.uniform(0.15, 0.85) * w, rng.uniform(0.15, 0.85) * h)
        at = ((a[int(uv[1]), int(uv[0])] - amin) / mpp, (b[int(uv[1]), int(uv[0])] - bmin) / mpp)
        size = mesh.diameter * rng.uniform(1.0, 2.8) / mpp  # poster-sized: looks as big as a real part
        col = random_colour(rng) if rng.uniform() < 0.6 else random_colour(rng, s=(0, 0.08))
        printed_part(rng, tex, mesh, size, at, col, light)
        desc["printed_part"] = name
    # mild large-scale unevenness, then onto the image
    uneven = fbm(rng, ta.shape, cell=max(300 / mpp, 4), octaves=2) - 0.5
    tex *= (1.0 + rng.uniform(0.02, 0.1) * uneven)[..., None]
    img = cv2.remap(tex, (a - amin) / np.float32(mpp), (b - bmin) / np.float32(mpp), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REFLECT)
    if kind == "plain":
        g = np.float32(rng.normal(0, 1, 2))
        uu, vv = np.meshgrid(np.linspace(-1, 1, w, dtype=np.float32), np.linspace(-1, 1, h, dtype=np.float32))
        img *= (1.0 + 0.08 * (g[0] * uu + g[1] * vv))[..., None]
    return img, depth, desc | {"mean_bgr": [round(float(x), 1) for x in np.asarray(c0)]}


# --- objects ------------------------------------------------------------------------------------

def shade_layer(mesh: Mesh, pose: Pose, K, w, h, colour, light, *, ambient=0.4, spec=0.15, shininess=30.0):
    """Render ``mesh`` shaded; ``None`` when nothing lands in the image. Arrays cover the render's ROI:
    ``colour`` (bh, bw, 3) mean over covered sub-samples, ``cov`` coverage, ``depth`` nearest
    sub-sample (inf when uncovered), ``origin`` = (v0, u0) in the image; ``mask`` / ``depth_mm``
    are the renderer's full-image ones (the ground-truth mask)."""
    r = render(mesh.V, mesh.F, pose, K, (w, h), supersample=SUPERSAMPLE)
    fss = r.face_id_ss
    if fss.size == 0 or not (fss >= 0).any():
        return None
    s = r.supersample
    nrm = r.face_normals_cam.astype(np.float64)
    ldir = np.asarray(light, float) / np.linalg.norm(light)
    view = -(pose.t_mm + pose.R @ mesh.centre)
    view /= np.linalg.norm(view)
    half = (ldir + view) / np.linalg.norm(ldir + view)
    lam = np.clip(nrm @ ldir, 0, None)
    hl = np.clip(nrm @ half, 0, None) ** shininess
    face_col = np.float32(colour)[None] * np.float32(ambient + (1 - ambient) * lam)[:, None] \
        + np.float32(255 * spec * hl)[:, None]
    m = fss >= 0
    col_ss = np.zeros(fss.shape + (3,), np.float32)
    col_ss[m] = face_col[fss[m]]
    cnt = _blocks(m, s).sum(axis=2)
    cov = cnt.astype(np.float32) / (s * s)
    colour_px = _blocks(col_ss, s).sum(axis=2) / np.maximum(cnt, 1)[..., None]
    depth = _blocks(r.depth_ss, s).min(axis=2)
    return {"colour": colour_px, "cov": cov, "depth": depth, "origin": (r.roi_ss[1] // s, r.roi_ss[0] // s),
            "mask": r.mask, "depth_mm": r.depth_mm, "render": r}


def _blocks(x, s):
    """(s bh, s bw, ...) -> (bh, bw, s * s, ...): each pixel's sub-samples."""
    bh, bw = x.shape[0] // s, x.shape[1] // s
    return x.reshape(bh, s, bw, s, *x.shape[2:]).swapaxes(1, 2).reshape(bh, bw, s * s, *x.shape[2:])


def relight(ly: dict, obj: dict, light, look: Look, smap: ShadowMap | None) -> None:
    """Replace a layer's colours by the realistic look's: smooth normals, shadows, highlight, gamma."""
    r, mesh, pose = ly["render"], obj["mesh"], obj["pose"]
    m, P, f, w = synth_light.surface_points(r, mesh.V, mesh.F, pose)
    n = synth_light.shading_normals(r, mesh.V, mesh.F, pose, f, w, look)
    lit = smap.lit(P, n) if smap is not None else np.ones(len(P))
    # the object's own highlight strength varies about the scene's
    lk = replace(look, specular=look.specular * float(obj["spec"]) / 0.16)
    col_ss = np.zeros(m.shape + (3,), np.float32)
    col_ss[m] = synth_light.radiance(obj["colour"], n, P, light, lit, lk)
    s = r.supersample
    cnt = _blocks(m, s).sum(axis=2)
    ly["colour"] = _blocks(col_ss, s).sum(axis=2) / np.maximum(cnt, 1)[..., None]


def floor_shadow(floor_depth: np.ndarray, K: np.ndarray, light, look: Look, smap: ShadowMap) -> np.ndarray:
    """(h, w) multiplier of the floor texture: the casters' shadows, a penumbra as wide as the light's
    angular radius makes it at the median blocker-to-floor distance."""
    h, w = floor_depth.shape
    q = 2  # half resolution: the penumbra is blurred anyway
    v, u = np.mgrid[0:h:q, 0:w:q].astype(np.float64)
    z = floor_depth[::q, ::q].astype(np.float64)
    P = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=-1).reshape(-1, 3)
    n = floor_normal(floor_depth, K)
    lit = smap.lit(P, np.broadcast_to(n, P.shape)).reshape(z.shape).astype(np.float32)
    if (lit < 1).any() and look.light_radius_deg > 0:
        gap = float(np.median(smap.blocker_gap_mm(P[lit.reshape(-1) < 1])))
        sigma = gap * np.tan(np.radians(look.light_radius_deg)) * K[0, 0] / float(np.median(z)) / q
        if sigma > 0.3:
            lit = cv2.GaussianBlur(lit, (0, 0), sigma)
    lit = cv2.resize(lit, (w, h), interpolation=cv2.INTER_LINEAR)
    lam = float(n @ (np.asarray(light, float) / np.linalg.norm(light)))
    return synth_light.floor_factor(lam, np.clip(lit, 0, 1), look).astype(np.float32)


def floor_normal(floor_depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The floor plane's unit normal (camera frame) facing the camera, from three of its pixels."""
    h, w = floor_depth.shape
    pts = []
    for u, v in ((0, 0), (w - 1, 0), (0, h - 1)):
        z = float(floor_depth[v, u])
        pts.append(np.array([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z]))
    n = np.cross(pts[1] - pts[0], pts[2] - pts[0])
    n /= np.linalg.norm(n)
    return -n if n @ pts[0] > 0 else n


def sample_distractor(rng, K, w, h, models: list[str], target: str | None, near=None) -> dict:
    """A random distractor; ``near = (uv, z_max)`` puts it in front of the target, around pixel uv."""
    others = [m for m in models if m != target]
    u = rng.uniform()
    if others and u < 0.22:
        kind = str(rng.choice(others))
        mesh = load_model(kind)
    else:
        kind = str(rng.choice(["box", "cylinder", "sphere"], p=[0.45, 0.4, 0.15]))
        mesh = primitive(kind)
        if kind == "box":
            scale = rng.uniform(25, 150, 3)
        elif kind == "cylinder":
            r = rng.uniform(12, 50)
            scale = np.array([r, r, rng.uniform(40, 220)])
        else:
            scale = np.full(3, rng.uniform(15, 60))
        mesh = _mesh(mesh.V * scale, mesh.F)
    if near is not None:
        uv, zmax = near
        z = rng.uniform(DIST_RANGE_MM[0], max(zmax, DIST_RANGE_MM[0] + 1))
        uv = np.asarray(uv) + rng.normal(0, 0.05 * w, 2)
    else:
        z = rng.uniform(*DIST_RANGE_MM)
        uv = (rng.uniform(-0.05, 1.05) * w, rng.uniform(-0.05, 1.05) * h)
    pose = pose_at_pixel(mesh, random_rotation(rng), uv, z, K)
    return {"kind": kind, "mesh": mesh, "pose": pose, "colour": random_colour(rng),
            "ambient": rng.uniform(0.3, 0.5), "spec": rng.uniform(0.0, 0.3)}


# Target visible fractions drawn by ``--occlusion clutter``: a quarter of the targets keep the scene's
# own occlusion (mostly none), the rest get an occluder hiding them down to U(0.5, 0.9) visible, so the
# set's visible fractions spread like the Blender clutter sets' (0.5-1.0, median 0.72-0.77).
OCCLUDE_P = 0.75
OCCLUDE_VISIBLE = (0.5, 0.9)
OCCLUDER_BISECT = 8  # steps of the bisection on the occluder's offset from the target's centre


def _visible(full: np.ndarray, t_depth: np.ndarray, layers) -> np.ndarray:
    occ = np.full(full.shape, np.inf, np.float32)
    for ly in layers:
        np.minimum(occ, np.where(ly["mask"], ly["depth_mm"], np.inf), out=occ)
    return full & (t_depth <= occ)


def add_occluder(orng, K, w, h, models: list[str], target: dict, t_layer: dict, full: np.ndarray,
                 keep: list, light) -> tuple[dict, dict] | None:
    """An object in front of the target hiding it down to a visible fraction drawn from
    ``OCCLUDE_VISIBLE`` (``None``: the target stays as it is, or is already hidden that much).

    The occluder (a box, cylinder, sphere or another CAD part, random colour) sits between the camera
    and the target's nearest point, about the target's projected size; its projected centre moves out
    from the target's centroid along a random direction, and a bisection on that offset meets the
    visible fraction (the renderer's own masks, as ``visible_fraction`` counts it). Only ``orng`` is
    drawn from: the scene's own random stream, hence the rest of the scene, is unchanged."""
    if orng.uniform() >= OCCLUDE_P:
        return None
    goal = orng.uniform(*OCCLUDE_VISIBLE)
    n_full = max(int(full.sum()), 1)
    now = float(_visible(full, t_layer["depth_mm"], [ly for _, ly in keep]).sum()) / n_full
    if now <= goal:
        return None
    vv, uu = np.nonzero(full)
    centre = np.array([uu.mean(), vv.mean()])
    radius_px = float(np.sqrt(n_full / np.pi))
    z_near = float(t_layer["depth_mm"][full].min())
    z_o = orng.uniform(0.55, 0.9) * z_near
    others = [m for m in models if m != target["kind"]]
    kind = str(orng.choice(others)) if others and orng.uniform() < 0.2 else \
        str(orng.choice(["box", "cylinder", "sphere"], p=[0.45, 0.4, 0.15]))
    size_mm = 2.0 * radius_px * z_o / K[0, 0] * orng.uniform(0.7, 1.5)  # ~ the target's projected size
    if kind in ("box", "cylinder", "sphere"):
        base = primitive(kind)
        aspect = {"box": orng.uniform(0.4, 1.6, 3), "cylinder": np.r_[np.full(2, orng.uniform(0.3, 0.7)),
                                                                       orng.uniform(1.0, 2.5)],
                  "sphere": np.full(3, 0.5)}[kind]
        mesh = _mesh(base.V * aspect * size_mm, base.F)
    else:
        base = load_model(kind)
        mesh = _mesh(base.V * (size_mm / base.diameter), base.F)
    R = random_rotation(orng)
    ang = orng.uniform(0, 2 * np.pi)
    direction = np.array([np.cos(ang), np.sin(ang)])
    others_layers = [ly for _, ly in keep]

    def visible_at(offset):
        pose = pose_at_pixel(mesh, R, centre + offset * radius_px * direction, z_o, K)
        r = render(mesh.V, mesh.F, pose, K, (w, h), supersample=SUPERSAMPLE)
        ly = {"mask": r.mask, "depth_mm": r.depth_mm}
        return float(_visible(full, t_layer["depth_mm"], others_layers + [ly]).sum()) / n_full, pose

    lo, hi = 0.0, 4.0  # offsets in target radii: more offset, more of the target visible
    vis_lo, pose = visible_at(lo)
    if vis_lo > goal:  # even centred the occluder hides too little: take it centred
        best = pose
    else:
        best = None
        for _ in range(OCCLUDER_BISECT):
            mid = 0.5 * (lo + hi)
            vis, pose = visible_at(mid)
            if vis < goal:
                lo = mid
            else:
                hi, best = mid, pose
        if best is None:
            best = visible_at(hi)[1]
    d = {"kind": kind, "mesh": mesh, "pose": best, "colour": random_colour(orng),
         "ambient": orng.uniform(0.3, 0.5), "spec": orng.uniform(0.0, 0.3), "occluder": True}
    ly = shade_layer(mesh, best, K, w, h, d["colour"], light, ambient=d["ambient"], spec=d["spec"])
    return (d, ly) if ly is not None else None


# --- the scene ----------------------------------------------------------------------------------

def scene(seed: int, index: int, w: int, h: int, models: list[str], *, absent_frac: float = 0.25,
          min_visible: float = 0.5, omit_target: bool = False, clean: bool = False,
          look: str = "flat", occlusion: str = "none") -> dict:
    """One scene: ``{"image": (h, w, 3) uint8 BGR, "gt": dict, "visible_mask", "full_mask",
    "target_shadow"}``. ``omit_target`` draws the very same scene without painting the target (nor
    its shadow); ``clean`` skips blur, noise and JPEG (both for tests).

    ``look="real"``: the same scene (same geometry, colours and floor) shaded like a renderer: smooth
    normals within a crease angle, Blinn-Phong highlights, a directional light whose shadow map casts
    shadows onto the floor, onto other objects and onto the part itself, ambient light, gamma, and the
    renderer's soft pixel filter (``synth_light``; its parameters are drawn from an rng of their own).
    ``target_shadow`` is then None.

    ``occlusion="clutter"``: after the scene's own distractors, an occluder is put in front of the target
    (``add_occluder``, from an rng of its own) so the visible fractions spread like the Blender clutter
    sets'; ``"none"`` leaves the scene as it always was."""
    rng = np.random.default_rng([seed, index])
    lk = sample_look(np.random.default_rng([seed, index, 2])) if look == "real" else None
    absent = bool(rng.uniform() < absent_frac)
    model = str(rng.choice(models))
    K = sample_K(rng, w, h)
    el, az = np.radians(rng.uniform(20, 70)), rng.uniform(0, 2 * np.pi)
    light = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el)])  # towards the light
    floor, floor_depth, floor_desc = make_floor(rng, K, w, h, models, light, model)
    floor_mean = np.float32(floor.reshape(-1, 3).mean(axis=0))

    target = None
    if not absent:
        mesh = load_model(model)
        m = CENTRE_MARGIN
        uv_t = (rng.uniform(m, 1 - m) * w, rng.uniform(m, 1 - m) * h)
        z_t = rng.uniform(*DIST_RANGE_MM)
        colour, colour_mode = part_colour(rng, floor_mean)
        pose_t = pose_at_pixel(mesh, random_rotation(rng), uv_t, z_t, K)
        target = {"kind": model, "mesh": mesh, "pose": pose_t, "colour": colour,
                  "ambient": rng.uniform(0.3, 0.5), "spec": rng.uniform(0.02, 0.3)}
        t_layer = shade_layer(mesh, target["pose"], K, w, h, colour, light, ambient=target["ambient"],
                              spec=target["spec"])
        full = t_layer["mask"]

    n_d = int(rng.integers(N_DISTRACTORS[0], N_DISTRACTORS[1] + 1))
    occlude = target is not None and z_t > 420 and rng.uniform() < 0.65
    visible = vis_frac = None
    for attempt in range(MAX_TRIES):
        dist = [sample_distractor(rng, K, w, h, models, model,
                                  near=(uv_t, z_t - 80) if occlude and i == 0 else None) for i in range(n_d)]
        layers = [shade_layer(d["mesh"], d["pose"], K, w, h, d["colour"], light, ambient=d["ambient"],
                              spec=d["spec"]) for d in dist]
        keep = [(d, ly) for d, ly in zip(dist, layers, strict=True) if ly is not None]
        if target is None:
            break
        occ = np.full((h, w), np.inf, np.float32)
        for _d, ly in keep:
            np.minimum(occ, np.where(ly["mask"], ly["depth_mm"], np.inf), out=occ)
        visible = full & (t_layer["depth_mm"] <= occ)
        vis_frac = float(visible.sum()) / max(int(full.sum()), 1)
        if vis_frac >= min_visible:
            break
        occlude = occlude and attempt < MAX_TRIES // 2  # keep trying a partial occlusion for a while
    else:  # no luck: drop the distractors that hide the part
        keep = [(d, ly) for d, ly in keep if not (ly["mask"] & full).any()]
        occ = np.full((h, w), np.inf, np.float32)
        for _d, ly in keep:
            np.minimum(occ, np.where(ly["mask"], ly["depth_mm"], np.inf), out=occ)
        visible = full & (t_layer["depth_mm"] <= occ)
        vis_frac = float(visible.sum()) / max(int(full.sum()), 1)
    n_occluders = 0
    if occlusion == "clutter" and target is not None:
        added = add_occluder(np.random.default_rng([seed, index, 3]), K, w, h, models, target, t_layer, full,
                             keep, light)
        if added is not None:
            keep.append(added)
            n_occluders = 1
            visible = _visible(full, t_layer["depth_mm"], [ly for _, ly in keep])
            vis_frac = float(visible.sum()) / max(int(full.sum()), 1)

    # soft cast shadows on the floor (quarter resolution), the target's kept apart for tests
    q = 4
    hq, wq = (h + q - 1) // q, (w + q - 1) // q
    shadow_dir = np.array([-light[0], -light[1]]) / max(np.hypot(light[0], light[1]), 1e-6)
    shadow_gain, shadow_blur = rng.uniform(0.25, 0.55), rng.uniform(2.0, 6.0)

    def shadow_of(ly, z):
        Zf = floor_desc["dist_mm"]
        off = shadow_dir * (Zf - z) * rng.uniform(0.12, 0.25) * K[0, 0] / Zf
        (v0, u0) = ly["origin"]
        M = np.float32([[1.0 / q, 0, (u0 + off[0]) / q], [0, 1.0 / q, (v0 + off[1]) / q]])
        return cv2.warpAffine(ly["cov"], M, (wq, hq), flags=cv2.INTER_LINEAR)

    sh_d = np.zeros((hq, wq), np.float32)
    for d, ly in keep:
        np.maximum(sh_d, shadow_of(ly, float(d["pose"].t_mm[2])), out=sh_d)
    sh_t = shadow_of(t_layer, z_t) if target is not None else np.zeros_like(sh_d)

    def soft(sm):
        sm = cv2.GaussianBlur(sm, (0, 0), shadow_blur)
        return cv2.resize(sm, (w, h), interpolation=cv2.INTER_LINEAR)[:h, :w]

    sh_all = np.maximum(sh_d, sh_t) if target is not None and not omit_target else sh_d
    img = floor * (1.0 - shadow_gain * np.clip(soft(sh_all), 0, 1))[..., None]
    target_shadow = soft(sh_t)
    if lk is not None:  # the shadow map replaces the shifted silhouettes, under the look's light
        light = np.asarray(lk.light)
        objs = [d for d, _ in keep] + ([target] if target is not None and not omit_target else [])
        smap = ShadowMap([(o["mesh"].V, o["mesh"].F, o["pose"]) for o in objs], light) if lk.shadows else None
        for o, ly in list(keep) + ([(target, t_layer)] if target is not None and not omit_target else []):
            relight(ly, o, light, lk, smap)
        img = floor * (floor_shadow(floor_depth, K, light, lk, smap)[..., None] if smap is not None else 1.0)
        target_shadow = None

    # composite far to near with a per-pixel z-test, coverage as alpha
    zbuf = np.full((h, w), np.inf, np.float32)
    painted = list(keep) + ([(target, t_layer)] if target is not None and not omit_target else [])
    for _d, ly in sorted(painted, key=lambda p: -float(p[0]["pose"].t_mm[2])):
        (v0, u0), (bh, bw) = ly["origin"], ly["cov"].shape
        zr = zbuf[v0:v0 + bh, u0:u0 + bw]
        win = (ly["cov"] > 0) & (ly["depth"] < zr)
        a = np.where(win, ly["cov"], 0.0)[..., None]
        sub = img[v0:v0 + bh, u0:u0 + bw]
        sub[:] = sub * (1 - a) + ly["colour"] * a
        zr[win] = ly["depth"][win]

    # light: gain, linear gradient, a soft dark blob
    uu, vv = np.meshgrid(np.linspace(-1, 1, w, dtype=np.float32), np.linspace(-1, 1, h, dtype=np.float32))
    g = rng.normal(0, 1, 2)
    lightmap = rng.uniform(0.75, 1.2) * (1 + rng.uniform(0, 0.2) * (g[0] * uu + g[1] * vv) / np.hypot(*g))
    bx, by, br = rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.3, 0.9)
    lightmap = lightmap * (1 - rng.uniform(0, 0.3) * np.exp(-((uu - bx) ** 2 + (vv - by) ** 2) / br ** 2))
    img = img * lightmap[..., None]
    post = np.random.default_rng([seed, index, 1])  # independent of what the scene contains
    blur = float(post.uniform(0.5, 1.2)) if post.uniform() < 0.25 else None
    sigma = float(post.uniform(1.0, 4.0))
    jpeg = int(post.integers(70, 93)) if post.uniform() < 0.3 else None
    if lk is not None:
        blur = max(blur or 0.0, lk.blur_px)
    if not clean:
        if blur:
            img = cv2.GaussianBlur(img, (0, 0), blur)
        img = img + np.float32(sigma) * post.standard_normal(img.shape, dtype=np.float32)
    img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    if jpeg and not clean:
        img = cv2.imdecode(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, jpeg])[1], cv2.IMREAD_COLOR)

    gt = {"model": model, "K": K.tolist(), "width": w, "height": h, "symmetry": SYMMETRY.get(model, "none")}
    if target is None:
        gt |= {"absent": True, "visible_fraction": 0.0}
    else:
        pose = target["pose"]
        gt |= {"R": pose.R.tolist(), "t_mm": pose.t_mm.tolist(), "visible_fraction": round(vis_frac, 4),
               "euler_xyz_deg": pose.euler_xyz_deg().tolist()}
        if gt["symmetry"] == "y":
            gt["axis_alpha_gamma_deg"] = list(axis_alpha_gamma_deg(pose.R @ np.array([0.0, 1.0, 0.0])))
        gt |= {"mask_px": int(full.sum()), "visible_px": int(visible.sum()), "colour_mode": colour_mode}
    gt |= {"noise_sigma": round(sigma, 3), "jpeg_quality": jpeg, "blur_sigma": blur and round(blur, 3),
           "n_distractors": len(keep), "distractors": [d["kind"] for d, _ in keep], "floor": floor_desc}
    if occlusion != "none":
        gt["occluders_added"] = n_occluders
    if lk is not None:
        gt["look"] = {k: round(v, 3) if isinstance(v, float) else v for k, v in vars(lk).items()} | {
            "light": [round(x, 4) for x in lk.light]}
    return {"image": img, "gt": gt, "visible_mask": visible, "target_shadow": target_shadow,
            "full_mask": full if target is not None else None}


def model_meta(name: str) -> dict:
    import trimesh

    m = trimesh.load(MODELS_DIR / f"{name}.stl", force="mesh")
    lo, hi = m.bounds
    return {"file": f"{name}.stl", "symmetry": SYMMETRY.get(name, "none"), "vertices": len(m.vertices),
            "faces": len(m.faces), "extents_mm": [round(float(x), 3) for x in hi - lo],
            "bounds_mm": [[round(float(x), 3) for x in lo], [round(float(x), 3) for x in hi]],
            "diameter_mm": round(float(np.linalg.norm(hi - lo)), 3), "watertight": bool(m.is_watertight)}


def generate(out: Path, n: int, seed: int, size: tuple[int, int], models: list[str], absent_frac: float,
             min_visible: float, quiet: bool = False, look: str = "flat", occlusion: str = "none") -> dict:
    w, h = size
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "models").mkdir(exist_ok=True)
    for m in models:
        shutil.copyfile(MODELS_DIR / f"{m}.stl", out / "models" / f"{m}.stl")
    digits = max(4, len(str(n)))
    t0 = time.perf_counter()
    n_absent, vis = 0, []
    with open(out / "gt.jsonl", "w") as f:
        for i in range(1, n + 1):
            s = scene(seed, i, w, h, models, absent_frac=absent_frac, min_visible=min_visible, look=look,
                      occlusion=occlusion)
            name = f"images/{i:0{digits}d}.png"
            cv2.imwrite(str(out / name), s["image"])
            f.write(json.dumps({"image": name} | s["gt"]) + "\n")
            if s["gt"].get("absent"):
                n_absent += 1
            else:
                vis.append(s["gt"]["visible_fraction"])
            if not quiet and (i % 10 == 0 or i == n):
                el = time.perf_counter() - t0
                print(f"  {i}/{n}  {el / i:.2f} s/image", flush=True)
    dt = (time.perf_counter() - t0) / max(n, 1)
    meta = {"set": out.name, "generator": "bench/synth_scenes.py", "n_images": n, "seed": seed,
            "size": [w, h], "absent_frac": absent_frac, "min_visible": min_visible, "look": look,
            **({"occlusion": occlusion} if occlusion != "none" else {}),
            "visible_fraction": "target pixels not occluded / target pixels rendered alone, inside the image",
            "models": {m: model_meta(m) for m in models},
            "render_mean_s_per_image": {"total_s": round(dt, 3)}}
    (out / "meta.json").write_text(json.dumps(meta, indent=1))
    return {"n": n, "absent": n_absent, "s_per_image": dt,
            "visible_mean": float(np.mean(vis)) if vis else float("nan")}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out_dir", type=Path, help="output set folder, outside the repo (e.g. /tmp/synth)")
    ap.add_argument("--n", type=int, default=300)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--size", default="1280x960", help="WxH; 640x480 uses Linemod-Occluded's camera")
    ap.add_argument("--absent-frac", type=float, default=0.25)
    ap.add_argument("--min-visible", type=float, default=0.5)
    ap.add_argument("--models", default=",".join(DEFAULT_MODELS))
    ap.add_argument("--models-dir", type=Path, default=None,
                    help="where the models' STL files are (default: the shared data's models/; e.g. "
                         "../shared/data/lmo_dev/models for Linemod-Occluded's objects)")
    ap.add_argument("--look", choices=("flat", "real"), default="flat",
                    help="flat: Lambert per face (the older sets); real: smooth normals, highlights, "
                         "shadow maps, gamma (bench/synth_light.py)")
    ap.add_argument("--occlusion", choices=("none", "clutter"), default="none",
                    help="clutter: an occluder in front of most targets, visible fractions spread like the "
                         "Blender clutter sets' (0.5-1.0, median ~0.75); none: the scenes as before")
    args = ap.parse_args(argv)
    if args.models_dir is not None:
        global MODELS_DIR
        MODELS_DIR = args.models_dir
    w, h = (int(x) for x in args.size.lower().split("x"))
    models = [m.strip() for m in args.models.split(",") if m.strip()]
    r = generate(args.out_dir, args.n, args.seed, (w, h), models, args.absent_frac, args.min_visible,
                 look=args.look, occlusion=args.occlusion)
    print(f"synth_scenes: {r['n']} images ({r['absent']} absent) {w}x{h} seed {args.seed} -> {args.out_dir}, "
          f"{r['s_per_image']:.2f} s/image, mean visible fraction {r['visible_mean']:.2f}")


if __name__ == "__main__":
    main()
