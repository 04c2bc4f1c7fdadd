"""Copies resting on a supporting plane: per-instance recall, wrong instances and latency, with and
without ``options.plane``, and with an ROI.

Each scene: a camera 400-500 mm from the point its optical axis meets a plane, the axis 20-60 deg from
straight down (the plane's normal), any roll about the plane normal; 2-8 copies of an L-shaped block
(no symmetry; 80 x 60 x 40 mm) resting on the plane in stable poses (the bank's families, drawn by their
probability), any spin about the normal, packed close together round the axis' foot point: footprints
(convex hull of the posed part on the plane) never overlap but may touch, so nearer copies hide parts
of farther ones in the image. All copies are rendered as one mesh by the project's rasteriser (z-buffer:
mutual occlusion), Lambert-shaded, on a plain plane or a textured one (smooth noise fixed on the plane,
so perspective-foreshortened). Every scene is drawn from ``np.random.default_rng([seed, textured, i])``.

Each scene is estimated with ``max_instances`` = the number of copies: without a plane (distance range
300-700 mm), with the plane, and with the plane and an ROI (the copies' bounding box grown by 40 px); and
one copy's scene without a plane, for the cost ratio. On the plane the block is judged as calibrated for
one, as the service calibrates it (``--calibration-scenes``, records kept in bench/out/plane_calibration).

Columns: scenes; targets (copies at least 70 % visible: pixels in the image not hidden by another copy /
pixels of the copy's whole silhouette, in the image or not); recall (targets matched by a found instance
at MSPD < 5 px, 640 px width); wrong (found instances matching no copy at MSPD < 20 px, as
bench/detection.py); latency p50 / p95 of the whole estimate, ms.

    NUMBA_NUM_THREADS=1 python bench/plane.py [--scenes 10] [--seed 5] [--parts 2-8]
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

from bench.instances import INTR, RIGHT_MSPD_PX, SIZE, nearest_copies, roi_of  # noqa: E402
from bench.lib.calibration import plane_calibration  # noqa: E402
from bench.lib.policy import add_policy_options, policy_of  # noqa: E402
from bench.lib.scenes import l_block_bank  # noqa: E402
from service.vision import pipeline  # noqa: E402
from service.vision.geometry.frames import Pose, Rz  # noqa: E402
from service.vision.geometry.plane import Plane  # noqa: E402
from service.vision.geometry.render import render, render_shaded  # noqa: E402
from service.vision.pipeline.plane_calibration import MARGIN, SCENES  # noqa: E402

RANGE = (300.0, 700.0)
WRONG_MSPD_PX = 20.0
MIN_VISIBLE = 0.7


def camera(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
    """(R_cam_world, t_cam_world, tilt_deg): world = the plane's frame (z up, plane z = 0)."""
    tilt = rng.uniform(20.0, 60.0)
    dist = rng.uniform(400.0, 500.0)
    a = np.radians(tilt)
    z_c = np.array([0.0, np.sin(a), -np.cos(a)])
    x_c = np.array([1.0, 0.0, 0.0])
    y_c = np.cross(z_c, x_c)
    R = np.stack([x_c, y_c, z_c]) @ Rz(rng.uniform(0.0, 360.0)).T  # any heading about the plane normal
    C = -dist * (R.T @ np.array([0.0, 0.0, 1.0]))  # the axis meets the plane at the world origin
    return R, -R @ C, tilt


def plane_of(R_cw: np.ndarray, t_cw: np.ndarray) -> Plane:
    n = R_cw @ np.array([0.0, 0.0, 1.0])
    return Plane(n, float(n @ t_cw))


def footprint(V_world: np.ndarray, origin: np.ndarray, px_mm: float, size: int) -> np.ndarray:
    m = np.zeros((size, size), np.uint8)
    hull = cv2.convexHull(np.rint((V_world[:, :2] - origin) / px_mm).astype(np.int32))
    cv2.fillConvexPoly(m, hull, 1)
    return m.astype(bool)


