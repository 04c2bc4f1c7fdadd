"""The paper's directional chamfer read-outs, kept to check the fast paths against: the nearest-pixel,
nearest-channel cost of eq. 14 and the integral distance transform of eqs. 15-16.

The service reads DT3 bilinearly (``estimate/chamfer.sample``) and scans it with compiled loops
(``estimate/coarse.py``); the tests check both against these.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.vision.estimate.chamfer import DistanceTensor
from service.vision.estimate.edges import channel_of


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
