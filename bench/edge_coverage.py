"""How much of the true outline the edge detector sees: the fraction of the model's border points,
at the ground-truth pose, with an image edge of matching orientation within 3 px (the verification
score of ``refine.verify`` on the DT3 of the edges). The search cannot find what this misses.

    python bench/edge_coverage.py [--sets paper,clutter]
    python bench/edge_coverage.py --sets lmo_dev --per-part --min-visible 0.9 --detectors pipeline

``--per-part``: one row per model of each set (its own meshes, ``models/`` beside ``gt.jsonl``).

Detectors: LSD as the pipeline runs it (half resolution), LSD at full resolution, and Canny on the
half-size image (a polarity-free reference; not used by the pipeline).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # `python bench/edge_coverage.py`
from bench.lib.data import DATA_DIR, PART_NAMES, gt_bank, load_bank, read_grey, read_gt  # noqa: E402
from service.vision.estimate.chamfer import DEFAULT_TAU_PX, distance_tensor, distance_tensor_from_edges  # noqa: E402
from service.vision.estimate.edges import channel_of, detect_segments  # noqa: E402
from service.vision.estimate.refine import border_points, verify  # noqa: E402
from service.vision.geometry.camera import Intrinsics  # noqa: E402
from service.vision.geometry.frames import Pose  # noqa: E402

SCALE = 0.5  # the pipeline's DT3 grid
SCORE_PX = 3.0


def canny_dt3(grey: np.ndarray, low: int = 20, high: int = 40):
    img = cv2.resize(grey, None, fx=SCALE, fy=SCALE, interpolation=cv2.INTER_AREA)
    v, u = np.nonzero(cv2.Canny(img, low, high, L2gradient=True))
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    masks = np.zeros((16,) + img.shape, np.uint8)
    masks[channel_of(np.mod(np.arctan2(gy[v, u], gx[v, u]) + np.pi / 2, np.pi), 16), v, u] = 1
    return distance_tensor_from_edges(masks, tau_px=DEFAULT_TAU_PX * SCALE, scale=SCALE)


DETECTORS = {
    "LSD 1/2 (pipeline)": lambda g: distance_tensor(detect_segments(g), scale=SCALE),
    "LSD 1/1": lambda g: distance_tensor(detect_segments(g, scale=1.0), scale=SCALE),
    "Canny 1/2": canny_dt3,
}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sets", default="paper,clutter")
    ap.add_argument("--per-part", action="store_true", help="a row per model (the set's own meshes)")
    ap.add_argument("--min-visible", type=float, default=0.0, help="only gt lines at least this visible")
    ap.add_argument("--detectors", default="all", choices=["all", "pipeline"])
    a = ap.parse_args()
    detectors = DETECTORS if a.detectors == "all" else dict(list(DETECTORS.items())[:1])
    print("| set | part | detector | n | coverage mean | min | p25 | p50 | p75 | ms p50 |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name in a.sets.split(","):
        rows = [g for g in read_gt(DATA_DIR / name) if g.get("visible_fraction", 1.0) >= a.min_visible]
        banks: dict = {}
        cov: dict[tuple[str, str], list[float]] = {}
        ms: dict[str, list[float]] = {}  # per detector: an image's edges serve every part in it
        image_edges: tuple = (None, {})  # lmo_dev has several gt lines per image: its edges once
        for g in rows:
            m = g["model"]
            if m not in banks:
                banks[m] = gt_bank(DATA_DIR / name, m) if a.per_part else \
                    load_bank(m, DATA_DIR / "models" / f"{m}.stl", None)
            grey = read_grey(DATA_DIR / name / g["image"])
            intr = Intrinsics.from_K(np.array(g["K"]))
            pose = Pose(np.array(g["R"]), np.array(g["t_mm"]))
            border = border_points(banks[m], pose, intr, (grey.shape[1], grey.shape[0]))
            if image_edges[0] != g["image"]:
                image_edges = (g["image"], {})
            part = PART_NAMES.get(m, m) if a.per_part else "all"
            for k, make in detectors.items():
                if k not in image_edges[1]:
                    t0 = time.perf_counter()
                    image_edges[1][k] = make(grey)
                    ms.setdefault(k, []).append((time.perf_counter() - t0) * 1000)
                dtt = image_edges[1][k]
                cov.setdefault((part, k), []).append(verify(border, pose, intr, dtt, score_px=SCORE_PX)[0])
        for (part, k), c in sorted(cov.items()):
            c = np.array(c)
            q25, q50, q75 = np.quantile(c, [0.25, 0.5, 0.75])
            print(f"| {name} | {part} | {k} | {len(c)} | {c.mean():.2f} | {c.min():.2f} | {q25:.2f} "
                  f"| {q50:.2f} | {q75:.2f} | {np.median(ms[k]):.0f} |")


if __name__ == "__main__":
    main()
