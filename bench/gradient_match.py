"""Gradient-orientation matching (LINE-2D style) of every visible CAD edge, searched on a known plane.

A prototype of issue 47's proposal stage, outside the service. Three parts:

- **templates** (``plane_templates``): the part's resting pose families on the plane x spins about
  the plane's normal, each rendered (``service.vision.geometry.render``) at the plane's depth and
  reduced to ``MAX_POINTS`` edge points: silhouette and depth-jump pixels of the z-buffer PLUS crease
  edges (mesh edges with a dihedral angle above ``CREASE_DEG``) that the z-buffer shows. Each point
  keeps its image offset from the template's anchor (the projection of the plane point under the
  part's centre of mass) and its gradient orientation (normal to the projected edge, mod 180 deg)
  quantised to ``N_ORI`` bins;
- **image side** (``ResponseMaps``): per-channel Sobel on the colour image, the strongest channel per
  pixel, orientation quantised where the magnitude exceeds ``MAG_THRESHOLD`` (a 3 x 3 majority keeps
  it stable), spread over ``T`` x ``T`` pixels, and one response map per orientation (4 where the same
  orientation is present, 1 where a neighbouring one is, else 0), stored "linearised" (one map per
  offset mod T) so a template is scored on the T-pixel grid with contiguous adds;
- **search** (``match``): every template at every T-pixel grid position (optionally in zones of the
  image whose own templates were rendered there: perspective), score = mean response / 4 = the share
  of the template's points whose gradient agrees; local maxima above a threshold, NMS, lifted to
  ``T_cam_obj`` on the plane: ``R = A @ Rz(spin) @ R_rest_obj``, ``t = p0(u, v) - A @ Rz(spin) @ s``
  with ``p0`` the plane point on the pixel's ray and ``s`` the rest frame's offset of the part.

Frames and units as in the service: mm, OpenCV camera frame, pose = T_cam_obj, pixels uv (u = column).
A plane is ``{"normal": n, "d_mm": d}``: the points p with n . p = d, n pointing towards the camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba
import numpy as np
import trimesh

from service.vision.geometry.frames import Pose, R_between, Rx, Rz
from service.vision.geometry.render import render

# --- named parameters -------------------------------------------------------------------------------
CREASE_DEG = 30.0  # a mesh edge whose adjacent faces turn by more than this is a crease edge
MIN_REST_PROBABILITY = 0.02  # resting families rarer than this are not searched
SYM_GROUP_DEG = 3.0  # continuous symmetry: poses whose up makes the same angle with the axis are one family
SPIN_STEP_DEG = 10.0  # the coarsest spin step (small parts)
MIN_SPIN_STEP_DEG = 2.0
BIG_PART_PX = 40.0  # parts with a larger radius (px) are searched with T = 8
MAX_POINTS = 96  # edge points kept per template
MIN_POINTS = 12
DEPTH_JUMP_MM = 2.0  # a step in the z-buffer larger than this is an occluding edge
VISIBLE_TOL_MM = 1.5  # crease sample visible when the z-buffer there is not nearer than this
N_ORI = 8  # orientation bins over 180 deg
MAG_THRESHOLD = 40.0  # Sobel (3 x 3) magnitude on 0..255 channels below which a pixel has no orientation
SOFT_DEG = 5.0  # image orientations this close to a bin boundary also set the neighbouring bin
T = 4  # spreading neighbourhood and search grid step, px


# --- geometry helpers ---------------------------------------------------------------------------------
def plane_point_on_ray(uv: np.ndarray, K: np.ndarray, plane: dict) -> np.ndarray:
    """(N, 2) pixels -> (N, 3) points (mm, camera frame) where their rays meet the plane."""
    uv = np.atleast_2d(np.asarray(uv, float))
    d = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))], 1)
    n = np.asarray(plane["normal"], float)
    s = plane["d_mm"] / (d @ n)
    return d * s[:, None]


def plane_align(plane: dict) -> np.ndarray:
    """``A``: rest frame (+z up) -> camera frame, with A @ e_z = the plane's normal (towards the camera)."""
    n = np.asarray(plane["normal"], float)
    # Rx(180) turns +z onto -z (the top-down camera's "up"); the small remainder is well defined.
    return R_between([0.0, 0.0, -1.0], n) @ Rx(180.0)


