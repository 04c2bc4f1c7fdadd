"""Pose proposals from colour-homogeneous image regions (issue #14: clutter).

On a textured floor the chamfer cost of texture is lower than that of a partly hidden true outline, so
ranking by chamfer cost loses the part; a person finds a single-coloured part by its region instead.
Every node of the image's region hierarchy (``segmentation``) is a candidate region. A candidate whose
area fits the part's projected area over the distance range is compared with every template's silhouette
(``Silhouettes``, rasterised once per bank): shape descriptors first (elongation, solidity), then the
intersection over union of the best templates placed on the region (depth from the area ratio,
in-plane angle from the principal axes), giving ``search.Hypothesis`` proposals ranked by IoU.
``refine_on_boundary`` then runs level B and the polish on the region's own boundary only (a clean
edge map: the floor's texture inside it does not count).
"""

from __future__ import annotations

import heapq
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numba as nb
import numpy as np

from service.vision.bank import TemplateBank, view_neighbours
from service.vision.deadline import NO_DEADLINE, Deadline, RunningMean
from service.vision.estimate.chamfer import distance_tensor, quantised
from service.vision.estimate.colour_prior import likelihood
from service.vision.estimate.edges import Segments
from service.vision.estimate.level_b import local_scan, polish
from service.vision.estimate.search import Hypothesis, SearchParams
from service.vision.estimate.segmentation import WORK_WIDTH, Regions, node_means, region_mask, segment, shrink
from service.vision.estimate.shapes import (
    CANON_PX,
    ROUND_ELONG,
    SCALES,
    best_iou_rows,
    canonical,
    canonical_turns,
    generic_family,
    principal_axis,
)
from service.vision.geometry.frames import Pose, Rz
from service.vision.geometry.render import rasterise_roi
from service.vision.memo import Memo

MASK_PX = 64  # template silhouettes are rasterised on MASK_PX x MASK_PX
AREA_SLACK = (0.35, 1.3)  # a region may hold this fraction of the smallest .. largest projected area
PER_REGION = 3  # proposals kept per region (distinct poses): silhouettes are ambiguous
PER_REGION_SCORED = 8  # ... when the proposals are scored before refinement (``region_proposals``' score)
SHAPE_GATE = 0.15  # a region farther than this from every template's (elongation, compactness) is dropped
N_REGIONS = 300  # candidate regions matched per frame, by contrast to their surroundings
DISTANCE_SLACK = 1.25  # a given distance: the part's reference point lies within this factor of it
# The look-alike gate: a region is evidence for the part only if the part's silhouette explains it
# clearly better than the best of a family of generic shapes (``shapes.generic_shapes``) does: a plain
# cylinder's or box's region is fitted by a revolved part's side view at IoU ~0.9 too, but a cylinder
# fits it better. Regions whose best part IoU is under best generic IoU + LOOKALIKE_MARGIN propose nothing.
LOOKALIKE_MARGIN = 0.0  # IoU (docs/detection-history.md)
GATE_CHUNK = 16  # regions gated per matrix product (the next ones to reach the front)


@dataclass(frozen=True)
class Silhouettes:
    masks: np.ndarray  # (N, S, S) uint8 0/1: template n's silhouette, reference point at the centre
    px_per_unit: float  # mask px per normalised image unit (x / z) at the bank's reference distance
    area_n: np.ndarray  # (N,) silhouette area, normalised units^2, at the reference distance
    centroid_n: np.ndarray  # (N, 2) silhouette centroid relative to the reference point, normalised
    axis_rad: np.ndarray  # (N,) principal axis angle (image x towards y)
    elong: np.ndarray  # (N,) sqrt(minor / major second moment)
    solidity: np.ndarray  # (N,) area / convex hull area
    compact: np.ndarray  # (N,) ``moment_shape``'s compactness


_SIL = Memo(8)


