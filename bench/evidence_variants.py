"""Which evidence could tell a true pose from a wrong one: variants measured on cached hypotheses.

Reads the feature rows of ``bench/hypotheses.py features`` / ``truths`` (each with its refined pose,
``R1`` / ``t1``), recomputes candidate evidence at the refined poses (no search, no refinement: a few
ms per row) and prints, per variant, how well it separates right rows (refined MSPD < 20 px, the
truth hypotheses included) from wrong ones (the rest, and every row of an absent image):

- ``auc``: probability that a right row scores above a wrong one;
- ``>p99`` / ``>max``: right rows above the wrong rows' 99th percentile / maximum: what a verdict
  can accept with (almost) no wrong answer, which is what ``found`` needs.

Variants (the verdict's own ``shading_r2`` and ``region_global`` are ``q2`` and ``rgb6``):

- shading: ``q2`` quadratic in the face normals (the verdict's); ``quv`` the same plus a linear term in
  image position (a light's fall-off); ``trim`` ``q2`` refitted on the 80 % best-fitting pixels
  (shadows, bores, an occluder left out); ``face`` piecewise constant over ~15 deg normal bins;
- region: total-variation distance of inside / outside band colour histograms, ``rgb6`` / ``rgb8``
  (6 / 8 bins per channel), ``ab`` (Lab chroma only, 16 x 16 bins: shading- and shadow-blind), ``w``
  suffix a band twice as wide; ``cpost`` the contour posterior (RBOT / SRT3D): per outline point, the
  mean foreground posterior (from those band histograms) 1-5 px inside minus 1-5 px outside.

    python bench/hypotheses.py features --set clutter   # and truths; rows now carry R1 / t1
    python bench/evidence_variants.py --sets clutter,clutter2,absent,absent2
"""

from __future__ import annotations

import argparse
import pickle
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import service.vision.estimate.evidence as _evidence  # noqa: E402
from bench.accuracy import (  # noqa: E402
    gt_bank,
    read_colour,
    read_gt,
)
from bench.hypotheses import OUT, set_dir_of  # noqa: E402
from service.vision.estimate import evidence as ev  # noqa: E402
from service.vision.geometry.camera import Intrinsics, undistort_image  # noqa: E402
from service.vision.geometry.frames import Pose  # noqa: E402
from service.vision.geometry.render import face_normals_cam  # noqa: E402

_evidence.VISIBLE_PART = True  # the visible part's evidence is what these tables study too

RIGHT_PX = 20.0
MARGIN_PX = 40  # ROI margin: the widest band read


def _r2(A: np.ndarray, g: np.ndarray) -> tuple[float, np.ndarray]:
    coef = np.linalg.lstsq(A.T @ A, A.T @ g, rcond=None)[0]
    res = g - A @ coef
    return float(1.0 - res.var() / (g.var() + 1e-9)), res


