"""Fitting a verification score: the class-balanced logistic regression, its sign-constrained form, and
the AUC a fit is read by (``bench/fit_verdict.py``, ``bench/appearance.py``)."""

from __future__ import annotations

import numpy as np


def fit_logistic(X: np.ndarray, y: np.ndarray, l2: float = 1.0, iters: int = 50) -> np.ndarray:
    """Newton's method on the L2-regularised log-loss, the classes weighted to equal total weight
    (right hypotheses are a few percent of all); returns (bias, weights...)."""
    cw = np.where(y > 0, 0.5 / max(y.mean(), 1e-9), 0.5 / max(1 - y.mean(), 1e-9))
    A = np.hstack([np.ones((len(X), 1)), X])
    w = np.zeros(A.shape[1])
    reg = l2 * np.eye(A.shape[1])
    reg[0, 0] = 0.0
    for _ in range(iters):
        p = 1.0 / (1.0 + np.exp(-A @ w))
        g = A.T @ (cw * (p - y)) + reg @ w
        H = (A * (cw * p * (1 - p))[:, None]).T @ A + reg
        step = np.linalg.solve(H, g)
        w -= step
        if np.abs(step).max() < 1e-8:
            break
    return w


def fit_monotone(X: np.ndarray, y: np.ndarray, signs: np.ndarray) -> np.ndarray:
    """The logistic fit with every weight's sign fixed by ``signs`` (+1: more of the evidence never
    lowers the score; -1: never raises it): features whose fitted weight takes the wrong sign are
    dropped one at a time (the most wrong first) and the rest refitted. Returns (bias, weights...)."""
    active = list(range(X.shape[1]))
    while True:
        Xs = X[:, active] * signs[active]
        mu, sd = Xs.mean(0), Xs.std(0) + 1e-9
        ws = fit_logistic((Xs - mu) / sd, y)
        if min(ws[1:]) >= 0:
            break
        active.pop(int(np.argmin(ws[1:])))
    w = np.zeros(X.shape[1] + 1)
    w[0] = ws[0] - (ws[1:] * mu / sd).sum()
    for a, v in zip(active, ws[1:] / sd, strict=True):
        w[a + 1] = v * signs[a]
    return w


def auc(pos: np.ndarray, neg: np.ndarray, lower_is_better: bool = False) -> float:
    """P(a truth's value beats a wrong candidate's), ties half."""
    if not len(pos) or not len(neg):
        return float("nan")
    if lower_is_better:
        pos, neg = -pos, -neg
    d = pos[:, None] - neg[None, :]
    return float((d > 0).mean() + 0.5 * (d == 0).mean())
