"""The found/absent verdict: one verification score from all the evidence, and the reason it gives.

A pose is reported as found only when its verification score reaches the operating point. The score
is a logistic regression on the evidence of a refined hypothesis: the grey edge support of the
refinement (``refine.verify``), the unexplained edges inside the silhouette (``interior``), and the
colour-image evidence (``evidence``: colour edges along the outline, the coherence of their contrast,
the inside/outside colour separability, the shading the part's normals explain). Its weights were
fitted by ``bench/fit_verdict.py`` on the tuning sets (seeded synthetic scenes of
``bench/synth_scenes.py``, and the shared ``clutter2`` / ``absent2``), never on the sets it is reported
on. Evidence the fit gave no weight is still reported: the reason of a rejection names the evidence
furthest from a true pose's.

How closely a plain shape fits the pose's silhouette (``generic``, ``shapes.genericity``) and how far
apart the two outlines lie (``distinct_px``) are reported and not scored (docs/detection-history.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

# The evidence every verdict reports (each a fraction in [0, 1] but ``unexplained``, which may exceed 1,
# and ``shading_std``, in grey levels).
FEATURES = ("edge_support", "unexplained", "colour_edge", "polarity", "region", "region_low", "region_global",
            "coherence", "shading_r2", "shading_std",
            # how closely a plain shape fits the pose's silhouette (``shapes.genericity``), and how far
            # apart, in image pixels, the two outlines lie on average (``shapes.distinct_px``)
            "generic", "distinct_px",
            # the taught appearance's (``evidence.appearance``): only for a part with reference photos
            "appearance", "appearance_known",
            # with a plane: the gradient orientation along every visible CAD edge, along the inner ones
            # and along the outline alone, and along every edge and the outline by their extent
            # (``edge_agreement.py``): evidence that assumes no material
            "edge_agreement", "inner_agreement", "outline_agreement", "edge_coverage", "outline_coverage")
# Evidence an older record (a bench cache made before it existed) may lack: read as 0 in a feature vector.
# Of these, reported only for a part with taught colours (scored by ``APPEARANCE_WEIGHTS`` then).
TAUGHT_FEATURES = ("appearance", "appearance_known")
# Reported only with a plane (``pipeline/check.judge``).
PLANE_FEATURES = ("edge_agreement", "inner_agreement", "outline_agreement", "edge_coverage",
                  "outline_coverage")
LATER_FEATURES = ("distinct_px", *TAUGHT_FEATURES, *PLANE_FEATURES)
# Evidence the verification score of an untaught part may use, and which of it counts against a pose.
MODEL_FEATURES = ("edge_support", "unexplained", "colour_edge", "region_low", "region_global", "coherence",
                  "shading_r2", "generic")
LOWER_IS_BETTER = ("unexplained", "generic")
# The score's weights (logistic regression, each weight's sign fixed so that better evidence never lowers
# the score), fitted by ``bench/fit_verdict.py`` on the tuning sets (120 synthetic scenes of
# bench/synth_scenes.py, seed 11, and clutter2 / absent2); evidence it dropped has weight 0.
WEIGHTS = {"bias": -3.935, "unexplained": -0.339, "region_global": 5.265, "shading_r2": 4.329}
# The score of a part with taught colours (``model/appearance.py``; its evidence has ``appearance``): the
# untextured shading model says nothing about a printed or painted part, the taught colours do. Fitted by
# ``bench/appearance.py`` (logistic, signs fixed) on half of lmo_dev's images (the even ones among those
# not used as reference photos), reported on the other half. (Its teaching now hides the other annotated
# parts' pixels through ``pipeline.teach_appearance``: the refit moves each weight by under 0.02.)
APPEARANCE_WEIGHTS = {"bias": -5.58, "appearance": 4.43, "appearance_known": 3.76, "region_global": 4.29}
# Operating point (``options.min_score`` moves it).
MIN_SCORE = 0.98
# On a plane, a part whose agreement was calibrated (``pipeline/plane_calibration``) is also scored on
# evidence that assumes no material (``material_free``): its score reaches ``MIN_SCORE`` at the part's
# calibrated agreement and rises this steeply (logit per unit of agreement) above it.
AGREEMENT_SLOPE = 40.0
# ... where its outline lies at least this far (image pixels, ``distinct_px``) from the nearest plain
# shape's: nearer, no image tells the part from a plain object of that outline (a screw standing on its
# head is a small circle, as is a nut, a hole, a nozzle standing on either end), and edges alone cannot
# tell the part's pose from another pose of that outline
MIN_DISTINCT_PX = 1.0
# Refits on the visible part's evidence and on ``generic``: docs/detection-history.md.

# The reasons a verdict gives.
REASONS = ("found", "no_candidate", "outside_distance_range", "outside_image", "off_plane", "low_support",
           "interior_edges", "region_mismatch", "shading_mismatch", "generic_outline", "low_score",
           "deadline", "appearance_mismatch", "edges_disagree", "rival_at_place")
# "deadline": the search stopped early (``deadline_ms``) before a candidate was found; the pipeline
# sets it (``decide`` judges one hypothesis and never returns it); so is "rival_at_place": a pose found only
# at its part's place point, refused since another candidate at its place agrees more (``pipeline/place``).
# A rejected pose is said to fail on the evidence furthest below a true pose's typical value (medians
# over the truth hypotheses of the tuning sets): the reason names the one a person should look at.
TYPICAL_RIGHT = {"edge_support": 0.9, "unexplained": 0.1, "colour_edge": 0.95, "region_global": 0.85,
                 "shading_r2": 0.9, "generic": 0.88, "appearance": 0.74}
# A pose whose outline lies more than a fifth outside the image is not checked ("outside_image"): the
# evidence sees only its inside part, and the cut-off part is where a wrong pose on the part's own visible
# piece would be refuted (docs/detection-history.md).
MIN_IN_IMAGE = 0.8


@dataclass(frozen=True)
class Verdict:
    found: bool
    score: float  # verification score in [0, 1] of the pose the answer reports (or of the best rejected)
    reason: str  # one of REASONS
    evidence: dict[str, float] = field(default_factory=dict)


def _read(ev: dict, k: str) -> float:
    """``ev[k]``; evidence a record made before it existed lacks (``LATER_FEATURES``) reads 0."""
    return float(ev[k] if k in ev or k not in LATER_FEATURES else 0.0)


def feature_vector(ev: dict) -> np.ndarray:
    """The evidence in ``FEATURES`` order, (len(FEATURES),) float64."""
    return np.array([_read(ev, k) for k in FEATURES], float)


def weights_for(ev: dict) -> dict:
    """The score's weights for this evidence: ``APPEARANCE_WEIGHTS`` where the part's colours were taught."""
    return APPEARANCE_WEIGHTS if "appearance" in ev else WEIGHTS


def verification_score(ev: dict, weights: dict | None = None) -> float:
    """The logistic verification score of an evidence dict, in [0, 1] (default weights: ``weights_for``)."""
    w = weights_for(ev) if weights is None else weights
    z = w["bias"] + sum(wk * _read(ev, k) for k, wk in w.items() if k != "bias")
    return float(1.0 / (1.0 + np.exp(-z)))


def distinct(ev: dict) -> bool:
    """The pose's outline lies at least ``MIN_DISTINCT_PX`` from the nearest plain shape's."""
    return _read(ev, "distinct_px") >= MIN_DISTINCT_PX


# The agreements a part's calibration may judge it on (``pipeline/plane_calibration``): along every visible
# edge, or along the outline alone (a part whose creases seldom show reads its outline undiluted), each by
# its orientations or by its extent (a look-alike longer or shorter than the part differs at an end only).
AGREEMENT_EVIDENCE = ("edge_agreement", "outline_agreement", "edge_coverage", "outline_coverage")


def material_free(ev: dict, along: str = "edge_agreement") -> float:
    """The share of the pose's visible CAD edges (``along``: one of ``AGREEMENT_EVIDENCE``) whose image
    gradient agrees, held down by how consistently the outline's contrast keeps its sign
    (``polarity``): a pose laid across other parts' straight edges agrees in orientation but flips
    contrast from part to part."""
    return min(_read(ev, along), float(ev.get("polarity", 0.0)))


@dataclass(frozen=True)
class PlaneAgreement:
    """A part's material-free operating point on a plane, calibrated on rendered scenes of it
    (``pipeline/plane_calibration``): a pose is also found when its agreement ``along`` reaches
    ``point`` (its resting family's: ``at_rest``), and never found under ``floor``, whatever its other
    evidence."""
    point: float | None  # None: not calibrated (too few wrong poses to say how high one reads)
    floor: float | None  # None: too few right poses to say how low one reads
    along: str = "edge_agreement"  # one of ``AGREEMENT_EVIDENCE``
    # the point of a pose in each resting family (``part.rest_family``), where its scenes said how high a
    # wrong pose in it reads; None (or no entry): ``point``
    points_by_rest: tuple[float | None, ...] = ()
    # the point a pose reaches to be found if no other candidate at its place agrees more
    # (``pipeline/place``): wrong poses away from every copy read lower than those at one; None: none
    place_point: float | None = None

    def at_place(self) -> PlaneAgreement | None:
        """The operating point at the place point, where it lies under the pose's own; else None."""
        if self.place_point is None or self.point is None or self.place_point >= self.point:
            return None
        return replace(self, point=self.place_point)

    def at_rest(self, family: int) -> PlaneAgreement:
        """The operating point of a pose in resting family ``family``."""
        if not 0 <= family < len(self.points_by_rest) or self.points_by_rest[family] is None:
            return self
        return replace(self, point=self.points_by_rest[family])


def agreement_score(ev: dict, agreement: PlaneAgreement) -> float:
    """The score of ``material_free(ev, agreement.along)`` for a part calibrated at ``agreement.point``:
    ``MIN_SCORE`` there; 0 for an outline a plain shape has too (``MIN_DISTINCT_PX``) or an uncalibrated
    part."""
    if not distinct(ev) or agreement.point is None:
        return 0.0
    z = math.log(MIN_SCORE / (1.0 - MIN_SCORE)) + AGREEMENT_SLOPE * (
        material_free(ev, agreement.along) - agreement.point)
    return float(1.0 / (1.0 + math.exp(-min(max(z, -50.0), 50.0))))


def rejection_reason(ev: dict) -> str:
    """The evidence furthest from a true pose's: which one a person should look at."""
    gaps = {
        "low_support": TYPICAL_RIGHT["edge_support"] - ev["edge_support"],
        "interior_edges": ev["unexplained"] - TYPICAL_RIGHT["unexplained"],
        "region_mismatch": max(TYPICAL_RIGHT["region_global"] - ev["region_global"],
                               TYPICAL_RIGHT["colour_edge"] - ev["colour_edge"]),
        "shading_mismatch": TYPICAL_RIGHT["shading_r2"] - ev["shading_r2"],
        # (evidence made before ``generic`` existed lacks it: never the reason then)
        "generic_outline": ev.get("generic", 0.0) - TYPICAL_RIGHT["generic"],
    }
    if "appearance" in ev:  # taught colours: they, not the untextured shading model, judge the inside
        del gaps["shading_mismatch"]
        gaps["appearance_mismatch"] = TYPICAL_RIGHT["appearance"] - ev["appearance"]
    reason, gap = max(gaps.items(), key=lambda kv: kv[1])
    return reason if gap > 0 else "low_score"


def decide(ev: dict | None, *, z_mm: float | None = None,
           distance_range_mm: tuple[float, float] | None = None, min_score: float | None = None,
           weights: dict | None = None, plane_gap_mm: float | None = None,
           plane_tolerance_mm: float | None = None, agreement: PlaneAgreement | None = None) -> Verdict:
    """The verdict on one refined hypothesis's evidence (``None``: there was no hypothesis).

    ``plane_gap_mm``: with a supporting plane, the height of the posed part's lowest point above it
    (negative: through it); beyond +-``plane_tolerance_mm`` the pose does not rest on the plane and is
    not found ("off_plane", the gap in the evidence as ``plane_gap_mm``). ``agreement``: with a plane,
    the part's calibrated agreement: the score is then the higher of the verification score and
    ``agreement_score``, and a pose scoring enough but reading less than its floor is not found
    ("edges_disagree"); a pose that scores enough only at the part's place point is found with
    ``at_place_point`` 1 in its evidence (the pipeline holds it against the candidates at its place)."""
    if ev is None:
        return Verdict(False, 0.0, "no_candidate")
    score = verification_score(ev, weights)
    # (a record made before the agreement was measured is judged as it was then)
    calibrated = plane_gap_mm is not None and "edge_agreement" in ev and agreement is not None
    at_place = None
    if calibrated:
        score = max(score, agreement_score(ev, agreement))
        at_place = agreement.at_place()
    # (a part without taught colours lacks their evidence: reported as given)
    evidence = {k: float(ev[k]) for k in FEATURES if k in ev} | {"in_image": float(ev.get("in_image", 1.0))}
    if distance_range_mm is not None and z_mm is not None and not (
            distance_range_mm[0] <= z_mm <= distance_range_mm[1]):
        return Verdict(False, score, "outside_distance_range", evidence | {"z_mm": float(z_mm)})
    if ev.get("in_image", 1.0) < MIN_IN_IMAGE:
        return Verdict(False, score, "outside_image", evidence)
    if plane_gap_mm is not None:
        evidence["plane_gap_mm"] = float(plane_gap_mm)
        if plane_tolerance_mm is not None and abs(plane_gap_mm) > plane_tolerance_mm:
            return Verdict(False, score, "off_plane", evidence)
    threshold = MIN_SCORE if min_score is None else min_score
    if score < threshold and at_place is not None:
        place_score = agreement_score(ev, at_place)
        if place_score >= threshold:
            score = place_score
            evidence["at_place_point"] = 1.0
    if score >= threshold:
        # (a pose under the operating point keeps the reason its evidence gives: only a would-be-found
        # one is refused for its edges)
        floor = agreement.floor if calibrated else None
        if floor is not None and material_free(ev, agreement.along) < floor:
            return Verdict(False, score, "edges_disagree", evidence)
        return Verdict(True, score, "found", evidence)
    return Verdict(False, score, rejection_reason(evidence), evidence)
