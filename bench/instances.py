"""Several instances: per-instance recall, wrong instances and latency, on seeded rendered scenes.

Each scene holds 2-6 copies of an L-shaped block (no symmetry; 80 x 60 x 40 mm) rendered with the
project's rasteriser (``render_shaded``) at random non-overlapping places of a 640 x 480 image, 400-470
mm away, tilted 20-45 deg, any in-plane angle, on a plain floor or a textured one (smooth seeded noise).
Every scene is estimated with ``max_instances`` = the number of copies, over the whole frame and with
an ROI (the bounding box of the copies grown by 40 px).

Columns: scenes; copies; recall (copies matched by a found instance at MSPD < 5 px, 640 px width);
wrong (found instances matching no copy at MSPD < 5 px); latency p50 of the whole estimate, ms.

    python bench/instances.py [--scenes 10] [--seed 3]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.lib.scenes import l_block_bank  # noqa: E402
from service.vision import pipeline  # noqa: E402
from service.vision.estimate.roi import rect_polygon  # noqa: E402
from service.vision.geometry.camera import Intrinsics  # noqa: E402
from service.vision.geometry.frames import Pose, Rx, Ry, Rz  # noqa: E402
from service.vision.geometry.render import render, render_shaded  # noqa: E402
from service.vision.reference.metrics import mspd_px  # noqa: E402

INTR = Intrinsics(600.0, 600.0, 319.5, 239.5)
SIZE = (640, 480)
RANGE = (300.0, 600.0)
RIGHT_MSPD_PX = 5.0
CELL = (4, 3)  # copies go to distinct cells of this grid (columns, rows): they never overlap


def floor(rng: np.random.Generator, textured: bool) -> np.ndarray:
    w, h = SIZE
    if not textured:
        return np.full((h, w), float(rng.integers(50, 90)))
    noise = rng.normal(0.0, 1.0, (h // 16 + 1, w // 16 + 1))
    tex = cv2.resize(noise, (w, h), interpolation=cv2.INTER_CUBIC)
    return np.clip(70.0 + 25.0 * tex / max(float(np.abs(tex).max()), 1e-6), 20, 110)


def scene(rng: np.random.Generator, bank, n: int, textured: bool):
    """(BGR image, the copies' poses) of one scene."""
    cells = rng.permutation(CELL[0] * CELL[1])[:n]
    poses = []
    img = floor(rng, textured)
    for c in cells:
        cu, cv_ = c % CELL[0], c // CELL[0]
        u = (cu + 0.5 + rng.uniform(-0.1, 0.1)) * SIZE[0] / CELL[0]
        v = (cv_ + 0.5 + rng.uniform(-0.1, 0.1)) * SIZE[1] / CELL[1]
        z = rng.uniform(400.0, 470.0)
        R = Rx(rng.uniform(20.0, 45.0)) @ Ry(-rng.uniform(10.0, 30.0)) @ Rz(rng.uniform(0.0, 360.0))
        centre_cam = np.array([(u - INTR.cx) / INTR.fx * z, (v - INTR.cy) / INTR.fy * z, z])
        pose = Pose(R, centre_cam - R @ bank.centre_obj)
        poses.append(pose)
        shaded = render_shaded(bank.vertices_mm, bank.faces, pose, INTR.K, SIZE, background=0).astype(float)
        cov = render(bank.vertices_mm, bank.faces, pose, INTR.K, SIZE, supersample=2).coverage
        img = img * (1 - cov) + shaded  # shaded on a black floor is coverage x shade
    grey = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=2), poses


def roi_of(poses, bank, margin_px: float = 40.0) -> np.ndarray:
    uv = []
    for p in poses:
        x = p.apply(bank.vertices_mm.astype(float))
        uv.append(np.column_stack([INTR.fx * x[:, 0] / x[:, 2] + INTR.cx,
                                   INTR.fy * x[:, 1] / x[:, 2] + INTR.cy]))
    uv = np.concatenate(uv)
    lo = np.maximum(uv.min(axis=0) - margin_px, 0)
    hi = np.minimum(uv.max(axis=0) + margin_px, np.array(SIZE) - 1)
    return rect_polygon(lo[0], lo[1], hi[0] - lo[0], hi[1] - lo[1])


def nearest_copies(instances, truth, pts) -> list[tuple[int, float]]:
    """Per found instance: the copy nearest it and their MSPD (px at 640 px width)."""
    scale = 640.0 / SIZE[0]
    out = []
    for inst in instances:
        pose = inst.refined.pose if inst.refined is not None else inst.coarse.pose
        d = [scale * mspd_px(pose.R, pose.t_mm, g.R, g.t_mm, INTR.K, pts) for g in truth]
        k = int(np.argmin(d))
        out.append((k, d[k]))
    return out


def judge(instances, truth, pts) -> tuple[int, int]:
    """(copies matched by some instance at MSPD < RIGHT_MSPD_PX, instances matching none)."""
    near = nearest_copies(instances, truth, pts)
    return len({k for k, d in near if d < RIGHT_MSPD_PX}), sum(d >= RIGHT_MSPD_PX for _, d in near)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=10, help="scenes per background")
    ap.add_argument("--seed", type=int, default=3)
    args = ap.parse_args()
    bank = l_block_bank()
    pts = bank.vertices_mm.astype(float)
    print("| floor | ROI | scenes | copies | recall (MSPD < 5 px) | wrong instances | latency p50, ms |")
    print("|---|---|---|---|---|---|---|")
    for textured in (False, True):
        rows = {"no": [], "yes": []}
        for i in range(args.scenes):
            rng = np.random.default_rng([args.seed, int(textured), i])
            n = int(rng.integers(2, 7))
            img, truth = scene(rng, bank, n, textured)
            for label, roi in (("no", None), ("yes", roi_of(truth, bank))):
                t0 = time.perf_counter()
                out = pipeline.estimate(bank, img, INTR, distance_range_mm=RANGE, max_instances=n, roi_uv=roi)
                ms = (time.perf_counter() - t0) * 1000.0
                right, wrong = judge(out.instances, truth, pts)
                rows[label].append((n, right, wrong, ms))
        for label, r in rows.items():
            a = np.array(r, float)
            print(f"| {'textured' if textured else 'plain'} | {label} | {len(a)} | {int(a[:, 0].sum())} | "
                  f"{a[:, 1].sum() / a[:, 0].sum():.2f} | {int(a[:, 2].sum())} | {np.median(a[:, 3]):.0f} |")


if __name__ == "__main__":
    main()
