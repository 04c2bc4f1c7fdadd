"""Parallel paths give the serial answers bit for bit: each compiled kernel or threaded split against a
plain one-thread transliteration of the loop it replaced, and on 1 and 2 numba threads."""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest

from service.vision.estimate.chamfer import segment_distance_tensor
from service.vision.estimate.edges import Segments, channel_of


def _segment_dt_serial(C, h, w, p0, p1, chan, lam, tau):
    """The segment-by-segment loop ``_segment_dt`` ran before its row bands, in plain Python."""
    dt = np.full((C, h, w), tau, np.float32)
    for s in range(len(p0)):
        ax, ay = float(p0[s, 0]), float(p0[s, 1])
        dx, dy = float(p1[s, 0]) - ax, float(p1[s, 1]) - ay
        L2 = dx * dx + dy * dy
        u_lo = max(int(math.floor(min(ax, ax + dx) - tau)), 0)
        u_hi = min(int(math.ceil(max(ax, ax + dx) + tau)), w - 1)
        v_lo = max(int(math.floor(min(ay, ay + dy) - tau)), 0)
        v_hi = min(int(math.ceil(max(ay, ay + dy) + tau)), h - 1)
        cs = int(chan[s])
        for v in range(v_lo, v_hi + 1):
            for u in range(u_lo, u_hi + 1):
                t = 0.0
                if L2 > 0.0:
                    t = min(max(((u - ax) * dx + (v - ay) * dy) / L2, 0.0), 1.0)
                ex, ey = u - (ax + t * dx), v - (ay + t * dy)
                d = math.sqrt(ex * ex + ey * ey)
                if d >= tau:
                    continue
                if d < dt[cs, v, u]:
                    dt[cs, v, u] = d
                reach = min(int((tau - d) / lam) if lam > 0 else C, C // 2)
                for j in range(1, reach + 1):
                    val = d + lam * j
                    for k in ((cs + j) % C, (cs - j) % C):
                        if val < dt[k, v, u]:
                            dt[k, v, u] = val
    return dt


@pytest.mark.parametrize("n_threads", [1, 2])
def test_segment_distance_tensor_bands_equal_the_segment_loop(n_threads):
    rng = np.random.default_rng(5)
    n = 40
    p0 = rng.uniform(-5, 70, (n, 2)).astype(np.float32)
    p1 = (p0 + rng.uniform(-25, 25, (n, 2))).astype(np.float32)
    p1[3] = p0[3]  # a zero-length segment
    d = p1 - p0
    th = np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi).astype(np.float32)
    roi = (3, 2, 61, 53)  # h = 53: the last row band is a short one
    C, tau, lam = 8, 9.0, 1.3
    before = numba.get_num_threads()
    numba.set_num_threads(min(n_threads, numba.config.NUMBA_NUM_THREADS))
    try:
        dtt = segment_distance_tensor(Segments(p0, p1, th, (70, 70)), roi, n_channels=C, tau_px=tau,
                                      lambda_px=lam)
    finally:
        numba.set_num_threads(before)
    org = np.array(roi[:2], np.float64)
    g0 = (p0.astype(np.float64) - org + 0.5) * 1.0 - 0.5  # as segment_distance_tensor maps them (scale 1)
    g1 = (p1.astype(np.float64) - org + 0.5) * 1.0 - 0.5
    chan = channel_of(th, C)
    serial = _segment_dt_serial(C, roi[3], roi[2], g0, g1, chan, lam, tau)
    assert dtt.dt.dtype == np.float32
    np.testing.assert_array_equal(dtt.dt, serial)


def test_segment_distance_tensor_without_segments_is_tau():
    z = np.zeros((0, 2), np.float32)
    empty = Segments(z, z, np.zeros(0, np.float32), (20, 20))
    dtt = segment_distance_tensor(empty, (0, 0, 11, 9), n_channels=4, tau_px=5.0)
    np.testing.assert_array_equal(dtt.dt, np.full((4, 9, 11), 5.0, np.float32))


