"""Region proposals (``vision/estimate/regions.py``) measured per query: is the truth among the first K?

For every query (targets at least half visible) it segments the colour image, proposes poses from the
regions whose area fits the part (``regions.propose``, ranked by silhouette IoU), and judges the first
30 by MSPD at 640 px width (< 20 px: the truth), raw and after level B + polish on the region's own
outline (``regions.refine_on_boundary``). CPU time per frame (``time.thread_time``, one thread).

    python bench/region_proposals.py --set clutter2 [--every 8] [--limit N] [--no-refine]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.accuracy import (  # noqa: E402
    gt_bank,
    load_model_info,
    read_colour,
    stage_errors,
)
from bench.stages import target_queries  # noqa: E402
from service.vision.estimate import regions  # noqa: E402
from service.vision.estimate.coarse import poses_of  # noqa: E402
from service.vision.geometry.frames import Pose  # noqa: E402
from service.vision.pipeline import DEFAULT_DISTANCE_RANGE_MM, DEFAULT_POLICY  # noqa: E402

RIGHT_PX = 20.0
KS = (5, 12, 30)


def mspds(bank, hyps, K, g, info) -> list[float]:
    if not hyps:
        return []
    Rs, ts = poses_of(bank, hyps, K, None)
    return [stage_errors(Pose(R, t), g, info, K, int(g["width"]))["mspd640_px"]
            for R, t in zip(Rs, ts, strict=True)]


def read_bgr(path: Path) -> np.ndarray:
    """(H, W, 3) BGR: a grey image repeated, an alpha channel dropped (``segmentation.segment`` reads it)."""
    image = read_colour(path)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    return image[..., :3]


def first_right(ms: list[float]) -> int:
    return next((i for i, m in enumerate(ms) if m < RIGHT_PX), -1)


def run(a) -> None:
    set_dir, meta, gts = target_queries(a)
    minfo: dict = {}
    raw_at = {k: 0 for k in KS}
    ref_at = {k: 0 for k in KS}
    cpu_p, cpu_r = [], []
    print("q image model vis | n_prop raw_first raw_best_mspd | ref_first ref_best_mspd | cpu ms")
    for qi, g in enumerate(gts):
        bank = gt_bank(set_dir, g["model"])
        regions.silhouettes(bank)  # once per bank, not per frame
        info = load_model_info(set_dir, g["model"], meta, minfo)
        image = read_bgr(set_dir / g["image"])
        K = np.asarray(g["K"], float)
        t0 = time.thread_time()
        props, reg = regions.propose(bank, image, K, DEFAULT_DISTANCE_RANGE_MM, n_out=max(KS))
        cpu_p.append(1000 * (time.thread_time() - t0))
        m_raw = mspds(bank, [p.hyp for p in props], K, g, info)
        r_raw = first_right(m_raw)
        line = (f"{qi:3d} {g['image']:16s} {g['model']:9s} {g.get('visible_fraction', 1):.2f} | "
                f"{len(props):3d} {r_raw:3d} {min(m_raw, default=np.inf):7.1f} |")
        for k in KS:
            raw_at[k] += 0 <= r_raw < k
        if not a.no_refine:
            t1 = time.thread_time()
            hs = [regions.refine_on_boundary(bank, p, reg, K, image.shape[:2], DEFAULT_POLICY.search_params)
                  for p in props]
            cpu_r.append(1000 * (time.thread_time() - t1))
            m_ref = mspds(bank, hs, K, g, info)
            r_ref = first_right(m_ref)
            for k in KS:
                ref_at[k] += 0 <= r_ref < k
            line += f" {r_ref:3d} {min(m_ref, default=np.inf):7.1f} |"
        line += f" {cpu_p[-1]:6.0f}" + (f" + {cpu_r[-1]:6.0f}" if cpu_r else "")
        print(line, flush=True)
    n = len(gts)
    print(f"\n{a.set}: {n} queries; truth (MSPD < {RIGHT_PX:.0f} px) in the first K region proposals")
    print("| K | raw | after level B + polish on the region outline |")
    print("|---|---|---|")
    for k in KS:
        print(f"| {k} | {raw_at[k]} | {ref_at[k] if not a.no_refine else '-'} |")
    print(f"CPU ms per frame (one thread): proposals p50 {np.median(cpu_p):.0f} "
          f"p95 {np.percentile(cpu_p, 95):.0f}"
          + (f"; refinement of {max(KS)} p50 {np.median(cpu_r):.0f}" if cpu_r else ""))


def set_args(ap: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options choosing a set's queries: --set, --every, --start, --limit."""
    ap.add_argument("--set", required=True)
    ap.add_argument("--every", type=int, default=1)
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--limit", type=int, default=None)
    return ap


def main() -> None:
    ap = set_args(argparse.ArgumentParser())
    ap.add_argument("--no-refine", action="store_true")
    run(ap.parse_args())


if __name__ == "__main__":
    main()
