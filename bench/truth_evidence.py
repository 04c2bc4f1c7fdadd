"""The verdict's evidence at TRUE poses, per set, against a reference set and against wrong candidates.

Does the tuning data look like the data the verdict is judged on? Per query (the part at least half
visible) the ground-truth pose is checked as ``bench/rejected_truths.py`` checks its ``truth`` line
(``pipeline.check_candidate``: refined from the truth, evidence at the refined pose, the verdict);
the evidence is cached in ``bench/out/truth_ev/<set>.pkl``. Wrong candidates are the wrong rows
(refined MSPD >= 20 px, or on an absent image) of ``bench/hypotheses.py features`` caches, when present.

Per evidence it prints each set's truth median (p25-p75), the Kolmogorov-Smirnov distance of its truth
distribution to the reference set's (``--ref``, default clutter2: the Blender tuning set), the wrong
candidates' median, and the truth's own verification score (median, how many reach the operating point)
under the service's weights and, with ``--weights file.json``, under others.

    python bench/truth_evidence.py --sets /tmp/synth_a,/tmp/synth_b,clutter2,clutter [--ref clutter2]
                                   [--wrong clutter2,absent2,synth_a] [--weights w.json] [--limit N]
"""

from __future__ import annotations

import argparse
import json
import pickle
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import service.vision.estimate.evidence as _evidence  # noqa: E402
from bench.accuracy import (  # noqa: E402
    DATA_DIR,
    gt_bank,
    load_model_info,
    read_colour,
    read_gt,
    read_meta,
    stage_errors,
)
from service.vision.estimate.verdict import FEATURES, MIN_SCORE, WEIGHTS, verification_score  # noqa: E402

OUT = ROOT / "bench" / "out" / "truth_ev"
HYPS = ROOT / "bench" / "out" / "hyps"
RIGHT_PX = 20.0


def set_dir_of(name: str) -> Path:
    p = Path(name)
    return p if p.is_dir() else DATA_DIR / name


def truth_rows(name: str, limit: int | None = None, refresh: bool = False) -> list[dict]:
    """Evidence of each visible target checked at its true pose (cached per set)."""
    path = OUT / f"{Path(name).name}.pkl"
    if path.exists() and not refresh:
        rows = pickle.loads(path.read_bytes())
        return rows[:limit] if limit else rows
    from service.vision.estimate.edges import to_grey_u8
    from service.vision.estimate.evidence import colour_frame
    from service.vision.geometry.camera import Intrinsics, undistort_image
    from service.vision.geometry.frames import Pose
    from service.vision.pipeline import (
        DEFAULT_DISTANCE_RANGE_MM,
        PoseCandidate,
        check_candidate,
        search_params,
    )

    set_dir = set_dir_of(name)
    meta, minfo = read_meta(set_dir), {}
    gts = [g for g in read_gt(set_dir) if not g.get("absent") and g.get("visible_fraction", 1) >= 0.5]
    gts = gts[:limit] if limit else gts
    n_channels = search_params(1).n_channels
    rows = []
    for g in gts:
        bank = gt_bank(set_dir, g["model"])
        image = read_colour(set_dir / g["image"])
        K = np.asarray(g["K"], float)
        intr = Intrinsics.from_K(K)
        gt = Pose(np.asarray(g["R"], float), np.asarray(g["t_mm"], float))
        c = check_candidate(bank, PoseCandidate(gt, 0.0, 0.0), to_grey_u8(image),
                            colour_frame(undistort_image(image, intr)), intr, distance_mm=None,
                            distance_range_mm=DEFAULT_DISTANCE_RANGE_MM, min_score=None,
                            n_channels=n_channels)
        info = load_model_info(set_dir, g["model"], meta, minfo)
        m1 = stage_errors(c.refined.pose, g, info, K, int(g["width"]))["mspd640_px"]
        rows.append({"image": g["image"], "model": g["model"], "vis": float(g.get("visible_fraction", 1)),
                     "mspd1": m1, "ev": dict(c.verdict.evidence), "reason": c.verdict.reason})
        print(f"  {Path(name).name} {g['image']} {g['model']:9s} m1={m1:5.1f} score={c.verdict.score:.3f} "
              f"{c.verdict.reason}", file=sys.stderr)
    if not limit:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(pickle.dumps(rows))
    return rows


def wrong_rows(names: list[str]) -> list[dict]:
    rows = []
    for name in names:
        for p in sorted(HYPS.glob(f"{Path(name).name}-default-features.pkl")):
            rows += [r for r in pickle.loads(p.read_bytes())
                     if r["rank"] >= 0 and (r["absent"] or r["mspd1"] >= RIGHT_PX)]
    return rows


