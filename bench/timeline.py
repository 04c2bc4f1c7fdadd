"""Where one frame's time goes, per thread: CPU (thread_time) of each stage piece, and the critical path.

Wraps the pipeline's pieces (edges, coarse search, refinement, evidence, ...) with recorders of each
call's thread, wall start / stop and thread CPU, then runs paper renders (distance given unless
``--no-distance``) and prints markdown tables; asserts nothing::

    python bench/timeline.py [--limit N] [--repeat R] [--no-distance] [--frame K]

Tables: per piece, the median over frames of its CPU per frame (exclusive of wrapped pieces inside it),
by thread (main: the thread that called ``estimate``; bg: the background pool); per frame, the main
thread's CPU, the pool's, the wall time, and the critical path: the frame replayed on CPU times with a
free core for every background task (a task starts when it is submitted; ``Future.result`` waits for
its end). With NUMBA_NUM_THREADS=1 the CPU times are the whole work; with more, numba's own worker
threads are not counted (the critical path then assumes its kernels split evenly). The replay knows
nothing of the GIL: a task that holds it while the main thread needs it counts as parallel here but is
not. ``--frame K`` prints frame K's timeline (one line per piece call).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import functools
import importlib
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.speed import frames  # noqa: E402
from service.vision.pipeline import estimate, warm_up  # noqa: E402

PIECES = {
    "service.vision.pipeline.propose": ["propose", "distinct_candidates"],
    "service.vision.pipeline.check": ["refine"],
    "service.vision.geometry.camera": ["undistort_image"],
    "service.vision.estimate.verdict": ["decide"],
    "service.vision.estimate.edges": ["to_grey_u8", "detect_segments", "detect_segments_in_bands"],
    "service.vision.estimate.chamfer": ["distance_tensor", "segment_distance_tensor", "pooled_and_quantised"],
    "service.vision.estimate.coarse": ["_cached_level_a", "scan_level_a", "background_cost", "pick_peaks",
                                       "local_scan", "evaluate", "polish", "poses_of", "_scan_window",
                                       "_window_offsets", "_window_bounds", "_scan_bounded"],
    "service.vision.estimate.refine": ["border_points", "_image_side", "_dt_stage", "_line_stage",
                                       "unexplained_edge_ratio", "verify", "match_lines", "_moved"],
    "service.vision.estimate.lsq": ["least_squares"],
    "service.vision.geometry.silhouette": ["border_with_tangents"],
    "service.vision.geometry.render": ["rasterise_roi"],
    "service.vision.estimate.evidence": ["colour_frame", "evidence", "face_ids_roi", "_window", "_outline",
                                         "_edge_and_polarity",
                                         "_region", "_shading"],
}

_rec: list[tuple] = []  # (name, thread ident, depth, wall0, wall1, cpu0, cpu1)
# ("submit" | "wait", thread, cpu, wall, task id) and ("task", thread, cpu, wall, task id, cpu1, wall1)
_events: list[tuple] = []
_local = threading.local()
_ids = iter(range(1 << 62))


def _wrap(name, fn):
    @functools.wraps(fn)
    def inner(*a, **k):
        depth = getattr(_local, "depth", 0)
        _local.depth = depth + 1
        w0, c0 = time.perf_counter(), time.thread_time()
        try:
            return fn(*a, **k)
        finally:
            _rec.append((name, threading.get_ident(), depth, w0, time.perf_counter(), c0, time.thread_time()))
            _local.depth = depth
    inner._orig = fn
    return inner


def instrument() -> None:
    """Replace every piece, in every ``service`` module that refers to it, by its recorder; and record
    the background pool's submits, tasks and waits."""
    for mod_name, names in PIECES.items():
        mod = importlib.import_module(mod_name)
        for name in names:
            orig = getattr(mod, name)
            w = _wrap(name, orig)
            for m in list(sys.modules.values()):
                if getattr(m, "__name__", "").startswith("service") and getattr(m, name, None) is orig:
                    setattr(m, name, w)
    submit0 = concurrent.futures.ThreadPoolExecutor.submit
    result0 = concurrent.futures.Future.result

    def submit(self, fn, *a, **k):
        tid = next(_ids)
        _events.append(("submit", threading.get_ident(), time.thread_time(), time.perf_counter(), tid))

        def task():
            c0, w0 = time.thread_time(), time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                _events.append(("task", threading.get_ident(), c0, w0, tid, time.thread_time(),
                                time.perf_counter()))
        fut = submit0(self, task)
        fut._tid = tid
        return fut

    def result(self, timeout=None):
        tid = getattr(self, "_tid", None)
        out = result0(self, timeout)
        if tid is not None:
            _events.append(("wait", threading.get_ident(), time.thread_time(), time.perf_counter(), tid))
        return out

    concurrent.futures.ThreadPoolExecutor.submit = submit
    concurrent.futures.Future.result = result


