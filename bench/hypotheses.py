"""Proposals and their evidence, per query, cached: the data the verdict is fitted and judged on.

For every query (one gt line: an image and a model) of a set it runs the proposal engine (edges and
the coarse search, with many hypotheses kept) once and caches the hypotheses with their MSPD against
the ground truth in ``bench/out/hyps/<set>.pkl``; ``features`` then computes every hypothesis's
evidence (refined or not) so a verdict can be fitted without re-running the search.

Usage:
  python bench/hypotheses.py proposals --set clutter [--limit N] [--data DIR]
  python bench/hypotheses.py recall --set clutter          # is the truth among the proposals at all?
  python bench/hypotheses.py features --set clutter        # each hypothesis refined and checked
  python bench/hypotheses.py truths --set clutter          # the same from near the ground truth
  python bench/hypotheses.py reevidence --set clutter      # the colour evidence again at the refined poses
"""

from __future__ import annotations

import argparse
import os
import pickle
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.lib.data import (  # noqa: E402
    RIGHT_PX,
    gt_bank,
    load_model_info,
    read_colour,
    read_gt,
    read_meta,
    set_dir_of,
    stage_errors,
)
from service.vision.geometry.camera import Intrinsics  # noqa: E402
from service.vision.geometry.frames import Pose  # noqa: E402

OUT = ROOT / "bench" / "out" / "hyps"


def queries(set_dir: Path, limit: int | None) -> list[dict]:
    gts = read_gt(set_dir)
    return gts[:limit] if limit else gts


def proposals(set_dir: Path, *, limit: int | None, distance_given: bool, params=None,
              regions: int = 0) -> list[dict]:
    """``regions`` > 0: also the search's second pass (the level-A peaks' other templates) and that many
    region proposals (``propose``'s ``n_regions``), appended after the first pass's hypotheses with
    their ``source`` ("second", "regions"): the pipeline checks them only when the first pass fails."""
    from service.vision.geometry.camera import undistort_image
    from service.vision.pipeline import propose

    meta = read_meta(set_dir)
    minfo: dict = {}
    recs = []
    for i, g in enumerate(queries(set_dir, limit)):
        bank = gt_bank(set_dir, g["model"])
        image = read_colour(set_dir / g["image"])
        intr = Intrinsics.from_K(np.asarray(g["K"], float))
        dist = float(g["t_mm"][2]) if distance_given and not g.get("absent") else None
        t0 = time.perf_counter()
        deferred: list = []
        cands, _, timing = propose(bank, image, intr, distance_mm=dist, params=params,
                                   deferred=deferred if regions else None,
                                   colour=undistort_image(image, intr) if regions else None,
                                   n_regions=regions)
        sources = ["first"] * len(cands)
        for later in deferred:
            more = later()
            name = "regions" if later.func.__name__ == "from_regions" else "second"
            cands, sources = cands + more, sources + [name] * len(more)
        wall = 1000 * (time.perf_counter() - t0)
        info = load_model_info(set_dir, g["model"], meta, minfo)
        hyps = []
        for c, source in zip(cands, sources, strict=True):
            e = {} if g.get("absent") else stage_errors(c.pose, g, info, np.asarray(g["K"], float),
                                                        int(g["width"]))
            hyps.append({"R": c.pose.R, "t": c.pose.t_mm, "cost": c.cost, "score": c.score,
                         "mspd640": e.get("mspd640_px", float("inf")), "source": source})
        recs.append({"i": i, "g": g, "hyps": hyps, "wall_ms": wall, "timing": timing})
        best = min((h["mspd640"] for h in hyps), default=float("inf"))
        print(f"{i:4d} {g['image']} {g['model']:9s} n={len(hyps):2d} best_mspd={best:7.1f} "
              f"rank0={hyps[0]['mspd640'] if hyps else float('inf'):7.1f} {wall:6.0f} ms", file=sys.stderr)
    return recs


TRUTH_NOISE_DEG, TRUTH_NOISE_MM = 2.0, 3.0  # a truth hypothesis starts this far from the ground truth


