"""A pose's verification score as it stands, before any refinement: how the twin check, the colour polish
and a taught part's proposal order rank poses without refining each."""

from __future__ import annotations

import numpy as np

from service.vision.bank import TemplateBank
from service.vision.deadline import NO_DEADLINE, Deadline
from service.vision.estimate.evidence import REGION_AND_SHADING, ColourFrame, evidence, region_and_shading
from service.vision.estimate.verdict import APPEARANCE_WEIGHTS, WEIGHTS, verification_score
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose
from service.vision.model.appearance import Appearance
from service.vision.pipeline import timing
from service.vision.pipeline.types import PoseCandidate

PERFECT_EDGES = {"edge_support": 1.0, "unexplained": 0.0}  # the refinement's evidence, before it runs


def face_bgr_of(appearance: Appearance | None) -> np.ndarray | None:
    return None if appearance is None else appearance.face_bgr


def unrefined_score(bank: TemplateBank, pose: Pose, frame: ColourFrame, intr: Intrinsics,
                    others_depth_mm: np.ndarray | None, appearance: Appearance | None = None) -> float:
    """The verification score of ``pose`` as it stands, the refinement's own evidence read as perfect."""
    face_bgr = face_bgr_of(appearance)
    read = set(APPEARANCE_WEIGHTS if face_bgr is not None else WEIGHTS) - {"bias", *PERFECT_EDGES}
    if read <= set(REGION_AND_SHADING):  # the service's weights: what the score reads, measured alone
        ev = region_and_shading(bank, pose, intr, frame, others_depth_mm, face_bgr)
    else:
        ev = evidence(bank, pose, intr, frame, others_depth_mm, face_bgr).as_dict()
    return verification_score(ev | PERFECT_EDGES)


def by_unrefined_score(bank: TemplateBank, cands: list[PoseCandidate], frame: ColourFrame, intr: Intrinsics,
                       appearance: Appearance | None, deadline: Deadline = NO_DEADLINE
                       ) -> list[PoseCandidate]:
    """``cands`` by their unrefined verification score, highest first (stable; those the ``deadline``
    left no time to score keep their order after the scored ones)."""
    scored: list[tuple[float, int]] = []
    for i, c in enumerate(cands):
        if not deadline.allows(timing.EVIDENCE_MS + timing.CHECK_MS.high):
            break
        scored.append((unrefined_score(bank, c.pose, frame, intr, None, appearance), i))
    order = [i for _, i in sorted(scored, key=lambda si: -si[0])] + list(range(len(scored), len(cands)))
    return [cands[i] for i in order]
