"""The region proposals' hierarchical merging and matching as first written (``estimate/regions.py``):
a reference implementation.

Clarity over speed: the merging is a Python loop over a heap of boundary contrasts with a neighbour
dict per live region, and every candidate region's mask is gathered from its initial regions by
``np.isin``. The service runs the numba kernel ``segmentation.merge`` and the batched ``regions.propose``;
tests and ``bench/region_speed.py`` check that both give the same hierarchy and the same proposals.
"""

from __future__ import annotations

import heapq
import math

import cv2
import numpy as np

from service.vision.bank import TemplateBank
from service.vision.estimate import regions as rg
from service.vision.estimate import segmentation as sg
from service.vision.estimate import shapes
from service.vision.estimate.search import Hypothesis


def merge_py(labels: np.ndarray, sc: float, st: sg.RegionStats) -> sg.Regions:
    """Hierarchical merging: every merge of the weakest shared boundary (mean contrast, specks discounted)
    is a node, up to ``MAX_MERGE_DE``."""
    n0 = len(st.area)
    mom = [st.moments[i] for i in range(n0)]
    # A live region is held by a representative id whose neighbour dict the merge keeps (the larger dict
    # absorbs the smaller, so a floor region with thousands of neighbours is not copied at each merge); a
    # heap entry is stale when its pair's current mean contrast differs from it.
    nb: list[dict[int, list[float]]] = [dict() for _ in range(n0)]
    for (i, j), s, c in zip(st.pair.tolist(), st.s_de, st.c_de, strict=True):
        nb[i][j] = [s, c]
        nb[j][i] = [s, c]
    children: list[tuple[int, int]] = [(-1, -1)] * n0
    area = list(st.area)
    bbox = [[int(v) for v in b] for b in st.bbox]
    born = [0.0] * n0
    died = [np.inf] * n0
    node_of = list(range(n0))  # representative -> its current node

    def key(i: int, j: int, e: list[float]) -> float:
        # a speck (noise, a mean-shift leftover) merges before its contrast says: otherwise a part's
        # region absorbs the specks along its outline one at a time and never stands out as one node
        a = min(area[node_of[i]], area[node_of[j]])
        return e[0] / e[1] * min(1.0, a / sg.SPECK_PX)

    heap = [(key(i, j, e), i, j) for i in range(n0) for j, e in nb[i].items() if i < j]
    heapq.heapify(heap)
    while heap:
        d, i, j = heapq.heappop(heap)
        if d > sg.MAX_MERGE_DE:
            break
        e = nb[i].get(j)
        if e is None:
            continue
        now = key(i, j, e)
        if now > d + 1e-9:  # a side grew past a speck since: its turn comes later
            heapq.heappush(heap, (now, i, j))
            continue
        if now < d - 1e-9:  # a fresher entry of the pair was pushed when its contrast changed
            continue
        big, small = (i, j) if len(nb[i]) >= len(nb[j]) else (j, i)
        ni, nj = node_of[i], node_of[j]
        k = len(children)
        children.append((ni, nj))
        area.append(area[ni] + area[nj])
        bi, bj = bbox[ni], bbox[nj]
        bbox.append([min(bi[0], bj[0]), min(bi[1], bj[1]), max(bi[2], bj[2]), max(bi[3], bj[3])])
        born.append(d)
        mom.append(mom[ni] + mom[nj])
        died.append(np.inf)
        died[ni] = died[nj] = d
        node_of[big] = k
        keep = nb[big]
        del keep[small]
        for m, (s, c) in nb[small].items():
            if m == big:
                continue
            del nb[m][small]
            if m in keep:
                keep[m][0] += s
                keep[m][1] += c
                nb[m][big] = keep[m]  # one shared list per pair
            else:
                keep[m] = [s, c]
                nb[m][big] = keep[m]
            heapq.heappush(heap, (key(big, m, keep[m]), min(big, m), max(big, m)))
        nb[small] = {}
    return sg.Regions(labels, sc, np.array(children, np.int64).reshape(-1, 2), np.array(area),
                     np.array(bbox, int).reshape(-1, 4), np.array(born), np.array(died), np.array(mom))


def members_py(reg: sg.Regions, c: int) -> list[int]:
    out, stack = [], [c]
    while stack:
        n = stack.pop()
        a, b = reg.children[n]
        if a < 0:
            out.append(int(n))
        else:
            stack += [int(a), int(b)]
    return out


def region_mask_py(reg: sg.Regions, c: int) -> np.ndarray:
    x0, y0, x1, y1 = reg.bbox[c]
    lab = reg.labels[y0:y1, x0:x1]
    return np.isin(lab, members_py(reg, c)).astype(np.uint8)


def segment_py(image_bgr: np.ndarray, work_width: int = sg.WORK_WIDTH) -> sg.Regions:
    sc, lab = sg.smooth(image_bgr, work_width)
    labels, n0, dh, dv = sg.initial_regions(lab)
    return merge_py(labels, sc, sg.region_stats(labels, n0, dh, dv))


