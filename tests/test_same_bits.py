"""Faster paths that must give their reference's answer bit for bit: the coarse search's compiled
read-out (``chamfer.sample_mean`` against ``sample`` and numpy's mean), ``level_b.evaluate``'s one-matmul
path against its numpy one, and the evidence's front-face raster against the whole mesh's."""

from __future__ import annotations

import numpy as np
import pytest

from service.vision.estimate.chamfer import DistanceTensor, _pairwise, sample, sample_mean


@pytest.mark.parametrize("n", [1, 7, 8, 9, 15, 16, 80, 127, 128, 129, 160, 255, 256, 257, 300, 512])
def test_pairwise_sum_is_numpys_row_sum(n):
    rng = np.random.default_rng(n)
    a = rng.uniform(0.0, 8.0, (3, n)) * 10.0 ** rng.integers(-3, 4, (3, n))
    for row in a:
        assert _pairwise(np.ascontiguousarray(row), 0, n) == np.add.reduce(row)
    assert np.array_equal([_pairwise(np.ascontiguousarray(r), 0, n) / n for r in a], a.mean(axis=1))


@pytest.mark.parametrize("P", [7, 80, 160, 300])
def test_sample_mean_is_samples_mean_bit_for_bit(P):
    rng = np.random.default_rng(P)
    C, h, w = 16, 60, 80
    dtt = DistanceTensor(rng.uniform(0, 4, (C, h, w)).astype(np.float32), 0.5, (3.0, -2.0), 4.0, 0.6)
    M = 9
    # Full-resolution points over the grid's area and beyond it (outside reads tau), on its last pixel
    # centre too, and orientations over [0, pi] with both ends.
    uv = np.stack([rng.uniform(-20, 2 * w + 20, (M, P)), rng.uniform(-20, 2 * h + 20, (M, P))], axis=-1)
    uv[0, 0] = (np.array([w - 1, h - 1]) + 0.5) / 0.5 - 0.5 + np.array([3.0, -2.0])
    theta = rng.uniform(0, np.pi, (M, P))
    theta[1, :2] = (0.0, np.pi)
    for tau_px, score_px in ((np.inf, 3.0), (5.0, 2.0)):
        val = sample(dtt, dtt.to_grid(uv), theta) / dtt.scale
        cost, score = sample_mean(dtt, uv, theta, tau_px=tau_px, score_px=score_px)
        assert np.array_equal(cost, np.minimum(val, tau_px).mean(axis=1))
        assert np.array_equal(score, (val <= score_px).mean(axis=1))


def test_fast_evaluate_equals_the_numpy_evaluate(l_block_bank):
    from service.vision.estimate import level_b
    from service.vision.geometry.camera import Intrinsics
    from service.vision.geometry.frames import R_from_rotvec
    from service.vision.reference.evaluate import evaluate_numpy

    bank = l_block_bank
    rng = np.random.default_rng(5)
    K = Intrinsics(1100.0, 1100.0, 639.5, 479.5).K
    dtt = DistanceTensor(rng.uniform(0, 8, (16, 480, 640)).astype(np.float32), 0.5, (0.0, 0.0), 8.0, 0.6)
    M = 12
    views = rng.integers(0, bank.n_templates, M)
    Rs = np.stack([R_from_rotvec(rng.normal(size=3)) for _ in range(M)])
    ts = np.column_stack([rng.uniform(-80, 80, M), rng.uniform(-60, 60, M), rng.uniform(350, 700, M)])
    for n_points in (80, 160):
        fast = level_b.evaluate(bank, views, Rs, ts, K, dtt, n_points, 3.0, 8.0)
        slow = evaluate_numpy(bank, views, Rs, ts, K, dtt, n_points, 3.0, 8.0)
        for a, b in zip(slow, fast, strict=True):
            assert np.array_equal(a, b)


def test_front_face_raster_equals_the_whole_mesh_raster(sprayer_mesh):
    from service.vision.estimate import evidence as ev
    from service.vision.geometry.camera import Intrinsics
    from service.vision.geometry.frames import Pose, R_from_rotvec

    bank = type("B", (), {"vertices_mm": np.asarray(sprayer_mesh.vertices, float),
                          "faces": np.asarray(sprayer_mesh.faces)})
    from service.vision.geometry.render import rasterise_roi
    from service.vision.geometry.silhouette import mesh_topology

    assert mesh_topology(bank.vertices_mm, bank.faces).closed  # else only the whole mesh is rasterised
    intr = Intrinsics(1100.0, 1100.0, 639.5, 479.5)
    rng = np.random.default_rng(11)
    for _ in range(6):
        pose = Pose(R_from_rotvec(rng.normal(size=3)), np.array([*rng.uniform(-40, 40, 2), 450.0]))
        fid, invz, origin = ev.face_ids_roi(bank, pose, intr, (1280, 960), ev.BAND_MAX_PX + 2)
        invz_all, fid_all, origin_all = rasterise_roi(bank.vertices_mm, bank.faces, pose, intr, (1280, 960),
                                                      margin_px=ev.BAND_MAX_PX + 2, inverse_depth=True)
        assert origin == origin_all
        assert np.array_equal(fid, fid_all)
        assert np.array_equal(invz, invz_all)
        assert (fid >= 0).sum() > 1000


def test_block_ids_are_numpys_unique_rows():
    from service.vision.estimate.level_a import _block_ids

    rng = np.random.default_rng(3)
    for n in (1, 2, 17, 400, 3000):
        tile = rng.integers(0, 12, n).astype(np.int32)
        bv, bu = rng.integers(0, 8, n), rng.integers(0, 11, n)
        want, inverse = np.unique(np.stack([tile, bv, bu], 1), axis=0, return_inverse=True)
        got, got_inverse = _block_ids(tile, bv, bu)
        assert np.array_equal(got, want) and np.array_equal(got_inverse, inverse.ravel())


def test_window_grid_is_nearest_first_with_row_order_ties():
    from service.vision.estimate.level_b import _window_grid

    gu, gv = _window_grid(4, 2)
    # brute force: every (du, dv) on the stride grid, sorted by squared distance, ties in row order
    want = sorted(((du, dv) for dv in range(-4, 5, 2) for du in range(-4, 5, 2)),
                  key=lambda p: p[0] ** 2 + p[1] ** 2)
    assert list(zip(gu.tolist(), gv.tolist(), strict=True)) == want


def test_rasterise_roi_writes_the_given_face_ids():
    import trimesh

    from service.vision.geometry.camera import Intrinsics
    from service.vision.geometry.frames import Pose, Rx
    from service.vision.geometry.render import rasterise_roi

    mesh = trimesh.creation.icosphere(subdivisions=2, radius=30.0)
    V, F = np.asarray(mesh.vertices, float), np.asarray(mesh.faces)
    pose, intr = Pose(Rx(20.0), np.array([5.0, -3.0, 300.0])), Intrinsics(800.0, 800.0, 319.5, 239.5)
    depth, fid, uv0 = rasterise_roi(V, F, pose, intr, (640, 480))
    ids = (7 * np.arange(len(F)) + 3).astype(np.int32)
    depth2, fid2, uv02 = rasterise_roi(V, F, pose, intr, (640, 480), face_ids=ids)
    assert uv02 == uv0 and np.array_equal(depth2, depth) and (fid >= 0).sum() > 1000
    assert np.array_equal(fid2, np.where(fid >= 0, 7 * fid + 3, -1))
