"""Why the region engine misses the truth, per query (issue #14 clutter; session 14 diagnostic).

For each query (targets at least half visible) the ground-truth pose's silhouette is rendered (full
resolution, the project's rasteriser) and shrunk to the segmentation's working size. Occluders are not
rendered: the visible mask V is approximated from the full silhouette S and the gt's
``visible_fraction`` v, assuming a node covers none of the hidden part (an occluder is not the part's
colour): IoU(N, V) ~ |N & S| / (|N| + v |S| - |N & S|). Every node of the hierarchy is scored at once
(its intersection with S is a range sum in the hierarchy's leaf order), and the best node is followed
through ``propose``'s gates:

    a  segmentation never forms the part's region (best node visible-IoU < 0.6), with why:
       "merged" (the best node spills outside S: precision < 0.7), "split" (it holds < 70 % of V)
    b  the region exists but a gate drops it: area range, border, SHAPE_GATE, N_REGIONS (contrast rank),
       look-alike gate
    c  it survives but no proposal within 20 px is among the first 12 (template fit wrong / ranked out)
    d  proposed among 12 (raw) but refinement on the region outline goes astray (> 20 px)
    ok proposed and refined within 20 px among 12

    python bench/region_diagnose.py --set clutter
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.accuracy import gt_bank, load_model_info  # noqa: E402
from bench.region_proposals import RIGHT_PX, mspds, read_bgr, set_args  # noqa: E402
from bench.stages import target_queries  # noqa: E402
from service.vision.estimate import regions, segmentation  # noqa: E402
from service.vision.geometry.frames import Pose  # noqa: E402
from service.vision.geometry.render import rasterise_roi  # noqa: E402
from service.vision.pipeline import DEFAULT_DISTANCE_RANGE_MM, DEFAULT_POLICY  # noqa: E402

N_KEEP = 12


def truth_mask(bank, g: dict) -> np.ndarray:
    W, H = int(g["width"]), int(g["height"])
    pose = Pose(np.asarray(g["R"], float), np.asarray(g["t_mm"], float))
    _, face, (u0, v0) = rasterise_roi(bank.vertices_mm, bank.faces, pose, np.asarray(g["K"], float), (W, H))
    m = np.zeros((H, W), np.uint8)
    m[v0:v0 + face.shape[0], u0:u0 + face.shape[1]] = face >= 0
    return m


def node_scores(reg: segmentation.Regions, S_w: np.ndarray, v: float) -> tuple[np.ndarray, np.ndarray]:
    """(every node's |N & S| in working px, its approximate IoU with the visible mask)."""
    pos, span = reg.leaf_ranges()
    n_leaf = int(span[:, 1].max())
    hist = np.bincount(pos[S_w > 0], minlength=n_leaf)
    cs = np.concatenate([[0], np.cumsum(hist)])
    inter = (cs[span[:, 1]] - cs[span[:, 0]]).astype(float)
    vis = v * float(S_w.sum())
    return inter, inter / np.maximum(reg.area + vis - inter, 1e-9)


def gate_of(bank, reg, K, c: int) -> str:
    """Which of ``propose``'s gates drops node ``c`` ('' if none): ``regions.candidate_stages``."""
    st = regions.candidate_stages(regions.silhouettes(bank), reg, K, bank, DEFAULT_DISTANCE_RANGE_MM)
    if c not in st.sized:
        return "area"
    if c not in st.framed:
        return "border"
    if c not in st.shaped:
        return "shape"
    if c not in st.ranked:
        rank = int(np.flatnonzero(st.shaped[np.argsort(-reg.died[st.shaped], kind="stable")] == c)[0])
        return f"n_regions(rank {rank})"
    return ""


def run(a) -> None:
    set_dir, meta, gts = target_queries(a)
    minfo: dict = {}
    counts: dict[str, int] = {}
    print("| image | part | visible | best node vIoU | node precision / recall(V) | class | why |")
    print("|---|---|---|---|---|---|---|")
    for g in gts:
        bank = gt_bank(set_dir, g["model"])
        info = load_model_info(set_dir, g["model"], meta, minfo)
        image = read_bgr(set_dir / g["image"])
        K = np.asarray(g["K"], float)
        v = float(g.get("visible_fraction", 1.0))
        reg = segmentation.segment(image)
        h, w = reg.labels.shape
        S = truth_mask(bank, g)
        S_w = (cv2.resize(S.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) > 0.5).astype(np.uint8)
        inter, viou = node_scores(reg, S_w, v)
        c = int(np.argmax(viou))
        prec = inter[c] / reg.area[c]
        rec = inter[c] / max(v * S_w.sum(), 1)
        # the engine's own proposals, gate on (service) and off (what the gate removes)
        props, _ = regions.propose(bank, image, K, DEFAULT_DISTANCE_RANGE_MM, n_out=N_KEEP, reg=reg)
        m_raw = mspds(bank, [p.hyp for p in props], K, g, info)
        hit = [i for i, m in enumerate(m_raw) if m < RIGHT_PX]
        why = ""
        if hit:
            hs = [regions.refine_on_boundary(bank, p, reg, K, image.shape[:2], DEFAULT_POLICY.search_params)
                  for p in props]
            m_ref = mspds(bank, hs, K, g, info)
            cls = "ok" if any(m < RIGHT_PX for m in m_ref) else "d"
            why = f"raw rank {hit[0]}"
        elif viou[c] < 0.6:
            cls = "a"
            why = "merged with surroundings" if prec < 0.7 else "split (shading / occluder)" \
                if rec < 0.7 else "partly merged and split"
        else:
            gate = gate_of(bank, reg, K, c)
            if gate:
                cls, why = "b", gate
            else:
                regions.LOOKALIKE_GATE = False
                try:
                    p_all, _ = regions.propose(bank, image, K, DEFAULT_DISTANCE_RANGE_MM, n_out=300, reg=reg)
                finally:
                    regions.LOOKALIKE_GATE = True
                m_all = mspds(bank, [p.hyp for p in p_all], K, g, info)
                r_all = [i for i, m in enumerate(m_all) if m < RIGHT_PX]
                mine = [p for p in p_all if p.region == c]
                if r_all and r_all[0] < N_KEEP:
                    cls, why = "b", f"look-alike (ungated rank {r_all[0]})"
                elif r_all:
                    whose = "own" if p_all[r_all[0]].region == c else "other"
                    cls, why = "c", f"ranked {r_all[0]} of 300 (region {whose})"
                else:
                    best_own = min((m for p, m in zip(p_all, m_all, strict=True) if p.region == c),
                                   default=np.inf)
                    cls = "c"
                    why = (f"fit wrong (own region's best mspd {best_own:.0f} px, "
                           f"{len(mine)} fits, best IoU {max((p.iou for p in mine), default=0):.2f})")
        counts[cls] = counts.get(cls, 0) + 1
        print(f"| {Path(g['image']).name} | {g['model']} | {v:.2f} | {viou[c]:.2f} | {prec:.2f} / {rec:.2f} "
              f"| {cls} | {why} |", flush=True)
    print(f"\n{a.set}: {len(gts)} queries; classes "
          + ", ".join(f"{k} {n}" for k, n in sorted(counts.items())))


def main() -> None:
    run(set_args(argparse.ArgumentParser()).parse_args())


if __name__ == "__main__":
    main()
