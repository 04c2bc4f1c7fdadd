"""Detection with the region proposals off and on, frame by frame in one process (``bench/detection.py``'s
judgement: one estimate per gt line, colour image, distance not given, default operating point).

Per query the estimate runs with ``pipeline.REGION_PROPOSALS`` = 0, then = N, alternating, so both see
the same machine load; CPU time is ``time.process_time`` (this process's threads only). Besides found /
right / **wrong found** it reports "truth proposed": a candidate the estimate proposed (either pass,
coarse pose) within MSPD < 20 px, so a gain in the proposals shows even where the verdict refuses it.

    python bench/region_detection.py --sets clutter2,absent2 [--n 5] [--every-image 8]
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
    MIN_VISIBLE,
    gt_bank,
    load_model_info,
    read_colour,
    read_gt,
    read_meta,
    stage_errors,
)
from bench.detection import RIGHT_PX, set_dir_of, summarise  # noqa: E402
from service import pipeline  # noqa: E402
from service.vision.geometry.camera import Intrinsics  # noqa: E402


def run_set(name: str, n_regions: int, every_image: int, limit: int | None) -> dict[int, list[dict]]:
    set_dir = set_dir_of(name)
    meta = read_meta(set_dir)
    gts = read_gt(set_dir)
    if every_image > 1:
        images = sorted({g["image"] for g in gts})[::every_image]
        gts = [g for g in gts if g["image"] in set(images)]
    gts = gts[:limit] if limit else gts
    minfo: dict = {}
    recs: dict[int, list[dict]] = {0: [], n_regions: []}
    for g in gts:
        bank = gt_bank(set_dir, g["model"])
        image = read_colour(set_dir / g["image"])
        K = np.asarray(g["K"], float)
        intr = Intrinsics.from_K(K)
        absent = bool(g.get("absent", False))
        info = load_model_info(set_dir, g["model"], meta, minfo) if not absent else None
        line = f"{g['image']:18s} {g['model']:10s}"
        for n in (0, n_regions):
            pipeline.REGION_PROPOSALS = n
            t0, c0 = time.perf_counter(), time.process_time()
            out = pipeline.estimate(bank, image, intr, top_k=1000)
            ms, cpu = 1000 * (time.perf_counter() - t0), 1000 * (time.process_time() - c0)
            pose = (out.refined or out.coarse).pose if out.found else None
            mspd = float("inf")
            proposed = False
            if not absent:
                if pose is not None:
                    mspd = stage_errors(pose, g, info, K, int(g["width"]))["mspd640_px"]
                proposed = any(stage_errors(c.pose, g, info, K, int(g["width"]))["mspd640_px"] < RIGHT_PX
                               for c in out.candidates)
            vis = float(g.get("visible_fraction", 0.0 if absent else 1.0))
            recs[n].append({"image": g["image"], "model": g["model"], "absent": absent, "found": out.found,
                            "mspd640": mspd, "visible": vis, "reason": out.verdict.reason,
                            "score": out.verdict.score, "ms": ms, "cpu": cpu, "proposed": proposed})
            line += f" | {n:2d}: found {int(out.found)} mspd {mspd:6.1f} prop {int(proposed)} " \
                    f"score {out.verdict.score:.2f} cpu {cpu:6.0f}"
        print(line, flush=True)
    pipeline.REGION_PROPOSALS = 0
    return recs


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sets", required=True)
    ap.add_argument("--n", type=int, default=5, help="REGION_PROPOSALS when on")
    ap.add_argument("--every-image", type=int, default=1)
    ap.add_argument("--limit", type=int, default=None)
    a = ap.parse_args()
    rows = []
    for name in a.sets.split(","):
        recs = run_set(name, a.n, a.every_image, a.limit)
        for n, rs in recs.items():
            s = summarise(rs)
            tg = [r for r in rs if not r["absent"] and r["visible"] >= MIN_VISIBLE]
            cpu = np.array([r["cpu"] for r in rs])
            prec = "-" if s["found"] == 0 else format(s["precision"], ".0%")
            mode = f"on ({n})" if n else "off"
            rows.append(f"| {Path(name).name} | {mode} | {s['queries']} ({s['targets']}) "
                        f"| {sum(r['proposed'] for r in tg)} | {s['found']} | {s['right']} "
                        f"| **{s['wrong']}** | {s['recall20']:.0%} | {prec} "
                        f"| {s['p50']:.0f} / {s['p95']:.0f} "
                        f"| {np.median(cpu):.0f} / {np.percentile(cpu, 95):.0f} |")
            print(rows[-1], file=sys.stderr, flush=True)
    print("\n| set | regions | queries (targets) | truth proposed | found | right | wrong found "
          "| recall <20px | precision | wall p50 / p95 ms | CPU p50 / p95 ms |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
