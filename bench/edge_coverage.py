"""How much of the true outline the edge detector sees: the fraction of the model's border points,
at the ground-truth pose, with an image edge of matching orientation within 3 px (the verification
score of ``refine.verify`` on the DT3 of the edges). The search cannot find what this misses.

    python bench/edge_coverage.py [--sets paper,clutter]

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
from bench.accuracy import DATA_DIR, load_bank, read_grey, read_gt  # noqa: E402
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
    a = ap.parse_args()
    print("| set | detector | n | coverage mean | min | p25 | ms p50 |")
    print("|---|---|---|---|---|---|---|")
    for name in a.sets.split(","):
        rows = read_gt(DATA_DIR / name)
        banks: dict = {}
        cov: dict[str, list[float]] = {k: [] for k in DETECTORS}
        ms: dict[str, list[float]] = {k: [] for k in DETECTORS}
        for g in rows:
            m = g["model"]
            if m not in banks:
                banks[m] = load_bank(m, DATA_DIR / "models" / f"{m}.stl", None)
            grey = read_grey(DATA_DIR / name / g["image"])
            intr = Intrinsics.from_K(np.array(g["K"]))
            pose = Pose(np.array(g["R"]), np.array(g["t_mm"]))
            border = border_points(banks[m], pose, intr, (grey.shape[1], grey.shape[0]))
            for k, make in DETECTORS.items():
                t0 = time.perf_counter()
                dtt = make(grey)
                ms[k].append((time.perf_counter() - t0) * 1000)
                cov[k].append(verify(border, pose, intr, dtt, score_px=SCORE_PX)[0])
        for k in DETECTORS:
            c = np.array(cov[k])
            print(f"| {name} | {k} | {len(c)} | {c.mean():.2f} | {c.min():.2f} | {np.quantile(c, 0.25):.2f} "
                  f"| {np.median(ms[k]):.0f} |")


if __name__ == "__main__":
    main()
