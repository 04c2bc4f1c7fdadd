"""One frame's story: propose -> check -> answer (``estimate``); the request's scale probe
(``estimate_image``, ``misscaled_request``)."""

from __future__ import annotations

import math
import time
from dataclasses import replace

import cv2
import numpy as np

from service.vision.bank import TemplateBank
from service.vision.deadline import Deadline
from service.vision.estimate.edges import to_grey_u8
from service.vision.estimate.evidence import ColourFrame, colour_frame
from service.vision.estimate.plane import PLANE_TOLERANCE_MM
from service.vision.estimate.search import SearchParams
from service.vision.estimate.verdict import PlaneAgreement, Verdict, decide
from service.vision.geometry.camera import Intrinsics, undistort_image
from service.vision.geometry.plane import Plane, depths_in_view_mm
from service.vision.model.appearance import Appearance
from service.vision.pipeline import timing
from service.vision.pipeline.check import verify_candidates
from service.vision.pipeline.instances import sort_instances, verify_instances
from service.vision.pipeline.policy import DEFAULT_DISTANCE_RANGE_MM, DEFAULT_POLICY, Policy, TaughtSearch
from service.vision.pipeline.propose import ByColours, LaterPass, propose, taught_colour_density
from service.vision.pipeline.types import Checked, EstimateOutput, Instance, PoseCandidate


