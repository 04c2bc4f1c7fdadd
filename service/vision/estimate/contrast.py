"""Oriented region contrast for the proposal engine: a cost tensor laid out like level A's chamfer tensor.

Chamfer cost asks whether an edge of the template's orientation lies near each border point; texture
and distractors offer such edges everywhere, and a partly covered or low-gradient true outline costs
more than they do (issue #14). Region-based trackers (RBOT, SRT3D) look instead at the colours a few
pixels inside and outside the outline along its normal. For every orientation channel ``o`` (edge
direction ``o pi / C``, normal ``n_o``) and pixel ``x``:

    C_o(x) = | Lab(x + d n_o) - Lab(x - d n_o) |   (polarity-free, on a smoothed image)

normalised by the local mean contrast over all channels (a textured floor contrasts everywhere, so
only an outline standing out of its neighbourhood scores high), max-pooled to level A's grid, and
turned into a cost in level A's quantised units: ``tau_q (1 - C / (C + mean + floor))``. Level A then
scores a blend of both tensors with its unchanged kernel (``blend``): a template's sum over its border
points is the sum of its chamfer and contrast costs.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from service.vision.estimate.chamfer import DistanceTensor

CONTRAST_D_PX = 8.0  # full-resolution px either side of the outline the colours are compared at
CONTRAST_SCALE = 0.25  # the grid the contrast is computed on (then max-pooled to level A's)
CONTRAST_FLOOR = 4.0  # Lab units added to the local mean: sensor noise on plain ground is no contrast


@dataclass(frozen=True)
class ContrastParams:
    weight: float = 0.5  # share of the contrast cost in level A's blended cost (0: chamfer only)
    weight_b: float = 0.0  # ... in level B's ranking (its placements and polished hypotheses)
    d_px: float = CONTRAST_D_PX
    scale: float = CONTRAST_SCALE
    floor: float = CONTRAST_FLOOR
    normalise: bool = True  # divide by the local mean contrast (else by a fixed reference)


def oriented_contrast(image: np.ndarray, n_channels: int, scale: float, d_px: float) -> np.ndarray:
    """(C, h, w) float32: Lab colour distance across each orientation channel's normal, ``d_px``
    (full-res) either side, on the image resized to ``scale``. Grey images: the grey difference."""
    img = np.asarray(image)
    h, w = img.shape[:2]
    hs, ws = max(int(round(h * scale)), 1), max(int(round(w * scale)), 1)
    small = cv2.resize(img, (ws, hs), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
    lab = cv2.cvtColor(small, cv2.COLOR_BGR2Lab) if small.ndim == 3 else (small * 100.0)[..., None]
    lab = cv2.GaussianBlur(lab, (3, 3), 0)
    if lab.ndim == 2:
        lab = lab[..., None]
    d = d_px * scale
    out = np.empty((n_channels, hs, ws), np.float32)
    for o in range(n_channels):
        th = o * np.pi / n_channels
        nu, nv = -np.sin(th) * d, np.cos(th) * d
        # dst(x) = src(x - t): shifting by -t samples x + t
        a = _shift(lab, nu, nv)
        b = _shift(lab, -nu, -nv)
        diff = (a - b).reshape(hs, ws, -1)
        out[o] = np.sqrt((diff * diff).sum(axis=2))
    return out


def _shift(img: np.ndarray, du: float, dv: float) -> np.ndarray:
    """``img`` sampled at x + (du, dv) (bilinear, border replicated)."""
    M = np.float32([[1, 0, -du], [0, 1, -dv]])
    return cv2.warpAffine(img, M, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REPLICATE)


def contrast_score(image: np.ndarray, n_channels: int, cp: ContrastParams, radius_px: float) -> np.ndarray:
    """(C, h, w) float32 in [0, 1] on the ``cp.scale`` grid: ``oriented_contrast`` over the local mean
    contrast (all channels, a box of ``radius_px`` full-res px round each pixel): 1 where an outline
    stands out of its surroundings, 0 where it contrasts no more than they do."""
    c = oriented_contrast(image, n_channels, cp.scale, cp.d_px)
    if not cp.normalise:
        return np.clip(c / 40.0, 0.0, 1.0)
    k = 2 * max(int(round(radius_px * cp.scale)), 1) + 1
    mean = cv2.blur(c.mean(axis=0), (k, k), borderType=cv2.BORDER_REFLECT)
    norm = c / (c + mean[None] + cp.floor)
    # C / (C + mean) is about 1/2 where a pixel contrasts like its neighbourhood: no evidence either way
    return np.clip(2.0 * norm - 0.5, 0.0, 1.0)


class Contrast:
    """One frame's oriented contrast, made on first use (the normalising window follows the template
    size, which the search knows): level A's blended tensor, and level B's mean contrast cost."""

    def __init__(self, image: np.ndarray, n_channels: int, level_scale: float, cp: ContrastParams):
        self.image, self.n_channels, self.level_scale, self.cp = image, n_channels, level_scale, cp
        self.score: np.ndarray | None = None

    @property
    def weight_b(self) -> float:
        return self.cp.weight_b

    def _score(self, radius_px: float) -> np.ndarray:
        if self.score is None:
            from service.vision.estimate.colour_edges import colour_u8  # any depth or BGRA, as uint8 BGR

            self.score = contrast_score(colour_u8(self.image), self.n_channels, self.cp, radius_px)
        return self.score

    def level_a(self, dt_q: np.ndarray, tau_q: int, radius_lvl: int) -> np.ndarray:
        """``coarse.scan_level_a``'s tensor: (1 - w) DT3 + w tau (1 - contrast score max-pooled over
        each level-A cell, as DT3 is min-pooled)."""
        sc = self._score(radius_lvl / self.level_scale)
        f = int(round(self.cp.scale / self.level_scale))
        hl, wl = dt_q.shape[:2]
        C, hs, ws = sc.shape
        pad = np.zeros((C, hl * f, wl * f), np.float32)
        hh, ww = min(hs, hl * f), min(ws, wl * f)
        pad[:, :hh, :ww] = sc[:, :hh, :ww]
        pooled = pad.reshape(C, hl, f, wl, f).max(axis=(2, 4))
        cost = np.ascontiguousarray((tau_q * (1.0 - pooled)).transpose(1, 2, 0))
        return blend(dt_q, tau_q, cost, self.cp.weight)

    def fine_tensor(self, dtt: DistanceTensor, tau_px: float, radius_px: float) -> DistanceTensor:
        """Level B's tensor: (1 - w_b) min(DT3, tau) + w_b tau (1 - contrast score), on ``dtt``'s grid
        (the score resized to it), in its units: the local scans, their ranking and the polish read
        it as they read the DT3."""
        sc = self._score(radius_px)
        C, h, w = dtt.dt.shape
        up = np.stack([cv2.resize(sc[c], (w, h), interpolation=cv2.INTER_LINEAR) for c in range(C)])
        wb = np.float32(self.cp.weight_b)
        dt = (1 - wb) * np.minimum(dtt.dt, np.float32(tau_px)) + wb * np.float32(tau_px) * (1 - up)
        return DistanceTensor(dt.astype(np.float32), dtt.scale, dtt.origin_uv, tau_px, dtt.lambda_px)


def blend(dt_q: np.ndarray, tau_q: int, cost: np.ndarray, weight: float) -> np.ndarray:
    """Level A's (H, W, C) uint8 tensor with the contrast cost mixed in: (1 - w) DT3 + w contrast."""
    h, w = dt_q.shape[:2]
    out = (1.0 - weight) * dt_q.astype(np.float32) + weight * cost[:h, :w]
    return np.minimum(out + 0.5, tau_q).astype(np.uint8)
