"""Directional chamfer distance: the distance tensor DT3 (paper eqs. 11-13), the integral distance
transform (eqs. 15-16) and template costs read from them.

DT3 has shape (C, H, W): channel c holds, for every pixel, the distance in pixels to the nearest
image edge of orientation channel c, relaxed across channels by ``lambda_px`` per channel step
(cyclically: orientation pi equals 0) and truncated at ``tau_px``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from service.vision.estimate.edges import Segments, channel_of, edge_channels

DEFAULT_CHANNELS = 16
DEFAULT_TAU_PX = 20.0  # truncation: an edge further than this is as bad as no edge (robust to clutter)
DEFAULT_LAMBDA_PX_PER_RAD = 6.0  # orientation penalty: 11.25 deg of mismatch costs ~1.2 px


@dataclass(frozen=True)
class DistanceTensor:
    dt: np.ndarray  # (C, H, W) float32, pixels of this tensor's grid
    scale: float  # this grid's pixels per full-resolution pixel
    origin_uv: tuple[float, float]  # full-resolution uv of this grid's pixel (0, 0) centre... see to_grid
    tau_px: float
    lambda_px: float  # per channel step, pixels of this grid

    @property
    def n_channels(self) -> int:
        return int(self.dt.shape[0])

    def to_grid(self, uv_full: np.ndarray) -> np.ndarray:
        """Full-resolution uv -> this grid's pixel coordinates."""
        return (np.asarray(uv_full, float) - np.asarray(self.origin_uv) + 0.5) * self.scale - 0.5

    def to_full(self, uv_grid: np.ndarray) -> np.ndarray:
        return (np.asarray(uv_grid, float) + 0.5) / self.scale - 0.5 + np.asarray(self.origin_uv)


def orientation_relax(dt: np.ndarray, lambda_px: float) -> np.ndarray:
    """Eqs. 12-13 in place: DT3[c] = min(DT3[c], DT3[c -/+ 1] + lambda), cyclic over channels.

    Two sweeps each way reach every channel from every other one on the cycle.
    """
    _relax_rows(dt, np.float32(lambda_px))
    return dt


@nb.njit(parallel=True, cache=True)
def _relax_rows(dt, lam):  # row by row, the (C, W) slab stays in cache: numpy's full-image passes took 9 ms
    C, H, W = dt.shape
    for y in nb.prange(H):
        for _ in range(2):
            for c in range(C):  # forward recursion (eq. 13), cyclic: channel -1 is the last one
                p = (c - 1) % C
                for x in range(W):
                    dt[c, y, x] = min(dt[c, y, x], dt[p, y, x] + lam)
            for c in range(C - 1, -1, -1):  # backward recursion (eq. 12)
                n = (c + 1) % C
                for x in range(W):
                    dt[c, y, x] = min(dt[c, y, x], dt[n, y, x] + lam)


@nb.njit(parallel=True, cache=True)
def truncated_edt(edges, tau_px):
    """(C, H, W) uint8 edge masks -> (C, H, W) float32 Euclidean distance to the nearest edge pixel of
    the same channel, capped at ``tau_px``.

    Every edge pixel stamps its disc of radius tau into the output: with the truncation this is exact,
    and LSD edges are sparse (a few hundred to a few ten thousand pixels at half resolution), so it is
    5-20x faster than a full transform per channel. Work items are (channel, band of rows), so threads
    never write the same pixel.
    """
    C, H, W = edges.shape
    tau = np.float32(tau_px)
    R = int(np.floor(tau_px))
    table = np.empty((2 * R + 1, 2 * R + 1), np.float32)
    for dy in range(-R, R + 1):
        for dx in range(-R, R + 1):
            table[dy + R, dx + R] = min(np.float32(np.sqrt(dy * dy + dx * dx)), tau)
    # Edge pixels per channel in row order, with each row's first index.
    row_start = np.zeros((C, H + 1), np.int64)
    for c in nb.prange(C):
        for y in range(H):
            n = 0
            for x in range(W):
                n += edges[c, y, x] != 0
            row_start[c, y + 1] = n
    for c in range(C):
        for y in range(H):
            row_start[c, y + 1] += row_start[c, y]
    xs = np.empty((C, max(row_start[:, H].max(), 1)), np.int32)
    for c in nb.prange(C):
        for y in range(H):
            k = row_start[c, y]
            for x in range(W):
                if edges[c, y, x] != 0:
                    xs[c, k] = x
                    k += 1
    out = np.full((C, H, W), tau, np.float32)
    band = 16
    n_bands = (H + band - 1) // band
    for item in nb.prange(C * n_bands):
        c = item // n_bands
        y0 = (item % n_bands) * band
        y1 = min(H, y0 + band)
        for ye in range(max(0, y0 - R), min(H, y1 + R)):
            for k in range(row_start[c, ye], row_start[c, ye + 1]):
                xe = xs[c, k]
                for y in range(max(y0, ye - R), min(y1, ye + R + 1)):
                    for x in range(max(0, xe - R), min(W, xe + R + 1)):
                        v = table[y - ye + R, x - xe + R]
                        if v < out[c, y, x]:
                            out[c, y, x] = v
    return out


