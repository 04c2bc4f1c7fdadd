"""A set's parts taught their colours from some of its own images (``pipeline.teach_appearance``), as
``bench/detection.py --references`` and ``bench/appearance.py`` run them: ``n`` reference images spread
evenly over the sorted image list, the rest split into an even and an odd half by position."""

from __future__ import annotations

import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from bench.lib.data import gt_bank, read_colour, read_gt
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose
from service.vision.geometry.render import rasterise_roi
from service.vision.model.appearance import Appearance
from service.vision.pipeline import DEFAULT_POLICY, Policy, operating_point, teach_appearance


def reference_images(set_dir: Path, n: int, offset: int = 0) -> list[str]:
    """``n`` images spread evenly over the set's sorted image list, moved by ``offset`` positions (another
    choice of the same spread)."""
    images = sorted({g["image"] for g in read_gt(set_dir)})
    if n <= 0:
        return []
    return [images[(i * len(images) // n + offset) % len(images)] for i in range(n)]


def half_of(set_dir: Path, n_references: int, offset: int = 0) -> dict[str, str]:
    """Each non-reference image's half: "even" or "odd" by its position among them."""
    refs = set(reference_images(set_dir, n_references, offset))
    rest = [im for im in sorted({g["image"] for g in read_gt(set_dir)}) if im not in refs]
    return {im: ("even", "odd")[i % 2] for i, im in enumerate(rest)}


def gt_pose(g: dict) -> Pose:
    return Pose(np.asarray(g["R"], float), np.asarray(g["t_mm"], float))


def taught(set_dir: Path, n_references: int, policy: Policy = DEFAULT_POLICY, *, calibrate: bool = False,
           offset: int = 0) -> dict[str, Appearance]:
    """Each model's appearance taught from the reference images it appears in (``pipeline.teach_appearance``,
    the other annotated parts' pixels hidden: a fixture shot shows the part alone); ``calibrate``: each
    part's operating point calibrated on its reference photos at ``policy``."""
    by_image: dict[str, list[dict]] = defaultdict(list)
    for g in read_gt(set_dir):
        if not g.get("absent"):
            by_image[g["image"]].append(g)
    views: dict[str, list[tuple]] = defaultdict(list)
    for im in reference_images(set_dir, n_references, offset):
        image = read_colour(set_dir / im)
        h, w = image.shape[:2]
        depths = {}
        for g in by_image[im]:
            bank = gt_bank(set_dir, g["model"])
            K = np.asarray(g["K"], float)
            d, _, (u0, v0) = rasterise_roi(bank.vertices_mm, bank.faces, gt_pose(g), K, (w, h))
            full = np.full((h, w), np.inf, np.float32)
            full[v0:v0 + d.shape[0], u0:u0 + d.shape[1]] = d
            depths[g["model"]] = full
        for g in by_image[im]:
            others = [d for m, d in depths.items() if m != g["model"]]
            hidden = (np.min(others, axis=0) < depths[g["model"]]) if others else None
            intr = Intrinsics.from_K(np.asarray(g["K"], float))
            views[g["model"]].append((image, intr, gt_pose(g), hidden))
    out = {m: teach_appearance(gt_bank(set_dir, m), v, calibrate=calibrate, policy=policy)
           for m, v in views.items()}
    if calibrate:
        for m, a in sorted(out.items()):
            print(f"calibrated {m}: {a.calibrated_photos} photos, highest wrong score {a.wrong_score:.4f}, "
                  f"operating point {operating_point(a, policy) or float('nan'):.4f}", file=sys.stderr)
    return out
