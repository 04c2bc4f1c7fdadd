"""Unexplained interior edges: the same silhouette over a checkerboard, with and without the part there."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from service.vision import pipeline
from service.vision.estimate.edges import detect_segments
from service.vision.estimate.interior import model_edges, unexplained_edge_ratio
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, Rx, Rz
from service.vision.geometry.render import render, render_shaded
from tests.tolerances import INTERIOR_PART_MAX, INTERIOR_TEXTURE_MIN

INTR = Intrinsics(1000.0, 1000.0, 319.5, 239.5)
SIZE = (640, 480)
POSE = Pose(Rx(35.0) @ Rz(20.0), np.array([10.0, -5.0, 400.0]))


@pytest.fixture(scope="module")
def box_bank():
    return pipeline.build_templates(trimesh.creation.box((90.0, 60.0, 30.0)), symmetry="none",
                                    grid={"view_step_deg": 40.0, "render_px": 96})


def _checkerboard(square_px: int = 23) -> np.ndarray:
    v, u = np.mgrid[0:SIZE[1], 0:SIZE[0]]
    board = ((u // square_px + v // square_px) % 2).astype(np.uint8)
    return np.where(board, 185, 65).astype(np.uint8)


def _noisy(img, seed=3):
    rng = np.random.default_rng(seed)
    return np.clip(img + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)


def test_texture_inside_an_empty_silhouette_is_unexplained_the_parts_own_creases_are_not(box_bank):
    floor = _checkerboard()
    part = render_shaded(box_bank.vertices_mm, box_bank.faces, POSE, INTR.K, SIZE)
    mask = render(box_bank.vertices_mm, box_bank.faces, POSE, INTR.K, SIZE).mask
    with_part = np.where(mask, part, floor)
    empty = unexplained_edge_ratio(box_bank, POSE, INTR, detect_segments(_noisy(floor), scale=1.0), SIZE)
    there = unexplained_edge_ratio(box_bank, POSE, INTR, detect_segments(_noisy(with_part), scale=1.0), SIZE)
    assert empty >= INTERIOR_TEXTURE_MIN
    assert there <= INTERIOR_PART_MAX


def test_model_edges_mark_the_boxs_visible_face_boundaries(box_bank):
    mask, crease, (u0, v0) = model_edges(box_bank, POSE, INTR, SIZE)
    # seen from this pose the box shows three faces: creases inside the silhouette, none off it
    assert crease.sum() > 0 and not (crease & ~mask).any()
    # every crease pixel lies within 2 px of a projected box edge that is not on the outline
    V = box_bank.vertices_mm @ POSE.R.T + POSE.t_mm
    uv = (INTR.K @ (V / V[:, 2:3]).T).T[:, :2] - np.array([u0, v0])
    edges = trimesh.creation.box((90.0, 60.0, 30.0)).edges_unique
    vs, us = np.nonzero(crease)
    p = np.stack([us, vs], 1).astype(float)
    a, b = uv[edges[:, 0]][None], uv[edges[:, 1]][None]
    t = np.clip(((p[:, None] - a) * (b - a)).sum(-1) / ((b - a) ** 2).sum(-1), 0, 1)
    dist = np.linalg.norm(p[:, None] - (a + t[..., None] * (b - a)), axis=-1).min(axis=1)
    assert np.quantile(dist, 0.99) <= 2.0