def truth_hypotheses(recs: list[dict], seed: int = 0) -> list[dict]:
    """The records with their hypotheses replaced by one near the ground truth (rank -1): the search
    rarely proposes the truth in clutter, so the verdict's fit sees right poses from these."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    out = []
    for r in recs:
        g = r["g"]
        if g.get("absent"):
            continue
        dR = Rotation.from_rotvec(rng.normal(size=3) * np.radians(TRUTH_NOISE_DEG) / np.sqrt(3)).as_matrix()
        dt = rng.normal(size=3) * TRUTH_NOISE_MM / np.sqrt(3)
        h = {"R": dR @ np.asarray(g["R"], float), "t": np.asarray(g["t_mm"], float) + dt,
             "cost": float("nan"), "score": float("nan"), "mspd640": float("nan")}
        out.append(r | {"hyps": [h], "truth": True})
    return out


def features(set_dir: Path, recs: list[dict], *, max_refine: int = 12) -> list[dict]:
    """Per hypothesis, what the pipeline's verdict reads: the hypothesis refined and checked exactly as
    an estimate checks it (``pipeline.check_candidate``), with the refined pose's MSPD to the truth."""
    from service.vision.estimate.edges import to_grey_u8
    from service.vision.estimate.evidence import colour_frame
    from service.vision.geometry.camera import undistort_image
    from service.vision.pipeline import PoseCandidate, check_candidate

    meta = read_meta(set_dir)
    minfo: dict = {}
    rows = []
    for r in recs:
        g = r["g"]
        bank = gt_bank(set_dir, g["model"])
        image = read_colour(set_dir / g["image"])
        grey = to_grey_u8(image)
        intr = Intrinsics.from_K(np.asarray(g["K"], float))
        frame = colour_frame(undistort_image(image, intr))
        info = load_model_info(set_dir, g["model"], meta, minfo)
        seen: dict[str, int] = {}
        for j, h in enumerate(r["hyps"]):
            # the first ``max_refine`` of each source (the second pass and the regions come after)
            seen[h.get("source", "first")] = seen.get(h.get("source", "first"), 0) + 1
            if seen[h.get("source", "first")] > max_refine:
                continue
            cand = PoseCandidate(Pose(np.asarray(h["R"]), np.asarray(h["t"])), h["cost"], h["score"])
            c = check_candidate(bank, cand, grey, frame, intr, distance_mm=None, distance_range_mm=None,
                                min_score=None, n_channels=16)
            m1 = float("inf") if g.get("absent") else stage_errors(
                c.refined.pose, g, info, np.asarray(g["K"], float), int(g["width"]))["mspd640_px"]
            rows.append({"q": r["i"], "rank": -1 if r.get("truth") else j, "absent": bool(g.get("absent")),
                         "source": "truth" if r.get("truth") else h.get("source", "first"),
                         "image": g["image"], "model": g["model"],
                         "vis": float(g.get("visible_fraction", 0.0)), "mspd0": h["mspd640"], "mspd1": m1,
                         "ev": c.verdict.evidence, "R1": c.refined.pose.R, "t1": c.refined.pose.t_mm})
        print(f"{r['i']:4d} {g['image']} {g['model']}", file=sys.stderr)
    return rows


def reevidence(set_dir: Path, rows: list[dict]) -> list[dict]:
    """The feature rows with the colour evidence recomputed at their refined poses (``R1`` / ``t1``):
    no search, no refinement, so a change of ``evidence`` is measured in seconds; ``edge_support`` and
    ``unexplained`` (the refinement's) are kept."""
    from service.vision.estimate.evidence import colour_frame, evidence
    from service.vision.geometry.camera import undistort_image

    gts = {(g["image"], g["model"]): g for g in read_gt(set_dir)}
    frames: dict = {}
    out = []
    for r in rows:
        g = gts[(r["image"], r["model"])]
        intr = Intrinsics.from_K(np.asarray(g["K"], float))
        if r["image"] not in frames:
            frames.clear()
            frames[r["image"]] = colour_frame(undistort_image(read_colour(set_dir / r["image"]), intr))
        ev = evidence(gt_bank(set_dir, g["model"]), Pose(np.asarray(r["R1"]), np.asarray(r["t1"])), intr,
                      frames[r["image"]]).as_dict()
        out.append(r | {"ev": r["ev"] | ev})
    return out


def cache_path(set_name: str, tag: str) -> Path:
    return OUT / f"{Path(set_name).name}-{tag}.pkl"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("cmd", choices=["proposals", "recall", "features", "truths", "reevidence"])
    ap.add_argument("--set", required=True)
    ap.add_argument("--data", type=Path, default=None)
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--distance-given", action="store_true")
    ap.add_argument("--tag", default="default")
    ap.add_argument("--regions", type=int, default=0,
                    help="also the second pass and this many region proposals (proposals)")
    ap.add_argument("--max-refine", type=int, default=12, help="hypotheses refined per query (features)")
    a = ap.parse_args(argv)
    set_dir = set_dir_of(a.set, a.data)
    path = cache_path(a.set, a.tag + ("-dist" if a.distance_given else ""))
    if a.cmd == "proposals":
        from service.vision.estimate.search import SearchParams

        wide = SearchParams(n_peaks=30, n_polish=12, peak_accept_ratio=3.0)
        recs = proposals(set_dir, limit=a.limit, distance_given=a.distance_given, params=wide,
                         regions=a.regions)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(pickle.dumps(recs))
    if a.cmd == "reevidence":  # both feature files of the set, rewritten in place
        for suffix in ("-features.pkl", "-truth-features.pkl"):
            fpath = path.with_name(path.stem + suffix)
            if fpath.exists():
                rows = reevidence(set_dir, pickle.loads(fpath.read_bytes()))
                fpath.write_bytes(pickle.dumps(rows))
                print(f"{len(rows)} rows re-evidenced -> {fpath}")
        return 0
    recs = pickle.loads(path.read_bytes())
    if a.cmd in ("features", "truths"):
        rows = features(set_dir, recs if a.cmd == "features" else truth_hypotheses(recs),
                        max_refine=a.max_refine)
        suffix = "-features.pkl" if a.cmd == "features" else "-truth-features.pkl"
        fpath = path.with_name(path.stem + suffix)
        fpath.write_bytes(pickle.dumps(rows))
        print(f"{len(rows)} rows -> {fpath}")
        return 0
    ev = [r for r in recs if not r["g"].get("absent") and r["g"].get("visible_fraction", 1) >= 0.5]
    for k in (1, 3, 5, 10, 20, 40):
        hit = sum(any(h["mspd640"] < RIGHT_PX for h in r["hyps"][:k]) for r in ev)
        print(f"truth (MSPD<{RIGHT_PX:.0f}px) in top {k:2d}: {hit}/{len(ev)}")
    w = np.array([r["wall_ms"] for r in recs])
    print(f"proposal time p50 {np.median(w):.0f} ms, p95 {np.percentile(w, 95):.0f} ms; "
          f"hypotheses per query {np.mean([len(r['hyps']) for r in recs]):.1f}")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    sys.exit(main())
