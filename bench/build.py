"""Template-bank build benchmark: time, size and symmetry detection per model (prints tables only).

Models: every mesh in ``../shared/data/models`` plus two large synthetic ones (``--no-large`` skips
them): the sprayer subdivided twice (266k faces, revolved) and T-LESS 6 subdivided twice (182k
faces, no symmetry: the full view sphere), both above the 100k-face budget case.

Table 1 (symmetry): per model the best candidate axis, its score (mean silhouette-border
displacement when spun, relative to the radius about the axis; see ``service.vision.model.symmetry``), the
runner-up,
the threshold and the decision, and the detection time.

Table 2 (build): model, faces, symmetry used, views, border points, build seconds (wall, default
grid, all cores the builder uses), CPU seconds, bank MB as ``np.savez`` of ``to_arrays()``.

Targets (default grid, 2 cores): sprayer <= 5 s, T-LESS 6 <= 15 s, a 100k-face mesh <= 60 s,
every bank <= 20 MB.

Usage: python bench/build.py [--models sprayer,tless_06,...] [--no-large] [--grid JSON]
"""

from __future__ import annotations

import argparse
import io
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import trimesh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.vision.model.symmetry import SYMMETRY_THRESHOLD, score_candidates  # noqa: E402
from service.vision.model.templates import build_bank  # noqa: E402

DATA_DIR = Path(os.environ.get("POSE_DATA_DIR", ROOT.parent / "shared" / "data"))
TARGET_S = {"sprayer": 5.0, "tless_06": 15.0}
LARGE_TARGET_S = 60.0
MAX_MB = 20.0


def load_models(names: list[str] | None, large: bool) -> list[tuple[str, trimesh.Trimesh]]:
    out = []
    for p in sorted((DATA_DIR / "models").iterdir()):
        if p.suffix.lower() not in (".stl", ".ply", ".obj"):
            continue
        if names and p.stem not in names:
            continue
        out.append((p.stem, trimesh.load(p, force="mesh")))
    if large:
        by_name = {n: m for n, m in out}
        spr = by_name.get("sprayer") or trimesh.load(DATA_DIR / "models" / "sprayer.stl", force="mesh")
        t06 = by_name.get("tless_06") or trimesh.load(DATA_DIR / "models" / "tless_06.ply", force="mesh")
        big = spr
        for _ in range(2):
            big = big.subdivide()
        out.append(("sprayer x16 (subdivided)", big))
        big = t06
        for _ in range(2):
            big = big.subdivide()
        out.append(("tless_06 x16 (subdivided)", big))
    return out


def fmt_axis(a) -> str:
    return "(" + ", ".join(f"{x:+.3f}" for x in a) + ")"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", default="", help="comma-separated model stems (default: all)")
    ap.add_argument("--no-large", action="store_true", help="skip the subdivided large meshes")
    ap.add_argument("--grid", default="{}", help="grid options as JSON (default: GRID_DEFAULTS)")
    args = ap.parse_args()
    names = [s for s in args.models.split(",") if s] or None
    grid = json.loads(args.grid)
    models = load_models(names, not args.no_large)
    print(f"cores: {os.cpu_count()}, load average: {os.getloadavg()[0]:.2f}\n")

    print("## Symmetry detection\n")
    print(f"threshold: score <= {SYMMETRY_THRESHOLD} "
          "(mean border displacement when spun / radius about the axis)\n")
    print("| model | faces | best axis | point (mm) | score | runner-up score | symmetric | s |")
    print("|---|---:|---|---|---:|---:|---|---:|")
    for name, mesh in models:
        t = time.perf_counter()
        sc = score_candidates(mesh)
        dt = time.perf_counter() - t
        best = sc[0]
        second = f"{sc[1].score:.4f}" if len(sc) > 1 else "-"
        sym = "yes" if best.score <= SYMMETRY_THRESHOLD else "no"
        print(f"| {name} | {len(mesh.faces)} | {fmt_axis(best.axis_obj)} {best.source} | "
              f"{fmt_axis(best.point_obj)} | {best.score:.4f} | {second} | {sym} | {dt:.2f} |")
    print()

    print("## Bank build (default grid" + (f" + {grid}" if grid else "") + ")\n")
    print("| model | faces | symmetry | views | points | build s | cpu s | bank MB | target s |")
    print("|---|---:|---|---:|---:|---:|---:|---:|---|")
    for name, mesh in models:
        t, c = time.perf_counter(), time.process_time()
        bank = build_bank(mesh, symmetry="auto", grid=grid)
        dt, dc = time.perf_counter() - t, time.process_time() - c
        buf = io.BytesIO()
        np.savez(buf, **bank.to_arrays())
        mb = buf.getbuffer().nbytes / 1e6
        sym = "none" if bank.symmetry_axis_obj is None else fmt_axis(bank.symmetry_axis_obj)
        target = TARGET_S.get(name, LARGE_TARGET_S if len(mesh.faces) >= 100_000 else None)
        mark = "" if target is None else f"<= {target:g} {'ok' if dt <= target else 'MISSED'}"
        mb_mark = "" if mb <= MAX_MB else " (> 20 MB)"
        print(f"| {name} | {len(mesh.faces)} | {sym} | {bank.n_templates} | {len(bank.xy_n)} | {dt:.2f} | "
              f"{dc:.2f} | {mb:.2f}{mb_mark} | {mark} |")


if __name__ == "__main__":
    main()
