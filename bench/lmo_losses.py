"""Where the truth is lost on real photos, per object: edges, proposals, refinement, verdict.

For every query of a set (one gt line at least half visible; ``--every`` n-th) it measures, with the
service's search parameters and distance range:

- ``cov``: the share of the true outline with an edge of matching orientation within 3 px, for the
  pipeline's edges (grey LSD at half size) and for the colour Canny edges (``colour_edges``);
- ``p1`` / ``p2``: the rank of the first candidate within MSPD < 20 px (640 px) of the truth among the
  first pass's and the second pass's distinct candidates (-1: none), as ``pipeline.propose`` proposes
  them from the chosen ``--edges``; ``dg``: the same with the true distance given (first pass);
- ``ref``: the MSPD after the pipeline's check (``check_candidate``: refinement and verdict) of that
  near candidate, and its verification score;
- ``truth``: the true pose checked the same way (refined from the truth; MSPD after, score, reason),
  and its evidence (edge support, unexplained, region_global, shading_r2): the score a perfect
  proposal would get;
- with ``--check-all``: every candidate an estimate checks (the first ``N_VERIFY`` of each pass), refined,
  with its evidence and pose.

Then a table per object (how many queries lose the truth at each stage) and, with ``--check-all``, whether
the evidence tells the truth from the wrong candidates at all: per evidence the AUC of the truth against
them; per verification score (the service's, and others fitted on the tuning sets) the recall at
precision >= 95 % if every query's truth were among its candidates; and the AUC of evidence the service
does not read yet (``candidate_evidence``: colour Canny support, chroma region separability).

    python bench/lmo_losses.py --set lmo_dev --every 6 --check-all [--edges lsd|canny] [--out F.jsonl]
    python bench/lmo_losses.py --set lmo_dev --table-only F.jsonl   # the tables again, from the records
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import service.vision.estimate.evidence as _evidence  # noqa: E402
from bench.accuracy import (  # noqa: E402
    DATA_DIR,
    OUT_DIR,
    gt_bank,
    load_model_info,
    read_colour,
    read_gt,
    read_meta,
    stage_errors,
)
from service.vision import pipeline  # noqa: E402
from service.vision.estimate import colour_edges  # noqa: E402
from service.vision.estimate.chamfer import distance_tensor  # noqa: E402
from service.vision.estimate.edges import detect_segments, to_grey_u8  # noqa: E402
from service.vision.estimate.evidence import colour_frame, face_ids_roi  # noqa: E402
from service.vision.estimate.refine import border_points, verify  # noqa: E402
from service.vision.estimate.verdict import (  # noqa: E402
    FEATURES,
    LOWER_IS_BETTER,
    MODEL_FEATURES,
    WEIGHTS,
    verification_score,
)
from service.vision.geometry.camera import Intrinsics, undistort_image  # noqa: E402
from service.vision.geometry.frames import Pose  # noqa: E402
from service.vision.pipeline import (  # noqa: E402
    DEFAULT_DISTANCE_RANGE_MM,
    DEFAULT_POLICY,
    PoseCandidate,
    check_candidate,
    search_params,
)

N_VERIFY = DEFAULT_POLICY.n_verify  # candidates an estimate checks per pass

_evidence.VISIBLE_PART = True  # the visible part's evidence is what these tables study too

RIGHT_PX = 20.0
MIN_SCORE = 0.98  # verdict.MIN_SCORE, printed for the reader


# the module (the package's ``propose`` is its function)
_PROPOSE = sys.modules["service.vision.pipeline.propose"]


class CannyEdges:
    """While active, ``pipeline.propose`` builds its distance tensor from the colour Canny edges of the
    frame (``colour_edges.canny_tensor``) instead of the grey LSD segments."""

    def __init__(self, image: np.ndarray | None):
        self.image = image
        self._orig = _PROPOSE.distance_tensor

    def __enter__(self):
        if self.image is not None:
            img = self.image

            def dt(seg, *, n_channels, scale):
                return colour_edges.canny_tensor(img, n_channels=n_channels, scale=scale)

            _PROPOSE.distance_tensor = dt
        return self

    def __exit__(self, *exc):
        _PROPOSE.distance_tensor = self._orig


def pose_list(pose: Pose) -> list[list[float]]:
    """R (3 rows) and t_mm as lists: the pose kept in the records, for evidence measured later."""
    return [list(map(float, row)) for row in pose.R] + [list(map(float, pose.t_mm))]


def first_near(mspds: list[float]) -> int:
    return next((i for i, m in enumerate(mspds) if m < RIGHT_PX), -1)


def query(g: dict, set_dir: Path, meta: dict, minfo: dict, edges: str, check_all: bool) -> dict:
    bank = gt_bank(set_dir, g["model"])
    info = load_model_info(set_dir, g["model"], meta, minfo)
    image = read_colour(set_dir / g["image"])
    grey = to_grey_u8(image)
    K = np.asarray(g["K"], float)
    intr = Intrinsics.from_K(K)
    frame = colour_frame(undistort_image(image, intr))
    gt = Pose(np.asarray(g["R"], float), np.asarray(g["t_mm"], float))
    p = search_params(1)

    def mspd(pose: Pose) -> float:
        return float(stage_errors(pose, g, info, K, int(g["width"]))["mspd640_px"])

    border = border_points(bank, gt, intr, (grey.shape[1], grey.shape[0]))
    cov_lsd = float(verify(border, gt, intr, distance_tensor(detect_segments(grey), n_channels=p.n_channels,
                                                            scale=p.fine_scale), score_px=3.0)[0])
    canny = colour_edges.canny_tensor(image, n_channels=p.n_channels, scale=p.fine_scale)
    cov_canny = float(verify(border, gt, intr, canny, score_px=3.0)[0])
    size = K[0, 0] * bank.diameter_mm / float(gt.apply(bank.centre_obj[None])[0, 2])
    kw = dict(distance_mm=None, distance_range_mm=DEFAULT_DISTANCE_RANGE_MM, min_score=None,
              n_channels=p.n_channels)
    t0 = time.process_time()
    with CannyEdges(image if edges == "canny" else None):
        second: list = []
        c1, _, _ = pipeline.propose(bank, grey, intr, distance_range_mm=DEFAULT_DISTANCE_RANGE_MM, params=p,
                                    deferred=second)
        c2 = second[0]() if second else []
        cd, _, _ = pipeline.propose(bank, grey, intr, distance_mm=float(gt.t_mm[2]), params=p)
    search_s = time.process_time() - t0
    m1, m2, md = [mspd(c.pose) for c in c1], [mspd(c.pose) for c in c2], [mspd(c.pose) for c in cd]
    r1, r2, rd = first_near(m1), first_near(m2), first_near(md)
    rec = {"image": g["image"], "model": g["model"], "vis": float(g.get("visible_fraction", 1.0)),
           "size_px": float(size), "z_mm": float(gt.t_mm[2]), "cov_lsd": cov_lsd, "cov_canny": cov_canny,
           "p1": r1, "p2": r2, "dg": rd, "n1": len(c1), "n2": len(c2), "search_cpu_s": search_s}
    near = c1[r1] if r1 >= 0 else (c2[r2] if r2 >= 0 else None)
    if near is not None:
        ch = check_candidate(bank, near, grey, frame, intr, **kw)
        rec |= {"ref_mspd": mspd(ch.refined.pose), "ref_score": ch.verdict.score,
                "ref_reason": ch.verdict.reason}
    tc = check_candidate(bank, PoseCandidate(gt, 0.0, 0.0), grey, frame, intr, **kw)
    ev = tc.verdict.evidence
    rec |= {"truth_mspd": mspd(tc.refined.pose), "truth_score": tc.verdict.score,
            "truth_reason": tc.verdict.reason, "truth_ev": {k: round(float(v), 3) for k, v in ev.items()},
            "truth_pose": pose_list(tc.refined.pose)}
    if check_all:
        # What an estimate checks (the first N_VERIFY of each pass), each with its evidence: an
        # alternative verdict can then be judged offline on these records (``--table-only``).
        rec["checked"] = []
        for pas, cs, ms in ((1, c1, m1), (2, c2, m2)):
            for j, (c, m0) in enumerate(zip(cs[:N_VERIFY], ms[:N_VERIFY], strict=True)):
                ch = check_candidate(bank, c, grey, frame, intr, **kw)
                rec["checked"].append({"pass": pas, "rank": j, "mspd0": m0, "mspd1": mspd(ch.refined.pose),
                                       "z_mm": float(ch.refined.pose.t_mm[2]), "score": ch.verdict.score,
                                       "reason": ch.verdict.reason, "pose": pose_list(ch.refined.pose),
                                       "ev": {k: round(float(v), 4) for k, v in ch.verdict.evidence.items()}})
    return rec


def table(recs: list[dict]) -> None:
    by: dict[str, list[dict]] = defaultdict(list)
    for r in recs:
        by[r["model"]].append(r)
    by["all"] = list(recs)
    print("\n| object | n | size px | vis | cov LSD | cov Canny | near in pass 1 (top 5) | pass 1+2 | "
          "dist given | refined < 20 px | truth score p50 | truth >= 0.98 | truth reasons |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name in sorted(by, key=lambda k: (k == "all", k)):
        rs = by[name]
        n = len(rs)
        p1 = sum(r["p1"] >= 0 for r in rs)
        p1_5 = sum(0 <= r["p1"] < N_VERIFY for r in rs)
        p12 = sum(r["p1"] >= 0 or r["p2"] >= 0 for r in rs)
        dg = sum(r["dg"] >= 0 for r in rs)
        ref = sum(r.get("ref_mspd", np.inf) < RIGHT_PX for r in rs)
        ts = [r["truth_score"] for r in rs]
        reasons: dict[str, int] = defaultdict(int)
        for r in rs:
            reasons[r["truth_reason"]] += 1
        rtxt = ", ".join(f"{k} {v}" for k, v in sorted(reasons.items(), key=lambda kv: -kv[1]))
        print(f"| {name} | {n} | {np.median([r['size_px'] for r in rs]):.0f} | "
              f"{np.median([r['vis'] for r in rs]):.2f} | {np.mean([r['cov_lsd'] for r in rs]):.2f} | "
              f"{np.mean([r['cov_canny'] for r in rs]):.2f} | {p1} ({p1_5}) | {p12} | {dg} | {ref} | "
              f"{np.median(ts):.2f} | {sum(s >= MIN_SCORE for s in ts)} | {rtxt} |")


def tuning_rows() -> list[dict]:
    """The tuning sets' hypotheses (``bench/hypotheses.py features``: synth_a, clutter2, absent2), each
    with its evidence dict as the verdict reads it (older caches keep it in columns)."""
    from bench.fit_verdict import OUT, load

    if not OUT.is_dir():
        return []
    rows = [r for s in ("synth_a", "clutter2", "absent2") for r in load(s)]
    for r in rows:
        if "ev" not in r:
            r["ev"] = {k: r.get(f"{k}1", 0.0) for k in FEATURES} | {"edge_support": r["rscore"],
                                                                   "unexplained": r["unexplained"]}
    return rows


def fitted_weights(use: tuple[str, ...]) -> dict | None:
    """A verification score on the evidence ``use``, fitted on the tuning sets as ``bench/fit_verdict.py``
    fits the service's (never on the set it is judged on here)."""
    from bench.fit_verdict import design, fit_monotone

    rows = tuning_rows()
    if not rows:
        return None
    X, y = design(rows)
    idx = [FEATURES.index(f) for f in use]
    signs = np.array([-1.0 if f in LOWER_IS_BETTER else 1.0 for f in use])
    w = fit_monotone(X[:, idx], y, signs)
    return {"bias": float(w[0])} | {f: float(v) for f, v in zip(use, w[1:], strict=True) if v != 0}


