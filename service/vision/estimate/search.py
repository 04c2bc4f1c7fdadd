"""What the search modules exchange: the search's parameters, a hypothesis (template view, in-plane
angle, depth and pixel of the reference point) and its 6D pose, and the depths a distance range spans.

A hypothesis becomes a 6D pose without assuming the object sits on the optical axis: with the
reference point seen at pixel ``uv`` (viewing ray ``r``), ``R = R_between(e_z, r) @ Rz(phi) @ R_view``
and the reference point lies on ``r`` at depth ``z``, so the coarse rotation is right at the image
corners too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from service.vision.bank import TemplateBank
from service.vision.geometry.camera import ray_rotations
from service.vision.geometry.frames import Rz


@dataclass(frozen=True)
class SearchParams:
    n_channels: int = 16
    level_scale: float = 0.125
    fine_scale: float = 0.5
    inplane_step_deg: float = 10.0
    view_step_deg: float = 6.0  # out-of-plane spacing used at level A for a revolved part (1 DoF)
    view_step_any_deg: float = 20.0  # ... and for any other part (2 DoF): level B covers +-local_view_deg
    depth_step: float = 0.15  # ratio between successive distances tried when the distance is not given
    anchor_stride: int = 2  # level-A pixels (16 full-res px: level B searches +-local_radius_px)
    points_per_template: int = 32
    fine_points: int = 160
    scan_points: int = 80  # level B's wide block: a placement's rank needs fewer points than its polish
    tiles: tuple[int, int] = (4, 3)
    n_peaks: int = 12
    n_polish: int = 4
    accept_frac: float = 0.5  # level A: a template must average under this fraction of tau
    min_edge_frac: float = 0.3  # level A: edge pixels near an anchor, as a fraction of a border's length
    score_px: float = 3.0  # full-resolution px: a border point is "supported" within this distance
    local_phi_step_deg: float = 2.0  # level B: in-plane steps of the local scan around each peak
    local_radius_px: float = 24.0  # level B: full-resolution px searched around each peak
    local_view_deg: float = 20.0  # level B: bank views within this angle of a peak's view are tried
    # Level B ranks by the DT3 mean truncated here (full-res px): a hidden border point then costs no
    # more than a badly placed one, so a 30 % occluded truth still beats a wrong pose on clutter.
    rank_tau_px: float = 8.0
    # Level B: a later peak's scan only accepts placements within this ratio of the best cost so far.
    peak_accept_ratio: float = 1.5
    # Rank level-A peaks, level-B scans and the polished hypotheses by cost over the local background
    # cost (``background_cost``) instead of by cost alone (issue #14: clutter).
    bg_norm: bool = True
    # Level B starts per level-A peak: its own level-A template (the first pass), then (a second pass,
    # ``coarse_search``) its best others, mutually distinct (rotations more than
    # ``distinct_template_deg`` apart), each the best over the peak's anchor and its neighbours within
    # ``template_anchor_reach`` anchor strides (1: the first pass only) ...
    templates_per_peak: int = 3
    distinct_template_deg: float = 30.0
    template_anchor_reach: int = 1
    # ... at the first this many peaks only: the second pass runs on every frame where nothing is found,
    # and more peaks cost time for no part found (docs/detection-history.md)
    template_peaks: int = 4


@dataclass
class Hypothesis:
    view: int
    phi_deg: float
    z_mm: float  # depth (camera z) of the bank's reference point centre_obj
    uv: np.ndarray  # (2,) full-resolution pixel of the reference point
    cost: float = np.inf  # mean directional chamfer distance, full-resolution px
    score: float = 0.0
    rank_cost: float = np.inf  # what the search ranks by: ``cost``, or cost / background (bg_norm)


def poses_of(bank: TemplateBank, hs: list[Hypothesis], K: np.ndarray, distance_mm: float | None
             ) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3, 3) R and (M, 3) t of hypotheses; with a known distance the depth follows from it."""
    if not hs:
        return np.zeros((0, 3, 3)), np.zeros((0, 3))
    d, R_ray = ray_rotations(np.array([h.uv for h in hs], float), K)
    Rs = R_ray @ np.stack([Rz(h.phi_deg) for h in hs]) @ bank.R_tpl_obj[[h.view for h in hs]]
    c_rot = Rs @ bank.centre_obj  # (M, 3)
    z = (distance_mm + c_rot[:, 2]) if distance_mm is not None else np.array([h.z_mm for h in hs])
    return Rs, d / d[:, 2:3] * z[:, None] - c_rot


def depth_scales(distance_range_mm: tuple[float, float], depth_step: float) -> tuple[float, np.ndarray]:
    """Level A's reference depth for a searched distance range (its geometric middle) and the scale
    factors of the depths tried, ``depth_step`` apart from the near end to past the far end."""
    lo, hi = distance_range_mm
    n = max(int(math.ceil(math.log(hi / lo) / math.log(1 + depth_step))), 1)
    z_ref = float(math.sqrt(lo * hi))
    return z_ref, z_ref / (lo * (1 + depth_step) ** np.arange(n + 1))