def silhouettes(bank: TemplateBank) -> Silhouettes:
    """Every template's silhouette (the mesh's faces filled), once per bank."""

    def make() -> Silhouettes:
        S = MASK_PX
        v = np.asarray(bank.vertices_mm, float) - bank.centre_obj
        r_obj = float(np.linalg.norm(v, axis=1).max())
        z_ref = bank.reference_distance_mm
        ppu = (S / 2 - 2) / (r_obj / (z_ref - r_obj))
        N = bank.n_templates
        masks = np.zeros((N, S, S), np.uint8)
        area = np.zeros(N)
        cen = np.zeros((N, 2))
        axis = np.zeros(N)
        elong = np.zeros(N)
        solid = np.zeros(N)
        compact = np.zeros(N)
        # a camera with focal length ppu and the reference point at the mask's centre
        K_m = np.array([[ppu, 0.0, S / 2 - 0.5], [0.0, ppu, S / 2 - 0.5], [0.0, 0.0, 1.0]])
        for n in range(N):
            R = bank.R_tpl_obj[n]
            pose = Pose(R, np.array([0.0, 0.0, z_ref]) - R @ bank.centre_obj)
            _, face, (u0, v0) = rasterise_roi(bank.vertices_mm, bank.faces, pose, K_m, (S, S))
            masks[n, v0:v0 + face.shape[0], u0:u0 + face.shape[1]] = face >= 0
            mo = cv2.moments(masks[n], True)
            if mo["m00"] <= 0:
                continue
            area[n] = mo["m00"] / ppu**2
            cen[n] = (np.array([mo["m10"], mo["m01"]]) / mo["m00"] + 0.5 - S / 2) / ppu
            axis[n], elong[n] = principal_axis(mo)
            solid[n] = _solidity(masks[n], mo["m00"])
            raw = np.array([[mo[k] for k in ("m00", "m10", "m01", "m20", "m11", "m02")]])
            compact[n] = moment_shape(raw)[1][0]
        return Silhouettes(masks, ppu, area, cen, axis, elong, solid, compact)

    return _SIL.get(bank, "sil", make)


