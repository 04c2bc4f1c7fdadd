"""Several instances in one frame: candidates checked until that many distinct ones are found, each found
one explaining its pixels for the others, and the found ones sorted."""

from __future__ import annotations

import numpy as np

from service.vision.bank import TemplateBank
from service.vision.deadline import NO_DEADLINE, Deadline
from service.vision.estimate.evidence import ColourFrame
from service.vision.estimate.plane import PLANE_TOLERANCE_MM
from service.vision.estimate.verdict import PlaneAgreement, material_free
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose
from service.vision.geometry.plane import Plane, centre_height_mm
from service.vision.geometry.render import rasterise_roi
from service.vision.pipeline import place, timing
from service.vision.pipeline.check import Checker
from service.vision.pipeline.place import silhouette_iou
from service.vision.pipeline.policy import DEFAULT_POLICY, Policy
from service.vision.pipeline.types import Checked, PoseCandidate

SORTS = ("score", "distance", "height")
# Rejections a touching copy's pixels can cause: judged again once that copy is found.
REJUDGE_REASONS = ("region_mismatch", "shading_mismatch", "appearance_mismatch", "low_score")


def verify_instances(bank: TemplateBank, cands: list[PoseCandidate], grey: np.ndarray, frame: ColourFrame,
                     intr: Intrinsics, *, max_instances: int, distance_mm: float | None,
                     distance_range_mm: tuple[float, float] | None, min_score: float | None,
                     n_channels: int, deadline: Deadline = NO_DEADLINE, plane: Plane | None = None,
                     plane_tolerance_mm: float = PLANE_TOLERANCE_MM, appearance=None,
                     policy: Policy = DEFAULT_POLICY, agreement: PlaneAgreement | None = None
                     ) -> tuple[list[Checked], list[Checked]]:
    """Refine and verify candidates (best chamfer cost first) until ``max_instances`` distinct ones are
    found or the candidates run out -> (found, in the order found; rejected, best verification first).
    A candidate whose silhouette overlaps a found instance's by more than ``policy.instance_iou`` (IoU) is
    the same instance: it is skipped before refinement, and a refined one is dropped. No check starts that
    the ``deadline`` leaves no time for.

    Found instances explain their pixels (``judge``'s ``others_depth_mm``): candidates checked after
    one is found are judged with it, and a rejected candidate is judged again (its evidence only: the
    refinement does not change) once an instance is found after it: a copy touching another looked
    like a part on a background of its own colour until that one was found.

    A pose found only at its part's place point holds against the candidates at its place
    (``Scene.holds_place``)."""
    check = Checker(bank, grey, frame, intr, distance_mm, n_channels,
                    dict(distance_range_mm=distance_range_mm, min_score=min_score, plane=plane,
                         plane_tolerance_mm=plane_tolerance_mm, appearance=appearance,
                         agreement=agreement), deadline, policy)
    scene = Scene(check, max_instances)
    for k, cand in enumerate(cands):
        if scene.full():
            break
        if k in scene.done or scene.overlaps_found(cand.pose):
            continue
        if not deadline.allows_first(timing.CHECK_MS.high):
            break
        c = scene.checked(cand)
        if not c.verdict.found:
            scene.rejected.append(c)
        elif scene.distinct(c) and scene.holds_place(c, cands, k + 1):
            scene.add(c)
            scene.rejudge_rejected()
    scene.mutual()
    scene.rejected.sort(key=lambda c: c.verdict.score, reverse=True)
    return scene.found, scene.rejected


