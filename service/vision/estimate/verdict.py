"""The found/absent verdict: one verification score from all the evidence, and the reason it gives.

A pose is reported as found only when its verification score reaches the operating point. The score
is a logistic regression on the evidence of a refined hypothesis: the grey edge support of the
refinement (``refine.verify``), the unexplained edges inside the silhouette (``interior``), and the
colour evidence (``evidence``: colour edges along the outline, their polarity, the inside/outside
colour separability). Its weights were fitted by ``bench/fit_verdict.py`` on seeded synthetic scenes
(``bench/synth_scenes.py``), not on the shared sets it is reported on.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Order of the weights below; each is a fraction in [0, 1] (``unexplained`` may exceed 1).
FEATURES = ("edge_support", "unexplained", "colour_edge", "polarity", "region", "region_low", "region_global",
            "coherence", "shading_r2", "shading_std")
WEIGHTS = {"bias": -61.513, "edge_support": -3.189, "unexplained": 18.647, "colour_edge": 8.324,
           "polarity": 8.876, "region": 19.825, "region_low": 31.617, "region_global": 0.0, "coherence": 0.0}
# Operating point: on the fit data the precision of found answers reaches 99.5 % at this score.
MIN_SCORE = 0.9

# The reasons a verdict gives, in the order they are tried for a rejection.
REASONS = ("found", "no_candidate", "outside_distance_range", "outside_image", "low_support",
           "interior_edges", "region_mismatch", "low_score", "deadline")
# A rejected pose is said to fail on one evidence when that evidence is this far from a true pose's
# typical value (the bench's medians over right hypotheses): the reason names the weakest one.
TYPICAL_RIGHT = {"edge_support": 0.9, "unexplained": 0.1, "colour_edge": 0.8, "region": 0.6}
MIN_IN_IMAGE = 0.5  # a pose whose outline is mostly outside the image cannot be checked


@dataclass(frozen=True)
class Verdict:
    found: bool
    score: float  # verification score in [0, 1] of the pose the answer reports (or of the best rejected)
    reason: str  # one of REASONS
    evidence: dict[str, float] = field(default_factory=dict)


def feature_vector(ev: dict) -> np.ndarray:
    """The features in ``FEATURES`` order from an evidence dict (bench rows use suffix 1: refined)."""
    def get(k):
        for key in (k, k + "1", {"edge_support": "rscore"}.get(k, k)):
            if key in ev:
                return float(ev[key])
        raise KeyError(k)

    return np.array([get(k) for k in FEATURES], float)


def verification_score(ev: dict, weights: dict | None = None) -> float:
    w = WEIGHTS if weights is None else weights
    z = w["bias"] + float(np.dot([w[k] for k in FEATURES], feature_vector(ev)))
    return float(1.0 / (1.0 + np.exp(-z)))


def rejection_reason(ev: dict) -> str:
    """The evidence furthest from a true pose's: which one a person should look at."""
    gaps = {
        "low_support": TYPICAL_RIGHT["edge_support"] - ev["edge_support"],
        "interior_edges": ev["unexplained"] - TYPICAL_RIGHT["unexplained"],
        "region_mismatch": max(TYPICAL_RIGHT["region"] - ev["region"],
                               TYPICAL_RIGHT["colour_edge"] - ev["colour_edge"]),
    }
    reason, gap = max(gaps.items(), key=lambda kv: kv[1])
    return reason if gap > 0 else "low_score"


def decide(ev: dict | None, *, z_mm: float | None = None,
           distance_range_mm: tuple[float, float] | None = None, min_score: float | None = None,
           weights: dict | None = None) -> Verdict:
    """The verdict on one refined hypothesis's evidence (``None``: there was no hypothesis)."""
    if ev is None:
        return Verdict(False, 0.0, "no_candidate")
    score = verification_score(ev, weights)
    evidence = {k: float(ev[k]) for k in FEATURES} | {"in_image": float(ev.get("in_image", 1.0))}
    if distance_range_mm is not None and z_mm is not None and not (
            distance_range_mm[0] <= z_mm <= distance_range_mm[1]):
        return Verdict(False, score, "outside_distance_range", evidence | {"z_mm": float(z_mm)})
    if ev.get("in_image", 1.0) < MIN_IN_IMAGE:
        return Verdict(False, score, "outside_image", evidence)
    if score >= (MIN_SCORE if min_score is None else min_score):
        return Verdict(True, score, "found", evidence)
    return Verdict(False, score, rejection_reason(evidence), evidence)