def _window_offsets_serial(p_rel, theta, Rv, zc, depth_f, ray, fx, fy, cx, cy, s, c0u, c0v, phis_rad, C):
    """``level_b._window_offsets``'s loop, one template after the other, in plain Python."""
    Tv, P = theta.shape
    T, D = len(Rv), len(depth_f)
    off_u = np.empty((1, D, T, P), np.int16)
    off_v = np.empty((1, D, T, P), np.int16)
    chan = np.empty((T, P), np.int32)
    for t in range(T):
        iv, phi, R = t % Tv, phis_rad[t // Tv], Rv[t]
        for i in range(P):
            x, y, z = p_rel[iv, i]
            qx = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z
            qy = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z
            qz = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z
            for k in range(D):
                zk = zc[t] * depth_f[k]
                X, Y, Z = qx + ray[0] * zk, qy + ray[1] * zk, qz + zk
                off_u[0, k, t, i] = np.int16(np.rint((fx * X / Z + cx + 0.5) * s - 0.5 - c0u))
                off_v[0, k, t, i] = np.int16(np.rint((fy * Y / Z + cy + 0.5) * s - 0.5 - c0v))
            a = (theta[iv, i] + phi) % np.pi
            chan[t, i] = np.int32(np.floor(a * (C / np.pi) + 0.5)) % C
    return off_u, off_v, chan


@pytest.mark.parametrize("n_threads", [1, 2])
def test_window_offsets_equal_the_template_loop(n_threads):
    from service.vision.estimate.level_b import _window_offsets
    from service.vision.geometry.frames import R_from_rotvec

    rng = np.random.default_rng(7)
    Tv, Tp, P = 5, 7, 23
    p_rel = rng.uniform(-30, 30, (Tv, P, 3))
    theta = rng.uniform(0, np.pi, (Tv, P))
    Rv = np.stack([R_from_rotvec(rng.normal(size=3)) for _ in range(Tv * Tp)])
    zc = rng.uniform(400, 600, Tv * Tp)
    depth_f = np.array([1.0, 1.075, 1 / 1.075])
    ray = np.array([0.1, -0.05, 1.0])
    phis = np.deg2rad(np.arange(-6.0, 7.0, 2.0))
    args = (p_rel, theta, Rv, zc, depth_f, ray, 1100.0, 1100.0, 643.0, 477.0, 0.5, 350.0, 240.0, phis, 16)
    before = numba.get_num_threads()
    numba.set_num_threads(min(n_threads, numba.config.NUMBA_NUM_THREADS))
    try:
        got = _window_offsets(*args)
    finally:
        numba.set_num_threads(before)
    for a, b in zip(got, _window_offsets_serial(*args), strict=True):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)


def _evidence_serial(bank, pose, intr, frame, others=None):
    """``evidence.evidence`` with every piece run in turn on the calling thread."""
    from service.vision.estimate import evidence as ev
    from service.vision.estimate.shapes import distinct_px, genericity

    H, W = frame.shape
    fid, invz, (u0, v0) = ev.face_ids_roi(bank, pose, intr, (W, H), margin_px=ev.BAND_MAX_PX + 2)
    mask = fid >= 0
    hidden = explained = None
    if others is not None:
        o = others[v0:v0 + mask.shape[0], u0:u0 + mask.shape[1]]
        with np.errstate(divide="ignore"):
            own = np.where(mask, 1.0 / np.maximum(invz, 1e-12), np.inf)
        hidden = mask & (o < own - ev.OCCLUSION_MARGIN_MM)
        explained = ~mask & np.isfinite(o)
        fid = np.where(hidden, -1, fid)
    win = ev._window(frame, u0, v0, mask.shape[1], mask.shape[0])
    band = int(np.clip(ev.BAND_FRACTION * np.sqrt(mask.sum() / np.pi), ev.BAND_MIN_PX, ev.BAND_MAX_PX))
    p, n = ev._outline(mask)
    u, v = p[:, 0] + u0, p[:, 1] + v0
    in_image = (u >= 1) & (u < W - 1) & (v >= 1) & (v < H - 1)
    e = ev._edge_and_polarity(win, p, n, in_image)
    r = ev._region(win, mask, band, hidden, explained)
    inside = ev._inside_samples(fid, bank, pose)
    s = ev._shading(win, inside)
    generic = genericity(mask)
    return ev.Evidence(e[0], e[1], r[0], r[1], r[2], e[2], s[0], s[1], float(in_image.mean()),
                       generic, distinct_px(mask, generic))


def test_evidence_with_its_region_on_the_pool_equals_the_pieces_in_turn():
    import trimesh

    from service.vision.estimate.evidence import colour_frame, evidence
    from service.vision.geometry.camera import Intrinsics
    from service.vision.geometry.frames import Pose, Rx, Ry
    from service.vision.geometry.render import render_shaded

    mesh = trimesh.creation.box(extents=(60.0, 40.0, 25.0))
    bank = type("B", (), {"vertices_mm": np.asarray(mesh.vertices, float), "faces": np.asarray(mesh.faces)})
    intr = Intrinsics(900.0, 900.0, 319.5, 239.5)
    pose = Pose(Rx(35.0) @ Ry(20.0), np.array([10.0, -5.0, 400.0]))
    img = render_shaded(bank.vertices_mm, bank.faces, pose, intr.K, (640, 480))
    noise = np.random.default_rng(1).integers(0, 30, img.shape[:2] + (3,), dtype=np.uint8)
    frame = colour_frame(np.dstack([img] * 3) // 2 + noise if img.ndim == 2 else img // 2 + noise)
    others = np.full((480, 640), np.inf, np.float32)
    others[200:260, 300:340] = 350.0  # a nearer part hides a corner of this one
    for off in (None, others):
        for p in (pose, Pose(Rx(38.0) @ Ry(17.0), np.array([13.0, -3.0, 405.0]))):
            assert evidence(bank, p, intr, frame, off) == _evidence_serial(bank, p, intr, frame, off)
