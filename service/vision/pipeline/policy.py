"""Every tuned number of the estimate, once, with why; the figures behind each are in
docs/detection-history.md.

An estimate reads one ``Policy`` value passed down explicitly (``estimate(..., policy=...)``); a
benchmark or a test passes another (``dataclasses.replace(DEFAULT_POLICY, ...)``) instead of rewriting
module globals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from service.vision.estimate.plane_match import GradientSearch
from service.vision.estimate.search import SearchParams
from service.vision.estimate.verdict import MIN_SCORE
from service.vision.model.appearance import Appearance

DEFAULT_DISTANCE_RANGE_MM = (300.0, 1200.0)  # searched when the request gives no distance


@dataclass(frozen=True)
class TaughtSearch:
    """How a taught part's frames are searched beyond the region proposals.

    ``scored_fits``: the region proposals are chosen by their unrefined score (the taught colours) from
    this many fits (8 a region) before their refinement (``regions.region_proposals``' score; 0: not).
    ``colour_prior``: they are ranked by how part-coloured each region is too (``colour_prior.py``).
    ``order_first``: the later passes are put in order of unrefined score before near duplicates are
    dropped (the kept one of a group the best-coloured) instead of after. ``polish_from``: near misses
    from this score are polished (``check.polish_appearance``). ``colour_sweep``: a last pass sweeps the
    silhouettes over the taught colours (``estimate/colour_sweep.py``)."""
    scored_fits: int = 0
    colour_prior: bool = False
    order_first: bool = False
    polish_from: float = 0.9
    colour_sweep: bool = False


# A translation step in mm along a camera axis ("t") or a turn in deg about it ("r"): the colour polish's
# neighbourhood, the depth step larger since the colours read depth more weakly than position.
POLISH_STEPS = (("t", 0, 1.0), ("t", 1, 1.0), ("t", 2, 4.0), ("r", 0, 1.0), ("r", 1, 1.0), ("r", 2, 1.0))


@dataclass(frozen=True)
class Policy:
    """What an estimate may be tuned by. Defaults are the service's."""

    # -- the search
    # as many polished hypotheses as the verdict checks
    search_params: SearchParams = SearchParams(n_polish=5)
    # candidates refined and verified per frame at most: on synthetic clutter the truth was among the
    # first 5 proposals on 16 of 83 targets, the first 10 on 17
    n_verify: int = 5
    # level-A peaks scale with a ROI's share of the image, down to this many
    roi_min_peaks: int = 4
    # the anytime search keeps this many mean checks on top of one check's high estimate: its own last
    # unit of work overruns by a part of the mean it was judged against
    search_reserve_checks: float = 0.25

    # the gradient search of a part on a plane (``estimate/plane_match.py``)
    gradient: GradientSearch = GradientSearch()
    # a plane is searched out to where the part spans this many pixels (``estimate.plane_range``): the
    # gradient templates' smallest spread cell is 4 px, a part under 3 cells across has no shape left
    plane_smallest_part_px: float = 12.0

    # -- several instances: more proposals (each peak costs a level-B scan, each polished hypothesis a
    # refinement and its evidence), and a later peak's placement accepted further from the best: another
    # copy lies among its neighbours' edges and costs more than the cleanest copy
    peaks_per_instance: int = 6
    max_peaks: int = 80
    polish_per_instance: int = 4
    max_polish: int = 40
    instances_peak_accept_ratio: float = 3.0
    # two found instances whose silhouettes overlap more than this are one
    instance_iou: float = 0.4
    # near misses (rejected for a reason another part's pixels can cause) judged with each other
    # explaining their pixels: two touching copies can each fail alone for the other's pixels
    mutual_min_score: float = 0.85
    mutual_explainer_min_score: float = 0.3
    # a pose found only at its part's place point is held against this many more candidates proposed at its
    # place (``pipeline/place``), looked for among the next ``place_rival_scan`` proposals
    place_rivals: int = 3
    place_rival_scan: int = 40

    # -- taught parts
    # region proposals for a part with taught colours: they hold its true poses on real photos, and the
    # taught colours refuse the distractors' regions an untaught verdict took
    region_proposals_taught: int = 12
    # the wider searches judge more candidates, so more wrong ones: they run only where the part's
    # operating point was calibrated on its own photos, the colour sweep only from enough photos
    taught_search: TaughtSearch = TaughtSearch()
    calibrated_search: TaughtSearch = TaughtSearch(scored_fits=48, colour_prior=True, order_first=True,
                                                   polish_from=0.85)
    sweep_min_photos: int = 5

    # -- the teach-time calibration of a taught part's operating point
    # a judged pose this far from the photo's known one (MSPD, 640 px wide) is a wrong answer
    calibration_wrong_px: float = 20.0
    # the operating point lies this far (logit) above the highest wrong score: wrong poses the few
    # photos did not show reach higher
    calibration_margin: float = 0.7
    calibration_points: int = 500  # model vertices the calibration's MSPD reads
    # a wrong pose at least this much inside a photo counts, though refused there as outside_image
    calibration_min_in_image: float = 0.5

    # -- the verdict
    # the verification score's weights for a part without taught colours, as (evidence, weight) pairs
    # with "bias" (None: ``verdict.WEIGHTS``, the service's fit); a benchmark judges with a refit
    # (``bench/fit_verdict.py --save``, ``bench/detection.py --weights``)
    verdict_weights: tuple[tuple[str, float], ...] | None = None

    # -- the check of one candidate
    # a twin is refined only if its unrefined pose scores this: better twins scored 0.97-0.99 unrefined
    twin_unrefined_min_score: float = 0.5
    # a refused candidate on a plane is refined again from its pose polished on its own edge points
    # (``estimate/plane_polish.py``) where that raises their agreeing share by this
    plane_polish_min_gain: float = 0.05
    # a refinement ending beyond the searched range by at most this share is refined again held at the
    # bound: refined depths on real photos scatter by +-5 %, proposals lie up to ~10 % past the range
    range_hold_max: float = 0.10
    same_place_px: float = 2.0  # two poses whose model vertices project this close on average are one
    same_place_vertices: int = 256
    # a found answer held at its colours' outline's depth is kept if, its depth aside, it lies this close
    # to the found pose: further, the edges turned it instead
    hold_same_place_px: float = 3.0

    # -- the colour polish of a taught near miss: coordinate ascent on the unrefined score
    polish_steps: tuple[tuple[str, int, float], ...] = POLISH_STEPS
    polish_rounds: int = 4
    polish_min_gain: float = 1e-4  # a step must raise the score by this much

    # -- the scale probe: a frame not found at a given distance searched nearer and farther, up to this
    # factor, in bands of at most this ratio (over a wider one the farthest templates fit clutter better)
    scale_probe_factor: float = 12.0
    scale_probe_band: float = 4.0
    # the part's projected diameter kept between these: smaller, nothing is told apart; larger, the
    # search's tables grow with the square of the part's size
    scale_probe_min_px: float = 40.0
    scale_probe_max_diagonals: float = 1.0
    # a found depth within this factor of the requested one (give or take the part's radius) is the
    # request's: the first search missed it
    scale_probe_agree: float = 2.0
    # the probe is a hint, not an answer: a lighter search (one template per peak, fewer peaks and
    # polishes, one candidate checked) on the frame shrunk to this width: an absent frame at a given
    # distance costs ~0.3 s more instead of ~4 s, and fx x 10 on the paper renders reads the same
    scale_probe_search: SearchParams = SearchParams(n_peaks=6, n_polish=2, templates_per_peak=1)
    scale_probe_verify: int = 1
    scale_probe_max_width: int = 640

    def search_params_for(self, max_instances: int) -> SearchParams:
        """The search's parameters for ``max_instances`` instances (1: ``search_params`` itself)."""
        p = self.search_params
        if max_instances <= 1:
            return p
        extra = max_instances - 1
        # several instances rank by plain cost: over the background a wrong instance ranked first
        return replace(p, bg_norm=False,
                       n_peaks=min(p.n_peaks + self.peaks_per_instance * extra, self.max_peaks),
                       n_polish=min(p.n_polish + self.polish_per_instance * extra, self.max_polish),
                       peak_accept_ratio=self.instances_peak_accept_ratio)

    def search_of(self, appearance: Appearance | None) -> TaughtSearch | None:
        """The search of a taught part (None untaught): calibrated on ``sweep_min_photos`` photos or more,
        the calibrated search with the colour sweep; calibrated on fewer, without; else the taught one."""
        if appearance is None:
            return None
        if appearance.calibrated_photos >= self.sweep_min_photos:
            return replace(self.calibrated_search, colour_sweep=True)
        return self.calibrated_search if appearance.calibrated_photos > 0 else self.taught_search

    def operating_point(self, appearance: Appearance | None) -> float | None:
        """A calibrated part's operating point: ``calibration_margin`` (logit) above its highest wrong
        score, never under the global one (``verdict.MIN_SCORE``); None (the global one) for a part not
        calibrated."""
        if appearance is None or not np.isfinite(appearance.wrong_score):
            return None
        s = min(max(appearance.wrong_score, 1e-9), 1 - 1e-9)
        z = math.log(s / (1 - s)) + self.calibration_margin
        return max(MIN_SCORE, 1.0 / (1.0 + math.exp(-z)))


DEFAULT_POLICY = Policy()


def operating_point(appearance: Appearance | None, policy: Policy = DEFAULT_POLICY) -> float | None:
    """``policy.operating_point(appearance)``: the calibrated part's operating point, or None."""
    return policy.operating_point(appearance)


def taught_search(appearance: Appearance | None, policy: Policy = DEFAULT_POLICY) -> TaughtSearch | None:
    """``policy.search_of(appearance)``: the search of a taught part, None untaught."""
    return policy.search_of(appearance)


def search_params(max_instances: int, policy: Policy = DEFAULT_POLICY) -> SearchParams:
    """``policy.search_params_for(max_instances)``."""
    return policy.search_params_for(max_instances)
