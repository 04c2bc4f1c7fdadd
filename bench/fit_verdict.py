"""Fit the verdict's verification score on hypothesis features, and read its operating points.

Input: the ``*-features.pkl`` files of ``bench/hypotheses.py features`` (one row per refined
hypothesis, labelled right when its refined MSPD (640 px) is under 20 px). A logistic regression on
the evidence (``service.vision.estimate.verdict.MODEL_FEATURES``, each weight's sign fixed so that
better evidence never lowers the score) is fitted on the sets given with ``--fit``; every
set is then judged per query as the pipeline judges it: the hypothesis with the highest verification
score is reported, found when the score reaches the threshold.

    python bench/synth_scenes.py /tmp/synth_a --n 120 --seed 11
    python bench/hypotheses.py proposals --set /tmp/synth_a  # then features, truths; also clutter2, absent2
    python bench/fit_verdict.py --fit synth_a,clutter2,absent2 --report clutter,absent,paper
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

from bench.lib.data import RIGHT_PX  # noqa: E402
from bench.lib.fit import fit_monotone  # noqa: E402
from service.vision.estimate.verdict import (  # noqa: E402
    FEATURES,
    LOWER_IS_BETTER,
    MIN_SCORE,
    MODEL_FEATURES,
    WEIGHTS,
    feature_vector,
)
from service.vision.pipeline import DEFAULT_DISTANCE_RANGE_MM as DISTANCE_RANGE_MM  # noqa: E402

OUT = ROOT / "bench" / "out" / "hyps"


def load(name: str, tag: str = "*") -> list[dict]:
    rows = []
    for p in sorted(OUT.glob(f"{name}-{tag}-*features.pkl" if tag != "*" else f"{name}-*features.pkl")):
        rows += [r | {"set": name} for r in pickle.loads(p.read_bytes())]
    return rows


def printed_part_images(set_dir: Path) -> set[str]:
    """The images of a ``bench/synth_scenes.py`` set with a picture of a part printed on its floor."""
    lines = [json.loads(x) for x in (set_dir / "gt.jsonl").read_text().splitlines() if x.strip()]
    return {g["image"] for g in lines if (g.get("floor") or {}).get("printed_part")}


def design(rows: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    X = np.array([feature_vector(r["ev"]) for r in rows], float)
    y = np.array([(not r["absent"]) and r["mspd1"] < RIGHT_PX for r in rows], float)
    return X, y


def judge(rows: list[dict], w: np.ndarray, thr: float) -> dict:
    """Per query: the best-scoring hypothesis is the answer; found if its score >= thr."""
    by_q: dict = {}
    for r in rows:
        if r["rank"] < 0:  # a truth hypothesis: fitted on, never proposed by the search
            continue
        if not DISTANCE_RANGE_MM[0] <= float(r["t1"][2]) <= DISTANCE_RANGE_MM[1]:
            continue  # never returned: the search's range when the distance is not given
        by_q.setdefault((r["set"], r["q"]), []).append(r)
    n = found = right = wrong = evaluated = recall5 = recall20 = 0
    for rs in by_q.values():
        n += 1
        X, _ = design(rs)
        s = 1.0 / (1.0 + np.exp(-(w[0] + X @ w[1:])))
        b = int(np.argmax(s))
        best = rs[b]
        ev = (not best["absent"]) and best["vis"] >= 0.5
        evaluated += ev
        if s[b] >= thr:
            found += 1
            ok = (not best["absent"]) and best["mspd1"] < RIGHT_PX
            right += ok
            wrong += not ok
            recall20 += ev and ok
            recall5 += ev and best["mspd1"] < 5.0
    return {"queries": n, "found": found, "right": right, "wrong": wrong, "evaluated": evaluated,
            "recall5": recall5 / max(evaluated, 1), "recall20": recall20 / max(evaluated, 1),
            "precision": right / max(found, 1)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--fit", required=True, help="comma-separated feature sets to fit on")
    ap.add_argument("--report", default="", help="comma-separated feature sets to report on")
    ap.add_argument("--use", default=",".join(MODEL_FEATURES), help="evidence the score may use")
    ap.add_argument("--min-score", type=float, default=None, help="operating point to report at")
    ap.add_argument("--weights", default=None,
                    help="'service' or a JSON file: judge with these weights instead of fitting")
    ap.add_argument("--tag", default="*", help="the caches' tag (bench/hypotheses.py --tag)")
    ap.add_argument("--exclude-printed", default="",
                    help="comma-separated synthetic set folders: leave their images with a picture of a part "
                         "printed on the floor out of the fit (a photograph of the part at its size is the "
                         "part to any monocular evidence: docs/detection-history.md)")
    ap.add_argument("--save", type=Path, default=None, help="write the fitted weights to this JSON file")
    a = ap.parse_args(argv)
    fit_rows = [r for s in a.fit.split(",") for r in load(s, a.tag)]
    for d in [Path(x) for x in a.exclude_printed.split(",") if x]:
        printed = printed_part_images(d)
        fit_rows = [r for r in fit_rows if not (r["set"] == d.name and r["image"] in printed)]
    X, y = design(fit_rows)
    w = np.zeros(len(FEATURES) + 1)
    if a.weights:
        given = WEIGHTS if a.weights == "service" else json.loads(Path(a.weights).read_text())
        w[0] = given["bias"]
        for k, v in given.items():
            if k in FEATURES:
                w[FEATURES.index(k) + 1] = v
    else:
        use = [FEATURES.index(f) for f in a.use.split(",")]
        signs = np.array([-1.0 if FEATURES[i] in LOWER_IS_BETTER else 1.0 for i in use])
        w_use = fit_monotone(X[:, use], y, signs)
        w[0] = w_use[0]
        w[[i + 1 for i in use]] = w_use[1:]
    print(f"{'judged' if a.weights else 'fitted'} on {len(fit_rows)} hypotheses, {int(y.sum())} right")
    if a.save:
        fitted = {f: round(float(v), 3) for f, v in zip(("bias",) + FEATURES, w, strict=True) if v != 0}
        a.save.write_text(json.dumps(fitted))
    print("weights:", {f: round(float(v), 3) for f, v in zip(("bias",) + FEATURES, w, strict=True) if v != 0})
    print("\nOn the fit sets, per query (the best-scoring hypothesis is the answer):\n")
    print("| threshold | found | right | wrong | recall<5px | recall<20px | precision |")
    print("|---|---|---|---|---|---|---|")
    for thr in (0.5, 0.7, 0.8, 0.9, 0.95, 0.97, 0.98, 0.99, 0.995):
        j = judge(fit_rows, w, thr)
        print(f"| {thr} | {j['found']} | {j['right']} | {j['wrong']} | {j['recall5']:.0%} "
              f"| {j['recall20']:.0%} | {j['precision']:.1%} |")
    thr = a.min_score if a.min_score is not None else MIN_SCORE
    print(f"\nAt the operating point {thr}:\n")
    print("| set | queries | found | right | wrong | recall<5px | recall<20px | precision |")
    print("|---|---|---|---|---|---|---|---|")
    for s in [x for x in a.report.split(",") if x]:
        j = judge(load(s, a.tag), w, thr)
        print(f"| {s} | {j['queries']} | {j['found']} | {j['right']} | {j['wrong']} | {j['recall5']:.0%} | "
              f"{j['recall20']:.0%} | {j['precision']:.1%} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
