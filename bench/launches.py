"""How many parallel regions (numba ``prange`` loops) a frame starts, and from which kernel. With
OpenMP threads that sleep between kernels (OMP_WAIT_POLICY=PASSIVE) each start wakes a thread, so the
count is a cost of its own. Counts Python-level calls of every ``parallel=True`` kernel of the vision
core; ``_scan_bounded`` starts one region per round of anchors (see there), counted as such.

    python bench/launches.py [--sets paper] [--limit N] [--distance-given] [--ab REPEAT [--serial-upto N]]

``--ab``: instead, in one process, alternate frame by frame between the kernels' serial small rounds and
blocks (as configured) and every round and block table in parallel (``serial_round`` = ``serial_blocks``
= 0, as before), REPEAT times per frame, and print the coarse and total wall-clock p50 / p95 of each.
"""

from __future__ import annotations

import argparse
import collections
import importlib
import pkgutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import service.vision as vision  # noqa: E402
from bench.accuracy import gt_bank, read_colour  # noqa: E402
from bench.repeat import frames  # noqa: E402
from service.vision.geometry.camera import Intrinsics  # noqa: E402
from service.vision.pipeline import estimate  # noqa: E402

COUNTS: collections.Counter = collections.Counter()


def _rounds(kernel, args) -> int:
    """Parallel regions one call starts: one, but ``_scan_bounded`` starts one per round of anchors that
    is larger than ``serial_round`` (smaller rounds run on the calling thread), ``_block_lower_bounds``
    none for at most ``serial_blocks`` blocks."""
    from service.vision.estimate import coarse, scan
    if kernel.py_func.__name__ == "_block_lower_bounds":
        serial = args[9] if len(args) > 9 else getattr(coarse, "SERIAL_BLOCKS", 0)
        return int(len(args[6]) > serial)
    if kernel.py_func.__name__ != "_scan_bounded":
        return 1
    n_anchors, shared = len(args[5]), bool(args[10])
    serial = args[13] if len(args) > 13 else getattr(coarse, "SERIAL_ROUND", 0)
    size, start, n = (scan.SHARED_FIRST_ROUND if shared else n_anchors), 0, 0
    while start < n_anchors:
        n += min(size, n_anchors - start) > serial
        start += size
        size *= 2
    return n


def _wrap(name, kernel):
    def counted(*args, **kw):
        COUNTS[name] += _rounds(kernel, args)
        return kernel(*args, **kw)
    return counted


def instrument() -> list[str]:
    """Replace every parallel kernel of the vision core, in every module that holds it, by a counter."""
    mods = [importlib.import_module(m.name)
            for m in pkgutil.walk_packages(vision.__path__, "service.vision.")]
    names = []
    for mod in mods:
        for attr, obj in list(vars(mod).items()):
            if getattr(obj, "targetoptions", {}).get("parallel"):
                setattr(mod, attr, _wrap(f"{obj.py_func.__module__.split('.')[-1]}.{attr}", obj))
                names.append(attr)
    return names


def _with_last(kernel, serial_upto: int):
    return lambda *a: kernel(*a, serial_upto)


def ab(todo, distance_given: bool, repeat: int, upto: int | None) -> None:
    from service.vision.estimate import coarse, scan
    kernels = {"_scan_bounded": scan._scan_bounded, "_block_lower_bounds": scan._block_lower_bounds}
    serial = dict(kernels) if upto is None else {k: _with_last(f, upto) for k, f in kernels.items()}
    parallel = {k: _with_last(f, 0) for k, f in kernels.items()}
    times: dict[str, list] = {"serial small kernels": [], "all parallel": []}
    for _, g, set_dir in todo:
        bank = gt_bank(set_dir, g["model"])
        image = read_colour(set_dir / g["image"])
        for i in range(-1, 2 * repeat):  # -1: a warm-up (level-A tables, ...), not counted
            name, kernels = (("serial small kernels", serial), ("all parallel", parallel))[i % 2]
            for attr, k in kernels.items():
                setattr(coarse, attr, k)
            out = estimate(bank, image, Intrinsics.from_K(np.asarray(g["K"], float)),
                           distance_mm=float(g["t_mm"][2]) if distance_given else None)
            if i >= 0:
                times[name].append((out.timing_ms["coarse"], out.timing_ms["total"]))
    for attr, k in kernels.items():
        setattr(coarse, attr, k)
    print(f"| kernels ({len(todo)} frames x {repeat}, alternating) | coarse p50 / p95 ms "
          "| total p50 / p95 ms |\n|---|---|---|")
    for name, ts in times.items():
        c, t = np.array(ts).T
        print(f"| {name} | {np.percentile(c, 50):.1f} / {np.percentile(c, 95):.1f} "
              f"| {np.percentile(t, 50):.1f} / {np.percentile(t, 95):.1f} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sets", default="paper")
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--distance-given", action="store_true")
    ap.add_argument("--ab", type=int, default=0)
    ap.add_argument("--serial-upto", type=int, default=None, help="with --ab: the serial side's serial_round "
                    "and serial_blocks (default: the kernels' own)")
    a = ap.parse_args(argv)
    todo = frames(a.sets, a.limit)
    if a.ab:
        ab(todo, a.distance_given, a.ab, a.serial_upto)
        return 0
    instrument()
    for _, g, set_dir in todo:
        bank = gt_bank(set_dir, g["model"])
        image = read_colour(set_dir / g["image"])
        estimate(bank, image, Intrinsics.from_K(np.asarray(g["K"], float)),
                 distance_mm=float(g["t_mm"][2]) if a.distance_given else None)
    n = len(todo)
    print(f"| kernel | parallel regions per frame ({n} frames, {a.sets}"
          f"{', distance given' if a.distance_given else ''}) |\n|---|---:|")
    for name, c in COUNTS.most_common():
        print(f"| {name} | {c / n:.1f} |")
    print(f"| total | {sum(COUNTS.values()) / n:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