def auc(pos: np.ndarray, neg: np.ndarray) -> float:
    """P(a positive's value exceeds a negative's), ties half."""
    if not len(pos) or not len(neg):
        return float("nan")
    return float(((pos[:, None] > neg[None]).sum() + 0.5 * (pos[:, None] == neg[None]).sum())
                 / (len(pos) * len(neg)))


def verdict_table(recs: list[dict]) -> None:
    """Whether the evidence tells the truth from the wrong candidates on these frames: per evidence, the
    AUC of the truth (refined from the true pose) against the wrong candidates an estimate checks; and
    per score, the recall at precision >= 95 % if every query's truth were among its candidates (the
    answer is the best-scoring of the truth and those candidates)."""
    recs = [r for r in recs if "checked" in r]
    if not recs:
        return
    truth = [r["truth_ev"] for r in recs if r["truth_mspd"] < RIGHT_PX]
    wrong = [c["ev"] for r in recs for c in r["checked"] if c["mspd1"] >= RIGHT_PX]
    print(f"\nEvidence, truth (n={len(truth)}) against wrong candidates checked (n={len(wrong)}): AUC")
    print("| evidence | truth p50 | wrong p50 | AUC |\n|---|---|---|---|")
    for k in FEATURES:
        t, w = np.array([e[k] for e in truth]), np.array([e[k] for e in wrong])
        sign = -1.0 if k in LOWER_IS_BETTER else 1.0
        print(f"| {k} | {np.median(t):.2f} | {np.median(w):.2f} | {auc(sign * t, sign * w):.2f} |")
    scores = {"service (WEIGHTS)": WEIGHTS}
    colour_only = ("edge_support", "colour_edge", "polarity", "region", "region_low", "region_global",
                   "coherence")
    for use in (colour_only, MODEL_FEATURES, FEATURES):
        w = fitted_weights(use)
        if w is not None:
            scores[f"fitted on tuning sets: {','.join(use)}"] = w
    print("\n| score | weights | truth score p50 | AUC truth / wrong | oracle recall at precision >= 95 % "
          "(threshold) | at 0.98: right / wrong |\n|---|---|---|---|---|---|")
    for name, w in scores.items():
        st = np.array([verification_score(e, w) for e in truth])
        sw = np.array([verification_score(e, w) for e in wrong])
        # per query: the answer is the best of the truth (if it refines to within 20 px) and its wrongs
        best = []
        for r in recs:
            ws = [verification_score(c["ev"], w) for c in r["checked"] if c["mspd1"] >= RIGHT_PX]
            tv = verification_score(r["truth_ev"], w) if r["truth_mspd"] < RIGHT_PX else -1.0
            mw = max(ws, default=-1.0)
            best.append((max(tv, mw), tv > mw))
        rec95, thr95 = 0.0, float("nan")
        for thr in sorted({b[0] for b in best}):
            f = [b for b in best if b[0] >= thr]
            right = sum(b[1] for b in f)
            if f and right / len(f) >= 0.95 and right / len(best) > rec95:
                rec95, thr95 = right / len(best), thr
        at = [b for b in best if b[0] >= MIN_SCORE]
        wtxt = " ".join(f"{k}={v:+.2f}" for k, v in w.items())
        print(f"| {name} | {wtxt} | {np.median(st):.2f} | {auc(st, sw):.2f} | {rec95:.0%} ({thr95:.3f}) | "
              f"{sum(b[1] for b in at)} / {sum(not b[1] for b in at)} |")


