"""Scenes of a part resting on a table among look-alike shapes, drawn by the project's rasteriser, with
their exact truth: what a part's plane operating point is calibrated on (``pipeline/plane_calibration``).

A scene: a camera 20-50 deg from straight down, its distance putting the part's diameter at 70-170 px
(held inside the distance range a request without one searches, so a small part appears smaller);
2-5 copies of the part in its resting poses (the bank's families, by their probability), any spin,
and 3-7 distractors on a plain, noisy, grained or checked table: cylinders, bars, rings, discs and plates
sized like the part, and the part itself scaled, or stretched along the table (a short screw's wrong
poses lie on long ones, a nozzle's on larger nozzles); and 0-2 more copies lying on top of those
objects, flat or tilted (a pose on the table fits a stacked copy's outline at the wrong height and
turn). Each object has its own material: matte or shiny (Blinn-Phong highlights with a reflected sky
gradient for metal), any colour, one light. Copies and distractors may touch and hide each other.
Everything is drawn from the ``rng`` given.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import trimesh

from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, Rz
from service.vision.geometry.plane import Plane
from service.vision.geometry.render import render
from service.vision.pipeline.policy import DEFAULT_DISTANCE_RANGE_MM

SIZE = (640, 480)
INTR = Intrinsics(600.0, 600.0, 319.5, 239.5)
TILT_DEG = (20.0, 50.0)
PART_PX = (70.0, 170.0)  # the part's diameter in the image at the scene's centre
# the scene's centre lies this far in, from each end of the default range: copies lie nearer and farther
DISTANCE_MM = (1.1 * DEFAULT_DISTANCE_RANGE_MM[0], 0.8 * DEFAULT_DISTANCE_RANGE_MM[1])
COPIES = (2, 5)
DISTRACTORS = (3, 8)
# objects lie within this many part diameters (times the square root of their number) of the scene's
# centre, a pile's density, and within the image's middle two thirds
SPREAD_DIAMETERS = 1.0
# two objects' footprint circles may overlap by this share of their radii: touching, hiding each other
OVERLAP = 0.3
STACKED = (0, 2)  # copies lying on top of another object
# a stacked copy lies on its object turned by up to this: flat too, as a clamp on an air diverter's disc lies
# (a pose on the table under it fits its outline a few mm too low)
STACKED_TILT_DEG = (0.0, 25.0)
STACKED_SINK = (0.5, 0.9)  # the stacked copy's lowest point at this share of the object's height under it
# a part stretched along an axis standing up more than this (the axis's share of the table's normal) is
# stretched along its flattest axis instead (``_along_table``)
MAX_STRETCH_UP = 0.5
SHINY_SHARE = 0.5


@dataclass(frozen=True)
class Scene:
    bgr: np.ndarray  # (h, w, 3) uint8
    intr: Intrinsics
    plane: Plane
    poses: list[Pose]  # T_cam_obj of every copy
    visible: list[float]  # each copy's visible share of its whole silhouette


@dataclass(frozen=True)
class _Solid:
    vertices_mm: np.ndarray  # resting frame: lowest point at z = 0, centred on x = y = 0
    faces: np.ndarray


def _distractor(rng: np.random.Generator, bank) -> _Solid:
    """A look-alike shape about the part's size, resting on the plane (z up)."""
    d = float(bank.diameter_mm) * rng.uniform(0.3, 1.0)
    kind = rng.choice(["cylinder_lying", "cylinder_standing", "bar", "ring", "disc", "plate", "scaled_part",
                       "stretched_part"])
    if kind in ("scaled_part", "stretched_part"):
        return _part_alike(rng, bank, kind == "stretched_part")
    if kind == "cylinder_lying":
        m = trimesh.creation.cylinder(radius=d * rng.uniform(0.04, 0.2), height=d, sections=32)
        m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    elif kind == "cylinder_standing":
        m = trimesh.creation.cylinder(radius=d * rng.uniform(0.1, 0.4), height=d * rng.uniform(0.1, 0.6),
                                      sections=32)
    elif kind == "bar":
        m = trimesh.creation.box([d, d * rng.uniform(0.08, 0.3), d * rng.uniform(0.03, 0.2)])
    elif kind == "ring":
        r = d * rng.uniform(0.2, 0.5)
        m = trimesh.creation.annulus(r_min=r * rng.uniform(0.4, 0.8), r_max=r,
                                     height=d * rng.uniform(0.05, 0.3), sections=32)
    elif kind == "disc":
        m = trimesh.creation.cylinder(radius=d * rng.uniform(0.15, 0.5), height=d * 0.05, sections=32)
    else:
        m = trimesh.creation.box([d, d * rng.uniform(0.4, 1.0), d * rng.uniform(0.02, 0.1)])
    V = np.asarray(m.vertices, float)
    V -= np.array([*V[:, :2].mean(axis=0), V[:, 2].min()])
    return _Solid(V, np.asarray(m.faces, np.int64))


