"""Robust nonlinear least squares for the refinement's small problems (n <= 6 parameters).

Minimises ``0.5 * sum_i s^2 rho((f_i(x) / s)^2)`` (``s`` = ``f_scale``; rho: "linear", "soft_l1",
"huber", "cauchy", as scipy defines them) from an analytic Jacobian, by trust-region
Levenberg-Marquardt: the algorithm of ``scipy.optimize.least_squares(method="trf")`` without bounds
and with ``tr_solver="exact"`` (More's trust-region step from one SVD of the scaled Jacobian per
iteration; the robust loss by rescaling residuals and Jacobian with rho' and rho'', Triggs et al.),
with the same stopping rules (``ftol``, ``xtol``, ``gtol``, ``max_nfev``) and status codes.

Why not scipy's: its wrapper (argument checks, function and loss wrappers, result object) cost about
as much as the residuals themselves on these problems (~1.2 ms a call, three calls a frame).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

EPS = float(np.finfo(float).eps)
LOSSES = ("linear", "soft_l1", "huber", "cauchy")


@dataclass(frozen=True)
class LsqResult:
    x: np.ndarray  # (n,) the solution
    fun: np.ndarray  # (m,) residuals at x (not rescaled by the loss)
    status: int  # 0: max_nfev reached; 1: gtol; 2: ftol; 3: xtol; 4: ftol and xtol (scipy's codes)
    nfev: int  # residual evaluations
    njev: int  # Jacobians used (accepted steps + 1)


def _loss(loss: str, f: np.ndarray, f_scale: float, cost_only: bool):
    """cost, and (unless ``cost_only``) rho' and rho'' / f_scale^2 per residual."""
    if loss == "linear":
        return 0.5 * float(f @ f), None, None
    z = (f / f_scale) ** 2
    if loss == "soft_l1":
        t = 1.0 + z
        r0 = 2.0 * (np.sqrt(t) - 1.0)
        if cost_only:
            return 0.5 * f_scale ** 2 * float(r0.sum()), None, None
        r1 = 1.0 / np.sqrt(t)
        r2 = -0.5 * r1 / t
    elif loss == "huber":
        lin = z <= 1.0
        sq = np.sqrt(z)
        r0 = np.where(lin, z, 2.0 * sq - 1.0)
        if cost_only:
            return 0.5 * f_scale ** 2 * float(r0.sum()), None, None
        big = ~lin  # z > 1 there: no division by zero
        r1 = np.ones_like(z)
        r2 = np.zeros_like(z)
        r1[big] = 1.0 / sq[big]
        r2[big] = -0.5 / (z[big] * sq[big])
    elif loss == "cauchy":
        r0 = np.log1p(z)
        if cost_only:
            return 0.5 * f_scale ** 2 * float(r0.sum()), None, None
        t = 1.0 + z
        r1 = 1.0 / t
        r2 = -r1 * r1
    else:
        raise ValueError(f"loss must be one of {LOSSES}.")
    return 0.5 * f_scale ** 2 * float(r0.sum()), r1, r2 / f_scale ** 2


def _scaled(loss: str, f: np.ndarray, J: np.ndarray, f_scale: float):
    """(cost, f, J) with f and J rescaled for the robust loss (new arrays)."""
    cost, r1, r2 = _loss(loss, f, f_scale, False)
    if r1 is None:
        return cost, f, J
    js = r1 + 2.0 * r2 * f ** 2
    js[js < EPS] = EPS
    js = np.sqrt(js)
    return cost, f * (r1 / js), J * js[:, None]


