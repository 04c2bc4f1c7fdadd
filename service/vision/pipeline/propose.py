"""The proposal passes: LSD edges, their distance tensor and the coarse search (the paper's method), or,
on a plane, the gradient search of every visible CAD edge and the plane search over a part's resting
poses; then, run only when the first pass's candidates all fail, the peaks' other templates and, for a
part with taught colours, region proposals and the colour sweep."""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial

import cv2
import numpy as np

from service.vision import threads
from service.vision.bank import TemplateBank
from service.vision.deadline import NO_DEADLINE, Deadline
from service.vision.estimate.chamfer import distance_tensor
from service.vision.estimate.coarse import coarse_search
from service.vision.estimate.colour_prior import part_density
from service.vision.estimate.colour_sweep import colour_sweep
from service.vision.estimate.edges import detect_segments_in_bands, to_grey_u8, undistort_segments
from service.vision.estimate.evidence import ColourFrame, colour_frame
from service.vision.estimate.plane import plane_search, polish
from service.vision.estimate.plane_match import (
    best_at_each_place,
    gradient_search,
    matches_as_hypotheses,
    polish_on_gradients,
)
from service.vision.estimate.regions import bgr_u8, region_proposals, searched_range, working_likelihood
from service.vision.estimate.roi import crop_segments, roi_mask
from service.vision.estimate.roi import inside as roi_inside
from service.vision.estimate.search import Hypothesis, SearchParams, poses_of
from service.vision.geometry.camera import Intrinsics, project
from service.vision.geometry.frames import Pose, canonical_spin
from service.vision.geometry.plane import Plane
from service.vision.model.appearance import Appearance
from service.vision.pipeline import timing
from service.vision.pipeline.part import crease_edges_of, face_areas_mm2, resting_rotations
from service.vision.pipeline.policy import DEFAULT_DISTANCE_RANGE_MM, DEFAULT_POLICY, Policy
from service.vision.pipeline.types import PoseCandidate
from service.vision.pipeline.unrefined import by_unrefined_score, unrefined_score

Order = Callable[[list[PoseCandidate]], list[PoseCandidate]]
LaterPass = Callable[[], list[PoseCandidate]]


