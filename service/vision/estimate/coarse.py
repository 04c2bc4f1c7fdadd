"""Coarse pose by directional chamfer matching over the whole image (paper section II.B).

Search, coarse to fine:
1. level A (DT3 min-pooled to ``level_scale``, 1/8): every out-of-plane view x in-plane rotation x
   distance is tried at every anchor (stride ``anchor_stride``) by a compiled scan with early
   termination (a template is abandoned once its partial sum exceeds the anchor's best so far, or
   its first points, taken in ``spread_order`` round the border, already average well above it);
   the image is split into tiles so each tile uses the template shape seen along its own viewing ray;
   anchors are scanned in bands of rows, a template's first points summed for a whole band at once
   from a DT3 laid out so that one point's costs along a row of anchors are contiguous (``_scan_bands``;
   exact);
2. level B (``fine_scale``, 1/2): around each distinct peak a compiled exhaustive scan of the
   nearby views, in-plane angles, depths and pixels (``local_scan``: level A says which basin to
   look in, not where in it; the same block bounds, ``_window_bounds``), then the best few are
   polished sub-pixel by a pattern search over (view, in-plane angle, distance, position) with exact
   perspective projection of the templates' 3D border points.

Peaks, level-B placements and polished hypotheses are ranked by cost over the local background's
(``bg_norm``, ``background_cost``): on texture every template is cheap, and an outline standing out
of plainer ground should outrank it. Level A keeps one template per anchor, and at a clutter peak near
the truth that one is often another rotation level B cannot turn back from: a second pass starts
level B from the first peaks' other distinct templates too (``templates_per_peak``, ``peak_starts``),
deferred by the pipeline until the first pass's candidates have all failed verification.

Level A lives in ``level_a``, level B in ``level_b``, the compiled scans both run in ``scan``, and the
parameters and hypotheses the search exchanges with its callers in ``search``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from service.vision.bank import TemplateBank, view_neighbours
from service.vision.deadline import NO_DEADLINE, Deadline
from service.vision.estimate.chamfer import DistanceTensor, pooled_and_quantised
from service.vision.estimate.level_a import (
    LEVEL_A_RESERVE_FACTOR,
    _bg_at,
    _cached_level_a,
    _level_a_in_time,
    background_cost,
    peak_starts,
    pick_peaks,
    scan_level_a,
)
from service.vision.estimate.level_b import evaluate, local_scan, polish
from service.vision.estimate.search import Hypothesis, SearchParams, depth_scales, poses_of
from service.vision.geometry.camera import Intrinsics

PEAK_RADIUS_EXTENT = 0.25  # level-A peaks closer than this fraction of the template extent are one peak
MIN_PEAK_RADIUS_PX = 2.0  # ... and never closer than this (level px)
# Background normalisation (``SearchParams.bg_norm``): a placement's cost is divided by the mean over
# channels and pixels of the DT3 (truncated at tau) in a box of this fraction of the templates' extent
# round it -- what a template costs there by chance: textured floors and distractors, where every
# template is cheap, then rank below an outline standing out of a plainer neighbourhood.
BG_WINDOW_EXTENT = 0.5


def coarse_search(bank: TemplateBank, dtt_b: DistanceTensor, intr: Intrinsics,
                  image_shape: tuple[int, int], p: SearchParams, *, distance_mm: float | None,
                  distance_range_mm: tuple[float, float], anchor_mask: np.ndarray | None = None,
                  deadline: Deadline = NO_DEADLINE, reserve_ms: float = 0.0,
                  deferred: list[Callable[[], list[Hypothesis]]] | None = None) -> list[Hypothesis]:
    """Ranked, polished, mutually distinct hypotheses (best first). ``dtt_b`` is the DT3 at
    ``fine_scale``; level A's grid is min-pooled from it. ``anchor_mask`` (full-resolution (h, w)
    bool): level A places the reference point only there (``scan_level_a``).

    Two passes: level B from each level-A peak's own template, then (``templates_per_peak`` > 1) from
    its other distinct templates (``peak_starts``), each pass polishing its best ``n_polish``. With a
    ``deferred`` list the second pass is not run here: a callable running it (and returning its
    hypotheses, ranked) is appended to the list, for a caller that needs it only when the first
    pass's hypotheses all fail verification (``pipeline.estimate``); without, both passes' hypotheses
    are returned together, ranked.

    Anytime: each unit of work (a chunk of level-A anchors, a peak's local scan, a polish) starts only
    while the ``deadline`` leaves more than ``reserve_ms`` (the caller's time to verify a result); what
    was reached by then is returned, hypotheses left unpolished with their level-B costs."""
    K = intr.K
    dtt_a, dt_q, tau_q = pooled_and_quantised(dtt_b, p.level_scale, p.rank_tau_px * dtt_b.scale)
    z_ref, scales = (distance_mm, np.array([1.0])) if distance_mm is not None else \
        depth_scales(distance_range_mm, p.depth_step)
    if deadline.ms is None:
        tpl = _cached_level_a(bank, intr, image_shape, p, distance_mm, z_ref)
    else:
        tpl = _level_a_in_time(bank, intr, image_shape, p, distance_mm, z_ref, scales, deadline,
                               LEVEL_A_RESERVE_FACTOR * reserve_ms)
        if tpl is None:
            return []
    r_bg = int(BG_WINDOW_EXTENT * tpl.extent_px * float(np.median(scales)))
    au, av, tile, cost, t, d = scan_level_a(dtt_a, tpl, scales, image_shape, p, anchor_mask, deadline,
                                            reserve_ms)
    radius = max(PEAK_RADIUS_EXTENT * tpl.extent_px * float(np.median(scales)), MIN_PEAK_RADIUS_PX)
    bg = background_cost(dtt_a, r_bg) if p.bg_norm else None
    rank_a = cost / bg[av, au] if bg is not None else cost
    peaks = pick_peaks(au, av, rank_a, p.n_peaks, radius)
    n_phi = len(tpl.phis_deg)

    def start_of(a, t, d) -> Hypothesis:
        ti = int(t[a])
        uv = np.array([(au[a] + 0.5) / p.level_scale - 0.5, (av[a] + 0.5) / p.level_scale - 0.5])
        return Hypothesis(int(tpl.views[ti // n_phi]), float(tpl.phis_deg[ti % n_phi]),
                          float(tpl.z_ref_mm[tile[a], ti] / scales[d[a]]), uv)

    starts = [start_of(a, t, d) for a in peaks]
    if not starts:
        return []
    state = _LevelB(bank, dtt_b, dt_q, tau_q, K, p, distance_mm, bg, deadline, reserve_ms)
    out = state.run(starts)
    if p.templates_per_peak <= 1:
        return out

    def second() -> list[Hypothesis]:
        # Each peak's second distinct template first, then each one's third, ...: the deadline reaches
        # every peak's best alternative before any peak's next.
        extra = peak_starts(bank, tpl, scales, dtt_a, au, av, cost, t, peaks[:p.template_peaks],
                            image_shape, p)
        more: list[Hypothesis] = []
        for rank in range(p.templates_per_peak - 1):
            more += [s[rank] for s in extra if len(s) > rank]
        return sorted(state.run(more), key=lambda h: h.rank_cost)

    if deferred is not None:
        deferred.append(second)
        return out
    return sorted(out + second(), key=lambda h: h.rank_cost)


class _LevelB:
    """Level B of one frame's search, run on batches of starts (``coarse_search``'s passes): each
    start's local scan, accepted within ``peak_accept_ratio`` of the best so far over all batches
    (over its background with ``bg_norm``), then the batch's best ``n_polish`` polished."""

    def __init__(self, bank, dtt_b, dt_q, tau_q, K, p: SearchParams, distance_mm, bg, deadline: Deadline,
                 reserve_ms: float):
        self.bank, self.dtt_b, self.dt_q, self.tau_q, self.K, self.p = bank, dtt_b, dt_q, tau_q, K, p
        self.distance_mm, self.bg, self.deadline, self.reserve_ms = distance_mm, bg, deadline, reserve_ms
        self.best_q = np.inf  # the best cost so far (over its background with bg_norm)

    def bg_of(self, hs: list[Hypothesis]) -> np.ndarray:
        if self.bg is None or not hs:
            return np.ones(len(hs))
        return _bg_at(self.bg, np.array([x.uv for x in hs]), self.p.level_scale)

    def run(self, starts: list[Hypothesis]) -> list[Hypothesis]:
        p, bank, K, dtt_b, deadline = self.p, self.bank, self.K, self.dtt_b, self.deadline
        scanned: list[Hypothesis] = []
        deadline.new_loop()
        for h in starts:
            if not deadline.allows_next(self.reserve_ms):
                break
            # A peak whose neighbourhood cannot come near the best so far would never be reported first.
            accept = int(min(self.tau_q, p.peak_accept_ratio * self.best_q * float(self.bg_of([h])[0])))
            hyp, q = local_scan(bank, h, self.dt_q, self.tau_q, dtt_b, K, p, distance_mm=self.distance_mm,
                                accept_q=accept)
            if hyp is not None:
                scanned.append(hyp)
                self.best_q = min(self.best_q, q / float(self.bg_of([hyp])[0]))
        if not scanned:
            return []
        Rs, ts = poses_of(bank, scanned, K, self.distance_mm)
        cost_b, score_b = evaluate(bank, np.array([h.view for h in scanned]), Rs, ts, K, dtt_b, p.fine_points,
                                   p.score_px, p.rank_tau_px)
        order = np.argsort(cost_b / self.bg_of(scanned))[:p.n_polish]
        neighbours = view_neighbours(bank)
        out = []
        deadline.new_loop()
        for i in order:
            if deadline.allows_next(self.reserve_ms):
                out.append(polish(bank, scanned[i], dtt_b, K, p, distance_mm=self.distance_mm,
                                  neighbours=neighbours, step_phi_deg=p.local_phi_step_deg / 2,
                                  step_uv_px=1.0 / dtt_b.scale, step_z=p.depth_step / 4))
            else:
                h = scanned[i]
                h.cost, h.score = float(cost_b[i]), float(score_b[i])
                out.append(h)
        for h, b in zip(out, self.bg_of(out), strict=True):
            h.rank_cost = h.cost / float(b)
        out.sort(key=lambda h: h.rank_cost)
        return out