def _tr_step(n: int, m: int, uf: np.ndarray, s: np.ndarray, V: np.ndarray, Delta: float, alpha: float,
             rtol: float = 0.01, max_iter: int = 10) -> tuple[np.ndarray, float]:
    """The step p minimising ||J p + f|| within ||p|| <= Delta, from J = U diag(s) V^T and uf = U^T f,
    and its Levenberg-Marquardt parameter alpha ((J^T J + alpha I) p = -J^T f; More 1977)."""
    suf = s * uf
    full_rank = m >= n and s[-1] > EPS * m * s[0]
    if full_rank:
        p = -V @ (uf / s)
        if math.sqrt(float(p @ p)) <= Delta:
            return p, 0.0

    def phi(a):
        denom = s ** 2 + a
        pn = math.sqrt(float(np.sum((suf / denom) ** 2)))
        return pn - Delta, -float(np.sum(suf ** 2 / denom ** 3)) / pn

    upper = math.sqrt(float(suf @ suf)) / Delta
    if full_rank:
        ph, dph = phi(0.0)
        lower = -ph / dph
    else:
        lower = 0.0
    if not full_rank and alpha == 0:
        alpha = max(0.001 * upper, math.sqrt(lower * upper))
    for _ in range(max_iter):
        if alpha < lower or alpha > upper:
            alpha = max(0.001 * upper, math.sqrt(lower * upper))
        ph, dph = phi(alpha)
        if ph < 0:
            upper = alpha
        ratio = ph / dph
        lower = max(lower, alpha - ratio)
        alpha -= (ph + Delta) * ratio / Delta
        if abs(ph) < rtol * Delta:
            break
    p = -V @ (suf / (s ** 2 + alpha))
    p *= Delta / math.sqrt(float(p @ p))
    return p, alpha


def least_squares(fun_jac: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], x0: np.ndarray, *,
                  x_scale: np.ndarray, loss: str = "linear", f_scale: float = 1.0, max_nfev: int = 100,
                  ftol: float = 1e-8, xtol: float = 1e-8, gtol: float = 1e-8) -> LsqResult:
    """Minimise the robust cost of ``fun_jac(x) -> (f (m,), J (m, n))`` from ``x0`` (n,).

    ``x_scale`` (n,): the variables' characteristic scales (the trust region is round in x / x_scale).
    Stops when the cost changes less than ``ftol`` (relative, on a good step), the step is shorter
    than ``xtol`` (relative to |x|), the gradient's largest component is below ``gtol``, or after
    ``max_nfev`` evaluations of ``fun_jac``. Raises ValueError when the residuals at ``x0`` are not
    finite."""
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}.")
    x = np.array(x0, dtype=float)
    f, J = fun_jac(x)
    f = np.asarray(f, float)
    if not np.all(np.isfinite(f)):
        raise ValueError("Residuals are not finite in the initial point.")
    nfev = njev = 1
    m, n = J.shape
    f_true = f
    cost, f, J = _scaled(loss, f, J, f_scale)
    g = J.T @ f
    d = np.asarray(x_scale, float)
    Delta = float(np.linalg.norm(x / d)) or 1.0
    alpha = 0.0
    status = None
    while True:
        if float(np.max(np.abs(g))) < gtol:
            status = 1
        if status is not None or nfev == max_nfev:
            break
        g_h = d * g
        J_h = J * d
        U, s, Vt = np.linalg.svd(J_h, full_matrices=False)
        uf = U.T @ f
        reduction = -1.0
        while reduction <= 0 and nfev < max_nfev:
            step_h, alpha = _tr_step(n, m, uf, s, Vt.T, Delta, alpha)
            Js = J_h @ step_h
            predicted = -(0.5 * float(Js @ Js) + float(step_h @ g_h))
            step = d * step_h
            x_new = x + step
            f_new, J_new = fun_jac(x_new)
            f_new = np.asarray(f_new, float)
            nfev += 1
            step_h_norm = math.sqrt(float(step_h @ step_h))
            if not np.all(np.isfinite(f_new)):
                Delta = 0.25 * step_h_norm
                continue
            cost_new = _loss(loss, f_new, f_scale, True)[0]
            reduction = cost - cost_new
            # the trust radius: shrink on a poor prediction, grow on a good one at the boundary
            if predicted > 0:
                ratio = reduction / predicted
            elif predicted == reduction == 0:
                ratio = 1.0
            else:
                ratio = 0.0
            Delta_new = Delta
            if ratio < 0.25:
                Delta_new = 0.25 * step_h_norm
            elif ratio > 0.75 and step_h_norm > 0.95 * Delta:
                Delta_new = 2.0 * Delta
            f_ok = reduction < ftol * cost and ratio > 0.25
            x_ok = math.sqrt(float(step @ step)) < xtol * (xtol + math.sqrt(float(x @ x)))
            if f_ok or x_ok:
                status = 4 if f_ok and x_ok else (2 if f_ok else 3)
                break
            alpha *= Delta / Delta_new
            Delta = Delta_new
        if reduction > 0:
            x, f_true, cost = x_new, f_new, cost_new
            njev += 1
            _, f, J = _scaled(loss, f_new, J_new, f_scale)
            g = J.T @ f
    return LsqResult(x, f_true.copy(), status or 0, nfev, njev)
