"""Where the truth is lost in the proposal engine, per query: the edges, level A, level B, the polish.

For every query (an image and a model with its ground truth) it runs the proposal engine's stages
as ``pipeline.propose`` does (LSD, the distance tensor, ``coarse.coarse_search``), with the search's
stages observed, and prints per query and summed over the set:

- ``size``: the part's projected diameter, px; ``cov``: the share of the true outline with an edge
  of matching orientation within 3 px (``refine.verify`` on the search's own distance tensor);
- ``A``: rank (0-based, by level-A cost) of the best anchor within ``NEAR_PX`` of the truth's
  reference point among all scanned anchors, and whether a picked peak lies within level B's
  radius of it (``peak``);
- ``truth cost``: the chamfer cost (level B's, truncated) of the true pose itself, and how many
  proposals cost less (when some do, the search ranking by cost cannot put the truth first);
- ``B``: whether a level-B local scan ended within MSPD < 20 px (``inB``) and that scan's rank by
  level-B cost; ``P``: whether a polished proposal is within MSPD < 20 px and its rank.

    python bench/stages.py --set lmo_dev --every 8 [--distance-given] [--lsd-scale 1 --fine-scale 1]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.accuracy import (  # noqa: E402
    DATA_DIR,
    gt_bank,
    load_model_info,
    read_colour,
    read_gt,
    read_meta,
    stage_errors,
)
from service.vision.bank import view_dirs_obj  # noqa: E402
from service.vision.estimate import coarse, contrast, level_a, level_b  # noqa: E402
from service.vision.estimate.chamfer import distance_tensor, pooled_distance_tensor  # noqa: E402
from service.vision.estimate.edges import detect_segments, to_grey_u8  # noqa: E402
from service.vision.estimate.refine import border_points, verify  # noqa: E402
from service.vision.geometry.camera import Intrinsics, project, ray_rotation  # noqa: E402
from service.vision.geometry.frames import Pose  # noqa: E402
from service.vision.pipeline import DEFAULT_DISTANCE_RANGE_MM, DEFAULT_POLICY  # noqa: E402

RIGHT_PX = 20.0
NEAR_PX = 12.0  # full-res px: an anchor this close to the truth's reference point is "the truth's"


class Observer:
    """Wraps coarse.scan_level_a / pick_peaks / local_scan to keep what they return."""

    def __init__(self):
        self.anchors = None  # the first level-A scan's (the DT3's, or the blend's when it replaces it)
        self.anchors_all: list[tuple] = []  # every level-A scan (a second: the contrast blend's)
        self.peaks: list[int] = []  # every peak picked (with contrast extra peaks: both scans')
        self.scans: list[tuple] = []
        self._orig = (coarse.scan_level_a, coarse.pick_peaks, coarse.local_scan)

    def __enter__(self):
        def scan_level_a(*a, **k):
            out = self._orig[0](*a, **k)
            self.anchors_all.append(out)
            self.anchors = self.anchors_all[0]
            return out

        def pick_peaks(*a, **k):
            out = self._orig[1](*a, **k)
            self.peaks = self.peaks + out
            return out

        def local_scan(bank, h, *a, **k):
            hyp, q = self._orig[2](bank, h, *a, **k)
            self.scans.append((h, hyp, q))
            return hyp, q

        coarse.scan_level_a, coarse.pick_peaks, coarse.local_scan = scan_level_a, pick_peaks, local_scan
        return self

    def __exit__(self, *exc):
        coarse.scan_level_a, coarse.pick_peaks, coarse.local_scan = self._orig


def mspd_of(bank, hyps, K, dist, g, info) -> list[float]:
    if not hyps:
        return []
    Rs, ts = coarse.poses_of(bank, hyps, K, dist)
    return [stage_errors(Pose(R, t), g, info, K, int(g["width"]))["mspd640_px"]
            for R, t in zip(Rs, ts, strict=True)]


def edge_tensor(kind: str, image: np.ndarray, grey: np.ndarray, lsd_scale: float, p):
    """The search's distance tensor at ``p.fine_scale`` from one of the edge sources compared."""
    if kind == "lsd":
        seg = detect_segments(grey, scale=lsd_scale)
        return distance_tensor(seg, n_channels=p.n_channels, scale=p.fine_scale)
    from service.vision.estimate import colour_edges

    if kind == "lsd-bgr":
        seg = colour_edges.channel_segments(image, scale=lsd_scale)
        return distance_tensor(seg, n_channels=p.n_channels, scale=p.fine_scale)
    if kind == "canny-bgr":
        return colour_edges.canny_tensor(image, n_channels=p.n_channels, scale=p.fine_scale)
    raise ValueError(kind)


