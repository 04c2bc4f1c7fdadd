"""Why a proposed truth is not found: per query, the candidates near the truth, their refinement and verdict.

For every query of a set (one gt line, the part visible) it runs the search as ``pipeline.estimate``
does with the service's settings (both passes of the 6D search: the first pass's candidates, then the
peaks' other templates), and checks every candidate (``pipeline.check_candidate``, the refinement and
the evidence of an estimate), not only the ``N_VERIFY`` an estimate checks. A query is printed when a
candidate is near the truth (coarse MSPD < 20 px at 640 px) or its refinement lands there, with:

- ``pass/rank``: the candidate's pass (1, 2) and rank in it; ``chk``: whether an estimate checks it
  (rank < ``N_VERIFY``, and pass 2 only when pass 1 found nothing);
- ``m0`` / ``m1``: the MSPD of the coarse candidate and of the refined pose (px, 640 px);
- the verification score, the verdict's reason and its evidence, and the score's terms;
- per evidence value, its percentile among the *wrong* hypotheses of the cached feature rows
  (``bench/hypotheses.py features``; ``--hyps`` names the directory) of the reference sets;
- the truth pose itself checked the same way (``truth``), and the best-scoring wrong candidate.

    python bench/rejected_truths.py --set clutter2 [--images 0003,0017] [--hyps /work/main/bench/out/hyps]
"""

from __future__ import annotations

import argparse
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
from service.vision.estimate.edges import to_grey_u8  # noqa: E402
from service.vision.estimate.evidence import colour_frame  # noqa: E402
from service.vision.estimate.refine import refine_pose  # noqa: E402
from service.vision.estimate.verdict import FEATURES, WEIGHTS  # noqa: E402
from service.vision.geometry.camera import Intrinsics, undistort_image  # noqa: E402
from service.vision.geometry.frames import Pose  # noqa: E402
from service.vision.pipeline import (  # noqa: E402
    DEFAULT_DISTANCE_RANGE_MM,
    DEFAULT_POLICY,
    Checked,
    PoseCandidate,
    RefinedPose,
    check_candidate,
    judge,
    propose,
    search_params,
)

N_VERIFY = DEFAULT_POLICY.n_verify  # candidates an estimate checks per pass

_evidence.VISIBLE_PART = True  # the visible part's evidence is what these tables study too

RIGHT_PX = 20.0
REF_SETS = ("clutter", "clutter2", "absent", "absent2", "lmo_dev", "paper")
SHOW = ("edge_support", "unexplained", "colour_edge", "polarity", "region", "region_low", "region_global",
        "coherence", "shading_r2", "shading_std")


def wrong_rows(hyps_dir: Path) -> dict[str, np.ndarray]:
    """Per evidence name, its values over the wrong hypotheses of the reference sets' cached features."""
    vals: dict[str, list[float]] = {k: [] for k in FEATURES}
    used = []
    for name in REF_SETS:
        for p in sorted(hyps_dir.glob(f"{name}-default-features.pkl")):
            rows = pickle.loads(p.read_bytes())
            used.append(f"{name}:{len(rows)}")
            for r in rows:
                if r["rank"] < 0 or (not r["absent"] and r["mspd1"] < RIGHT_PX):
                    continue
                ev = r.get("ev") or ({k: r.get(f"{k}1", r.get(k)) for k in FEATURES}
                                     | {"edge_support": r.get("rscore")})  # the older cache's columns
                for k in FEATURES:
                    if ev.get(k) is not None:
                        vals[k].append(float(ev[k]))
    print("wrong-hypothesis reference rows:", ", ".join(used) or "none")
    return {k: np.asarray(v) for k, v in vals.items()}


def pct(ref: dict[str, np.ndarray], k: str, v: float) -> str:
    a = ref.get(k)
    if a is None or not len(a):
        return "  -"
    return f"{100.0 * float(np.mean(a < v)):3.0f}"


def terms(ev: dict) -> str:
    return " ".join(f"{k}={w * float(ev[k]):+.2f}" for k, w in WEIGHTS.items() if k != "bias")


def line(tag: str, m0: float, m1: float, v, ref) -> str:
    ev = v.evidence
    s = " ".join(f"{k[:9]}={ev[k]:.2f}(p{pct(ref, k, ev[k]).strip()})" for k in SHOW)
    return (f"  {tag:10s} m0={m0:6.1f} m1={m1:6.1f} score={v.score:.3f} {v.reason:16s} | {s} | "
            f"{terms(ev)} bias={WEIGHTS['bias']:+.2f}")


