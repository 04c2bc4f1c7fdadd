"""Checking a candidate: refine -> evidence -> verdict (``estimate/verdict.py`` decides found / absent),
then the mirror-twin check of a found answer and, for a part with taught colours, the colour polish of a
near miss and the found answer moved to its colours' outline.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from service.vision.bank import TemplateBank
from service.vision.deadline import NO_DEADLINE, Deadline
from service.vision.estimate.contour_region import region_contour_refine
from service.vision.estimate.edge_agreement import agreement_of_edges
from service.vision.estimate.evidence import ColourFrame, evidence
from service.vision.estimate.plane import PLANE_TOLERANCE_MM
from service.vision.estimate.plane_polish import polish_on_plane
from service.vision.estimate.verdict import PlaneAgreement, decide
from service.vision.geometry.camera import Intrinsics, project
from service.vision.geometry.frames import Pose, Rx, Ry, Rz
from service.vision.geometry.plane import Plane, rest_gap_mm
from service.vision.model.appearance import Appearance
from service.vision.model.edge_points import edge_points_of
from service.vision.model.mirror import twin_poses
from service.vision.pipeline import place, timing
from service.vision.pipeline.part import mirror_planes_of, rest_family, shown_edges
from service.vision.pipeline.policy import DEFAULT_POLICY, Policy
from service.vision.pipeline.types import Checked, PoseCandidate, RefinedPose
from service.vision.pipeline.unrefined import face_bgr_of, unrefined_score

# Reasons a pose is refused for where it lies, not for how it looks: the colour polish leaves them.
NOT_POLISHED = ("outside_distance_range", "outside_image", "off_plane")

Unexplained = float | Callable[[], float]


def refine(bank: TemplateBank, best: PoseCandidate, grey: np.ndarray, intr: Intrinsics, *,
           distance_mm: float | None, n_channels: int, plane: Plane | None = None
           ) -> tuple[RefinedPose, Unexplained]:
    """Refine a candidate -> (the kept pose, a callable waiting for its unexplained-edge ratio
    ``interior.unexplained_edge_ratio``, or the ratio itself).

    ``refine_pose`` keeps the refined pose only if it verifies at least as well on the full-resolution
    edges (less ``refine.SCORE_SLACK``), else the candidate; the kept pose's ``score`` is that
    full-resolution verification, the verdict's edge support. The candidate's own score is the coarse,
    half-resolution one and is not compared with it: a textured floor inflates it. The interior check
    runs on the background pool, waited for after the evidence: the calling thread measures the evidence
    instead of idling. ``plane``: the candidate rests on it, and is refined on it (``refine_pose``'s
    ``normal_cam``)."""
    from service.vision.estimate.refine import refine_pose

    r = refine_pose(bank, best.pose, grey, intr, None, distance_mm=distance_mm, n_channels=n_channels,
                    interior_later=True, normal_cam=None if plane is None else plane.normal)
    return RefinedPose(r.pose, float(r.cost), float(r.score), int(r.iterations), float(r.inlier_ratio)), \
        (r.unexplained_later if r.unexplained_later is not None else r.unexplained)


def judge(bank: TemplateBank, c: Checked, frame: ColourFrame, intr: Intrinsics, *, edge_support: float,
          unexplained: Unexplained, distance_range_mm: tuple[float, float] | None, min_score: float | None,
          plane: Plane | None = None, plane_tolerance_mm: float = PLANE_TOLERANCE_MM,
          others_depth_mm: np.ndarray | None = None, appearance: Appearance | None = None,
          weights: tuple[tuple[str, float], ...] | None = None,
          agreement: PlaneAgreement | None = None) -> Checked:
    """``c`` with the verdict on its refined pose: the evidence measured there (``evidence``; the
    refinement's ``edge_support`` and ``unexplained`` edges with it), the distance range and the
    plane. ``unexplained`` may be a callable giving it (read after the evidence is measured).
    ``weights``: the score's weights for a part without taught colours (``Policy.verdict_weights``;
    None: the service's). On a plane the evidence also reports ``edge_agreement``, and a part whose
    agreement is calibrated (``agreement``, ``pipeline/plane_calibration``) is also scored on it (at the
    point of the resting family the pose is in), and not found under its floor."""
    pose = c.refined.pose
    ev = evidence(bank, pose, intr, frame, others_depth_mm, face_bgr_of(appearance)).as_dict()
    ev |= {"edge_support": edge_support, "unexplained": float(unexplained() if callable(unexplained)
                                                              else unexplained)}
    if plane is not None:  # reported: the evidence a material-free score of a part on a plane will read
        h, w = frame.agreeing.shape
        ev |= agreement_of_edges(shown_edges(bank, pose, intr, (w, h)), intr, frame.agreeing)
    gap = rest_gap_mm(bank, pose, plane) if plane is not None else None
    if plane is not None and agreement is not None and agreement.points_by_rest:
        agreement = agreement.at_rest(rest_family(bank, pose.R, plane.normal))
    untaught = weights is not None and "appearance" not in ev  # taught: ``verdict.APPEARANCE_WEIGHTS``
    v = decide(ev, z_mm=float(pose.t_mm[2]), distance_range_mm=distance_range_mm, min_score=min_score,
               weights=dict(weights) if untaught else None, plane_gap_mm=gap,
               plane_tolerance_mm=plane_tolerance_mm, agreement=agreement)
    return Checked(c.candidate, c.refined, v)


def same_place(bank: TemplateBank, a: Pose, b: Pose, K: np.ndarray, px: float, n_vertices: int) -> bool:
    """The model's vertices (about ``n_vertices`` of them) at ``a`` and at ``b`` project within ``px`` of
    each other on average."""
    v = np.asarray(bank.vertices_mm, float)
    v = v[:: max(1, len(v) // n_vertices)]
    d = np.linalg.norm(project(a.apply(v), K) - project(b.apply(v), K), axis=1)
    return float(d.mean()) < px


def same_place_but_depth(bank: TemplateBank, a: Pose, b: Pose, K: np.ndarray,
                         policy: Policy = DEFAULT_POLICY) -> bool:
    """``b``, moved along its line of sight to ``a``'s depth, is at ``a``'s place (``same_place`` within
    ``policy.hold_same_place_px``)."""
    return same_place(bank, a, Pose(b.R, b.t_mm * (a.t_mm[2] / b.t_mm[2])), K, policy.hold_same_place_px,
                      policy.same_place_vertices)


@dataclass(frozen=True)
class Checker:
    """Refine-and-judge for one frame (``check_candidate``), and the twin check of a found answer.
    ``judge_kw``: ``judge``'s distance range, min_score, plane, plane tolerance and appearance."""
    bank: TemplateBank
    grey: np.ndarray
    frame: ColourFrame
    intr: Intrinsics
    distance_mm: float | None
    n_channels: int
    judge_kw: dict
    deadline: Deadline = NO_DEADLINE
    policy: Policy = DEFAULT_POLICY

    def __call__(self, cand: PoseCandidate, others_depth_mm: np.ndarray | None,
                 unless_at: Pose | None = None) -> Checked | None:
        """``cand`` refined and judged; None if ``unless_at`` is given and the refinement ends on it."""
        t0 = time.perf_counter()
        kept, unexplained = self._refined(cand)
        if unless_at is not None and same_place(self.bank, kept.pose, unless_at, self.intr.K,
                                                self.policy.same_place_px, self.policy.same_place_vertices):
            return None
        c = self.polished_on_plane(self._judged(cand, kept, unexplained, others_depth_mm), others_depth_mm)
        c = self.outlined_on_colours(self.polished(c, others_depth_mm), others_depth_mm)
        timing.CHECK_MS.add(timing.ms_since(t0))
        self.deadline.checked()
        return c

    def judged(self, c: Checked, others_depth_mm: np.ndarray | None, **evidence_kw) -> Checked:
        """``c`` judged at its refined pose; ``evidence_kw``: the refinement's edge support and unexplained
        edges."""
        return judge(self.bank, c, self.frame, self.intr, others_depth_mm=others_depth_mm, **evidence_kw,
                     **self.judge_kw, weights=self.policy.verdict_weights)

    def _judged(self, cand: PoseCandidate, kept: RefinedPose, unexplained: Unexplained,
                others_depth_mm: np.ndarray | None) -> Checked:
        return self.judged(Checked(cand, kept, decide(None)), others_depth_mm, edge_support=kept.score,
                           unexplained=unexplained)

    def _on_colours(self) -> bool:
        return self.distance_mm is None and self.judge_kw.get("appearance") is not None

    def _refined(self, cand: PoseCandidate) -> tuple[RefinedPose, Unexplained]:
        """``refine`` (a candidate resting on a plane refined on it: ``_resting_on``), held at the searched
        range's bound its refinement passed (``_bound_passed``)."""
        kept, unexplained = refine(self.bank, cand, self.grey, self.intr, distance_mm=self.distance_mm,
                                   n_channels=self.n_channels, plane=self._resting_on(cand.pose))
        bound = self._bound_passed(kept.pose)
        if bound is None:
            return kept, unexplained
        return self._refined_at(cand, kept.pose, bound)

    def _resting_on(self, pose: Pose) -> Plane | None:
        """The request's plane if ``pose`` rests on it (within the plane tolerance), else None."""
        plane = self.judge_kw.get("plane")
        tolerance = self.judge_kw.get("plane_tolerance_mm", PLANE_TOLERANCE_MM)
        if plane is None or abs(rest_gap_mm(self.bank, pose, plane)) > tolerance:
            return None
        return plane

    def _refined_at(self, cand: PoseCandidate, pose: Pose, z_mm: float) -> tuple[RefinedPose, Unexplained]:
        """``refine`` from ``pose`` moved along its line of sight to depth ``z_mm``, the depth held there."""
        held = replace(cand, pose=Pose(pose.R, pose.t_mm * (z_mm / pose.t_mm[2])))
        return refine(self.bank, held, self.grey, self.intr, distance_mm=z_mm, n_channels=self.n_channels)

    def _bound_passed(self, pose: Pose) -> float | None:
        """The searched range's bound a refined ``pose`` lies beyond by at most ``policy.range_hold_max``,
        else None: the truth inside the range, the bound is no further from it than the refinement's end."""
        rng = self.judge_kw.get("distance_range_mm")
        if self.distance_mm is not None or rng is None:
            return None
        z, slack = float(pose.t_mm[2]), self.policy.range_hold_max
        if rng[0] <= z <= rng[1] or not rng[0] * (1 - slack) <= z <= rng[1] * (1 + slack):
            return None
        return float(rng[0] if z < rng[0] else rng[1])

    def polished_on_plane(self, c: Checked, others_depth_mm: np.ndarray | None) -> Checked:
        """A candidate resting on the plane and refused (not for its place), refined again on the plane from
        its pose polished on the edge points it shows (``polish_on_plane``) where their agreeing share
        rises by ``policy.plane_polish_min_gain``, and judged there; the better scored of the two. The
        refinement follows the image's segments, which a pile's other parts pull at; the polish follows
        the part's own edges."""
        plane = self.judge_kw.get("plane")
        pose = c.refined.pose
        if (plane is None or c.verdict.found or c.verdict.reason in NOT_POLISHED
                or self._resting_on(pose) is None or not self.deadline.allows(timing.CHECK_MS.high)):
            return c
        size = (self.grey.shape[1], self.grey.shape[0])
        edges = edge_points_of(shown_edges(self.bank, pose, self.intr, size), pose)
        polished, agrees, before = polish_on_plane(self.bank.vertices_mm, self.bank.centre_obj, edges, pose,
                                                   plane, self.intr, self.frame.agreeing)
        if agrees < before + self.policy.plane_polish_min_gain:
            return c
        kept, unexplained = refine(self.bank, replace(c.candidate, pose=polished), self.grey, self.intr,
                                   distance_mm=self.distance_mm, n_channels=self.n_channels, plane=plane)
        again = self._judged(c.candidate, kept, unexplained, others_depth_mm)
        return again if again.verdict.score > c.verdict.score else c

    def outlined_on_colours(self, c: Checked, others_depth_mm: np.ndarray | None) -> Checked:
        """A taught part's found answer (the distance not given) moved to its colours' outline and refined
        again on edges with its depth held there, if that is the found pose at another depth
        (``same_place_but_depth``: else the edges turned it) and found there too; else ``c``, also when
        the deadline leaves no time for a check. A free edge refinement keeps about half a start's depth
        error (printed edges inside the rim); the outline's depth does not."""
        if not (c.verdict.found and self._on_colours() and self.deadline.allows(timing.CHECK_MS.high)):
            return c
        pose = region_contour_refine(self.bank, c.refined.pose, self.frame.bgr, self.intr)
        if pose is c.refined.pose:
            return c
        kept, unexplained = self._refined_at(c.candidate, pose, float(pose.t_mm[2]))
        if not same_place_but_depth(self.bank, c.refined.pose, kept.pose, self.intr.K, self.policy):
            return c
        moved = self._judged(c.candidate, kept, unexplained, others_depth_mm)
        return moved if moved.verdict.found else c

    def polished(self, c: Checked, others_depth_mm: np.ndarray | None) -> Checked:
        """A taught part's near miss (its search's ``polish_from``) judged again at the pose nearby whose
        taught colours fit best (``polish_appearance``): a pose a pixel or a degree off loses the
        correlation of its colours, which the edges' refinement does not look at."""
        appearance = self.judge_kw.get("appearance")
        if (appearance is None or c.verdict.found
                or c.verdict.score < self.policy.search_of(appearance).polish_from
                or c.verdict.reason in NOT_POLISHED):
            return c
        pose = polish_appearance(self.bank, c.refined.pose, self.frame, self.intr, appearance,
                                 others_depth_mm, self.deadline, self.judge_kw.get("distance_range_mm"),
                                 policy=self.policy)
        if pose is c.refined.pose:
            return c
        ev = c.verdict.evidence
        return self.judged(Checked(c.candidate, replace(c.refined, pose=pose), decide(None)), others_depth_mm,
                           edge_support=ev["edge_support"], unexplained=ev["unexplained"])

    def twin_checked(self, c: Checked, others_depth_mm: np.ndarray | None) -> Checked:
        """``c``, or if it is found, it or its better-verified mirror twin (``model/mirror.py``), with
        ``evidence.twin_score``: the best score of the other poses (close to ``score``, the image hardly
        tells them apart). A twin whose unrefined evidence scores under ``policy.twin_unrefined_min_score``
        is not refined (that is its score); one refined back onto the found pose is that pose (no score).
        With a plane, a twin that does not rest on it is not checked: it would be refused there
        (``off_plane``). Twins are checked while the deadline leaves time for a check."""
        if not c.verdict.found:
            return c
        appearance = self.judge_kw.get("appearance")
        found_pose = c.refined.pose
        on_plane = self.judge_kw.get("plane") is not None
        scores: list[float] = []
        for twin in twin_poses(found_pose, mirror_planes_of(self.bank)):
            if not self.deadline.allows(timing.CHECK_MS.high):
                break
            if on_plane and self._resting_on(twin) is None:
                continue
            unrefined = unrefined_score(self.bank, twin, self.frame, self.intr, others_depth_mm, appearance)
            if unrefined < self.policy.twin_unrefined_min_score:
                scores.append(unrefined)
                continue
            t = self(PoseCandidate(twin, c.candidate.cost, c.candidate.score), others_depth_mm, found_pose)
            if t is None:
                continue
            if t.verdict.found and t.verdict.score > c.verdict.score:
                c, t = t, c
            scores.append(t.verdict.score)
        if not scores:
            return c
        evidence = c.verdict.evidence | {"twin_score": max(scores)}
        return replace(c, verdict=replace(c.verdict, evidence=evidence))


def check_candidate(bank: TemplateBank, cand: PoseCandidate, grey: np.ndarray, frame: ColourFrame,
                    intr: Intrinsics, *, distance_mm: float | None,
                    distance_range_mm: tuple[float, float] | None, min_score: float | None,
                    n_channels: int, plane: Plane | None = None,
                    plane_tolerance_mm: float = PLANE_TOLERANCE_MM,
                    others_depth_mm: np.ndarray | None = None, deadline: Deadline = NO_DEADLINE,
                    appearance: Appearance | None = None, policy: Policy = DEFAULT_POLICY,
                    agreement: PlaneAgreement | None = None) -> Checked:
    """One candidate refined, its evidence measured at the refined pose, and the verdict on it (with a
    plane, also whether the refined pose rests on it; ``others_depth_mm``: see ``judge``). A found one
    is checked against its mirror twins (``Checker.twin_checked``)."""
    check = Checker(bank, grey, frame, intr, distance_mm, n_channels,
                    dict(distance_range_mm=distance_range_mm, min_score=min_score, plane=plane,
                         plane_tolerance_mm=plane_tolerance_mm, appearance=appearance,
                         agreement=agreement), deadline, policy)
    return check.twin_checked(check(cand, others_depth_mm), others_depth_mm)


def verify_candidates(bank: TemplateBank, cands: list[PoseCandidate], grey: np.ndarray, frame: ColourFrame,
                      intr: Intrinsics, *, distance_mm: float | None,
                      distance_range_mm: tuple[float, float] | None, min_score: float | None,
                      n_channels: int, deadline: Deadline = NO_DEADLINE, plane: Plane | None = None,
                      plane_tolerance_mm: float = PLANE_TOLERANCE_MM,
                      appearance: Appearance | None = None, policy: Policy = DEFAULT_POLICY,
                      agreement: PlaneAgreement | None = None
                      ) -> list[Checked]:
    """Refine and verify the best ``policy.n_verify`` candidates, best verification first. Stops at the
    first found one: the search ranks by chamfer cost (over the local background's), and on a clean frame
    the first is the truth; and before a check the ``deadline`` leaves no time for. A pose found only at
    its part's place point holds against the candidates at its place (``place.contest``)."""
    def check(cand: PoseCandidate) -> Checked:
        return check_candidate(bank, cand, grey, frame, intr, distance_mm=distance_mm,
                               distance_range_mm=distance_range_mm, min_score=min_score,
                               n_channels=n_channels, plane=plane, plane_tolerance_mm=plane_tolerance_mm,
                               deadline=deadline, appearance=appearance, policy=policy, agreement=agreement)

    out: list[Checked] = []
    done: set[int] = set()
    for k, cand in enumerate(cands[:policy.n_verify]):
        if k in done:
            continue
        if not deadline.allows_first(timing.CHECK_MS.high):
            break
        now = [check(cand)]
        if place.at_place_point_only(now[0]):
            now = place.contest(bank, now[0], out, cands, k + 1, done, check, intr,
                                (grey.shape[1], grey.shape[0]), {}, deadline, scan=policy.place_rival_scan,
                                n=policy.place_rivals, along=agreement.along)
        out += now
        if any(x.verdict.found for x in now):
            break
    out.sort(key=lambda c: (c.verdict.found, c.verdict.score), reverse=True)
    return out


def polish_appearance(bank: TemplateBank, pose: Pose, frame: ColourFrame, intr: Intrinsics,
                      appearance: Appearance, others_depth_mm: np.ndarray | None,
                      deadline: Deadline = NO_DEADLINE,
                      distance_range_mm: tuple[float, float] | None = None, *,
                      policy: Policy = DEFAULT_POLICY) -> Pose:
    """``pose`` moved, a step at a time (``policy.polish_steps``, for up to ``policy.polish_rounds``
    rounds), to the neighbour whose unrefined score (taught colours included) is highest, while a step
    raises it; ``pose`` itself (the same object) if none does. With ``distance_range_mm`` no step leaves
    it (the unrefined score does not read the range)."""
    best = unrefined_score(bank, pose, frame, intr, others_depth_mm, appearance)
    for _ in range(policy.polish_rounds):
        moved = best
        for kind, axis, step in policy.polish_steps:
            for sign in (1.0, -1.0):
                if not deadline.allows(timing.EVIDENCE_MS):
                    return pose
                trial = _nudged(pose, kind, axis, sign * step)
                if distance_range_mm is not None and not _in_range(trial, distance_range_mm):
                    continue
                score = unrefined_score(bank, trial, frame, intr, others_depth_mm, appearance)
                if score > best + policy.polish_min_gain:
                    best, pose = score, trial
        if best == moved:
            break
    return pose


def _in_range(pose: Pose, distance_range_mm: tuple[float, float]) -> bool:
    return distance_range_mm[0] <= float(pose.t_mm[2]) <= distance_range_mm[1]


def _nudged(pose: Pose, kind: str, axis: int, step: float) -> Pose:
    """``pose`` moved ``step`` mm along camera axis ``axis`` ("t"), or turned ``step`` deg about it ("r")."""
    if kind == "t":
        t = np.array(pose.t_mm, float)
        t[axis] += step
        return Pose(np.asarray(pose.R, float), t)
    return Pose((Rx, Ry, Rz)[axis](step) @ np.asarray(pose.R, float), np.asarray(pose.t_mm, float))