CHROMA_BINS = 8  # per Lab chroma axis (a, b): 64 bins, lightness left out


def chroma_hist(lab: np.ndarray) -> np.ndarray:
    """Normalised (a, b) histogram of (N, 3) uint8 Lab pixels."""
    a, b = (lab[:, 1].astype(int) * CHROMA_BINS) // 256, (lab[:, 2].astype(int) * CHROMA_BINS) // 256
    q = a * CHROMA_BINS + b
    return np.bincount(q, minlength=CHROMA_BINS ** 2) / max(len(q), 1)


def candidate_evidence(bank, pose: Pose, intr: Intrinsics, image: np.ndarray, lab: np.ndarray,
                       canny_dtt) -> dict | None:
    """Evidence the service does not read yet, measured at ``pose``:

    - ``canny_cov``: the share of the outline with a colour Canny edge of matching orientation within 2 px
      (full resolution): colour edges as chamfer support;
    - ``chroma_sep``: the total-variation distance between the (a, b) chroma histograms of the band just
      inside the silhouette and the band just outside it (the region evidence without lightness: black
      and white marker squares have grey contrast, no chroma contrast);
    - ``chroma_conc``: the share of the silhouette's pixels in its two most frequent chroma bins (a painted
      part is a few colours)."""
    h, w = image.shape[:2]
    border = border_points(bank, pose, intr, (w, h))
    fid, _, (u0, v0) = face_ids_roi(bank, pose, intr, (w, h), margin_px=16)
    mask = fid >= 0
    n_px = int(mask.sum())
    if n_px < 30:
        return None
    win = lab[v0:v0 + mask.shape[0], u0:u0 + mask.shape[1]]
    band = int(np.clip(0.15 * np.sqrt(n_px / np.pi), 3, 14))
    m8 = mask.astype(np.uint8)
    inner = mask & (cv2.distanceTransform(m8, cv2.DIST_L2, 3) <= band)
    outer = ~mask & (cv2.distanceTransform(1 - m8, cv2.DIST_L2, 3) <= band)
    return {"canny_cov": verify(border, pose, intr, canny_dtt, score_px=2.0)[0],
            "chroma_sep": float(0.5 * np.abs(chroma_hist(win[inner]) - chroma_hist(win[outer])).sum()),
            "chroma_conc": float(np.sort(chroma_hist(win[mask]))[-2:].sum())}


