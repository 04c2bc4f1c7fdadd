"""Is the estimate repeatable? Runs ``pipeline.estimate`` on the same frames several times in one process
and prints, per frame, whether the candidate lists, the chosen pose and the verdict were identical
every time; ``--dump`` writes each frame's first answer (a fingerprint: every candidate's pose, cost and
score; the verdict; the refined pose) so that two processes can be compared with ``--against``.

    python bench/repeat.py --sets clutter [--limit N] [--runs 2] [--cold] [--dump a.json] [--against b.json]
                           [--distance-given]

``--cold``: empty the process's memos (level-A tables, scaled offsets, ...) before every run, so that
each run makes its tables again (run 1 of a process is cold anyway). The answer must not depend on
whether a cache was warm, on the thread count (NUMBA_NUM_THREADS) or on the time a stage took when no
deadline is given.
"""

from __future__ import annotations

import argparse
import gc
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.lib.data import gt_bank, read_colour, read_gt, set_dir_of  # noqa: E402
from service.vision.geometry.camera import Intrinsics  # noqa: E402
from service.vision.memo import Memo  # noqa: E402
from service.vision.pipeline import estimate  # noqa: E402


def clear_memos() -> None:
    """Empty every ``Memo`` of the process (the next estimate is as cold as a fresh process's, but for
    numba's compiled kernels)."""
    for m in [o for o in gc.get_objects() if isinstance(o, Memo)]:
        m.clear()


def _pose(p) -> list[float]:
    return [float(x) for x in np.concatenate([np.asarray(p.R).ravel(), np.asarray(p.t_mm).ravel()])]


def fingerprint(out) -> dict:
    """What an answer is made of, exactly (floats as repr: any difference counts)."""
    v = out.verdict
    return {"found": bool(out.found), "reason": v.reason, "score": repr(float(v.score)),
            "candidates": [[repr(x) for x in _pose(c.pose) + [c.cost, c.score]] for c in out.candidates],
            "refined": [repr(x) for x in _pose(out.refined.pose)] if out.refined is not None else None,
            "deadline": bool(out.deadline_reached)}


def first_difference(a: dict, b: dict) -> str:
    """A short description of where two fingerprints first differ ("" when identical)."""
    for k in ("found", "reason", "score", "refined", "deadline"):
        if a[k] != b[k]:
            return k
    ca, cb = a["candidates"], b["candidates"]
    if len(ca) != len(cb):
        return f"candidates: {len(ca)} vs {len(cb)}"
    for i, (x, y) in enumerate(zip(ca, cb, strict=True)):
        if x != y:
            dmax = max(abs(float(p) - float(q)) for p, q in zip(x, y, strict=True))
            return f"candidate {i} (max |diff| {dmax:.3g})"
    return ""


def frames(sets: str, limit: int | None) -> list[tuple[str, dict, Path]]:
    out = []
    for name in sets.split(","):
        set_dir = set_dir_of(name)
        gts = read_gt(set_dir)
        out += [(f"{name}/{g['image']}:{g['model']}", g, set_dir) for g in (gts[:limit] if limit else gts)]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sets", default="clutter")
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--cold", action="store_true", help="empty the memos before every run")
    ap.add_argument("--dump", type=Path, default=None)
    ap.add_argument("--against", type=Path, default=None, help="a --dump of another process to compare with")
    ap.add_argument("--distance-given", action="store_true", help="estimate with each frame's true distance "
                    "(the ground truth's t_z), as the paper protocol does")
    a = ap.parse_args(argv)
    todo = frames(a.sets, a.limit)
    runs: list[dict[str, dict]] = []
    for _ in range(a.runs):
        if a.cold:
            clear_memos()
        run = {}
        for key, g, set_dir in todo:
            bank = gt_bank(set_dir, g["model"])
            image = read_colour(set_dir / g["image"])
            out = estimate(bank, image, Intrinsics.from_K(np.asarray(g["K"], float)),
                           distance_mm=float(g["t_mm"][2]) if a.distance_given else None)
            run[key] = fingerprint(out)
        runs.append(run)
    other = json.loads(a.against.read_text()) if a.against else None
    n_diff = 0
    for key, *_ in todo:
        diffs = [first_difference(runs[0][key], r[key]) for r in runs[1:]]
        if other is not None:
            diffs.append(first_difference(runs[0][key], other[key]) if key in other else "missing")
        names = [f"run {i + 2}" for i in range(a.runs - 1)] + (["other process"] if other is not None else [])
        bad = [f"{n}: {d}" for n, d in zip(names, diffs, strict=True) if d]
        n_diff += bool(bad)
        print(f"{key:40s} {'found' if runs[0][key]['found'] else runs[0][key]['reason']:20s} "
              f"{'; '.join(bad) or 'identical'}")
    print(f"\n{n_diff} of {len(todo)} frames differ ({a.runs} runs{', cold' if a.cold else ''}"
          f"{', and against ' + str(a.against) if a.against else ''})")
    if a.dump:
        a.dump.write_text(json.dumps(runs[0], indent=0))
    return 0


if __name__ == "__main__":
    sys.exit(main())