def estimate(bank: TemplateBank, image: np.ndarray, intr: Intrinsics, *, distance_mm: float | None = None,
             distance_range_mm: tuple[float, float] | None = None, refine: bool = True, top_k: int = 5,
             overlay: bool = False, params: SearchParams | None = None,
             min_score: float | None = None, roi_uv: np.ndarray | None = None, max_instances: int = 1,
             sort: str = "score", deadline_ms: float | None = None, started_at: float | None = None,
             plane: Plane | None = None, plane_tolerance_mm: float = PLANE_TOLERANCE_MM,
             appearance: Appearance | None = None, agreement: PlaneAgreement | None = None,
             policy: Policy = DEFAULT_POLICY) -> EstimateOutput:
    """Grey (H, W) or BGR (H, W, 3) image + intrinsics -> ranked poses and the verdict on the best.

    The coarse search proposes; up to ``policy.n_verify`` candidates are refined (also with ``refine``
    false: refinement is the check then, and ``refined`` stays null) and verified on the colour image
    (``verdict``); the one with the highest verification score is reported, found when that score
    reaches ``min_score`` (default: the part's operating point, ``Policy.operating_point``, else
    ``verdict.MIN_SCORE``) and its distance lies in the searched range.

    ``roi_uv``: see ``propose``. ``max_instances`` > 1: more proposals are kept (``search_params_for``) and
    verified until that many distinct instances are found (``verify_instances``); they are reported
    in ``instances`` sorted by ``sort`` ("score": verification score, highest first; "distance": the
    part's centre nearest the camera first; "height", with a plane: the part's centre highest above
    it first), and the top-level fields describe the first.

    ``deadline_ms``: the search is anytime (``vision/deadline.py``): it stops starting new work when
    the deadline, counted from ``started_at`` (a ``time.perf_counter()`` reading; default: now), no
    longer leaves time to verify a candidate, and reports the best verified result so far;
    ``deadline_reached`` says so, and ``verdict.reason`` is "deadline" when nothing was found.

    ``plane``: the supporting plane (see ``propose``); a refined pose whose lowest point lies more than
    ``plane_tolerance_mm`` above or below it is not found (verdict reason "off_plane").

    ``appearance``: the part's colours taught from reference photos (``model/appearance.py``): every
    candidate is then judged on them too (``verdict.APPEARANCE_WEIGHTS``), unless the photos show a plain
    part or disagree (``Appearance.used``).

    ``agreement``: the part's agreement calibrated on rendered scenes (``pipeline/plane_calibration``):
    on a plane a candidate is also scored on its visible edges' agreement (``verdict.agreement_score``),
    and none is found under its floor.
    """
    if sort == "height" and plane is None:
        raise ValueError("sort 'height' needs a plane")
    if plane is not None:
        distance_mm = None  # the plane fixes the depth of every placement
    appearance = appearance_in_use(appearance)
    if min_score is None:
        min_score = policy.operating_point(appearance)
    p = params or policy.search_params_for(max_instances)
    t_start = time.perf_counter() if started_at is None else started_at
    deadline = Deadline(deadline_ms, start=t_start)
    grey = to_grey_u8(image)
    h, w = grey.shape
    if plane is not None and distance_range_mm is None:
        distance_range_mm = plane_range(bank, plane, intr, (w, h), policy)
    # The evidence reads pixels where the ideal camera projects the model: undistort the frame once.
    ideal = undistort_image(image, intr)
    frame = colour_frame(ideal)
    # One instance: the later passes run only when the first pass's candidates all fail.
    later: list[LaterPass] = []
    search = policy.search_of(appearance)
    cands, _, timing_ms = propose(
        bank, grey, intr, distance_mm=distance_mm, distance_range_mm=distance_range_mm, params=p,
        roi_uv=roi_uv, deadline=deadline,
        reserve_ms=timing.CHECK_MS.high + policy.search_reserve_checks * timing.CHECK_MS.value,
        plane=plane, max_instances=max_instances, deferred=later if max_instances <= 1 else None,
        colour=ideal, frame=frame, policy=policy,
        **_taught_passes(bank, frame, intr, appearance, search, deadline, policy))
    t0 = time.perf_counter()
    deadline.enter("checks")
    kw = dict(distance_mm=distance_mm, distance_range_mm=judged_range(distance_mm, distance_range_mm),
              min_score=min_score, n_channels=p.n_channels, deadline=deadline, plane=plane,
              plane_tolerance_mm=plane_tolerance_mm, appearance=appearance, policy=policy,
              agreement=agreement)
    if max_instances <= 1:
        checked = verify_candidates(bank, cands, grey, frame, intr, **kw)
        checked, more, t_later = _later_checks(bank, checked, later, grey, frame, intr, search, appearance,
                                               kw)
        cands = cands + more
        timing_ms["coarse"] += t_later
        best = checked[0] if checked else None
        found_list = [best] if best is not None and best.verdict.found else []
    else:
        found_list, rejected = verify_instances(bank, cands, grey, frame, intr, max_instances=max_instances,
                                                **kw)
        found_list = sort_instances(found_list, bank, sort, plane)
        best = found_list[0] if found_list else (rejected[0] if rejected else None)
        checked = found_list + rejected
        t_later = 0.0
    timing_ms["refine"] = timing.ms_since(t0) - t_later
    return _answer(bank, image, intr, best, found_list, checked, cands[:top_k], timing_ms, deadline,
                   refine=refine, overlay=overlay, t_start=t_start)


def _taught_passes(bank: TemplateBank, frame: ColourFrame, intr: Intrinsics, appearance: Appearance | None,
                   search: TaughtSearch | None, deadline: Deadline, policy: Policy) -> dict:
    """``propose``'s later passes for a part with taught colours (none untaught): region proposals, ranked
    on its colours, and the searches its calibration allows (``Policy.search_of``)."""
    if appearance is None:
        return {}
    by_colours = ByColours(bank, frame, intr, appearance, deadline)
    return dict(n_regions=policy.region_proposals_taught,
                part_colours=taught_colour_density(bank, appearance) if search.colour_prior else None,
                order=by_colours.order if search.order_first else None, score=by_colours.score,
                n_scored=search.scored_fits, sweep_colours=search.colour_sweep)


