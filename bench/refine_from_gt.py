"""Refinement accuracy and time on the paper renders, starting from the ground truth perturbed by
(2 deg, 3 mm), with the distance given (tz held at 500 mm) and not given.

    python bench/refine_from_gt.py [--loss soft_l1|huber|median|...] [--residual dt+line|dt|line] [-n 20]

Errors are the paper's columns: mean |tx|, |ty|, |tz| (mm) and, for the revolved sprayer with its
axis written a = Rx(alpha) @ Rz(gamma) @ e_y, mean |alpha| (Rx) and |gamma| (Rz) errors (deg).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np
import trimesh

from service.vision.build.templates import build_bank
from service.vision.estimate.refine import refine_pose
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, R_from_rotvec, axis_alpha_gamma_deg

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "paper"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--loss", default="soft_l1")
    ap.add_argument("--residual", default="dt+line")
    ap.add_argument("-n", type=int, default=20)
    ap.add_argument("--deg", type=float, default=2.0)
    ap.add_argument("--mm", type=float, default=3.0)
    a = ap.parse_args()
    mesh = trimesh.load(DATA / "models" / "sprayer.stl", force="mesh")
    bank = build_bank(mesh, symmetry="auto", grid={"render_px": 100, "supersample": 1, "tilt_step_deg": 30.0})
    axis = bank.symmetry_axis_obj
    gts = [json.loads(s) for s in (DATA / "gt.jsonl").read_text().splitlines()][: a.n]
    print(f"paper renders: {len(gts)}, start = gt perturbed by {a.deg} deg / {a.mm} mm, loss={a.loss}, "
          f"residual={a.residual}")
    print("| distance | pose | tx mm | ty mm | tz mm | Rx deg | Rz deg | score | refine p50 ms | max ms |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for given in (True, False):
        rng = np.random.default_rng(1)
        e0, e1, ms, sc = [], [], [], []
        for g in gts:
            img = cv2.imread(str(DATA / g["image"]), cv2.IMREAD_GRAYSCALE)
            intr = Intrinsics.from_K(np.array(g["K"]))
            gt = Pose(np.array(g["R"]), np.array(g["t_mm"]))
            ax = rng.normal(size=3)
            dv = rng.normal(size=3)
            if given:
                dv[2] = 0.0
            start = Pose(R_from_rotvec(np.deg2rad(a.deg) * ax / np.linalg.norm(ax)) @ gt.R,
                         gt.t_mm + a.mm * dv / np.linalg.norm(dv))
            t0 = time.perf_counter()
            res = refine_pose(bank, start, img, intr, distance_mm=500.0 if given else None, loss=a.loss,
                              residual=a.residual)
            ms.append((time.perf_counter() - t0) * 1e3)
            sc.append(res.score)
            ag = np.array(axis_alpha_gamma_deg(gt.R @ axis))
            for p, out in ((start, e0), (res.pose, e1)):
                a_p = np.array(axis_alpha_gamma_deg(p.R @ axis))
                out.append([*np.abs(p.t_mm - gt.t_mm), *np.abs(a_p - ag)])
        for name, e in (("start", e0), ("refined", e1)):
            m = np.mean(e, axis=0)
            tail = (f"{np.mean(sc):.3f} | {np.median(ms):.0f} | {np.max(ms):.0f}" if name == "refined"
                    else " | | ")
            print(f"| {'given' if given else 'refined'} | {name} | {m[0]:.3f} | {m[1]:.3f} | {m[2]:.3f} | "
                  f"{m[3]:.3f} | {m[4]:.3f} | {tail} |")


if __name__ == "__main__":
    main()