def ks(a: np.ndarray, b: np.ndarray) -> float:
    """Two-sample Kolmogorov-Smirnov distance: the largest gap between the empirical CDFs."""
    if not len(a) or not len(b):
        return float("nan")
    x = np.concatenate([a, b])
    fa = np.searchsorted(np.sort(a), x, side="right") / len(a)
    fb = np.searchsorted(np.sort(b), x, side="right") / len(b)
    return float(np.abs(fa - fb).max())


def auc(pos: np.ndarray, neg: np.ndarray, lower_is_better: bool = False) -> float:
    """P(a truth's value beats a wrong candidate's), ties half."""
    if not len(pos) or not len(neg):
        return float("nan")
    if lower_is_better:
        pos, neg = -pos, -neg
    d = pos[:, None] - neg[None, :]
    return float((d > 0).mean() + 0.5 * (d == 0).mean())


def q3(a: np.ndarray) -> str:
    if not len(a):
        return "-"
    p25, p50, p75 = np.percentile(a, [25, 50, 75])
    return f"{p50:.2f} ({p25:.2f}-{p75:.2f})"


def column(rows: list[dict], k: str) -> np.ndarray:
    return np.array([float(r["ev"][k]) for r in rows if k in r["ev"]])


def main(argv=None) -> int:
    # the visible part's evidence is what these tables study too (set here: importing a helper of this
    # module leaves the service's evidence as it is)
    _evidence.VISIBLE_PART = True
    ap = argparse.ArgumentParser()
    ap.add_argument("--sets", required=True, help="comma-separated set names or folders")
    ap.add_argument("--ref", default="clutter2", help="the set whose truths the others are held to")
    ap.add_argument("--wrong", default="", help="sets whose cached wrong hypotheses are compared")
    ap.add_argument("--weights", type=Path, default=None, help="JSON weights to score the truths with too")
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--refresh", action="store_true", help="recompute cached truth evidence")
    a = ap.parse_args(argv)
    names = [s for s in a.sets.split(",") if s]
    truths = {Path(s).name: truth_rows(s, a.limit, a.refresh) for s in names}
    ref = truth_rows(a.ref, a.limit) if Path(a.ref).name not in truths else truths[Path(a.ref).name]
    wrong = wrong_rows([s for s in a.wrong.split(",") if s])
    sets = list(truths)
    print(f"\nTruth evidence (median, p25-p75) and KS distance to {Path(a.ref).name}'s truths; "
          f"wrong: {len(wrong)} wrong hypotheses of {a.wrong or '-'}.\n")
    print("| evidence | " + " | ".join(f"{s} (n={len(truths[s])})" for s in sets) + " | wrong | "
          + " | ".join(f"KS {s}" for s in sets if s != Path(a.ref).name) + " |")
    print("|---" * (2 + len(sets) + len([s for s in sets if s != Path(a.ref).name])) + "|")
    for k in FEATURES:
        cells = [q3(column(truths[s], k)) for s in sets] + [q3(column(wrong, k))]
        cells += [f"{ks(column(truths[s], k), column(ref, k)):.2f}" for s in sets if s != Path(a.ref).name]
        print(f"| {k} | " + " | ".join(cells) + " |")
    weights = {"service": WEIGHTS}
    if a.weights:
        weights["new"] = json.loads(a.weights.read_text())
    for tag, w in weights.items():
        cells = []
        for s in sets:
            sc = np.array([verification_score(r["ev"], w) for r in truths[s]])
            cells.append(f"{np.median(sc):.2f}, {int((sc >= w.get('min_score', MIN_SCORE)).sum())}/{len(sc)}"
                         if len(sc) else "-")
        print(f"| truth score ({tag}): median, >= op. point | " + " | ".join(cells) + " | | |")
    reasons = {s: {} for s in sets}
    for s in sets:
        for r in truths[s]:
            reasons[s][r["reason"]] = reasons[s].get(r["reason"], 0) + 1
    print("| truth's verdict reason (service) | " + " | ".join(
        ", ".join(f"{k} {v}" for k, v in sorted(reasons[s].items(), key=lambda kv: -kv[1])) for s in sets)
        + " | | |")
    if wrong:
        print("\nAUC truth vs the wrong hypotheses (per truth set):\n")
        print("| evidence | " + " | ".join(sets) + " |")
        print("|---" * (1 + len(sets)) + "|")
        for k in FEATURES:
            cells = [f"{auc(column(truths[s], k), column(wrong, k), k == 'unexplained'):.2f}" for s in sets]
            print(f"| {k} | " + " | ".join(cells) + " |")
        for tag, w in weights.items():
            neg = np.array([verification_score(r["ev"], w) for r in wrong])
            cells = [f"{auc(np.array([verification_score(r['ev'], w) for r in truths[s]]), neg):.2f}"
                     for s in sets]
            print(f"| verification score ({tag}) | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