def _later_checks(bank: TemplateBank, checked: list[Checked], later: list[LaterPass], grey: np.ndarray,
                  frame: ColourFrame, intr: Intrinsics, search: TaughtSearch | None,
                  appearance: Appearance | None, kw: dict
                  ) -> tuple[list[Checked], list[PoseCandidate], float]:
    """While none of the candidates so far holds and the deadline leaves time for a check: each later pass
    (the peaks' other templates, then a taught part's region proposals and colour sweep) checked up to
    ``policy.n_verify`` -> (every checked candidate, found first then by score; the later passes'
    candidates; the time they took to propose, ms)."""
    deadline = kw["deadline"]
    more: list[PoseCandidate] = []
    t_later = 0.0
    for later_pass in later:
        if (checked and checked[0].verdict.found) or not deadline.allows(timing.CHECK_MS.high):
            break
        t2 = time.perf_counter()
        deadline.enter("second pass")
        cands = later_pass()
        if search is not None and not search.order_first:
            cands = ByColours(bank, frame, intr, appearance, deadline).order(cands)
        t_later += timing.ms_since(t2)
        checked = sorted(checked + verify_candidates(bank, cands, grey, frame, intr, **kw),
                         key=lambda c: (c.verdict.found, c.verdict.score), reverse=True)
        more += cands
        deadline.enter("checks")
    return checked, more, t_later


def _answer(bank: TemplateBank, image: np.ndarray, intr: Intrinsics, best: Checked | None,
            found_list: list[Checked], checked: list[Checked], candidates: list[PoseCandidate],
            timing_ms: dict[str, float], deadline: Deadline, *, refine: bool, overlay: bool,
            t_start: float) -> EstimateOutput:
    """The estimate's answer: found and its poses as the verdict on ``best`` says (``answer_verdict``)."""
    instances = [Instance(c.candidate, c.refined if refine else None, c.verdict) for c in found_list]
    verdict = answer_verdict(best, deadline)
    found = verdict.found
    coarse = best.candidate if found else None
    refined = best.refined if found and refine else None
    png = None
    if overlay:
        from service.vision.overlay import draw_overlay, encode_png

        png = encode_png(draw_overlay(image, bank, intr, coarse.pose if coarse else None,
                                      refined.pose if refined else None, found=found, score=verdict.score,
                                      rejected=None if found or best is None else best.refined.pose,
                                      instances=[(i.refined or i.coarse).pose for i in instances[1:]]))
    timing_ms["total"] = timing.ms_since(t_start)
    h, w = image.shape[:2]
    return EstimateOutput((w, h), found, coarse, refined, candidates, timing_ms, png, verdict, instances,
                          deadline.hit, checked, deadline.stopped_in, deadline.checks)


def answer_verdict(best: Checked | None, deadline: Deadline) -> Verdict:
    """The verdict ``verdict.decide`` gave the best checked candidate (none: ``decide(None)``), the one
    place found / absent is decided; an absent answer the deadline cut short says so in its reason."""
    verdict = best.verdict if best is not None else decide(None)
    return replace(verdict, reason="deadline") if deadline.hit and not verdict.found else verdict


def appearance_in_use(appearance: Appearance | None) -> Appearance | None:
    """``appearance`` if estimates are judged on it, else None: a plain part's colours, or photos that
    disagree, are kept and not used (``Appearance.used``)."""
    return appearance if appearance is not None and appearance.used else None


def plane_range(bank: TemplateBank, plane: Plane, intr: Intrinsics, image_size: tuple[int, int],
                policy: Policy = DEFAULT_POLICY) -> tuple[float, float]:
    """The distances searched on a plane when the request gives no range: the default range, its far end
    moved out to the plane's farthest point in view (where a cell looks across a table: the plane bounds
    where a part can lie), no farther than where the part would span ``policy.plane_smallest_part_px``."""
    lo, hi = DEFAULT_DISTANCE_RANGE_MM
    _, far = depths_in_view_mm(plane, intr, image_size)
    if math.isnan(far):
        return lo, hi
    smallest = intr.fx * float(bank.diameter_mm) / policy.plane_smallest_part_px
    return lo, max(hi, min(far, smallest))


def judged_range(distance_mm: float | None, distance_range_mm: tuple[float, float] | None
                 ) -> tuple[float, float] | None:
    """The distance range a checked pose must lie in: none with a given distance (the refinement holds
    it), else the request's range or the default one."""
    return None if distance_mm is not None else (distance_range_mm or DEFAULT_DISTANCE_RANGE_MM)