def moment_shape(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(elongation sqrt(minor / major), compactness A / (4 pi sqrt(det cov))) from raw moments (M, 6):
    1 for a disc, 0.95 for a rectangle, less the more a region's mass is scattered (a merge of stripes)."""
    a0 = np.maximum(m[:, 0], 1e-9)
    cx, cy = m[:, 1] / a0, m[:, 2] / a0
    sxx = m[:, 3] / a0 - cx * cx + 1 / 12
    sxy = m[:, 4] / a0 - cx * cy
    syy = m[:, 5] / a0 - cy * cy + 1 / 12
    tr, det = sxx + syy, np.maximum(sxx * syy - sxy * sxy, 1e-12)
    disc = np.sqrt(np.maximum(tr * tr / 4 - det, 0))
    l1, l2 = tr / 2 + disc, np.maximum(tr / 2 - disc, 1e-12)
    return np.sqrt(l2 / l1), a0 / (4 * np.pi * np.sqrt(det))


def _solidity(mask: np.ndarray, area: float) -> float:
    cs, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if not cs:
        return 0.0
    hull = cv2.convexHull(np.concatenate(cs))
    ha = cv2.contourArea(hull)
    return float(min(area / ha, 1.0)) if ha > 0 else 1.0


# --- segmentation ----------------------------------------------------------------------------------


def bgr_u8(image: np.ndarray) -> np.ndarray:
    """A frame as 8-bit BGR (grey repeated, an alpha channel dropped, other depths stretched to 0..255)."""
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    image = image[..., :3]
    if image.dtype != np.uint8:
        image = cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    return image


def searched_range(distance_mm: float | None, distance_range_mm: tuple[float, float]) -> tuple[float, float]:
    """The depths searched: ``distance_range_mm``, or within ``DISTANCE_SLACK`` of a given distance."""
    if distance_mm is None:
        return distance_range_mm
    return distance_mm / DISTANCE_SLACK, distance_mm * DISTANCE_SLACK


def working_likelihood(image_bgr: np.ndarray, part_colours: np.ndarray, work_width: int = WORK_WIDTH
                       ) -> np.ndarray:
    """``colour_prior.likelihood`` of the image shrunk as ``smooth`` shrinks it (before mean shift)."""
    return likelihood(shrink(image_bgr, work_width)[1], part_colours)


# --- proposals -------------------------------------------------------------------------------------


@dataclass
class RegionProposal:
    hyp: Hypothesis
    iou: float
    region: int  # candidate index in ``Regions``
    # the look-alike gate's reading of the region: its best part IoU - its best generic IoU (nan: gate off)
    lookalike_gap: float = float("nan")


def projected_area_range(bank: TemplateBank, sil: Silhouettes, K: np.ndarray,
                         distance_range_mm: tuple[float, float]) -> tuple[float, float]:
    """Full-resolution px^2: smallest and largest silhouette area over the templates and distances."""
    f2 = float(K[0, 0] * K[1, 1])
    z_ref = bank.reference_distance_mm
    ok = sil.area_n > 0
    lo = float(sil.area_n[ok].min()) * f2 * (z_ref / distance_range_mm[1]) ** 2
    hi = float(sil.area_n[ok].max()) * f2 * (z_ref / distance_range_mm[0]) ** 2
    return lo, hi


_CANON = Memo(8)
_CANON_AREA = Memo(8)


def canonical_templates(bank: TemplateBank, sil: Silhouettes) -> np.ndarray:
    """(len(SCALES), N, CANON_PX^2) every template's silhouette in its canonical frame, per area scale."""

    def make() -> np.ndarray:
        out = np.zeros((len(SCALES), bank.n_templates, CANON_PX * CANON_PX), np.float32)
        for n in range(bank.n_templates):
            mo = cv2.moments(sil.masks[n], True)
            if mo["m00"] <= 0:
                continue
            for k, s_a in enumerate(SCALES):
                out[k, n] = canonical(sil.masks[n], mo, sil.axis_rad[n], s_a).ravel() > 0.5
        return out

    return _CANON.get(bank, "canon", make)


@dataclass(frozen=True)
class CandidateStages:
    """The regions ``propose`` matches, gate by gate (node indices, each a subset of the one before)."""
    sized: np.ndarray  # area within the part's projected area over the distance range (AREA_SLACK)
    framed: np.ndarray  # ... not spanning most of the image (floor), and not a speck
    shaped: np.ndarray  # ... elongation and compactness within SHAPE_GATE of some template's
    ranked: np.ndarray  # ... the N_REGIONS that stand out most from their surroundings, in that order


def candidate_stages(sil: Silhouettes, reg: Regions, K: np.ndarray, bank: TemplateBank,
                     distance_range_mm: tuple[float, float],
                     purity: np.ndarray | None = None) -> CandidateStages:
    a_lo, a_hi = projected_area_range(bank, sil, K, distance_range_mm)
    area_full = reg.area / reg.scale**2
    sized = np.flatnonzero((area_full >= AREA_SLACK[0] * a_lo) & (area_full <= AREA_SLACK[1] * a_hi))
    h, w = reg.labels.shape
    # a region touching most of the image border is floor
    bw = reg.bbox[:, 2] - reg.bbox[:, 0]
    bh = reg.bbox[:, 3] - reg.bbox[:, 1]
    framed = sized[(bw[sized] < 0.9 * w) & (bh[sized] < 0.9 * h) & (reg.area[sized] >= 12)]
    # shaped like some template (elongation and compactness from the additive moments), then the
    # regions that stand out most from all their surroundings (merged latest) first
    el, co = moment_shape(reg.moments[framed])
    ok_t = sil.area_n > 0
    shaped = framed[_shape_gate(el, co, sil.elong[ok_t], sil.compact[ok_t], SHAPE_GATE)]
    key = reg.died[shaped] if purity is None else purity[shaped]
    ranked = shaped[np.argsort(-key, kind="stable")[:N_REGIONS]]
    return CandidateStages(sized, framed, shaped, ranked)


def propose(bank: TemplateBank, image_bgr: np.ndarray, K: np.ndarray,
            distance_range_mm: tuple[float, float], *, n_out: int = 30,
            reg: Regions | None = None, purity: np.ndarray | None = None, per_region: int = PER_REGION,
            lookalike_margin: float | None = LOOKALIKE_MARGIN) -> tuple[list[RegionProposal], Regions]:
    """Region proposals, best IoU first, mutually distinct (reference points, depths or rotations apart).

    ``purity``: (C,) per node of ``reg`` in [0, 1], how much it looks like the part (``colour_prior``,
    for a taught part): the regions matched are then the purest, and proposals come best IoU x purity
    first. ``per_region``: distinct fits a region may propose. ``lookalike_margin``: the look-alike gate's
    margin (None: no gate, what the reference implementation is compared with)."""
    sil = silhouettes(bank)
    canon = canonical_templates(bank, sil)
    t_area = _CANON_AREA.get(bank, "area", lambda: canon.sum(2))  # (S, N)
    reg = reg if reg is not None else segment(image_bgr)
    sc = reg.scale
    cand = candidate_stages(sil, reg, K, bank, distance_range_mm, purity).ranked
    ok_t = sil.area_n > 0
    fx, fy = float(K[0, 0]), float(K[1, 1])
    F = np.diag([fx, fy])
    z_ref = bank.reference_distance_mm
    bad_t = ~ok_t
    # every region's canonical turns first, then one product per area scale for all of them
    info = []
    masks = []
    n_rows = 0
    for c in cand:
        m = region_mask(reg, int(c))
        mo = cv2.moments(m, True)
        if mo["m00"] < 12:
            continue
        ang_r, el_r = principal_axis(mo)
        # the region turned by each of these onto the templates' canonical frame: its axis either
        # way round; a roundish region every 30 degrees (its axis says little)
        turns = (0.0, 180.0) if el_r < ROUND_ELONG else tuple(range(0, 360, 30))
        x0, y0 = reg.bbox[c, :2]
        c_full = (np.array([mo["m10"], mo["m01"]]) / mo["m00"] + np.array([x0, y0]) + 0.5) / sc - 0.5
        info.append((int(c), ang_r, turns, c_full, mo["m00"] / sc**2, n_rows))
        masks.append((m.astype(np.float32), mo))
        n_rows += len(turns)
    if not n_rows:
        return [], reg
    # every turn written straight into the product's rows (the size the reference's stack had)
    rows = np.empty((n_rows, CANON_PX * CANON_PX), np.float32)
    for (_, ang_r, turns, _, _, r0), (m_f, mo) in zip(info, masks, strict=True):
        canonical_turns(m_f, mo, [ang_r + math.radians(tn) for tn in turns], rows[r0:r0 + len(turns)])
    Rc_all = rows  # (sum of turns, G^2)
    r_area_all = Rc_all.sum(1)
    inter_all = [Rc_all @ canon[k].T for k in range(len(SCALES))]  # (sum of turns, N) per scale
    # every region's best template fits per area scale at once, regions with as many turns together:
    # the same IoU per (turn, template) and the same sort of each region's (turns x templates) block
    N = bank.n_templates
    A_r = np.array([x[4] for x in info])
    den = np.maximum(sil.area_n, 1e-12) * fx * fy
    kz_all = [np.sqrt(s_a * A_r[:, None] / den[None]) for s_a in SCALES]  # (regions, N) per scale
    z_all = [z_ref / kz for kz in kz_all]
    far = [(z < distance_range_mm[0]) | (z > distance_range_mm[1]) for z in z_all]
    n_top = per_region * 4
    top: list[list] = [[None] * len(SCALES) for _ in info]
    n_turns = np.array([len(x[2]) for x in info])
    for T in np.unique(n_turns):
        ids = np.flatnonzero(n_turns == T)
        at = np.array([info[i][5] for i in ids])[:, None] + np.arange(T)  # (G, T) rows
        r_area = r_area_all[at][..., None]
        for k in range(len(SCALES)):
            inter = inter_all[k][at]  # (G, T, N)
            iou = inter / (r_area + t_area[k][None, None] - inter + 1e-9)
            iou[:, :, bad_t] = 0
            iou[np.broadcast_to(far[k][ids][:, None, :], iou.shape)] = 0
            best = _best_fits(iou.reshape(len(ids), T * N), n_top)
            for g, i in enumerate(ids.tolist()):
                top[i][k] = best[g]
    # Each region's fits, best first (positive ones: the reference takes them down to the first zero).
    fits: list[list[tuple]] = []
    for g, (_, _, turns, _, _, _) in enumerate(info):
        scored = []
        for k in range(len(SCALES)):
            z, kz = z_all[k][g], kz_all[k][g]
            for idx, v in zip(*top[g][k], strict=True):
                if v <= 0:
                    break
                ti, t = divmod(idx, N)
                scored.append((v, t, float(turns[ti]), float(z[t]), float(kz[t])))
        scored.sort(key=lambda x: -x[0])
        fits.append(scored)
    # A region proposes its fits in that order, each distinct from its earlier ones, up to PER_REGION
    # (its "survivors"); all regions' survivors are then taken best IoU first (ties: region order, then
    # the region's order, as a stable sort of them all) while distinct from the kept ones, up to n_out.
    # Survivors are made lazily, a region's next one when its last is taken: a merge of the regions'
    # lists in that order, so only the few that reach the front are posed and compared.
    nxt = [0] * len(info)  # each region's next fit to try
    survivors: list[list[RegionProposal]] = [[] for _ in info]

    generic, generic_area = generic_family() if lookalike_margin is not None else (None, None)
    gap = [float("nan")] * len(info)
    # regions in the order their first fits reach the front: the gate reads them in chunks of this order
    # (one product per chunk reads the family's masks once for many regions: one region at a time is
    # bound by that read)
    gate_order = sorted((g for g, f in enumerate(fits) if f), key=lambda g: -fits[g][0][0])
    gate_pos = {g: i for i, g in enumerate(gate_order)}

    def gate(g: int) -> None:
        chunk = [q for q in gate_order[gate_pos[g]:gate_pos[g] + GATE_CHUNK] if math.isnan(gap[q])]
        spans = [(info[q][5], info[q][5] + len(info[q][2])) for q in chunk]
        best = best_iou_rows(np.concatenate([Rc_all[a:b] for a, b in spans]), generic, generic_area)
        at = 0
        for q, (a, b) in zip(chunk, spans, strict=True):
            gap[q] = fits[q][0][0] - float(best[at:at + b - a].max())
            at += b - a

    def advance(g: int) -> RegionProposal | None:
        c, ang_r, turns, c_full, _, r0 = info[g]
        mine = survivors[g]
        # the look-alike gate, once per region when its first fit reaches the front: the region's turns
        # against the generic family (a region that never gets there costs nothing); a region it drops
        # only leaves the ungated list (``kept`` below), its place not refilled
        if generic is not None and not mine and nxt[g] == 0 and fits[g] and math.isnan(gap[g]):
            gate(g)
        while nxt[g] < len(fits[g]) and len(mine) < per_region:
            iou_v, t, tn, z, kz = fits[g][nxt[g]]
            nxt[g] += 1
            # the template's axis (canonical x) is the region's axis turned by tn: in-plane angle
            phi = math.degrees(ang_r - sil.axis_rad[t]) + tn
            cp, sp = math.cos(math.radians(phi)), math.sin(math.radians(phi))
            uv_ref = c_full - F @ np.array([[cp, -sp], [sp, cp]]) @ sil.centroid_n[t] * kz
            hyp = Hypothesis(t, float(phi % 360), z, uv_ref)
            if any(_same(hyp, q.hyp, bank) for q in mine):
                continue
            mine.append(RegionProposal(hyp, iou_v, c, gap[g]))
            return mine[-1]
        return None

    # a taught part's regions are taken by fit x purity: a distractor's region fits a silhouette too
    weight = [1.0 if purity is None else float(purity[x[0]]) for x in info]
    front = [(-f[0][0] * weight[g], g, 0) for g, f in enumerate(fits) if f]  # a region's first fit survives
    heapq.heapify(front)
    kept: list[RegionProposal] = []
    n_keep = max(n_out, 1)  # (the reference's loop stops after the first kept one that reaches n_out)
    kept_uv = np.zeros((n_keep, 2))
    while front and len(kept) < n_keep:
        _, g, pos = heapq.heappop(front)
        r = survivors[g][pos] if pos < len(survivors[g]) else advance(g)
        if r is None:
            continue
        following = advance(g)
        if following is not None:
            heapq.heappush(front, (-following.iou * weight[g], g, pos + 1))
        # ``_same`` needs the reference points within 8 px first: only those few are compared in full
        d = r.hyp.uv - kept_uv[:len(kept)]
        near = np.flatnonzero(np.hypot(d[:, 0], d[:, 1]) < 8.0)
        if any(_same(r.hyp, kept[q].hyp, bank) for q in near):
            continue
        kept_uv[len(kept)] = r.hyp.uv
        kept.append(r)
    if generic is not None:
        kept = [r for r in kept if r.lookalike_gap >= lookalike_margin]
    return kept, reg


def _best_fits(iou: np.ndarray, n_top: int) -> list[tuple[list[int], list[float]]]:
    """Per row of ``iou`` (regions, turns x templates): the positive entries among the first ``n_top`` of
    ``np.argsort(-row)`` (indices, values), best first, as the reference takes them. A partition finds
    the ``n_top`` + 1 largest; when no two positive ones among them are equal their order is the sort's
    whatever its tie rule, else the row is sorted in full as the reference sorts it."""
    n_rows, n_cols = iou.shape
    if n_cols <= n_top + 1:
        order = [np.argsort(-row)[:n_top] for row in iou]
        return [(o.tolist(), row[o].tolist()) for o, row in zip(order, iou, strict=True)]
    part = np.argpartition(-iou, n_top, axis=1)[:, :n_top + 1]
    pv = np.take_along_axis(iou, part, 1)
    o = np.argsort(-pv, axis=1, kind="stable")
    part, pv = np.take_along_axis(part, o, 1), np.take_along_axis(pv, o, 1)
    tied = ((pv[:, 1:] == pv[:, :-1]) & (pv[:, 1:] > 0)).any(1)
    out = []
    for g in range(n_rows):
        if tied[g]:
            best = np.argsort(-iou[g])[:n_top]
            out.append((best.tolist(), iou[g, best].tolist()))
        else:
            out.append((part[g, :n_top].tolist(), pv[g, :n_top].tolist()))
    return out


@nb.njit(cache=True)
def _shape_gate(el, co, el_t, co_t, gate):
    """Whether some template's |elongation difference| + |compactness difference| is below ``gate``, per
    region (the first such template ends the search)."""
    ok = np.zeros(el.shape[0], np.bool_)
    for i in range(el.shape[0]):
        for t in range(el_t.shape[0]):
            if abs(el[i] - el_t[t]) + abs(co[i] - co_t[t]) < gate:
                ok[i] = True
                break
    return ok


def _same(a: Hypothesis, b: Hypothesis, bank: TemplateBank) -> bool:
    """Two proposals one pose: reference points within 8 px, depths within 10 %, rotations within 15 deg."""
    if np.hypot(*(a.uv - b.uv)) >= 8.0 or abs(math.log(a.z_mm / b.z_mm)) >= 0.1:
        return False
    Ra = Rz(a.phi_deg) @ bank.R_tpl_obj[a.view]
    Rb = Rz(b.phi_deg) @ bank.R_tpl_obj[b.view]
    return (np.trace(Ra @ Rb.T) - 1) / 2 > math.cos(math.radians(15.0))


def boundary_segments(reg: Regions, c: int, image_shape: tuple[int, int]) -> Segments:
    """The candidate region's outline as segments in full-resolution pixels, through its boundary pixels'
    centres."""
    m = region_mask(reg, c)
    x0, y0 = reg.bbox[c, :2]
    cs, _ = cv2.findContours(np.pad(m, 1), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    uv0, uv1 = [], []
    for cnt in cs:
        ab = _chords(cnt.reshape(-1, 2))
        if ab is None:
            continue
        a, b = ab
        shift = np.array([x0, y0], np.float32) - 1 + 0.5
        uv0.append((a + shift) / reg.scale - 0.5)
        uv1.append((b + shift) / reg.scale - 0.5)
    if not uv0:
        e = np.zeros((0, 2), np.float32)
        return Segments(e, e, np.zeros(0, np.float32), image_shape)
    a, b = np.concatenate(uv0), np.concatenate(uv1)
    d = b - a
    theta = np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi).astype(np.float32)
    return Segments(a, b, theta, image_shape)


def _chords(contour: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The contour's polygon as segments through its boundary pixels' centres."""
    poly = _polygon(contour).astype(np.float32)
    return (poly, np.roll(poly, -1, axis=0)) if len(poly) >= 2 else None


def _polygon(contour: np.ndarray) -> np.ndarray:
    """The vertices (M, 2) int of a contour's polygon (``approxPolyDP``, within 0.7 px), a subset of its
    points in its order."""
    return cv2.approxPolyDP(contour.reshape(-1, 1, 2), 0.7, True).reshape(-1, 2)


def refine_on_boundary(bank: TemplateBank, prop: RegionProposal, reg: Regions, K: np.ndarray,
                       image_shape: tuple[int, int], p: SearchParams, *, level_b: bool = True,
                       distance_mm: float | None = None) -> Hypothesis:
    """Level B (optional) and the polish from a region proposal on the region's own outline."""
    seg = boundary_segments(reg, prop.region, image_shape)
    dtt = distance_tensor(seg, n_channels=p.n_channels, scale=p.fine_scale)
    h = Hypothesis(prop.hyp.view, prop.hyp.phi_deg, prop.hyp.z_mm, prop.hyp.uv.copy())
    if level_b:
        dt_q, tau_q = quantised(dtt, p.rank_tau_px * dtt.scale)
        hb, _ = local_scan(bank, h, dt_q, tau_q, dtt, K, p, distance_mm=distance_mm, accept_q=int(tau_q))
        if hb is not None:
            h = hb
    return polish(bank, h, dtt, K, p, distance_mm=distance_mm, neighbours=view_neighbours(bank),
                  step_phi_deg=2.0, step_uv_px=2.0, step_z=0.04)


def refine_all(bank: TemplateBank, props: list[RegionProposal], reg: Regions, K: np.ndarray,
               image_shape: tuple[int, int], p: SearchParams, *, distance_mm: float | None = None,
               deadline: Deadline = NO_DEADLINE, reserve_ms: float = 0.0) -> list[Hypothesis]:
    """``refine_on_boundary`` of each proposal in order, each started only if the previous one's duration
    and ``reserve_ms`` fit the ``deadline``. (Keeping a region's outline distance tensor for its other
    proposals saved no CPU: the kept full-frame tensors cost fresh pages instead.)"""
    out: list[Hypothesis] = []
    deadline.new_loop()
    for r in props:
        if not deadline.allows_next(reserve_ms):
            break
        out.append(refine_on_boundary(bank, r, reg, K, image_shape, p, distance_mm=distance_mm))
    return out


# What segmenting a frame and matching its regions (``propose``) take in this process, ms: they start only
# when a deadline leaves this much. Starts at clutter2's median after the numba merge (2 shared cores).
_PROPOSE_MS = RunningMean(200.0)


def region_proposals(bank: TemplateBank, image: np.ndarray, K: np.ndarray, image_shape: tuple[int, int],
                     p: SearchParams, *, distance_mm: float | None, distance_range_mm: tuple[float, float],
                     n_out: int, deadline: Deadline = NO_DEADLINE,
                     reserve_ms: float = 0.0, part_colours: np.ndarray | None = None,
                     score: Callable[[list[Hypothesis]], list[float]] | None = None,
                     n_scored: int = 0, likelihood: Callable[[], np.ndarray] | None = None
                     ) -> list[Hypothesis]:
    """The first ``n_out`` region proposals (``propose``), each refined on its region's outline
    (``refine_on_boundary``), in the proposals' order (silhouette IoU). With ``distance_mm`` the
    regions' areas are judged within ``DISTANCE_SLACK`` of it. Anytime: with a ``deadline`` nothing is
    proposed unless segmenting and matching (their running mean's ``high``) and ``reserve_ms`` fit, and
    each refinement starts only if the previous one's duration and ``reserve_ms`` do (fewer proposals,
    best first, rather than a late answer). ``part_colours``: a taught part's colour density
    (``colour_prior.part_density``): regions are then ranked by how part-coloured they are too.
    ``score`` (hypotheses -> their scores) with ``n_scored`` > ``n_out``: that many proposals, up to
    ``PER_REGION_SCORED`` a region, are scored and the best ``n_out`` refined.
    ``likelihood``: makes ``working_likelihood`` of the frame and ``part_colours`` (a caller's, made once
    for several passes) instead."""
    if not deadline.allows(_PROPOSE_MS.high + reserve_ms):
        return []
    image = bgr_u8(image)
    rng = searched_range(distance_mm, distance_range_mm)
    t0 = time.perf_counter()
    if likelihood is None and part_colours is not None:
        lik = working_likelihood(image, part_colours)
    else:
        lik = None if likelihood is None else likelihood()
    reg = segment(image)
    purity = None if lik is None else node_means(reg, lik)
    if score is None or n_scored <= n_out:
        props, reg = propose(bank, image, K, rng, n_out=n_out, reg=reg, purity=purity)
    else:
        # more fits per region, the best ``n_out`` by ``score`` refined: a region's silhouette fits
        # several rotations about as well, and a taught part's colours tell them apart
        props, reg = propose(bank, image, K, rng, n_out=n_scored, reg=reg, purity=purity,
                             per_region=PER_REGION_SCORED)
        s = np.asarray(score([r.hyp for r in props]), float)
        props = [props[i] for i in np.argsort(-s, kind="stable")[:n_out]]
    _PROPOSE_MS.add((time.perf_counter() - t0) * 1000.0)
    return refine_all(bank, props, reg, K, image_shape, p, distance_mm=distance_mm, deadline=deadline,
                      reserve_ms=reserve_ms)
