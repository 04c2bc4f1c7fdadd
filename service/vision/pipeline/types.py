"""What an estimate answers: candidates, refined poses, the checked ones with their verdicts, instances."""

from __future__ import annotations

from dataclasses import dataclass, field

from service.vision.estimate.verdict import Verdict, decide
from service.vision.geometry.frames import Pose


@dataclass(frozen=True)
class PoseCandidate:
    pose: Pose  # T_cam_obj, mm
    cost: float  # mean directional chamfer distance, px (lower is better)
    score: float  # 0..1 fraction of border points with a matching image edge nearby (higher is better)


@dataclass(frozen=True)
class RefinedPose(PoseCandidate):
    iterations: int = 0
    inlier_ratio: float = 0.0


@dataclass(frozen=True)
class Checked:
    candidate: PoseCandidate  # as the coarse search proposed it
    refined: RefinedPose  # the pose refinement kept (the candidate itself when refinement lost score)
    verdict: Verdict


@dataclass(frozen=True)
class Instance:
    coarse: PoseCandidate
    refined: RefinedPose | None  # None when refinement was not asked for
    verdict: Verdict


@dataclass(frozen=True)
class EstimateOutput:
    image_size: tuple[int, int]  # (w, h)
    found: bool
    coarse: PoseCandidate | None
    refined: RefinedPose | None
    candidates: list[PoseCandidate]
    timing_ms: dict[str, float]  # edges, coarse, refine, total
    overlay_png: bytes | None = None
    # the found/absent decision, its reason and the evidence it read (estimate/verdict.py)
    verdict: Verdict = field(default_factory=lambda: decide(None))
    # every found instance, each refined and verified on its own, sorted (``estimate``'s ``sort``); the
    # fields above describe instances[0]; empty when nothing is found
    instances: list[Instance] = field(default_factory=list)
    deadline_reached: bool = False  # the search stopped early at ``deadline_ms`` (anytime)
    # every candidate refined and judged, the verdict's order (found first, then by score): what the
    # teach-time calibration reads (``teach.calibrate_appearance``)
    checked: list[Checked] = field(default_factory=list)
    # how far the search got: the stage the deadline stopped ("search", "checks", "second pass", ...;
    # None when it did not), and how many candidates were refined and judged
    deadline_stopped_in: str | None = None
    candidates_checked: int = 0
    # sentences for the integrator when the evidence points at the request rather than the scene
    warnings: tuple[str, ...] = ()
