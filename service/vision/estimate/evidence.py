"""Evidence for a pose hypothesis beyond grey-level chamfer support, read off the colour image.

Chamfer matching only asks whether the silhouette's border lies on grey edges; a checkerboard or a
distractor satisfies that almost anywhere. A real part at the right pose also shows:

- ``colour_edge``: a colour gradient (max over B, G, R, so a yellow part on an orange floor with equal
  grey levels still has one) across the outline, along its normal, on most of the outline;
- ``polarity``: that contrast keeps its sign along the outline (the part against its background),
  while a fit to texture sees it alternate square by square;
- ``region``: the colours just inside the outline differ from those just outside (the region-based
  trackers' evidence, PWP3D / RBOT / SRT3D), judged per angular sector so a varied background and a
  partial occluder cost only their sectors; it needs no colour in the CAD model;

All three are fractions in [0, 1], higher is better, computed in the region of interest of the
projected model only (a few ms per hypothesis at 1280 x 960).

A part partly hidden by a nearer object spoils this evidence; the robust colour fit measured for it is
not in the service (docs/detection-history.md, "Switches taken out of the service").
"""

from __future__ import annotations

import functools
from concurrent.futures import Future
from dataclasses import dataclass, replace

import cv2
import numpy as np

from service.vision import threads
from service.vision.bank import TemplateBank
from service.vision.estimate.edge_agreement import FAINT_MAG_THRESHOLD, agreeing_bits
from service.vision.estimate.gradients import Gradient, gradient_bits, image_gradient
from service.vision.estimate.shapes import distinct_px, genericity
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose
from service.vision.geometry.render import face_normals_cam, rasterise_roi
from service.vision.geometry.silhouette import mesh_topology

BAND_FRACTION = 0.12  # region band width as a fraction of the silhouette's equivalent radius ...
BAND_MIN_PX, BAND_MAX_PX = 3, 14  # ... within these bounds
CONTOUR_STEP_PX = 3  # outline sampling for the edge and polarity evidence
NORMAL_SEARCH_PX = 2  # an edge within this distance along the normal supports the outline point
EDGE_ANGLE_DEG = 30.0  # ... if its gradient is within this angle of the normal
EDGE_MIN_GRADIENT = 6.0  # grey levels per pixel (max channel, after a 1 px blur): sensor noise stays under
POLARITY_OFFSET_PX = 3  # inside/outside colour samples this far from the outline
REGION_SECTORS = 8
REGION_BINS = 6  # per colour channel: 216 bins; coarse enough that a band of a few hundred pixels fills them
MIN_REGION_PIXELS = 30  # a sector with fewer inside or outside pixels is not judged


@dataclass(frozen=True)
class Evidence:
    colour_edge: float  # fraction of outline points with a colour edge along their normal
    polarity: float  # fraction of neighbouring outline points whose inside-outside contrast agrees
    region: float  # mean per-sector separability of inside and outside colours (0: same, 1: disjoint)
    region_low: float  # the second-worst sector's separability (a varied background spoils a few)
    region_global: float  # separability of the whole inside band against the whole outside band
    coherence: float  # |sum of inside-outside colour differences| / sum of their norms along the outline
    shading_r2: float  # share of the inside's grey variance explained by a quadratic in the normals
    shading_std: float  # grey-level standard deviation inside (small: the fit above says little)
    in_image: float  # fraction of the outline points inside the image
    # how closely a plain shape (ellipse, rectangle, cylinder or box view) fits the pose's silhouette
    # (``shapes.genericity``): near 1, any everyday object of that outline explains the rest as well
    generic: float = 1.0
    # the mean distance, image pixels, of the silhouette's outline from that plain shape's
    # (``shapes.distinct_px``): under a pixel nothing in the image can tell the part from the plain object
    distinct_px: float = 0.0
    # The taught appearance's evidence (``appearance``), None for a part with no reference photos.
    appearance: float | None = None  # correlation of the image's colours with the taught face colours
    appearance_known: float | None = None  # share of the inside whose face colour was taught

    def as_dict(self) -> dict[str, float]:
        return {"colour_edge": self.colour_edge, "polarity": self.polarity, "region": self.region,
                "region_low": self.region_low, "region_global": self.region_global,
                "coherence": self.coherence, "shading_r2": self.shading_r2, "shading_std": self.shading_std,
                "in_image": self.in_image, "generic": self.generic, "distinct_px": self.distinct_px} | (
            {} if self.appearance is None else {"appearance": self.appearance,
                                                 "appearance_known": self.appearance_known})