def scene(rng: np.random.Generator, bank, n: int, textured: bool):
    """(BGR image, truth poses T_cam_obj, visible fractions, plane) of one scene."""
    R_cw, t_cw, _ = camera(rng)
    V = np.asarray(bank.vertices_mm, float)
    prob = bank.rest_probability / bank.rest_probability.sum()
    spread = 0.55 * bank.diameter_mm * np.sqrt(n)
    grid_mm, size = 1.0, int(4 * spread + 2 * bank.diameter_mm)
    origin = np.array([-size / 2.0, -size / 2.0])
    occupied = np.zeros((size, size), bool)
    poses: list[Pose] = []
    for _ in range(n):
        for _try in range(200):
            s = int(rng.choice(len(prob), p=prob))
            R_wo = Rz(rng.uniform(0.0, 360.0)) @ bank.R_rest_obj[s]
            q = V @ R_wo.T
            xy = rng.uniform(-spread, spread, 2)
            t_wo = np.array([xy[0], xy[1], 0.0]) - np.array([*(q[:, :2].mean(axis=0)), q[:, 2].min()])
            fp = footprint(q + t_wo, origin, grid_mm, size)
            if not (fp & occupied).any():
                occupied |= fp
                poses.append(Pose(R_cw @ R_wo, R_cw @ t_wo + t_cw))
                break
    # one mesh: the rasteriser's z-buffer hides copies behind nearer ones
    Vs = np.concatenate([p.apply(V) for p in poses])
    F = np.asarray(bank.faces)
    Fs = np.concatenate([F + k * len(V) for k in range(len(poses))])
    eye = Pose(np.eye(3), np.zeros(3))
    shaded = render_shaded(Vs, Fs, eye, INTR.K, SIZE, background=0).astype(float)
    all_r = render(Vs, Fs, eye, INTR.K, SIZE, supersample=2)
    visible = []
    m = 400  # the copy alone on a canvas 400 px wider each side: its whole silhouette, also off the image
    K_big = INTR.K + np.array([[0, 0, m], [0, 0, m], [0, 0, 0]])
    for k, p in enumerate(poses):
        alone = render(V, F, p, K_big, (SIZE[0] + 2 * m, SIZE[1] + 2 * m), supersample=2).mask
        own = all_r.mask & (all_r.face_id >= k * len(F)) & (all_r.face_id < (k + 1) * len(F))
        visible.append(float(own.sum()) / max(float(alone.sum()), 1.0))
    img = floor(rng, R_cw, t_cw, textured) * (1 - all_r.coverage) + shaded
    grey = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=2), poses, visible, plane_of(R_cw, t_cw)


def floor(rng: np.random.Generator, R_cw: np.ndarray, t_cw: np.ndarray, textured: bool) -> np.ndarray:
    """(h, w) grey levels of the plane: plain, or smooth noise fixed on the plane (mm scale 25)."""
    w, h = SIZE
    base = float(rng.integers(50, 90))
    if not textured:
        return np.full((h, w), base)
    cells = 25.0
    noise = rng.normal(0.0, 1.0, (64, 64))
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    r = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones_like(u, float)], -1)
    n = R_cw[:, 2]
    lam = (n @ t_cw) / np.minimum(r @ n, -1e-6)  # the ray meets the plane n . p = n . t_cw
    p_world = (lam[..., None] * r - t_cw) @ R_cw  # R_cw.T @ (p_cam - t)
    gx = np.clip(p_world[..., 0] / cells + 32, 0, 63).astype(np.float32)
    gy = np.clip(p_world[..., 1] / cells + 32, 0, 63).astype(np.float32)
    tex = cv2.remap(noise.astype(np.float32), gx, gy, cv2.INTER_CUBIC)
    return np.clip(base + 30.0 * tex / max(float(np.abs(noise).max()), 1e-6) * 2.0, 15, 130)


def judge(instances, truth, visible, pts) -> tuple[int, int, int]:
    """(targets, targets matched at MSPD < RIGHT_MSPD_PX, found instances matching no copy)."""
    targets = {k for k, f in enumerate(visible) if f >= MIN_VISIBLE}
    near = nearest_copies(instances, truth, pts)
    matched = {k for k, d in near if d < RIGHT_MSPD_PX}
    return len(targets), len(matched & targets), sum(d >= WRONG_MSPD_PX for _, d in near)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=10, help="scenes per plane texture")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--parts", default="2-8", help="copies per scene, lo-hi")
    ap.add_argument("--no-baseline", action="store_true", help="skip the searches without a plane")
    ap.add_argument("--cost-scenes", type=int, default=0, help="only the cost of 5 copies on the plane "
                    "against one copy without it: this many scenes of each, CPU and wall time")
    ap.add_argument("--calibration-scenes", type=int, default=SCENES,
                    help="the part calibrated for a plane on this many rendered scenes (0: not)")
    ap.add_argument("--agreement-margin", type=float, default=MARGIN,
                    help="the calibrated agreement's margin above the highest wrong candidate's (and the "
                         "floor's under the lowest right one's)")
    ap.add_argument("--min-score", type=float, default=None, help="the verdict's operating point (default: "
                    "the pipeline's)")
    add_policy_options(ap)
    args = ap.parse_args()
    policy = policy_of(args)
    lo, hi = (int(x) for x in args.parts.split("-"))
    bank = l_block_bank()
    # the part calibrated for a plane as the service calibrates it once it is ready
    cal = plane_calibration(bank, "l_block", None, args.calibration_scenes, args.agreement_margin, policy) \
        if args.calibration_scenes else None
    agreement = cal.agreement if cal else None
    pts = bank.vertices_mm.astype(float)
    if args.cost_scenes:
        return five_copies_cost(bank, args.seed, args.cost_scenes, pts)
    modes = ["plane", "plane + ROI"] if args.no_baseline else ["no plane", "plane", "plane + ROI"]
    rows_all = []
    single = []
    for textured in (False, True):
        rows = {m: [] for m in modes}
        for i in range(args.scenes):
            rng = np.random.default_rng([args.seed, int(textured), i])
            n = int(rng.integers(lo, hi + 1))
            img, truth, visible, plane = scene(rng, bank, n, textured)
            for mode in modes:
                kw = {"max_instances": n, "min_score": args.min_score, "policy": policy}
                if mode == "no plane":
                    kw["distance_range_mm"] = RANGE
                else:
                    kw |= {"plane": plane, "agreement": agreement}
                if mode == "plane + ROI":
                    kw["roi_uv"] = roi_of(truth, bank)
                t0 = time.perf_counter()
                out = pipeline.estimate(bank, img, INTR, **kw)
                ms = (time.perf_counter() - t0) * 1000.0
                rows[mode].append((n, *judge(out.instances, truth, visible, pts), ms))
            if not args.no_baseline and i < 5:  # one copy, no plane: the single search the ratio is against
                rng1 = np.random.default_rng([args.seed, int(textured), i, 1])
                img1, truth1, _, _ = scene(rng1, bank, 1, textured)
                t0 = time.perf_counter()
                pipeline.estimate(bank, img1, INTR, distance_range_mm=RANGE)
                single.append((time.perf_counter() - t0) * 1000.0)
        for mode, r in rows.items():
            a = np.array(r, float)
            rows_all.append((textured, mode, a))
    print("| plane texture | search | scenes | copies | targets (>= 70 % visible) | recall (MSPD < 5 px) | "
          "wrong instances | latency p50 / p95, ms |")
    print("|---|---|---|---|---|---|---|---|")
    for textured, mode, a in rows_all:
        print(f"| {'textured' if textured else 'plain'} | {mode} | {len(a)} | {int(a[:, 0].sum())} | "
              f"{int(a[:, 1].sum())} | {a[:, 2].sum() / max(a[:, 1].sum(), 1):.2f} | {int(a[:, 3].sum())} | "
              f"{np.median(a[:, 4]):.0f} / {np.percentile(a[:, 4], 95):.0f} |")
    if single:
        print(f"\none copy, no plane (max_instances 1): latency p50 {np.median(single):.0f} ms over "
              f"{len(single)} scenes")
        for textured, mode, a in rows_all:
            five = a[a[:, 0] == 5, 4]
            if len(five) and mode != "no plane":
                print(f"{'textured' if textured else 'plain'}, {mode}, 5 copies: p50 {np.median(five):.0f} "
                      f"ms = {np.median(five) / np.median(single):.2f} x the single search")


