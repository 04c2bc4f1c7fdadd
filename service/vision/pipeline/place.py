"""A copy's place: the candidates whose silhouettes overlap there, and the rule for a pose found only at
its part's place point (``plane_calibration.place_point``): it holds where no other candidate at its place
agrees more with the image's gradients. Most wrong poses that read high lie at a copy's place, the part
flipped or spun on itself; the truth there agrees more than they do."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import replace

import numpy as np

from service.vision.bank import TemplateBank
from service.vision.deadline import Deadline
from service.vision.estimate.verdict import distinct, material_free
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose
from service.vision.geometry.render import rasterise_roi
from service.vision.pipeline import timing
from service.vision.pipeline.types import Checked, PoseCandidate

# Two poses whose silhouettes overlap at least this much (IoU) lie at one place: in the calibration
# scenes the wrong poses at a copy's place (its flips and spins) read 0.05-0.25 higher than those elsewhere
SAME_PLACE_IOU = 0.4


def at_place_point_only(c: Checked) -> bool:
    """``c`` is found, and only by reaching its part's place point."""
    return c.verdict.found and c.verdict.evidence.get("at_place_point", 0.0) > 0.0


def rivals_at(bank: TemplateBank, c: Checked, checked: Iterable[Checked], intr: Intrinsics,
              size: tuple[int, int], memo: dict) -> list[Checked]:
    """The candidates of ``checked`` (other than ``c``) at ``c``'s place."""
    return [r for r in checked if r is not c and silhouette_iou(bank, c.refined.pose, r.refined.pose, intr,
                                                                 size, memo=memo) >= SAME_PLACE_IOU]


def upcoming_at(bank: TemplateBank, c: Checked, cands: list[PoseCandidate], start: int, skip: set[int],
                intr: Intrinsics, size: tuple[int, int], memo: dict, *, scan: int, n: int) -> list[int]:
    """Indices of the first ``n`` candidates of ``cands[start:start + scan]`` (not in ``skip``) proposed at
    ``c``'s place."""
    out: list[int] = []
    for j in range(start, min(len(cands), start + scan)):
        if len(out) >= n:
            break
        if j not in skip and silhouette_iou(bank, c.refined.pose, cands[j].pose, intr, size,
                                            memo=memo) >= SAME_PLACE_IOU:
            out.append(j)
    return out


def contest(bank: TemplateBank, c: Checked, before: list[Checked], cands: list[PoseCandidate], start: int,
            done: set[int], check: Callable[[PoseCandidate], Checked], intr: Intrinsics,
            size: tuple[int, int], memo: dict, deadline: Deadline, *, scan: int, n: int, along: str
            ) -> list[Checked]:
    """``c`` (found only at its place point) and the next ``n`` candidates proposed at its place
    (``upcoming_at`` from ``start``; checked now while the deadline allows, their indices added to
    ``done``), each judged by ``outagreed`` against the others and the candidates of ``before`` at its
    place."""
    group = [c]
    for j in upcoming_at(bank, c, cands, start, done, intr, size, memo, scan=scan, n=n):
        if not deadline.allows_first(timing.CHECK_MS.high):
            break
        done.add(j)
        group.append(check(cands[j]))
    rivals = rivals_at(bank, c, before, intr, size, memo)
    return [outagreed(g, rivals + [h for h in group if h is not g], along) for g in group]


def outagreed(c: Checked, rivals: list[Checked], along: str) -> Checked:
    """``c``, or if it is found only at its place point (``at_place_point_only``) and a rival at its place
    agrees more along ``along``, ``c`` not found (reason ``rival_at_place``, the rival's agreement in the
    evidence as ``rival_agreement``)."""
    if not at_place_point_only(c):
        return c
    best = max((material_free(r.verdict.evidence, along) for r in rivals if distinct(r.verdict.evidence)),
               default=-1.0)
    if best <= material_free(c.verdict.evidence, along):
        return c
    evidence = c.verdict.evidence | {"rival_agreement": float(best)}
    return replace(c, verdict=replace(c.verdict, found=False, reason="rival_at_place", evidence=evidence))


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