def estimate_image(bank: TemplateBank, image: np.ndarray, intr: Intrinsics, *,
                   policy: Policy = DEFAULT_POLICY, **options) -> EstimateOutput:
    """A decoded request image -> ``estimate`` (``options``: its keyword arguments), and when the part is
    not found at a given distance, the scale probe's sentence in its warnings (``misscaled_request``)."""
    out = estimate(bank, image, intr, policy=policy, **options)
    distance_mm = options.get("distance_mm")
    if out.found or distance_mm is None or options.get("plane") is not None or out.deadline_reached:
        return out
    warning = misscaled_request(bank, image, intr, float(distance_mm), policy)
    return out if warning is None else replace(out, warnings=(*out.warnings, warning))


def misscaled_request(bank: TemplateBank, image: np.ndarray, intr: Intrinsics, distance_mm: float,
                      policy: Policy = DEFAULT_POLICY) -> str | None:
    """A sentence naming ``distance_mm`` and the focal length when the part, not found at ``distance_mm``,
    is found (verified) at a depth far from it, searched nearer and farther up to
    ``policy.scale_probe_factor`` times (a focal length 10 times too large reads as the part 10 times
    farther); else None. The search is ``policy``'s lighter probe (``scale_probe_search``) on the frame
    shrunk to at most ``scale_probe_max_width``."""
    image, intr = _shrunk(image, intr, policy.scale_probe_max_width)
    probe_policy = replace(policy, search_params=policy.scale_probe_search,
                           n_verify=policy.scale_probe_verify)
    h, w = image.shape[:2]
    f_diameter = max(intr.fx, intr.fy) * bank.diameter_mm
    # nearer than its radius plus this, a point of the part projects farther out than the bound allows
    near_px = f_diameter / (policy.scale_probe_max_diagonals * math.hypot(w, h))
    nearest = max(distance_mm / policy.scale_probe_factor, 0.5 * bank.diameter_mm + near_px)
    farthest = min(distance_mm * policy.scale_probe_factor, f_diameter / policy.scale_probe_min_px)
    radius_mm = 0.5 * bank.diameter_mm
    agree, band = policy.scale_probe_agree, policy.scale_probe_band
    nearer = _probe_bands(nearest, distance_mm / agree - radius_mm, band)
    farther = _probe_bands(distance_mm * agree + radius_mm, farthest, band)
    for lo, hi in nearer + farther:
        probe = estimate(bank, image, intr, distance_range_mm=(lo, hi), top_k=1, policy=probe_policy)
        if probe.found:
            z_mm = float((probe.refined or probe.coarse).pose.t_mm[2])
            return (f"The part is not found at options.distance_mm {distance_mm:g} mm but is found "
                    f"{z_mm:.0f} mm away ({z_mm / distance_mm:.2g} times as far): check that distance_mm is "
                    "in millimetres and that the camera's fx and fy are in pixels, calibrated at this "
                    "image's resolution")
    return None


def _shrunk(image: np.ndarray, intr: Intrinsics, max_width: int) -> tuple[np.ndarray, Intrinsics]:
    """``image`` scaled down by a whole factor to at most ``max_width`` px wide, with its intrinsics."""
    factor = -(-image.shape[1] // max_width)
    if factor <= 1:
        return image, intr
    h, w = image.shape[0] // factor, image.shape[1] // factor
    small = cv2.resize(image[:h * factor, :w * factor], (w, h), interpolation=cv2.INTER_AREA)
    return small, intr.scaled(1.0 / factor)


def _probe_bands(lo: float, hi: float, band: float) -> list[tuple[float, float]]:
    """[lo, hi] cut into ranges of at most ``band`` ratio, nearest the requested distance first (the
    likelier mistakes are the smaller ones)."""
    if lo >= hi:
        return []
    n = max(int(math.ceil(math.log(hi / lo) / math.log(band))), 1)
    edges = lo * (hi / lo) ** (np.arange(n + 1) / n)
    return [(float(a), float(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]
