"""Speed (issue 19): where a frame's time goes, what the deadline does to it, and the first frame.

Prints markdown tables; asserts nothing::

    python bench/speed.py [--parts runs,deadline,first,clients] [--limit N] [--repeat R]

runs      paper renders (1280 x 960) with the distance given and not given, and the clutter renders
          (distance not given; ``--clutter-sets``) with the default deadline and without one: p50 / p95
          of each stage of ``timing_ms``, found / right / wrong found, recall at MSPD < 5 px (targets
          >= half visible) and the refined pose's mean errors beside them (the accuracy must not move).
deadline  clutter renders at several ``deadline_ms``: p50 / p95 of the total against the deadline,
          and the share of frames answered past it by more than 10 %.
first     a fresh ``python`` process: start-up (imports + ``warm_up``), then the first paper frame with
          the distance given and the next ones: the first frame's cost against a warm one.
clients   two threads estimating at once in one process (as uvicorn's threadpool would), against one:
          frames per second and latency.

Latencies are ``timing_ms`` (``estimate``'s own clock, decoding excluded) on this machine: run it
on a quiet one (``nproc`` cores; docs/benchmarks.md's table is 2 cores).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.lib.data import (  # noqa: E402
    FINE_PX,
    MIN_VISIBLE,
    RIGHT_PX,
    gt_bank,
    load_model_info,
    read_colour,
    read_gt,
    read_meta,
    set_dir_of,
    stage_errors,
)
from service.vision.geometry.camera import Intrinsics  # noqa: E402
from service.vision.pipeline import estimate, warm_up  # noqa: E402

STAGES = ("edges", "coarse", "refine", "total")

# A cell at a few frames a second sets about this much (the service has no deadline by default).
CELL_DEADLINE_MS = 450.0


def frames(set_name: str, limit: int | None) -> list[dict]:
    set_dir = set_dir_of(set_name)
    out = []
    for g in read_gt(set_dir)[:limit] if limit else read_gt(set_dir):
        out.append({"g": g, "set_dir": set_dir, "image": read_colour(set_dir / g["image"]),
                    "intr": Intrinsics.from_K(np.asarray(g["K"], float)),
                    "bank": gt_bank(set_dir, g["model"])})
    return out


def run(fs: list[dict], *, distance_given: bool, deadline_ms: float | None, repeat: int = 1) -> list[dict]:
    recs = []
    minfo: dict = {}
    for f in fs:
        g = f["g"]
        for _ in range(repeat):
            out = estimate(f["bank"], f["image"], f["intr"], distance_mm=float(g["t_mm"][2]) if distance_given
                           else None, deadline_ms=deadline_ms)
            pose = (out.refined or out.coarse).pose if out.found else None
            err = {}
            if pose is not None and not g.get("absent"):
                info = load_model_info(f["set_dir"], g["model"], read_meta(f["set_dir"]), minfo)
                err = stage_errors(pose, g, info, np.asarray(g["K"], float), int(g["width"]))
            recs.append({"t": out.timing_ms, "found": out.found, "err": err, "deadline": out.deadline_reached,
                         "visible": float(g.get("visible_fraction", 1.0)), "absent": bool(g.get("absent"))})
    return recs


def pct(xs, q) -> float:
    return float(np.percentile(xs, q)) if len(xs) else float("nan")


def runs_table(limit: int | None, repeat: int, clutter_sets: list[str]) -> None:
    paper = frames("paper", limit)
    for f in paper[:1]:  # level-A templates of the camera and distance, outside the timing
        run([f], distance_given=False, deadline_ms=None)
    run(paper[:1], distance_given=True, deadline_ms=None)
    rows = [("paper, distance given", run(paper, distance_given=True, deadline_ms=None, repeat=repeat)),
            ("paper, distance not given", run(paper, distance_given=False, deadline_ms=None, repeat=repeat))]
    for name in clutter_sets:
        clutter = frames(name, limit)
        label = Path(name).name
        rows += [(f"{label}, deadline {CELL_DEADLINE_MS:g} ms",
                  run(clutter, distance_given=False, deadline_ms=CELL_DEADLINE_MS)),
                 (f"{label}, no deadline", run(clutter, distance_given=False, deadline_ms=None))]
    print("| run | frames | " + " | ".join(f"{s} p50 / p95 ms" for s in STAGES)
          + " | found | right | wrong found | recall <5px | deadline reached "
          "| refined tx / ty / tz mm, rot deg |")
    print("|---|---|" + "---|" * (len(STAGES) + 6))
    for name, recs in rows:
        cells = [f"{pct([r['t'][s] for r in recs], 50):.0f} / {pct([r['t'][s] for r in recs], 95):.0f}"
                 for s in STAGES]
        found = [r for r in recs if r["found"]]
        right = [r for r in found if r["err"] and r["err"]["mspd640_px"] < RIGHT_PX]
        targets = [r for r in recs if not r["absent"] and r["visible"] >= MIN_VISIBLE]
        rec5 = sum(r["found"] and r["err"] and r["err"]["mspd640_px"] < FINE_PX for r in targets)
        errs = [r["err"] for r in right]
        acc = ("-" if not errs else " / ".join(f"{np.mean([e[k] for e in errs]):.2f}"
                                               for k in ("tx_mm", "ty_mm", "tz_mm", "re_deg")))
        print(f"| {name} | {len(recs)} | " + " | ".join(cells)
              + f" | {len(found)} | {len(right)} | **{len(found) - len(right)}** | "
              f"{rec5}/{len(targets)} | {sum(r['deadline'] for r in recs)} | {acc} |")


def deadline_table(limit: int | None) -> None:
    clutter = frames("clutter", limit)
    run(clutter[:1], distance_given=False, deadline_ms=None)
    print("| deadline ms | frames | total p50 / p95 ms | p95 / deadline | past deadline +10 % "
          "| deadline reached | found |")
    print("|---|---|---|---|---|---|---|")
    for dl in (50.0, 100.0, 200.0, CELL_DEADLINE_MS, 1000.0):
        recs = run(clutter, distance_given=False, deadline_ms=dl)
        tot = [r["t"]["total"] for r in recs]
        print(f"| {dl:g} | {len(recs)} | {pct(tot, 50):.0f} / {pct(tot, 95):.0f} | {pct(tot, 95) / dl:.2f} | "
              f"{sum(t > 1.1 * dl for t in tot)} | {sum(r['deadline'] for r in recs)} | "
              f"{sum(r['found'] for r in recs)} |")


FIRST_SCRIPT = r"""
import json, sys, time
t0 = time.perf_counter()
sys.path.insert(0, {root!r})
from bench.speed import frames
from service.vision.pipeline import estimate, warm_up
t1 = time.perf_counter()
warm_up()
t2 = time.perf_counter()
fs = frames("paper", 6)
out = []
for f in fs:
    r = estimate(f["bank"], f["image"], f["intr"], distance_mm={distance})
    out.append(r.timing_ms["total"])
