"""Silhouette borders of a mesh at a pose, and the mesh topology they need.

The border is traced on a supersampled silhouette (``cv2.findContours``, external contours only),
moved out by half a sub-pixel (the traced chain runs through the centres of the outermost covered
sub-pixels, the true edge lies half a sub-pixel further out), smoothed along the chain and resampled
by arc length. For a closed mesh (watertight, outward normals) each traced point is then snapped
onto the nearest projected contour-generator edge (an edge between a front and a back face): the
point, its orientation and its 3D point (on that edge, perspective-correct) are then exact, whatever
the supersampling. Otherwise ``p_obj`` is the point on the viewing ray at the depth of the nearest
covered sub-pixel (the paper's eq. 7). This replaces the paper's scan-line node procedure (kept, for
reference and tests, in ``reference/scanline.py``), with the same border on the paper's cases.

The bank's templates (``model/templates.py``) and the refinement (``estimate/refine.py``, through
``border_with_tangents``) trace their borders here.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import cv2
import numba
import numpy as np
from scipy.ndimage import gaussian_filter1d

from service.vision.geometry.camera import Intrinsics, as_intrinsics, project, unproject
from service.vision.geometry.frames import Pose
from service.vision.geometry.render import rasterise_roi
from service.vision.memo import Memo

MIN_BLOB_AREA_FRACTION = 0.05  # external contours smaller than this fraction of the largest are dropped
SMOOTH_SIGMA_PX = 0.5  # Gaussian smoothing of the traced chain along its length, output pixels


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
    mask_p = np.zeros((mask.shape[0] + 2, mask.shape[1] + 2), bool)  # np.pad's bookkeeping costs more
    mask_p[1:-1, 1:-1] = mask
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
    ok, z = _nearest_covered_depth(np.ascontiguousarray(q), mask, invz_ss)
    uv, theta, z = uv[ok], theta[ok], z[ok]
    p_cam = unproject(uv, z, intr.K)
    if sil_edges_cam is not None and len(sil_edges_cam):
        uv, theta, p_cam = snap_to_edges(uv, theta, p_cam, sil_edges_cam, intr)
    p_obj = (p_cam - pose.t_mm) @ pose.R
    return uv, theta, p_obj


@numba.njit(cache=True, nogil=True)
def _nearest_covered_depth(q, mask, invz):  # pragma: no cover - compiled
    """Per point q (M, 2) (col, row) of the ROI's sub-pixels: whether a sub-pixel of the 5 x 5 window about
    its rounded position is covered, and the depth (mm) of the nearest covered one (the first of equals,
    rows then columns). One loop: the (M, 25) candidate arrays cost ~0.3 ms a border."""
    hh, ww = mask.shape
    M = q.shape[0]
    ok = np.zeros(M, np.bool_)
    z = np.zeros(M)
    for m in range(M):
        i0, j0 = int(np.rint(q[m, 0])), int(np.rint(q[m, 1]))
        best, bi, bj = np.inf, 0, 0
        for j in range(j0 - 2, j0 + 3):
            for i in range(i0 - 2, i0 + 3):
                if i < 0 or i >= ww or j < 0 or j >= hh or not mask[j, i]:
                    continue
                du, dv = i - q[m, 0], j - q[m, 1]
                d2 = du * du + dv * dv
                if d2 < best:
                    best, bi, bj = d2, i, j
        if best < np.inf:
            ok[m] = True
            z[m] = 1.0 / np.float64(invz[bj, bi])
    return ok, z


SNAP_MAX_PX = 0.75  # a border point further than this from every contour-generator edge is kept as traced
SNAP_MAX_DEPTH_FRACTION = 0.05  # ... and so is one whose edge point is this much (of z) off the z-buffer
SNAP_SAMPLE_PX = 2.0  # edges are sampled this often to find the candidates (the 6 nearest samples' edges)


@numba.njit(cache=True, nogil=True)
def _closest_candidate(uv, a, b, cand):  # pragma: no cover - compiled
    """Per point uv (M, 2): of its candidate edges ``cand`` (M, k) (ids into the projected edges a -> b,
    (S, 2) each), the one passing closest (the first of equals): that distance, the edge and the point's
    parameter on it in [0, 1]. One loop: the (M, k, 2) arrays cost ~0.2 ms a border."""
    M, k = cand.shape
    dmin, best, tb = np.empty(M), np.empty(M, cand.dtype), np.empty(M)
    for m in range(M):
        for c in range(k):
            e = cand[m, c]
            ab0, ab1 = b[e, 0] - a[e, 0], b[e, 1] - a[e, 1]
            den = ab0 * ab0 + ab1 * ab1
            if den < 1e-18:
                den = 1e-18
            t = ((uv[m, 0] - a[e, 0]) * ab0 + (uv[m, 1] - a[e, 1]) * ab1) / den
            if t < 0.0:  # as np.clip: a -0.0 stays
                t = 0.0
            if t > 1.0:
                t = 1.0
            d0, d1 = (a[e, 0] + t * ab0) - uv[m, 0], (a[e, 1] + t * ab1) - uv[m, 1]
            d = math.sqrt(d0 * d0 + d1 * d1)
            if c == 0 or d < dmin[m]:
                dmin[m], best[m], tb[m] = d, e, t
    return dmin, best, tb


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
    K = intr.K
    a, b = project(P0, K), project(P1, K)
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
    dmin, best, tb = _closest_candidate(np.ascontiguousarray(uv, np.float64), a, b, cand)
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
    uv[use] = project(ps, K)
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
    face_v0: np.ndarray  # (F, 3) float64: each face's first vertex (front_facing reads it every call)

    def front_facing(self, pose: Pose) -> np.ndarray:
        """(F,) bool: faces whose outward normal points towards the camera."""
        cam_obj = -np.asarray(pose.R, float).T @ np.asarray(pose.t_mm, float)
        return np.einsum("ij,ij->i", self.face_normals, cam_obj - self.face_v0) > 0.0

    def contour_edges_cam(self, pose: Pose, front: np.ndarray) -> np.ndarray:
        """(S, 2, 3) mm, camera frame: edges between a front and a back face (contour generators)."""
        sel = front[self.edge_faces[:, 0]] != front[self.edge_faces[:, 1]]
        e = self.edges[sel]
        p = self.vertices[e.reshape(-1)] @ np.asarray(pose.R, float).T + np.asarray(pose.t_mm, float)
        return p.reshape(-1, 2, 3)


def _build_topology(V: np.ndarray, F: np.ndarray) -> MeshTopology:
    tri = V[F]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    edges = np.zeros((0, 2), np.int64)
    edge_faces = np.zeros((0, 2), np.int64)
    d = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]).astype(np.int64)
    key = np.stack([np.minimum(d[:, 0], d[:, 1]), np.maximum(d[:, 0], d[:, 1])], axis=1)
    # One stable sort of one int64 key orders the edges as np.lexsort((key[:, 1], key[:, 0])) would.
    order = np.argsort(key[:, 0] * (int(F.max()) + 1 if len(F) else 1) + key[:, 1], kind="stable")
    closed = _closed_outward(V, F, d, key, order)
    if closed:
        face_of = np.tile(np.arange(len(F)), 3)
        # Closed: every undirected edge occurs exactly twice, so sorted pairs are adjacent.
        first, second = order[0::2], order[1::2]
        edges = key[first]
        edge_faces = np.stack([face_of[first], face_of[second]], axis=1)
    return MeshTopology(V, F, closed, normals, edges, edge_faces, np.ascontiguousarray(tri[:, 0]))


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
    d = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    key = np.stack([np.minimum(d[:, 0], d[:, 1]), np.maximum(d[:, 0], d[:, 1])], axis=1)
    return _closed_outward(vertices_mm, F, d, key, np.argsort(key[:, 0] * (int(F.max()) + 1) + key[:, 1],
                                                              kind="stable"))


def _closed_outward(vertices_mm, F: np.ndarray, d: np.ndarray, key: np.ndarray, order: np.ndarray) -> bool:
    """``is_closed_outward`` given the faces' directed edges ``d`` (3F, 2) int64, the same edges
    undirected (``key``: (lower, higher) vertex) and the order sorting them (``_build_topology``'s)."""
    if len(F) == 0 or (d[:, 0] == d[:, 1]).any():  # a degenerate face cannot close a surface
        return False
    k = key[order]
    a, b = order[0::2], order[1::2]
    if len(order) % 2 or not (k[0::2] == k[1::2]).all() or (k[1:-1:2] == k[2::2]).all(axis=1).any():
        return False  # an edge not shared by exactly two faces
    if not ((d[a, 0] == d[b, 1]) & (d[a, 1] == d[b, 0])).all():  # two faces traversing an edge alike
        return False
    tri = np.asarray(vertices_mm, float)[F]
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0
    return bool(volume > 0.0)


# --- a border with 3D tangents (the refinement's residuals move with the pose) --------------------


@dataclass(frozen=True)
class Border:
    """Outer silhouette border at ``pose``: 3D model points and their 3D border tangents."""

    p_obj: np.ndarray  # (M, 3) float64 mm, object frame
    tan_obj: np.ndarray  # (M, 3) float64 unit, object frame (direction of the border through p)
    pose: Pose  # the pose it was extracted at


def _tangents_from_order(p_obj: np.ndarray, uv: np.ndarray, spacing_px: float) -> np.ndarray:
    """3D tangents of an ordered border from its neighbours (one-sided across gaps)."""
    M = len(p_obj)
    if M < 2:
        return np.tile([1.0, 0.0, 0.0], (M, 1))
    nxt = np.r_[np.arange(1, M), 0]
    prv = np.r_[M - 1, np.arange(M - 1)]
    gap = 3.0 * spacing_px
    ok_n = np.linalg.norm(uv[nxt] - uv, axis=1) <= gap
    ok_p = np.linalg.norm(uv[prv] - uv, axis=1) <= gap
    a = np.where(ok_p[:, None], p_obj[prv], p_obj)
    b = np.where(ok_n[:, None], p_obj[nxt], p_obj)
    T = b - a
    nrm = np.linalg.norm(T, axis=1, keepdims=True)
    T = np.where(nrm > 1e-12, T / np.maximum(nrm, 1e-12), [1.0, 0.0, 0.0])
    return T


def border_with_tangents(vertices_mm, faces, pose: Pose, intr: Intrinsics, image_size, *, spacing_px: float,
                         supersample: int) -> Border:
    """The outer border at ``pose`` (``border_at_pose`` in the pinhole part of ``intr``; ``image_size =
    (w, h)``) with 3D tangents from the neighbouring border points."""
    uv, _, p_obj = border_at_pose(vertices_mm, faces, pose, intr.pinhole(), image_size, spacing_px=spacing_px,
                                  supersample=supersample)
    p_obj = np.asarray(p_obj, np.float64).reshape(-1, 3)
    return Border(p_obj, _tangents_from_order(p_obj, np.asarray(uv, float).reshape(-1, 2), spacing_px), pose)