@dataclass(frozen=True)
class RestFamily:
    R_rest_obj: np.ndarray  # (3, 3) object frame -> rest frame (+z up, the part on z = 0)
    s_rest_mm: np.ndarray  # (3,) rest-frame offset: posed point = R_rest_obj @ p_obj - s (COM over origin)
    probability: float
    spins_deg: np.ndarray  # spins about +z searched for this family


def rest_families(
    mesh: trimesh.Trimesh,
    symmetry: str = "none",
    *,
    min_probability: float = MIN_REST_PROBABILITY,
    spin_step_deg: float = SPIN_STEP_DEG,
) -> list[RestFamily]:
    """Resting pose families of ``mesh`` on a plane, most probable first.

    A continuous symmetry axis (``"x" | "y" | "z"``) groups trimesh's hull-face poses by the angle
    their up direction makes with the axis (a tessellated cylinder's facets are one family); without
    one, each pose is its own family. A family whose up is the axis needs a single spin.
    """
    hull = mesh.convex_hull
    com = np.asarray(mesh.center_mass if mesh.is_watertight else hull.center_mass, float)
    with np.errstate(all="ignore"):
        Ts, prob = trimesh.poses.compute_stable_poses(hull, center_mass=com)
    Rs = np.asarray(Ts, float)[:, :3, :3]
    prob = np.asarray(prob, float)
    order = np.argsort(-prob, kind="stable")
    axis = {"x": np.array([1.0, 0, 0]), "y": np.array([0, 1.0, 0]), "z": np.array([0, 0, 1.0])}.get(symmetry)
    fams: list[list] = []  # [R, prob_sum, angle]
    for i in order:
        R = Rs[i]
        up = R[2]
        ang = None if axis is None else math.degrees(math.acos(np.clip(abs(up @ axis), 0, 1)))
        if ang is not None:
            hit = next((f for f in fams if abs(f[2] - ang) <= SYM_GROUP_DEG), None)
            if hit is not None:
                hit[1] += prob[i]
                continue
        fams.append([R, float(prob[i]), ang])
    V = np.asarray(mesh.vertices, float)
    out = []
    for R, p, ang in sorted(fams, key=lambda f: -f[1]):
        if p < min_probability:
            continue
        q = V @ R.T
        c = R @ com
        s = np.array([c[0], c[1], q[:, 2].min()])
        one_spin = ang is not None and ang < SYM_GROUP_DEG
        spins = np.zeros(1) if one_spin else np.arange(0.0, 360.0, spin_step_deg)
        out.append(RestFamily(R, s, p, spins))
    return out


# --- templates ----------------------------------------------------------------------------------------
@dataclass
class TemplateSet:
    """Templates of one part on one plane, rendered in ``zones`` (each zone's own anchor pixel)."""

    t: int  # the spreading / grid step these templates are searched with, px
    spin_step_deg: float
    dx: np.ndarray  # (M, P) int32 offsets of the points from the anchor, px (u)
    dy: np.ndarray  # (M, P) int32 (v)
    ori: np.ndarray  # (M, P) int32 orientation bin; -1 pads
    n_pts: np.ndarray  # (M,) int32
    family: np.ndarray  # (M,) int32 index into families
    spin_deg: np.ndarray  # (M,) float64
    zone: np.ndarray  # (M,) int32
    families: list
    zone_rects: list  # per zone: (u0, v0, u1, v1) anchor pixels searched with its templates
    zone_anchor_uv: np.ndarray  # (Z, 2) the pixel each zone's templates were rendered at
    A: np.ndarray
    n_crease: np.ndarray  # (M,) how many of the points came from crease edges

    def __post_init__(self):
        M, P = self.dx.shape
        valid = self.ori >= 0
        self.w_flat = (valid / np.maximum(self.n_pts, 1)[:, None]).astype(np.float32)
        # balanced: a point weighs 1 / (the points of its bin, at least n / (2 N_ORI)), normalised
        cnt = np.zeros((M, N_ORI))
        for o in range(N_ORI):
            cnt[:, o] = (self.ori == o).sum(axis=1)
        c = np.take_along_axis(cnt, np.maximum(self.ori, 0), axis=1)
        w = valid / np.maximum(c, self.n_pts[:, None] / (2.0 * N_ORI))
        self.w_bal = (w / w.sum(axis=1, keepdims=True)).astype(np.float32)


