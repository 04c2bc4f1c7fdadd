"""Why the clutter targets fail: what each stage could reach at the ground-truth pose, per image.

    python bench/clutter_ceiling.py [--limit N]

Per clutter image (distance not given, as the benchmark runs it), with the pipeline's own pieces:
- ``cov 1/2`` / ``cov 1/1``: the true outline's edge coverage (``refine.verify``'s score at the
  ground-truth pose) on the coarse stage's half-resolution LSD and on full-resolution LSD (what the
  found verdict reads as its ``edge_support`` evidence);
- ``A rank``: rank of the best level-A anchor within 2 level pixels of the truth's reference point
  among all anchors (level B only looks around ``SearchParams.n_peaks`` of them);
- ``truth cost`` / ``found cost``: level B's ranking cost (mean DT3, truncated at
  ``rank_tau_px``) of the true border and of the best hypothesis the search returned, and that
  hypothesis's MSPD (px at 640 wide): when the truth costs more, no search can rank it first;
- ``region truth`` / ``region found``: colour separability of the silhouette against a 20 px band
  around it (``separability``; 1 = disjoint colours, 0 = the same), a cue the pipeline does not use.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # `python bench/clutter_ceiling.py`
from bench.accuracy import DATA_DIR, gt_bank, load_model_info, read_gt, read_meta, stage_errors  # noqa: E402
from service.vision.estimate import chamfer, coarse, level_a  # noqa: E402
from service.vision.estimate.chamfer import distance_tensor  # noqa: E402
from service.vision.estimate.edges import detect_segments, to_grey_u8  # noqa: E402
from service.vision.estimate.refine import border_points, dt_residuals, verify  # noqa: E402
from service.vision.geometry.camera import Intrinsics  # noqa: E402
from service.vision.geometry.frames import Pose  # noqa: E402
from service.vision.geometry.render import render  # noqa: E402
from service.vision.geometry.rotations import PoseParams  # noqa: E402
from service.vision.pipeline import DEFAULT_DISTANCE_RANGE_MM, estimate  # noqa: E402

REGION_BAND_PX = 20
REGION_BINS = 8  # per Lab channel


def separability(bgr: np.ndarray, mask: np.ndarray) -> float:
    """Mean posterior of the right side, inside (eroded 2 px) and in the band outside, minus 1, with
    the posterior from the two regions' own Lab histograms."""
    k = lambda r: np.ones((2 * r + 1, 2 * r + 1), np.uint8)  # noqa: E731
    m8 = mask.astype(np.uint8)
    inner = cv2.erode(m8, k(2)) > 0
    outer = (cv2.dilate(m8, k(REGION_BAND_PX)) > 0) & ~(cv2.dilate(m8, k(2)) > 0)
    if inner.sum() < 20 or outer.sum() < 20:
        return float("nan")
    q = (cv2.cvtColor(bgr, cv2.COLOR_BGR2Lab) // (256 // REGION_BINS)).astype(np.int64)
    code = (q[..., 0] * REGION_BINS + q[..., 1]) * REGION_BINS + q[..., 2]
    h_in = np.bincount(code[inner], minlength=REGION_BINS ** 3) / inner.sum()
    h_out = np.bincount(code[outer], minlength=REGION_BINS ** 3) / outer.sum()
    p_in = h_in / np.maximum(h_in + h_out, 1e-12)
    return float(p_in[code[inner]].mean() + (1.0 - p_in[code[outer]]).mean() - 1.0)


def silhouette(bank, pose: Pose, intr: Intrinsics, w: int, h: int) -> np.ndarray:
    return render(bank.vertices_mm, bank.faces, pose, intr.K, (w, h)).mask


def truth_cost(border, pose: Pose, intr: Intrinsics, dtt, tau_px: float) -> float:
    """Level B's ranking cost of ``border`` at ``pose``: mean DT3 read-out truncated at ``tau_px``."""
    params = PoseParams(pose, np.zeros(3))
    r, _ = dt_residuals(params, np.zeros(params.n), border, intr, dtt, with_jac=False)
    return float(np.minimum(r, tau_px).mean())


def level_a_rank(bank, intr: Intrinsics, dtt_b, shape, truth: Pose, p: coarse.SearchParams) -> int:
    z_ref, scales = coarse.depth_scales(DEFAULT_DISTANCE_RANGE_MM, p.depth_step)
    tpl = level_a.level_a_templates(bank, intr, shape, p, distance_mm=None, z_ref_mm=z_ref)
    dtt_a = chamfer.pooled_distance_tensor(dtt_b, p.level_scale)
    au, av, _, cost, _, _ = level_a.scan_level_a(dtt_a, tpl, scales, shape, p)
    c = truth.apply(bank.centre_obj[None])[0]
    uv = intr.K[:2, :2] @ (c[:2] / c[2]) + intr.K[:2, 2]
    ul, vl = (uv + 0.5) * p.level_scale - 0.5
    near = ((au - ul) ** 2 + (av - vl) ** 2 <= 4.0) & np.isfinite(cost)
    if not near.any():
        return -1  # pruned before the scan (too few edges around it)
    return int((cost < cost[near].min()).sum())


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--limit", type=int, default=None)
    a = ap.parse_args()
    set_dir = DATA_DIR / "clutter"
    meta, rows, banks, infos = read_meta(set_dir), read_gt(set_dir), {}, {}
    p = coarse.SearchParams()
    print("| image | model | visible | cov 1/2 | cov 1/1 | A rank | truth cost | found cost | found MSPD640 "
          "| region truth | region found |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for g in rows[:a.limit]:
        m = g["model"]
        if m not in banks:
            banks[m] = gt_bank(set_dir, m)
        bank, K = banks[m], np.asarray(g["K"], float)
        bgr = cv2.imread(str(set_dir / g["image"]), cv2.IMREAD_COLOR)
        grey = to_grey_u8(bgr)
        h, w = grey.shape
        intr = Intrinsics.from_K(K)
        truth = Pose(np.asarray(g["R"], float), np.asarray(g["t_mm"], float))
        border = border_points(bank, truth, intr, (w, h))
        dtt_b = distance_tensor(detect_segments(grey), n_channels=p.n_channels, scale=p.fine_scale)
        dtt_1 = distance_tensor(detect_segments(grey, scale=1.0), n_channels=p.n_channels, scale=p.fine_scale)
        out = estimate(bank, grey, intr, refine=False)
        best = out.candidates[0] if out.candidates else None
        mspd = stage_errors(best.pose, g, load_model_info(set_dir, m, meta, infos), K, w)["mspd640_px"] \
            if best else float("nan")
        cols = [
            verify(border, truth, intr, dtt_b, score_px=p.score_px)[0],
            verify(border, truth, intr, dtt_1, score_px=p.score_px)[0],
        ]
        rank = level_a_rank(bank, intr, dtt_b, (h, w), truth, p)
        reg_t = separability(bgr, silhouette(bank, truth, intr, w, h))
        reg_f = separability(bgr, silhouette(bank, best.pose, intr, w, h)) if best else float("nan")
        c_truth = truth_cost(border, truth, intr, dtt_b, p.rank_tau_px)
        cells = [Path(g["image"]).name, m, f"{g['visible_fraction']:.2f}", f"{cols[0]:.2f}", f"{cols[1]:.2f}",
                 str(rank) if rank >= 0 else "pruned", f"{c_truth:.2f}",
                 f"{best.cost:.2f}" if best else "-", f"{mspd:.0f}", f"{reg_t:.2f}", f"{reg_f:.2f}"]
        print("| " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
