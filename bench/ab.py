"""Two configurations of the pipeline in ONE process, frame by frame in turn (A, B, A, B, ...): the host's
drift and the other jobs on the machine hit both alike, where two separate runs differ by +-20 ms.

    python bench/ab.py SWITCH[,SWITCH...] [--sets paper] [--limit N] [--repeat R] [--no-distance]

A has the named switches off, B on (each switch's "on" is the code as committed). Prints, per side,
``timing_ms`` p50 / p95 (edges, coarse, refine, total) and the process's CPU per frame (all threads:
what a loaded machine's wall clock pays), and whether the two sides' answers were identical frame by
frame (poses, verdicts). Switches:

nogil           the vision kernels release the GIL (``nogil=True``; off: recompiled without it)
front_faces     the evidence rasterises a closed mesh's front faces only (``evidence.FRONT_FACES_ONLY``)
fast_evaluate   the coarse search's ``evaluate``: one matmul, a compiled read-out (``coarse.FAST_EVALUATE``)
visible_part    the evidence's robust colour shading fit (``evidence.VISIBLE_PART``: ``visible``,
                ``shading_r2_robust``; the score does not read them)
numba1          numba's parallel kernels on one thread (the calling one; the background pool unchanged):
                B is one thread, A the budget (not a code path of the service: a measurement)
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numba
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.repeat import fingerprint  # noqa: E402
from bench.speed import frames  # noqa: E402
from service.vision import threads  # noqa: E402
from service.vision.estimate import coarse, evidence  # noqa: E402
from service.vision.pipeline import estimate, warm_up  # noqa: E402

NOGIL_MODULES = ("service.vision.estimate.coarse", "service.vision.estimate.chamfer",
                 "service.vision.estimate.refine", "service.vision.estimate.interior")
_without_gil_release: dict = {}


def _nogil(on: bool) -> None:
    """Swap every top-level nogil kernel of ``NOGIL_MODULES`` for a copy compiled without nogil (off)."""
    import importlib

    for name in NOGIL_MODULES:
        mod = importlib.import_module(name)
        for attr, k in list(vars(mod).items()):
            key = (name, attr)
            if key in _without_gil_release:
                orig, alt = _without_gil_release[key]
                setattr(mod, attr, orig if on else alt)
            elif isinstance(k, numba.core.registry.CPUDispatcher) and k.targetoptions.get("nogil"):
                opts = {o: v for o, v in k.targetoptions.items() if o not in ("nogil", "cache")}
                alt = numba.njit(**opts)(k.py_func)
                _without_gil_release[key] = (k, alt)
                setattr(mod, attr, k if on else alt)


def _flag(attr: str, module):
    def set_(on: bool) -> None:
        setattr(module, attr, on)
    return set_


_USE_BUDGET = threads.use_budget


def _numba1(on: bool) -> None:
    threads.use_budget = (lambda: numba.set_num_threads(1)) if on else _USE_BUDGET


SWITCHES = {"numba1": _numba1, "nogil": _nogil,
            "front_faces": _flag("FRONT_FACES_ONLY", evidence),
            "fast_evaluate": _flag("FAST_EVALUATE", coarse), "visible_part": _flag("VISIBLE_PART", evidence)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("switches")
    ap.add_argument("--sets", default="paper")
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--no-distance", action="store_true")
    a = ap.parse_args(argv)
    names = [s for s in a.switches.split(",") if s]
    for s in names:
        if s not in SWITCHES:
            ap.error(f"unknown switch {s!r}: one of {sorted(SWITCHES)}")

    def side(on: bool) -> None:
        for s in names:
            SWITCHES[s](on)

    warm_up()
    fs = frames(a.sets, a.limit)
    for on in (False, True):  # compile both sides' kernels, level-A tables: not counted
        side(on)
        for f in fs[:2]:
            estimate(f["bank"], f["image"], f["intr"],
                     distance_mm=None if a.no_distance else float(f["g"]["t_mm"][2]))
    rec: dict[bool, list] = {False: [], True: []}
    prints: dict[bool, list] = {False: [], True: []}
    for r in range(a.repeat):
        for f in fs:
            for on in ((False, True) if r % 2 == 0 else (True, False)):  # who goes first alternates too
                side(on)
                c0 = time.process_time()
                out = estimate(f["bank"], f["image"], f["intr"],
                               distance_mm=None if a.no_distance else float(f["g"]["t_mm"][2]))
                cpu = (time.process_time() - c0) * 1e3
                t = out.timing_ms
                rec[on].append((t["edges"], t["coarse"], t["refine"], t["total"], cpu))
                if r == 0:
                    prints[on].append(fingerprint(out))
    side(True)
    n = len(fs)
    same = sum(x == y for x, y in zip(prints[False], prints[True], strict=True))
    print(f"| {a.sets}{'' if a.no_distance else ', distance given'}, {n} frames x {a.repeat}, "
          "alternating | edges | coarse | refine | total p50 / p95 ms | process CPU p50 / mean ms |\n"
          "|---|---|---|---|---|---|")
    for on in (False, True):
        x = np.array(rec[on])
        cells = [f"{np.percentile(x[:, i], 50):.1f}" for i in range(3)]
        print(f"| {'B: ' if on else 'A: no '}{a.switches} | " + " | ".join(cells)
              + f" | {np.percentile(x[:, 3], 50):.1f} / {np.percentile(x[:, 3], 95):.1f} "
              f"| {np.percentile(x[:, 4], 50):.1f} / {x[:, 4].mean():.1f} |")
    d = np.array(rec[True])[:, 3] - np.array(rec[False])[:, 3]
    print(f"\nB - A total per frame pair: median {np.median(d):+.1f} ms, mean {d.mean():+.1f}; "
          f"answers identical on {same} of {n} frames")
    return 0


if __name__ == "__main__":
    sys.exit(main())
