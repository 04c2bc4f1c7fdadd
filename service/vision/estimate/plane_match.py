"""Gradient-orientation search of a part resting on a known plane: every resting family x spin x
position on the plane, scored on LINE-2D response maps (``gradients.py``).

Templates: each family's edge points (``model/edge_points.py``) posed at each spin with the part's
reference point ``centre_obj`` over the centre of each of ``zones`` x ``zones`` image zones (perspective:
a part far from the centre is seen from the side), projected by the request's camera; each point keeps
its pixel offset from the reference point's projection (the anchor) and the orientation of its
projected tangent's normal. Its weight is 1 / (the template's points in the same orientation bin, at
least ``n / (2 N_ORI)``), normalised: a template that is mostly one straight edge does not score high on
any straight edge.

Search: each zone's templates at every ``t``-pixel cell of the zone, the best score per cell; local maxima
refined to the pixel and to the neighbouring spins; non-maximum suppression; at each place kept, its
rivals: other rotations scoring nearly as well round it (``rivals``: one outline, two poses); each lifted
to ``T_cam_obj`` resting on the plane at that anchor (``geometry/plane.placements``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from service.vision.bank import TemplateBank
from service.vision.estimate.edge_agreement import edge_normals_px, share_agreeing
from service.vision.estimate.gradients import (
    ResponseMaps,
    balanced_weights,
    best_in_window,
    best_near,
    best_on_grid,
    quantise,
    response_maps,
)
from service.vision.estimate.plane import PlaneHypothesis, rotations
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, Rz
from service.vision.geometry.plane import Plane, R_cam_rest, placements, rest_heights_mm
from service.vision.memo import Memo
from service.vision.model.edge_points import EMPTY_EDGES, EdgePoints, edge_points_at

MIN_TEMPLATE_POINTS = 12  # a view showing fewer edge points is not searched


@dataclass(frozen=True)
class PlaneTemplates:
    """Templates of one part on one plane seen by one camera (M of them, P points at most each)."""

    t: int  # the grid step they are searched on, px
    spin_step_deg: float
    dx: np.ndarray  # (M, P) int32 pixel offsets from the anchor (u)
    dy: np.ndarray  # (M, P) int32 (v)
    ori: np.ndarray  # (M, P) int32 orientation bin
    weight: np.ndarray  # (M, P) float32, each row summing to 1 (0 pads)
    n_pts: np.ndarray  # (M,) int32
    family: np.ndarray  # (M,) int: resting family
    psi_deg: np.ndarray  # (M,) spin about the plane's normal
    zone: np.ndarray  # (M,) int
    cells: np.ndarray  # (M, 4) int64 grid cells (gx0, gy0, gx1, gy1) the template is searched over
    R: np.ndarray  # (M, 3, 3) R_cam_obj
    h_mm: np.ndarray  # (M,) height of centre_obj above the plane
    rotation: np.ndarray  # (M,) int: the family x spin the template shows, an index into ``points``
    points: tuple[EdgePoints, ...]  # each family x spin's visible edge points, object frame


@dataclass(frozen=True)
class PlaneMatch:
    score: float  # the share of the template's points whose gradient agrees, weighted
    uv: tuple[float, float]  # the anchor: where centre_obj projects
    template: int
    pose: Pose
    place: int = 0  # matches of one place: the best there and its rivals (``rivals``)


def radius_px(bank: TemplateBank, intr: Intrinsics, plane: Plane, image_size: tuple[int, int]) -> float:
    """The part's radius in pixels where the plane meets the image centre's ray."""
    w, h = image_size
    ray = np.array([(w / 2 - intr.cx) / intr.fx, (h / 2 - intr.cy) / intr.fy, 1.0])
    z = plane.d_mm / float(ray @ plane.normal)
    return 0.5 * bank.diameter_mm * intr.fx / max(abs(z), 1e-6)


def spin_step_for(r_px: float, t: int, lo_deg: float, hi_deg: float) -> float:
    """A spin step (deg) that moves the part's farthest point by about ``t`` px, within [lo, hi],
    dividing 360."""
    step = float(np.clip(math.degrees(t / max(r_px, 1.0)), lo_deg, hi_deg))
    return 360.0 / math.ceil(360.0 / step)


def plane_templates(bank: TemplateBank, creases: np.ndarray, R_rest_obj: np.ndarray, intr: Intrinsics,
                    image_size: tuple[int, int], plane: Plane, *, t: int, spin_step_deg: float,
                    zones: int) -> PlaneTemplates:
    """Every family x spin: its visible edges rendered with the part at the image centre (the camera's
    own view of it: a tilted camera sees other sides than one looking straight down), projected with the
    part at the centre of each of ``zones`` x ``zones`` image zones."""
    hyp = rotations(bank, R_rest_obj, plane, spin_step_deg)
    w_img, h_img = image_size
    centre = np.array([(w_img - 1) / 2.0, (h_img - 1) / 2.0])
    t_centre, ok_centre = placements(hyp.R, hyp.h_mm, np.repeat(centre[None], len(hyp.R), 0), bank, intr,
                                     plane)
    V, F = np.asarray(bank.vertices_mm, float), np.asarray(bank.faces, np.int64)
    points = [edge_points_at(V, F, creases, Pose(hyp.R[m], t_centre[m]), intr, image_size) if ok_centre[m]
              else EMPTY_EDGES for m in range(len(hyp.R))]
    usable = np.flatnonzero([len(e.p_obj) >= MIN_TEMPLATE_POINTS for e in points])
    P = max([len(points[m].p_obj) for m in usable], default=1)
    rows = []
    for j in range(zones):
        for i in range(zones):
            rect = (i * w_img // zones, j * h_img // zones,
                    (i + 1) * w_img // zones, (j + 1) * h_img // zones)
            anchor = np.array([(rect[0] + rect[2] - 1) / 2.0, (rect[1] + rect[3] - 1) / 2.0])
            t_cam, ok = placements(hyp.R, hyp.h_mm, np.repeat(anchor[None], len(hyp.R), 0), bank, intr, plane)
            cells = (rect[0] // t, rect[1] // t, -(-rect[2] // t), -(-rect[3] // t))
            rows.append((usable[ok[usable]], anchor, t_cam, j * zones + i, cells))
    M = sum(len(r[0]) for r in rows)
    dx = np.zeros((M, P), np.int32)
    dy = np.zeros((M, P), np.int32)
    ori = np.zeros((M, P), np.int32)
    weight = np.zeros((M, P), np.float32)
    n_pts = np.zeros(M, np.int32)
    zone = np.zeros(M, int)
    cells = np.zeros((M, 4), np.int64)
    rotation = np.zeros(M, int)
    k = 0
    for idx, anchor, t_cam, z, c in rows:
        for m in idx:
            uv, theta = _projected(points[m], hyp.R[m], t_cam[m], intr)
            if not np.all(np.abs(uv - anchor) < max(w_img, h_img)):  # near the horizon: larger than the image
                continue
            n = len(uv)
            off = np.rint(uv - anchor).astype(np.int32)
            dx[k, :n], dy[k, :n] = off[:, 0], off[:, 1]
            ori[k, :n] = quantise(theta)
            weight[k, :n] = balanced_weights(ori[k, :n])
            n_pts[k], zone[k], cells[k], rotation[k] = n, z, c, m
            k += 1
    kept = (dx, dy, ori, weight, n_pts, zone, cells, rotation)
    dx, dy, ori, weight, n_pts, zone, cells, rotation = (a[:k] for a in kept)
    return PlaneTemplates(t, spin_step_deg, dx, dy, ori, weight, n_pts, hyp.s[rotation],
                          hyp.psi_deg[rotation], zone, cells, hyp.R[rotation], hyp.h_mm[rotation], rotation,
                          tuple(points))


def _projected(e: EdgePoints, R: np.ndarray, t_cam: np.ndarray, intr: Intrinsics
               ) -> tuple[np.ndarray, np.ndarray]:
    """Edge points posed at (R, t) -> (P, 2) pixels and (P,) edge-normal directions (rad)."""
    return edge_normals_px(e.p_obj @ R.T + t_cam, e.tangent_obj @ R.T, intr)


def match(rm: ResponseMaps, tpl: PlaneTemplates, bank: TemplateBank, intr: Intrinsics, plane: Plane, *,
          top_k: int, nms_px: float, min_score: float = 0.0, n_rivals: int = 0,
          rival_margin: float = 0.0) -> list[PlaneMatch]:
    """The best ``top_k`` placements, at least ``nms_px`` apart, each followed by up to ``n_rivals``
    other rotations scoring within ``rival_margin`` of it within ``nms_px`` (``rivals``), each lifted to
    T_cam_obj on the plane."""
    t = rm.t
    gh, gw = rm.grid_shape
    reach = max(int(np.abs(tpl.dx).max()), int(np.abs(tpl.dy).max()))
    if reach >= (rm.pad - 1) * t:
        raise ValueError("the templates outgrow the response maps' padding")
    cells = tpl.cells.copy()
    cells[:, 2] = np.minimum(cells[:, 2], gw)
    cells[:, 3] = np.minimum(cells[:, 3], gh)
    best = np.full((gh, gw), -1.0, np.float32)
    best_m = np.full((gh, gw), -1, np.int64)
    best_on_grid(rm.lin, rm.pad, t, tpl.dx, tpl.dy, tpl.ori, tpl.weight, tpl.n_pts, cells, best, best_m)
    peaks = np.argwhere((best >= cv2.dilate(best, np.ones((3, 3), np.uint8)) - 1e-9) & (best >= min_score))
    peaks = peaks[np.argsort(-best[peaks[:, 0], peaks[:, 1]], kind="stable")]
    picked: list[tuple[float, int, int, int]] = []
    for gy, gx in peaks:
        s, u, v, m = refine_placement(rm, tpl, gx * t, gy * t, int(best_m[gy, gx]), t // 2)
        if any((u - pu) ** 2 + (v - pv) ** 2 < nms_px ** 2 for _, pu, pv, _ in picked):
            continue
        picked.append((s, u, v, m))
        if len(picked) >= 3 * top_k:
            break
    picked.sort(key=lambda x: -x[0])
    out = []
    for place, (s, u, v, m) in enumerate(picked[:top_k]):
        here = [(s, u, v, m)]
        if n_rivals:
            here += rivals(rm, tpl, u, v, m, reach_px=nms_px, min_score=s - rival_margin, n=n_rivals)
        out += [PlaneMatch(s2, (float(u2), float(v2)), m2, lift(tpl, m2, (u2, v2), bank, intr, plane), place)
                for s2, u2, v2, m2 in here]
    return out


def rivals(rm: ResponseMaps, tpl: PlaneTemplates, u: int, v: int, m: int, *, reach_px: float,
           min_score: float, n: int) -> list[tuple[float, int, int, int]]:
    """Up to ``n`` (score, u, v, template) of other rotations than template m's (another family, or a
    spin more than two steps from it) scoring at least ``min_score`` within ``reach_px`` of (u, v),
    best first, no two of one family within two spin steps (the best ``3 n`` on the grid's cells, refined
    to the pixel: ``refine_placement``). A block lying on its side and the same block standing can show
    one outline: which of the two the grid scores best is a toss, the edges inside it tell them apart
    (``polish_on_gradients``)."""
    same = np.flatnonzero(tpl.zone == tpl.zone[m])
    other = np.array([k for k in same if not _same_rotation(tpl, k, m)], np.int64)
    if not len(other):
        return []
    t = rm.t
    gh, gw = rm.grid_shape
    r = int(math.ceil(reach_px / t))
    g0, h0 = max(u // t - r, 0), max(v // t - r, 0)
    g1, h1 = min(u // t + r + 1, gw), min(v // t + r + 1, gh)
    scores, at = best_in_window(rm.lin, rm.pad, t, tpl.dx, tpl.dy, tpl.ori, tpl.weight, tpl.n_pts, other,
                                g0, h0, g1, h1)
    # the grid's cells are a step apart: the best few rotations by it are refined, then judged
    tried: list[tuple[float, int, int, int]] = []
    for k in np.argsort(-scores, kind="stable"):
        if len(tried) >= 3 * n:
            break
        mm = int(other[k])
        if not any(_same_rotation(tpl, mm, o) for *_, o in tried):
            tried.append(refine_placement(rm, tpl, int(at[k, 0]) * t, int(at[k, 1]) * t, mm, t // 2))
    tried.sort(key=lambda x: -x[0])
    return [x for x in tried if x[0] >= min_score][:n]


def _same_rotation(tpl: PlaneTemplates, a: int, b: int) -> bool:
    """Templates a and b show one family within two spin steps."""
    return bool(tpl.family[a] == tpl.family[b]
                and _spin_gap(tpl.psi_deg[a], tpl.psi_deg[b]) <= 2 * tpl.spin_step_deg + 1e-6)


def _spin_gap(a_deg, b_deg):
    return np.abs((np.asarray(a_deg) - b_deg + 180.0) % 360.0 - 180.0)


def refine_placement(rm: ResponseMaps, tpl: PlaneTemplates, u: int, v: int, m: int, reach_px: int
                     ) -> tuple[float, int, int, int]:
    """The best (score, u, v, template) within ``reach_px`` of (u, v) over template m and its
    neighbouring spins (same family and zone)."""
    same = np.flatnonzero((tpl.family == tpl.family[m]) & (tpl.zone == tpl.zone[m]))
    dpsi = _spin_gap(tpl.psi_deg[same], tpl.psi_deg[m])
    s, u, v, m = best_near(rm.pixels, rm.pad * rm.t, tpl.dx, tpl.dy, tpl.ori, tpl.weight, tpl.n_pts,
                           same[dpsi <= tpl.spin_step_deg + 1e-6], int(u), int(v), int(reach_px), int(m))
    return float(s), int(u), int(v), int(m)


def lift(tpl: PlaneTemplates, m: int, uv: tuple[float, float], bank: TemplateBank, intr: Intrinsics,
         plane: Plane) -> Pose:
    """Template m's rotation resting on the plane with ``centre_obj`` on the ray through ``uv``."""
    t_cam, _ = placements(tpl.R[m][None], tpl.h_mm[m:m + 1], np.array([uv], float), bank, intr, plane)
    return Pose(tpl.R[m], t_cam[0])



