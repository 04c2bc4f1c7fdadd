"""What simplifying a large mesh to the template face budget costs: silhouette error and build memory.

For each test mesh (a 2.0 M-face sphere, the shape of the issue's 100 MB upload; the sprayer
subdivided to 266 k faces), simplify it to ``decode.TEMPLATE_FACE_BUDGET`` faces the way a build does
(``decode.fit_face_budget``), render both silhouettes at template resolution (``render_px`` 400,
2x supersampled, the canonical camera of ``templates.build_bank``) from 20 views, and print how far
the simplified silhouette's border lies from the original's, in template pixels (mean, max)::

    python bench/mesh_budget.py
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.lib.data import DATA_DIR  # noqa: E402
from service.decode import TEMPLATE_FACE_BUDGET, fit_face_budget  # noqa: E402
from service.vision.geometry.camera import Intrinsics  # noqa: E402
from service.vision.geometry.frames import Pose  # noqa: E402
from service.vision.geometry.render import render  # noqa: E402
from service.vision.model.grid import GRID_DEFAULTS  # noqa: E402

N_VIEWS = 20


def views(n: int, seed: int = 7) -> list[np.ndarray]:
    from scipy.spatial.transform import Rotation

    return list(Rotation.random(n, random_state=seed).as_matrix())


def border_error_px(mesh_a: trimesh.Trimesh, mesh_b: trimesh.Trimesh) -> tuple[float, float]:
    """Mean and max distance (template px) from b's silhouette border to a's, over ``N_VIEWS`` views."""
    V = np.asarray(mesh_a.vertices)
    centre = (V.min(0) + V.max(0)) / 2
    diameter = float(np.linalg.norm(np.ptp(V, axis=0)))
    d_ref = max(GRID_DEFAULTS["reference_distance_mm"], 2.5 * diameter)
    render_px = GRID_DEFAULTS["render_px"]
    f = render_px * d_ref / diameter
    size = int(1.6 * render_px)
    intr = Intrinsics(f, f, (size - 1) / 2, (size - 1) / 2)
    dists = []
    for R in views(N_VIEWS):
        pose = Pose(R, np.array([0.0, 0.0, d_ref]) - R @ centre)
        ma = render(mesh_a.vertices, mesh_a.faces, pose, intr, (size, size), supersample=2).mask
        mb = render(mesh_b.vertices, mesh_b.faces, pose, intr, (size, size), supersample=2).mask
        ba = ma ^ cv2.erode(ma.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        bb = mb ^ cv2.erode(mb.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        dt = cv2.distanceTransform((~ba).astype(np.uint8), cv2.DIST_L2, 5)
        dists.append(dt[bb])
    d = np.concatenate(dists)
    return float(d.mean()), float(d.max())


def main(argv: list[str] | None = None) -> None:
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
                            ).parse_args(argv)
    sprayer = trimesh.load(DATA_DIR / "models" / "sprayer.stl", force="mesh")
    meshes = {
        "sphere r50, 2.0 M faces (the issue's upload)": trimesh.creation.uv_sphere(50, count=[707, 707]),
        "sprayer subdivided x16, 266 k faces": sprayer.subdivide().subdivide(),
        "torus r60/15, 1.0 M faces": trimesh.creation.torus(60, 15, major_sections=1000, minor_sections=500),
    }
    print(f"face budget: {TEMPLATE_FACE_BUDGET:,} faces; views: {N_VIEWS}; template resolution: render_px "
          f"{GRID_DEFAULTS['render_px']}, supersample 2")
    print("| mesh | faces in | faces out | simplify s | border error mean / max, template px |")
    print("|---|---|---|---|---|")
    for name, mesh in meshes.items():
        t0 = time.perf_counter()
        small = fit_face_budget(mesh, TEMPLATE_FACE_BUDGET)
        dt = time.perf_counter() - t0
        mean, worst = border_error_px(mesh, small)
        print(f"| {name} | {len(mesh.faces):,} | {len(small.faces):,} | {dt:.1f} | {mean:.3f} / "
              f"{worst:.2f} |")


if __name__ == "__main__":
    main()
