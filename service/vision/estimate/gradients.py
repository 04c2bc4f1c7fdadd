"""Gradient orientations of a colour image, spread into LINE-2D response maps, and the template scores
read from them.

Per pixel: Sobel on each channel, the strongest channel's gradient, its orientation quantised to
``N_ORI`` bins over 180 deg (the edge's polarity is not kept: a metal part is brighter or darker than
the table depending on the light), where the magnitude reaches ``MAG_THRESHOLD``, kept only where at
least 5 of its 3 x 3 neighbours agree (a stable direction, not noise). Near a bin boundary the
neighbouring bin is set too. The bits are OR-ed over ``t`` x ``t`` pixels (the matching tolerance), then
read as response maps: 4 where a point's own orientation is present, 1 where a neighbouring one is, else
0, stored "linearised" (one map per offset mod t) so that a template scores on the t-pixel grid with
contiguous adds (Hinterstoisser et al., LINE-2D).

A template is a set of points (offset from an anchor pixel, orientation bin, weight summing to 1): its
score at an anchor is the weighted mean response / 4, the share of its points whose gradient agrees.
A half-hidden part scores its visible half, and texture does not add up beyond 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

from service.vision import threads

N_ORI = 8  # orientation bins over 180 deg
MAG_THRESHOLD = 40.0  # Sobel (3 x 3) magnitude on 0..255 channels below which a pixel has no orientation
BLUR_SIGMA = 1.0  # Gaussian blur before the gradient (px)
SOFT_DEG = 5.0  # image orientations this close to a bin boundary also set the neighbouring bin
MAJORITY = 5  # of the 3 x 3 neighbours that must share a bin for a pixel to keep it


def quantise(theta_rad: np.ndarray) -> np.ndarray:
    """Directions (rad, any range) -> orientation bins 0..N_ORI-1 over 180 deg."""
    a = np.mod(theta_rad, np.pi)
    return np.minimum((a / np.pi * N_ORI).astype(np.int32), N_ORI - 1)


def balanced_weights(ori: np.ndarray) -> np.ndarray:
    """Weights of points with orientation bins ``ori``: 1 / (the points of the same bin, at least
    n / (2 N_ORI)), summing to 1: a long straight side does not outvote the rest."""
    count = np.bincount(ori, minlength=N_ORI).astype(float)
    w = 1.0 / np.maximum(count[ori], len(ori) / (2.0 * N_ORI))
    return w / w.sum()


@numba.njit(cache=True)
def _majority(q, mask, majority, out):  # pragma: no cover - compiled
    h, w = q.shape
    hist = np.zeros(8, np.int32)
    for v in range(1, h - 1):
        for u in range(1, w - 1):
            if not mask[v, u]:
                continue
            for k in range(8):
                hist[k] = 0
            for dv in range(-1, 2):
                for du in range(-1, 2):
                    if mask[v + dv, u + du]:
                        hist[q[v + dv, u + du]] += 1
            best = 0
            for k in range(1, 8):
                if hist[k] > hist[best]:
                    best = k
            if hist[best] >= majority:
                out[v, u] = np.uint8(1 << best)


@dataclass(frozen=True)
class Gradient:
    """An image's strongest-channel gradient, per pixel: its direction's bin and magnitude."""

    q: np.ndarray  # (h, w) int32 orientation bin (``quantise``)
    frac: np.ndarray  # (h, w) where in its bin the direction lies, 0..1
    mag: np.ndarray  # (h, w) float32 Sobel magnitude on 0..255 channels


def image_gradient(image: np.ndarray) -> Gradient:
    """The gradient ``orientation_bits`` reads: blurred by ``BLUR_SIGMA``, Sobel 3 x 3 per channel, the
    strongest channel's."""
    img = cv2.GaussianBlur(image.astype(np.float32), (0, 0), BLUR_SIGMA)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    if gx.ndim == 2:
        gx, gy = gx[..., None], gy[..., None]
    m2 = gx * gx + gy * gy
    c = np.argmax(m2, axis=2)[..., None]
    gxs = np.take_along_axis(gx, c, 2)[..., 0]
    gys = np.take_along_axis(gy, c, 2)[..., 0]
    theta = np.arctan2(gys, gxs)
    a = np.degrees(np.mod(theta, np.pi)) / (180.0 / N_ORI)
    return Gradient(quantise(theta), a - np.floor(a), np.sqrt(np.take_along_axis(m2, c, 2)[..., 0]))