def distance_tensor_from_edges(edges: np.ndarray, *, tau_px: float = DEFAULT_TAU_PX,
                               lambda_px: float | None = None, scale: float = 1.0,
                               origin_uv: tuple[float, float] = (0.0, 0.0)) -> DistanceTensor:
    """(C, H, W) uint8 edge masks -> DistanceTensor (eq. 11 by truncated 2D DTs + orientation recursion)."""
    C, h, w = edges.shape
    if lambda_px is None:
        lambda_px = DEFAULT_LAMBDA_PX_PER_RAD * (np.pi / C) * scale
    dt = truncated_edt(np.ascontiguousarray(edges, np.uint8), float(tau_px))
    orientation_relax(dt, lambda_px)
    return DistanceTensor(dt, scale, origin_uv, tau_px, float(lambda_px))


def distance_tensor(seg: Segments, *, n_channels: int = DEFAULT_CHANNELS, scale: float = 1.0,
                    roi: tuple[int, int, int, int] | None = None, tau_px: float | None = None,
                    lambda_px: float | None = None) -> DistanceTensor:
    """Segments -> DT3 on the full image (or ``roi = (u0, v0, w, h)``) resized by ``scale``."""
    H, W = seg.image_shape
    u0, v0, w, h = roi if roi is not None else (0, 0, W, H)
    s = seg.crop(u0, v0, w, h) if roi is not None else seg
    shape = (max(int(round(h * scale)), 1), max(int(round(w * scale)), 1))
    edges = edge_channels(s, n_channels, shape, scale=scale)
    tau = DEFAULT_TAU_PX * scale if tau_px is None else tau_px
    return distance_tensor_from_edges(edges, tau_px=tau, lambda_px=lambda_px, scale=scale,
                                      origin_uv=(float(u0), float(v0)))


# --- reading costs ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Cells:
    """Where sub-pixel points fall in DT3: the two channels' top-left flat indices and the fractions."""

    inside: np.ndarray
    base0: np.ndarray  # flat index of the top-left neighbour in the lower channel
    base1: np.ndarray  # ... and in the next channel (cyclically)
    fu: np.ndarray
    fv: np.ndarray
    fc: np.ndarray


def _cells(dtt: DistanceTensor, uv_grid: np.ndarray, theta_rad: np.ndarray) -> _Cells:
    C, h, w = dtt.dt.shape
    uv = np.asarray(uv_grid, np.float64)
    u, v = uv[..., 0], uv[..., 1]
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    uc = np.clip(u, 0, w - 1.0001)
    vc = np.clip(v, 0, h - 1.0001)
    u0 = np.floor(uc).astype(np.int64)
    v0 = np.floor(vc).astype(np.int64)
    cf = np.mod(np.asarray(theta_rad, np.float64) * (C / np.pi), C)
    c0 = np.floor(cf).astype(np.int64) % C
    pix = v0 * w + u0
    return _Cells(inside, c0 * (h * w) + pix, ((c0 + 1) % C) * (h * w) + pix, uc - u0, vc - v0,
                  cf - np.floor(cf))


def sample(dtt: DistanceTensor, uv_grid: np.ndarray, theta_rad: np.ndarray) -> np.ndarray:
    """Directional chamfer distance at sub-pixel grid points, bilinear in space and linear, cyclic
    across orientation channels; outside the grid the cost is tau. (..., 2), (...) -> (...)."""
    k = _cells(dtt, uv_grid, theta_rad)
    flat, w = dtt.dt.reshape(-1), dtt.dt.shape[2]
    fu, fv = k.fu, k.fv

    def bil(base):
        return ((1 - fv) * ((1 - fu) * flat[base] + fu * flat[base + 1])
                + fv * ((1 - fu) * flat[base + w] + fu * flat[base + w + 1]))

    val = (1 - k.fc) * bil(k.base0) + k.fc * bil(k.base1)
    return np.where(k.inside, val, dtt.tau_px)


def sample_with_grad(dtt: DistanceTensor, uv_grid: np.ndarray, theta_rad: np.ndarray):
    """``sample`` and its partial derivatives: (val, d/du, d/dv, d/dtheta), grid units; outside the
    grid: tau, zero gradient. Separate from ``sample`` so the coarse search does not pay for them."""
    k = _cells(dtt, uv_grid, theta_rad)
    flat, w, C = dtt.dt.reshape(-1), dtt.dt.shape[2], dtt.dt.shape[0]
    fu, fv, fc = k.fu, k.fv, k.fc

    def bil(base):
        a, b = flat[base].astype(np.float64), flat[base + 1].astype(np.float64)
        c, d = flat[base + w].astype(np.float64), flat[base + w + 1].astype(np.float64)
        val = (1 - fv) * ((1 - fu) * a + fu * b) + fv * ((1 - fu) * c + fu * d)
        du = (1 - fv) * (b - a) + fv * (d - c)
        dv = (1 - fu) * (c - a) + fu * (d - b)
        return val, du, dv

    A0, Au0, Av0 = bil(k.base0)
    A1, Au1, Av1 = bil(k.base1)
    val = np.where(k.inside, (1 - fc) * A0 + fc * A1, dtt.tau_px)
    z = np.zeros_like(val)
    gu = np.where(k.inside, (1 - fc) * Au0 + fc * Au1, z)
    gv = np.where(k.inside, (1 - fc) * Av0 + fc * Av1, z)
    return val, gu, gv, np.where(k.inside, (A1 - A0) * (C / np.pi), z)


