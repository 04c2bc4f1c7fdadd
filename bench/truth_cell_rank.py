"""Where the truth's own level-A cell ranks among all anchors, by chamfer cost and by contrast blends.

``bench/stages.py`` ranks the best anchor near the truth by that anchor's best template, which is often
another rotation or distance (a lucky fit near the part). This asks what a ranking must achieve for level
A to propose the truth itself: the truth-like templates (level-A templates whose rotation, about the
viewing ray, lies within ``TOL_SYM_DEG`` (revolved part: of its axis) or ``TOL_ANY_DEG`` of the truth's,
at the scales within 0.75 depth steps of the true depth) at the anchors within ``NEAR_PX`` of the
truth's reference point; their best cost, over the local background as the search ranks
(``SearchParams.bg_norm``), against every other anchor's best. ``rank`` = how many other anchors rank
before it: level A's ``n_peaks`` could only start level B from the truth's cell where it is below about
``n_peaks`` (peak suppression aside). A truth cell over level A's acceptance bound (``accept_frac``)
ranks after every anchor.

Each configuration ``w:d`` scans level A on ``contrast.Contrast``'s blend (1 - w) DT3 + w contrast cost
with the contrast taken ``d`` full-res px either side of the outline (``w:d:0``: not normalised by the
local mean contrast); ``0:8`` is the chamfer cost alone.

    python bench/truth_cell_rank.py --set clutter2 [--every 3] [--configs 0:8,0.5:8,1:8] [--distance-given]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.accuracy import (  # noqa: E402
    DATA_DIR,
    gt_bank,
    read_colour,
    read_gt,
)
from bench.stages import edge_tensor  # noqa: E402
from service.vision.estimate import coarse, contrast, level_a  # noqa: E402
from service.vision.estimate.chamfer import DT_QUANT, pooled_and_quantised, quantised  # noqa: E402
from service.vision.estimate.edges import to_grey_u8  # noqa: E402
from service.vision.geometry.camera import Intrinsics, project, ray_rotation  # noqa: E402
from service.vision.geometry.frames import Pose  # noqa: E402
from service.vision.pipeline import DEFAULT_DISTANCE_RANGE_MM, DEFAULT_POLICY  # noqa: E402

NEAR_PX = 17.0  # full-res px: the anchors (16 px apart) next to the truth's reference point
TOL_SYM_DEG = 8.0  # a revolved part's level-A views are 6 deg apart
TOL_ANY_DEG = 20.0  # any other part's: 20 deg views x 10 deg in-plane steps


def truth_templates(bank, tpl, R_ray: np.ndarray, gt: Pose) -> np.ndarray:
    """Level-A template indices whose rotation about the ray is within tolerance of the truth's."""
    axes = level_a.template_axes(bank, tpl)
    Rt = R_ray.T @ gt.R
    if bank.symmetry_axis_obj is not None:
        a_t = Rt @ np.asarray(bank.symmetry_axis_obj, float)
        # level A keeps one of each mirror pair: the axis mirrored through the image plane has the same
        # outline (up to perspective), and level B tries it
        cos = np.maximum(axes[:, 0] @ a_t, axes[:, 0] @ (a_t * np.array([1.0, 1.0, -1.0])))
        ang = np.degrees(np.arccos(np.clip(cos, -1, 1)))
        return np.flatnonzero(ang <= TOL_SYM_DEG)
    tr = np.einsum("tij,ij->t", axes, Rt)
    return np.flatnonzero(np.degrees(np.arccos(np.clip((tr - 1) / 2, -1, 1))) <= TOL_ANY_DEG)