def _timed(bank, img, **kw) -> tuple[float, float, object]:
    """(CPU ms of this process, wall ms, the answer) of one estimate."""
    c0, t0 = time.process_time(), time.perf_counter()
    out = pipeline.estimate(bank, img, INTR, **kw)
    return (time.process_time() - c0) * 1000.0, (time.perf_counter() - t0) * 1000.0, out


def five_copies_cost(bank, seed: int, n_scenes: int, pts) -> None:
    """What a frame of 5 copies costs with the plane (and with an ROI round them) against one copy
    searched without it, per plane texture: p50 CPU time (less sensitive to other work on the machine)
    and wall time, and the 5-copy recall beside it. Also the single search (max_instances 1, no plane)
    on the 5-copy frames themselves: the other reading of "a single search"."""
    print("| plane texture | search | scenes | CPU p50 ms | x single | wall p50 ms | x single | "
          "recall (MSPD < 5 px) | wrong instances |")
    print("|---|---|---|---|---|---|---|---|---|")
    for textured in (False, True):
        single, same, rows = [], [], {"plane": [], "plane + ROI": []}
        for i in range(n_scenes):
            rng1 = np.random.default_rng([seed, int(textured), i, 1])
            img1, _, _, _ = scene(rng1, bank, 1, textured)
            single.append(_timed(bank, img1, distance_range_mm=RANGE)[:2])
            rng = np.random.default_rng([seed, int(textured), i, 5])
            img, truth, visible, plane = scene(rng, bank, 5, textured)
            same.append(_timed(bank, img, distance_range_mm=RANGE)[:2])
            for mode, extra in (("plane", {}), ("plane + ROI", {"roi_uv": roi_of(truth, bank)})):
                cpu, wall, out = _timed(bank, img, max_instances=5, plane=plane, **extra)
                rows[mode].append((cpu, wall, *judge(out.instances, truth, visible, pts)))
        s = np.median(np.array(single), axis=0)
        tex = "textured" if textured else "plain"
        print(f"| {tex} | one copy, no plane | {n_scenes} | {s[0]:.0f} | 1.00 | {s[1]:.0f} | 1.00 | | |")
        f = np.median(np.array(same), axis=0)
        print(f"| {tex} | 5 copies, no plane, max_instances 1 | {n_scenes} | {f[0]:.0f} | "
              f"{f[0] / s[0]:.2f} | {f[1]:.0f} | {f[1] / s[1]:.2f} | | |")
        for mode, r in rows.items():
            a = np.array(r, float)
            cpu, wall = np.median(a[:, 0]), np.median(a[:, 1])
            print(f"| {tex} | 5 copies, {mode} | {n_scenes} | {cpu:.0f} | {cpu / s[0]:.2f} | {wall:.0f} | "
                  f"{wall / s[1]:.2f} | {a[:, 3].sum() / max(a[:, 2].sum(), 1):.2f} | {int(a[:, 4].sum())} |")


if __name__ == "__main__":
    main()