def target_queries(a) -> tuple[Path, dict, list[dict]]:
    """(set folder, its meta, the gt lines of targets at least half visible, ``--start`` / ``--every`` /
    ``--limit`` applied) of ``--set`` (a name under the data folder, or a folder)."""
    set_dir = Path(a.set) if Path(a.set).is_dir() else DATA_DIR / a.set
    gts = [g for g in read_gt(set_dir) if not g.get("absent") and g.get("visible_fraction", 1) >= 0.5]
    return set_dir, read_meta(set_dir), gts[a.start::a.every][:a.limit]


def run(a) -> None:
    set_dir, meta, gts = target_queries(a)
    minfo: dict = {}
    p = replace(DEFAULT_POLICY.search_params, fine_scale=a.fine_scale, level_scale=a.level_scale,
                n_peaks=a.n_peaks,
                n_polish=a.n_polish, peak_accept_ratio=a.accept_ratio,
                bg_norm=DEFAULT_POLICY.search_params.bg_norm if a.bg_norm is None else a.bg_norm == "on",
                templates_per_peak=a.templates_per_peak or DEFAULT_POLICY.search_params.templates_per_peak,
                template_peaks=a.template_peaks or DEFAULT_POLICY.search_params.template_peaks)
    coarse.CONTRAST_TEMPLATES = a.contrast_templates
    tot = {"n": 0, "peak": 0, "inB": 0, "inP": 0, "inP1": 0, "inP5": 0, "cheap": 0, "oracleB": 0}
    cov_all, search_ms, ranks_a, ranks_c = [], [], [], []
    cp = contrast.ContrastParams(weight=a.contrast_weight, weight_b=a.contrast_weight_b, d_px=a.contrast_d,
                                 normalise=a.contrast_norm == "on")
    print("q image model size vis cov | A rank/n peak | B in rank | P in rank")
    for qi, g in enumerate(gts):
        bank = gt_bank(set_dir, g["model"])
        info = load_model_info(set_dir, g["model"], meta, minfo)
        image = read_colour(set_dir / g["image"])
        grey = to_grey_u8(image)
        K = np.asarray(g["K"], float)
        intr = Intrinsics.from_K(K)
        gt = Pose(np.asarray(g["R"], float), np.asarray(g["t_mm"], float))
        dist = float(g["t_mm"][2]) if a.distance_given else None
        dtt = edge_tensor(a.edges, image, grey, a.lsd_scale, p)
        border = border_points(bank, gt, intr, (grey.shape[1], grey.shape[0]))
        cov = verify(border, gt, intr, dtt, score_px=3.0)[0]
        cov_all.append(cov)
        c_uv = project(gt.apply(bank.centre_obj[None]), K)[0]
        size = K[0, 0] * bank.diameter_mm / float(gt.apply(bank.centre_obj[None])[0, 2])
        t0 = time.perf_counter()
        con = contrast.Contrast(image, p.n_channels, p.level_scale, cp) if a.contrast_weight > 0 else None
        with Observer() as ob:
            hyps = coarse.coarse_search(bank, dtt, intr, grey.shape, p, distance_mm=dist,
                                        distance_range_mm=DEFAULT_DISTANCE_RANGE_MM, contrast=con,
                                        extra_peaks=a.contrast_extra)
        search_ms.append(1000 * (time.perf_counter() - t0))
        au, av, _, cost, _, _ = ob.anchors
        uf = (au + 0.5) / p.level_scale - 0.5
        vf = (av + 0.5) / p.level_scale - 0.5
        dd = np.hypot(uf - c_uv[0], vf - c_uv[1])

        def truth_rank(cost, dd=dd):
            order = np.argsort(np.where(np.isfinite(cost), cost, np.inf))
            rank_of = np.empty(len(order), int)
            rank_of[order] = np.arange(len(order))
            near = np.flatnonzero((dd <= NEAR_PX) & np.isfinite(cost))
            return int(rank_of[near].min()) if len(near) else -1

        a_rank = truth_rank(cost)
        c_rank = truth_rank(ob.anchors_all[-1][3]) if len(ob.anchors_all) > 1 else a_rank
        ranks_a.append(a_rank if a_rank >= 0 else len(cost))
        ranks_c.append(c_rank if c_rank >= 0 else len(cost))
        peak = any(dd[i] <= p.local_radius_px for i in ob.peaks)
        scanned = [s for s in ob.scans if s[1] is not None]
        m_b = mspd_of(bank, [s[1] for s in scanned], K, dist, g, info)
        qs = np.array([s[2] for s in scanned])
        b_in = [i for i, m in enumerate(m_b) if m < RIGHT_PX]
        b_rank = int(min(np.sum(qs < qs[i]) for i in b_in)) if b_in else -1
        m_p = mspd_of(bank, hyps, K, dist, g, info)
        v_gt = int(np.argmax(view_dirs_obj(bank) @ (gt.R.T @ (gt.apply(bank.centre_obj[None])[0]))))
        tc = float(level_b.evaluate(bank, np.array([v_gt]), gt.R[None], gt.t_mm[None], K, dtt, p.fine_points,
                                   p.score_px, p.rank_tau_px)[0][0])
        if p.bg_norm:  # the truth's cost over its background, as the search ranks
            z_ref, sc = (dist, np.array([1.0])) if dist is not None else \
                coarse.depth_scales(DEFAULT_DISTANCE_RANGE_MM, p.depth_step)
            lv = level_a._cached_level_a(bank, intr, grey.shape, p, dist, z_ref)
            r_bg = int(coarse.BG_WINDOW_EXTENT * lv.extent_px * float(np.median(sc)))
            bgm = level_a.background_cost(pooled_distance_tensor(dtt, p.level_scale), r_bg)
            tc_rank = tc / float(level_a._bg_at(bgm, c_uv, p.level_scale)[0])
        else:
            tc_rank = tc
        beat = sum(h.rank_cost < tc_rank for h in hyps)
        # Oracle: level B started from the truth's own level-A cell (nearest level-A view, in-plane angle
        # on level A's 10-degree grid, the anchor nearest the truth's reference point, true depth).
        _, R_ray = ray_rotation(c_uv, K)
        lvl_views = level_a._level_a_views(bank, p.view_step_deg if bank.symmetry_axis_obj is not None
                                          else p.view_step_any_deg)
        zd = view_dirs_obj(bank)[lvl_views] @ (gt.R.T @ R_ray[:, 2])
        v0 = int(lvl_views[int(np.argmax(zd))])
        M = R_ray.T @ gt.R @ bank.R_tpl_obj[v0].T
        phi0 = round(np.degrees(np.arctan2(M[1, 0], M[0, 0])) / p.inplane_step_deg) * p.inplane_step_deg
        step = p.anchor_stride / p.level_scale
        uv0 = np.round((c_uv + 0.5) / step) * step - 0.5
        z0 = float(gt.apply(bank.centre_obj[None])[0, 2])
        dt_q, tau_q = coarse.quantised(dtt, p.rank_tau_px * dtt.scale)
        oh, _ = level_b.local_scan(bank, coarse.Hypothesis(v0, float(phi0), z0, uv0), dt_q, tau_q, dtt, K, p,
                                  distance_mm=dist, accept_q=int(tau_q))
        m_o = mspd_of(bank, [oh], K, dist, g, info)[0] if oh is not None else np.inf
        tot["oracleB"] += m_o < RIGHT_PX
        tot["cheap"] += beat == 0
        p_in = [i for i, m in enumerate(m_p) if m < RIGHT_PX]
        tot["n"] += 1
        tot["peak"] += peak
        tot["inB"] += bool(b_in)
        tot["inP"] += bool(p_in)
        tot["inP1"] += bool(p_in) and p_in[0] == 0
        tot["inP5"] += bool(p_in) and p_in[0] < 5
        print(f"{qi:3d} {g['image'][-8:]} {g['model']:7s} {size:5.0f} {g.get('visible_fraction', 1):.2f} "
              f"{cov:.2f} | {a_rank:5d}/{int(np.isfinite(cost).sum()):5d} c {c_rank:5d} {int(peak)} | "
              f"{int(bool(b_in))} {b_rank:3d}/{len(scanned):2d} | "
              f"{int(bool(p_in))} {p_in[0] if p_in else -1:2d}/{len(hyps):2d}  "
              f"best {min(m_p, default=np.inf):6.1f} | "
              f"truth cost {tc:4.2f} "
              f"best {hyps[0].cost if hyps else np.inf:4.2f} cheaper {beat} | oracle B {m_o:5.1f}",
              flush=True)
    n = tot["n"]
    print(f"\n{a.set} {a.edges} {a.lsd_scale} fine {a.fine_scale} level {a.level_scale} peaks {a.n_peaks} "
          f"polish {a.n_polish} bg_norm {p.bg_norm} "
          f"templates/peak {p.templates_per_peak} at {p.template_peaks} peaks "
          f"dist {'given' if a.distance_given else 'not given'}: n={n} "
          f"contrast w {a.contrast_weight} / {a.contrast_weight_b} d {a.contrast_d} norm {a.contrast_norm} "
          f"extra {a.contrast_extra} templates {a.contrast_templates}: "
          f"cov mean {np.mean(cov_all):.2f} | truth's level-A rank p50 {np.median(ranks_a):.0f} "
          f"(second scan {np.median(ranks_c):.0f}) | peak near truth {tot['peak']} | "
          f"truth after level B {tot['inB']} | "
          f"in proposals {tot['inP']} (first {tot['inP1']}, top5 {tot['inP5']}) | "
          f"truth cheaper than every proposal {tot['cheap']} | "
          f"level B from the truth's level-A cell reaches it {tot['oracleB']} | "
          f"search p50 {np.median(search_ms):.0f} ms")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--set", default="lmo_dev")
    ap.add_argument("--every", type=int, default=1)
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--distance-given", action="store_true")
    ap.add_argument("--edges", default="lsd", choices=["lsd", "lsd-bgr", "canny-bgr"])
    ap.add_argument("--lsd-scale", type=float, default=0.5)
    ap.add_argument("--fine-scale", type=float, default=DEFAULT_POLICY.search_params.fine_scale)
    ap.add_argument("--level-scale", type=float, default=DEFAULT_POLICY.search_params.level_scale)
    ap.add_argument("--n-peaks", type=int, default=30)
    ap.add_argument("--n-polish", type=int, default=12)
    ap.add_argument("--accept-ratio", type=float, default=3.0)
    ap.add_argument("--bg-norm", choices=["on", "off"], default=None,
                    help="SearchParams.bg_norm (default: the service's)")
    ap.add_argument("--templates-per-peak", type=int, default=None,
                    help="SearchParams.templates_per_peak (default: the service's)")
    ap.add_argument("--template-peaks", type=int, default=None,
                    help="SearchParams.template_peaks (default: the service's)")
    ap.add_argument("--contrast-weight", type=float, default=0.0,
                    help="level A scans (1 - w) DT3 + w oriented contrast cost (contrast.py); 0: off")
    ap.add_argument("--contrast-weight-b", type=float, default=0.0,
                    help="level B ranks by (1 - w) chamfer + w tau contrast cost")
    ap.add_argument("--contrast-d", type=float, default=contrast.CONTRAST_D_PX)
    ap.add_argument("--contrast-norm", choices=["on", "off"], default="on")
    ap.add_argument("--contrast-templates", action=argparse.BooleanOptionalAction, default=True,
                    help="with --contrast-extra: its peaks' other distinct templates (on the blend) too")
    ap.add_argument("--contrast-extra", type=int, default=0,
                    help="0: the blend replaces level A's ranking; k: k extra peaks from it (second pass)")
    run(ap.parse_args(argv))
    return 0


if __name__ == "__main__":
    sys.exit(main())
