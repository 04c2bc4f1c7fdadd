"""What a score on evidence that assumes no material would find of parts on a plane (issue 47): the
service reports this evidence (``edge_agreement``, ``inner_agreement``) with a plane and does not score it
yet.

Records: every candidate the estimate checks on a set's images (none found: ``min_score`` 2), with the
table plane of the gt lines and ``max_instances`` the copies of that model (as ``bench/cell.py`` runs
it), each with its evidence and its MSPD (640 px width) to the nearest copy: right under ``RIGHT_PX``,
wrong from ``WRONG_PX`` (between: left out of the fit). They are kept in bench/out/plane_records/ per
(set, stride, start) and made again only with ``--rebuild``.

The fit: the sign-constrained logistic regression (``bench/lib/fit.fit_monotone``) on ``FEATURES`` of the
``--fit`` records. The operating point: the highest score of a wrong candidate of the fit records, raised
by ``--margin`` in logit; the printed weights put it at ``verdict.MIN_SCORE`` (0.98). Then per set
(``--fit`` and ``--report``): checked candidates right / wrong, and right / wrong at or above the
operating point; and per part of the fit records, how many right candidates score above that part's own
highest wrong one (what an operating point calibrated per part could find)::

    python bench/fit_plane_verdict.py --fit sygrid_synth:2:0 --report sygrid_synth:2:1
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.cell import mspd640, plane_of, queries_of  # noqa: E402
from bench.lib.data import OUT_DIR, gt_bank, load_model_info, read_colour, read_gt, read_meta, set_dir_of  # noqa: E402
from bench.lib.fit import fit_monotone  # noqa: E402
from service.vision.estimate.verdict import LOWER_IS_BETTER, MIN_SCORE  # noqa: E402
from service.vision.geometry.camera import Intrinsics  # noqa: E402
from service.vision.pipeline import estimate  # noqa: E402

FEATURES = ("edge_agreement", "inner_agreement", "edge_support", "colour_edge", "polarity", "unexplained")
RIGHT_PX = 10.0
WRONG_PX = 20.0
MAX_INSTANCES = 8
NOTHING_FOUND = 2.0  # a min_score no candidate reaches: every proposal is checked, whatever the verdict


def records(spec: str, rebuild: bool) -> list[dict]:
    """The checked candidates of ``set[:stride[:start]]``, made once and kept."""
    name, stride, start = (spec.split(":") + ["1", "0"])[:3]
    set_dir = Path(name) if "/" in name else set_dir_of(name)
    path = OUT_DIR / "plane_records" / f"{set_dir.name}-{stride}-{start}.jsonl"
    if path.exists() and not rebuild:
        return [json.loads(s) for s in path.read_text().splitlines() if s.strip()]
    gts = read_gt(set_dir)
    meta = read_meta(set_dir) if (set_dir / "meta.json").exists() else {}
    cache: dict = {}
    rows = []
    for image, model, lines in queries_of(gts, stride=int(stride), start=int(start)):
        copies = [g for g in lines if not g.get("absent", False)]
        bank = gt_bank(set_dir, model)
        info = load_model_info(set_dir, model, meta, cache)
        intr = Intrinsics.from_K(np.asarray(lines[0]["K"], float))
        out = estimate(bank, read_colour(set_dir / image), intr,
                       plane=plane_of(lines[0]), max_instances=max(1, min(len(copies), MAX_INSTANCES)),
                       min_score=NOTHING_FOUND)
        for c in out.checked:
            err = min((mspd640(c.refined.pose, g, info) for g in copies), default=math.inf)
            rows.append({"set": set_dir.name, "image": image, "model": model, "mspd": err,
                         "ev": c.verdict.evidence})
        print(f"{set_dir.name} {image} {model}: {len(out.checked)} checked", file=sys.stderr)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    return rows


def design(rows: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """The labelled rows (right or wrong, not between) -> (X, y)."""
    rows = [r for r in rows if r["mspd"] < RIGHT_PX or r["mspd"] >= WRONG_PX]
    X = np.array([[float(r["ev"].get(k, 0.0)) for k in FEATURES] for r in rows], float)
    X = X.reshape(-1, len(FEATURES))
    return X, np.array([r["mspd"] < RIGHT_PX for r in rows], float)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fit", required=True, help="set[:stride[:start]], comma-separated")
    ap.add_argument("--report", default="", help="set[:stride[:start]], comma-separated")
    ap.add_argument("--margin", type=float, default=0.5, help="logit above the highest wrong score")
    ap.add_argument("--rebuild", action="store_true")
    args = ap.parse_args()
    fit_rows = [r for s in args.fit.split(",") for r in records(s, args.rebuild)]
    X, y = design(fit_rows)
    signs = np.array([-1.0 if k in LOWER_IS_BETTER else 1.0 for k in FEATURES])
    w = fit_monotone(X, y, signs)
    z_wrong = float((w[0] + X[y == 0] @ w[1:]).max()) if (y == 0).any() else -math.inf
    z_op = z_wrong + args.margin
    bias = w[0] - z_op + math.log(MIN_SCORE / (1 - MIN_SCORE))
    weights = {"bias": round(float(bias), 3)} | {k: round(float(v), 3) for k, v in zip(FEATURES, w[1:],
                                                                                        strict=True) if v}
    print(f"PLANE_WEIGHTS = {weights}")
    print()
    print("| records | checked | right (< 10 px) | wrong (>= 20 px) | right found | **wrong found** |")
    print("|---|---|---|---|---|---|")
    for spec in [*args.fit.split(","), *[s for s in args.report.split(",") if s]]:
        Xs, ys = design(records(spec, args.rebuild))
        z = bias + Xs @ np.array([weights.get(k, 0.0) for k in FEATURES])
        found = z >= math.log(MIN_SCORE / (1 - MIN_SCORE)) - 1e-9
        role = "fit" if spec in args.fit.split(",") else "report"
        print(f"| {spec} ({role}) | {len(ys)} | {int(ys.sum())} | {int((1 - ys).sum())} "
              f"| {int((found & (ys == 1)).sum())} | **{int((found & (ys == 0)).sum())}** |")
    print()
    print("| part (fit records) | right | wrong | right above the part's highest wrong |")
    print("|---|---|---|---|")
    for model in sorted({r["model"] for r in fit_rows}):
        Xm, ym = design([r for r in fit_rows if r["model"] == model])
        z = Xm @ np.array([weights.get(k, 0.0) for k in FEATURES])
        top_wrong = z[ym == 0].max() if (ym == 0).any() else -math.inf
        above = int((z[ym == 1] > top_wrong).sum())
        print(f"| {model} | {int(ym.sum())} | {int((1 - ym).sum())} | {above} |")


if __name__ == "__main__":
    main()