def matches_as_hypotheses(matches: list[PlaneMatch], tpl: PlaneTemplates) -> list[PlaneHypothesis]:
    """The matches as the plane search's hypotheses (family, spin, anchor, pose), for its polish."""
    return [PlaneHypothesis(int(tpl.family[x.template]), float(tpl.psi_deg[x.template]),
                            np.array(x.uv, float), x.pose.R, x.pose.t_mm, score=x.score) for x in matches]


def best_at_each_place(hs: list[PlaneHypothesis], places: list[int], margin: float) -> list[PlaneHypothesis]:
    """The polished hypotheses place by place (in the order the places come), each place's best first,
    without those more than ``margin`` below its best: a rival that explains the edges there clearly
    better leaves the worse rotation nothing to be found on."""
    out = []
    for place in dict.fromkeys(places):
        here = sorted((h for h, p in zip(hs, places, strict=True) if p == place), key=lambda h: -h.score)
        out += [h for h in here if h.score >= here[0].score - margin]
    return out


@dataclass(frozen=True)
class GradientSearch:
    """The gradient search's settings (``pipeline/policy.Policy.gradient``)."""

    fine_t: int = 4  # grid step of a part smaller than ``big_part_px`` (radius), px
    coarse_t: int = 8  # grid step of a larger part: its templates tolerate more
    big_part_px: float = 40.0
    spin_step_deg: tuple[float, float] = (2.0, 10.0)  # the spin step's bounds (``spin_step_for``)
    zones: int = 3  # templates projected at the centre of zones x zones image zones
    nms_px: float = 16.0  # two matches closer than this are one
    proposals: int = 4  # matches proposed for one instance
    proposals_per_instance: int = 2  # and for each further instance
    rivals: int = 2  # other rotations proposed at each match's place (``rivals``)
    # a rival scores within this of its place's match on the grid; polished, a proposal this far under
    # its place's best is dropped (``best_at_each_place``)
    rival_margin: float = 0.05


