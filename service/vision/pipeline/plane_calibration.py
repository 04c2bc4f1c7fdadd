"""A part's operating point on a plane, calibrated on rendered scenes of it (``model/calibration_scenes``).

On a plane the verdict may also find a pose by the share of its visible CAD edges whose image gradient
agrees (``verdict.material_free``): evidence that assumes no material. How high a wrong pose of a part
reads there depends on the part: a tube's circles agree with any cylinder's end, a clamp's outline with
nothing else. So each part's agreement to reach is the highest a wrong pose reached in its calibration
scenes (every candidate judged, as a request on a plane judges them), raised by a margin: the rendered
scenes are cleaner than a cell's photos, where wrong poses read a little higher. The agreement is read
along every visible edge, or along the outline alone where that lets more of the scenes' right poses reach
their point: a smooth moulding's creases seldom show under one light, and dilute what its outline says.
A resting family whose scenes hold enough wrong poses in it has its own point (look-alikes fit an allen
key in one of its lying poses better than in the other).
Most of the wrong poses that set the point lie at a copy's place: the part flipped or spun on itself. Away
from every copy a wrong pose reads lower, so a part has a second point, the place point: ``margin`` above
the highest wrong pose away from every copy. A pose reaching only it is found if no other candidate at its
place agrees more (``pipeline/place``), and the part has the place point only if in its scenes the
best-agreeing candidate at every copy's place that reached it was right.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from service.vision.bank import TemplateBank
from service.vision.estimate.verdict import AGREEMENT_EVIDENCE, PlaneAgreement, distinct, material_free
from service.vision.pipeline.calibration_scenes import scene
from service.vision.pipeline.estimate import estimate
from service.vision.pipeline.part import rest_family
from service.vision.pipeline.place import SAME_PLACE_IOU, silhouette_iou
from service.vision.pipeline.policy import DEFAULT_POLICY, Policy
from service.vision.pipeline.teach import pose_error_px

_NEVER = 2.0  # a min_score no candidate reaches: every proposal is checked and judged
WRONG_PX = 20.0  # a judged pose this far (MSPD, 640 px wide) from every copy is wrong
RIGHT_PX = 5.0  # and this close to one, right
# Poses refused for where they lie, not how they look: a request refuses them the same way.
REFUSED_FOR_PLACE = ("outside_distance_range", "outside_image", "off_plane")
SCENES = 12  # about a minute a part on 2 cores
# agreement above the highest wrong candidate's: the smallest that found no wrong instance on the fit sets
# (sygrid_synth, the Blender piles) and the project's plane renders: at 0.06 a face-up flange is found on
# a copy lying tilted and face down (docs/benchmarks.md)
MARGIN = 0.08
# Fewer wrong candidates than this a scene say too little of how high a wrong pose reads: not calibrated
# (a part's scenes give 12-19 a scene where its outlines are distinct; a long spanner, 2)
MIN_WRONG_PER_SCENE = 8
# ... and fewer right ones than this a scene, of how low a right pose reads: no floor
MIN_RIGHT_PER_SCENE = 1
# A resting family has its own point where its scenes gave at least this many wrong candidates in it a
# scene: how high a wrong pose reads depends on the view (an allen key's look-alikes fit it in one of its
# lying poses better than in the other: 0.59 against 0.53), and a pose is found in the family it is in.
# The highest of fewer says too little: at 2 a scene an allen key's family of 32 wrong poses and no
# right one read 0.40 at most, sygrid_synth's wrong poses in it 0.50 and 0.60
MIN_WRONG_PER_REST_SCENE = 4
# Another agreement than the first of ``along`` is read only where it lets this share more of the scenes'
# right candidates reach their point: one or two more is the scenes' noise (a sygrid clamp's outline let
# 26 of 39 reach it against its edges' 25, and found 18 of its copies against 24)
ALONG_MIN_GAIN = 0.1


@dataclass(frozen=True)
class PlaneRecord:
    error_px: float  # MSPD to the nearest copy, 640 px wide
    reason: str
    evidence: dict
    rest: int = -1  # the resting family the candidate's pose is in (``part.rest_family``); -1: not known
    scene: int = -1  # the calibration scene it was judged in; -1: not known
    place: int = -1  # the copy its silhouette overlaps most (index in the scene's poses); -1: none
    overlap: float = 0.0  # that silhouette IoU


def plane_records(bank: TemplateBank, n_scenes: int, seed: int = 0,
                  progress: Callable[[int, int], None] | None = None, *,
                  policy: Policy = DEFAULT_POLICY) -> list[PlaneRecord]:
    """Every candidate judged on ``n_scenes`` calibration scenes of ``bank``'s part, with its error (none for
    a bank made before resting poses were: it is never searched on a plane)."""
    out: list[PlaneRecord] = []
    if bank.R_rest_obj is None or not len(bank.R_rest_obj):
        return out
    for i in range(n_scenes):
        if progress is not None:
            progress(i, n_scenes)
        sc = scene(bank, np.random.default_rng([seed, i]))
        est = estimate(bank, sc.bgr, sc.intr, plane=sc.plane, max_instances=max(1, len(sc.poses)),
                       min_score=_NEVER, policy=policy)
        size, memo = (sc.bgr.shape[1], sc.bgr.shape[0]), {}
        for c in est.checked:
            err = min((pose_error_px(bank, c.refined.pose, q, sc.intr, sc.bgr.shape[1], policy)
                       for q in sc.poses), default=math.inf)
            iou = [silhouette_iou(bank, c.refined.pose, q, sc.intr, size, memo=memo) for q in sc.poses]
            place = int(np.argmax(iou)) if iou and max(iou) > 0.0 else -1
            out.append(PlaneRecord(float(err), c.verdict.reason, c.verdict.evidence,
                                   rest_family(bank, c.refined.pose.R, sc.plane.normal), i, place,
                                   float(iou[place]) if place >= 0 else 0.0))
    return out


@dataclass(frozen=True)
class PlaneCalibration:
    agreement_min: float | None  # the material-free score a pose must reach; None: not calibrated
    wrong_max: float  # the highest a wrong candidate read
    right: int  # right candidates at or above ``agreement_min``, of ``right_total``
    right_total: int
    wrong_total: int
    scenes: int
    # the least a found pose may read, whatever its other evidence; None: no right candidate to say
    agreement_floor: float | None = None
    agreement_along: str = "edge_agreement"  # the agreement both are read on (``verdict.AGREEMENT_EVIDENCE``)
    # each resting family's agreement to reach, where its scenes had enough wrong candidates in it
    # (``MIN_WRONG_PER_REST_SCENE``); None: ``agreement_min``
    agreement_min_by_rest: tuple[float | None, ...] = ()
    # the agreement a pose no other candidate at its place outagrees must reach (``place_point``); None:
    # none (not calibrated, or a wrong pose was its place's best there)
    agreement_min_place: float | None = None

    @property
    def agreement(self) -> PlaneAgreement:
        """The operating point as the verdict takes it."""
        return PlaneAgreement(self.agreement_min, self.agreement_floor, self.agreement_along,
                              self.agreement_min_by_rest, self.agreement_min_place)


def calibrated(records: list[PlaneRecord], scenes: int, margin: float = MARGIN,
               along: tuple[str, ...] = AGREEMENT_EVIDENCE) -> PlaneCalibration:
    """The part's calibration on the agreement of ``along`` under which most right candidates reach their
    point (the first unless another gains ``ALONG_MIN_GAIN``): some parts' creases seldom show, and their
    outline tells them better; a part whose outline look-alikes share tells them by its creases
    (``_calibrated_along``)."""
    # (which candidates are wrong or right does not depend on ``along``: an uncalibrated part reaches 0)
    first, *others = [_calibrated_along(records, scenes, margin, a) for a in along]
    best = max(others, key=lambda c: c.right, default=first)
    return best if best.right - first.right >= max(1.0, ALONG_MIN_GAIN * best.right_total) else first


def _calibrated_along(records: list[PlaneRecord], scenes: int, margin: float, along: str) -> PlaneCalibration:
    """The agreement a part's pose must reach to be found on it: ``margin`` above the highest wrong
    candidate's, over its scenes and over those in each resting family (``_points_by_rest``); and the
    least it may read to be found at all: ``margin`` below the lowest right one's (a pose whose visible
    edges mostly disagree is not the part, however its shading reads)."""
    # (a pose whose outline a plain shape has too is never found on agreement: ``verdict.distinct``)
    wrong = [r for r in records
             if r.error_px >= WRONG_PX and r.reason not in REFUSED_FOR_PLACE and distinct(r.evidence)]
    right = [r for r in records if r.error_px < RIGHT_PX and distinct(r.evidence)]
    top = max((material_free(r.evidence, along) for r in wrong), default=0.0)
    agreement_min = top + margin if len(wrong) >= MIN_WRONG_PER_SCENE * scenes else None
    by_rest = _points_by_rest(wrong, scenes, margin, along) if agreement_min is not None else ()
    point = PlaneAgreement(agreement_min, None, along, by_rest)
    reached = sum(material_free(r.evidence, along) >= point.at_rest(r.rest).point for r in right) \
        if agreement_min is not None else 0
    # every right candidate, an outline a plain shape has too or not: the floor holds for all of them
    every_right = [material_free(r.evidence, along) for r in records if r.error_px < RIGHT_PX]
    floor = min(every_right) - margin if len(every_right) >= MIN_RIGHT_PER_SCENE * scenes else None
    place = place_point(records, margin, along) if agreement_min is not None else None
    return PlaneCalibration(agreement_min, top, reached, len(right), len(wrong), scenes, floor, along,
                            by_rest, place if place is not None and place < agreement_min else None)


def place_point(records: list[PlaneRecord], margin: float, along: str) -> float | None:
    """``margin`` above the highest agreement of a wrong candidate away from every copy (silhouette IoU
    under ``SAME_PLACE_IOU``); None if the records do not say where they lie, or if at some copy's place
    the best-agreeing candidate reaching that point was wrong: there a flip of the part on itself
    outagrees the truth, and only the full point keeps it out."""
    if any(r.scene < 0 for r in records):
        return None
    judged = [r for r in records if r.reason not in REFUSED_FOR_PLACE and distinct(r.evidence)]
    elsewhere = [material_free(r.evidence, along) for r in judged
                 if r.error_px >= WRONG_PX and r.overlap < SAME_PLACE_IOU]
    point = max(elsewhere, default=0.0) + margin
    best: dict[tuple[int, int], tuple[float, PlaneRecord]] = {}
    for r in judged:
        read = material_free(r.evidence, along)
        if r.overlap >= SAME_PLACE_IOU and read > best.get((r.scene, r.place), (-1.0, r))[0]:
            best[(r.scene, r.place)] = (read, r)
    if any(read >= point and r.error_px >= WRONG_PX for read, r in best.values()):
        return None
    return point

def _points_by_rest(wrong: list[PlaneRecord], scenes: int, margin: float, along: str
                    ) -> tuple[float | None, ...]:
    """Per resting family (0 .. the highest a record is in), ``margin`` above the highest wrong candidate's
    agreement in it; None for a family with fewer than ``MIN_WRONG_PER_REST_SCENE`` a scene."""
    n = max((r.rest for r in wrong), default=-1) + 1
    out: list[float | None] = []
    for family in range(n):
        read = [material_free(r.evidence, along) for r in wrong if r.rest == family]
        out.append(max(read) + margin if len(read) >= MIN_WRONG_PER_REST_SCENE * scenes else None)
    return tuple(out)


def calibrate_plane(bank: TemplateBank, n_scenes: int = SCENES, seed: int = 0,
                    progress: Callable[[int, int], None] | None = None, *,
                    policy: Policy = DEFAULT_POLICY) -> PlaneCalibration:
    """``bank``'s part calibrated on ``n_scenes`` rendered scenes (``plane_records``, ``calibrated``)."""
    return calibrated(plane_records(bank, n_scenes, seed, progress, policy=policy), n_scenes)
