"""Taught appearance (``service/vision/model/appearance.py``): does the part's colour, taught from a few
reference photos at known poses, tell a printed or painted part at its true pose from the wrong poses?

Protocol on a set with several images of the same parts (lmo_dev): ``--references N`` images, spread
evenly over the sorted image list (0, n/N, 2n/N, ...), are the reference photos, taught with their
ground-truth poses (the other annotated parts' pixels hidden: a fixture shot shows the part alone);
the remaining images are split into two halves by position (even / odd). The verdict's
``APPEARANCE_WEIGHTS`` are fitted on the even half (``--fit-half``) and reported on both.

``evidence``: the appearance evidence of every cached candidate and truth of
``bench/hypotheses.py features`` (``bench/out/hyps/<set>-r13-features.pkl``, ``-truth-features``) at its
refined pose; prints the truths' and wrong candidates' medians and AUC, the fitted weights (``--save``
writes them as JSON) and, per half and operating point, what the verdict would find (best score per
query among the cached candidates, distance 300-1200 mm).

    python bench/appearance.py evidence [--set lmo_dev] [--references 4] [--save w.json]

``polish``: the cached candidates and truths scoring ``Policy.taught_search.polish_from``-0.98 under the
taught score, moved by ``pipeline.polish_appearance`` and scored again: how many cross the operating
point, per half (right candidates, wrong ones, truths).

    python bench/appearance.py polish [--set lmo_dev] [--references 4]

``parts``: per set and part, what its reference photos teach and whether estimates would use it
(``Appearance``: faces known, reference shading r2, hue share, agreement, plain, used).

    python bench/appearance.py parts --sets lmo_dev,paper,clutter2,clutter --references 4

The pipeline run with the taught colours is ``bench/detection.py --references 4``.
"""

from __future__ import annotations

import argparse
import json
import pickle
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.lib.data import RIGHT_PX, gt_bank, read_colour, read_gt, set_dir_of  # noqa: E402
from bench.lib.fit import auc, fit_monotone  # noqa: E402
from bench.lib.teach import half_of, taught  # noqa: E402
from service.vision.estimate import evidence as _evidence  # noqa: E402
from service.vision.geometry.camera import Intrinsics  # noqa: E402
from service.vision.geometry.frames import Pose  # noqa: E402
from service.vision.pipeline import DEFAULT_DISTANCE_RANGE_MM as RANGE_MM  # noqa: E402

HYPS = ROOT / "bench" / "out" / "hyps"
FEATURES = ("appearance", "appearance_known", "region_global")


def appearance_rows(name: str, n_references: int) -> list[dict]:
    """The cached candidates and truths of the non-reference images, with their appearance evidence."""
    set_dir = set_dir_of(name)
    app = taught(set_dir, n_references)
    halves = half_of(set_dir, n_references)
    rows = []
    for kind in ("features", "truth-features"):
        cached = pickle.loads((HYPS / f"{name}-r13-{kind}.pkl").read_bytes())
        rows += [r for r in cached if r["image"] in halves]
    rows.sort(key=lambda r: r["image"])
    K = {g["image"]: np.asarray(g["K"], float) for g in read_gt(set_dir)}
    current, frame = None, None
    out = []
    for r in rows:
        if r["image"] != current:
            current = r["image"]
            frame = _evidence.colour_frame(read_colour(set_dir / current))
        ev = _evidence.evidence(gt_bank(set_dir, r["model"]), Pose(np.asarray(r["R1"]), np.asarray(r["t1"])),
                                Intrinsics.from_K(K[current]), frame, face_bgr=app[r["model"]].face_bgr)
        out.append(r | {"half": halves[current], "ev": r["ev"] | {
            "appearance": ev.appearance, "appearance_known": ev.appearance_known}})
    return out


def _X(rows: list[dict]) -> np.ndarray:
    return np.array([[r["ev"][k] for k in FEATURES] for r in rows], float)


def _score(w: np.ndarray, rows: list[dict]) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-(w[0] + _X(rows) @ w[1:])))


def judge(rows: list[dict], w: np.ndarray, thr: float) -> tuple[int, int, int, int]:
    """Per query the best-scoring cached candidate in range is the answer -> (found, right, wrong,
    queries)."""
    by_q: dict = defaultdict(list)
    for r in rows:
        if r["rank"] >= 0 and RANGE_MM[0] <= float(r["t1"][2]) <= RANGE_MM[1]:
            by_q[r["q"]].append(r)
    found = right = 0
    for rs in by_q.values():
        s = _score(w, rs)
        b = int(np.argmax(s))
        if s[b] >= thr:
            found += 1
            right += rs[b]["mspd1"] < RIGHT_PX
    return found, right, found - right, len({r["q"] for r in rows})


