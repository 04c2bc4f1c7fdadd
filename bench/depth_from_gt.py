"""Does the refinement's depth stick? Each gt line started from its truth moved along its line of sight
(t_mm x factor: the silhouette shrinks or grows about its centre, as a region proposal's does), refined
as the service refines a candidate (``pipeline.check.refine``), and the refined depth compared with the
truth's.

    python bench/depth_from_gt.py [--sets lmo_dev,paper] [--every 4] [--factors 0.94,1.06]
                                  [--variants service,line-only,gate6,region,region-then,service-depth]
                                  [--references N]

Per set, variant and start factor: the lines refined, the median and p10 / p90 of refined tz / true tz,
the share within 1 % and 2 % of the truth's depth, and the median MSPD (640 px). A variant is a way of
refining (``VARIANTS``); "service" is the edge refinement as it is.
"""

from __future__ import annotations

import argparse
import sys
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.accuracy import (  # noqa: E402
    DATA_DIR,
    MIN_VISIBLE,
    gt_bank,
    load_model_info,
    read_colour,
    read_gt,
    read_meta,
    stage_errors,
)
from service.vision.estimate import refine  # noqa: E402
from service.vision.estimate.contour_region import region_contour_refine  # noqa: E402
from service.vision.geometry.camera import Intrinsics  # noqa: E402
from service.vision.geometry.frames import Pose  # noqa: E402


def _edges(**consts):
    """The edge refinement (``refine.refine_pose``) with these module constants of refine.py set."""
    def run(bank, start: Pose, image, grey, intr) -> Pose:
        with _settings(consts):
            return refine.refine_pose(bank, start, grey, intr, None).pose
    return run


def _edges_line_only(bank, start: Pose, image, grey, intr) -> Pose:
    return refine.refine_pose(bank, start, grey, intr, None, residual="line").pose


def _outline(bank, start: Pose, image, grey, intr) -> Pose:
    """The colour outline alone (``contour_region``)."""
    return region_contour_refine(bank, start, image, intr)


def _outline_then_edges(bank, start: Pose, image, grey, intr) -> Pose:
    return _edges()(bank, _outline(bank, start, image, grey, intr), image, grey, intr)


def _edges_depth_from_outline(bank, start: Pose, image, grey, intr) -> Pose:
    """The edge refinement's pose, its depth from the colour outline."""
    pose = _edges()(bank, start, image, grey, intr)
    moved = _outline(bank, pose, image, grey, intr)
    return Pose(pose.R, pose.t_mm * (moved.t_mm[2] / pose.t_mm[2]))


@contextmanager
def _settings(consts: dict):
    old = {k: getattr(refine, k) for k in consts}
    for k, v in consts.items():
        setattr(refine, k, v)
    try:
        yield
    finally:
        for k, v in old.items():
            setattr(refine, k, v)


# name -> (bank, start pose, colour image, grey image, intrinsics) -> refined pose
VARIANTS = {
    "service": _edges(),
    "line-only": _edges_line_only,
    "gate6": _edges(LINE_GATE_PX=6.0),
    "region": _outline,
    "region-then": _outline_then_edges,
    "service-depth": _edges_depth_from_outline,
}


def run(set_name: str, every: int, factors: list[float], variants: list[str], limit: int | None,
        references: int = 0) -> list[dict]:
    set_dir = DATA_DIR / set_name
    meta = read_meta(set_dir)
    gts = [g for g in read_gt(set_dir)
           if not g.get("absent") and g.get("visible_fraction", 1.0) >= MIN_VISIBLE]
    images = sorted({g["image"] for g in gts})[::every]
    gts = [g for g in gts if g["image"] in set(images)][:limit]
    minfo: dict = {}
    rows = []
    if references:  # the images a --references run of bench/detection.py queries
        from bench.appearance import reference_images

        refs = set(reference_images(set_dir, references))
        gts = [g for g in gts if g["image"] not in refs]
    for g in gts:
        bank = gt_bank(set_dir, g["model"])
        image = read_colour(set_dir / g["image"])
        grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        intr = Intrinsics.from_K(np.asarray(g["K"], float))
        info = load_model_info(set_dir, g["model"], meta, minfo)
        truth = Pose(np.asarray(g["R"], float), np.asarray(g["t_mm"], float))
        for f in factors:
            start = Pose(truth.R, truth.t_mm * f)
            for v in variants:
                pose = VARIANTS[v](bank, start, image, grey, intr)
                e = stage_errors(pose, g, info, np.asarray(g["K"], float), int(g["width"]))
                rows.append({"variant": v, "factor": f, "ratio": float(pose.t_mm[2] / truth.t_mm[2]),
                             "mspd": e["mspd640_px"]})
    return rows


def table(set_name: str, rows: list[dict], variants: list[str], factors: list[float]) -> str:
    out = [f"{set_name}:", "| variant | start | lines | tz ratio p10 / p50 / p90 | within 1 % | within 2 % | "
           "MSPD p50 px |", "|---|---|---|---|---|---|---|"]
    for v in variants:
        for f in factors:
            rs = [r for r in rows if r["variant"] == v and r["factor"] == f]
            if not rs:
                continue
            q = np.array([r["ratio"] for r in rs])
            p10, p50, p90 = np.percentile(q, [10, 50, 90])
            out.append(f"| {v} | x {f:.2f} | {len(rs)} | {p10:.3f} / {p50:.3f} / {p90:.3f} | "
                       f"{np.mean(np.abs(q - 1) < 0.01):.0%} | {np.mean(np.abs(q - 1) < 0.02):.0%} | "
                       f"{np.median([r['mspd'] for r in rs]):.1f} |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sets", default="lmo_dev,paper")
    ap.add_argument("--every", type=int, default=4, help="every n-th image of each set")
    ap.add_argument("--factors", default="0.94,1.06")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--references", type=int, default=0,
                    help="leave out the reference images of bench/detection.py --references N")
    a = ap.parse_args(argv)
    factors = [float(x) for x in a.factors.split(",")]
    variants = a.variants.split(",")
    for s in a.sets.split(","):
        rows = run(s, a.every, factors, variants, a.limit, a.references)
        print(table(s, rows, variants, factors), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
