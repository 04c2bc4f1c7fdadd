"""Realistic shading for bench/synth_scenes.py: smooth normals, Blinn-Phong, shadow maps, gamma.

The flat Lambert look of the project's rasteriser is not what Blender (or a camera) shows: curved
surfaces are smoothly shaded, highlights sit at the mirror direction, parts cast shadows onto the floor
and onto each other, a large share of the light is ambient, and the result is gamma-encoded. Everything
here works on the rasteriser's own buffers (``render``'s face ids and depths at the supersampled
resolution) with numpy: a surface point is recovered from its pixel and depth, its normal interpolated
from per-corner normals (those of the faces around a vertex within a crease angle), and a directional
light's shadow map is the same rasteriser run from the light (a pinhole far away along it).

Conventions: camera frame (OpenCV), mm; ``light`` is the unit direction from a surface TOWARDS the light.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.vision.geometry.frames import Pose
from service.vision.geometry.render import rasterise_roi

LIGHT_DISTANCE_MM = 50_000.0  # the light's pinhole sits this far along the light: nearly orthographic
SHADOW_MAP_PX = 1024  # the longer side of the shadow map over the casters
SHADOW_BIAS_TEXELS = 1.5  # depth bias against self-shadowing acne, in texels (more on slanted faces)


@dataclass(frozen=True)
class Look:
    """How one scene is lit and encoded (drawn per image by ``sample_look``)."""
    ambient: float  # share of the light that reaches every point (shadowed points get only this)
    smooth: bool  # interpolate normals across edges sharper than crease_deg
    crease_deg: float
    specular: float  # Blinn-Phong highlight strength, in units of full white
    shininess: float
    shadows: bool
    light_radius_deg: float  # angular radius of the light: the penumbra's width on the floor
    gamma: float  # display encoding: linear radiance ** (1 / gamma)
    blur_px: float  # the renderer's pixel filter (soft edges)
    light: tuple[float, float, float]  # unit, towards the light, camera frame: from behind the camera


def light_direction(off_axis_deg: float, azimuth_rad: float) -> tuple[float, float, float]:
    """Unit direction towards a light ``off_axis_deg`` from the camera's optical axis (on the camera's
    side): the floor behind the parts then shows their shadows near them, as in the Blender sets."""
    a = np.radians(off_axis_deg)
    return (float(np.sin(a) * np.cos(azimuth_rad)), float(np.sin(a) * np.sin(azimuth_rad)), float(-np.cos(a)))


def sample_look(rng) -> Look:
    return Look(ambient=float(rng.uniform(0.3, 0.65)), smooth=True, crease_deg=float(rng.uniform(25, 50)),
                specular=float(rng.uniform(0.03, 0.35)), shininess=float(np.exp(rng.uniform(np.log(8),
                                                                                              np.log(150)))),
                shadows=True, light_radius_deg=float(rng.uniform(1.5, 6.0)), gamma=2.2,
                blur_px=float(rng.uniform(0.4, 0.9)),
                light=light_direction(float(rng.uniform(10, 40)), float(rng.uniform(0, 2 * np.pi))))


# --- normals ------------------------------------------------------------------------------------

_CORNER_NORMALS: dict = {}


def corner_normals(V: np.ndarray, F: np.ndarray, crease_deg: float) -> np.ndarray:
    """(F, 3, 3) unit normals at each face's corners, object frame: the angle-weighted mean of the
    normals of the faces around the corner's vertex that lie within ``crease_deg`` of this face's (so
    a cylinder is smooth and a box keeps its edges)."""
    key = (hash(V.tobytes()), hash(F.tobytes()), round(crease_deg, 3))
    if key in _CORNER_NORMALS:
        return _CORNER_NORMALS[key]
    tri = V[F]
    an = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    un = an / np.maximum(np.linalg.norm(an, axis=1, keepdims=True), 1e-30)
    corner_v = F.reshape(-1)  # corner c = 3 f + k
    corner_f = np.repeat(np.arange(len(F)), 3)
    order = np.argsort(corner_v, kind="stable")
    deg = np.bincount(corner_v, minlength=len(V))
    start = np.concatenate([[0], np.cumsum(deg)[:-1]])
    # every (corner, face around its vertex) pair
    n_pairs = deg[corner_v]
    c_idx = np.repeat(np.arange(len(corner_v)), n_pairs)
    offs = np.arange(len(c_idx)) - np.repeat(np.cumsum(n_pairs) - n_pairs, n_pairs)
    other = order[start[corner_v[c_idx]] + offs]  # the corner of face g at the same vertex
    g = corner_f[other]
    f = corner_f[c_idx]
    keep = np.einsum("ij,ij->i", un[f], un[g]) >= np.cos(np.radians(crease_deg))
    # weighted by the face's angle at the vertex: a quad split in two counts as much as one quad
    e1 = np.roll(tri, -1, axis=1) - tri
    e2 = np.roll(tri, 1, axis=1) - tri
    cosang = np.einsum("fkj,fkj->fk", e1, e2) / np.maximum(
        np.linalg.norm(e1, axis=2) * np.linalg.norm(e2, axis=2), 1e-30)
    angle = np.arccos(np.clip(cosang, -1, 1)).reshape(-1)
    acc = np.zeros((len(corner_v), 3))
    np.add.at(acc, c_idx[keep], un[g[keep]] * angle[other[keep]][:, None])
    acc /= np.maximum(np.linalg.norm(acc, axis=1, keepdims=True), 1e-30)
    out = acc.reshape(len(F), 3, 3)
    _CORNER_NORMALS[key] = out
    return out


# --- surface points of a render -----------------------------------------------------------------

def surface_points(r, V: np.ndarray, F: np.ndarray, pose: Pose):
    """For each covered sub-sample of the render ``r`` (``render(..., supersample=s)``): its boolean
    mask over the ROI buffers, the camera-frame point (M, 3) mm, the face id (M,) and the barycentric
    weights (M, 3) of the point in its face (exact: the point is the pixel's ray at the z-buffer depth)."""
    fss, dss = r.face_id_ss, r.depth_ss
    m = fss >= 0
    j, i = np.nonzero(m)
    K = r.K_ss
    z = dss[j, i].astype(np.float64)
    u, v = i + r.roi_ss[0], j + r.roi_ss[1]
    P = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)
    f = fss[j, i]
    tri = (V @ pose.R.T + pose.t_mm)[F[f]]  # (M, 3, 3)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    nn = np.maximum(np.einsum("ij,ij->i", n, n), 1e-30)
    wb = np.einsum("ij,ij->i", np.cross(P - a, c - a), n) / nn
    wc = np.einsum("ij,ij->i", np.cross(b - a, P - a), n) / nn
    w = np.clip(np.stack([1 - wb - wc, wb, wc], axis=1), 0, 1)
    return m, P, f, w / w.sum(axis=1, keepdims=True)


