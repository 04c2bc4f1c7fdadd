"""Several instances in one frame: candidates checked until that many distinct ones are found, each found
one explaining its pixels for the others, and the found ones sorted."""

from __future__ import annotations

import numpy as np

from service.vision.bank import TemplateBank
from service.vision.deadline import NO_DEADLINE, Deadline
from service.vision.estimate.evidence import ColourFrame
from service.vision.estimate.plane import PLANE_TOLERANCE_MM
from service.vision.estimate.verdict import PlaneAgreement
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose
from service.vision.geometry.plane import Plane, centre_height_mm
from service.vision.geometry.render import rasterise_roi
from service.vision.pipeline import timing
from service.vision.pipeline.check import Checker
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
    like a part on a background of its own colour until that one was found."""
    check = Checker(bank, grey, frame, intr, distance_mm, n_channels,
                    dict(distance_range_mm=distance_range_mm, min_score=min_score, plane=plane,
                         plane_tolerance_mm=plane_tolerance_mm, appearance=appearance,
                         agreement=agreement), deadline, policy)
    scene = Scene(check, max_instances)
    for cand in cands:
        if scene.full():
            break
        if scene.overlaps_found(cand.pose):
            continue
        if not deadline.allows_first(timing.CHECK_MS.high):
            break
        others = scene.others if scene.found else None
        c = check.twin_checked(check(cand, others), others)
        if not c.verdict.found:
            scene.rejected.append(c)
        elif scene.distinct(c):
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

    def full(self) -> bool:
        return len(self.found) >= self.max_instances

    def overlaps_found(self, pose: Pose) -> bool:
        return any(silhouette_iou(self.bank, pose, f.refined.pose, self.intr, self.size,
                                  memo=self.silhouettes) > self.policy.instance_iou for f in self.found)

    def distinct(self, c: Checked) -> bool:
        return all(silhouette_iou(self.bank, c.refined.pose, f.refined.pose, self.intr, self.size,
                                  memo=self.silhouettes) <= self.policy.instance_iou for f in self.found)

    def add(self, c: Checked) -> None:
        self.found.append(c)
        paint_depth(self.others, self.bank, c.refined.pose, self.intr)

    def add_checked(self, c: Checked, others_depth_mm: np.ndarray) -> None:
        """Add a candidate found on being judged again, after its twin check (which can replace it by
        its mirror twin, in the same place)."""
        self.add(self.check.twin_checked(c, others_depth_mm))

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


def silhouette_iou(bank: TemplateBank, a: Pose, b: Pose, intr: Intrinsics,
                   image_size: tuple[int, int], *, memo: dict | None = None) -> float:
    """Intersection over union of the silhouettes of the model at poses ``a`` and ``b`` in the image
    (``image_size`` = (w, h); the project's rasteriser, pixel centres). ``memo``: a dict kept for one
    frame's poses, each rasterised only the first time it is asked about."""
    ma, na, (ua, va) = _silhouette(bank, a, intr, image_size, memo)
    mb, nb, (ub, vb) = _silhouette(bank, b, intr, image_size, memo)
    if na == 0 or nb == 0:
        return 0.0
    u0, v0 = max(ua, ub), max(va, vb)
    u1, v1 = min(ua + ma.shape[1], ub + mb.shape[1]), min(va + ma.shape[0], vb + mb.shape[0])
    if u1 <= u0 or v1 <= v0:
        return 0.0
    inter = int((ma[v0 - va:v1 - va, u0 - ua:u1 - ua] & mb[v0 - vb:v1 - vb, u0 - ub:u1 - ub]).sum())
    return inter / float(na + nb - inter)


def _silhouette(bank: TemplateBank, pose: Pose, intr: Intrinsics, image_size: tuple[int, int],
                memo: dict | None) -> tuple[np.ndarray, int, tuple[int, int]]:
    """(mask of the silhouette's window, its pixel count, the window's (u0, v0)) of the model at
    ``pose`` (``rasterise_roi``), from ``memo`` (keyed by the pose object, which it keeps) if there."""
    hit = memo.get(id(pose)) if memo is not None else None
    if hit is not None and hit[0] is pose:
        return hit[1]
    _, face, uv0 = rasterise_roi(bank.vertices_mm, bank.faces, pose, intr.K, image_size)
    mask = face >= 0
    out = (mask, int(mask.sum()), uv0)
    if memo is not None:
        memo[id(pose)] = (pose, out)
    return out