def propose(bank: TemplateBank, image: np.ndarray, intr: Intrinsics, *, distance_mm: float | None = None,
            distance_range_mm: tuple[float, float] | None = None, params: SearchParams | None = None,
            roi_uv: np.ndarray | None = None, deadline: Deadline = NO_DEADLINE, reserve_ms: float = 0.0,
            plane: Plane | None = None, deferred: list[LaterPass] | None = None,
            colour: np.ndarray | None = None, frame: ColourFrame | None = None, n_regions: int = 0,
            part_colours: np.ndarray | None = None,
            order: Order | None = None, score: Callable[[PoseCandidate], float] | None = None,
            n_scored: int = 0, sweep_colours: bool = False, policy: Policy = DEFAULT_POLICY,
            max_instances: int = 1):
    """The first pass -> (distinct candidates, lowest chamfer cost first; full-image segments; timing_ms
    with "edges" and "coarse").

    ``roi_uv``: (N, 2) polygon, pixels: only placements whose object centre projects inside it are
    searched (level A's anchors are restricted to it), and only the edges within the part's largest
    projected radius of its bounding box are used. ``deadline`` / ``reserve_ms``: see ``coarse_search``
    (the edges are always detected and the search always started: a deadline never leaves a frame
    without a proposal to check, ``Deadline.allows_first``).

    ``plane``: the supporting plane (camera frame): the search runs over the part's stable resting
    poses x spin about the plane's normal x position on the plane (``estimate/plane.py``) instead of
    all of 6D; ``distance_mm`` is then not used. A part without stable poses is searched in 6D.

    ``max_instances``: how many instances the frame may hold; more than one keeps candidates apart by
    pose (``distinct_candidates``' ``by_pose``), and the gradient search on a plane proposes more
    (``Policy.gradient``).

    ``deferred``: a list to which the later passes are appended, each a callable returning its distinct
    candidates: the 6D search's second pass (``coarse_search``: the level-A peaks' other templates), then
    with ``colour`` (the undistorted BGR image) and no ROI ``n_regions`` region proposals
    (``regions.region_proposals``), then with ``sweep_colours`` the silhouettes swept over the part's
    colours (``colour_sweep``). Without it there is no later pass.

    ``frame``: the colour image as the evidence reads it (``evidence.colour_frame``: its gradient
    orientations, made once per frame, are the gradient search's); made from ``image`` when not given.

    ``part_colours``: a taught part's colour density (``taught_colour_density``): the region proposals
    are ranked by how part-coloured each region is too, and the colour sweep reads it. ``order``: the later
    passes' candidates are put in this order before near duplicates are dropped (the first of each group
    is kept). ``score``: a candidate's score as it stands (a taught part's unrefined score): ``n_scored``
    region fits are scored, and the best ``n_regions`` of them refined."""
    p = params or policy.search_params
    threads.use_budget()
    t0 = time.perf_counter()
    grey = to_grey_u8(image)
    h, w = grey.shape
    deadline.enter("edges")
    seg = detect_segments_in_bands(grey)
    if intr.dist is not None:
        # Straighten the edges once; everything after works in the ideal pinhole camera intr.K.
        seg = undistort_segments(seg, intr)
    rng = distance_range_mm or DEFAULT_DISTANCE_RANGE_MM
    anchor_mask = None
    if roi_uv is not None:
        z_mm = distance_mm if distance_mm is not None else rng[0]
        seg, anchor_mask, p = _within_roi(bank, seg, intr, roi_uv, (h, w), p, z_mm, policy)
    # Level A's coarse grid is pooled from level B's (coarse_search): one set of distance transforms.
    dtt_b = distance_tensor(seg, n_channels=p.n_channels, scale=p.fine_scale)
    t_edges = timing.ms_since(t0)
    t1 = time.perf_counter()
    deadline.enter("search")
    several = max_instances > 1
    search = Search(bank, intr, (h, w), p, distance_mm, rng, deadline, roi_uv, several)
    rest = resting_rotations(bank) if plane is not None else None
    if rest is not None and len(rest):
        ph = plane_search(bank, rest, dtt_b, intr, (h, w), plane, p, distance_range_mm=rng,
                          anchor_mask=anchor_mask, deadline=deadline,
                          reserve_ms=reserve_ms) if deadline.allows_first(reserve_ms) else []
        by_gradient = _gradient_proposals(bank, rest, frame or colour_frame(image), intr, plane, dtt_b, p,
                                          max_instances, deadline, reserve_ms, policy)
        cands = [candidate(bank, Pose(x.R, x.t), x.cost, x.score) for x in by_gradient + ph]
    else:
        later: list[Callable[[], list[Hypothesis]]] = []
        hyps = coarse_search(bank, dtt_b, intr, (h, w), p, distance_mm=distance_mm, distance_range_mm=rng,
                             anchor_mask=anchor_mask, deadline=deadline, reserve_ms=reserve_ms,
                             deferred=later) if deadline.allows_first(reserve_ms) else []
        cands = search.candidates(hyps)
        if deferred is not None:
            deferred += _later_passes(search, later, colour, n_regions, part_colours, order, score, n_scored,
                                      sweep_colours)
    return (search.distinct(cands, roi_uv, several), seg,
            {"edges": t_edges, "coarse": timing.ms_since(t1)})


def _gradient_proposals(bank: TemplateBank, rest: np.ndarray, frame: ColourFrame, intr: Intrinsics,
                        plane: Plane, dtt_b, p: SearchParams, max_instances: int, deadline: Deadline,
                        reserve_ms: float, policy: Policy) -> list:
    """The gradient search's placements on the plane (``estimate/plane_match.py``: every visible CAD edge
    by its gradient orientation, on the colour image), polished on the same gradients to a fraction of a
    pixel, with their chamfer cost on the edges as the plane search's own. They come first: they see
    curved, short and inner edges that the segments miss."""
    if not deadline.allows_first(reserve_ms):
        return []
    matches, tpl = gradient_search(bank, crease_edges_of(bank), rest, frame.orientations, intr, plane,
                                   policy.gradient, max_instances=max_instances)
    hs = polish_on_gradients(bank, tpl, rest, matches_as_hypotheses(matches, tpl), intr, plane,
                             frame.agreeing)
    hs = best_at_each_place(hs, [x.place for x in matches], policy.gradient.rival_margin)
    return polish(bank, rest, hs, dtt_b, intr, plane, p, max_iter=0)