def truth_rank(g: dict, set_dir: Path, configs: list[tuple[float, float]], distance_given: bool) -> list[int]:
    p = DEFAULT_POLICY.search_params
    bank = gt_bank(set_dir, g["model"])
    image = read_colour(set_dir / g["image"])
    grey = to_grey_u8(image)
    K = np.asarray(g["K"], float)
    intr = Intrinsics.from_K(K)
    gt = Pose(np.asarray(g["R"], float), np.asarray(g["t_mm"], float))
    dist = float(g["t_mm"][2]) if distance_given else None
    dtt = edge_tensor("lsd", image, grey, 0.5, p)
    dtt_a, _, _ = pooled_and_quantised(dtt, p.level_scale, p.rank_tau_px * dtt.scale)
    z_ref, scales = (dist, np.array([1.0])) if dist is not None else \
        coarse.depth_scales(DEFAULT_DISTANCE_RANGE_MM, p.depth_step)
    tpl = level_a._cached_level_a(bank, intr, grey.shape, p, dist, z_ref)
    off_u, off_v = level_a.scaled_offsets(tpl, scales)
    c_uv = project(gt.apply(bank.centre_obj[None]), K)[0]
    zt = float(gt.apply(bank.centre_obj[None])[0, 2])
    tok = truth_templates(bank, tpl, ray_rotation(c_uv, K)[1], gt)
    r_bg = int(coarse.BG_WINDOW_EXTENT * tpl.extent_px * float(np.median(scales)))
    bg = level_a.background_cost(dtt_a, r_bg) if p.bg_norm else np.ones(dtt_a.dt.shape[1:])
    out = []
    for w, d, *norm in configs:
        cp = contrast.ContrastParams(weight=w, d_px=d, normalise=not norm or norm[0] != 0)
        con = contrast.Contrast(image, p.n_channels, p.level_scale, cp) if w > 0 else None
        lac = (lambda q, tq, con=con: con.level_a(q, tq, r_bg)) if con is not None else None
        au, av, tile, cost, _, _ = level_a.scan_level_a(dtt_a, tpl, scales, grey.shape, p, level_a_cost=lac)
        dd = np.hypot((au + 0.5) / p.level_scale - 0.5 - c_uv[0], (av + 0.5) / p.level_scale - 0.5 - c_uv[1])
        near = np.flatnonzero(dd <= NEAR_PX)
        if len(near) == 0 or len(tok) == 0:
            out.append(len(au))  # the truth's cell is not even scanned (too few edges near it)
            continue
        dt_q, tau_q = quantised(dtt_a, dtt_a.tau_px)
        if lac is not None:
            dt_q = lac(dt_q, tau_q)
        # level A's own acceptance: a template averaging over accept_frac x tau is never a peak
        accept_q = int(p.accept_frac * tau_q) * off_u.shape[3]
        best = np.inf
        for di in range(len(scales)):
            z = tpl.z_ref_mm[tile[near]][:, tok] / scales[di]
            ok_z = np.abs(np.log(z / zt)) <= 0.75 * np.log1p(p.depth_step)
            if not ok_z.any():
                continue
            ou, ov = off_u[:, di:di + 1][:, :, tok], off_v[:, di:di + 1][:, :, tok]
            c, _ = level_a._scan_templates(dt_q, tau_q, ou, ov, tpl.chan[tok], au[near], av[near], tile[near],
                                          np.full(len(near), accept_q, np.int64))
            c = np.where(ok_z, c / DT_QUANT, np.inf) / bg[av[near], au[near]][:, None]
            best = min(best, float(c.min()))
        rank = cost / bg[av, au]
        far = np.setdiff1d(np.arange(len(au)), near)
        # not accepted: ranks after every anchor that is
        out.append(int(np.sum(np.isfinite(rank[far]) & (rank[far] < best))) if np.isfinite(best) else len(au))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--set", default="clutter2")
    ap.add_argument("--every", type=int, default=1)
    ap.add_argument("--configs", default="0:8,0.5:8,1:8",
                    help="w:d[:0],... (w = 0: chamfer alone; :0 contrast not normalised by its surroundings)")
    ap.add_argument("--distance-given", action="store_true")
    a = ap.parse_args(argv)
    set_dir = Path(a.set) if Path(a.set).is_dir() else DATA_DIR / a.set
    configs = [tuple(float(x) for x in c.split(":")) for c in a.configs.split(",")]
    gts = [g for g in read_gt(set_dir) if not g.get("absent") and g.get("visible_fraction", 1) >= 0.5]
    gts = gts[::a.every]
    ranks = []
    print("image model | " + " ".join(":".join(f"{x:g}" for x in c) for c in configs))
    for g in gts:
        r = truth_rank(g, set_dir, configs, a.distance_given)
        ranks.append(r)
        print(f"{g['image'][-8:]} {g['model']} | " + " ".join(f"{x:6d}" for x in r), flush=True)
    R = np.array(ranks)
    print(f"\n| {a.set} ({len(gts)}{', distance given' if a.distance_given else ''}) | rank p50 | "
          "in first 12 | in first 30 | in first 80 |\n|---|---|---|---|---|")
    for k, (w, d, *norm) in enumerate(configs):
        name = "chamfer (DT3) alone" if w == 0 else f"(1 - {w:g}) DT3 + {w:g} contrast, d {d:g} px" + \
            (", not normalised" if norm and norm[0] == 0 else "")
        r = R[:, k]
        print(f"| {name} | {np.median(r):.0f} | {int(np.sum(r < 12))} | {int(np.sum(r < 30))} | "
              f"{int(np.sum(r < 80))} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