_TEMPLATES = Memo(16)


def gradient_search(bank: TemplateBank, creases: np.ndarray, R_rest_obj: np.ndarray,
                    orientations: np.ndarray, intr: Intrinsics, plane: Plane, settings: GradientSearch, *,
                    max_instances: int = 1) -> tuple[list[PlaneMatch], PlaneTemplates]:
    """The part's best placements on the plane in a frame (its ``orientation_bits``, the ideal camera's),
    best first; the templates are made once per (bank, camera, image size, plane)."""
    h, w = orientations.shape
    r_px = radius_px(bank, intr, plane, (w, h))
    t = settings.fine_t if r_px < settings.big_part_px else settings.coarse_t
    step = spin_step_for(r_px, t, *settings.spin_step_deg)
    key = (intr.fx, intr.fy, intr.cx, intr.cy, w, h, tuple(np.round(plane.normal, 9)), round(plane.d_mm, 6),
           t, step, settings.zones)
    tpl = _TEMPLATES.get(bank, key, lambda: plane_templates(bank, creases, R_rest_obj, intr, (w, h), plane,
                                                            t=t, spin_step_deg=step, zones=settings.zones))
    if not len(tpl.n_pts):
        return [], tpl
    reach = max(int(np.abs(tpl.dx).max()), int(np.abs(tpl.dy).max()))
    rm = response_maps(orientations, t, reach // t + 2)
    top_k = settings.proposals + settings.proposals_per_instance * (max_instances - 1)
    return match(rm, tpl, bank, intr, plane, top_k=top_k, nms_px=settings.nms_px, n_rivals=settings.rivals,
                 rival_margin=settings.rival_margin), tpl


def agreement_on_plane(edges: EdgePoints, R: np.ndarray, t_cam: np.ndarray, intr: Intrinsics,
                       agreeing: np.ndarray) -> float:
    """The weighted share of the family's edge points, posed at (R, t), whose image gradient agrees
    within ``edge_agreement``'s tolerance (``agreeing``: a frame's ``agreeing_bits``)."""
    uv, theta = _projected(edges, R, t_cam, intr)
    return share_agreeing(uv, quantise(theta), agreeing)


def polish_on_gradients(bank: TemplateBank, tpl: PlaneTemplates, R_rest_obj: np.ndarray,
                        hs: list[PlaneHypothesis], intr: Intrinsics, plane: Plane, agreeing: np.ndarray, *,
                        step_px: float = 2.0, step_deg: float = 2.0, min_step_px: float = 0.25,
                        max_iter: int = 40) -> list[PlaneHypothesis]:
    """A pattern search over (spin, u, v) on the plane from each hypothesis, on the agreement of the edge
    points of its family's nearest template spin (``agreement_on_plane``): the grid search's placement is
    good to its step, this to a fraction of a pixel."""
    on_plane = _OnPlane(bank, tpl, R_rest_obj, intr, plane, agreeing)
    moves = [(-1, 0, 0), (1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]
    out = []
    for hyp in hs:
        psi, uv = float(hyp.psi_deg), np.asarray(hyp.uv, float)
        scored: dict = {}  # a step back, or a halved step, lands on a placement already scored
        best, R, t, ok = on_plane.scored(hyp.s, psi, uv, scored)
        if not ok:  # the start is scored where it lies, even where its ray misses the plane
            best = agreement_on_plane(on_plane.points_of(hyp.s, psi), R, t, intr, agreeing)
        d_px, d_deg = step_px, step_deg
        for _ in range(max_iter):
            moved = False
            for dpsi, du, dv in moves:
                psi2, uv2 = psi + dpsi * d_deg, uv + np.array([du, dv]) * d_px
                score, R2, t2, _ = on_plane.scored(hyp.s, psi2, uv2, scored)
                if score > best + 1e-9:
                    best, psi, uv, R, t, moved = score, psi2, uv2, R2, t2, True
            if not moved:
                if d_px <= min_step_px:
                    break
                d_px, d_deg = d_px / 2, d_deg / 2
        out.append(PlaneHypothesis(hyp.s, psi, uv, R, t, hyp.cost, best))
    return out


class _OnPlane:
    """``polish_on_gradients``' placements: a family at a spin and an anchor pixel, posed on the plane and
    scored on the frame's agreeing bits."""

    def __init__(self, bank: TemplateBank, tpl: PlaneTemplates, R_rest_obj: np.ndarray, intr: Intrinsics,
                 plane: Plane, agreeing: np.ndarray):
        self.bank, self.tpl, self.R_rest_obj, self.intr, self.plane = bank, tpl, R_rest_obj, intr, plane
        self.agreeing = agreeing
        self.Rc = R_cam_rest(plane)
        self.heights = rest_heights_mm(bank, R_rest_obj)
        self.nearest: dict[tuple[int, float], EdgePoints] = {}

    def pose_of(self, s: int, psi: float, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
        R = self.Rc @ Rz(psi) @ self.R_rest_obj[s]
        t, ok = placements(R[None], self.heights[s:s + 1], uv[None], self.bank, self.intr, self.plane)
        return R, t[0], bool(ok[0])

    def points_of(self, s: int, psi: float) -> EdgePoints:
        """The edge points of family s's template spin nearest ``psi`` (most steps keep the spin)."""
        if (s, psi) not in self.nearest:
            same = np.flatnonzero(self.tpl.family == s)
            gap = np.abs((self.tpl.psi_deg[same] - psi + 180.0) % 360.0 - 180.0)
            self.nearest[s, psi] = self.tpl.points[self.tpl.rotation[same[np.argmin(gap)]]]
        return self.nearest[s, psi]

    def scored(self, s: int, psi: float, uv: np.ndarray, memo: dict
               ) -> tuple[float, np.ndarray, np.ndarray, bool]:
        """(agreement, or -1 off the plane; R; t; on the plane) of family s at (psi, uv), from ``memo``
        (one hypothesis's, keyed by the exact spin and pixel) when it holds them."""
        key = (psi, float(uv[0]), float(uv[1]))
        if key not in memo:
            R, t, ok = self.pose_of(s, psi, uv)
            score = agreement_on_plane(self.points_of(s, psi), R, t, self.intr, self.agreeing) if ok else -1.0
            memo[key] = (score, R, t, ok)
        return memo[key]
