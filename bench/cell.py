"""A cell's table per set (issue 47's targets): several copies of a part on a table, found as the API finds
them. One query per (image, model) of a set in the gt.jsonl format, estimated with ``max_instances`` (the
number of copies of that model in the image, capped at MAX_INSTANCES, or ``--max-instances``), with the
table's plane of the gt lines (``--no-plane``: without), distance not given, colour image as stored.

Each found instance (its refined pose, else its coarse one) is matched to the gt copies of that model in
that image (any visibility) by MSPD at 640 px width (symmetry as the gt line's "symmetry" says, as
bench/lib/data.py does): greedily by verification score, highest first, each instance to the nearest copy
not yet taken within the threshold, one instance per copy (a second instance on a copy already taken is
wrong). Targets: the copies at least ``--min-visible`` visible.

Columns, per set and per model: queries; copies (targets); found instances; right (matched at MSPD < 20
px); **wrong found** (found instances matching no copy at MSPD < 20 px, counted also on images without
a copy); recall at MSPD < 5 px and < 20 px over the targets (each threshold matched on its own);
precision (right / found); latency p50 / p95 of the whole estimate, ms. Under each table: the reasons
the best rejected candidate gave on the queries where nothing was found (``out.verdict.reason``).

Sets: names under ../shared/data (sygrid_synth, lmo_dev, clutter, absent, ...) or any folder in the same
format (gt.jsonl, images/, models/<model>.stl). Each model's bank is built once and cached
(bench/lib/data.py: bench/out/banks); its build or load time goes to stderr.

    NUMBA_NUM_THREADS=1 python bench/cell.py --sets sygrid_synth,lmo_dev [--stride 4] [--start 0]
        [--limit N] [--models a,b] [--max-instances 8] [--no-plane] [--min-visible 0.7] [--json out.jsonl]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.lib.calibration import plane_calibration  # noqa: E402
from bench.lib.data import (  # noqa: E402
    FINE_PX,
    PART_NAMES,
    RIGHT_PX,
    bank_path,
    gt_bank,
    load_model_info,
    read_colour,
    read_gt,
    read_meta,
    set_dir_of,
    symmetry_axis,
)
from bench.lib.policy import add_policy_options, policy_of  # noqa: E402
from service.vision.estimate.verdict import (  # noqa: E402
    AGREEMENT_EVIDENCE,
    PlaneAgreement,
    distinct,
    material_free,
    verification_score,
)
from service.vision.geometry.camera import Intrinsics  # noqa: E402
from service.vision.geometry.plane import Plane  # noqa: E402
from service.vision.pipeline import DEFAULT_POLICY, Policy, estimate  # noqa: E402
from service.vision.pipeline.plane_calibration import MARGIN, SCENES  # noqa: E402
from service.vision.reference import metrics  # noqa: E402

MIN_VISIBLE = 0.7  # the targets: copies at least this share visible
MAX_INSTANCES = 8  # the default max_instances (copies of the model in the image) is capped here


def plane_of(line: dict) -> Plane:
    """The gt line's table plane as the API maps a request's ``plane`` (``schemas.Plane.to_plane``): the
    normal scaled to unit length, ``d_mm`` with it; refused as the API refuses it."""
    p = line["plane"]
    n = float(np.linalg.norm(p["normal"]))
    if not n > 1e-12 or not float(p["d_mm"]) / n < 0:
        raise ValueError(f"{line['image']}: plane {p} is not one the API takes (normal 0 or d_mm >= 0)")
    return Plane(np.asarray(p["normal"], float) / n, float(p["d_mm"]) / n)


def queries_of(gts: list[dict], *, stride: int = 1, start: int = 0, models: set[str] | None = None,
               limit: int | None = None) -> list[tuple[str, str, list[dict]]]:
    """(image, model, its gt lines) per (image, model) in the order of the gt file, on the images
    ``sorted(images)[start::stride]``, only ``models`` (None: all), the first ``limit`` (None: all)."""
    images = set(sorted({g["image"] for g in gts})[start::stride])
    groups: dict[tuple[str, str], list[dict]] = {}
    for g in gts:
        if g["image"] in images and (models is None or g["model"] in models):
            groups.setdefault((g["image"], g["model"]), []).append(g)
    out = [(image, model, lines) for (image, model), lines in groups.items()]
    return out[:limit] if limit else out


def mspd640(pose, g: dict, info) -> float:
    """MSPD (px at 640 px width) of ``pose`` against one gt copy, symmetry as the gt line says: the MSPD of
    ``bench.lib.data.stage_errors`` without its other errors."""
    R_e, t_e = np.asarray(pose.R, float), np.asarray(pose.t_mm, float)
    R_g, t_g = np.asarray(g["R"], float), np.asarray(g["t_mm"], float)
    syms = metrics.pose_symmetries(R_e, R_g, symmetry_axis(g))
    return metrics.mspd_px(R_e, t_e, R_g, t_g, np.asarray(g["K"], float), info.pts_obj, syms) * 640.0 / int(
        g["width"])


def greedy_match(d: np.ndarray, scores: list[float], threshold_px: float) -> list[int | None]:
    """(I, C) MSPD of each instance to each copy -> per instance the copy it takes (None: none): instances
    by score, highest first (ties: first listed), each the nearest copy not yet taken under the threshold."""
    taken: set[int] = set()
    match: list[int | None] = [None] * d.shape[0]
    for i in sorted(range(d.shape[0]), key=lambda i: -scores[i]):
        free = [(d[i, c], c) for c in range(d.shape[1]) if c not in taken and d[i, c] < threshold_px]
        if free:
            match[i] = min(free)[1]
            taken.add(match[i])
    return match


def run_query(bank, set_dir: Path, image: str, lines: list[dict], info, *, use_plane: bool,
              max_instances: int | None, min_visible: float, policy: Policy = DEFAULT_POLICY,
              agreement: PlaneAgreement | None = None, warm: bool = False) -> dict:
    """One estimate of ``image`` for the model of ``lines`` (its gt lines: the copies, or one "absent"
    line), judged against the copies -> the query's record. ``agreement``: the part's plane calibration
    as ``estimate`` takes it. ``warm``: the frame is estimated once before the timed run, so its latency
    is a fixed camera's over a fixed table (the plane templates made, as after a cell's first frame)."""
    copies = [g for g in lines if not g.get("absent", False)]
    n = max_instances or max(1, min(len(copies), MAX_INSTANCES))
    g0 = lines[0]
    plane = plane_of(g0) if use_plane else None
    img = read_colour(set_dir / image)
    intr = Intrinsics.from_K(np.asarray(g0["K"], float))
    if warm:
        estimate(bank, img, intr, plane=plane, max_instances=n, policy=policy, agreement=agreement)
    t0 = time.perf_counter()
    out = estimate(bank, img, intr, plane=plane, max_instances=n, policy=policy, agreement=agreement)
    ms = 1000.0 * (time.perf_counter() - t0)
    along = agreement.along if agreement is not None else "edge_agreement"
    poses = [(inst.refined or inst.coarse).pose for inst in out.instances]
    scores = [float(inst.verdict.score) for inst in out.instances]
    d = np.array([[mspd640(p, g, info) for g in copies] for p in poses], float)
    d = d.reshape(len(poses), len(copies))
    m20, m5 = greedy_match(d, scores, RIGHT_PX), greedy_match(d, scores, FINE_PX)
    # a copy some checked candidate lay near, whatever its verdict: where the verdict, not the search, lost it
    near = {c for cand in out.checked for c, g in enumerate(copies)
            if mspd640(cand.refined.pose, g, info) < RIGHT_PX}
    targets = [c for c, g in enumerate(copies) if float(g.get("visible_fraction", 1.0)) >= min_visible]
    return {
        "image": image, "model": lines[0]["model"], "max_instances": n, "plane": plane is not None,
        "ms": ms, "reason": out.verdict.reason, "n_targets": len(targets),
        "copies": [{"visible": float(g.get("visible_fraction", 1.0)), "target": c in targets,
                    "mspd640": float(d[:, c].min()) if len(poses) else None,
                    "right": c in m20, "fine": c in m5, "proposed": c in near} for c, g in enumerate(copies)],
        "instances": [{"score": s, "reason": inst.verdict.reason,
                       "material_free": material_free(inst.verdict.evidence, along),
                       **{k: inst.verdict.evidence.get(k) for k in AGREEMENT_EVIDENCE},
                       "distinct": distinct(inst.verdict.evidence),
                       "material_bound": verification_score(inst.verdict.evidence),
                       "mspd640": float(d[i].min()) if len(copies) else None,
                       "copy": m20[i], "right": m20[i] is not None}
                      for i, (s, inst) in enumerate(zip(scores, out.instances, strict=True))],
    }


def run_set(name: str, *, stride: int = 1, start: int = 0, models: set[str] | None = None,
            limit: int | None = None, plane: bool | None = None, max_instances: int | None = None,
            min_visible: float = MIN_VISIBLE, policy: Policy = DEFAULT_POLICY, warm: bool = False,
            calibration_scenes: int = SCENES, calibration_margin: float = MARGIN,
            calibration_along: tuple[str, ...] = AGREEMENT_EVIDENCE) -> list[dict]:
    """Every query of the set (``queries_of``) -> their records. ``plane`` None: the plane when the gt lines
    carry one. With a plane each part is calibrated on ``calibration_scenes`` rendered scenes, as the
    service calibrates it at upload (0: not). ``warm``: see ``run_query``."""
    set_dir = set_dir_of(name)
    meta = read_meta(set_dir)
    gts = read_gt(set_dir)
    use_plane = all("plane" in g for g in gts) if plane is None else plane
    if use_plane and not all("plane" in g for g in gts):
        raise SystemExit(f"{name}: --plane asked but not every gt line carries a plane")
    banks: dict = {}
    agreement: dict = {}
    minfo: dict = {}
    recs = []
    for image, model, lines in queries_of(gts, stride=stride, start=start, models=models, limit=limit):
        if model not in banks:
            cached = bank_path(model, set_dir / "models" / f"{model}.stl", None).exists()
            t0 = time.perf_counter()
            banks[model] = gt_bank(set_dir, model)
            print(f"{Path(name).name} bank {model}: {'loaded' if cached else 'built'} "
                  f"({banks[model].n_templates} templates) in {time.perf_counter() - t0:.1f} s",
                  file=sys.stderr)
            agreement[model] = None
            if use_plane and calibration_scenes:
                cal = plane_calibration(banks[model], model, set_dir / "models" / f"{model}.stl",
                                        calibration_scenes, calibration_margin, policy, calibration_along)
                agreement[model] = cal.agreement
                by_rest = ", ".join("-" if a is None else f"{a:.3f}" for a in cal.agreement_min_by_rest)
                print(f"{Path(name).name} {model}: agreement_min {cal.agreement_min}, by rest [{by_rest}], "
                      f"at a place {cal.agreement_min_place}, "
                      f"floor {cal.agreement_floor}, along {cal.agreement_along}, right "
                      f"{cal.right}/{cal.right_total}, wrong max {cal.wrong_max:.3f} of {cal.wrong_total}",
                      file=sys.stderr)
        info = load_model_info(set_dir, model, meta, minfo)
        recs.append(run_query(banks[model], set_dir, image, lines, info, use_plane=use_plane,
                              max_instances=max_instances, min_visible=min_visible, policy=policy, warm=warm,
                              agreement=agreement[model]))
        r = recs[-1]
        print(f"{Path(name).name} {image} {model}: {len(r['copies'])} copies, "
              f"{sum(i['right'] for i in r['instances'])} right / {len(r['instances'])} found, "
              f"{r['ms']:.0f} ms", file=sys.stderr)
    return recs


def summarise(recs: list[dict]) -> dict:
    inst = [i for r in recs for i in r["instances"]]
    targets = [c for r in recs for c in r["copies"] if c["target"]]
    right = sum(i["right"] for i in inst)
    ms = np.array([r["ms"] for r in recs]) if recs else np.array([np.nan])
    return {"queries": len(recs), "copies": sum(len(r["copies"]) for r in recs), "targets": len(targets),
            "found": len(inst), "right": right, "wrong": len(inst) - right,
            "recall5": _share(sum(c["fine"] for c in targets), len(targets)),
            "recall20": _share(sum(c["right"] for c in targets), len(targets)),
            "proposed": _share(sum(c.get("proposed", False) for c in targets), len(targets)),
            "precision": _share(right, len(inst)),
            "p50": float(np.median(ms)), "p95": float(np.percentile(ms, 95))}


def _share(n: int, of: int) -> float:
    return n / of if of else float("nan")


def _pct(x: float) -> str:
    return "-" if np.isnan(x) else f"{x:.0%}"


def _row(label: str, s: dict) -> str:
    cells = [label, str(s["queries"]), f"{s['copies']} ({s['targets']})", str(s["found"]), str(s["right"]),
             f"**{s['wrong']}**", _pct(s["recall5"]), _pct(s["recall20"]), _pct(s["proposed"]),
             _pct(s["precision"]),
             f"{s['p50']:.0f} / {s['p95']:.0f}"]
    return "| " + " | ".join(cells) + " |"


def table(name: str, recs: list[dict]) -> str:
    """The set's markdown table: one row per model (sorted by name), then the set's."""
    lines = ["| model | queries | copies (targets) | found | right | wrong found | recall <5px "
             "| recall <20px | checked <20px | precision | latency p50 / p95 ms |", "|---" * 11 + "|"]
    for model in sorted({r["model"] for r in recs}):
        lines.append(_row(PART_NAMES.get(model, model), summarise([r for r in recs if r["model"] == model])))
    lines.append(_row(f"**{Path(name).name}**", summarise(recs)))
    return "\n".join(lines)


def reasons_line(name: str, recs: list[dict]) -> str:
    """The reasons the best rejected candidate gave where nothing was found."""
    none = [r for r in recs if not r["instances"]]
    with_copies = Counter(r["reason"] for r in none if r["copies"])
    without = Counter(r["reason"] for r in none if not r["copies"])
    text = (f"{Path(name).name}: nothing found on {len(none)} of {len(recs)} queries; reasons "
            f"{dict(with_copies.most_common())}")
    return text + (f"; on images without a copy {dict(without.most_common())}" if without else "")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", default="sygrid_synth,lmo_dev")
    ap.add_argument("--limit", type=int, default=None, help="the first N queries of each set")
    ap.add_argument("--stride", type=int, default=1, help="every k-th image (sorted by name)")
    ap.add_argument("--start", type=int, default=0,
                    help="from the S-th image (0-based; with --stride k: S, S+k, ...)")
    ap.add_argument("--models", default=None, help="only these models (comma-separated gt names)")
    ap.add_argument("--plane", action=argparse.BooleanOptionalAction, default=None,
                    help="the gt lines' table plane (default: when every line carries one)")
    ap.add_argument("--max-instances", type=int, default=None,
                    help=f"fixed max_instances (default: the copies of the model in the image, capped at "
                         f"{MAX_INSTANCES}, at least 1)")
    ap.add_argument("--min-visible", type=float, default=MIN_VISIBLE,
                    help="targets: the copies at least this share visible")
    ap.add_argument("--json", type=Path, default=None, help="one JSON line per query")
    ap.add_argument("--calibration-scenes", type=int, default=SCENES,
                    help="with a plane: each part calibrated on this many rendered scenes (0: not)")
    ap.add_argument("--agreement-margin", type=float, default=MARGIN,
                    help="its agreement this far above the highest wrong one's (default: the service's)")
    ap.add_argument("--agreement-along", default=",".join(AGREEMENT_EVIDENCE),
                    help="the agreements its calibration may choose from (comma-separated; default: the "
                         "service's)")
    ap.add_argument("--warm", action="store_true",
                    help="time each frame's second estimate: a fixed camera's latency over a fixed table "
                         "(its templates made by the first)")
    add_policy_options(ap)
    a = ap.parse_args(argv)
    policy = policy_of(a)
    models = set(a.models.split(",")) if a.models else None
    from service.vision.pipeline import warm_up

    warm_up()  # as the service does at start: the first query's latency is not the kernels' compile time
    out = a.json.open("w") if a.json else None
    for name in a.sets.split(","):
        t0 = time.perf_counter()
        recs = run_set(name, stride=a.stride, start=a.start, models=models, limit=a.limit, plane=a.plane,
                       warm=a.warm,
                       max_instances=a.max_instances, min_visible=a.min_visible, policy=policy,
                       calibration_scenes=a.calibration_scenes, calibration_margin=a.agreement_margin,
                       calibration_along=tuple(a.agreement_along.split(",")))
        print(f"{Path(name).name}: {len(recs)} queries in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
        for r in recs if out else []:
            out.write(json.dumps({"set": Path(name).name, **r}) + "\n")
        plane = "given" if recs and recs[0]["plane"] else "not given"
        head = (f"{Path(name).name}: plane {plane}, distance not given, max_instances "
                f"{a.max_instances or f'the copies (<= {MAX_INSTANCES})'}, stride {a.stride} from {a.start}"
                f"{f', first {a.limit} queries' if a.limit else ''}; MSPD at 640 px width; targets >= "
                f"{a.min_visible:.0%} visible.")
        print(f"\n{head}\n\n{table(name, recs)}\n\n{reasons_line(name, recs)}", flush=True)
    if out:
        out.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