def orientation_bits(image: np.ndarray, *, mag_threshold: float = MAG_THRESHOLD) -> np.ndarray:
    """(h, w) uint8: bit b set where the image's strongest-channel gradient orientation is bin b."""
    return gradient_bits(image_gradient(image), mag_threshold)


def gradient_bits(g: Gradient, mag_threshold: float = MAG_THRESHOLD) -> np.ndarray:
    """``orientation_bits`` of an image whose ``image_gradient`` is ``g``."""
    q = g.q
    bits = np.zeros(q.shape, np.uint8)
    _majority(q, g.mag > mag_threshold, MAJORITY, bits)
    # an edge at 179 deg and one at 1 deg are the same edge: near a boundary the other bin is set too
    soft = SOFT_DEG / (180.0 / N_ORI)
    on = bits > 0
    lo = np.where(on & (g.frac < soft), 1 << ((q - 1) % N_ORI), 0)
    hi = np.where(on & (g.frac > 1 - soft), 1 << ((q + 1) % N_ORI), 0)
    return bits | lo.astype(np.uint8) | hi.astype(np.uint8)


def spread(bits: np.ndarray, t: int) -> np.ndarray:
    """OR of the bits over the t x t neighbourhood centred (to within a pixel) on each pixel."""
    h, w = bits.shape
    out = np.zeros_like(bits)
    lo = -(t // 2)
    for dv in range(lo, lo + t):
        for du in range(lo, lo + t):
            out[max(0, -dv):h - max(0, dv), max(0, -du):w - max(0, du)] |= \
                bits[max(0, dv):h - max(0, -dv), max(0, du):w - max(0, -du)]
    return out


@dataclass(frozen=True)
class ResponseMaps:
    """``lin[o, ry, rx, gy + pad, gx + pad]``: the response (0, 1 or 4) to orientation o at pixel
    (v, u) = (gy * t + ry, gx * t + rx); zero outside the image."""

    lin: np.ndarray  # (N_ORI, t, t, Gh + 2 pad, Gw + 2 pad) uint8
    pad: int
    grid_shape: tuple[int, int]  # (Gh, Gw)
    t: int
    # (N_ORI, (Gh + 2 pad) t, (Gw + 2 pad) t) uint8: the same responses by pixel, (v, u) at
    # [o, v + pad t, u + pad t]: read at any anchor pixel without splitting it by t
    pixels: np.ndarray


def response_maps(bits: np.ndarray, t: int, pad: int) -> ResponseMaps:
    """The linearised response maps of ``bits`` spread over t x t pixels, padded by ``pad`` grid cells."""
    b_spread = spread(bits, t)
    h, w = bits.shape
    gh, gw = -(-h // t), -(-w // t)
    b = np.zeros((gh * t, gw * t), np.uint8)
    b[:h, :w] = b_spread
    lin = np.zeros((N_ORI, t, t, gh + 2 * pad, gw + 2 * pad), np.uint8)
    for o in range(N_ORI):
        same = (b & (1 << o)) != 0
        near = (b & ((1 << ((o + 1) % N_ORI)) | (1 << ((o - 1) % N_ORI)))) != 0
        r = np.where(same, 4, np.where(near, 1, 0)).astype(np.uint8)
        for ry in range(t):
            for rx in range(t):
                lin[o, ry, rx, pad:pad + gh, pad:pad + gw] = r[ry::t, rx::t]
    pixels = lin.transpose(0, 3, 1, 4, 2).reshape(N_ORI, (gh + 2 * pad) * t, (gw + 2 * pad) * t)
    return ResponseMaps(lin, pad, (gh, gw), t, pixels)


CHUNK = 8  # score_grid adds a row's cells in whole chunks of this many: fixed-width vector adds


@numba.njit(cache=True, nogil=True)
def score_grid(flat, shape, pad, t, dx, dy, ori, wt, npts, cells, best, best_m, m0, m1):  # pragma: no cover
    """Every template m in [m0, m1) at every grid cell of its rectangle ``cells[m]`` = (gx0, gy0, gx1,
    gy1): keeps the best score and its template per cell in ``best`` / ``best_m`` (Gh, Gw), the first
    template on a tie. ``flat``: the response maps of ``shape`` flattened, then ``CHUNK`` more bytes.

    A cell's score is summed over the points in order in float32. Each term (a quarter weight times a
    response of 0, 1 or 4) is exact in float32, so a float32 add rounds as a float64 add stored in float32
    would. A row of cells takes every point's term before the next row (the row's sums stay in the
    cache), in whole chunks, the cells past its end included (they read the next row, or the slack, and
    are never compared): the compiler vectorises an add of a few chunks, not of a row's odd length."""
    row_len = shape[4]
    plane_len = shape[3] * row_len
    quarter = np.float32(0.25)
    start = np.empty(dx.shape[1], np.int64)
    w = np.empty(dx.shape[1], np.float32)
    acc = np.empty(best.shape[1] + CHUNK, np.float32)
    for m in range(m0, m1):
        g0, h0, g1, h1 = cells[m, 0], cells[m, 1], cells[m, 2], cells[m, 3]
        n = (g1 - g0 + CHUNK - 1) // CHUNK * CHUNK
        for p in range(npts[m]):
            w[p] = wt[m, p] * quarter
            rx = dx[m, p] % t
            ry = dy[m, p] % t
            start[p] = (((ori[m, p] * t + ry) * t + rx) * plane_len + ((dy[m, p] - ry) // t + pad) * row_len
                        + (dx[m, p] - rx) // t + pad + g0)
        a = acc[:max(n, 0)]
        for gy in range(h0, h1):
            a[:] = 0.0
            for p in range(npts[m]):
                row = flat[start[p] + gy * row_len:start[p] + gy * row_len + n]
                wp = w[p]
                for k in range(n):
                    a[k] += wp * np.float32(row[k])
            for k in range(g1 - g0):
                if a[k] > best[gy, g0 + k]:
                    best[gy, g0 + k] = a[k]
                    best_m[gy, g0 + k] = m


def best_on_grid(lin, pad, t, dx, dy, ori, wt, npts, cells, best, best_m) -> None:
    """``score_grid`` over every template, in runs of templates on the process's threads (``_in_runs``),
    each run on its own copy of ``best`` / ``best_m``, then merged in template order: a later run's cell
    replaces the earlier ones' only where it scores higher, as one run over them all leaves it."""
    flat = np.concatenate([lin.ravel(), np.zeros(CHUNK, np.uint8)])

    def scored(m0: int, m1: int) -> tuple[np.ndarray, np.ndarray]:
        b, bm = best.copy(), best_m.copy()
        score_grid(flat, lin.shape, pad, t, dx, dy, ori, wt, npts, cells, b, bm, m0, m1)
        return b, bm

    for b, bm in _in_runs(np.asarray(npts, np.float64) * _cell_counts(cells), scored):
        higher = b > best
        best[higher] = b[higher]
        best_m[higher] = bm[higher]


def _in_runs(work: np.ndarray, call) -> list:
    """``call(a, b)`` for each contiguous run [a, b) of items of about equal total ``work`` (``_runs``,
    one a thread of numba's count in the calling thread: ``threads.use_budget``), the later runs on the
    process's background pool while the calling thread does the first -> their results in run order."""
    starts = _runs(work, numba.get_num_threads())
    bounds = [(int(a), int(b)) for a, b in zip(starts[:-1], starts[1:], strict=True)]
    later = [threads.background().submit(call, a, b) for a, b in bounds[1:]]
    return [call(*bounds[0]), *(f.result() for f in later)]


def _cell_counts(cells: np.ndarray) -> np.ndarray:
    """(M,) grid cells of each template's rectangle (gx0, gy0, gx1, gy1)."""
    c = np.asarray(cells, np.float64)
    return np.maximum(c[:, 2] - c[:, 0], 0.0) * np.maximum(c[:, 3] - c[:, 1], 0.0)


def _runs(work: np.ndarray, n: int) -> np.ndarray:
    """Boundaries 0 = s_0 < ... < s_k = len(work) of at most ``n`` contiguous runs of about equal total
    ``work``."""
    total = float(work.sum())
    if n <= 1 or len(work) < 2 or total <= 0.0:
        return np.array([0, len(work)])
    cut = np.searchsorted(np.cumsum(work), total * np.arange(1, n) / n)
    return np.unique(np.concatenate([[0], np.clip(cut + 1, 1, len(work) - 1), [len(work)]]))


@numba.njit(cache=True, nogil=True)
def score_at(lin, pad, t, dx, dy, ori, wt, n, u, v):  # pragma: no cover - compiled
    """One template's score at anchor pixel (u, v), any pixel; 0 for points beyond the padding."""
    s = 0.0
    lim_y = lin.shape[3]
    lim_x = lin.shape[4]
    for p in range(n):
        pu = u + dx[p]
        pv = v + dy[p]
        rx = pu % t
        ry = pv % t
        cy = (pv - ry) // t + pad
        cx = (pu - rx) // t + pad
        if 0 <= cy < lim_y and 0 <= cx < lim_x:
            s += wt[p] * lin[ori[p], ry, rx, cy, cx]
    return s / 4.0


@numba.njit(cache=True, nogil=True)
def best_near(pixels, off, dx, dy, ori, wt, npts, ids, u, v, reach, m):  # pragma: no cover - compiled
    """The best (score, u, v, template) of the templates ``ids`` at the anchor pixels within ``reach`` of
    (u, v) in u and in v, template by template, row by row: the first on a tie; (-1, u, v, m) if none
    scores above -1. ``pixels``: ``ResponseMaps.pixels``, pixel (v, u) at [v + off, u + off]. A score is
    ``score_at``'s, summed in the same order (0 for points beyond the padding)."""
    best, bu, bv, bm = -1.0, u, v, m
    lim_y, lim_x = pixels.shape[1], pixels.shape[2]
    for mm in ids:
        for dv in range(-reach, reach + 1):
            for du in range(-reach, reach + 1):
                s = 0.0
                for p in range(npts[mm]):
                    y = v + dv + dy[mm, p] + off
                    x = u + du + dx[mm, p] + off
                    if 0 <= y < lim_y and 0 <= x < lim_x:
                        s += wt[mm, p] * pixels[ori[mm, p], y, x]
                s = s / 4.0
                if s > best:
                    best, bu, bv, bm = s, u + du, v + dv, mm
    return best, bu, bv, bm


def best_in_window(lin, pad, t, dx, dy, ori, wt, npts, ids, g0, h0, g1, h1) -> tuple[np.ndarray, np.ndarray]:
    """``_best_in_window`` of the templates ``ids``, in runs of them on the process's threads
    (``_in_runs``): each template's best is its own."""
    def run(a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        return _best_in_window(lin, pad, t, dx, dy, ori, wt, npts, ids[a:b], g0, h0, g1, h1)

    parts = _in_runs(np.asarray(npts, np.float64)[ids], run)
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


@numba.njit(cache=True, nogil=True)
def _best_in_window(lin, pad, t, dx, dy, ori, wt, npts, ids, g0, h0, g1, h1):  # pragma: no cover - compiled
    """Each template ``ids[k]``'s best score over the grid cells [g0, g1) x [h0, h1) -> ((K,) scores,
    (K, 2) its cell (gx, gy)). A point's place in the flattened maps is worked out once per template
    (``_flat_offsets``), not once per cell."""
    scores = np.full(ids.shape[0], -1.0, np.float32)
    at = np.zeros((ids.shape[0], 2), np.int64)
    flat = lin.ravel()
    row = lin.shape[4]
    offsets = np.empty(dx.shape[1], np.int64)
    for k in range(ids.shape[0]):
        m = ids[k]
        n = npts[m]
        _flat_offsets(lin.shape, pad, t, dx[m], dy[m], ori[m], n, offsets)
        for gy in range(h0, h1):
            for gx in range(g0, g1):
                s = 0.0
                cell = gy * row + gx
                for p in range(n):
                    s += wt[m, p] * flat[offsets[p] + cell]
                s *= 0.25
                if s > scores[k]:
                    scores[k] = s
                    at[k, 0] = gx
                    at[k, 1] = gy
    return scores, at


@numba.njit(cache=True, nogil=True)
def _flat_offsets(shape, pad, t, dx, dy, ori, n, out):  # pragma: no cover - compiled
    """``out[p]``: where point p of a template anchored at grid cell (0, 0) reads the flattened response
    maps of ``shape`` (N_ORI, t, t, Gh + 2 pad, Gw + 2 pad); cell (gx, gy) reads it ``gy * shape[4] + gx``
    further on."""
    for p in range(n):
        rx = dx[p] % t
        ry = dy[p] % t
        cy = (dy[p] - ry) // t + pad
        cx = (dx[p] - rx) // t + pad
        out[p] = (((ori[p] * t + ry) * t + rx) * shape[3] + cy) * shape[4] + cx
