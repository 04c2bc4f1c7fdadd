"""DT3 (eqs. 11-13) against brute force; the integral DT (eqs. 15-16) against point sums."""

import cv2
import numpy as np
import pytest

from service.vision.estimate.chamfer import distance_tensor_from_edges, sample, truncated_edt
from service.vision.reference.integral_dt import integral_dt, line_cost_idt, line_pixels, sample_nearest
from tests.tolerances import DT_EXACT_ATOL


def _random_edges(rng, C=8, h=17, w=23, n=12):
    edges = np.zeros((C, h, w), np.uint8)
    edges[rng.integers(0, C, n), rng.integers(0, h, n), rng.integers(0, w, n)] = 1
    return edges


def _brute_dt3(edges, lam, tau):
    C, h, w = edges.shape
    cs, vs, us = np.nonzero(edges)
    out = np.full((C, h, w), tau)
    for c in range(C):
        cyc = np.minimum(np.abs(cs - c), C - np.abs(cs - c))
        for v in range(h):
            for u in range(w):
                d = np.hypot(us - u, vs - v) + lam * cyc
                out[c, v, u] = min(tau, d.min()) if len(d) else tau
    return out


def test_dt3_equals_brute_force_directional_chamfer():
    rng = np.random.default_rng(3)
    edges = _random_edges(rng)
    dtt = distance_tensor_from_edges(edges, tau_px=9.0, lambda_px=1.7)
    np.testing.assert_allclose(dtt.dt, _brute_dt3(edges, 1.7, 9.0), atol=DT_EXACT_ATOL)


def test_truncated_edt_equals_opencv_exact_transform_capped():
    # Several row bands (the stamping's work items), edges on the image border, a fractional cap.
    rng = np.random.default_rng(11)
    edges = _random_edges(rng, C=3, h=100, w=130, n=90)
    edges[0, 0, 0] = edges[1, 99, 129] = edges[2, 50, 0] = 1
    edges[2, 16:18, 40] = 1
    tau = 7.5
    want = np.stack([np.minimum(cv2.distanceTransform((e == 0).astype(np.uint8), cv2.DIST_L2,
                                                      cv2.DIST_MASK_PRECISE), tau) for e in edges])
    np.testing.assert_allclose(truncated_edt(edges, tau), want, atol=DT_EXACT_ATOL)


def test_dt3_empty_channel_is_tau_plus_nothing_closer():
    edges = np.zeros((4, 9, 9), np.uint8)
    edges[0, 4, 4] = 1
    dtt = distance_tensor_from_edges(edges, tau_px=5.0, lambda_px=1.0)
    assert dtt.dt[0, 4, 4] == 0.0
    assert dtt.dt[2, 4, 4] == 2.0  # two channel steps away, either way round the cycle
    assert dtt.dt[3, 4, 4] == 1.0  # channel 3 neighbours channel 0 cyclically
    assert dtt.dt[0, 0, 0] == 5.0  # truncated


def test_integral_dt_line_cost_equals_point_by_point_sum():
    rng = np.random.default_rng(7)
    C = 12
    dtt = distance_tensor_from_edges(_random_edges(rng, C=C, h=40, w=50, n=60), tau_px=10.0, lambda_px=1.0)
    idt = integral_dt(dtt)
    checked = 0
    for c in range(C):
        for _ in range(20):
            u, v = int(rng.integers(0, 50)), int(rng.integers(0, 40))
            n = int(rng.integers(0, 15))
            pix = line_pixels(idt, c, (u, v), n)
            if not ((pix[:, 0] >= 0) & (pix[:, 0] < 50) & (pix[:, 1] >= 0) & (pix[:, 1] < 40)).all():
                continue
            # the digital line really runs along channel c's direction
            if n >= 8:
                d = pix[-1] - pix[0]
                ang = np.mod(np.arctan2(d[1], d[0]), np.pi)
                diff = abs(ang - c * np.pi / C)
                assert min(diff, np.pi - diff) < np.pi / C
            expect = dtt.dt[c, pix[:, 1], pix[:, 0]].sum()
            assert abs(line_cost_idt(idt, c, (u, v), n) - expect) < 1e-6 * max(1.0, expect)
            checked += 1
    assert checked > 100


