"""The outline moved to where the part's colours end (``vision/estimate/contour_region.py``): a start pose
too far or too near comes back to the rendered depth, also where only the hue tells part from floor; with
no colour step the pose is left as it is."""

import cv2
import numpy as np
import pytest

from service.vision.estimate.contour_region import REACH_PX, region_contour_refine, steps_along_normals
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, Rx, Ry, Rz
from service.vision.geometry.render import rasterise_roi

K = np.array([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]])
W, H = 640, 480
TRUTH = Pose(Rz(25.0) @ Rx(-40.0) @ Ry(30.0), np.array([40.0, -20.0, 600.0]))
# The rendered silhouette is whole pixels: its outline is known to half a pixel, on a part ~150 px across
# a depth to ~0.7 %.
DEPTH_TOL = 0.01


def scene(bank, pose: Pose, part_bgr, floor) -> np.ndarray:
    img = floor.copy()
    _, face, (u0, v0) = rasterise_roi(bank.vertices_mm, bank.faces, pose, K, (W, H))
    win = img[v0:v0 + face.shape[0], u0:u0 + face.shape[1]]
    win[face >= 0] = part_bgr
    return img


def checker(square_px=24) -> np.ndarray:
    v, u = np.mgrid[0:H, 0:W]
    g = np.where(((u // square_px) + (v // square_px)) % 2 == 0, 70, 170).astype(np.uint8)
    return np.repeat(g[..., None], 3, axis=2)


def grey_of(bgr) -> int:
    return int(cv2.cvtColor(np.uint8([[bgr]]), cv2.COLOR_BGR2GRAY)[0, 0])


@pytest.mark.parametrize("factor", [0.95, 1.06])
def test_a_start_too_near_or_too_far_comes_back_to_the_rendered_depth(l_block_bank, factor):
    image = scene(l_block_bank, TRUTH, (40, 150, 210), checker())
    start = Pose(TRUTH.R, TRUTH.t_mm * factor)
    pose = region_contour_refine(l_block_bank, start, image, Intrinsics.from_K(K))
    assert abs(pose.t_mm[2] / TRUTH.t_mm[2] - 1.0) < DEPTH_TOL
    assert abs(start.t_mm[2] / TRUTH.t_mm[2] - 1.0) > 4 * DEPTH_TOL  # the start was not already there


def test_colour_alone_places_the_outline(l_block_bank):
    """A part whose grey level equals the floor's: only its hue differs."""
    part = (60, 120, 200)
    floor = np.full((H, W, 3), grey_of(part), np.uint8)
    assert grey_of(part) == grey_of(floor[0, 0])
    image = scene(l_block_bank, TRUTH, part, floor)
    pose = region_contour_refine(l_block_bank, Pose(TRUTH.R, TRUTH.t_mm * 1.06), image, Intrinsics.from_K(K))
    assert abs(pose.t_mm[2] / TRUTH.t_mm[2] - 1.0) < DEPTH_TOL


def test_without_a_colour_step_the_pose_is_left_as_it_is(l_block_bank):
    image = np.full((H, W, 3), 128, np.uint8)
    start = Pose(TRUTH.R, TRUTH.t_mm * 1.06)
    assert region_contour_refine(l_block_bank, start, image, Intrinsics.from_K(K)) is start


def test_the_step_along_each_normal_is_the_disc_edge():
    """Log-odds +2 inside a disc of radius 40 px, -2 outside; points on a circle 5 px outside it, their
    outline's direction tangent: each step lies on the disc's edge, each normal points away from the
    centre (the mask says which side is inside)."""
    c, r = np.array([60.0, 60.0]), 40.0
    v, u = np.mgrid[0:120, 0:120]
    inside = (u - c[0]) ** 2 + (v - c[1]) ** 2 <= r ** 2
    L = np.where(inside, 2.0, -2.0).astype(np.float32)
    mask = ((u - c[0]) ** 2 + (v - c[1]) ** 2 <= (r + 5) ** 2).astype(np.uint8)
    a = np.linspace(0, 2 * np.pi, 36, endpoint=False)
    uv = c + (r + 5.0) * np.stack([np.cos(a), np.sin(a)], 1)
    theta = np.mod(a + np.pi / 2, np.pi)
    assert REACH_PX > 5.0  # the edge is within reach
    normal, target, good = steps_along_normals(L, mask, uv, theta)
    assert good.all()
    radial = (uv - c) / np.linalg.norm(uv - c, axis=1)[:, None]
    assert np.allclose(np.einsum("ij,ij->i", normal, radial), 1.0, atol=1e-9)
    # pixel centres sit on the integers; the disc's sampled edge lies within a pixel of r
    assert np.abs(np.linalg.norm(target - c, axis=1) - r).max() < 1.0
