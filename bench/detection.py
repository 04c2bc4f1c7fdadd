"""Detection table per set: can a found answer be trusted? One estimate per gt line (image, model),
run as the API runs it (colour image, distance not given unless --distance-given), judged by MSPD
at 640 px width (BOP).

Columns: queries; found; right found (MSPD < 20 px); **wrong found** (found with MSPD >= 20 px, or
found on an absent image: the failure that matters most); recall at MSPD < 5 px and < 20 px over
the targets at least half visible; precision (right / found); latency p50 / p95 of the whole
estimate, ms. Sets: names under ../shared/data (paper, clutter, clutter2, absent, absent2,
lmo_dev) or any folder in the same format (e.g. a bench/synth_scenes.py output).

    python bench/detection.py --sets clutter,absent,paper,lmo_dev [--limit N] [--repeat R]

With ``--repeat R`` every set is run R times and each figure printed as the mean with its run-to-run
range (latency varies; detections do not, the pipeline being deterministic).
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

from bench.lib.data import (  # noqa: E402
    FINE_PX,
    MIN_VISIBLE,
    OUT_DIR,
    PART_NAMES,
    RIGHT_PX,
    gt_bank,
    load_model_info,
    mspd640,
    read_colour,
    read_gt,
    read_meta,
    set_dir_of,
)
from bench.lib.policy import add_policy_options, policy_of  # noqa: E402
from bench.lib.teach import half_of, taught  # noqa: E402
from service.vision.geometry.camera import Intrinsics  # noqa: E402
from service.vision.pipeline import DEFAULT_POLICY, Policy, estimate  # noqa: E402

NEAR_PX = 50.0  # a checked pose this close is the right place at a wrong turn or depth (a near miss)
# under this share visible no lmo_dev query had a right candidate checked (session 19: 0 of 53)
OCCLUDED_BELOW = 0.7
FATES = ("found right", "found wrong", "right checked, refused", "near miss", "not proposed")
FOUND_RIGHT, FOUND_WRONG, REFUSED, NEAR_MISS, NOT_PROPOSED = FATES


def run_set(name: str, *, limit: int | None, distance_given: bool, min_score: float | None,
            every_image: int = 1, references: int = 0, half: str = "all",
            teach_from: str | None = None, distance_range_mm: tuple[float, float] | None = None,
            truth: bool = False, policy: Policy = DEFAULT_POLICY, calibrate: bool = True,
            reference_offset: int = 0) -> list[dict]:
    """``references`` > 0: each part's colours are taught from that many of the set's images
    (``bench/lib/teach.py``; moved by ``reference_offset`` positions; ``calibrate``: each part's operating
    point calibrated on them), which are then not queried; ``half``: only the even or odd half of the
    rest. ``teach_from``: another set whose images teach them (its parts' meshes the same), every image
    of this one queried. ``truth``: each target's true pose is also checked as an estimate checks a
    candidate (refined from there and judged, ``truth_checked``): whether the verdict would take the truth
    if the search proposed it."""
    set_dir = set_dir_of(name)
    meta = read_meta(set_dir)
    gts = read_gt(set_dir)
    appearance: dict = {}
    teach = {"calibrate": calibrate, "offset": reference_offset}
    if references > 0 and teach_from is not None and set_dir_of(teach_from) != set_dir:
        appearance = taught(set_dir_of(teach_from), references, policy, **teach)
    elif references > 0:
        appearance = taught(set_dir, references, policy, **teach)
        halves = half_of(set_dir, references, reference_offset)
        gts = [g for g in gts if g["image"] in halves and half in ("all", halves[g["image"]])]
    if every_image > 1:  # every n-th image (all its gt lines: lmo_dev has several per image)
        images = sorted({g["image"] for g in gts})[::every_image]
        gts = [g for g in gts if g["image"] in set(images)]
    gts = gts[:limit] if limit else gts
    minfo: dict = {}
    recs = []
    for g in gts:
        bank = gt_bank(set_dir, g["model"])
        image = read_colour(set_dir / g["image"])
        intr = Intrinsics.from_K(np.asarray(g["K"], float))
        absent = bool(g.get("absent", False))
        dist = float(g["t_mm"][2]) if distance_given and not absent else None
        t0 = time.perf_counter()
        out = estimate(bank, image, intr, distance_mm=dist, min_score=min_score,
                       distance_range_mm=distance_range_mm,
                       appearance=appearance.get(g["model"]), policy=policy)
        ms = 1000 * (time.perf_counter() - t0)
        pose = (out.refined or out.coarse).pose if out.found else None
        mspd = float("inf")
        right_checked = None
        nearest_checked = float("inf")
        if not absent:
            info = load_model_info(set_dir, g["model"], meta, minfo)
            if pose is not None:
                mspd = mspd640(pose, g, info)
            checked = [(c, mspd640(c.refined.pose, g, info)) for c in out.checked]
            nearest_checked = min((m for _, m in checked), default=float("inf"))
            # the best-scoring checked candidate within RIGHT_PX (found or not): the verdict's part in recall
            right = [c for c, m in checked if m < RIGHT_PX]
            if right:
                best = max(right, key=lambda c: c.verdict.score)
                right_checked = {"score": best.verdict.score, "reason": best.verdict.reason}
        truth_checked = None if absent or not truth else _truth_checked(bank, image, intr, g, info,
                                                                       appearance.get(g["model"]),
                                                                       distance_mm=dist,
                                                                       distance_range_mm=distance_range_mm,
                                                                       policy=policy)
        recs.append({"image": g["image"], "model": g["model"], "absent": absent, "found": out.found,
                     "mspd640": mspd, "visible": float(g.get("visible_fraction", 0.0 if absent else 1.0)),
                     "reason": out.verdict.reason, "score": out.verdict.score, "ms": ms,
                     "evidence": out.verdict.evidence, "right_checked": right_checked,
                     "nearest_checked_px": nearest_checked, "truth_checked": truth_checked,
                     "t_mm": None if pose is None else [float(x) for x in pose.t_mm],
                     "t_true_mm": None if absent else [float(x) for x in g["t_mm"]]})
    return recs


def _truth_checked(bank, image: np.ndarray, intr: Intrinsics, g: dict, info, appearance, *,
                   distance_mm: float | None, distance_range_mm: tuple[float, float] | None,
                   policy: Policy = DEFAULT_POLICY) -> dict:
    """The true pose refined and judged as ``estimate`` judges a candidate, at the part's operating point:
    its score, reason, whether found, and where the refinement took it (MSPD)."""
    from service.vision import pipeline
    from service.vision.estimate.edges import to_grey_u8
    from service.vision.estimate.evidence import colour_frame
    from service.vision.geometry.camera import undistort_image
    from service.vision.geometry.frames import Pose

    appearance = pipeline.appearance_in_use(appearance)
    truth = Pose(np.asarray(g["R"], float), np.asarray(g["t_mm"], float))
    c = pipeline.check_candidate(bank, pipeline.PoseCandidate(truth, 0.0, 0.0), to_grey_u8(image),
                                 colour_frame(undistort_image(image, intr)), intr, distance_mm=distance_mm,
                                 distance_range_mm=pipeline.judged_range(distance_mm, distance_range_mm),
                                 min_score=policy.operating_point(appearance),
                                 n_channels=policy.search_params.n_channels, appearance=appearance,
                                 policy=policy)
    return {"score": c.verdict.score, "reason": c.verdict.reason, "found": c.verdict.found,
            "mspd640": mspd640(c.refined.pose, g, info)}


def summarise(recs: list[dict]) -> dict:
    found = [r for r in recs if r["found"]]
    right = [r for r in found if not r["absent"] and r["mspd640"] < RIGHT_PX]
    targets = [r for r in recs if not r["absent"] and r["visible"] >= MIN_VISIBLE]
    ms = np.array([r["ms"] for r in recs])
    return {"queries": len(recs), "found": len(found), "right": len(right), "wrong": len(found) - len(right),
            "recall5": _share(sum(r["found"] and r["mspd640"] < FINE_PX for r in targets), len(targets)),
            "recall20": _share(sum(r["found"] and r["mspd640"] < RIGHT_PX for r in targets), len(targets)),
            "precision": _share(len(right), len(found)),
            "p50": float(np.median(ms)), "p95": float(np.percentile(ms, 95)), "targets": len(targets)}


def _share(n: int, of: int) -> float:
    return n / of if of else float("nan")  # an absent set has no targets: no recall, not 0 %


def _cell(vals: list[float], fmt: str) -> str:
    if np.isnan(vals).all():  # in every run nothing to count (no target, or nothing found)
        return "-"
    if len(vals) == 1 or max(vals) == min(vals):
        return format(vals[0], fmt)
    return f"{format(float(np.mean(vals)), fmt)} ({format(min(vals), fmt)}-{format(max(vals), fmt)})"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sets", default="clutter,absent,paper,lmo_dev")
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--distance-given", action="store_true")
    ap.add_argument("--distance-range", type=lambda v: tuple(float(x) for x in v.split(",")), default=None,
                    help="LO,HI mm: the queries' distance range, as a cell that knows it gives it (default: "
                         "the service's, pipeline.DEFAULT_DISTANCE_RANGE_MM; the calibration keeps it)")
    ap.add_argument("--min-score", type=float, default=None)
    ap.add_argument("--every-image", type=int, default=1, help="every n-th image of each set (a first look)")
    ap.add_argument("--references", type=int, default=0,
                    help="teach each part's colours from this many of the set's images (bench/lib/teach.py)")
    ap.add_argument("--reference-offset", type=int, default=0,
                    help="with --references: move the reference images by this many positions")
    ap.add_argument("--teach-from", default=None,
                    help="with --references: teach from this set's images instead (e.g. absent2 taught from "
                         "clutter2's)")
    ap.add_argument("--half", default="all", choices=["all", "even", "odd"],
                    help="with --references: only this half of the other images")
    ap.add_argument("--uncalibrated", action="store_true",
                    help="with --references: the parts' operating points not calibrated on their reference "
                         "photos (as the service does at POST /references: pipeline.calibrate_appearance)")
    ap.add_argument("--per-image", action="store_true",
                    help="after the table, each set's targets per image by what became of them")
    ap.add_argument("--truth", action="store_true",
                    help="also check each target's true pose as a candidate (its score shows in --per-image)")
    add_policy_options(ap)
    a = ap.parse_args(argv)
    policy = policy_of(a)
    rows = []
    dump = {}
    for name in a.sets.split(","):
        all_recs = [run_set(name, limit=a.limit, distance_given=a.distance_given, min_score=a.min_score,
                            every_image=a.every_image, references=a.references, half=a.half,
                            teach_from=a.teach_from, distance_range_mm=a.distance_range,
                            truth=a.truth, policy=policy, calibrate=not a.uncalibrated,
                            reference_offset=a.reference_offset)
                    for _ in range(a.repeat)]
        dump[name] = {"runs": [summarise(recs) for recs in all_recs], "records": all_recs}
        for r in (r for recs in all_recs for r in recs if r["found"] and not r["mspd640"] < RIGHT_PX):
            print(f"wrong found: {name} {r['image']} {r['model']} MSPD {r['mspd640']:.1f} px, score "
                  f"{r['score']:.4f}", file=sys.stderr)
        for recs in all_recs:
            print(_checked_line(name, recs), file=sys.stderr)
            print(_depth_line(name, recs), file=sys.stderr)
        parts = [("", all_recs)]
        # each half too: the weights were fitted on the even one
        if a.references and a.half == "all" and a.teach_from in (None, name):
            halves = half_of(set_dir_of(name), a.references, a.reference_offset)
            parts += [(f", {h} half", [[r for r in recs if halves[r["image"]] == h] for recs in all_recs])
                      for h in ("even", "odd")]
        for suffix, recs_runs in parts:
            if not any(recs_runs):  # a half --every-image left without queries
                continue
            rows.append(_row(Path(name).name + suffix, [summarise(recs) for recs in recs_runs]))
            print(rows[-1], file=sys.stderr)
    dist = "given" if a.distance_given else "not given"
    print(f"\nDistance {dist}; MSPD at 640 px width; recall over targets >= {MIN_VISIBLE:.0%} visible.\n")
    print("| set | queries (targets) | found | right | wrong found | recall <5px | recall <20px | precision "
          "| latency p50 / p95 ms |")
    print("|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    if a.per_image:
        for name, d in dump.items():
            table = per_image_table(d["records"][0])
            if table:  # an absent set has no targets (its wrong answers are in the table above)
                print(f"\n{Path(name).name}, first run: targets per image by what became of them\n")
                print(table)
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    (OUT_DIR / "detection.json").write_text(json.dumps(dump, indent=1))
    return 0


def fate(rec: dict) -> str:
    """What became of one target query: found (right or wrong), a right pose checked and refused by the
    verdict, only a near miss checked (within NEAR_PX), or nothing checked near it (the proposals)."""
    if rec["found"]:
        return FOUND_RIGHT if not rec["absent"] and rec["mspd640"] < RIGHT_PX else FOUND_WRONG
    if rec.get("right_checked"):
        return REFUSED
    return NEAR_MISS if rec.get("nearest_checked_px", float("inf")) < NEAR_PX else NOT_PROPOSED


def per_image_table(recs: list[dict]) -> str:
    """One row per image: each target's part under its fate (a refused right pose with its score, a near
    miss with its distance; * = under OCCLUDED_BELOW visible; with ``truth_checked``, the true pose's own
    score and whether it passes), the counts per fate, and per fate how many truths pass; "" without
    targets."""
    by_image: dict[str, list[dict]] = {}
    for r in recs:
        if not r["absent"] and r["visible"] >= MIN_VISIBLE:
            by_image.setdefault(r["image"], []).append(r)
    if not by_image:
        return ""
    lines = ["| image | targets | " + " | ".join(FATES) + " |", "|---|---" + "|---" * len(FATES) + "|"]
    counts, truths = Counter(), Counter()
    for image, rows in by_image.items():
        cells: dict[str, list[str]] = {f: [] for f in FATES}
        for r in rows:
            f = fate(r)
            counts[f] += 1
            label = PART_NAMES.get(r["model"], r["model"]) + ("*" if r["visible"] < OCCLUDED_BELOW else "")
            if f == REFUSED:
                label += f" {r['right_checked']['score']:.3f}"
            elif f == NEAR_MISS:
                label += f" {r['nearest_checked_px']:.0f} px"
            t = r.get("truth_checked")
            if t and f != FOUND_RIGHT:
                label += f" (truth {t['score']:.3f}{', passes' if _truth_passes(t) else ''})"
                truths[f] += _truth_passes(t)
            cells[f].append(label)
        lines.append(f"| {Path(image).stem} | {len(rows)} | "
                     + " | ".join(", ".join(cells[f]) or "-" for f in FATES) + " |")
    lines.append(f"| **all** | {sum(counts.values())} | "
                 + " | ".join(f"**{counts[f]}**" for f in FATES) + " |")
    if any(r.get("truth_checked") for rows in by_image.values() for r in rows):
        lines += ["", "The true pose, refined from there, found right at the part's operating point: "
                  + ", ".join(f"{f} {truths[f]} of {counts[f]}" for f in FATES[1:])]
    return "\n".join(lines)


def _truth_passes(t: dict) -> bool:
    return bool(t["found"]) and t["mspd640"] < RIGHT_PX


def _checked_line(name: str, recs: list[dict]) -> str:
    """Of the targets not found right, how many had a right candidate checked (the verdict refused it:
    its scores and reasons) and how many had none (the proposals missed)."""
    missed = [r for r in recs if not r["absent"] and r["visible"] >= MIN_VISIBLE
              and not (r["found"] and r["mspd640"] < RIGHT_PX)]
    refused = [r["right_checked"] for r in missed if r.get("right_checked")]
    scores = np.array([c["score"] for c in refused])
    reasons = Counter(c["reason"] for c in refused)
    spread = (f", scores p10 / p50 / p90 {np.percentile(scores, 10):.3f} / {np.median(scores):.3f} / "
              f"{np.percentile(scores, 90):.3f}, {reasons.most_common()}"
              if len(scores) else "")
    return (f"{name}: {len(missed)} targets not found right: a right candidate checked and refused on "
            f"{len(refused)}{spread}; none checked on {len(missed) - len(refused)}")


def _depth_line(name: str, recs: list[dict]) -> str:
    """The right answers' depth against the truth's: MSPD hardly sees a pose a few percent too far."""
    q = np.array([r["t_mm"][2] / r["t_true_mm"][2] for r in recs
                  if r["found"] and not r["absent"] and r["mspd640"] < RIGHT_PX])
    if not len(q):
        return f"{name}: no right answer"
    p10, p50, p90 = np.percentile(q, [10, 50, 90])
    return (f"{name}: right answers' tz / true tz p10 / p50 / p90 {p10:.3f} / {p50:.3f} / {p90:.3f}, "
            f"within 2 % {np.mean(np.abs(q - 1) < 0.02):.0%} of {len(q)}")


def _row(name: str, runs: list[dict]) -> str:
    col = {k: [r[k] for r in runs] for k in runs[0]}
    cells = [name, f"{col['queries'][0]} ({col['targets'][0]})", _cell(col["found"], "d"),
             _cell(col["right"], "d"), f"**{_cell(col['wrong'], 'd')}**", _cell(col["recall5"], ".0%"),
             _cell(col["recall20"], ".0%"), _cell(col["precision"], ".0%"),
             f"{_cell(col['p50'], '.0f')} / {_cell(col['p95'], '.0f')}"]
    return "| " + " | ".join(cells) + " |"


if __name__ == "__main__":
    sys.exit(main())