def _within_roi(bank: TemplateBank, seg, intr: Intrinsics, roi_uv: np.ndarray, shape: tuple[int, int],
                p: SearchParams, z_mm: float, policy: Policy):
    """(the segments near ``roi_uv``, level A's anchor mask, ``p`` with its peaks as dense as over the
    whole image) for a search restricted to the ROI; ``z_mm`` the nearest distance searched."""
    z_near = max(z_mm - 0.5 * bank.diameter_mm, 1.0)
    seg = crop_segments(seg, roi_uv, 0.5 * bank.diameter_mm * max(intr.fx, intr.fy) / z_near)
    # Anchors are 16 px apart: one whose cell touches the ROI is scanned (level B searches round it).
    reach = int(math.ceil(p.anchor_stride / p.level_scale / 2))
    anchor_mask = cv2.dilate(roi_mask(roi_uv, shape).astype(np.uint8),
                             np.ones((2 * reach + 1, 2 * reach + 1), np.uint8)).astype(bool)
    # Level B's scans cost per peak: keep the peaks as dense as over the whole image.
    p = replace(p, n_peaks=max(policy.roi_min_peaks, math.ceil(p.n_peaks * float(anchor_mask.mean()))))
    return seg, anchor_mask, p


def _later_passes(search: Search, later: list, colour: np.ndarray | None, n_regions: int,
                  part_colours: np.ndarray | None, order: Order | None,
                  score: Callable[[PoseCandidate], float] | None, n_scored: int,
                  sweep_colours: bool) -> list[LaterPass]:
    passes: list[LaterPass] = []
    if later:
        passes.append(partial(other_templates, search, later[0], order))
    # the taught colours' likelihood, made once for the region and colour-sweep passes that read it
    likelihood = functools.cache(lambda: working_likelihood(bgr_u8(colour), part_colours)) \
        if part_colours is not None and colour is not None else None
    if n_regions and colour is not None and search.roi_uv is None:
        passes.append(partial(from_regions, search, colour, n_regions, part_colours, score, n_scored,
                              likelihood, order))
    if sweep_colours and likelihood is not None and order is not None and search.roi_uv is None:
        passes.append(partial(from_colours, search, likelihood, order))
    return passes


@dataclass(frozen=True)
class Search:
    """One frame's search, as its later passes read it."""
    bank: TemplateBank
    intr: Intrinsics
    shape: tuple[int, int]  # (h, w)
    params: SearchParams
    distance_mm: float | None
    distance_range_mm: tuple[float, float]
    deadline: Deadline
    roi_uv: np.ndarray | None
    several: bool

    def candidates(self, hs: list[Hypothesis]) -> list[PoseCandidate]:
        if not hs:
            return []
        Rs, ts = poses_of(self.bank, hs, self.intr.K, self.distance_mm)
        return [candidate(self.bank, Pose(R, t), hy.cost, hy.score)
                for R, t, hy in zip(Rs, ts, hs, strict=True)]

    def distinct(self, cands: list[PoseCandidate], roi_uv: np.ndarray | None, several: bool
                 ) -> list[PoseCandidate]:
        """``distinct_candidates`` of those whose centre lies in ``roi_uv`` (level B's local scans may have
        walked it out)."""
        if roi_uv is not None and cands:
            inside = roi_inside(roi_uv, _centres_uv(cands, self.bank, self.intr.K))
            cands = [c for c, ok in zip(cands, inside, strict=True) if ok]
        return distinct_candidates(cands, self.bank, self.intr.K, by_pose=several)


def other_templates(search: Search, run: Callable[[], list[Hypothesis]], order: Order | None
                    ) -> list[PoseCandidate]:
    """The coarse search's second pass: level B from the peaks' other templates."""
    cands = search.candidates(run())
    return search.distinct(order(cands) if order is not None and cands else cands, search.roi_uv,
                           search.several)


