"""Would modelling the part's own shadows make the shading evidence tell right poses from wrong ones?

On the cached hypotheses (``bench/hypotheses.py``; truths and candidates scoring >= 0.5 with the service's
weights, in the searched distance range), per refined pose: the verdict's shading fit (grey level
quadratic in the rendered face normals, ``evidence._shading``, on its own pixels), and the same fit with
the part's shadows as regressors. The light is the direction of the Lambert fit (grey = a + b . n, light
along b); a pixel is in shadow when its face turns away from the light (attached) or when the part's own
surface lies between it and the light (cast: a depth map rasterised from the light, orthographic,
``MAP_PX`` across the part). The shadowed pixels get their own offset and normal terms, so the fit can
only explain more.

Prints per set the median r2 of right and wrong rows (refined MSPD < 20 px, not absent) and the AUC of
each fit (probability that a right row has the larger r2).

    python bench/shadow_shading.py --sets clutter,clutter2,paper [--tag r13]
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

from bench.accuracy import (  # noqa: E402
    gt_bank,
    read_colour,
    read_gt,
)
from bench.fit_verdict import load  # noqa: E402
from bench.hypotheses import set_dir_of  # noqa: E402
from service.vision.estimate import evidence as ev  # noqa: E402
from service.vision.estimate.verdict import verification_score  # noqa: E402
from service.vision.geometry.camera import Intrinsics, undistort_image  # noqa: E402
from service.vision.geometry.frames import Pose  # noqa: E402
from service.vision.geometry.render import rasterise_roi  # noqa: E402
from service.vision.pipeline import DEFAULT_DISTANCE_RANGE_MM  # noqa: E402

RIGHT_PX = 20.0
MAP_PX = 400  # the light's depth map across the part's diameter
LIGHT_DISTANCE_MM = 1e5  # a far perspective camera: orthographic enough


def _r2(A: np.ndarray, g: np.ndarray) -> float:
    coef = np.linalg.lstsq(A.T @ A + 1e-9 * np.eye(A.shape[1]), A.T @ g, rcond=None)[0]
    return float(1.0 - (g - A @ coef).var() / (g.var() + 1e-9))


def _lit_by(n: np.ndarray, grey: np.ndarray) -> np.ndarray | None:
    b = np.linalg.lstsq(np.hstack([np.ones((len(n), 1)), n]), grey, rcond=None)[0][1:]
    return b / np.linalg.norm(b) if np.linalg.norm(b) > 1e-6 else None


def _cast_shadow(bank, pose: Pose, p_cam: np.ndarray, light: np.ndarray) -> np.ndarray:
    """Points of the part (camera frame) that the part's own surface hides from the light."""
    e1 = np.cross(light, [0.0, 0.0, 1.0])
    e1 = e1 / np.linalg.norm(e1) if np.linalg.norm(e1) > 1e-6 else np.array([1.0, 0.0, 0.0])
    R_lc = np.stack([e1, np.cross(light, e1), -light])  # camera frame -> the light's frame
    C = pose.R @ bank.centre_obj + pose.t_mm + light * LIGHT_DISTANCE_MM
    f = LIGHT_DISTANCE_MM * MAP_PX / bank.diameter_mm
    K = np.array([[f, 0.0, MAP_PX / 2], [0.0, f, MAP_PX / 2], [0.0, 0.0, 1.0]])
    from_light = Pose(R_lc @ pose.R, R_lc @ (pose.t_mm - C))
    depth, fid, (u0, v0) = rasterise_roi(bank.vertices_mm, bank.faces, from_light, K, (MAP_PX, MAP_PX),
                                         margin_px=2)
    q = (p_cam - C) @ R_lc.T
    u = np.clip(np.rint(f * q[:, 0] / q[:, 2] + K[0, 2] - u0).astype(int), 0, depth.shape[1] - 1)
    v = np.clip(np.rint(f * q[:, 1] / q[:, 2] + K[1, 2] - v0).astype(int), 0, depth.shape[0] - 1)
    eps_mm = 2.0 + 2.0 * bank.diameter_mm / MAP_PX  # a map pixel's depth slope and the surface's own
    return (fid[v, u] >= 0) & (q[:, 2] > depth[v, u] + eps_mm)