def run(a) -> None:
    set_dir = Path(a.set) if Path(a.set).is_dir() else DATA_DIR / a.set
    ref = wrong_rows(Path(a.hyps))
    meta = read_meta(set_dir)
    minfo: dict = {}
    gts = [g for g in read_gt(set_dir) if not g.get("absent") and g.get("visible_fraction", 1) >= 0.5]
    if a.images:
        keep = a.images.split(",")
        gts = [g for g in gts if any(k in g["image"] for k in keep)]
    p = search_params(1)
    for g in gts[:a.limit]:
        bank = gt_bank(set_dir, g["model"])
        info = load_model_info(set_dir, g["model"], meta, minfo)
        image = read_colour(set_dir / g["image"])
        grey = to_grey_u8(image)
        K = np.asarray(g["K"], float)
        intr = Intrinsics.from_K(K)
        frame = colour_frame(undistort_image(image, intr))

        def mspd(pose: Pose) -> float:
            return stage_errors(pose, g, info, K, int(g["width"]))["mspd640_px"]  # noqa: B023

        second: list = []
        cands, _, _ = propose(bank, grey, intr, distance_range_mm=DEFAULT_DISTANCE_RANGE_MM, params=p,
                              deferred=second)
        more = second[0]() if second else []
        kw = dict(distance_mm=None, distance_range_mm=DEFAULT_DISTANCE_RANGE_MM, min_score=None,
                  n_channels=p.n_channels)
        rows = []
        for pas, cs in ((1, cands), (2, more)):
            for j, c in enumerate(cs[:a.max_check]):
                ch = check_candidate(bank, c, grey, frame, intr, **kw)
                rows.append((pas, j, mspd(c.pose), mspd(ch.refined.pose), ch))
        pass1_found = any(r[4].verdict.found for r in rows if r[0] == 1 and r[1] < N_VERIFY)
        near = [r for r in rows if min(r[2], r[3]) < RIGHT_PX]
        if not near and not a.all:
            continue
        gt = Pose(np.asarray(g["R"], float), np.asarray(g["t_mm"], float))
        tc = check_candidate(bank, PoseCandidate(gt, 0.0, 0.0), grey, frame, intr, **kw)
        print(f"\n{g['image']} {g['model']} vis={g.get('visible_fraction', 1):.2f} "
              f"candidates {len(cands)}+{len(more)}")
        for pas, j, m0, m1, ch in near:
            chk = j < N_VERIFY and (pas == 1 or not pass1_found)
            print(line(f"P{pas}/{j:02d} {'chk' if chk else '---'}", m0, m1, ch.verdict, ref))
            # What the refinement itself reached, kept or not (``check.refine`` keeps it only when its
            # full-resolution score reaches the candidate's coarse score).
            r = refine_pose(bank, ch.candidate.pose, grey, intr, None, distance_mm=None,
                            n_channels=p.n_channels)
            rc = judge(bank, Checked(ch.candidate, RefinedPose(r.pose, float(r.cost), float(r.score),
                                                               int(r.iterations), float(r.inlier_ratio)),
                                     ch.verdict), frame, intr, edge_support=float(r.score),
                       unexplained=r.unexplained, distance_range_mm=DEFAULT_DISTANCE_RANGE_MM, min_score=None)
            print(f"    refine_pose alone: MSPD {mspd(r.pose):.1f}, full-res score {r.score:.3f} vs the "
                  f"candidate's coarse score {ch.candidate.score:.3f} -> "
                  f"{'above' if r.score >= ch.candidate.score else 'below'}")
            print(line("  if kept", m0, mspd(r.pose), rc.verdict, ref))
        print(line("truth", 0.0, mspd(tc.refined.pose), tc.verdict, ref))
        wrong = [r for r in rows if r[3] >= RIGHT_PX]
        if wrong:
            pas, j, m0, m1, ch = max(wrong, key=lambda r: r[4].verdict.score)
            print(line(f"bestwr P{pas}/{j:02d}", m0, m1, ch.verdict, ref))
        sys.stdout.flush()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--set", default="clutter2")
    ap.add_argument("--images", default=None, help="comma-separated substrings of image names")
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--max-check", type=int, default=12, help="candidates checked per pass")
    ap.add_argument("--all", action="store_true", help="print queries with no candidate near the truth too")
    ap.add_argument("--hyps", default=str(ROOT / "bench" / "out" / "hyps"))
    run(ap.parse_args(argv))
    return 0


if __name__ == "__main__":
    sys.exit(main())
