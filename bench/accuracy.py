"""Accuracy and speed benchmark over the development renders (``../shared/data/*/gt.jsonl``).

Prints markdown tables and writes the numbers to ``bench/out/accuracy.json``; asserts nothing.

Runs (``--sets``):
  paper         the paper's protocol, ``distance_mm`` given (tz fixed, from meta.json: 500 mm)
  paper-nodist  the same images, distance not given
  clutter       three parts in clutter, distance not given
  absent        clutter without the part: ``found`` must be false

Per run it prints the paper's Table VI layout (mean |tx|, |ty|, |tz| in mm; Rx, Rz in degrees with a
symmetric part's axis written as Rx(alpha) Rz(gamma) e_y, see
``service.vision.reference.metrics.paper_errors``), the rotation error, BOP MSPD recall at 5 and 20 px
(errors scaled by 640 / width as BOP does), ADD-S recall at 10 % of the diameter, the found rate, a
target table with pass/fail marks and the paper's own figures, and one latency table (edges / coarse /
refine / total p50 and p95, ms).

Counting: targets with ``visible_fraction >= 0.5`` are evaluated (the others are listed under
``--verbose`` only). An image where ``found`` is false or the stage returned no pose is a miss for the
recalls and is left out of the mean errors (the ``n est`` column says how many are averaged).

Templates are built once per model with ``service.vision.pipeline.build_templates(mesh, symmetry="auto")`` and
cached in ``bench/out/banks/<model>-<key>.npz`` (key: hash of the grid options, the mesh bytes, the bank
format and the source of the modules that build a bank; ``--rebuild-banks`` forces a rebuild).

``--selftest`` feeds the ground truth (spun by a random angle about the axis of a symmetric part) as
the estimate, which checks the metric and table code without the estimator: every error is 0 (up to
ADD-S's vertex sampling of a spun part), every recall 100 %, absent images not found.

Usage: python bench/accuracy.py [--sets paper,paper-nodist,clutter,absent] [--limit N] [--no-refine]
                                [--json out.json] [--verbose] [--selftest] [--grid JSON] [--rebuild-banks]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # `python bench/accuracy.py` without an installed package
    sys.path.insert(0, str(ROOT))

from bench.lib.data import (  # noqa: E402
    DATA_DIR,
    MIN_VISIBLE,
    OUT_DIR,
    ModelInfo,
    load_bank,
    load_model_info,
    read_grey,
    read_gt,
    read_meta,
    stage_errors,
    symmetry_axis,
)
from service.vision.bank import TemplateBank  # noqa: E402
from service.vision.geometry.camera import Intrinsics  # noqa: E402
from service.vision.geometry.frames import Pose  # noqa: E402
from service.vision.pipeline import EstimateOutput, PoseCandidate, RefinedPose  # noqa: E402
from service.vision.reference import metrics  # noqa: E402

MSPD_THRESHOLDS_PX = (5.0, 20.0)  # at 640 px width (BOP)
ADDS_FRACTION = 0.1  # ADD-S threshold: 10 % of the object diameter
STAGES = ("coarse", "refined")
TIMING_KEYS = ("edges", "coarse", "refine", "total", "wall")


@dataclass(frozen=True)
class RunSpec:
    name: str
    set: str
    distance_given: bool


RUNS = {
    "paper": RunSpec("paper", "paper", True),
    "paper-nodist": RunSpec("paper-nodist", "paper", False),
    "clutter": RunSpec("clutter", "clutter", False),
    "absent": RunSpec("absent", "absent", False),
}

# The paper's Table VI (50 renders at fixed distance), mean absolute errors.
PAPER_FIGURES = {
    "coarse": {"tx_mm": 2.05, "ty_mm": 0.71, "rx_deg": 0.01, "rz_deg": 0.45},
    "refined": {"tx_mm": 1.82, "ty_mm": 0.24, "rx_deg": 2.88, "rz_deg": 0.82},
}


@dataclass(frozen=True)
class Target:
    run: str
    stage: str  # "coarse" | "refined" | "latency"
    metric: str  # key of the stage summary (or of the latency summary)
    op: str  # "<=" | ">="
    value: float

    def check(self, measured: float | None) -> bool | None:
        if measured is None or not math.isfinite(measured):
            return None
        return measured <= self.value if self.op == "<=" else measured >= self.value


def _targets() -> list[Target]:
    t: list[Target] = []
    # coarse
    t += [Target("paper", "coarse", k, "<=", 1.0) for k in ("tx_mm", "ty_mm", "rx_deg", "rz_deg")]
    t += [Target("clutter", "coarse", "mspd20_recall", ">=", 0.90),
          Target("clutter", "coarse", "found_rate", ">=", 1.0),
          Target("absent", "coarse", "found_rate", "<=", 0.0)]
    # refined
    t += [Target("paper", "refined", k, "<=", v)
          for k, v in (("tx_mm", 0.2), ("ty_mm", 0.2), ("rx_deg", 0.3), ("rz_deg", 0.3))]
    t += [Target("paper-nodist", "refined", k, "<=", v)
          for k, v in (("tx_mm", 0.2), ("ty_mm", 0.2), ("tz_mm", 3.0), ("rx_deg", 0.3), ("rz_deg", 0.3))]
    t += [Target("clutter", "refined", "mspd5_recall", ">=", 0.85),
          Target("clutter", "refined", "adds_recall", ">=", 0.90)]
    # speed (1280 x 960)
    t += [Target("paper", "latency", "coarse_p50", "<=", 80.0)]
    t += [Target(r, "latency", "coarse_p50", "<=", 250.0) for r in ("paper-nodist", "clutter", "absent")]
    t += [Target(r, "latency", "refine_p50", "<=", 40.0) for r in RUNS]
    t += [Target("paper", "latency", "total_p50", "<=", 150.0)]
    return t


TARGETS = _targets()


# --- per-image evaluation --------------------------------------------------------------------------


def evaluate_image(g: dict, out: EstimateOutput | None, info: ModelInfo, wall_ms: float,
                   error: str | None = None) -> dict:
    absent = bool(g.get("absent", False))
    vis = float(g.get("visible_fraction", 0.0 if absent else 1.0))
    K = np.asarray(g["K"], float)
    rec: dict = {"image": g["image"], "model": g["model"], "absent": absent, "visible_fraction": vis,
                 "evaluated": (not absent) and vis >= MIN_VISIBLE, "diameter_mm": info.diameter_mm,
                 "found": bool(out.found) if out is not None else False, "error": error,
                 "timing_ms": dict(out.timing_ms) if out is not None else {}}
    rec["timing_ms"]["wall"] = wall_ms
    for stage in STAGES:
        cand = None
        if out is not None and out.found:
            cand = out.coarse if stage == "coarse" else out.refined
        pose = cand.pose if cand is not None else None
        if absent:
            rec[stage] = {"has_pose": pose is not None}
        else:
            rec[stage] = stage_errors(pose, g, info, K, int(g["width"]))
        if cand is not None:
            rec[stage].update(cost=float(cand.cost), score=float(cand.score))
    return rec


# --- summaries -------------------------------------------------------------------------------------


def _mean(xs) -> float:
    a = np.asarray([x for x in xs if x is not None and math.isfinite(x)], float)
    return float(a.mean()) if a.size else float("nan")


def summarise_stage(recs: list[dict], stage: str) -> dict:
    if recs and all(r["absent"] for r in recs):
        return {"n": len(recs), "n_est": sum(r[stage]["has_pose"] for r in recs),
                "found_rate": float(np.mean([r["found"] for r in recs]))}
    ev = [r for r in recs if r["evaluated"]]
    est = [r for r in ev if r[stage]["has_pose"]]
    s: dict = {"n": len(ev), "n_est": len(est),
               "found_rate": float(np.mean([r["found"] for r in ev])) if ev else float("nan")}
    for k in ("tx_mm", "ty_mm", "tz_mm", "rx_deg", "rz_deg", "re_deg", "te_mm", "mssd_mm", "adds_mm"):
        s[k] = _mean(r[stage][k] for r in est)
    for th in MSPD_THRESHOLDS_PX:
        s[f"mspd{th:g}_recall"] = metrics.recall([r[stage]["mspd640_px"] for r in ev], th)
    s["adds_recall"] = (float(np.mean([r[stage]["adds_mm"] < ADDS_FRACTION * r["diameter_mm"] for r in ev]))
                        if ev else float("nan"))
    return s


def summarise_latency(recs: list[dict]) -> dict:
    s: dict = {"n": len(recs)}
    for k in TIMING_KEYS:
        v = np.asarray([r["timing_ms"][k] for r in recs if k in r["timing_ms"]], float)
        s[f"{k}_p50"] = float(np.percentile(v, 50)) if v.size else float("nan")
        s[f"{k}_p95"] = float(np.percentile(v, 95)) if v.size else float("nan")
    return s


def check_targets(run: str, summary: dict, latency: dict) -> list[dict]:
    rows = []
    for t in TARGETS:
        if t.run != run:
            continue
        measured = latency.get(t.metric) if t.stage == "latency" else summary.get(t.stage, {}).get(t.metric)
        rows.append({"run": run, "stage": t.stage, "metric": t.metric, "measured": measured,
                     "target": f"{t.op} {t.value:g}", "paper": PAPER_FIGURES.get(t.stage, {}).get(t.metric),
                     "pass": t.check(measured)})
    return rows


# --- tables ----------------------------------------------------------------------------------------


def fmt(x, nd: int = 2, pct: bool = False) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "—"
    if isinstance(x, bool):
        return "yes" if x else "no"
    return f"{100 * x:.0f}%" if pct else f"{x:.{nd}f}"


def md_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


MAIN_COLS = [("tx_mm", "tx mm", 2, False), ("ty_mm", "ty mm", 2, False), ("tz_mm", "tz mm", 2, False),
             ("rx_deg", "Rx °", 2, False), ("rz_deg", "Rz °", 2, False), ("re_deg", "rot err °", 2, False),
             ("mspd5_recall", "MSPD<5px", 0, True), ("mspd20_recall", "MSPD<20px", 0, True),
             ("adds_recall", "ADD-S<0.1d", 0, True), ("found_rate", "found", 0, True)]


def run_table(run: str, summary: dict) -> str:
    header = ["stage", "n", "n est"] + [c[1] for c in MAIN_COLS]
    rows = []
    for stage in STAGES:
        s = summary.get(stage)
        if s is None:
            continue
        rows.append([stage, str(s["n"]), str(s["n_est"])]
                    + [fmt(s.get(k), nd, pct) for k, _, nd, pct in MAIN_COLS])
    if RUNS[run].set == "paper":
        for stage in STAGES:
            p = PAPER_FIGURES[stage]
            rows.append([f"paper ({stage})", "50", "50"]
                        + [fmt(p.get(k), nd, pct) for k, _, nd, pct in MAIN_COLS])
    return md_table(header, rows)


def target_table(rows: list[dict]) -> str:
    def mark(p):
        return "n/a" if p is None else ("PASS" if p else "FAIL")

    def val(r):
        pct = r["metric"].endswith("recall") or r["metric"].endswith("rate")
        return fmt(r["measured"], 2, pct)

    return md_table(["run", "stage", "metric", "measured", "target", "paper", "pass"],
                    [[r["run"], r["stage"], r["metric"], val(r), r["target"], fmt(r["paper"]),
                      mark(r["pass"])] for r in rows])


def latency_table(latencies: dict[str, dict]) -> str:
    header = ["run", "n"] + [f"{k} p50/p95 ms" for k in TIMING_KEYS]
    rows = [[run, str(s["n"])] + [f"{fmt(s[f'{k}_p50'], 1)} / {fmt(s[f'{k}_p95'], 1)}" for k in TIMING_KEYS]
            for run, s in latencies.items()]
    return md_table(header, rows)


DETAIL_KEYS = ("tx_mm", "ty_mm", "tz_mm", "rx_deg", "rz_deg", "re_deg", "mspd640_px", "adds_mm", "cost")


def detail_table(recs: list[dict]) -> str:
    header = ["image", "model", "vis", "eval", "found", "stage", "tx", "ty", "tz", "Rx", "Rz", "rot",
              "MSPD640 px", "ADD-S mm", "cost", "total ms", "error"]
    rows = []
    for r in recs:
        for stage in STAGES:
            e = r[stage]
            rows.append([r["image"], r["model"], fmt(r["visible_fraction"]), fmt(r["evaluated"]),
                         fmt(r["found"]), stage]
                        + [fmt(e.get(k)) for k in DETAIL_KEYS]
                        + [fmt(r["timing_ms"].get("total"), 1), r["error"] or ""])
    return md_table(header, rows)


# --- estimators ------------------------------------------------------------------------------------

Estimator = Callable[[dict, np.ndarray, Intrinsics, bool], EstimateOutput]


def selftest_estimator(seed: int = 0) -> Estimator:
    """The ground truth as the estimate (spun about the symmetry axis by a random angle)."""
    rng = np.random.default_rng(seed)

    def est(g: dict, image: np.ndarray, intr: Intrinsics, refine: bool) -> EstimateOutput:
        size = (int(g["width"]), int(g["height"]))
        timing = dict.fromkeys(("edges", "coarse", "refine", "total"), float("nan"))  # not measured
        if g.get("absent"):
            return EstimateOutput(size, False, None, None, [], timing)
        R, t = np.asarray(g["R"], float), np.asarray(g["t_mm"], float)
        axis = symmetry_axis(g)
        if axis is not None:
            Rs, _ = metrics.symmetry_rotations(axis, spins_deg=[rng.uniform(-180.0, 180.0)])
            R = R @ Rs[0]
        cand = PoseCandidate(Pose(R, t), 0.0, 1.0)
        ref = RefinedPose(Pose(R, t), 0.0, 1.0, iterations=0, inlier_ratio=1.0) if refine else None
        return EstimateOutput(size, True, cand, ref, [cand], timing)

    return est


def pipeline_estimator(spec: RunSpec, meta: dict, *, grid: dict | None, rebuild: bool, set_dir: Path,
                       top_k: int = 5) -> Estimator:
    from service.vision.pipeline import estimate

    banks: dict[str, TemplateBank] = {}
    distance = float(meta.get("fixed_distance_mm", 500.0)) if spec.distance_given else None

    def est(g: dict, image: np.ndarray, intr: Intrinsics, refine: bool) -> EstimateOutput:
        model = g["model"]
        if model not in banks:
            banks[model] = load_bank(model, set_dir / "models" / f"{model}.stl", grid, rebuild=rebuild)
        return estimate(banks[model], image, intr, distance_mm=distance, refine=refine, top_k=top_k)

    return est


# --- driver ----------------------------------------------------------------------------------------


def run_one(spec: RunSpec, est: Estimator, *, limit: int | None, refine: bool, warmup: int,
            model_cache: dict) -> list[dict]:
    set_dir = DATA_DIR / spec.set
    meta = read_meta(set_dir)
    gts = read_gt(set_dir)[:limit] if limit else read_gt(set_dir)
    for g in gts[:warmup]:  # JIT compilation and caches: not timed
        est(g, read_grey(set_dir / g["image"]), Intrinsics.from_K(np.asarray(g["K"], float)), refine)
    recs = []
    for g in gts:
        image = read_grey(set_dir / g["image"])
        intr = Intrinsics.from_K(np.asarray(g["K"], float))
        info = load_model_info(set_dir, g["model"], meta, model_cache)
        out, err = None, None
        t0 = time.perf_counter()
        try:
            out = est(g, image, intr, refine)
        except NotImplementedError:
            raise
        except Exception as exc:  # a crash on one image is a miss, not the end of the benchmark
            err = f"{type(exc).__name__}: {exc}"
        wall = 1000.0 * (time.perf_counter() - t0)
        recs.append(evaluate_image(g, out, info, wall, err))
    return recs


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, float | np.floating):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer | np.bool_):
        return x.item()
    return x


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sets", default="paper,paper-nodist,clutter,absent",
                    help=f"comma-separated runs out of {','.join(RUNS)}")
    ap.add_argument("--limit", type=int, default=None, help="first N images of each set")
    ap.add_argument("--no-refine", action="store_true", help="coarse only")
    ap.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    ap.add_argument("--verbose", action="store_true", help="per-image detail tables")
    ap.add_argument("--selftest", action="store_true",
                    help="the ground truth as the estimate (checks this code)")
    ap.add_argument("--grid", default=None, help="JSON template-grid options passed to build_templates")
    ap.add_argument("--rebuild-banks", action="store_true", help="ignore cached template banks")
    ap.add_argument("--warmup", type=int, default=1, help="untimed estimates before each run (JIT)")
    args = ap.parse_args(argv)

    names = [s.strip() for s in args.sets.split(",") if s.strip()]
    unknown = [n for n in names if n not in RUNS]
    if unknown:
        ap.error(f"unknown set(s) {unknown}; choose from {list(RUNS)}")
    if not DATA_DIR.is_dir():
        print(f"development data not found at {DATA_DIR} (set POSE_DATA_DIR)", file=sys.stderr)
        return 2
    grid = json.loads(args.grid) if args.grid else None
    refine = not args.no_refine

    model_cache: dict = {}
    report: dict = {"config": {"sets": names, "limit": args.limit, "refine": refine,
                               "selftest": args.selftest, "grid": grid, "data_dir": str(DATA_DIR),
                               "min_visible": MIN_VISIBLE,
                               "mspd_thresholds_px_at_640": list(MSPD_THRESHOLDS_PX),
                               "adds_fraction_of_diameter": ADDS_FRACTION},
                    "runs": {}}
    latencies: dict[str, dict] = {}
    all_targets: list[dict] = []
    title = "selftest (ground truth as the estimate)" if args.selftest else "posecell accuracy"
    print(f"# {title}\n")
    for name in names:
        spec = RUNS[name]
        set_dir = DATA_DIR / spec.set
        if args.selftest:
            est = selftest_estimator()
        else:
            est = pipeline_estimator(spec, read_meta(set_dir), grid=grid, rebuild=args.rebuild_banks,
                                     set_dir=set_dir)
        try:
            recs = run_one(spec, est, limit=args.limit, refine=refine,
                           warmup=0 if args.selftest else args.warmup, model_cache=model_cache)
        except NotImplementedError as exc:
            print(f"service.pipeline.estimate is not available yet ({exc}); try --selftest", file=sys.stderr)
            return 2
        summary = {stage: summarise_stage(recs, stage) for stage in STAGES if refine or stage == "coarse"}
        latency = summarise_latency(recs)
        targets = check_targets(name, summary, latency)
        latencies[name] = latency
        all_targets += targets
        dist = f"distance_mm={read_meta(set_dir).get('fixed_distance_mm', 500.0):g}" if spec.distance_given \
            else "distance not given"
        n_err = sum(r["error"] is not None for r in recs)
        print(f"## {name} ({spec.set}, {dist}; {len(recs)} images"
              + (f", {n_err} raised" if n_err else "") + ")\n")
        print(run_table(name, summary) + "\n")
        if targets:
            print(target_table(targets) + "\n")
        if args.verbose:
            print(detail_table(recs) + "\n")
        report["runs"][name] = {"summary": summary, "latency": latency, "targets": targets, "images": recs}
    print("## latency (ms)\n")
    print(latency_table(latencies) + "\n")
    checked = [t for t in all_targets if t["pass"] is not None]
    print(f"targets: {sum(t['pass'] for t in checked)}/{len(checked)} pass"
          + (f", {len(all_targets) - len(checked)} not measured" if len(checked) < len(all_targets) else ""))

    OUT_DIR.mkdir(parents=True, exist_ok=True)
    text = json.dumps(_jsonable(report), indent=1)
    (OUT_DIR / "accuracy.json").write_text(text)
    if args.json:
        args.json.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