def test_bilinear_sample_is_exact_at_pixel_centres_and_channel_centres():
    rng = np.random.default_rng(11)
    C = 8
    dtt = distance_tensor_from_edges(_random_edges(rng, C=C), tau_px=9.0, lambda_px=1.0)
    v, u = np.meshgrid(np.arange(1, 16), np.arange(1, 22), indexing="ij")
    uv = np.stack([u.ravel(), v.ravel()], 1).astype(float)
    for c in range(C):
        theta = np.full(len(uv), c * np.pi / C)
        np.testing.assert_allclose(sample(dtt, uv, theta), dtt.dt[c, v.ravel(), u.ravel()], atol=1e-5)
        np.testing.assert_allclose(sample_nearest(dtt, uv, theta), dtt.dt[c, v.ravel(), u.ravel()])
    # half way between two channels: the mean of both
    theta = np.full(len(uv), 0.5 * np.pi / C)
    np.testing.assert_allclose(sample(dtt, uv, theta),
                               0.5 * (dtt.dt[0, v.ravel(), u.ravel()] + dtt.dt[1, v.ravel(), u.ravel()]),
                               atol=1e-5)


@pytest.mark.parametrize("shape", [(16, 48, 64), (4, 50, 67)])
def test_pooled_and_quantised_equals_the_two_passes(shape):
    """The one-pass level tensors equal ``pooled_distance_tensor`` and ``quantised`` exactly, also when
    the image is not a whole number of pooling cells (the leftover rows are quantised, not pooled)."""
    from service.vision.estimate.chamfer import (
        DistanceTensor,
        pooled_and_quantised,
        pooled_distance_tensor,
        quantised,
    )

    rng = np.random.default_rng(5)
    dtt = DistanceTensor(rng.uniform(0, 10, shape).astype(np.float32), 0.5, (0.0, 0.0), 10.0, 1.0)
    a, q, tau_q = pooled_and_quantised(dtt, 0.125, 4.0)
    want_a = pooled_distance_tensor(dtt, 0.125)
    want_q, want_tau = quantised(dtt, 4.0)
    np.testing.assert_array_equal(a.dt, want_a.dt)
    np.testing.assert_array_equal(q, want_q)
    assert tau_q == want_tau
    assert (a.scale, a.tau_px, a.lambda_px) == (want_a.scale, want_a.tau_px, want_a.lambda_px)


def test_orientation_relax_matches_brute_force():
    # eqs. 12-13: DT3[c] = min over c' of DT3[c'] + lambda * (cyclic channel steps from c' to c); rows
    # and pixels left at the truncation in every channel (no edge near) must stay there
    from service.vision.estimate.chamfer import orientation_relax

    rng = np.random.default_rng(1912)
    C, H, W, tau, lam = 16, 9, 40, 10.0, 0.6
    dt = np.full((C, H, W), tau, np.float32)
    dt[:, 2, 5:9] = rng.uniform(0, tau, (C, 4))  # a short span in one row
    dt[3, 4, 0] = 1.0  # single pixels at the row ends
    dt[11, 4, W - 1] = 2.5
    dt[:, 6:, :] = rng.uniform(0, tau, (C, H - 6, W))  # rows full of edges
    dt[:, 7, 10:20] = 4.0  # equal channels inside a busy row
    steps = np.abs(np.arange(C)[:, None] - np.arange(C)[None, :])
    cyc = np.minimum(steps, C - steps).astype(np.float64)  # (c, c')
    want = (dt.astype(np.float64)[None] + lam * cyc[:, :, None, None]).min(axis=1)
    got = orientation_relax(dt.copy(), lam)
    np.testing.assert_allclose(got, want, atol=1e-5)
    assert (got[:, [0, 1, 3, 5]] == np.float32(tau)).all()