class Scene:
    """One frame's found instances (and the depth map of their pixels, ``others``) and its rejected
    candidates, for ``verify_instances``."""

    def __init__(self, check: Checker, max_instances: int):
        self.check = check
        self.bank, self.frame, self.intr = check.bank, check.frame, check.intr
        self.policy, self.deadline = check.policy, check.deadline
        self.max_instances = max_instances
        self.found: list[Checked] = []
        self.rejected: list[Checked] = []
        self.others = np.full(self.frame.shape, np.inf, np.float32)
        self.size = (self.frame.shape[1], self.frame.shape[0])
        self.silhouettes: dict = {}  # silhouette_iou's memo: each pose rasterised once
        self.done: set[int] = set()  # candidates checked ahead of their turn, as rivals at a place
        agreement = check.judge_kw.get("agreement")
        self.along = agreement.along if agreement is not None else "edge_agreement"

    def full(self) -> bool:
        return len(self.found) >= self.max_instances

    def overlaps_found(self, pose: Pose) -> bool:
        return any(silhouette_iou(self.bank, pose, f.refined.pose, self.intr, self.size,
                                  memo=self.silhouettes) > self.policy.instance_iou for f in self.found)

    def distinct(self, c: Checked) -> bool:
        return all(silhouette_iou(self.bank, c.refined.pose, f.refined.pose, self.intr, self.size,
                                  memo=self.silhouettes) <= self.policy.instance_iou for f in self.found)

    def checked(self, cand: PoseCandidate) -> Checked:
        others = self.others if self.found else None
        return self.check.twin_checked(self.check(cand, others), others)

    def holds_place(self, c: Checked, cands: list[PoseCandidate], start: int) -> bool:
        """Whether found ``c`` is found: a pose found only at its part's place point (``place``) also
        needs to agree more than every candidate at its place, the rejected ones and the next
        ``policy.place_rivals`` proposed there (checked now, then skipped). Refused, ``c`` joins the
        rejected, and a rival found that agrees more is added."""
        if not place.at_place_point_only(c):
            return True
        judged, *fresh = place.contest(self.bank, c, self.rejected, cands, start, self.done, self.checked,
                                       self.intr, self.size, self.silhouettes, self.deadline,
                                       scan=self.policy.place_rival_scan, n=self.policy.place_rivals,
                                       along=self.along)
        if judged.verdict.found:
            self.rejected += [r for r in fresh if not r.verdict.found]
            return True
        self.rejected.append(judged)
        for r in sorted(fresh, key=lambda r: -material_free(r.verdict.evidence, self.along)):
            if r.verdict.found and self.distinct(r):
                self.add(r)
            else:
                self.rejected.append(r)
        return False

    def add(self, c: Checked) -> None:
        self.found.append(c)
        paint_depth(self.others, self.bank, c.refined.pose, self.intr)

    def add_checked(self, c: Checked, others_depth_mm: np.ndarray) -> None:
        """Add a candidate found on being judged again, after its twin check (which can replace it by
        its mirror twin, in the same place), unless it is found only at its place point and a rejected
        candidate at its place agrees more (then it stays rejected)."""
        c = self.check.twin_checked(c, others_depth_mm)
        rivals = place.rivals_at(self.bank, c, self.rejected, self.intr, self.size, self.silhouettes)
        judged = place.outagreed(c, rivals, self.along)
        if judged.verdict.found:
            self.add(judged)
        else:
            self.rejected.append(judged)

    def rejudged(self, c: Checked, others: np.ndarray) -> Checked:
        """``c`` judged again with the parts in ``others`` explaining their pixels, if its rejection
        could be theirs (its evidence only: the refinement does not change)."""
        if c.verdict.reason not in REJUDGE_REASONS:
            return c
        return self.check.judged(c, others, edge_support=c.verdict.evidence["edge_support"],
                                 unexplained=c.verdict.evidence["unexplained"])

    def rejudge_rejected(self) -> None:
        """Judge the rejected candidates again among the found instances, until none changes."""
        changed = True
        while changed and not self.full():
            changed = False
            for i, c in enumerate(self.rejected):
                if not self.deadline.allows(timing.EVIDENCE_MS):
                    return
                self.rejected[i] = again = self.rejudged(c, self.others)
                if again.verdict.found and self.distinct(again):
                    self.rejected.pop(i)
                    self.add_checked(again, self.others)
                    changed = True
                    break

    def mutual(self) -> None:
        """Judge each near miss (``policy.mutual_min_score``) with the found instances and the other near
        misses explaining their pixels, best first; one found joins the instances and the rest are judged
        again."""
        changed = True
        while changed and not self.full():
            changed = False
            could = [i for i, c in enumerate(self.rejected) if c.verdict.reason in REJUDGE_REASONS
                     and c.verdict.score >= self.policy.mutual_explainer_min_score and self.distinct(c)]
            near = [i for i in could if self.rejected[i].verdict.score >= self.policy.mutual_min_score]
            near.sort(key=lambda i: -self.rejected[i].verdict.score)
            for i in near:
                if not self.deadline.allows(timing.EVIDENCE_MS):
                    return
                scene_depth = self.others.copy()
                for j in could:
                    if j != i:
                        paint_depth(scene_depth, self.bank, self.rejected[j].refined.pose, self.intr)
                again = self.rejudged(self.rejected[i], scene_depth)
                if again.verdict.found:
                    self.rejected.pop(i)
                    self.add_checked(again, scene_depth)
                    self.rejudge_rejected()
                    changed = True
                    break


def paint_depth(depth_mm: np.ndarray, bank: TemplateBank, pose: Pose, intr: Intrinsics) -> None:
    """Draw the part at ``pose`` into the (H, W) depth map ``depth_mm`` (nearest surface wins)."""
    h, w = depth_mm.shape
    depth, _, (u0, v0) = rasterise_roi(bank.vertices_mm, bank.faces, pose, intr, (w, h))
    win = depth_mm[v0:v0 + depth.shape[0], u0:u0 + depth.shape[1]]
    np.minimum(win, depth, out=win)


def sort_instances(found: list[Checked], bank: TemplateBank, sort: str, plane: Plane | None = None
                   ) -> list[Checked]:
    """``found`` by verification score (highest first), by the distance of the part's centre from the
    camera (nearest first) or by its height above ``plane`` (highest first: the top of a pile)."""
    if sort == "score":
        return sorted(found, key=lambda c: -c.verdict.score)
    if sort == "distance":
        return sorted(found, key=lambda c: float(np.linalg.norm(c.refined.pose.apply(bank.centre_obj[None]))))
    if sort == "height":
        if plane is None:
            raise ValueError("sort 'height' needs a plane")
        return sorted(found, key=lambda c: -centre_height_mm(bank, c.refined.pose, plane))
    raise ValueError(f"unknown sort {sort!r}: one of {SORTS}")