def shading_variants(bgr: np.ndarray, fid: np.ndarray, bank, pose: Pose) -> dict[str, float]:
    inner = cv2.erode((fid >= 0).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    inner[1::2, :] = False
    inner[:, 1::2] = False
    if inner.sum() < ev.MIN_SHADING_PIXELS:
        return dict(q2=0.0, quv=0.0, trim=0.0, face=0.0)
    vi, ui = np.nonzero(inner)
    grey = cv2.cvtColor(bgr[vi, ui][None], cv2.COLOR_BGR2GRAY)[0].astype(np.float64)
    visible, index = np.unique(fid[vi, ui], return_inverse=True)
    n = face_normals_cam(bank.vertices_mm, bank.faces[visible], pose.R, pose.t_mm)[index].astype(np.float64)
    A = np.hstack([np.ones((len(n), 1)), n, n * n, n[:, [0]] * n[:, [1]], n[:, [1]] * n[:, [2]],
                   n[:, [0]] * n[:, [2]]])
    q2, res = _r2(A, grey)
    s = max(vi.max() - vi.min(), ui.max() - ui.min(), 1)
    uv = np.stack([(ui - ui.mean()) / s, (vi - vi.mean()) / s], axis=1)
    quv, _ = _r2(np.hstack([A, uv]), grey)
    keep = np.abs(res) <= np.quantile(np.abs(res), 0.8)
    trim, _ = _r2(A[keep], grey[keep])
    _, group = np.unique(np.round(n * 4).astype(int), axis=0, return_inverse=True)
    group = group.ravel()
    mean = np.bincount(group, grey) / np.bincount(group)
    face = float(1.0 - ((grey - mean[group]) ** 2).mean() / (grey.var() + 1e-9))
    return dict(q2=q2, quv=quv, trim=trim, face=face)


def _tv(a: np.ndarray, b: np.ndarray, nb: int) -> float:
    ha = np.bincount(a, minlength=nb) / max(len(a), 1)
    hb = np.bincount(b, minlength=nb) / max(len(b), 1)
    return float(0.5 * np.abs(ha - hb).sum())


def _bins(bgr: np.ndarray, nb: int) -> np.ndarray:
    q = (bgr.astype(np.int64) * nb) // 256
    return (q[..., 0] * nb + q[..., 1]) * nb + q[..., 2]


def region_variants(bgr: np.ndarray, lab: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    m8 = mask.astype(np.uint8)
    d_in = cv2.distanceTransform(m8, cv2.DIST_L2, 3)
    d_out = cv2.distanceTransform(1 - m8, cv2.DIST_L2, 3)
    band = int(np.clip(ev.BAND_FRACTION * np.sqrt(mask.sum() / np.pi), ev.BAND_MIN_PX, ev.BAND_MAX_PX))
    q6, q8 = _bins(bgr, 6), _bins(bgr, 8)
    qab = (lab[..., 1].astype(np.int64) * 16 // 256) * 16 + lab[..., 2].astype(np.int64) * 16 // 256
    out: dict[str, float] = {}
    for tag, width in (("", band), ("w", 2 * band)):
        inner, outer = mask & (d_in <= width), ~mask & (d_out <= width)
        if inner.sum() < ev.MIN_REGION_PIXELS or outer.sum() < ev.MIN_REGION_PIXELS:
            out |= {f"rgb6{tag}": 0.0, f"rgb8{tag}": 0.0, f"ab{tag}": 0.0}
            continue
        out |= {f"rgb6{tag}": _tv(q6[inner], q6[outer], 216), f"rgb8{tag}": _tv(q8[inner], q8[outer], 512),
                f"ab{tag}": _tv(qab[inner], qab[outer], 256)}
    inner, outer = mask & (d_in <= 2 * band), ~mask & (d_out <= 2 * band)
    hf = np.bincount(q8[inner], minlength=512) + 1.0
    hb = np.bincount(q8[outer], minlength=512) + 1.0
    post = (hf / hf.sum() / (hf / hf.sum() + hb / hb.sum()))[q8]  # P(part | colour), equal priors
    p, n = ev._outline(mask)
    if len(p) == 0:
        return out | {"cpost": 0.0}
    h, w = mask.shape

    def at(d: float) -> np.ndarray:
        uv = np.rint(p + d * n).astype(int)
        return post[np.clip(uv[:, 1], 0, h - 1), np.clip(uv[:, 0], 0, w - 1)]

    inside = np.mean([at(-d) for d in range(1, 6)], axis=0)
    outside = np.mean([at(d) for d in range(1, 6)], axis=0)
    return out | {"cpost": float(np.clip(inside - outside, 0.0, 1.0).mean())}


def variants(bank, pose: Pose, intr: Intrinsics, frame: ev.ColourFrame, lab: np.ndarray) -> dict[str, float]:
    H, W = frame.shape
    fid, _, (u0, v0) = ev.face_ids_roi(bank, pose, intr, (W, H), margin_px=MARGIN_PX)
    mask = fid >= 0
    if mask.sum() < ev.MIN_SHADING_PIXELS:
        return {}
    win = (slice(v0, v0 + mask.shape[0]), slice(u0, u0 + mask.shape[1]))
    return shading_variants(frame.bgr[win], fid, bank, pose) | region_variants(frame.bgr[win], lab[win], mask)


def rows_with_variants(name: str) -> list[dict]:
    rows = []
    for suffix in ("features", "truth-features"):
        p = OUT / f"{Path(name).name}-default-{suffix}.pkl"
        if p.exists():
            rows += [r for r in pickle.loads(p.read_bytes()) if "R1" in r]
    set_dir = set_dir_of(name, None)
    by_query = {(g["image"], g.get("model")): g for g in read_gt(set_dir)}
    by_image = {g["image"]: g for g in read_gt(set_dir)}
    frames: dict = {}
    for r in rows:
        g = by_query.get((r["image"], r["model"])) or by_image[r["image"]]
        if r["image"] not in frames:
            frames.clear()
            intr = Intrinsics.from_K(np.asarray(g["K"], float))
            frame = ev.colour_frame(undistort_image(read_colour(set_dir / g["image"]), intr))
            frames[r["image"]] = (frame, intr, cv2.cvtColor(frame.bgr, cv2.COLOR_BGR2LAB))
        frame, intr, lab = frames[r["image"]]
        bank = gt_bank(set_dir, r["model"])
        r["var"] = variants(bank, Pose(np.asarray(r["R1"]), np.asarray(r["t1"])), intr, frame, lab)
    return rows


def separation(right: np.ndarray, wrong: np.ndarray) -> str:
    auc = float((right[:, None] > wrong[None]).mean() + 0.5 * (right[:, None] == wrong[None]).mean())
    return (f"{auc:.2f} | {int((right > np.percentile(wrong, 99)).sum())} | "
            f"{int((right > wrong.max()).sum())}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sets", default="clutter,clutter2,absent,absent2")
    a = ap.parse_args(argv)
    rows = [r for s in a.sets.split(",") for r in rows_with_variants(s) if r["var"]]
    right = [r for r in rows if not r["absent"] and r["mspd1"] < RIGHT_PX]
    wrong = [r for r in rows if r["absent"] or r["mspd1"] >= RIGHT_PX]
    print(f"{a.sets}: {len(right)} right rows ({sum(r['rank'] < 0 for r in right)} truth hypotheses), "
          f"{len(wrong)} wrong\n")
    print("| variant | auc | right > wrong p99 | right > wrong max |")
    print("|---|---|---|---|")
    for k in right[0]["var"]:
        print(f"| {k} | " + separation(np.array([r["var"].get(k, 0.0) for r in right]),
                                       np.array([r["var"].get(k, 0.0) for r in wrong])) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