def shading_normals(r, V, F, pose: Pose, f: np.ndarray, w: np.ndarray, look: Look) -> np.ndarray:
    """(M, 3) unit camera-frame normals, facing the camera like the rasteriser's face normals."""
    face_n = r.face_normals_cam[f].astype(np.float64)  # already facing the camera
    if not look.smooth:
        return face_n
    cn = corner_normals(V, F, look.crease_deg)[f] @ pose.R.T  # (M, 3, 3)
    n = np.einsum("mk,mkj->mj", w, cn)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    # corner normals follow the mesh's winding; the rasteriser's face normal faces the camera
    flip = np.einsum("ij,ij->i", n, face_n) < 0
    n[flip] *= -1
    return n


# --- shadow map ---------------------------------------------------------------------------------

class ShadowMap:
    """Depth of the nearest caster seen from a directional light, over the casters' extent."""

    def __init__(self, casters: list[tuple[np.ndarray, np.ndarray, Pose]], light: np.ndarray):
        L = np.asarray(light, float) / np.linalg.norm(light)
        z = -L
        x = np.cross([0.0, 1.0, 0.0] if abs(z[1]) < 0.9 else [1.0, 0.0, 0.0], z)
        x /= np.linalg.norm(x)
        self.R = np.stack([x, np.cross(z, x), z])  # camera -> light frame (rows: the light's axes)
        pts = [V @ p.R.T + p.t_mm for V, _F, p in casters]
        centre = np.mean([q.mean(axis=0) for q in pts], axis=0) if pts else np.zeros(3)
        self.O = centre + L * LIGHT_DISTANCE_MM
        self.empty = not pts
        if self.empty:
            return
        ql = np.concatenate([(q - self.O) @ self.R.T for q in pts])
        xy = ql[:, :2] / ql[:, 2:3]
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        self.f = (SHADOW_MAP_PX - 8) / max(float((hi - lo).max()), 1e-9)
        self.c = 4.0 - self.f * lo
        self.size = (int(np.ceil(self.f * (hi[0] - lo[0]))) + 9, int(np.ceil(self.f * (hi[1] - lo[1]))) + 9)
        self.K = np.array([[self.f, 0, self.c[0]], [0, self.f, self.c[1]], [0, 0, 1.0]])
        self.depth = np.full(self.size[::-1], np.inf, np.float32)
        for V, F, p in casters:
            pl = Pose(self.R @ p.R, self.R @ (p.t_mm - self.O))
            d, _fid, (u0, v0) = rasterise_roi(V, F, pl, self.K, self.size)
            sub = self.depth[v0:v0 + d.shape[0], u0:u0 + d.shape[1]]
            np.minimum(sub, d, out=sub)
        self.texel_mm = LIGHT_DISTANCE_MM / self.f

    def _lookup(self, P: np.ndarray):
        ql = (P - self.O) @ self.R.T
        return ql[:, 2], ql[:, :2] / ql[:, 2:3] * self.f + self.c

    def blocker_gap_mm(self, P: np.ndarray) -> np.ndarray:
        """Distance along the light from the nearest caster to each point P (M, 3) (inf: no caster)."""
        zl, uv = self._lookup(P)
        h, w = self.depth.shape
        u, v = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        d = np.full(len(P), np.inf)
        d[inside] = self.depth[v[inside], u[inside]]
        return zl - d

    def lit(self, P: np.ndarray, normal: np.ndarray | None = None, pcf_texels: float = 1.0) -> np.ndarray:
        """Fraction (M,) in [0, 1] of the light that reaches the points P (M, 3): a 3 x 3 percentage-
        closer filter ``pcf_texels`` apart. ``normal``: the points' normals, to lift them off their own
        surface (against self-shadowing acne)."""
        if self.empty:
            return np.ones(len(P))
        bias = SHADOW_BIAS_TEXELS * self.texel_mm
        if normal is not None:
            P = P + normal * bias
        zl, uv = self._lookup(P)
        h, w = self.depth.shape
        out = np.zeros(len(P))
        for du in (-pcf_texels, 0.0, pcf_texels):
            for dv in (-pcf_texels, 0.0, pcf_texels):
                u = np.rint(uv[:, 0] + du).astype(int)
                v = np.rint(uv[:, 1] + dv).astype(int)
                inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
                d = np.full(len(P), np.inf)
                d[inside] = self.depth[v[inside], u[inside]]
                out += zl - bias <= d
        return out / 9.0


