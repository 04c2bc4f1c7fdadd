"""The refinement's robust least squares (``estimate/lsq.py``) on problems with known minima."""

from __future__ import annotations

import numpy as np
import pytest

from service.vision.estimate.lsq import LOSSES, least_squares


def _linear(A, b):
    return lambda x: (A @ x - b, A)


def test_linear_problem_reaches_the_normal_equations_solution():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(40, 5))
    b = rng.normal(size=40)
    res = least_squares(_linear(A, b), np.zeros(5), x_scale=np.ones(5), ftol=1e-12, xtol=1e-12, gtol=1e-12)
    x_star = np.linalg.solve(A.T @ A, A.T @ b)
    np.testing.assert_allclose(res.x, x_star, atol=1e-9)
    np.testing.assert_allclose(res.fun, A @ res.x - b)
    assert res.status > 0 and res.njev <= res.nfev


def test_rosenbrock_minimum_from_a_far_start():
    # f = (10 (x1 - x0^2), 1 - x0): the one zero, hence minimum, is (1, 1)
    def fj(x):
        return (np.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]]),
                np.array([[-20.0 * x[0], 10.0], [-1.0, 0.0]]))

    res = least_squares(fj, np.array([-1.2, 1.0]), x_scale=np.ones(2), max_nfev=200, ftol=1e-12, xtol=1e-12,
                        gtol=1e-12)
    np.testing.assert_allclose(res.x, [1.0, 1.0], atol=1e-8)
    assert res.status > 0


def _robust_cost(loss, f, s):
    z = (f / s) ** 2
    rho = {"linear": z, "soft_l1": 2 * (np.sqrt(1 + z) - 1), "cauchy": np.log1p(z),
           "huber": np.where(z <= 1, z, 2 * np.sqrt(z) - 1)}[loss]
    return 0.5 * s ** 2 * rho.sum()


@pytest.mark.parametrize("loss", LOSSES)
def test_robust_line_fit_is_a_stationary_point_and_ignores_outliers(loss):
    # y = 2 u + 1 with noise and 20 % gross outliers; the robust losses find the line, and at the
    # solution the robust cost's gradient (central finite differences, independent of the
    # algorithm's rescaling) vanishes
    rng = np.random.default_rng(7)
    u = np.linspace(-3, 3, 60)
    y = 2 * u + 1 + rng.normal(0, 0.05, len(u))
    out = rng.choice(len(u), 12, replace=False)
    y[out] += rng.choice([-1, 1], 12) * rng.uniform(5, 10, 12)
    A = np.stack([u, np.ones_like(u)], 1)
    s = 0.2
    res = least_squares(_linear(A, y), np.zeros(2), x_scale=np.ones(2), loss=loss, f_scale=s, max_nfev=200,
                        ftol=1e-12, xtol=1e-12, gtol=1e-10)
    h = 1e-6
    grad = [(_robust_cost(loss, A @ (res.x + h * e) - y, s) - _robust_cost(loss, A @ (res.x - h * e) - y, s))
            / (2 * h) for e in np.eye(2)]
    np.testing.assert_allclose(grad, 0.0, atol=1e-5)
    if loss != "linear":
        np.testing.assert_allclose(res.x, [2.0, 1.0], atol=0.05)


def test_x_scale_does_not_move_the_minimum():
    rng = np.random.default_rng(11)
    A = rng.normal(size=(30, 3)) * [100.0, 1.0, 0.01]
    b = rng.normal(size=30)
    kw = dict(loss="soft_l1", f_scale=0.5, max_nfev=200, ftol=1e-12, xtol=1e-12, gtol=1e-12)
    a = least_squares(_linear(A, b), np.zeros(3), x_scale=np.ones(3), **kw)
    c = least_squares(_linear(A, b), np.zeros(3), x_scale=np.array([0.01, 1.0, 100.0]), **kw)
    np.testing.assert_allclose(a.x, c.x, rtol=1e-6, atol=1e-9)


def test_stops_at_max_nfev_with_status_zero():
    def fj(x):
        return (np.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]]),
                np.array([[-20.0 * x[0], 10.0], [-1.0, 0.0]]))

    res = least_squares(fj, np.array([-1.2, 1.0]), x_scale=np.ones(2), max_nfev=3, ftol=1e-15, xtol=1e-15,
                        gtol=1e-15)
    assert res.status == 0 and res.nfev == 3


def test_not_finite_at_the_start_raises():
    with pytest.raises(ValueError):
        least_squares(lambda x: (np.array([np.nan]), np.ones((1, 1))), np.zeros(1), x_scale=np.ones(1))


def test_non_finite_trial_shrinks_the_step():
    # f = x^3 - 1/8 (zero at x = 0.5), not finite beyond x = 0.55: the first trust-region step from
    # x = 0.3 (radius |x0| = 0.3 for a unit x_scale) lands at 0.6 and is retried shorter
    tried = []

    def fj(x):
        tried.append(float(x[0]))
        f = np.array([x[0] ** 3 - 0.125 if x[0] <= 0.55 else np.nan])
        return f, np.array([[3.0 * x[0] ** 2]])

    res = least_squares(fj, np.array([0.3]), x_scale=np.ones(1), max_nfev=100, ftol=1e-12, xtol=1e-12,
                        gtol=1e-12)
    assert any(t > 0.55 for t in tried)
    np.testing.assert_allclose(res.x, [0.5], atol=1e-9)
