"""The found/absent decision: is the best candidate the part, on the evidence the image gives?

A grasp on a pose the image does not confirm is worse than no answer, so ``found`` asks for three
things in turn, each with its threshold here:

1. the best candidate's coarse score (half resolution) reaches ``FOUND_MIN_SCORE``;
2. the pose's border is confirmed at full resolution: the refinement's verified score reaches
   ``FOUND_MIN_REFINED_SCORE`` (the refinement runs as this check also when it is not reported, unless
   the coarse score already reaches that bar: ``needs_refined_check``);
3. the image shows little edge length inside the silhouette that the model's creases and occlusion
   steps do not explain (``interior.unexplained_edge_ratio`` <= ``FOUND_MAX_UNEXPLAINED``): a
   silhouette fitted to floor texture has the texture's lines running through it.

``screen`` and ``decide`` return a ``Verdict`` with the evidence it read, so a caller can show why.
"""

from __future__ import annotations

from dataclasses import dataclass, field

# Fraction of border points with a matching edge within score_px; an absent clutter scene reached 0.59.
# Under this the coarse pose is not even checked; over it the verdict is the refined pose's, below.
FOUND_MIN_SCORE = 0.65
# The verdict is taken on the refined pose's score (full resolution, sub-pixel), also when refinement
# is off (then it runs unreported, unless the coarse score already reaches this bar):
# on the paper renders every true pose refines to >= 0.94, while wrong poses on the checkerboard
# clutter stayed at 0.65-0.84 (one L-bracket match on the checkerboard's straight edges reached 0.99).
FOUND_MIN_REFINED_SCORE = 0.85
# ... and the image may show no more than this much edge length (per unit of silhouette perimeter)
# inside the silhouette that the model's creases and depth steps do not explain
# (interior.unexplained_edge_ratio). At the true pose: paper renders <= 0.06; clutter 0-0.36, and 0.59
# for a sprayer behind an occluder. The one confident wrong pose left in clutter (an L-bracket fitted to
# a block of checker squares, refined score 0.97) has 0.53.
FOUND_MAX_UNEXPLAINED = 0.4


@dataclass(frozen=True)
class Verdict:
    found: bool
    score: float  # 0..1: the score the decision read last (coarse, or full-resolution verified)
    reason: str  # one sentence: why found or not
    # what was measured: coarse_score, verified_score (full resolution), unexplained (edge length per
    # unit of perimeter); a check that did not run is absent
    evidence: dict[str, float] = field(default_factory=dict)


def needs_refined_check(coarse_score: float, *, refine: bool) -> bool:
    """Whether the refinement must run for the verdict: when it is reported anyway, and when the
    coarse score is one that wrong poses on textured floors reach too (0.65-0.76 in clutter)."""
    return refine or coarse_score < FOUND_MIN_REFINED_SCORE


def screen(coarse_score: float | None) -> Verdict | None:
    """The verdict when the coarse stage alone decides: no candidate (``coarse_score`` None), or a best
    coarse score under ``FOUND_MIN_SCORE``. None: the pose must be checked further (``decide``)."""
    if coarse_score is None:
        return Verdict(False, 0.0, "No candidate pose was found.")
    if coarse_score < FOUND_MIN_SCORE:
        return Verdict(False, float(coarse_score), "The best candidate's coarse score is under "
                       f"{FOUND_MIN_SCORE:g}.", {"coarse_score": float(coarse_score)})
    return None


def decide(coarse_score: float | None, *, verified_score: float | None = None,
           unexplained: float | None = None) -> Verdict:
    """The verdict on the best candidate from the evidence measured on it.

    coarse_score : the best candidate's coarse score, None without a candidate. verified_score : the
    full-resolution verification of the pose that would be reported (``refine.RefineResult.score``),
    None when the refinement did not run (``needs_refined_check`` was false). unexplained : the
    unexplained-edge ratio inside its silhouette; needed unless ``screen`` decides.
    """
    early = screen(coarse_score)
    if early is not None:
        return early
    evidence = {"coarse_score": float(coarse_score)}
    score = float(coarse_score)
    if verified_score is not None:
        evidence["verified_score"] = score = float(verified_score)
        if verified_score < FOUND_MIN_REFINED_SCORE:
            return Verdict(False, score, "The full-resolution edges confirm less than "
                           f"{FOUND_MIN_REFINED_SCORE:g} of the pose's border.", evidence)
    if unexplained is None:
        raise ValueError("the unexplained-edge ratio is needed for a candidate over FOUND_MIN_SCORE.")
    evidence["unexplained"] = float(unexplained)
    if unexplained > FOUND_MAX_UNEXPLAINED:
        return Verdict(False, score, "The image shows edges inside the silhouette that the model does not "
                       "explain.", evidence)
    return Verdict(True, score, "The image confirms the pose's border and its inside.", evidence)