def sample_nearest(dtt: DistanceTensor, uv_grid: np.ndarray, theta_rad: np.ndarray) -> np.ndarray:
    """Like ``sample`` but at the nearest pixel and nearest channel (the paper's eq. 14 read-out)."""
    dt = dtt.dt
    C, h, w = dt.shape
    uv = np.rint(np.asarray(uv_grid)).astype(np.int64)
    u, v = uv[..., 0], uv[..., 1]
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    c = channel_of(theta_rad, C)
    val = dt[c, np.clip(v, 0, h - 1), np.clip(u, 0, w - 1)]
    return np.where(inside, val, dtt.tau_px)


def chamfer_cost(dtt: DistanceTensor, uv_grid: np.ndarray, theta_rad: np.ndarray) -> float:
    """Eq. 14: mean directional chamfer distance of template points (grid pixels)."""
    return float(np.mean(sample_nearest(dtt, uv_grid, theta_rad)))


# --- integral distance transform (eqs. 15-16) ------------------------------------------------------


@dataclass(frozen=True)
class IntegralDT:
    """Per channel, cumulative sums of DT3 along that channel's direction on digital lines.

    For a channel whose direction is closer to horizontal, line k through pixel (u, v) is the set
    {(u', v + round(u' * m) - round(u * m))} with m = tan(theta_c); the sum over a run of that line
    from u_a to u_b is ``cum[v - round(u_a m) + pad, u_b + 1] - cum[..., u_a]`` (two look-ups).
    Closer-to-vertical channels are the same with u and v swapped.
    """

    cum: list  # per channel: (rows, major + 1) float64 sheared cumulative sums
    slope: np.ndarray  # (C,) m = tan or cot of the channel angle, |m| <= 1
    vertical: np.ndarray  # (C,) bool: major axis is v
    pad: np.ndarray  # (C,) row offset added in the sheared frame
    shape: tuple[int, int]


def integral_dt(dtt: DistanceTensor) -> IntegralDT:
    C, h, w = dtt.dt.shape
    cums, slopes, verts, pads = [], [], [], []
    for c in range(C):
        th = c * np.pi / C
        vertical = abs(np.sin(th)) > abs(np.cos(th))
        img = dtt.dt[c].T if vertical else dtt.dt[c]  # rows = minor axis, cols = major axis
        m = (np.cos(th) / np.sin(th)) if vertical else np.tan(th)
        rows, cols = img.shape
        shift = np.rint(np.arange(cols) * m).astype(np.int64)  # digital line offset per column
        pad = int(max(0, shift.max()))
        n_rows = rows + pad - int(min(0, shift.min()))
        sheared = np.full((n_rows, cols), dtt.tau_px, np.float64)
        r = np.arange(rows)[:, None]
        # pixel (r, col) lies on sheared row r - shift[col] + pad
        sheared[r - shift[None, :] + pad, np.arange(cols)[None, :]] = img
        cum = np.zeros((n_rows, cols + 1), np.float64)
        np.cumsum(sheared, axis=1, out=cum[:, 1:])
        cums.append(cum)
        slopes.append(m)
        verts.append(vertical)
        pads.append(pad)
    return IntegralDT(cums, np.array(slopes), np.array(verts), np.array(pads), (h, w))


def line_cost_idt(idt: IntegralDT, c: int, uv_start: tuple[int, int], n_steps: int) -> float:
    """Eq. 16 for one template line: the DT3 sum over ``n_steps + 1`` pixels of channel c's digital
    line starting at pixel ``uv_start`` and running towards increasing major coordinate."""
    u, v = uv_start
    major, minor = (v, u) if idt.vertical[c] else (u, v)
    row = minor - int(np.rint(major * idt.slope[c])) + int(idt.pad[c])
    cum = idt.cum[c]
    return float(cum[row, major + n_steps + 1] - cum[row, major])


def line_pixels(idt: IntegralDT, c: int, uv_start: tuple[int, int], n_steps: int) -> np.ndarray:
    """The (n_steps + 1, 2) integer uv pixels ``line_cost_idt`` sums over."""
    u, v = uv_start
    major0, minor0 = (v, u) if idt.vertical[c] else (u, v)
    majors = major0 + np.arange(n_steps + 1)
    m = idt.slope[c]
    minors = minor0 + np.rint(majors * m).astype(np.int64) - int(np.rint(major0 * m))
    return np.stack([minors, majors], 1) if idt.vertical[c] else np.stack([majors, minors], 1)