NO_EVIDENCE = Evidence(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
SHADING_ERODE_PX = 2  # the outline's mixed pixels and the pose's last pixel of error are not "inside"
MIN_SHADING_PIXELS = 50
# Another found part hides a pixel of this one where its surface is nearer by more than this (mm):
# rasterised depths of touching parts differ by less along their contact.
OCCLUSION_MARGIN_MM = 1.0


@dataclass(frozen=True)
class ColourFrame:
    """The frame as the evidence reads it: (H, W, 3) uint8 BGR (grey images repeated), made once."""
    bgr: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.bgr.shape[:2]

    @functools.cached_property
    def gradient(self) -> Gradient:
        """The frame's gradient (``gradients.image_gradient``), made once: both orientation bits read it."""
        return image_gradient(self.bgr)

    @functools.cached_property
    def orientations(self) -> np.ndarray:
        """(H, W) uint8 gradient orientation bits (``gradients.gradient_bits`` of ``gradient``), made once
        per frame."""
        return gradient_bits(self.gradient)

    @functools.cached_property
    def agreeing(self) -> np.ndarray:
        """The orientation bits ``edge_agreement`` reads (``agreeing_bits``, faint ones where the table is
        quiet), made once per frame."""
        return agreeing_bits(self.orientations, gradient_bits(self.gradient, FAINT_MAG_THRESHOLD))


@dataclass(frozen=True)
class _Window:
    """Arrays of one hypothesis's region of interest (gradients only where they are read)."""
    bgr: np.ndarray  # (h, w, 3) uint8
    blur: np.ndarray  # (h, w, 3) uint8: bgr smoothed by a 1 px Gaussian (gradients are read off it)

    def quantised_at(self, v: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Colour bin index in [0, REGION_BINS ** 3) of the pixels (v, u), int64: only where the
        region test reads (the band), not over the whole window."""
        q = (self.bgr[v, u].astype(np.int64) * REGION_BINS) // 256
        return (q[:, 0] * REGION_BINS + q[:, 1]) * REGION_BINS + q[:, 2]


def colour_frame(image: np.ndarray) -> ColourFrame:
    """(H, W) grey or (H, W, 3|4) BGR(A) uint8/uint16 image -> the frame the evidence reads."""
    from service.vision.estimate.edges import to_grey_u8

    img = np.asarray(image)
    if img.ndim == 3:
        img = img[..., :3]
        if img.dtype != np.uint8:
            img = np.dstack([to_grey_u8(img[..., c]) for c in range(3)])
    else:
        img = np.repeat(to_grey_u8(img)[..., None], 3, axis=2)
    return ColourFrame(np.ascontiguousarray(img))


def _window(frame: ColourFrame, u0: int, v0: int, w: int, h: int) -> _Window:
    bgr = frame.bgr[v0:v0 + h, u0:u0 + w]
    return _Window(bgr, cv2.GaussianBlur(bgr, (0, 0), 1.0))


def _gradient_at(win: _Window, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference gradient (levels/px) of the channel with the largest one, at the pixels
    nearest ``uv`` (..., 2): only where the outline is read, not over the whole window."""
    h, w = win.blur.shape[:2]
    u = np.clip(np.rint(uv[..., 0]).astype(int), 1, w - 2)
    v = np.clip(np.rint(uv[..., 1]).astype(int), 1, h - 2)
    # float32 only where read (the same values as converting the whole window first)
    gu = 0.5 * (win.blur[v, u + 1].astype(np.float32) - win.blur[v, u - 1])  # (..., 3)
    gv = 0.5 * (win.blur[v + 1, u].astype(np.float32) - win.blur[v - 1, u])
    best = np.argmax(gu * gu + gv * gv, axis=-1)[..., None]
    return np.take_along_axis(gu, best, -1)[..., 0], np.take_along_axis(gv, best, -1)[..., 0]


def face_ids_roi(bank: TemplateBank, pose: Pose, intr: Intrinsics, image_size, margin_px: int
                 ) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """Visible face index (h_r, w_r) int32 (-1 off the model) at ``pose`` in the image ROI of its
    projection widened by ``margin_px``, 1 / depth there (1/mm, 0 off the model), and the ROI's
    top-left pixel (u0, v0).

    A closed mesh's back faces are hidden behind its front faces (``MeshTopology.closed``): only the
    front ones are rasterised (half the triangles; the ROI is the whole mesh's projection either way),
    each pixel given its face's index in the whole mesh (``face_ids``)."""
    topo = mesh_topology(bank.vertices_mm, bank.faces)
    if not topo.closed:
        invz, fid, origin = rasterise_roi(bank.vertices_mm, bank.faces, pose, intr, image_size,
                                          margin_px=margin_px, inverse_depth=True)
        return fid, invz, origin
    front = np.flatnonzero(topo.front_facing(pose)).astype(np.int32)
    invz, fid, origin = rasterise_roi(topo.vertices, topo.faces[front], pose, intr, image_size,
                                      margin_px=margin_px, inverse_depth=True, face_ids=front)
    return fid, invz, origin



def _outline(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Outer outline points (N, 2) float64 uv in ROI pixels, every CONTOUR_STEP_PX, in order, and their
    outward unit normals (N, 2)."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    pts, nrm = [], []
    for c in contours:
        c = c[:, 0, :].astype(np.float64)
        if len(c) < 4 * CONTOUR_STEP_PX:
            continue
        k = CONTOUR_STEP_PX
        tangent = np.roll(c, -k, axis=0) - np.roll(c, k, axis=0)
        tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-9)
        # findContours runs its outer contours so that the inside is on one fixed side; find it from
        # the mask instead of relying on that.
        n = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)
        idx = np.arange(0, len(c), k)
        pts.append(c[idx])
        nrm.append(n[idx])
    if not pts:
        return np.zeros((0, 2)), np.zeros((0, 2))
    p, n = np.concatenate(pts), np.concatenate(nrm)
    probe = np.rint(p + 2.0 * n).astype(int)
    h, w = mask.shape
    ok = (probe[:, 0] >= 0) & (probe[:, 0] < w) & (probe[:, 1] >= 0) & (probe[:, 1] < h)
    inside = np.zeros(len(p), bool)
    inside[ok] = mask[probe[ok, 1], probe[ok, 0]]
    if inside.mean() > 0.5:  # the normals point inwards: flip them all
        n = -n
    return p, n


def _sample(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Nearest-pixel samples of ``img`` at uv (clipped to the image)."""
    h, w = img.shape[:2]
    u = np.clip(np.rint(uv[..., 0]).astype(int), 0, w - 1)
    v = np.clip(np.rint(uv[..., 1]).astype(int), 0, h - 1)
    return img[v, u]


def _edge_and_polarity(win: _Window, p: np.ndarray, n: np.ndarray, in_image: np.ndarray
                       ) -> tuple[float, float, float]:
    """``p``: outline points in the window's pixels; ``in_image``: which are inside the image."""
    if not in_image.any():
        return 0.0, 0.0, 0.0
    offs = np.arange(-NORMAL_SEARCH_PX, NORMAL_SEARCH_PX + 1, dtype=np.float64)
    q = p[:, None, :] + offs[None, :, None] * n[:, None, :]  # (N, S, 2)
    gu, gv = _gradient_at(win, q)
    along = np.abs(gu * n[:, None, 0] + gv * n[:, None, 1])
    mag = np.sqrt(gu * gu + gv * gv)
    ok = (mag >= EDGE_MIN_GRADIENT) & (along >= np.cos(np.radians(EDGE_ANGLE_DEG)) * mag)
    supported = ok.any(axis=1) & in_image
    colour_edge = float(supported.sum() / max(in_image.sum(), 1))
    c_in = _sample(win.bgr, p - POLARITY_OFFSET_PX * n).astype(np.float64)
    c_out = _sample(win.bgr, p + POLARITY_OFFSET_PX * n).astype(np.float64)
    d = c_in - c_out
    strong = (np.linalg.norm(d, axis=1) >= 2 * EDGE_MIN_GRADIENT) & in_image
    pair = strong & np.roll(strong, -1)
    if pair.sum() == 0:
        return colour_edge, 0.0, 0.0
    agree = np.einsum("ij,ij->i", d, np.roll(d, -1, axis=0)) > 0
    # Normalised by all in-image pairs: a weak outline cannot score by agreeing on a few points.
    polarity = float((agree & pair).sum() / max((in_image & np.roll(in_image, -1)).sum(), 1))
    # Over the whole outline: a part against one background keeps one contrast; checker squares
    # along the outline alternate it, and their differences cancel.
    di = d[in_image]
    coherence = float(np.linalg.norm(di.sum(axis=0)) / max(np.linalg.norm(di, axis=1).sum(), 1e-9))
    return colour_edge, polarity, coherence


def _tv(a: np.ndarray, b: np.ndarray) -> float:
    """Total variation distance of two colour-bin histograms (counts): 0 same, 1 disjoint."""
    return float(0.5 * np.abs(a / a.sum() - b / b.sum()).sum())


def _region(win: _Window, mask: np.ndarray, band_px: int, hidden: np.ndarray | None = None,
            explained: np.ndarray | None = None) -> tuple[float, float, float]:
    """``hidden``: pixels of the silhouette another, nearer part covers; ``explained``: pixels outside
    it another part covers. Neither is the part's inside nor its background."""
    m8 = mask.astype(np.uint8)
    d_in = cv2.distanceTransform(m8, cv2.DIST_L2, 3)
    d_out = cv2.distanceTransform(1 - m8, cv2.DIST_L2, 3)
    inner = mask & (d_in <= band_px)
    outer = ~mask & (d_out <= band_px)
    if hidden is not None:
        inner &= ~hidden
        outer &= ~explained
    # The silhouette's centroid from its row and column counts (exact integer sums: the mean of its
    # pixels' coordinates, without listing them).
    n_px = int(m8.sum())
    v_mean = float(m8.sum(axis=1, dtype=np.int64) @ np.arange(m8.shape[0])) / n_px
    u_mean = float(m8.sum(axis=0, dtype=np.int64) @ np.arange(m8.shape[1])) / n_px
    bv, bu = np.nonzero(inner | outer)  # sectors only where the bands are: not over the whole window
    angle = np.arctan2(bv - v_mean, bu - u_mean) + np.pi
    sector_of_band = np.minimum((angle * (REGION_SECTORS / (2 * np.pi))).astype(int), REGION_SECTORS - 1)
    nb = REGION_BINS ** 3
    # One histogram per (sector, inside / outside) in one pass: (REGION_SECTORS, 2, nb) counts.
    key = (2 * sector_of_band + ~inner[bv, bu]) * nb + win.quantised_at(bv, bu)
    hist = np.bincount(key, minlength=2 * REGION_SECTORS * nb).reshape(REGION_SECTORS, 2, nb)
    counts = hist.sum(axis=2)
    seps = [_tv(hist[s, 0], hist[s, 1]) for s in range(REGION_SECTORS)
            if counts[s, 0] >= MIN_REGION_PIXELS and counts[s, 1] >= MIN_REGION_PIXELS]
    if not seps:
        return 0.0, 0.0, 0.0
    seps = np.sort(np.asarray(seps))
    both = hist.sum(axis=0)
    overall = _tv(both[0], both[1])
    return float(seps.mean()), float(seps[min(1, len(seps) - 1)]), overall


@dataclass(frozen=True)
class _Inside:
    """The silhouette's inside as both shading fits read it: every other pixel of the eroded mask."""
    v: np.ndarray  # (N,) window rows
    u: np.ndarray  # (N,) window columns
    normals: np.ndarray  # (N, 3) camera-frame normal of each pixel's face


def _inside_samples(fid: np.ndarray, bank: TemplateBank, pose: Pose) -> _Inside | None:
    """``None`` with fewer than ``MIN_SHADING_PIXELS``."""
    inner = cv2.erode((fid >= 0).astype(np.uint8), np.ones((2 * SHADING_ERODE_PX + 1,) * 2, np.uint8))
    # Every other row and column: the fits need thousands of pixels, not all.
    vi, ui = np.nonzero(inner[::2, ::2])
    if len(vi) < MIN_SHADING_PIXELS:
        return None
    vi, ui = 2 * vi, 2 * ui
    f = fid[vi, ui]
    # The faces seen, sorted, and each pixel's index among them (np.unique's, without its sort).
    seen = np.zeros(len(bank.faces), bool)
    seen[f] = True
    visible = np.flatnonzero(seen)
    index = (np.cumsum(seen) - 1)[f]
    n = face_normals_cam(bank.vertices_mm, bank.faces[visible], pose.R, pose.t_mm)[index].astype(np.float64)
    return _Inside(vi, ui, n)


def _normal_design(n: np.ndarray) -> np.ndarray:
    """(N, 3) unit normals -> (N, 10) quadratic design: 1, n, n * n, the cross products."""
    return np.hstack([np.ones((len(n), 1)), n, n * n, n[:, [0]] * n[:, [1]], n[:, [1]] * n[:, [2]],
                      n[:, [0]] * n[:, [2]]])


def _shading(win: _Window, inside: _Inside | None) -> tuple[float, float]:
    if inside is None:
        return 0.0, 0.0
    grey = cv2.cvtColor(win.bgr[inside.v, inside.u][None], cv2.COLOR_BGR2GRAY)[0].astype(np.float64)
    A = _normal_design(inside.normals)
    # Normal equations: the 10 x 10 system costs a fraction of an SVD of the (pixels x 10) one.
    coef = np.linalg.lstsq(A.T @ A, A.T @ grey, rcond=None)[0]
    res = grey - A @ coef
    var = float(grey.var())
    return (float(1.0 - res.var() / var) if var > 0 else 0.0), float(np.sqrt(var))


def appearance(win: _Window, fid: np.ndarray, inside: _Inside | None, face_bgr: np.ndarray
               ) -> tuple[float, float]:
    """How well the taught face colours (``model/appearance.py``) predict the inside's colours ->
    (correlation, share of the inside whose face colour is known).

    The correlation is Pearson's over the three channels pooled, after each channel's mean is removed,
    on the ``1 - APPEARANCE_TRIM`` share of the known pixels an affine colour map from taught to seen
    colours fits best: the light differs between the reference photos and this one (an affine map per
    channel absorbs a change of gain and offset), and an occluder's pixels are the ones it fits worst.
    A printed or painted part at its true pose scores high; a pose fitted to texture or to another
    object sees colours unrelated to the part's pattern and scores near 0."""
    if inside is None:
        return 0.0, 0.0
    taught = face_bgr[fid[inside.v, inside.u]]
    known = np.isfinite(taught[:, 0])
    share = float(known.mean())
    if known.sum() < MIN_SHADING_PIXELS:
        return 0.0, share
    P = taught[known].astype(np.float64)
    O = win.bgr[inside.v[known], inside.u[known]].astype(np.float64)
    A = np.column_stack([P, np.ones(len(P))])
    res = np.linalg.norm(O - A @ np.linalg.lstsq(A.T @ A, A.T @ O, rcond=None)[0], axis=1)
    keep = res <= np.quantile(res, 1.0 - APPEARANCE_TRIM)
    Oc, Pc = O[keep] - O[keep].mean(axis=0), P[keep] - P[keep].mean(axis=0)
    denom = float(np.sqrt((Oc * Oc).sum() * (Pc * Pc).sum()))
    return (float((Oc * Pc).sum() / denom) if denom > 0 else 0.0), share


APPEARANCE_TRIM = 0.25  # the share of the known pixels left out as an occluder's (``appearance``)


@dataclass(frozen=True)
class _Covered:
    """What ``pose`` covers in the frame, as every measure of it reads it."""
    fid: np.ndarray  # (h, w) visible face index in the window, -1 off the part or hidden by another part
    mask: np.ndarray  # (h, w) bool: the silhouette (hidden pixels included)
    hidden: np.ndarray | None  # silhouette pixels another, nearer part covers
    explained: np.ndarray | None  # pixels outside the silhouette another part covers
    win: _Window
    band: int  # region band width, px
    p: np.ndarray  # (N, 2) outline points, window px (``_outline``)
    n: np.ndarray  # (N, 2) their outward normals
    in_image: np.ndarray  # (N,) bool: the outline point lies inside the image


def _covered(bank: TemplateBank, pose: Pose, intr: Intrinsics, frame: ColourFrame,
             others_depth_mm: np.ndarray | None) -> _Covered | None:
    """``None`` where the pose covers no pixel or has no outline in the frame."""
    H, W = frame.shape
    fid, invz, (u0, v0) = face_ids_roi(bank, pose, intr, (W, H), margin_px=BAND_MAX_PX + 2)
    mask = fid >= 0
    hidden = explained = None
    if others_depth_mm is not None:
        others = others_depth_mm[v0:v0 + mask.shape[0], u0:u0 + mask.shape[1]]
        with np.errstate(divide="ignore"):
            own_depth = np.where(mask, 1.0 / np.maximum(invz, 1e-12), np.inf)
        hidden = mask & (others < own_depth - OCCLUSION_MARGIN_MM)
        explained = ~mask & np.isfinite(others)
        fid = np.where(hidden, -1, fid)
    n_px = int(mask.sum())
    if n_px == 0:
        return None
    p, n = _outline(mask)
    if len(p) == 0:
        return None
    u, v = p[:, 0] + u0, p[:, 1] + v0
    in_image = (u >= 1) & (u < W - 1) & (v >= 1) & (v < H - 1)
    band = int(np.clip(BAND_FRACTION * np.sqrt(n_px / np.pi), BAND_MIN_PX, BAND_MAX_PX))
    return _Covered(fid, mask, hidden, explained, _window(frame, u0, v0, mask.shape[1], mask.shape[0]), band,
                    p, n, in_image)


def _nothing(face_bgr: np.ndarray | None) -> Evidence:
    # a part with taught colours keeps reporting its appearance: the verdict it gets reads it
    return NO_EVIDENCE if face_bgr is None else replace(NO_EVIDENCE, appearance=0.0, appearance_known=0.0)


def evidence(bank: TemplateBank, pose: Pose, intr: Intrinsics, frame: ColourFrame,
             others_depth_mm: np.ndarray | None = None, face_bgr: np.ndarray | None = None) -> Evidence:
    """The colour, polarity and region evidence for ``pose`` (T_cam_obj) in ``frame`` (ideal camera
    ``intr``, i.e. undistorted image coordinates).

    ``others_depth_mm``: (H, W) float32 depth of other parts already found in the frame (inf where
    there are none). Their pixels are explained: where one is nearer than this pose's surface it hides
    the part (left out of the inside and the shading fit), and next to the outline it is not the
    background (left out of the outside). Touching copies otherwise look like a part on a background
    of its own colour.

    ``face_bgr``: the part's taught colours (``model/appearance.Appearance.face_bgr``), if it has any:
    the evidence then includes ``appearance`` and ``appearance_known``."""
    c = _covered(bank, pose, intr, frame, others_depth_mm)
    if c is None:
        return _nothing(face_bgr)
    region_fut, _, m = _start_region_and_shading(c, bank, pose, face_bgr)
    colour_edge, polarity, coherence = _edge_and_polarity(c.win, c.p, c.n, c.in_image)
    generic = genericity(c.mask)
    region, region_low, region_global = region_fut.result()
    return Evidence(colour_edge, polarity, region, region_low, region_global, coherence, m["shading_r2"],
                    m["shading_std"], m["in_image"], generic, distinct_px(c.mask, generic),
                    appearance=m.get("appearance"), appearance_known=m.get("appearance_known"))


# The evidence ``region_and_shading`` measures: all a verification score of the service reads besides the
# refinement's own edge evidence (``verdict.WEIGHTS``, ``APPEARANCE_WEIGHTS``).
REGION_AND_SHADING = ("region", "region_low", "region_global", "shading_r2", "shading_std", "in_image",
                      "appearance", "appearance_known")


def region_and_shading(bank: TemplateBank, pose: Pose, intr: Intrinsics, frame: ColourFrame,
                       others_depth_mm: np.ndarray | None = None, face_bgr: np.ndarray | None = None
                       ) -> dict[str, float]:
    """``evidence(...).as_dict()``'s ``REGION_AND_SHADING`` entries (those a part without taught colours
    lacks left out), the same values, without the outline's edges or the plain-shape fit: the search
    scores hundreds of poses a frame as they stand, on the region and shading evidence only."""
    c = _covered(bank, pose, intr, frame, others_depth_mm)
    if c is None:
        ev = _nothing(face_bgr).as_dict()
        return {k: ev[k] for k in REGION_AND_SHADING if k in ev}
    region_fut, _, out = _start_region_and_shading(c, bank, pose, face_bgr)
    out["region"], out["region_low"], out["region_global"] = region_fut.result()
    return out


def _start_region_and_shading(c: _Covered, bank: TemplateBank, pose: Pose, face_bgr: np.ndarray | None
                              ) -> tuple[Future, _Inside | None, dict[str, float]]:
    """The region test started on the second core (its distance transforms release the GIL), and meanwhile
    the shading fit, the share in the image and the taught appearance: (the region's future, the inside's
    samples, those measures)."""
    region_fut = threads.background().submit(_region, c.win, c.mask, c.band, c.hidden, c.explained)
    inside = _inside_samples(c.fid, bank, pose)
    shading_r2, shading_std = _shading(c.win, inside)
    out = {"shading_r2": shading_r2, "shading_std": shading_std, "in_image": float(c.in_image.mean())}
    if face_bgr is not None:
        out["appearance"], out["appearance_known"] = appearance(c.win, c.fid, inside, face_bgr)
    return region_fut, inside, out