def pose_of(pl: list) -> Pose:
    """A record's pose ``[R rows..., t_mm]`` -> Pose."""
    return Pose(np.asarray(pl[:3], float), np.asarray(pl[3], float))


def record_inputs(recs: list[dict], set_dir: Path):
    """Per record with a truth pose: (index, record, (bank, intr, image, Lab image, colour Canny tensor)),
    the arguments ``candidate_evidence`` takes besides the pose; the gt lines read once."""
    gts = {(g["image"], g["model"]): g for g in read_gt(set_dir)}
    for qi, r in enumerate(recs):
        if "truth_pose" not in r:
            continue
        image = read_colour(set_dir / r["image"])[..., :3]
        intr = Intrinsics.from_K(np.asarray(gts[(r["image"], r["model"])]["K"], float))
        yield qi, r, (gt_bank(set_dir, r["model"]), intr, image, cv2.cvtColor(image, cv2.COLOR_BGR2LAB),
                      colour_edges.canny_tensor(image, scale=1.0))


def new_evidence_table(recs: list[dict], set_dir: Path) -> None:
    """``candidate_evidence`` of the truth (refined from the true pose) against the wrong candidates an
    estimate checks, on the poses the records keep (``--check-all`` runs): AUC per evidence."""
    truth: list[dict] = []
    wrong: list[dict] = []
    for _, r, inputs in record_inputs(recs, set_dir):
        if r["truth_mspd"] < RIGHT_PX:
            e = candidate_evidence(inputs[0], pose_of(r["truth_pose"]), *inputs[1:])
            truth += [e] if e else []
        for c in r["checked"]:
            if c["mspd1"] >= RIGHT_PX:
                e = candidate_evidence(inputs[0], pose_of(c["pose"]), *inputs[1:])
                wrong += [e] if e else []
    if not truth or not wrong:
        return
    print(f"\nNew evidence, truth (n={len(truth)}) against wrong candidates checked (n={len(wrong)}): AUC")
    print("| evidence | truth p50 | wrong p50 | AUC |\n|---|---|---|---|")
    for k in truth[0]:
        t, w = np.array([e[k] for e in truth]), np.array([e[k] for e in wrong])
        print(f"| {k} | {np.median(t):.2f} | {np.median(w):.2f} | {auc(t, w):.2f} |")