def _part_alike(rng: np.random.Generator, bank, stretched: bool) -> _Solid:
    """The part in one of its resting poses, scaled by 0.6-0.8 or 1.25-1.6 (or along one of its axes
    lying along the table only, by 0.5-0.75 or 1.3-2: ``_along_table``): a look-alike no true pose of it
    explains."""
    low, high = ((0.5, 0.75), (1.3, 2.0)) if stretched else ((0.6, 0.8), (1.25, 1.6))
    s = rng.uniform(*(low if rng.uniform() < 0.5 else high))
    # (drawn in the order the draws had before the axis was kept along the table: a scaled look-alike,
    # and a stretched one whose axis already lay along it, come out as they did)
    axis = int(rng.integers(0, 3)) if stretched else 0
    prob = np.asarray(bank.rest_probability, float)
    R_rest = np.asarray(bank.R_rest_obj[int(rng.choice(len(prob), p=prob / prob.sum()))], float)
    scale = np.ones(3)
    if stretched:
        scale[_along_table(R_rest, axis)] = s
    else:
        scale[:] = s
    V = (np.asarray(bank.vertices_mm, float) * scale) @ R_rest.T
    V -= np.array([*V[:, :2].mean(axis=0), V[:, 2].min()])
    return _Solid(V, np.asarray(bank.faces, np.int64))


def _along_table(R_rest_obj: np.ndarray, axis: int) -> int:
    """``axis`` (an object axis) if it lies along the table at the resting pose ``R_rest_obj``, else the
    object axis lying flattest: a part stretched in its height keeps its outline from above (a thinner
    allen key's), it is the part to a camera, not a look-alike its agreement must stay under."""
    up = np.abs(R_rest_obj[2])  # each object axis's share of the table's normal
    return axis if up[axis] <= MAX_STRETCH_UP else int(np.argmin(up))