# --- shading ------------------------------------------------------------------------------------

def radiance(colour, n: np.ndarray, P: np.ndarray, light: np.ndarray, lit: np.ndarray,
             look: Look) -> np.ndarray:
    """(M, 3) display values (BGR, 0-255 scale) of surface points with normals n: ambient plus diffuse
    where lit, gamma-encoded, plus a Blinn-Phong highlight where lit."""
    L = np.asarray(light, float) / np.linalg.norm(light)
    view = -P / np.maximum(np.linalg.norm(P, axis=1, keepdims=True), 1e-30)
    half = view + L
    half /= np.maximum(np.linalg.norm(half, axis=1, keepdims=True), 1e-30)
    lam = np.clip(n @ L, 0, None)
    hl = np.where(lam > 0, np.clip(np.einsum("ij,ij->i", n, half), 0, None) ** look.shininess, 0.0)
    e = (look.ambient + (1 - look.ambient) * lam * lit) ** (1.0 / look.gamma)
    return np.float32(colour)[None] * e[:, None].astype(np.float32) \
        + np.float32(255 * look.specular) * (hl * lit)[:, None].astype(np.float32)


def floor_factor(lam_floor: float, lit: np.ndarray, look: Look) -> np.ndarray:
    """Multiplier of the (fully lit) floor texture where a fraction ``lit`` of the light arrives: 1 where
    lit, (ambient / (ambient + (1 - ambient) lam)) ** (1 / gamma) in full shadow."""
    a = look.ambient
    full = a + (1 - a) * max(lam_floor, 0.0)
    return ((a + (1 - a) * max(lam_floor, 0.0) * lit) / full) ** (1.0 / look.gamma)