def ceiling(recs: list[dict], set_dir: Path) -> None:
    """How far the evidence could go at all: a logistic score learnt on these frames themselves (leave one
    image out, so no query is judged by a score fitted on it), on the service's evidence, on
    ``candidate_evidence`` and on both, with each query's truth among its candidates. A diagnostic, not
    an operating point: the service never fits on the set it reports."""
    from bench.fit_verdict import fit_logistic

    rows: list[tuple[int, str, bool, dict, dict]] = []  # query, image, truth?, evidence, new evidence
    for qi, r, inputs in record_inputs(recs, set_dir):
        items = ([(True, r["truth_ev"], r["truth_pose"])] if r["truth_mspd"] < RIGHT_PX else []) + \
            [(False, c["ev"], c["pose"]) for c in r["checked"] if c["mspd1"] >= RIGHT_PX]
        for truth, ev, pl in items:
            ne = candidate_evidence(inputs[0], pose_of(pl), *inputs[1:])
            if ne is not None:
                rows.append((qi, r["image"], truth, ev, ne))
    if not rows:
        return
    n_q = len({r[0] for r in rows})
    print(f"\nCeiling: a score learnt on these {n_q} queries (leave one image out), the truth a candidate")
    print("| evidence | AUC truth / wrong | recall at precision >= 95 % |\n|---|---|---|")
    y = np.array([r[2] for r in rows], float)
    for name, feats in (("service's", lambda r: [r[3][k] for k in FEATURES]),
                        ("candidate_evidence", lambda r: list(r[4].values())),
                        ("both", lambda r: [r[3][k] for k in FEATURES] + list(r[4].values()))):
        X = np.array([feats(r) for r in rows], float)
        X = (X - X.mean(0)) / (X.std(0) + 1e-9)
        s = np.zeros(len(rows))
        for im in {r[1] for r in rows}:
            te = np.array([r[1] == im for r in rows])
            w = fit_logistic(X[~te], y[~te])
            s[te] = 1.0 / (1.0 + np.exp(-(w[0] + X[te] @ w[1:])))
        best = []
        for qi in sorted({r[0] for r in rows}):
            idx = [i for i, r in enumerate(rows) if r[0] == qi]
            b = max(idx, key=lambda i: s[i])
            best.append((s[b], rows[b][2]))
        rec95 = max((sum(b[1] for b in best if b[0] >= t) / len(best) for t in {b[0] for b in best}
                     if np.mean([b[1] for b in best if b[0] >= t]) >= 0.95), default=0.0)
        print(f"| {name} | {auc(s[y > 0], s[y == 0]):.2f} | {rec95:.0%} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--set", default="lmo_dev")
    ap.add_argument("--every", type=int, default=3)
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--edges", choices=["lsd", "canny"], default="lsd",
                    help="what the proposals are made from")
    ap.add_argument("--check-all", action="store_true",
                    help="also check every candidate an estimate checks, with its evidence")
    ap.add_argument("--out", default=None, help="JSON lines of the per-query records")
    ap.add_argument("--table-only", default=None, help="print the table of a saved --out file")
    a = ap.parse_args(argv)
    set_dir = Path(a.set) if Path(a.set).is_dir() else DATA_DIR / a.set
    if a.table_only:
        recs = [json.loads(s) for s in Path(a.table_only).read_text().splitlines() if s.strip()]
        table(recs)
        verdict_table(recs)
        new_evidence_table(recs, set_dir)
        ceiling(recs, set_dir)
        return 0
    meta = read_meta(set_dir)
    gts = [g for g in read_gt(set_dir) if not g.get("absent") and g.get("visible_fraction", 1) >= 0.5]
    gts = gts[a.start::a.every][:a.limit]
    out = Path(a.out) if a.out else OUT_DIR / f"lmo_losses-{Path(a.set).name}-{a.edges}.jsonl"
    out.parent.mkdir(parents=True, exist_ok=True)
    minfo: dict = {}
    recs = []
    with out.open("w") as f:
        for g in gts:
            r = query(g, set_dir, meta, minfo, a.edges, a.check_all)
            recs.append(r)
            f.write(json.dumps(r) + "\n")
            f.flush()
            print(f"{r['image'][-10:]} {r['model']} size {r['size_px']:4.0f} vis {r['vis']:.2f} "
                  f"cov {r['cov_lsd']:.2f}/{r['cov_canny']:.2f} p1 {r['p1']:2d}/{r['n1']} "
                  f"p2 {r['p2']:2d}/{r['n2']} dg {r['dg']:2d} "
                  f"ref {r.get('ref_mspd', float('nan')):6.1f} {r.get('ref_score', float('nan')):.2f} | "
                  f"truth {r['truth_mspd']:5.1f} {r['truth_score']:.2f} {r['truth_reason']} "
                  f"rg {r['truth_ev']['region_global']:.2f} sh {r['truth_ev']['shading_r2']:.2f} "
                  f"es {r['truth_ev']['edge_support']:.2f} un {r['truth_ev']['unexplained']:.2f}", flush=True)
    table(recs)
    verdict_table(recs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
