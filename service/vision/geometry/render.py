"""Software rasteriser: silhouette mask, depth (z-buffer), face ids, normals and a shaded grey image.

No OpenGL: a z-buffer over triangles compiled with numba (releases the GIL, so threads scale), run
only inside the ROI of the projected vertices. Conventions are ``frames`` / ``camera``'s:

- ``pose`` is ``T_cam_obj`` (``p_cam = R @ p_obj + t_mm``), vertices in mm, object frame;
- pixels are ``uv`` (u = column, v = row), the centre of the top-left pixel is (0, 0), and a pixel
  belongs to a triangle when its CENTRE lies inside the projected triangle (edges inclusive);
- ``image_size = (w, h)``; every array is indexed ``[v, u]`` with shape ``(h, w)``;
- the camera is the ideal pinhole ``K``: lens distortion is not rendered (undistort the image side).

Triangles with a vertex at ``z <= Z_NEAR_MM`` are culled (no near-plane clipping).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np

from service.vision.geometry.camera import as_intrinsics, project
from service.vision.geometry.frames import Pose

Z_NEAR_MM = 1e-3  # triangles with any vertex closer than this (camera z, mm) are culled
_EDGE_EPS = 1e-9  # inclusive edge test, relative (barycentric); closes cracks between shared edges


@numba.njit(cache=True, nogil=True, inline="always")
def _clip_span(a, r, eps, lo, hi):  # pragma: no cover - compiled
    """Narrow the row span [lo, hi] of u to where a barycentric weight a * u + r is >= -eps
    (an empty span comes back with lo > hi)."""
    if a > 0.0:
        return max(lo, (-eps - r) / a), hi
    if a < 0.0:
        return lo, min(hi, (-eps - r) / a)
    return (lo, hi) if r >= -eps else (1e30, -1e30)


@numba.njit(cache=True, nogil=True)
def _zbuffer(uv, z, faces, ids, invz, fid, eps):  # pragma: no cover - compiled
    """Rasterise triangles into ``invz`` (H, W) float32 (init 0) and ``fid`` (H, W) int32 (init -1):
    a pixel's id is ``ids[f]`` of its nearest triangle ``faces[f]`` (ties: the first).

    uv (V, 2) float64 in buffer pixel coordinates; z (V,) float64 camera depth, mm. ``invz`` gets
    1 / depth of the nearest surface (perspective-correct: 1/z is affine in the image).
    """
    H, W = invz.shape
    for f in range(faces.shape[0]):
        i0 = faces[f, 0]
        i1 = faces[f, 1]
        i2 = faces[f, 2]
        z0 = z[i0]
        z1 = z[i1]
        z2 = z[i2]
        if z0 <= 1e-3 or z1 <= 1e-3 or z2 <= 1e-3:
            continue
        x0 = uv[i0, 0]
        y0 = uv[i0, 1]
        x1 = uv[i1, 0]
        y1 = uv[i1, 1]
        x2 = uv[i2, 0]
        y2 = uv[i2, 1]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if abs(area) < 1e-12:
            continue
        inv_area = 1.0 / area
        umin = max(int(np.ceil(min(x0, x1, x2))), 0)
        umax = min(int(np.floor(max(x0, x1, x2))), W - 1)
        vmin = max(int(np.ceil(min(y0, y1, y2))), 0)
        vmax = min(int(np.floor(max(y0, y1, y2))), H - 1)
        if umin > umax or vmin > vmax:
            continue
        iz0 = 1.0 / z0
        iz1 = 1.0 / z1
        iz2 = 1.0 / z2
        # Barycentric w_i(u, v) = (a_i * u + b_i * v + c_i) * inv_area; per row, each w_i >= -eps
        # bounds u from one side, so only the covered span of the row is visited.
        a0 = (y1 - y2) * inv_area
        b0 = (x2 - x1) * inv_area
        c0 = (x1 * y2 - x2 * y1) * inv_area
        a1 = (y2 - y0) * inv_area
        b1 = (x0 - x2) * inv_area
        c1 = (x2 * y0 - x0 * y2) * inv_area
        for v in range(vmin, vmax + 1):
            lo = -1e30
            hi = 1e30
            r0 = b0 * v + c0
            r1 = b1 * v + c1
            # w2 = 1 - w0 - w1
            a2 = -a0 - a1
            r2 = 1.0 - r0 - r1
            lo, hi = _clip_span(a0, r0, eps, lo, hi)
            lo, hi = _clip_span(a1, r1, eps, lo, hi)
            lo, hi = _clip_span(a2, r2, eps, lo, hi)
            if lo > hi + 1.0:  # no pixel (also a weight that is constant and negative along the row)
                continue
            ulo = max(int(np.ceil(lo - 1e-9)), umin)
            uhi = min(int(np.floor(hi + 1e-9)), umax)
            # 1/z is affine along the row: compare inverse depths, no division per pixel.
            iza = a0 * (iz0 - iz2) + a1 * (iz1 - iz2)
            izb = r0 * (iz0 - iz2) + r1 * (iz1 - iz2) + iz2
            for u in range(ulo, uhi + 1):
                iz = iza * u + izb
                if iz > invz[v, u]:
                    invz[v, u] = iz
                    fid[v, u] = ids[f]


@dataclass
class Render:
    """Result of ``render``. Full-resolution arrays, shape ``(h, w)``, indexed ``[v, u]``.

    mask : bool, True where the object covers the pixel (for ``supersample > 1``: coverage >= 0.5)
    depth_mm : float32, camera z of the nearest surface, mm; ``np.inf`` off the object
    face_id : int32, index of the visible face; -1 off the object
    coverage : float32 in [0, 1], fraction of the pixel's sub-samples covered (anti-aliasing)
    supersample : the factor s used
    mask_ss, depth_ss, face_id_ss : the raw buffers at s times the resolution, CROPPED to the ROI of the
        projected mesh: element [j, i] is pixel (u0_ss + i, v0_ss + j) of the (s*h, s*w) image seen
        with ``K_ss`` (= ``Intrinsics.scaled(s).K``), where ``(u0_ss, v0_ss) = roi_ss``
    normal_cam : (h, w, 3) float32 unit face normals in the camera frame, facing the camera (lazy)
    """

    mask: np.ndarray
    depth_mm: np.ndarray
    face_id: np.ndarray
    coverage: np.ndarray
    supersample: int
    mask_ss: np.ndarray
    depth_ss: np.ndarray
    face_id_ss: np.ndarray
    roi_ss: tuple[int, int]
    K_ss: np.ndarray
    face_normals_cam: np.ndarray = field(repr=False)  # (F, 3) float32
    _normal_cam: np.ndarray | None = field(default=None, repr=False)

    @property
    def normal_cam(self) -> np.ndarray:
        if self._normal_cam is None:
            n = np.zeros(self.face_id.shape + (3,), np.float32)
            m = self.face_id >= 0
            n[m] = self.face_normals_cam[self.face_id[m]]
            self._normal_cam = n
        return self._normal_cam


def face_normals_cam(vertices_mm: np.ndarray, faces: np.ndarray, R: np.ndarray,
                     t_mm: np.ndarray) -> np.ndarray:
    """(F, 3) float32 unit face normals in the camera frame, flipped to face the camera."""
    p = np.asarray(vertices_mm, float) @ np.asarray(R, float).T + np.asarray(t_mm, float)
    tri = p[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    # Facing the camera: the normal points against the viewing ray to the face centre.
    flip = np.einsum("ij,ij->i", n, tri.mean(axis=1)) > 0
    n[flip] *= -1
    return n.astype(np.float32)


def rasterise_roi(vertices_mm, faces, pose: Pose, K_or_intr, image_size, *, margin_px: int = 2,
                  align: int = 1, inverse_depth: bool = False, face_ids: np.ndarray | None = None):
    """Z-buffer inside the ROI of the projected vertices (no full-image buffers).

    ``face_ids``: (F,) int32, the id written for each of ``faces`` (default: its index), e.g. the
    mesh's own face indices when ``faces`` is a subset of them.

    ``align``: the ROI's origin and size are multiples of it (image size must be too).

    Returns ``(depth (h_r, w_r) float32, face_id (h_r, w_r) int32, (u0, v0))`` where (u0, v0) is the
    ROI's top-left pixel in the image; an empty ROI gives (0, 0)-shaped arrays. With
    ``inverse_depth`` the first array is ``1 / depth`` (1/mm, 0 off the object) and is not converted.
    """
    intr = as_intrinsics(K_or_intr)
    w, h = int(image_size[0]), int(image_size[1])
    V = np.asarray(vertices_mm, np.float64)
    F = np.ascontiguousarray(faces, dtype=np.int32)
    p = V @ np.asarray(pose.R, float).T + np.asarray(pose.t_mm, float)
    z = np.ascontiguousarray(p[:, 2])
    front = z > Z_NEAR_MM
    # Vertices behind the camera get a harmless depth: their triangles are culled in _zbuffer.
    uv = project(np.column_stack([p[:, :2], np.where(front, z, 1.0)]), intr.K)
    if not front.any():
        return np.zeros((0, 0), np.float32), np.zeros((0, 0), np.int32), (0, 0)
    uvf = uv[front]
    u0 = max(int(np.floor(uvf[:, 0].min())) - margin_px, 0)
    v0 = max(int(np.floor(uvf[:, 1].min())) - margin_px, 0)
    u1 = min(int(np.ceil(uvf[:, 0].max())) + margin_px, w - 1)
    v1 = min(int(np.ceil(uvf[:, 1].max())) + margin_px, h - 1)
    if align > 1:
        u0, v0 = u0 - u0 % align, v0 - v0 % align
        u1, v1 = u1 + (align - 1 - u1 % align), v1 + (align - 1 - v1 % align)
    if u1 < u0 or v1 < v0:
        return np.zeros((0, 0), np.float32), np.zeros((0, 0), np.int32), (0, 0)
    invz = np.zeros((v1 - v0 + 1, u1 - u0 + 1), np.float32)
    fid = np.full(invz.shape, -1, np.int32)
    uv_roi = np.ascontiguousarray(uv - np.array([u0, v0], float))
    ids = np.arange(len(F), dtype=np.int32) if face_ids is None else np.ascontiguousarray(face_ids, np.int32)
    _zbuffer(uv_roi, z, F, ids, invz, fid, _EDGE_EPS)
    if inverse_depth:
        return invz, fid, (u0, v0)
    with np.errstate(divide="ignore"):
        depth = (1.0 / invz).astype(np.float32)
    return depth, fid, (u0, v0)


def render(vertices_mm, faces, pose: Pose, K, image_size, *, supersample: int = 1) -> Render:
    """Rasterise a triangle mesh seen at ``pose`` (T_cam_obj) by the pinhole ``K``.

    vertices_mm : (V, 3) mm, object frame; faces : (F, 3) int; K : (3, 3) or ``Intrinsics``;
    image_size : (w, h). With ``supersample = s > 1`` the mesh is rasterised at s times the
    resolution with ``Intrinsics.scaled(s)`` (pixel centres stay consistent) and reduced per s x s
    block: ``mask`` = coverage >= 0.5, ``depth_mm`` = nearest sub-sample, ``face_id`` its face.
    """
    s = int(supersample)
    if s < 1:
        raise ValueError("supersample must be a positive integer.")
    intr = as_intrinsics(K)
    w, h = int(image_size[0]), int(image_size[1])
    intr_s = intr.scaled(s) if s > 1 else intr
    ws, hs = w * s, h * s
    d_roi, f_roi, (u0, v0) = rasterise_roi(vertices_mm, faces, pose, intr_s, (ws, hs), align=s)
    rh, rw = d_roi.shape
    normals = face_normals_cam(vertices_mm, np.asarray(faces), pose.R, pose.t_mm)
    if s == 1:
        depth = np.full((h, w), np.inf, np.float32)
        fid = np.full((h, w), -1, np.int32)
        depth[v0:v0 + rh, u0:u0 + rw] = d_roi
        fid[v0:v0 + rh, u0:u0 + rw] = f_roi
        mask = fid >= 0
        return Render(mask, depth, fid, mask.astype(np.float32), 1, f_roi >= 0, d_roi, f_roi, (u0, v0),
                      intr.K, normals)
    depth = np.full((h, w), np.inf, np.float32)
    fid = np.full((h, w), -1, np.int32)
    coverage = np.zeros((h, w), np.float32)
    if d_roi.size:  # reduce the ROI (aligned to s x s blocks) only
        bh, bw = rh // s, rw // s
        bd = d_roi.reshape(bh, s, bw, s).transpose(0, 2, 1, 3).reshape(bh, bw, s * s)
        bf = f_roi.reshape(bh, s, bw, s).transpose(0, 2, 1, 3).reshape(bh, bw, s * s)
        arg = np.argmin(bd, axis=2)[..., None]
        cov = (bf >= 0).mean(axis=2, dtype=np.float32)
        inside = cov >= 0.5
        sl = (slice(v0 // s, v0 // s + bh), slice(u0 // s, u0 // s + bw))
        coverage[sl] = cov
        depth[sl] = np.where(inside, np.take_along_axis(bd, arg, axis=2)[..., 0], np.inf)
        fid[sl] = np.where(inside, np.take_along_axis(bf, arg, axis=2)[..., 0], -1)
    return Render(fid >= 0, depth, fid, coverage, s, f_roi >= 0, d_roi, f_roi, (u0, v0), intr_s.K, normals)


DEFAULT_LIGHT_DIR_CAM = (0.35, -0.45, -0.82)  # towards the light (up-left, from the camera side)


def render_shaded(vertices_mm, faces, pose: Pose, K, image_size, *, background: int = 70,
                  light_dir_cam=None, ambient: float = 0.35, object_range: tuple[int, int] = (120, 230),
                  supersample: int = 2) -> np.ndarray:
    """Lambert-shaded grey picture of the mesh: (h, w) uint8, object in ``object_range`` on ``background``.

    Shading is two-sided: ``ambient + (1 - ambient) * |n . l|`` mapped linearly onto ``object_range``;
    ``light_dir_cam`` points from the surface towards the light (camera frame, default up-left-front).
    With ``supersample = s > 1`` each pixel is the mean of s x s sub-samples (anti-aliased edges).
    """
    r = render(vertices_mm, faces, pose, K, image_size, supersample=supersample)
    lo, hi = float(object_range[0]), float(object_range[1])
    ldir = np.asarray(DEFAULT_LIGHT_DIR_CAM if light_dir_cam is None else light_dir_cam, float)
    ldir = ldir / np.linalg.norm(ldir)
    lam = np.abs(r.face_normals_cam.astype(np.float64) @ ldir)
    shade = lo + (hi - lo) * (ambient + (1.0 - ambient) * lam)
    w, h = int(image_size[0]), int(image_size[1])
    img = np.full((h, w), float(background))
    s = r.supersample
    fss = r.face_id_ss
    if fss.size:
        roi = np.full(fss.shape, float(background))
        m = fss >= 0
        roi[m] = shade[fss[m]]
        if s > 1:  # the ROI is aligned to s x s blocks
            roi = roi.reshape(fss.shape[0] // s, s, fss.shape[1] // s, s).mean(axis=(1, 3))
        u0, v0 = r.roi_ss[0] // s, r.roi_ss[1] // s
        img[v0:v0 + roi.shape[0], u0:u0 + roi.shape[1]] = roi
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
