"""Region proposals' CPU per stage, the reference (``vision/reference/regions.py``: Python merging, one
region at a time) against the service's (``vision/estimate/regions.py``), frame by frame in one process,
and whether both give the same hierarchy and the same proposals.

Per query (gt line, absent ones too) both run on the same image: mean shift (``smooth``), linking
(``initial_regions``), region statistics (``region_stats``), merging (``merge_py`` / ``merge``),
matching (``propose_py`` / ``propose`` on that hierarchy, 30 proposals), then the first ``--n`` proposals
are refined on their outlines (``refine_on_boundary`` each; ``refine_all``, as ``region_proposals``
does). "Frames differing": the hierarchy, or the proposals or refined poses, not identical. CPU time is
``time.process_time`` (all this process's threads); the bank's silhouettes are made before timing;
freed memory stays mapped (``memory.keep_mapped``, as the service's warm-up sets it).

    python bench/region_speed.py --sets clutter2,absent2,lmo_dev:8 [--n 5] [--limit N]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.accuracy import (  # noqa: E402
    gt_bank,
    read_colour,
    read_gt,
)
from bench.detection import set_dir_of  # noqa: E402
from service.vision import memory  # noqa: E402
from service.vision.estimate import regions, segmentation  # noqa: E402
from service.vision.pipeline import DEFAULT_DISTANCE_RANGE_MM, DEFAULT_POLICY  # noqa: E402
from service.vision.reference import regions as ref  # noqa: E402

STAGES = ("mean shift", "linking", "stats", "merge", "matching", "refine", "total")


def queries(spec: str) -> tuple[str, Path, list[dict]]:
    name, _, every = spec.partition(":")
    set_dir = set_dir_of(name)
    gts = read_gt(set_dir)
    if every:
        images = set(sorted({g["image"] for g in gts})[::int(every)])
        gts = [g for g in gts if g["image"] in images]
    return name, set_dir, gts


def same_regions(a: segmentation.Regions, b: segmentation.Regions) -> bool:
    fields = ("labels", "children", "area", "bbox", "born", "died", "moments")
    return a.scale == b.scale and all(np.array_equal(getattr(a, f), getattr(b, f)) for f in fields)


def same_proposals(a: list, b: list) -> bool:
    def key(p) -> tuple:
        return p.region, p.iou, p.hyp.view, p.hyp.phi_deg, p.hyp.z_mm, tuple(p.hyp.uv)

    return [key(p) for p in a] == [key(q) for q in b]


def same_hyps(a: list, b: list) -> bool:
    return [(h.view, h.phi_deg, h.z_mm, tuple(h.uv)) for h in a] == [(h.view, h.phi_deg, h.z_mm, tuple(h.uv))
                                                                    for h in b]


def timed(f, *args, **kw):
    c0 = time.process_time()
    out = f(*args, **kw)
    return out, 1000 * (time.process_time() - c0)


def run_frame(impl: str, bank, image, K, n_refine: int) -> tuple[dict, segmentation.Regions, list, list]:
    t: dict[str, float] = {}
    (sc, lab), t["mean shift"] = timed(segmentation.smooth, image)
    (labels, n0, dh, dv), t["linking"] = timed(segmentation.initial_regions, lab)
    st, t["stats"] = timed(segmentation.region_stats, labels, n0, dh, dv)
    merge, propose = ((ref.merge_py, ref.propose_py) if impl == "ref"
                      else (segmentation.merge, regions.propose))
    reg, t["merge"] = timed(merge, labels, sc, st)
    (props, _), t["matching"] = timed(propose, bank, image, K, DEFAULT_DISTANCE_RANGE_MM, n_out=30, reg=reg)
    shape, first = image.shape[:2], props[:n_refine]
    if impl == "ref":
        params = DEFAULT_POLICY.search_params
        hs, t["refine"] = timed(lambda: [regions.refine_on_boundary(bank, r, reg, K, shape, params)
                                         for r in first])
    else:
        hs, t["refine"] = timed(regions.refine_all, bank, first, reg, K, shape, DEFAULT_POLICY.search_params)
    t["total"] = sum(t.values())
    return t, reg, props, hs


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sets", default="clutter2,absent2,lmo_dev:8", help="name[:every n-th image],...")
    ap.add_argument("--n", type=int, default=5,
                    help="proposals refined (a taught part's: Policy.region_proposals_taught)")
    ap.add_argument("--limit", type=int, default=None)
    a = ap.parse_args()
    memory.keep_mapped(memory.RESERVE_MB)  # freed buffers stay mapped, as in the service after its warm-up
    table = []
    for spec in a.sets.split(","):
        name, set_dir, gts = queries(spec)
        gts = gts[:a.limit] if a.limit else gts
        times: dict[str, list[dict]] = {"ref": [], "new": []}
        n_diff_reg = n_diff_prop = 0
        for qi, g in enumerate(gts):
            bank = gt_bank(set_dir, g["model"])
            regions.canonical_templates(bank, regions.silhouettes(bank))  # once per bank, not per frame
            image = read_colour(set_dir / g["image"])
            image = np.repeat(image[..., None], 3, axis=2) if image.ndim == 2 else image[..., :3]
            K = np.asarray(g["K"], float)
            if qi == 0:
                run_frame("new", bank, image, K, a.n)  # numba's first call loads the kernels
            order = ("ref", "new") if qi % 2 == 0 else ("new", "ref")
            out = {}
            for impl in order:
                t, reg, props, hs = run_frame(impl, bank, image, K, a.n)
                times[impl].append(t)
                out[impl] = (reg, props, hs)
            d_reg = not same_regions(out["ref"][0], out["new"][0])
            d_prop = not same_proposals(out["ref"][1], out["new"][1]) or \
                not same_hyps(out["ref"][2], out["new"][2])
            n_diff_reg += d_reg
            n_diff_prop += d_prop
            print(f"{name} {qi:3d} {g['image']:18s} {g['model']:9s} nodes {len(out['new'][0].area):6d} "
                  f"props {len(out['new'][1]):2d} diff reg {int(d_reg)} prop {int(d_prop)} | "
                  + " ".join(f"{s} {times['ref'][-1][s]:.0f}->{times['new'][-1][s]:.0f}" for s in STAGES),
                  flush=True)
        for s in STAGES:
            r = np.array([t[s] for t in times["ref"]])
            n = np.array([t[s] for t in times["new"]])
            table.append(f"| {name} ({len(gts)}) | {s} | {np.median(r):.1f} / {np.percentile(r, 95):.1f} "
                         f"| {np.median(n):.1f} / {np.percentile(n, 95):.1f} |")
        table.append(f"| {name} ({len(gts)}) | frames differing | hierarchy {n_diff_reg} "
                     f"| proposals {n_diff_prop} |")
    print("\n| set (queries) | stage | reference CPU ms p50 / p95 | service CPU ms p50 / p95 |")
    print("|---|---|---|---|")
    print("\n".join(table))


if __name__ == "__main__":
    main()