def from_regions(search: Search, colour: np.ndarray, n_regions: int, part_colours: np.ndarray | None,
                 score: Callable[[PoseCandidate], float] | None, n_scored: int,
                 likelihood: Callable[[], np.ndarray] | None, order: Order | None) -> list[PoseCandidate]:
    """Pose proposals from colour-homogeneous regions whose area and silhouette fit the part, each refined
    on its region's own outline; by pose: a region's other fits (other rotations at one place) stay."""
    def hyp_score(hs: list[Hypothesis]) -> list[float]:
        # those the deadline leaves no time to score come last, in the region fits' order
        return [score(c) if search.deadline.allows(timing.EVIDENCE_MS + timing.CHECK_MS.high) else -math.inf
                for c in search.candidates(hs)]

    hs = region_proposals(search.bank, colour, search.intr.K, search.shape, search.params,
                          distance_mm=search.distance_mm, distance_range_mm=search.distance_range_mm,
                          n_out=n_regions, deadline=search.deadline, part_colours=part_colours,
                          score=None if score is None else hyp_score,
                          n_scored=n_scored if score is not None else 0, likelihood=likelihood,
                          reserve_ms=timing.CHECK_MS.high)
    cands = search.candidates(hs)
    return search.distinct(order(cands) if order is not None and cands else cands, None, True)


def from_colours(search: Search, likelihood: Callable[[], np.ndarray], order: Order) -> list[PoseCandidate]:
    """The part's silhouettes swept over its taught colours (``colour_sweep``), in ``order``."""
    lik = likelihood()
    hs = colour_sweep(search.bank, lik, search.intr.K, lik.shape[1] / search.shape[1],
                      searched_range(search.distance_mm, search.distance_range_mm))
    return search.distinct(order(search.candidates(hs)), None, True)


@dataclass(frozen=True)
class ByColours:
    """A taught part's candidates ranked on its colours as they stand (``unrefined_score``)."""
    bank: TemplateBank
    frame: ColourFrame
    intr: Intrinsics
    appearance: Appearance
    deadline: Deadline = NO_DEADLINE

    def order(self, cands: list[PoseCandidate]) -> list[PoseCandidate]:
        return by_unrefined_score(self.bank, cands, self.frame, self.intr, self.appearance, self.deadline)

    def score(self, c: PoseCandidate) -> float:
        return unrefined_score(self.bank, c.pose, self.frame, self.intr, None, self.appearance)


def taught_colour_density(bank: TemplateBank, appearance: Appearance | None) -> np.ndarray | None:
    """The taught part's colour density (``colour_prior.part_density``: its faces' colours by area), or
    None untaught."""
    return None if appearance is None else part_density(appearance.face_bgr, face_areas_mm2(bank))


def candidate(bank: TemplateBank, pose: Pose, cost: float, score: float) -> PoseCandidate:
    # A revolved part is reported with spin 0 about its axis (API.md: one canonical angle).
    return PoseCandidate(canonical_spin(pose, bank.symmetry_axis_obj, bank.symmetry_point_obj), float(cost),
                         float(score))


def _centres_uv(cands: list[PoseCandidate], bank: TemplateBank, K: np.ndarray) -> np.ndarray:
    """(N, 2) pixels where the candidates' object centres project."""
    return project(np.array([c.pose.apply(bank.centre_obj[None])[0] for c in cands]), K)


def distinct_candidates(cands: list[PoseCandidate], bank: TemplateBank, K: np.ndarray, *,
                        by_pose: bool = False) -> list[PoseCandidate]:
    """Drop candidates whose object centre projects within a quarter diameter of a better one's: one
    earlier in ``cands``, which come best first as the search ranks them (by chamfer cost, or by cost
    over its background with ``SearchParams.bg_norm``).

    ``by_pose`` (several instances): drop only those whose bounding-box corners project, on average,
    within a quarter diameter of a better one's: a wrong placement straddling two touching copies
    lies near the centre of the copy behind it, and must not hide it."""
    corners = bank.centre_obj + 0.5 * np.asarray(bank.extents_mm) * np.array(
        [[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
    ref = corners if by_pose else bank.centre_obj[None]
    out: list[PoseCandidate] = []
    kept: list[np.ndarray] = []
    for c in cands:
        x = c.pose.apply(ref)
        uv = np.column_stack([K[0, 0] * x[:, 0] / x[:, 2], K[1, 1] * x[:, 1] / x[:, 2]])
        r = 0.25 * K[0, 0] * bank.diameter_mm / max(float(x[:, 2].mean()), 1e-6)
        if all(np.linalg.norm(uv - o, axis=1).mean() > r for o in kept):
            out.append(c)
            kept.append(uv)
    return out
