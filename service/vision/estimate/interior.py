"""Image edges inside a posed silhouette that the model does not explain.

Chamfer matching only asks whether the silhouette's border lies on image edges. On a textured floor
(checkerboard, stripes) a box-like silhouette finds such edges almost anywhere: in ``clutter`` an
L-bracket template fitted a 4 x 2 block of checker squares with 99 % border support. What gives it away
is the inside: the texture's lines run on through the would-be part, while a real part's inside
only shows the model's own creases and depth steps (plus occluders and highlights).

``unexplained_edge_ratio`` measures that: the length of image edges (LSD segments) inside the
silhouette, eroded by ``ERODE_PX``, that are further than ``CREASE_TOL_PX`` from any crease or depth
step of the model at that pose, per unit of silhouette perimeter. Paper renders (clean background):
<= 0.06 at the true pose; the checkerboard fit above: 0.53 (full-resolution LSD on the ROI).
"""

from __future__ import annotations

import cv2
import numba as nb
import numpy as np

from service.vision.bank import TemplateBank
from service.vision.estimate.edges import Segments, sample_segments
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose
from service.vision.geometry.render import rasterise_roi
from service.vision.geometry.silhouette import mesh_topology

ERODE_PX = 5  # the border's own edges (and the pose's last pixel of error) are not "inside"
CREASE_DEG = 25.0  # neighbouring pixels whose surface normals differ more than this: a model crease
CREASE_DEPTH_MM = 3.0  # ... or whose depths differ more than this: a step (holes, overlaps)
CREASE_TOL_PX = 3  # an image edge this close to a crease or step is explained by it
SAMPLE_STEP_PX = 1.0


def model_edges(bank: TemplateBank, pose: Pose, intr: Intrinsics, image_size
                ) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """Silhouette mask and crease/step mask of the model at ``pose`` in the ROI of its projection:
    ``(mask (h, w) bool, crease (h, w) bool, (u0, v0))``."""
    topo = mesh_topology(bank.vertices_mm, bank.faces)  # its arrays and face normals, made once per mesh
    faces, normals = topo.faces, topo.face_normals
    if topo.closed:  # a closed mesh's back faces are hidden: half the triangles to rasterise
        front = topo.front_facing(pose)
        faces, normals = faces[front], normals[front]
    invz, fid, origin = rasterise_roi(topo.vertices, faces, pose, intr, image_size, margin_px=8,
                                      inverse_depth=True)
    crease = _creases(fid, invz, faces, normals, np.cos(np.radians(CREASE_DEG)), CREASE_DEPTH_MM)
    return fid >= 0, crease, origin


@nb.njit(cache=True, nogil=True)
def _creases(fid, invz, faces, normals, cos_max, step_mm):  # numpy's (h, w, 3) temporaries took 10 ms
    """Pixels whose right or lower neighbour (both on the model) shows a face bent by more than
    acos(cos_max) (either winding; ``normals`` need not be unit length), or a face sharing no vertex
    with this one and more than ``step_mm`` nearer or further (an occlusion step: a face seen at a
    grazing angle changes depth by several mm per pixel without any step)."""
    h, w = fid.shape
    out = np.zeros((h, w), np.bool_)
    for v in range(h):
        for u in range(w):
            f = fid[v, u]
            if f < 0:
                continue
            for dv, du in ((0, 1), (1, 0)):
                vv, uu = v + dv, u + du
                if vv >= h or uu >= w or fid[vv, uu] < 0:
                    continue
                g = fid[vv, uu]
                if g == f:
                    continue
                # Scalar loads: ``nf @ nf`` of two 3-vectors was a BLAS call a pixel (3.5 -> 1.4 ms a frame).
                f0, f1, f2 = normals[f, 0], normals[f, 1], normals[f, 2]
                g0, g1, g2 = normals[g, 0], normals[g, 1], normals[g, 2]
                c = f0 * g0 + f1 * g1 + f2 * g2
                if abs(c) < cos_max * np.sqrt((f0 * f0 + f1 * f1 + f2 * f2) * (g0 * g0 + g1 * g1 + g2 * g2)):
                    out[v, u] = True
                    continue
                shared = False
                for i in range(3):
                    for j in range(3):
                        shared |= faces[f, i] == faces[g, j]
                if not shared and abs(1.0 / invz[v, u] - 1.0 / invz[vv, uu]) > step_mm:
                    out[v, u] = True
    return out


def unexplained_edge_ratio(bank: TemplateBank, pose: Pose, intr: Intrinsics, seg: Segments,
                           image_size) -> float:
    """Length of ``seg`` (full-image pixels, ideal camera ``intr``) inside the silhouette at ``pose``
    and away from the model's creases and depth steps, divided by the silhouette's perimeter."""
    mask, crease, (u0, v0) = model_edges(bank, pose, intr, image_size)
    if not mask.any() or len(seg) == 0:
        return 0.0
    m8 = mask.astype(np.uint8)
    contours, _ = cv2.findContours(m8, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    perimeter = sum(cv2.arcLength(c, True) for c in contours)
    inner = cv2.erode(m8, np.ones((2 * ERODE_PX + 1,) * 2, np.uint8)) > 0
    near = cv2.dilate(crease.astype(np.uint8), np.ones((2 * CREASE_TOL_PX + 1,) * 2, np.uint8)) > 0
    uv, _ = sample_segments(seg, step_px=SAMPLE_STEP_PX)
    u = np.rint(uv[:, 0]).astype(np.int64) - u0
    v = np.rint(uv[:, 1]).astype(np.int64) - v0
    ok = (u >= 0) & (u < mask.shape[1]) & (v >= 0) & (v < mask.shape[0])
    u, v = u[ok], v[ok]
    unexplained = inner[v, u] & ~near[v, u]
    return float(unexplained.sum() * SAMPLE_STEP_PX / max(perimeter, 1.0))
