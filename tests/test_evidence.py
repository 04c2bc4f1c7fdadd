"""The region and shading evidence against plain reference computations on synthetic windows."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import trimesh

from service.vision.estimate.evidence import (
    MIN_REGION_PIXELS,
    REGION_BINS,
    REGION_SECTORS,
    SHADING_ERODE_PX,
    ColourFrame,
    _inside_samples,
    _region,
    _shading,
    _window,
)
from service.vision.geometry.frames import Pose, Rx, Ry, Rz
from service.vision.geometry.render import face_normals_cam


def _frame_and_mask(seed: int):
    rng = np.random.default_rng(seed)
    bgr = rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)
    bgr[30:90, 40:120] //= 3  # a darker part, so the separations are not all alike
    mask = np.zeros((120, 160), bool)
    cv2.ellipse(mask.view(np.uint8), (80, 60), (45, 32), 20, 0, 360, 1, -1)
    return _window(ColourFrame(bgr), 0, 0, 160, 120), mask


def _tv(a, b):
    nb = REGION_BINS ** 3
    return 0.5 * np.abs(np.bincount(a, minlength=nb) / len(a) - np.bincount(b, minlength=nb) / len(b)).sum()


def _region_by_hand(win, mask, band_px, hidden=None, explained=None):
    """Per sector: every band pixel listed, binned and compared, one sector at a time."""
    m8 = mask.astype(np.uint8)
    inner = mask & (cv2.distanceTransform(m8, cv2.DIST_L2, 3) <= band_px)
    outer = ~mask & (cv2.distanceTransform(1 - m8, cv2.DIST_L2, 3) <= band_px)
    if hidden is not None:
        inner &= ~hidden
        outer &= ~explained
    vs, us = np.nonzero(mask)
    q = (win.bgr.astype(np.int64) * REGION_BINS) // 256
    q = (q[..., 0] * REGION_BINS + q[..., 1]) * REGION_BINS + q[..., 2]
    sector = np.minimum(((np.arctan2(np.arange(mask.shape[0])[:, None] - vs.mean(),
                                     np.arange(mask.shape[1])[None, :] - us.mean()) + np.pi)
                         * (REGION_SECTORS / (2 * np.pi))).astype(int), REGION_SECTORS - 1)
    seps = []
    for s in range(REGION_SECTORS):
        qi, qo = q[inner & (sector == s)], q[outer & (sector == s)]
        if len(qi) >= MIN_REGION_PIXELS and len(qo) >= MIN_REGION_PIXELS:
            seps.append(_tv(qi, qo))
    seps = np.sort(seps)
    return seps.mean(), seps[min(1, len(seps) - 1)], _tv(q[inner], q[outer])


def test_region_evidence_is_the_per_sector_histogram_comparison():
    for seed in (1, 2):
        win, mask = _frame_and_mask(seed)
        np.testing.assert_allclose(_region(win, mask, 6), _region_by_hand(win, mask, 6), rtol=0, atol=1e-12)
        hidden = mask.copy()
        hidden[:, :70] = False
        explained = ~mask
        explained[:60] = False
        np.testing.assert_allclose(_region(win, mask, 6, hidden, explained),
                                   _region_by_hand(win, mask, 6, hidden, explained), rtol=0, atol=1e-12)


def test_shading_fit_explains_a_grey_level_that_is_a_quadratic_in_the_normals():
    """A window painted with a quadratic of each pixel's face normal is explained entirely (r2 = 1),
    and the standard deviation is that of the eroded, every-other-pixel inside the fit reads."""
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=30.0)
    bank = SimpleNamespace(vertices_mm=np.asarray(mesh.vertices, float), faces=np.asarray(mesh.faces))
    pose = Pose(Rx(30.0), np.array([0.0, 0.0, 300.0]))
    rng = np.random.default_rng(3)
    fid = np.full((120, 160), -1, np.int32)
    blob = np.zeros((120, 160), np.uint8)
    cv2.circle(blob, (80, 60), 40, 1, -1)
    fid[blob > 0] = rng.integers(0, len(bank.faces), int(blob.sum()))
    n = face_normals_cam(bank.vertices_mm, bank.faces, pose.R, pose.t_mm).astype(np.float64)
    level = 100.0 + 60.0 * n[:, 2] + 40.0 * n[:, 0] ** 2
    bgr = np.zeros((120, 160, 3), np.uint8)
    on = fid >= 0
    bgr[on] = np.rint(level[fid[on]])[:, None].astype(np.uint8)
    r2, std = _shading(_window(ColourFrame(bgr), 0, 0, 160, 120), _inside_samples(fid, bank, pose))
    inner = cv2.erode(on.astype(np.uint8), np.ones((2 * SHADING_ERODE_PX + 1,) * 2, np.uint8)) > 0
    sampled = np.zeros_like(inner)
    sampled[::2, ::2] = inner[::2, ::2]
    assert r2 > 1 - 1e-4
    np.testing.assert_allclose(std, bgr[sampled][:, 0].astype(float).std(), rtol=1e-12)


# Poses of the painted box of tests/test_appearance.py: in full view, turned, cut by the image's left border,
# and wholly outside the image.
_SCORED_POSES = [Pose(Rx(-35.0) @ Ry(30.0), np.array([0.0, 0.0, 400.0])),
                 Pose(Rx(140.0) @ Ry(-40.0) @ Rz(20.0), np.array([10.0, -5.0, 420.0])),
                 Pose(Rx(-35.0) @ Ry(30.0), np.array([-120.0, 0.0, 400.0])),
                 Pose(Rx(-35.0) @ Ry(30.0), np.array([-900.0, 0.0, 400.0]))]


def test_the_region_and_shading_measure_alone_equals_the_whole_evidence_s(box_photo):
    """``region_and_shading`` is ``evidence`` without the measures a score does not read: on every pose,
    taught and untaught, with another part hiding some of it and without, its values are the whole
    evidence's, and the pipeline's unrefined score is the score of the whole evidence."""
    from service.vision import pipeline
    from service.vision.estimate.evidence import REGION_AND_SHADING, evidence, region_and_shading
    from service.vision.estimate.verdict import verification_score

    part, frame, intr, face_bgr, others = box_photo
    for pose in _SCORED_POSES:
        for taught in (None, face_bgr):
            for depth in (None, others):
                whole = evidence(part, pose, intr, frame, depth, taught).as_dict()
                alone = region_and_shading(part, pose, intr, frame, depth, taught)
                assert alone == {k: whole[k] for k in REGION_AND_SHADING if k in whole}
                app = None if taught is None else SimpleNamespace(face_bgr=taught)
                assert pipeline.unrefined_score(part, pose, frame, intr, depth, app) == verification_score(
                    whole | {"edge_support": 1.0, "unexplained": 0.0})
    assert region_and_shading(part, _SCORED_POSES[2], intr, frame)["in_image"] < 1.0  # the cut one
    # the nearer block changes what is measured: the comparison above covers the hidden pixels' handling
    assert region_and_shading(part, _SCORED_POSES[0], intr, frame, others) != region_and_shading(
        part, _SCORED_POSES[0], intr, frame)


@pytest.fixture(scope="module")
def box_photo():
    """The painted box at the first pose, its colours taught from that photo, and a nearer block's depth
    over part of it."""
    from service.vision.model.appearance import ReferenceView, teach
    from tests.test_appearance import BOX, INTR, _photo

    image, _ = _photo(_SCORED_POSES[0])
    face_bgr = teach(BOX.vertices_mm, BOX.faces, [ReferenceView(image, INTR, _SCORED_POSES[0])]).face_bgr
    others = np.full(image.shape[:2], np.inf, np.float32)
    others[100:140, 150:200] = 300.0  # nearer than the box (400 mm): hides some of it
    return BOX, ColourFrame(image), INTR, face_bgr, others