def _camera(rng: np.random.Generator, distance_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(R_cam_world, t_cam_world): world = the table (z up, z = 0), the optical axis meeting its origin."""
    a = np.radians(rng.uniform(*TILT_DEG))
    z_c = np.array([0.0, np.sin(a), -np.cos(a)])
    x_c = np.array([1.0, 0.0, 0.0])
    R = np.stack([x_c, np.cross(z_c, x_c), z_c]) @ Rz(rng.uniform(0.0, 360.0)).T
    return R, -R @ (-distance_mm * (R.T @ np.array([0.0, 0.0, 1.0])))


def _placed(rng: np.random.Generator, V_rest: np.ndarray, spread_mm: float, taken: list[np.ndarray]
            ) -> tuple[np.ndarray, np.ndarray] | None:
    """(R_world_obj-ish spin, t_world) placing ``V_rest`` at a random spot and spin whose footprint circle
    overlaps none of ``taken`` (each (x, y, r)), or None after a few tries."""
    r = float(np.linalg.norm(V_rest[:, :2] - V_rest[:, :2].mean(axis=0), axis=1).max())
    for _ in range(60):
        xy = rng.uniform(-spread_mm, spread_mm, 2)
        if all(np.hypot(*(xy - c[:2])) > (1.0 - OVERLAP) * (r + c[2]) for c in taken):
            taken.append(np.array([xy[0], xy[1], r]))
            spin = Rz(rng.uniform(0.0, 360.0))
            c = V_rest @ spin.T
            return spin, np.array([xy[0], xy[1], 0.0]) - np.array([*c[:, :2].mean(axis=0), c[:, 2].min()])
    return None


def _material(rng: np.random.Generator) -> dict:
    shiny = rng.uniform() < SHINY_SHARE
    colour = rng.uniform(0.15, 0.95, 3) if rng.uniform() < 0.5 else np.full(3, rng.uniform(0.2, 0.95))
    return {"colour": colour * 255.0, "diffuse": rng.uniform(0.2, 0.5) if shiny else rng.uniform(0.6, 0.95),
            "specular": rng.uniform(0.5, 1.0) if shiny else rng.uniform(0.0, 0.15),
            "shininess": rng.uniform(20.0, 120.0) if shiny else rng.uniform(5.0, 20.0),
            "sky": rng.uniform(0.3, 0.8) if shiny else 0.0}


def _table(rng: np.random.Generator, R_cw: np.ndarray, t_cw: np.ndarray) -> np.ndarray:
    """(h, w, 3) float table colours, the pattern fixed on the table (so foreshortened)."""
    w, h = SIZE
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    rays = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones_like(u, float)], -1)
    n = R_cw[:, 2]
    lam = (n @ t_cw) / np.minimum(rays @ n, -1e-6)
    p = (lam[..., None] * rays - t_cw) @ R_cw  # table coordinates, mm
    base = rng.uniform(40.0, 200.0, 3)
    kind = rng.choice(["plain", "noise", "grain", "checker"])
    if kind == "plain":
        t = np.zeros((h, w))
    elif kind == "noise":
        cell = rng.uniform(3.0, 20.0)
        noise = rng.normal(0.0, 1.0, (96, 96)).astype(np.float32)
        gx = np.clip(p[..., 0] / cell + 48, 0, 95).astype(np.float32)
        gy = np.clip(p[..., 1] / cell + 48, 0, 95).astype(np.float32)
        t = cv2.remap(noise, gx, gy, cv2.INTER_CUBIC) * 0.5
    elif kind == "grain":
        a = rng.uniform(0.0, np.pi)
        s = p[..., 0] * np.cos(a) + p[..., 1] * np.sin(a)
        t = np.sin(s / rng.uniform(1.0, 4.0) + 2.0 * np.sin(s / 37.0 + p[..., 0] / 91.0))
    else:
        cell = rng.uniform(5.0, 30.0)
        t = ((np.floor(p[..., 0] / cell) + np.floor(p[..., 1] / cell)) % 2) * 2.0 - 1.0
    contrast = rng.uniform(0.05, 0.3) * base.mean()
    return base + contrast * t[..., None]


def _shade(normals: np.ndarray, view: np.ndarray, light: np.ndarray, m: dict) -> np.ndarray:
    """(N, 3) colours of surface points with unit ``normals`` seen along unit ``view`` (towards the eye)."""
    lam = np.clip(normals @ light, 0.0, 1.0)
    half = light + view
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    spec = np.clip(np.einsum("ij,ij->i", normals, half), 0.0, 1.0) ** m["shininess"]
    sky = 0.5 + 0.5 * normals[:, 1] * -1.0  # surfaces turned up (camera -y) reflect a brighter sky
    c = m["colour"] * (0.15 + m["diffuse"] * lam)[:, None]
    return c + 255.0 * (m["specular"] * spec + m["sky"] * sky * 0.4)[:, None]


def scene(bank, rng: np.random.Generator) -> Scene:
    """One scene of ``bank``'s part (a ``TemplateBank``: mesh, diameter, resting poses)."""
    V = np.asarray(bank.vertices_mm, float)
    F = np.asarray(bank.faces, np.int64)
    diameter = float(bank.diameter_mm)
    distance = float(np.clip(INTR.fx * diameter / rng.uniform(*PART_PX), *DISTANCE_MM))
    R_cw, t_cw = _camera(rng, distance)
    n_copies = int(rng.integers(COPIES[0], COPIES[1] + 1))
    n_distractors = int(rng.integers(DISTRACTORS[0], DISTRACTORS[1] + 1))
    spread = min(0.35 * distance, SPREAD_DIAMETERS * diameter * np.sqrt(n_copies + n_distractors))
    prob = np.asarray(bank.rest_probability, float)
    prob = prob / prob.sum()
    taken: list[np.ndarray] = []
    solids: list[tuple[np.ndarray, np.ndarray, bool]] = []  # (V_cam, F, is_copy)
    poses: list[Pose] = []
    for _ in range(n_copies):
        R_rest = np.asarray(bank.R_rest_obj[int(rng.choice(len(prob), p=prob))], float)
        placed = _placed(rng, V @ R_rest.T, spread, taken)
        if placed is not None:
            spin, t_w = placed
            pose = Pose(R_cw @ spin @ R_rest, R_cw @ t_w + t_cw)
            poses.append(pose)
            solids.append((pose.apply(V), F, True))
    for _ in range(n_distractors):
        d = _distractor(rng, bank)
        placed = _placed(rng, d.vertices_mm, spread, taken)
        if placed is not None:
            spin, t_w = placed
            solids.append(((d.vertices_mm @ spin.T + t_w) @ R_cw.T + t_cw, d.faces, False))
    for _ in range(int(rng.integers(STACKED[0], STACKED[1] + 1))):
        under = (solids[int(rng.integers(0, len(solids)))][0] - t_cw) @ R_cw  # table frame
        R_wo = _tilt(rng) @ Rz(rng.uniform(0.0, 360.0)) @ np.asarray(
            bank.R_rest_obj[int(rng.choice(len(prob), p=prob))], float)
        q = V @ R_wo.T
        top = float(under[:, 2].max()) * rng.uniform(*STACKED_SINK)
        xy = under[:, :2].mean(axis=0) + rng.uniform(-0.2, 0.2, 2) * float(np.ptp(under[:, :2], axis=0).max())
        t_w = np.array([*xy, top]) - np.array([*q[:, :2].mean(axis=0), q[:, 2].min()])
        pose = Pose(R_cw @ R_wo, R_cw @ t_w + t_cw)
        poses.append(pose)
        solids.append((pose.apply(V), F, True))
    return _drawn(rng, solids, poses, V, F, R_cw, t_cw)


def _tilt(rng: np.random.Generator) -> np.ndarray:
    """A turn by ``STACKED_TILT_DEG`` about a random horizontal axis (Rodrigues)."""
    a = rng.uniform(0.0, 2.0 * np.pi)
    k = np.array([np.cos(a), np.sin(a), 0.0])
    th = np.radians(rng.uniform(*STACKED_TILT_DEG))
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(th) * K + (1.0 - np.cos(th)) * K @ K


def _drawn(rng, solids, poses, V, F, R_cw, t_cw) -> Scene:
    Vs = np.concatenate([s[0] for s in solids])
    offsets = np.cumsum([0] + [len(s[0]) for s in solids])
    Fs = np.concatenate([s[1] + offsets[k] for k, s in enumerate(solids)])
    face_of = np.cumsum([0] + [len(s[1]) for s in solids])
    eye = Pose(np.eye(3), np.zeros(3))
    s = 2
    r = render(Vs, Fs, eye, INTR.K, SIZE, supersample=s)
    w, h = SIZE
    img = np.repeat(np.repeat(_table(rng, R_cw, t_cw), s, axis=0), s, axis=1)
    fid = np.full((h * s, w * s), -1, np.int32)
    u0, v0 = r.roi_ss
    fid[v0:v0 + r.face_id_ss.shape[0], u0:u0 + r.face_id_ss.shape[1]] = r.face_id_ss
    light = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), -1.0])
    light /= np.linalg.norm(light)
    obj = np.searchsorted(face_of, np.maximum(fid, 0), side="right") - 1
    vs, us = np.nonzero(fid >= 0)
    # the sub-sample's centre in image pixels: (i + 0.5) / s - 0.5
    rays = np.stack([((us + 0.5) / s - 0.5 - INTR.cx) / INTR.fx, ((vs + 0.5) / s - 0.5 - INTR.cy) / INTR.fy,
                     np.ones(len(us))], -1)
    view = -rays / np.linalg.norm(rays, axis=1, keepdims=True)
    normals = r.face_normals_cam[fid[vs, us]].astype(float)
    for k in range(len(solids)):
        on = obj[vs, us] == k
        img[vs[on], us[on]] = _shade(normals[on], view[on], light, _material(rng))
    img = img.reshape(h, s, w, s, 3).mean(axis=(1, 3))
    img = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.3, 0.9))
    img += rng.normal(0.0, rng.uniform(1.0, 4.0), img.shape)
    n = R_cw[:, 2]
    copies = np.nonzero([sd[2] for sd in solids])[0]
    return Scene(np.clip(np.rint(img), 0, 255).astype(np.uint8), INTR, Plane(n, float(n @ t_cw)), poses,
                 [_visible_share(r, face_of, k, V, F, p) for k, p in zip(copies, poses, strict=True)])


def _visible_share(r, face_of: np.ndarray, k: int, V: np.ndarray, F: np.ndarray, pose: Pose) -> float:
    own = (r.face_id >= face_of[k]) & (r.face_id < face_of[k + 1])
    m = 400  # the copy alone on a canvas wider on each side: its whole silhouette, also off the image
    K_big = INTR.K + np.array([[0, 0, m], [0, 0, m], [0, 0, 0]])
    alone = render(V, F, pose, K_big, (SIZE[0] + 2 * m, SIZE[1] + 2 * m)).mask
    return float(own.sum()) / max(float(alone.sum()), 1.0)