print(json.dumps({{"import_ms": 1000 * (t1 - t0), "warm_up_ms": 1000 * (t2 - t1), "frames_ms": out}}))
"""


def first_table() -> None:
    print("| fresh process | imports ms | warm_up ms | first frame ms | warm frames p50 ms | first / warm |")
    print("|---|---|---|---|---|---|")
    for name, distance in (("distance given", 'float(f["g"]["t_mm"][2])'), ("distance not given", "None")):
        res = subprocess.run([sys.executable, "-c", FIRST_SCRIPT.format(root=str(ROOT), distance=distance)],
                             capture_output=True, text=True, check=True, cwd=ROOT)
        d = json.loads(res.stdout.strip().splitlines()[-1])
        first, warm = d["frames_ms"][0], float(np.median(d["frames_ms"][1:]))
        print(f"| {name} | {d['import_ms']:.0f} | {d['warm_up_ms']:.0f} | {first:.0f} | {warm:.0f} | "
              f"{first / warm:.2f} |")


def clients_table(limit: int | None) -> None:
    paper = frames("paper", limit)
    run(paper[:1], distance_given=True, deadline_ms=None)
    print("| clients | frames | frames/s | latency p50 / p95 ms |")
    print("|---|---|---|---|")
    for n in (1, 2):
        lat: list[float] = []
        t0 = time.perf_counter()
        threads = [threading.Thread(target=_client, args=(paper[k::n], lat)) for k in range(n)]
        for th in threads:
            th.start()
        for th in threads:
            th.join()
        wall = time.perf_counter() - t0
        print(f"| {n} | {len(lat)} | {len(lat) / wall:.1f} | {pct(lat, 50):.0f} / {pct(lat, 95):.0f} |")


def _client(fs: list[dict], lat: list[float]) -> None:
    for f in fs:  # list.append is atomic: no lock
        t = time.perf_counter()
        estimate(f["bank"], f["image"], f["intr"], distance_mm=float(f["g"]["t_mm"][2]))
        lat.append(1000 * (time.perf_counter() - t))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--parts", default="runs,deadline,first,clients")
    ap.add_argument("--limit", type=int, default=None, help="first N images of each set")
    ap.add_argument("--repeat", type=int, default=1, help="estimates per paper image (latency spread)")
    ap.add_argument("--clutter-sets", default="clutter", help="comma-separated sets (names under the data "
                    "dir, or folders like bench/synth_scenes.py's) run with and without the default deadline")
    a = ap.parse_args(argv)
    parts = a.parts.split(",")
    warm_up()
    if "runs" in parts:
        runs_table(a.limit, a.repeat, [s for s in a.clutter_sets.split(",") if s])
        print()
    if "deadline" in parts:
        deadline_table(a.limit)
        print()
    if "first" in parts:
        first_table()
        print()
    if "clients" in parts:
        clients_table(a.limit)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
