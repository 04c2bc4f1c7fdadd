"""The coarse search's pose evaluation in plain numpy, kept to check the compiled one against
(``estimate/level_b.evaluate``: one matmul and a compiled read-out, the same bits)."""

from __future__ import annotations

import numpy as np

from service.vision.bank import TemplateBank, border_triplets
from service.vision.estimate.chamfer import DistanceTensor, sample
from service.vision.geometry.camera import project


def evaluate_numpy(bank: TemplateBank, views: np.ndarray, Rs: np.ndarray, ts: np.ndarray, K: np.ndarray,
                   dtt: DistanceTensor, n_points: int, score_px: float, tau_px: float = np.inf
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Mean directional chamfer cost (full-res px, each point's truncated at ``tau_px``) and support
    score of M posed templates: each point, its successor and its predecessor projected apart."""
    views = np.asarray(views, np.int64)
    idx_all, prev_all, nxt_all = border_triplets(bank, n_points)

    def proj(ii):
        return project(bank.p_obj[ii].astype(np.float64) @ Rs.transpose(0, 2, 1) + ts[:, None, :], K)

    uv = proj(idx_all[views])
    d = proj(nxt_all[views]) - proj(prev_all[views])
    theta = np.mod(np.arctan2(d[..., 1], d[..., 0]), np.pi)
    val = sample(dtt, dtt.to_grid(uv), theta) / dtt.scale
    return np.minimum(val, tau_px).mean(axis=1), (val <= score_px).mean(axis=1)