def crease_edges(mesh: trimesh.Trimesh, crease_deg: float = CREASE_DEG) -> np.ndarray:
    """(E, 2, 3) mesh edges whose dihedral angle exceeds ``crease_deg``, object frame, mm."""
    ang = np.degrees(mesh.face_adjacency_angles)
    e = mesh.face_adjacency_edges[ang > crease_deg]
    return np.asarray(mesh.vertices, float)[e]


def _sample_segments(P: np.ndarray, step: float) -> np.ndarray:
    """(E, 2, 3) segments -> (S, 3) points about every ``step`` (same unit), and (S,) segment index."""
    L = np.linalg.norm(P[:, 1] - P[:, 0], axis=1)
    k = np.maximum(1, np.ceil(L / step).astype(int))
    idx = np.repeat(np.arange(len(P)), k)
    t = np.concatenate([(np.arange(n) + 0.5) / n for n in k]) if len(k) else np.zeros(0)
    pts = P[idx, 0] + (P[idx, 1] - P[idx, 0]) * t[:, None]
    return pts, idx


def _pick_spread(uv: np.ndarray, n_max: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of at most ``n_max`` points of ``uv`` spread out (greedy, minimum distance shrinking)."""
    if len(uv) <= n_max:
        return np.arange(len(uv))
    perm = rng.permutation(len(uv))
    # Start with the spacing that would give n_max points along the edges, relax until enough.
    d = max(1.0, len(uv) / n_max)
    for _ in range(30):
        keep = _greedy_min_dist(uv[perm], d * d)
        if len(keep) >= 0.8 * n_max or d <= 1.0:
            break
        d = max(1.0, d * 0.85)
    keep = perm[keep]
    return keep[:n_max]


@numba.njit(cache=True)
def _greedy_min_dist(uv, d2):  # pragma: no cover - compiled
    out = np.empty(len(uv), np.int64)
    n = 0
    for i in range(len(uv)):
        ok = True
        for j in range(n):
            k = out[j]
            if (uv[i, 0] - uv[k, 0]) ** 2 + (uv[i, 1] - uv[k, 1]) ** 2 < d2:
                ok = False
                break
        if ok:
            out[n] = i
            n += 1
    return out[:n]


def template_points(
    V: np.ndarray,
    F: np.ndarray,
    creases_obj: np.ndarray,
    pose: Pose,
    K: np.ndarray,
    image_size: tuple[int, int],
    plane: dict,
    *,
    n_max: int = MAX_POINTS,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Edge points of the part seen at ``pose``: (P, 2) uv float, (P,) orientation bins, #crease points.

    Silhouette and depth-jump pixels of the z-buffer (the table at the plane's depth behind the part),
    each with the direction of the depth gradient there; crease edges sampled every pixel, kept where
    the z-buffer shows them, each with the normal of its projected segment.
    """
    w, h = image_size
    r = render(V, F, pose, K, image_size)
    m = r.mask
    if m.sum() < 4:
        return np.zeros((0, 2)), np.zeros(0, np.int32), 0
    vs, us = np.nonzero(m)
    v0, v1 = max(vs.min() - 3, 0), min(vs.max() + 4, h)
    u0, u1 = max(us.min() - 3, 0), min(us.max() + 4, w)
    uu, vv = np.meshgrid(np.arange(u0, u1), np.arange(v0, v1))
    table = plane_point_on_ray(np.stack([uu.ravel(), vv.ravel()], 1), K, plane)[:, 2].reshape(uu.shape)
    depth = np.where(m[v0:v1, u0:u1], r.depth_mm[v0:v1, u0:u1], table).astype(np.float32)
    # Occluding edges: a jump in depth to a 4-neighbour (the nearer side's pixel is the edge).
    jump = np.zeros(depth.shape, bool)
    for ax in (0, 1):
        dd = np.diff(depth, axis=ax)
        big = np.abs(dd) > DEPTH_JUMP_MM
        near_first = big & (dd > 0)  # the first pixel is nearer
        near_second = big & (dd < 0)
        if ax == 0:
            jump[:-1] |= near_first
            jump[1:] |= near_second
        else:
            jump[:, :-1] |= near_first
            jump[:, 1:] |= near_second
    # direction from a slightly smoothed depth: a pixel staircase would tilt it by up to 45 deg
    ds = cv2.GaussianBlur(depth, (0, 0), 1.0)
    gx = cv2.Sobel(ds, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(ds, cv2.CV_32F, 0, 1, ksize=3)
    jv, ju = np.nonzero(jump)
    uv_sil = np.stack([ju + u0, jv + v0], 1).astype(float)
    th_sil = np.arctan2(gy[jv, ju], gx[jv, ju])
    # Crease edges visible by the z-buffer.
    uv_cr = np.zeros((0, 2))
    th_cr = np.zeros(0)
    if len(creases_obj):
        P = creases_obj @ pose.R.T + pose.t_mm  # (E, 2, 3) camera frame
        # sample every ~0.7 px: the pixel size at the part's depth
        px_mm = float(np.median(P[:, :, 2])) / K[0, 0]
        pts, seg = _sample_segments(P, 0.7 * px_mm)
        uvp = pts[:, :2] / pts[:, 2:3] * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]
        iu = np.rint(uvp[:, 0]).astype(int)
        iv = np.rint(uvp[:, 1]).astype(int)
        inside = (iu >= 1) & (iu < w - 1) & (iv >= 1) & (iv < h - 1)
        dm = r.depth_mm
        far = np.full(len(pts), -np.inf)
        for dv in (-1, 0, 1):
            for du in (-1, 0, 1):
                dval = np.where(inside, dm[np.clip(iv + dv, 0, h - 1), np.clip(iu + du, 0, w - 1)], -np.inf)
                far = np.maximum(far, np.where(np.isfinite(dval), dval, -np.inf))
        vis = inside & (far >= pts[:, 2] - VISIBLE_TOL_MM)
        a = P[seg, 0]
        b = P[seg, 1]
        ua = a[:, :2] / a[:, 2:3] * np.array([K[0, 0], K[1, 1]])
        ub = b[:, :2] / b[:, 2:3] * np.array([K[0, 0], K[1, 1]])
        tang = ub - ua
        ok = vis & (np.linalg.norm(tang, axis=1) > 1e-6)
        uv_cr = uvp[ok]
        th_cr = np.arctan2(tang[ok, 0], -tang[ok, 1])  # the normal of the segment
        # one point per pixel
        key = np.rint(uv_cr[:, 1]).astype(np.int64) * w + np.rint(uv_cr[:, 0]).astype(np.int64)
        _, first = np.unique(key, return_index=True)
        uv_cr, th_cr = np.rint(uv_cr[first]), th_cr[first]
        # a crease pixel already on an occluding edge keeps the occluding edge's direction
        on_sil = jump[
            np.clip(uv_cr[:, 1].astype(int) - v0, 0, jump.shape[0] - 1),
            np.clip(uv_cr[:, 0].astype(int) - u0, 0, jump.shape[1] - 1),
        ]
        uv_cr, th_cr = uv_cr[~on_sil], th_cr[~on_sil]
    uv_all = np.concatenate([uv_sil, uv_cr])
    th_all = np.concatenate([th_sil, th_cr])
    is_cr = np.concatenate([np.zeros(len(uv_sil), bool), np.ones(len(uv_cr), bool)])
    keep = _pick_spread(uv_all, n_max, rng)
    ori = quantise(th_all[keep])
    return uv_all[keep], ori, int(is_cr[keep].sum())


def quantise(theta_rad: np.ndarray) -> np.ndarray:
    """Gradient directions (rad) -> orientation bins 0..N_ORI-1 over 180 deg."""
    a = np.mod(theta_rad, np.pi)
    return np.minimum((a / np.pi * N_ORI).astype(np.int32), N_ORI - 1)


def part_radius_px(mesh: trimesh.Trimesh, K: np.ndarray, plane: dict) -> float:
    """The part's largest radius from its centre of mass, in pixels at the plane's depth on the axis."""
    V = np.asarray(mesh.vertices, float)
    r_mm = float(np.linalg.norm(V - V.mean(axis=0), axis=1).max())
    z = float(plane_point_on_ray(K[:2, 2], K, plane)[0, 2])
    return r_mm * K[0, 0] / z


def auto_t(radius_px: float) -> int:
    """Spreading / grid step for a part of this radius: 4 px for small parts, 8 for large ones."""
    return 4 if radius_px < BIG_PART_PX else 8


def auto_spin_step(radius_px: float, t: int) -> float:
    """Spin step (deg) that moves the part's farthest point by at most t px (t/2 either side of a
    template), within [MIN_SPIN_STEP_DEG, SPIN_STEP_DEG], dividing 360."""
    step = float(np.clip(math.degrees(t / max(radius_px, 1.0)), MIN_SPIN_STEP_DEG, SPIN_STEP_DEG))
    return 360.0 / math.ceil(360.0 / step)


def plane_templates(
    mesh: trimesh.Trimesh,
    symmetry: str,
    K: np.ndarray,
    image_size: tuple[int, int],
    plane: dict,
    *,
    zones: int = 1,
    spin_step_deg: float | None = None,
    t: int | None = None,
    n_max: int = MAX_POINTS,
    crease_deg: float = CREASE_DEG,
    use_creases: bool = True,
    seed: int = 0,
) -> TemplateSet:
    """Every resting family x spin, rendered at the centre of each of ``zones`` x ``zones`` image zones."""
    rng = np.random.default_rng(seed)
    r_px = part_radius_px(mesh, K, plane)
    t = auto_t(r_px) if t is None else t
    spin_step_deg = auto_spin_step(r_px, t) if spin_step_deg is None else spin_step_deg
    V = np.asarray(mesh.vertices, float)
    F = np.asarray(mesh.faces, np.int64)
    fams = rest_families(mesh, symmetry, spin_step_deg=spin_step_deg)
    creases = crease_edges(mesh, crease_deg) if use_creases else np.zeros((0, 2, 3))
    A = plane_align(plane)
    w, h = image_size
    rects, anchors = [], []
    for j in range(zones):
        for i in range(zones):
            ua, ub = i * w // zones, (i + 1) * w // zones
            va, vb = j * h // zones, (j + 1) * h // zones
            rects.append((ua, va, ub, vb))
            anchors.append(((ua + ub - 1) / 2.0, (va + vb - 1) / 2.0))
    anchors = np.asarray(anchors)
    rows = []
    for z, auv in enumerate(anchors):
        p0 = plane_point_on_ray(auv, K, plane)[0]
        for fi, fam in enumerate(fams):
            for spin in fam.spins_deg:
                Rs = A @ Rz(spin)
                pose = Pose(Rs @ fam.R_rest_obj, p0 - Rs @ fam.s_rest_mm)
                uv, ori, ncr = template_points(
                    V, F, creases, pose, K, image_size, plane, n_max=n_max, rng=rng
                )
                if len(uv) < MIN_POINTS:
                    continue
                off = np.rint(uv - auv).astype(np.int32)
                rows.append((off, ori, fi, spin, z, ncr))
    M = len(rows)
    P = max(len(r[0]) for r in rows)
    dx = np.zeros((M, P), np.int32)
    dy = np.zeros((M, P), np.int32)
    ori = np.full((M, P), -1, np.int32)
    npts = np.zeros(M, np.int32)
    for k, (off, o, *_rest) in enumerate(rows):
        n = len(off)
        dx[k, :n], dy[k, :n], ori[k, :n], npts[k] = off[:, 0], off[:, 1], o, n
    return TemplateSet(
        t,
        spin_step_deg,
        dx,
        dy,
        ori,
        npts,
        np.array([r[2] for r in rows], np.int32),
        np.array([r[3] for r in rows], float),
        np.array([r[4] for r in rows], np.int32),
        fams,
        rects,
        anchors,
        A,
        np.array([r[5] for r in rows], np.int32),
    )


# --- image side ---------------------------------------------------------------------------------------
@numba.njit(cache=True)
def _majority(q, mask, out):  # pragma: no cover - compiled
    """LINE-2D's 3 x 3 vote: keep a pixel's bin when >= 5 of its 9 neighbours (with it) share it."""
    H, W = q.shape
    hist = np.zeros(8, np.int32)
    for v in range(1, H - 1):
        for u in range(1, W - 1):
            if not mask[v, u]:
                continue
            for k in range(8):
                hist[k] = 0
            for dv in range(-1, 2):
                for du in range(-1, 2):
                    if mask[v + dv, u + du]:
                        hist[q[v + dv, u + du]] += 1
            best = 0
            for k in range(1, 8):
                if hist[k] > hist[best]:
                    best = k
            if hist[best] >= 5:
                out[v, u] = np.uint8(1 << best)


def orientation_bits(
    image_bgr: np.ndarray,
    *,
    mag_threshold: float = MAG_THRESHOLD,
    blur_sigma: float = 1.0,
    soft_deg: float = SOFT_DEG,
) -> np.ndarray:
    """(h, w) uint8: bit b set where the strongest channel's gradient orientation is bin b."""
    img = image_bgr.astype(np.float32)
    if blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    if gx.ndim == 2:
        gx, gy = gx[..., None], gy[..., None]
    m2 = gx * gx + gy * gy
    c = np.argmax(m2, axis=2)[..., None]
    gxs = np.take_along_axis(gx, c, 2)[..., 0]
    gys = np.take_along_axis(gy, c, 2)[..., 0]
    mag = np.sqrt(np.take_along_axis(m2, c, 2)[..., 0])
    th = np.arctan2(gys, gxs)
    q = quantise(th).astype(np.int32)
    bits = np.zeros(q.shape, np.uint8)
    _majority(q, mag > mag_threshold, bits)
    if soft_deg > 0:
        # near a bin boundary the neighbouring bin is set too: an edge at 179 deg and one at 1 deg are
        # the same edge, and a template point quantised on the other side still reads "agrees"
        a = np.degrees(np.mod(th, np.pi)) / (180.0 / N_ORI)
        frac = a - np.floor(a)
        w = soft_deg / (180.0 / N_ORI)
        lo = (frac < w) & (bits > 0)
        hi = (frac > 1 - w) & (bits > 0)
        bits = (
            bits
            | np.where(lo, (1 << ((q - 1) % N_ORI)), 0).astype(np.uint8)
            | np.where(hi, (1 << ((q + 1) % N_ORI)), 0).astype(np.uint8)
        )
    return bits


def spread(bits: np.ndarray, t: int = T) -> np.ndarray:
    """OR of the bits over the t x t neighbourhood whose top-left corner is the pixel (LINE-2D)."""
    h, w = bits.shape
    out = np.zeros_like(bits)
    for dv in range(t):
        for du in range(t):
            out[: h - dv, : w - du] |= bits[dv:, du:]
    return out


@dataclass
class ResponseMaps:
    """Linearised response maps: ``lin[o, ry, rx]`` is the response to orientation o (0, 1 or 4) at
    pixels (v, u) = (gy * T + ry, gx * T + rx), zero-padded by ``pad`` grid cells on every side."""

    lin: np.ndarray  # (N_ORI, T, T, Gh + 2 pad, Gw + 2 pad) uint8
    pad: int
    grid_shape: tuple[int, int]  # (Gh, Gw)
    t: int


def response_maps(bits_spread: np.ndarray, *, t: int = T, pad: int = 64) -> ResponseMaps:
    h, w = bits_spread.shape
    Gh, Gw = (h + t - 1) // t, (w + t - 1) // t
    b = np.zeros((Gh * t, Gw * t), np.uint8)
    b[:h, :w] = bits_spread
    lin = np.zeros((N_ORI, t, t, Gh + 2 * pad, Gw + 2 * pad), np.uint8)
    for o in range(N_ORI):
        same = (b & (1 << o)) != 0
        nb = (b & ((1 << ((o + 1) % N_ORI)) | (1 << ((o - 1) % N_ORI)))) != 0
        r = np.where(same, 4, np.where(nb, 1, 0)).astype(np.uint8)
        for ry in range(t):
            for rx in range(t):
                lin[o, ry, rx, pad : pad + Gh, pad : pad + Gw] = r[ry::t, rx::t]
    return ResponseMaps(lin, pad, (Gh, Gw), t)


# --- search -------------------------------------------------------------------------------------------
@numba.njit(cache=True, nogil=True)
def _score_all(lin, pad, t, dx, dy, ori, wt, npts, tzone, zrect, best, best_m):  # pragma: no cover - compiled
    """For every template m and every grid cell of its zone: score = sum of weighted responses / 4
    (weights sum to 1 per template); keeps the best score and its template per cell in ``best`` /
    ``best_m`` (Gh, Gw)."""
    M = dx.shape[0]
    acc = np.zeros(best.shape, np.float32)
    for m in range(M):
        z = tzone[m]
        g0, h0, g1, h1 = zrect[z, 0], zrect[z, 1], zrect[z, 2], zrect[z, 3]  # grid cells [g0, g1) x [h0, h1)
        for gy in range(h0, h1):
            for gx in range(g0, g1):
                acc[gy, gx] = 0.0
        for p in range(npts[m]):
            o = ori[m, p]
            ox = dx[m, p]
            oy = dy[m, p]
            w = wt[m, p] * 0.25
            rx = ox % t
            ry = oy % t
            cx = (ox - rx) // t + pad
            cy = (oy - ry) // t + pad
            L = lin[o, ry, rx]
            for gy in range(h0, h1):
                row = L[gy + cy]
                for gx in range(g0, g1):
                    acc[gy, gx] += w * row[gx + cx]
        for gy in range(h0, h1):
            for gx in range(g0, g1):
                s = acc[gy, gx]
                if s > best[gy, gx]:
                    best[gy, gx] = s
                    best_m[gy, gx] = m


@numba.njit(cache=True, nogil=True)
def _score_at(lin, pad, t, dx, dy, ori, wt, n, u, v):  # pragma: no cover - compiled
    """Score of one template at anchor pixel (u, v) (any pixel, not only the grid)."""
    s = 0.0
    for p in range(n):
        pu = u + dx[p]
        pv = v + dy[p]
        rx = pu % t
        ry = pv % t
        s += wt[p] * lin[ori[p], ry, rx, (pv - ry) // t + pad, (pu - rx) // t + pad]
    return s / 4.0


@dataclass
class Proposal:
    score: float
    uv: tuple[float, float]  # anchor pixel (the plane point under the part's centre of mass)
    template: int
    pose: Pose


def match(
    rm: ResponseMaps,
    ts: TemplateSet,
    K: np.ndarray,
    plane: dict,
    *,
    min_score: float = 0.0,
    nms_px: float = 16.0,
    top_k: int = 50,
    rm_fine: ResponseMaps | None = None,
    balanced: bool = True,
) -> list[Proposal]:
    """Best ``top_k`` placements of the templates, each lifted to T_cam_obj on the plane.

    Every local maximum of the coarse search (``rm``, T = ts.t) is refined to the pixel and the
    neighbouring spins, scored on ``rm_fine`` (a smaller T: tighter tolerance) when given.
    ``balanced``: each orientation bin of a template weighs about the same (``ts.w_bal``), so a
    template that is mostly one straight edge does not score high on any straight edge."""
    Gh, Gw = rm.grid_shape
    t = rm.t
    if t != ts.t:
        raise ValueError(f"templates made for T = {ts.t}, response maps for T = {t}")
    if np.abs(ts.dx).max() >= (rm.pad - 1) * t or np.abs(ts.dy).max() >= (rm.pad - 1) * t:
        raise ValueError("template larger than the response maps' padding")
    zr = np.array(
        [[r[0] // t, r[1] // t, (r[2] + t - 1) // t, (r[3] + t - 1) // t] for r in ts.zone_rects], np.int64
    )
    zr[:, 2] = np.minimum(zr[:, 2], Gw)
    zr[:, 3] = np.minimum(zr[:, 3], Gh)
    wt = ts.w_bal if balanced else ts.w_flat
    best = np.full((Gh, Gw), -1.0, np.float32)
    best_m = np.full((Gh, Gw), -1, np.int64)
    _score_all(rm.lin, rm.pad, t, ts.dx, ts.dy, ts.ori, wt, ts.n_pts, ts.zone, zr, best, best_m)
    # local maxima of the best-score map (3 x 3 cells) above the threshold
    dil = cv2.dilate(best.astype(np.float32), np.ones((3, 3), np.uint8))
    cand = np.argwhere((best >= dil - 1e-9) & (best >= min_score))
    order = np.argsort(-best[cand[:, 0], cand[:, 1]], kind="stable")
    cand = cand[order]
    picked: list[tuple[float, float, float, int]] = []
    for gy, gx in cand:
        u, v, m = gx * t, gy * t, int(best_m[gy, gx])
        s = best[gy, gx]
        s, u, v, m = _refine(rm if rm_fine is None else rm_fine, ts, wt, u, v, m, t // 2)
        if any((u - pu) ** 2 + (v - pv) ** 2 < nms_px**2 for _, pu, pv, _m in picked):
            continue
        picked.append((s, u, v, m))
        if len(picked) >= 3 * top_k:
            break
    picked.sort(key=lambda x: -x[0])
    out = []
    for s, u, v, m in picked[:top_k]:
        fam = ts.families[ts.family[m]]
        Rs = ts.A @ Rz(ts.spin_deg[m])
        p0 = plane_point_on_ray(np.array([u, v], float), K, plane)[0]
        out.append(
            Proposal(float(s), (float(u), float(v)), m, Pose(Rs @ fam.R_rest_obj, p0 - Rs @ fam.s_rest_mm))
        )
    return out


def _refine(
    rm: ResponseMaps, ts: TemplateSet, wt: np.ndarray, u: int, v: int, m: int, h: int
) -> tuple[float, int, int, int]:
    """Best pixel within +-t/2 (1 px steps) and the neighbouring spins of the same family and zone."""
    same = np.flatnonzero((ts.family == ts.family[m]) & (ts.zone == ts.zone[m]))
    spins = ts.spin_deg[same]
    dspin = np.abs((spins - ts.spin_deg[m] + 180.0) % 360.0 - 180.0)
    near = same[dspin <= ts.spin_step_deg + 1e-6]
    best = (-1.0, u, v, m)
    for mm in near:
        n = int(ts.n_pts[mm])
        for dv in range(-h, h + 1):
            for du in range(-h, h + 1):
                s = _score_at(
                    rm.lin, rm.pad, rm.t, ts.dx[mm], ts.dy[mm], ts.ori[mm], wt[mm], n, u + du, v + dv
                )
                if s > best[0]:
                    best = (s, u + du, v + dv, int(mm))
    return best
