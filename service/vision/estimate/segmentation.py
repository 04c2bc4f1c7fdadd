"""Colour segmentation into a region hierarchy, as selective search makes one: the image (at
``WORK_WIDTH`` px wide) smoothed by mean shift, split into pixel-connected regions of near-equal colour,
and those merged hierarchically, weakest shared boundary first (the mean Lab contrast across the
boundary: a smoothly shaded part's bands merge before the part meets its floor); every merge is a node.
``regions`` matches the nodes against the part's silhouettes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numba as nb
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from service.vision.estimate.containers import _drop, _get, _put, _rehash, _sift_down, _sift_up, _table

WORK_WIDTH = 320  # px: the segmentation's image width (1/4 of 1280, 1/2 of 640)
MS_SP, MS_SR = 5, 12  # mean shift's spatial and colour radii (working px, Lab-ish units of BGR)
LINK_DE = 4.0  # neighbouring pixels closer than this (Lab, after mean shift) start in one region
MAX_MERGE_DE = 45.0  # regions are not merged across a boundary contrast above this
SPECK_PX = 16.0  # working px: a region this small merges at a contrast discounted by its size


@dataclass
class Regions:
    labels: np.ndarray  # (h, w) int32 initial region of each working pixel
    scale: float  # working px per full-resolution px
    children: np.ndarray  # (C, 2) per node: the two nodes it merged ((-1, -1): an initial region)
    area: np.ndarray  # (C,) working px per node
    bbox: np.ndarray  # (C, 4) x0, y0, x1, y1 (exclusive) working px per node
    born: np.ndarray  # (C,) the boundary contrast at which the node formed (0: initial)
    died: np.ndarray  # (C,) ... at which it merged into a larger one (inf: never), specks aside: its
    # contrast to every neighbour when it stopped growing
    moments: np.ndarray  # (C, 6) m00, m10, m01, m20, m11, m02 (working px)

    _leaf: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False, compare=False)

    def leaf_ranges(self) -> tuple[np.ndarray, np.ndarray]:
        """(every working pixel's initial region's position in a leaf order where each node's initial
        regions are contiguous (h, w) int32, each node's [first, last + 1) positions (C, 2)): a node's
        mask is a range test, made once per hierarchy."""
        if self._leaf is None:
            n0 = int(np.count_nonzero(self.children[:, 0] < 0))
            span = _leaf_spans(self.children, n0)
            self._leaf = (span[:n0, 0].astype(np.int32)[self.labels], span)
        return self._leaf

    def members(self, c: int) -> list[int]:
        out, stack = [], [c]
        while stack:
            n = stack.pop()
            a, b = self.children[n]
            if a < 0:
                out.append(int(n))
            else:
                stack += [int(a), int(b)]
        return out


def shrink(image_bgr: np.ndarray, work_width: int = WORK_WIDTH) -> tuple[float, np.ndarray]:
    """(working px per full-resolution px, the image shrunk to ``work_width``; never enlarged)."""
    H, W = image_bgr.shape[:2]
    sc = min(work_width / W, 1.0)
    w, h = max(int(round(W * sc)), 1), max(int(round(H * sc)), 1)
    return sc, cv2.resize(image_bgr, (w, h), interpolation=cv2.INTER_AREA) if sc < 1 else image_bgr.copy()


def smooth(image_bgr: np.ndarray, work_width: int = WORK_WIDTH) -> tuple[float, np.ndarray]:
    """(working px per full-resolution px, the image shrunk to ``work_width`` and mean-shift smoothed, as
    float32 Lab: L 0..100, a and b centred on 0)."""
    sc, small = shrink(image_bgr, work_width)
    ms = cv2.pyrMeanShiftFiltering(small, MS_SP, MS_SR)
    lab = cv2.cvtColor(ms, cv2.COLOR_BGR2LAB).astype(np.float32)
    lab[..., 0] *= 100.0 / 255.0
    lab[..., 1:] -= 128.0
    return sc, lab


def initial_regions(lab: np.ndarray) -> tuple[np.ndarray, int, np.ndarray, np.ndarray]:
    """(labels (h, w) int32, their number, the Lab contrast of horizontal (h, w-1) and vertical (h-1, w)
    neighbours): pixel-connected regions of neighbours closer than ``LINK_DE``."""
    h, w = lab.shape[:2]
    idx = np.arange(h * w).reshape(h, w)
    dh = np.linalg.norm(lab[:, 1:] - lab[:, :-1], axis=2)
    dv = np.linalg.norm(lab[1:] - lab[:-1], axis=2)
    a = np.concatenate([idx[:, 1:][dh < LINK_DE], idx[1:][dv < LINK_DE]])
    b = np.concatenate([idx[:, :-1][dh < LINK_DE], idx[:-1][dv < LINK_DE]])
    g = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(h * w, h * w))
    n0, lab_id = connected_components(g, directed=False)
    return lab_id.reshape(h, w).astype(np.int32), int(n0), dh, dv


@dataclass
class RegionStats:
    pair: np.ndarray  # (E, 2) int64 neighbouring initial regions i < j, sorted
    s_de: np.ndarray  # (E,) sum of the Lab contrast over their boundary's pixel pairs
    c_de: np.ndarray  # (E,) number of those pixel pairs (float)
    area: np.ndarray  # (n0,) working px (float)
    bbox: np.ndarray  # (n0, 4) x0, y0, x1, y1 (exclusive)
    moments: np.ndarray  # (n0, 6) m00, m10, m01, m20, m11, m02


def region_stats(labels: np.ndarray, n0: int, dh: np.ndarray, dv: np.ndarray) -> RegionStats:
    """The initial regions' boundary contrasts, areas, boxes and raw moments."""
    h, w = labels.shape
    la = np.concatenate([labels[:, 1:].ravel(), labels[1:].ravel()])
    lb = np.concatenate([labels[:, :-1].ravel(), labels[:-1].ravel()])
    de = np.concatenate([dh.ravel(), dv.ravel()])
    cut = la != lb
    la, lb, de = la[cut], lb[cut], de[cut]
    lo, hi = np.minimum(la, lb), np.maximum(la, lb)
    key = lo.astype(np.int64) * n0 + hi
    uk, inv = np.unique(key, return_inverse=True)
    s_de = np.bincount(inv, de)
    c_de = np.bincount(inv).astype(float)
    area0 = np.bincount(labels.ravel(), minlength=n0).astype(float)
    idx = np.arange(h * w)
    ys, xs = np.divmod(idx, w)
    lr = labels.ravel()
    x0 = np.full(n0, w)
    y0 = np.full(n0, h)
    x1 = np.zeros(n0, int)
    y1 = np.zeros(n0, int)
    np.minimum.at(x0, lr, xs)
    np.minimum.at(y0, lr, ys)
    np.maximum.at(x1, lr, xs + 1)
    np.maximum.at(y1, lr, ys + 1)
    # raw moments (additive over merges): every node's second moments come for free
    xs_f, ys_f = xs.astype(float), ys.astype(float)
    mom0 = np.stack([np.bincount(lr, wts, minlength=n0) for wts in
                     (np.ones_like(xs_f), xs_f, ys_f, xs_f * xs_f, xs_f * ys_f, ys_f * ys_f)], 1)
    pair = np.stack([uk // n0, uk % n0], 1)
    return RegionStats(pair, s_de, c_de, area0, np.stack([x0, y0, x1, y1], 1), mom0)


def segment(image_bgr: np.ndarray, work_width: int = WORK_WIDTH) -> Regions:
    """Initial regions (mean shift, then pixel-connected components of near-equal colour) and every
    region of their hierarchical merging by weakest mean boundary contrast (``MAX_MERGE_DE`` at most)."""
    sc, lab = smooth(image_bgr, work_width)
    labels, n0, dh, dv = initial_regions(lab)
    return merge(labels, sc, region_stats(labels, n0, dh, dv))


def merge(labels: np.ndarray, sc: float, st: RegionStats) -> Regions:
    """Hierarchical merging of the initial regions, weakest mean boundary contrast first: every merge is
    a node (children, area, bbox, the contrast at which it formed and at which it was merged away,
    moments). The numba kernel ``_merge_kernel`` pops the same (contrast, i, j) heap entries in the same
    order as the Python reference (``vision/reference/regions.merge_py``), so the hierarchy is identical."""
    n0 = len(st.area)
    children, area, bbox, born, died, mom = _merge_kernel(
        n0, np.ascontiguousarray(st.pair, np.int64), np.ascontiguousarray(st.s_de, np.float64),
        np.ascontiguousarray(st.c_de, np.float64), np.ascontiguousarray(st.area, np.float64),
        np.ascontiguousarray(st.bbox, np.int64), np.ascontiguousarray(st.moments, np.float64),
        float(SPECK_PX), float(MAX_MERGE_DE))
    return Regions(labels, sc, children, area, bbox, born, died, mom)


@nb.njit
def _pair_key(i, j, n0):
    return min(i, j) * n0 + max(i, j)


@nb.njit(cache=True)
def _merge_kernel(n0, pair, s_de, c_de, area0, bbox0, mom0, speck_px, max_de):
    """Union of neighbouring regions, weakest (speck-discounted) mean boundary contrast first, exactly as
    ``merge_py``: a live region is held by a representative id; each neighbouring pair has one edge (sum
    and count of its pixel pairs' contrast) in a hash table by pair and in both representatives' linked lists
    (a slot per side); merging, the side with fewer neighbours hands its edges to the other (an edge to a
    common neighbour is added into the existing one). Heap entries are (contrast, i < j), stale ones
    skipped or pushed again as in the reference."""
    E = pair.shape[0]
    C = max(2 * n0 - 1, 1)
    children = np.full((C, 2), -1, np.int64)
    area = np.zeros(C)
    bbox = np.zeros((C, 4), np.int64)
    born = np.zeros(C)
    died = np.full(C, np.inf)
    mom = np.zeros((C, 6))
    area[:n0] = area0
    bbox[:n0] = bbox0
    mom[:n0] = mom0
    node_of = np.arange(n0)
    deg = np.zeros(n0, np.int64)
    ends = pair.copy()  # (E, 2): the edge's current representatives
    es = s_de.copy()
    ec = c_de.copy()
    alive = np.ones(E, np.bool_)
    head = np.full(n0, -1, np.int64)
    nxt = np.full(2 * E, -1, np.int64)  # slot 2 e + side: the next slot in ends[e, side]'s list
    hk, hv = _table(E)  # pair key -> its edge (an open-addressing table: numba's typed dict was 3x slower)
    n_used = 0
    cap = max(2 * E, 16)
    hd = np.empty(cap)
    hi = np.empty(cap, np.int64)
    hj = np.empty(cap, np.int64)
    n_heap = 0
    for e in range(E):
        i, j = pair[e, 0], pair[e, 1]
        _put(hk, hv, i * n0 + j, e)
        n_used += 1
        for side in range(2):
            x = pair[e, side]
            nxt[2 * e + side] = head[x]
            head[x] = 2 * e + side
            deg[x] += 1
        hd[n_heap] = es[e] / ec[e] * min(1.0, min(area0[i], area0[j]) / speck_px)
        hi[n_heap] = i
        hj[n_heap] = j
        n_heap += 1
    for k in range(n_heap // 2 - 1, -1, -1):
        _sift_down(hd, hi, hj, k, n_heap)
    n_nodes = n0
    while n_heap > 0:
        d, i, j = hd[0], hi[0], hj[0]
        n_heap -= 1
        if n_heap > 0:
            hd[0], hi[0], hj[0] = hd[n_heap], hi[n_heap], hj[n_heap]
            _sift_down(hd, hi, hj, 0, n_heap)
        if d > max_de:
            break
        e = _get(hk, hv, i * n0 + j)
        if e < 0:
            continue
        now = es[e] / ec[e] * min(1.0, min(area[node_of[i]], area[node_of[j]]) / speck_px)
        if now > d + 1e-9:  # a side grew past a speck since: its turn comes later
            if n_heap == cap:
                cap *= 2
                hd2, hi2, hj2 = np.empty(cap), np.empty(cap, np.int64), np.empty(cap, np.int64)
                hd2[:n_heap], hi2[:n_heap], hj2[:n_heap] = hd[:n_heap], hi[:n_heap], hj[:n_heap]
                hd, hi, hj = hd2, hi2, hj2
            hd[n_heap], hi[n_heap], hj[n_heap] = now, i, j
            n_heap += 1
            _sift_up(hd, hi, hj, n_heap - 1)
            continue
        if now < d - 1e-9:  # a fresher entry of the pair was pushed when its contrast changed
            continue
        if deg[i] >= deg[j]:
            big, small = i, j
        else:
            big, small = j, i
        ni, nj = node_of[i], node_of[j]
        k = n_nodes
        n_nodes += 1
        children[k, 0], children[k, 1] = ni, nj
        area[k] = area[ni] + area[nj]
        bbox[k, 0] = min(bbox[ni, 0], bbox[nj, 0])
        bbox[k, 1] = min(bbox[ni, 1], bbox[nj, 1])
        bbox[k, 2] = max(bbox[ni, 2], bbox[nj, 2])
        bbox[k, 3] = max(bbox[ni, 3], bbox[nj, 3])
        born[k] = d
        for q in range(6):
            mom[k, q] = mom[ni, q] + mom[nj, q]
        died[ni] = d
        died[nj] = d
        node_of[big] = k
        _drop(hk, hv, i * n0 + j)
        alive[e] = False
        deg[big] -= 1
        slot = head[small]
        while slot >= 0:
            nslot = nxt[slot]
            e2, side = slot >> 1, slot & 1
            if alive[e2]:
                m = ends[e2, 1 - side]
                _drop(hk, hv, _pair_key(small, m, n0))
                kb = _pair_key(big, m, n0)
                f = _get(hk, hv, kb)
                if f >= 0:  # a common neighbour: its edge to big takes small's boundary
                    es[f] += es[e2]
                    ec[f] += ec[e2]
                    alive[e2] = False
                    deg[m] -= 1
                else:  # small's edge becomes big's
                    f = e2
                    ends[e2, side] = big
                    if 4 * (n_used + 1) > 3 * hk.shape[0]:  # few free slots left: the live keys anew
                        hk, hv = _rehash(hk, hv)
                        n_used = 0
                        for q in range(hk.shape[0]):
                            n_used += hk[q] >= 0
                    _put(hk, hv, kb, e2)
                    n_used += 1
                    nxt[slot] = head[big]
                    head[big] = slot
                    deg[big] += 1
                if n_heap == cap:
                    cap *= 2
                    hd2, hi2, hj2 = np.empty(cap), np.empty(cap, np.int64), np.empty(cap, np.int64)
                    hd2[:n_heap], hi2[:n_heap], hj2[:n_heap] = hd[:n_heap], hi[:n_heap], hj[:n_heap]
                    hd, hi, hj = hd2, hi2, hj2
                hd[n_heap] = es[f] / ec[f] * min(1.0, min(area[k], area[node_of[m]]) / speck_px)
                hi[n_heap] = min(big, m)
                hj[n_heap] = max(big, m)
                n_heap += 1
                _sift_up(hd, hi, hj, n_heap - 1)
            slot = nslot
        head[small] = -1
        deg[small] = 0
    return (children[:n_nodes].copy(), area[:n_nodes].copy(), bbox[:n_nodes].copy(), born[:n_nodes].copy(),
            died[:n_nodes].copy(), mom[:n_nodes].copy())


def region_mask(reg: Regions, c: int) -> np.ndarray:
    """(bbox-sized uint8 0/1) the pixels of node ``c``'s initial regions within its box."""
    x0, y0, x1, y1 = reg.bbox[c]
    pos, span = reg.leaf_ranges()
    win = pos[y0:y1, x0:x1]
    return ((win >= span[c, 0]) & (win < span[c, 1])).view(np.uint8)


@nb.njit(cache=True)
def _leaf_spans(children, n0):
    """(C, 2) each node's [first, last + 1) in a leaf order where every node's leaves are contiguous:
    sizes bottom-up (a node's children come before it), then the roots one after another and each
    node's first child's leaves before its second's, top-down."""
    C = children.shape[0]
    size = np.ones(C, np.int64)
    has_parent = np.zeros(C, np.bool_)
    for k in range(C):
        a, b = children[k, 0], children[k, 1]
        if a >= 0:
            size[k] = size[a] + size[b]
            has_parent[a] = True
            has_parent[b] = True
    span = np.zeros((C, 2), np.int64)
    nxt = 0
    for k in range(C - 1, -1, -1):
        if not has_parent[k]:
            span[k, 0] = nxt
            nxt += size[k]
        span[k, 1] = span[k, 0] + size[k]
        a, b = children[k, 0], children[k, 1]
        if a >= 0:
            span[a, 0] = span[k, 0]
            span[b, 0] = span[k, 0] + size[a]
    return span


def node_means(reg: Regions, values: np.ndarray) -> np.ndarray:
    """(C,) the mean of ``values`` (working px, (h, w)) over each node's pixels."""
    n0 = int(np.count_nonzero(reg.children[:, 0] < 0))
    sums = np.zeros(len(reg.area))
    sums[:n0] = np.bincount(reg.labels.ravel(), np.asarray(values, float).ravel(), minlength=n0)[:n0]
    return _tree_sums(reg.children, sums) / np.maximum(reg.area, 1e-9)


@nb.njit(cache=True)
def _tree_sums(children, sums):
    # a node is made after its children (merge appends): one pass bottom-up
    for k in range(children.shape[0]):
        a, b = children[k, 0], children[k, 1]
        if a >= 0:
            sums[k] = sums[a] + sums[b]
    return sums