def exclusive(rec: list[tuple]) -> dict[tuple[str, int], float]:
    """CPU ms per (piece, thread), less the wrapped pieces called inside it on the same thread."""
    out: dict = defaultdict(float)
    by_thread: dict = defaultdict(list)
    for r in rec:
        by_thread[r[1]].append(r)
    for th, rs in by_thread.items():
        for r in rs:
            inner = sum(x[6] - x[5] for x in rs if x[2] == r[2] + 1 and x[3] >= r[3] and x[4] <= r[4])
            out[(r[0], th)] += 1000.0 * ((r[6] - r[5]) - inner)
    return out


def critical_path(main: int, cpu0: float, cpu1: float, events: list[tuple]) -> float:
    """The frame replayed on CPU time (ms): the main thread runs its CPU; a background task starts when
    submitted (on a free core) and runs its own CPU; a wait moves the main thread to the task's end.
    Tasks submitted from a task start at that task's replayed start (conservative)."""
    tasks = {e[4]: e[5] - e[2] for e in events if e[0] == "task"}
    end: dict = {}
    sim, last = 0.0, cpu0
    for e in events:
        if e[1] != main or e[0] == "task":
            continue
        sim += e[2] - last
        last = e[2]
        if e[0] == "submit":
            end[e[4]] = sim + tasks.get(e[4], 0.0)
        elif e[0] == "wait" and e[4] in end:
            sim = max(sim, end[e[4]])
    return 1000.0 * (sim + cpu1 - last)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--no-distance", action="store_true")
    ap.add_argument("--frame", type=int, default=None, help="print this frame's timeline")
    a = ap.parse_args(argv)
    fs = frames("paper", a.limit)

    def one(f):
        g = f["g"]
        return estimate(f["bank"], f["image"], f["intr"],
                        distance_mm=None if a.no_distance else float(g["t_mm"][2]))

    warm_up()  # as the service and bench/speed.py do: freed buffers stay mapped
    for f in fs:  # warm: level-A tables, numba kernels, memos
        one(f)
    instrument()
    per_piece: dict = defaultdict(list)
    rows = []
    main_th = threading.get_ident()
    for _ in range(a.repeat):
        for i, f in enumerate(fs):
            _rec.clear()
            _events.clear()
            w0, c0 = time.perf_counter(), time.thread_time()
            out = one(f)
            w1, c1 = time.perf_counter(), time.thread_time()
            ex = exclusive(_rec)
            for name in {k[0] for k in ex}:
                mine = [(th == main_th, v) for (n, th), v in ex.items() if n == name]
                per_piece[(name, "main")].append(sum(v for m, v in mine if m))
                per_piece[(name, "bg")].append(sum(v for m, v in mine if not m))
            bg = sum(1000.0 * (e[5] - e[2]) for e in _events if e[0] == "task")
            cp = critical_path(main_th, c0, c1, list(_events))
            rows.append((1000 * (c1 - c0), bg, 1000 * (w1 - w0), cp, out.timing_ms["total"]))
            if a.frame == i:
                print_frame(_rec, _events, w0, main_th)
    n = len(rows)
    print(f"\n{n} frames ({'distance not given' if a.no_distance else 'distance given'}), CPU ms per frame,"
          f" exclusive of the pieces listed inside each\n")
    print("| piece | main p50 | bg p50 | main+bg mean |")
    print("|---|---|---|---|")
    names = sorted({k[0] for k in per_piece}, key=lambda x: -np.mean(per_piece[(x, "main")] + [0])
                   - np.mean(per_piece[(x, "bg")] + [0]))
    for name in names:
        m = per_piece.get((name, "main"), [0.0])
        b = per_piece.get((name, "bg"), [0.0])
        m = m + [0.0] * (n - len(m))
        b = b + [0.0] * (n - len(b))
        print(f"| {name} | {np.median(m):.2f} | {np.median(b):.2f} | {np.mean(m) + np.mean(b):.2f} |")
    r = np.array(rows)
    print("\n| per frame | p50 | p95 | mean |\n|---|---|---|---|")
    for j, label in enumerate(("main thread CPU", "background CPU", "wall (this clock)", "critical path",
                               "timing_ms total")):
        x = r[:, j]
        print(f"| {label} | {np.median(x):.1f} | {np.percentile(x, 95):.1f} | {x.mean():.1f} |")
    return 0


def print_frame(rec, events, w0, main_th) -> None:
    print("\n| thread | piece | start ms | wall ms | CPU ms |\n|---|---|---|---|---|")
    rows = [(r[3], "main" if r[1] == main_th else f"bg{r[1] % 1000}", "  " * r[2] + r[0], r[4] - r[3],
             r[6] - r[5]) for r in rec]
    rows += [(e[3], "main" if e[1] == main_th else f"bg{e[1] % 1000}", f"<{e[0]} {e[4]}>", 0.0, 0.0)
             for e in events if e[0] != "task"]
    rows += [(e[3], f"bg{e[1] % 1000}", f"[task {e[4]}]", e[6] - e[3], e[5] - e[2]) for e in events
             if e[0] == "task"]
    for t, th, name, wall, cpu in sorted(rows):
        print(f"| {th} | {name} | {1000 * (t - w0):.1f} | {1000 * wall:.2f} | {1000 * cpu:.2f} |")


if __name__ == "__main__":
    sys.exit(main())