def polish(name: str, n_references: int, rows: list[dict]) -> int:
    from service.vision.estimate.verdict import MIN_SCORE, verification_score
    from service.vision.pipeline import DEFAULT_POLICY, polish_appearance, unrefined_score

    polish_from = DEFAULT_POLICY.taught_search.polish_from  # an uncalibrated part's

    set_dir = set_dir_of(name)
    app = taught(set_dir, n_references)
    K = {g["image"]: np.asarray(g["K"], float) for g in read_gt(set_dir)}
    near = [r for r in rows if polish_from <= verification_score(r["ev"]) < MIN_SCORE
            and RANGE_MM[0] <= float(r["t1"][2]) <= RANGE_MM[1]]
    counts: dict = defaultdict(lambda: [0, 0])
    current, frame = None, None
    for r in sorted(near, key=lambda r: r["image"]):
        if r["image"] != current:
            current = r["image"]
            frame = _evidence.colour_frame(read_colour(set_dir / current))
        bank, intr = gt_bank(set_dir, r["model"]), Intrinsics.from_K(K[current])
        pose = polish_appearance(bank, Pose(np.asarray(r["R1"]), np.asarray(r["t1"])), frame, intr,
                                 app[r["model"]], None)
        kind = "truth" if r["rank"] < 0 else ("right" if r["mspd1"] < RIGHT_PX else "wrong")
        cell = counts[(r["half"], kind)]
        cell[0] += 1
        cell[1] += unrefined_score(bank, pose, frame, intr, None, app[r["model"]]) >= MIN_SCORE
    print(f"{name}, {n_references} reference images: cached poses scoring {polish_from}-"
          f"{MIN_SCORE}, polished: how many reach {MIN_SCORE}\n")
    print("| half | right candidates | wrong candidates | truths (refined from the ground truth) |")
    print("|---|---|---|---|")
    for half in ("even", "odd"):
        cells = [f"{counts[(half, k)][1]} of {counts[(half, k)][0]}" for k in ("right", "wrong", "truth")]
        print(f"| {half} | " + " | ".join(cells) + " |")
    return 0


def parts(names: list[str], n_references: int) -> int:
    print("| set | part | photos | faces known | reference shading r2 | hue share | agreement | plain "
          "| used |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in names:
        for model, app in sorted(taught(set_dir_of(name), n_references).items()):
            print(f"| {name} | {model} | {app.n_views} | {app.known_fraction:.2f} "
                  f"| {app.reference_shading_r2:.2f} | {app.hue_share:.3f} | {app.agreement:.2f} "
                  f"| {app.plain} | {app.used} |")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("command", choices=["evidence", "parts", "polish"])
    ap.add_argument("--set", default="lmo_dev")
    ap.add_argument("--sets", default="lmo_dev,paper,clutter2,clutter", help="for parts")
    ap.add_argument("--references", type=int, default=4)
    ap.add_argument("--fit-half", default="even", choices=["even", "odd"])
    ap.add_argument("--save", type=Path, default=None)
    a = ap.parse_args(argv)
    if a.command == "parts":
        return parts(a.sets.split(","), a.references)
    rows = appearance_rows(a.set, a.references)
    if a.command == "polish":
        return polish(a.set, a.references, rows)
    truths = [r for r in rows if r["rank"] < 0 and r["mspd1"] < RIGHT_PX]
    wrong = [r for r in rows if r["rank"] >= 0 and r["mspd1"] >= RIGHT_PX]
    print(f"{a.set}: {a.references} reference images; {len(truths)} truths, {len(wrong)} wrong candidates\n")
    print("| evidence | truth p10 / p50 / p90 | wrong p10 / p50 / p90 | AUC truth vs wrong |")
    print("|---|---|---|---|")
    for k in (*FEATURES, "shading_r2"):
        t = np.array([r["ev"][k] for r in truths])
        n = np.array([r["ev"][k] for r in wrong])
        q = lambda v: " / ".join(f"{x:.2f}" for x in np.quantile(v, [0.1, 0.5, 0.9]))  # noqa: E731
        print(f"| {k} | {q(t)} | {q(n)} | {auc(t, n):.3f} |")
    fit = [r for r in rows if r["half"] == a.fit_half]
    y = np.array([r["mspd1"] < RIGHT_PX for r in fit], float)
    w = fit_monotone(_X(fit), y, np.ones(len(FEATURES)))
    weights = {"bias": round(float(w[0]), 3)} | {k: round(float(v), 3) for k, v in zip(FEATURES, w[1:],
                                                                                        strict=True)}
    print(f"\nweights fitted on the {a.fit_half} half: {json.dumps(weights)}\n")
    print("| operating point | even half: found / right / wrong (queries) | odd half |")
    print("|---|---|---|")
    for thr in (0.9, 0.95, 0.97, 0.98, 0.99):
        cells = []
        for half in ("even", "odd"):
            f, ri, wr, nq = judge([r for r in rows if r["half"] == half], w, thr)
            cells.append(f"{f} / {ri} / **{wr}** ({nq})")
        print(f"| {thr:.2f} | " + " | ".join(cells) + " |")
    if a.save:
        a.save.write_text(json.dumps(weights))
    return 0


if __name__ == "__main__":
    sys.exit(main())