def shading_r2(bank, pose: Pose, intr: Intrinsics, frame: ev.ColourFrame) -> tuple[float, float] | None:
    """(the verdict's shading r2, ``evidence._shading`` on its own pixels, and the shadow-aware fit's r2 on
    the same pixels) at ``pose``; None: too few pixels."""
    H, W = frame.shape
    fid, invz, (u0, v0) = ev.face_ids_roi(bank, pose, intr, (W, H), margin_px=2)
    inside = ev._inside_samples(fid, bank, pose)
    if inside is None:
        return None
    win = ev._window(frame, u0, v0, fid.shape[1], fid.shape[0])
    plain = ev._shading(win, inside)[0]
    grey = cv2.cvtColor(win.bgr[inside.v, inside.u][None], cv2.COLOR_BGR2GRAY)[0].astype(float)
    n = inside.normals
    light = _lit_by(n, grey)
    if light is None:
        return plain, plain
    z = 1.0 / invz[inside.v, inside.u]
    u, v = inside.u + u0, inside.v + v0
    p_cam = np.stack([(u - intr.cx) * z / intr.fx, (v - intr.cy) * z / intr.fy, z], axis=1)
    shadow = ((n @ light) < 0) | _cast_shadow(bank, pose, p_cam, light)
    s = shadow[:, None].astype(float)
    return plain, _r2(np.hstack([ev._normal_design(n), s, s * n]), grey)


def rows_of(name: str, tag: str) -> list[tuple[bool, float, float]]:
    set_dir = set_dir_of(name, None)
    gts = read_gt(set_dir)
    lo, hi = DEFAULT_DISTANCE_RANGE_MM
    out, frames = [], {}
    for r in load(name, tag):
        if r["rank"] >= 0 and (verification_score(r["ev"]) < 0.5 or not lo <= float(r["t1"][2]) <= hi):
            continue
        g = gts[r["q"]]
        if r["image"] not in frames:
            frames.clear()
            intr = Intrinsics.from_K(np.asarray(g["K"], float))
            image = undistort_image(read_colour(set_dir / g["image"]), intr)
            frames[r["image"]] = (ev.colour_frame(image), intr)
        frame, intr = frames[r["image"]]
        pose = Pose(np.asarray(r["R1"]), np.asarray(r["t1"]))
        got = shading_r2(gt_bank(set_dir, g["model"]), pose, intr, frame)
        if got is not None:
            out.append(((not r["absent"]) and r["mspd1"] < RIGHT_PX, *got))
    return out


def _auc(right: np.ndarray, wrong: np.ndarray) -> float:
    return float((right[:, None] > wrong[None]).mean()) if len(right) and len(wrong) else float("nan")


def _cell(right: np.ndarray, wrong: np.ndarray) -> str:
    med = [f"{np.median(x):.2f}" if len(x) else "-" for x in (right, wrong)]
    return f"{med[0]} / {med[1]}, {_auc(right, wrong):.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", default="clutter,clutter2,paper")
    ap.add_argument("--tag", default="*")
    a = ap.parse_args()
    print("| set | right / wrong rows | plain r2: right / wrong median, AUC "
          "| with shadows: right / wrong median, AUC |")
    print("|---|---|---|---|")
    for name in a.sets.split(","):
        rows = np.array([(ok, p, s) for ok, p, s in rows_of(name, a.tag)], float).reshape(-1, 3)
        right, wrong = rows[rows[:, 0] == 1], rows[rows[:, 0] == 0]
        cells = [_cell(right[:, k], wrong[:, k]) for k in (1, 2)]
        print(f"| {Path(name).name} | {len(right)} / {len(wrong)} | {cells[0]} | {cells[1]} |")


if __name__ == "__main__":
    main()
