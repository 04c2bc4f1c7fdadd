# ruff: noqa: E501  (the table and header lines print as they read)
"""Does gradient-orientation matching of every visible CAD edge propose the sygrid_synth parts, given
the table plane? (issue 47; the matcher is ``bench/gradient_match.py``, outside the service)::

    python bench/gradient_proposals.py [--limit 5] [--stride 10] [--parts nut,tube] [--zones 3]
        [--no-creases] [--flat]

One query per (image, part) as the issue's tables: the part's model, the image and the plane from the
gt line. For each gt copy at least ``--min-visible`` visible: is a proposal's centre (the model's
bounding-box centre, projected with the proposed pose) within ``--tol-px`` of the copy's among the top
N proposals (N = the copies of that part in the image) and the top 2N? Wrong = top-N proposals farther
than the tolerance from every copy (any visibility). Also: how many copies lean more than
``LEAN_DEG`` from every resting family the search tries (unreachable by a plane search). Templates are
built once per (part, plane) and cached for the run (their build time is reported apart: upload time
in a product); the image's response maps once per image; "match ms" is the per-query search.
Deterministic (seeded template point sampling, no other randomness).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
import trimesh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import gradient_match as gm  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "sygrid_synth"
LEAN_DEG = 15.0


def project(p_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    return p_cam[..., :2] / p_cam[..., 2:3] * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]


def lean_deg(R_gt: np.ndarray, plane: dict, families: list, symmetry: str) -> float:
    """Angle between the copy's up (the plane normal in its object frame) and the nearest family's up."""
    up = R_gt.T @ np.asarray(plane["normal"], float)
    axis = {"x": np.array([1.0, 0, 0]), "y": np.array([0, 1.0, 0]), "z": np.array([0, 0, 1.0])}.get(symmetry)
    best = 180.0
    for f in families:
        fu = f.R_rest_obj[2]
        if axis is None:
            a = math.degrees(math.acos(np.clip(up @ fu, -1, 1)))
        else:
            a = abs(
                math.degrees(math.acos(np.clip(up @ axis, -1, 1)))
                - math.degrees(math.acos(np.clip(fu @ axis, -1, 1)))
            )
        best = min(best, a)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--limit", type=int, default=5, help="first N images (0: all 51)")
    ap.add_argument("--stride", type=int, default=1, help="every k-th image (before --limit)")
    ap.add_argument("--start", type=int, default=0, help="skip the first k images (after --stride)")
    ap.add_argument("--parts", default="", help="comma-separated part names (sygrid_ prefix optional)")
    ap.add_argument("--zones", type=int, default=3, help="templates rendered at the centres of Z x Z zones")
    ap.add_argument("--spin-step", type=float, default=None, help="deg (default: from the part's size and T)")
    ap.add_argument("--points", type=int, default=gm.MAX_POINTS)
    ap.add_argument(
        "--t", type=int, default=None, help="spreading / grid step, px (default: 4 or 8 by part size)"
    )
    ap.add_argument("--mag", type=float, default=gm.MAG_THRESHOLD)
    ap.add_argument("--no-creases", action="store_true", help="silhouette and depth-jump edges only")
    ap.add_argument(
        "--flat",
        action="store_true",
        help="every template point weighs the same (default: orientation-balanced)",
    )
    ap.add_argument(
        "--fine-t",
        type=int,
        default=0,
        help="T of the maps the candidates are refined and ranked on (0: the search's)",
    )
    ap.add_argument("--nms-px", type=float, default=16.0)
    ap.add_argument("--tol-px", type=float, default=20.0)
    ap.add_argument("--min-visible", type=float, default=0.7)
    ap.add_argument("--dump", default="", help="write proposals and hits as JSON lines here")
    args = ap.parse_args()

    lines = [json.loads(s) for s in (DATA / "gt.jsonl").read_text().splitlines() if s.strip()]
    by_image: dict[str, list[dict]] = defaultdict(list)
    for ln in lines:
        by_image[ln["image"]].append(ln)
    images = sorted(by_image)[:: args.stride][args.start :][: args.limit or None]
    want = {p if p.startswith("sygrid_") else "sygrid_" + p for p in args.parts.split(",") if p}

    meshes: dict[str, trimesh.Trimesh] = {}
    tcache: dict[tuple, gm.TemplateSet] = {}
    stats: dict[str, dict] = defaultdict(lambda: defaultdict(float))
    build_s: dict[str, float] = defaultdict(float)
    prep_ms: list[float] = []
    query_ms: list[float] = []
    dump = open(args.dump, "w") if args.dump else None  # noqa: SIM115 (closed after the loop)
    scale_spread = []
    for im in images:
        gts = by_image[im]
        K = np.asarray(gts[0]["K"], float)
        plane = gts[0]["plane"]
        w, h = gts[0]["width"], gts[0]["height"]
        img = cv2.imread(str(DATA / im), cv2.IMREAD_COLOR)
        # how much the template scale varies over the image on this plane
        corners = np.array(
            [[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1], [(w - 1) / 2, (h - 1) / 2]], float
        )
        z = gm.plane_point_on_ray(corners, K, plane)[:, 2]
        scale_spread.append(float(np.ptp(z) / z[-1]))
        t0 = time.perf_counter()
        bits = gm.orientation_bits(img, mag_threshold=args.mag)
        rms = {
            t: gm.response_maps(gm.spread(bits, t), t=t)
            for t in {*((args.t,) if args.t else (4, 8)), *((args.fine_t,) if args.fine_t else ())}
        }
        prep_ms.append((time.perf_counter() - t0) * 1e3)
        parts = sorted({g["model"] for g in gts})
        for part in parts:
            if want and part not in want:
                continue
            copies = [g for g in gts if g["model"] == part]
            sym = copies[0]["symmetry"]
            if part not in meshes:
                meshes[part] = trimesh.load(DATA / "models" / f"{part}.stl", force="mesh")
            mesh = meshes[part]
            # planes within 5 mm and ~3 deg share templates (rendered on the first of them)
            key = (part, round(plane["d_mm"] / 5.0), tuple(np.round(np.asarray(plane["normal"]) * 20)))
            if key not in tcache:
                tb = time.perf_counter()
                tcache[key] = gm.plane_templates(
                    mesh,
                    sym,
                    K,
                    (w, h),
                    plane,
                    zones=args.zones,
                    spin_step_deg=args.spin_step,
                    t=args.t,
                    n_max=args.points,
                    use_creases=not args.no_creases,
                )
                build_s[part] += time.perf_counter() - tb
            ts = tcache[key]
            N = len(copies)
            tq = time.perf_counter()
            try:
                props = gm.match(
                    rms[ts.t],
                    ts,
                    K,
                    plane,
                    min_score=-1.0,
                    nms_px=args.nms_px,
                    balanced=not args.flat,
                    rm_fine=rms.get(args.fine_t),
                    top_k=2 * N,
                )
            except ValueError as e:  # a plane seen so obliquely that the templates outgrow the maps
                print(f"{im} {part}: no proposals ({e})", file=sys.stderr)
                props = []
            query_ms.append((time.perf_counter() - tq) * 1e3)
            centre = np.asarray(mesh.bounds, float).mean(axis=0)
            gt_uv = np.array(
                [project(np.asarray(g["R"]) @ centre + np.asarray(g["t_mm"]), K) for g in copies]
            )
            pr_uv = np.array([project(p.pose.R @ centre + p.pose.t_mm, K) for p in props]).reshape(-1, 2)
            d = np.linalg.norm(gt_uv[:, None] - pr_uv[None], axis=2) if len(props) else np.zeros((N, 0))
            st = stats[part]
            st["queries"] += 1
            st["ms"] += query_ms[-1]
            for i, g in enumerate(copies):
                vis = g.get("visible_fraction", 1.0)
                lean = lean_deg(np.asarray(g["R"]), plane, ts.families, sym)
                if vis < args.min_visible:
                    continue
                st["copies"] += 1
                st["lean"] += lean > LEAN_DEG
                hitN = bool((d[i, :N] < args.tol_px).any())
                hit2N = bool((d[i, : 2 * N] < args.tol_px).any())
                st["hitN"] += hitN
                st["hit2N"] += hit2N
                st["hitN_upright"] += hitN and lean <= LEAN_DEG
                st["upright"] += lean <= LEAN_DEG
                if dump:
                    dump.write(
                        json.dumps(
                            {
                                "image": im,
                                "part": part,
                                "copy": i,
                                "vis": vis,
                                "lean_deg": lean,
                                "uv": gt_uv[i].tolist(),
                                "hitN": hitN,
                                "hit2N": hit2N,
                                "nearest_px": float(d[i].min()) if d.shape[1] else None,
                            }
                        )
                        + "\n"
                    )
            topN = d[:, :N]
            st["props"] += topN.shape[1]
            st["wrong"] += int((topN.min(axis=0) >= args.tol_px).sum()) if topN.shape[1] else 0
            if dump:
                for k, p in enumerate(props):
                    dump.write(
                        json.dumps(
                            {
                                "image": im,
                                "part": part,
                                "rank": k,
                                "score": p.score,
                                "uv": pr_uv[k].tolist(),
                                "nearest_px": float(d[:, k].min()),
                                "template": p.template,
                            }
                        )
                        + "\n"
                    )

    def row(name, st):
        c = max(st["copies"], 1)
        prec = (st["props"] - st["wrong"]) / max(st["props"], 1)
        return (
            f"| {name} | {int(st['queries'])} | {int(st['copies'])} "
            f"| {int(st['hitN'])} ({100 * st['hitN'] / c:.0f} %) "
            f"| {int(st['hit2N'])} ({100 * st['hit2N'] / c:.0f} %) | {int(st['wrong'])} | {100 * prec:.0f} % "
            f"| {int(st['lean'])} | {int(st['hitN_upright'])}/{int(st['upright'])} "
            f"| {st['ms'] / max(st['queries'], 1):.0f} |"
        )

    print(
        f"images: {len(images)} ({images[0]} .. {images[-1]}); zones {args.zones}, spin {args.spin_step} deg, "
        f"points <= {args.points}, T {args.t or '4/8'}, mag {args.mag}, creases {'off' if args.no_creases else f'> {gm.CREASE_DEG} deg'}, "
        f"nms {args.nms_px} px, {'flat' if args.flat else 'balanced'} weights, fine T {args.fine_t or 'off'}, tol {args.tol_px} px, copies >= {args.min_visible:.0%} visible"
    )
    print(
        f"template depth spread over an image (max-min)/centre: median {100 * np.median(scale_spread):.2f} %, "
        f"max {100 * np.max(scale_spread):.2f} %"
    )
    print()
    print(
        "| part | queries | copies | right @N | right @2N | wrong @N | precision @N | leaning > 15 deg | right @N / not leaning | match ms/query |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    tot: dict[str, float] = defaultdict(float)
    for part in sorted(stats):
        print(row(part.removeprefix("sygrid_"), stats[part]))
        for k, v in stats[part].items():
            tot[k] += v
    print(row("**all**", tot))
    print()
    print(
        f"response maps per image: {np.median(prep_ms):.0f} ms median; match per query: p50 {np.median(query_ms):.0f} ms, "
        f"p90 {np.percentile(query_ms, 90):.0f} ms; template builds: "
        + ", ".join(f"{p.removeprefix('sygrid_')} {s:.1f}s" for p, s in sorted(build_s.items()))
        + f" ({len(tcache)} (part, plane) sets, {sum(len(t.n_pts) for t in tcache.values())} templates)"
    )
    if dump:
        dump.close()


if __name__ == "__main__":
    main()