def propose_py(bank: TemplateBank, image_bgr: np.ndarray, K: np.ndarray,
               distance_range_mm: tuple[float, float], *, n_out: int = 30,
               reg: sg.Regions | None = None) -> tuple[list[rg.RegionProposal], sg.Regions]:
    """``regions.propose`` as first written: one region at a time."""
    sil = rg.silhouettes(bank)
    canon = rg.canonical_templates(bank, sil)
    t_area = canon.sum(2)  # (S, N)
    reg = reg if reg is not None else segment_py(image_bgr)
    sc = reg.scale
    a_lo, a_hi = rg.projected_area_range(bank, sil, K, distance_range_mm)
    area_full = reg.area / sc**2
    cand = np.flatnonzero((area_full >= rg.AREA_SLACK[0] * a_lo) & (area_full <= rg.AREA_SLACK[1] * a_hi))
    h, w = reg.labels.shape
    bw = reg.bbox[:, 2] - reg.bbox[:, 0]
    bh = reg.bbox[:, 3] - reg.bbox[:, 1]
    cand = cand[(bw[cand] < 0.9 * w) & (bh[cand] < 0.9 * h) & (reg.area[cand] >= 12)]
    el, co = rg.moment_shape(reg.moments[cand])
    ok_t = sil.area_n > 0
    d_shape = (np.abs(el[:, None] - sil.elong[None, ok_t])
               + np.abs(co[:, None] - sil.compact[None, ok_t])).min(1)
    cand = cand[d_shape < rg.SHAPE_GATE]
    cand = cand[np.argsort(-reg.died[cand], kind="stable")[:rg.N_REGIONS]]
    fx, fy = float(K[0, 0]), float(K[1, 1])
    F = np.diag([fx, fy])
    z_ref = bank.reference_distance_mm
    bad_t = ~ok_t
    info = []
    rows: list[np.ndarray] = []
    for c in cand:
        m = region_mask_py(reg, int(c))
        mo = cv2.moments(m, True)
        if mo["m00"] < 12:
            continue
        ang_r, el_r = shapes.principal_axis(mo)
        turns = (0.0, 180.0) if el_r < shapes.ROUND_ELONG else tuple(range(0, 360, 30))
        x0, y0 = reg.bbox[c, :2]
        c_full = (np.array([mo["m10"], mo["m01"]]) / mo["m00"] + np.array([x0, y0]) + 0.5) / sc - 0.5
        info.append((int(c), ang_r, turns, c_full, mo["m00"] / sc**2, len(rows)))
        rows += [shapes.canonical(m, mo, ang_r + math.radians(tn)).ravel() for tn in turns]
    if not rows:
        return [], reg
    Rc_all = np.stack(rows)
    r_area_all = Rc_all.sum(1)
    inter_all = [Rc_all @ canon[k].T for k in range(len(shapes.SCALES))]
    out: list[rg.RegionProposal] = []
    for c, ang_r, turns, c_full, A_r, r0 in info:
        sl = slice(r0, r0 + len(turns))
        r_area = r_area_all[sl]
        scored = []
        for k, s_a in enumerate(shapes.SCALES):
            inter = inter_all[k][sl]
            iou = inter / (r_area[:, None] + t_area[k][None] - inter + 1e-9)
            iou[:, bad_t] = 0
            kz = np.sqrt(s_a * A_r / (np.maximum(sil.area_n, 1e-12) * fx * fy))
            z = z_ref / kz
            iou[:, (z < distance_range_mm[0]) | (z > distance_range_mm[1])] = 0
            top = np.unravel_index(np.argsort(-iou, axis=None)[:rg.PER_REGION * 4], iou.shape)
            for ti, t in zip(*top, strict=True):
                scored.append((float(iou[ti, t]), int(t), float(turns[ti]), float(z[t]), float(kz[t])))
        scored.sort(key=lambda x: -x[0])
        n_kept = 0
        for iou_v, t, tn, z, kz in scored:
            if iou_v <= 0 or n_kept >= rg.PER_REGION:
                break
            phi = math.degrees(ang_r - sil.axis_rad[t]) + tn
            cp, sp = math.cos(math.radians(phi)), math.sin(math.radians(phi))
            uv_ref = c_full - F @ np.array([[cp, -sp], [sp, cp]]) @ sil.centroid_n[t] * kz
            hyp = Hypothesis(t, float(phi % 360), z, uv_ref)
            if any(rg._same(hyp, q.hyp, bank) for q in out if q.region == c):
                continue
            out.append(rg.RegionProposal(hyp, iou_v, c))
            n_kept += 1
    out.sort(key=lambda r: -r.iou)
    kept: list[rg.RegionProposal] = []
    for r in out:
        if any(rg._same(r.hyp, q.hyp, bank) for q in kept):
            continue
        kept.append(r)
        if len(kept) >= n_out:
            break
    return kept, reg
