"""Overlay: coarse contour dashed, refined contour solid, at the silhouette border's pixels (drawn
1 px thick to check where they lie); by default lines that scale with the image, the object axes at
their projected pixels, and the verdict banner."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose
from service.vision.geometry.render import render
from service.vision.overlay import (
    ABSENT_BGR,
    AXES_BGR,
    BANNER_BG_BGR,
    COARSE_BGR,
    FOUND_BGR,
    REFINED_BGR,
    draw_axes,
    draw_overlay,
    encode_png,
    line_thickness_px,
)
from tests.tolerances import OVERLAY_ON_BORDER_PX

INTR = Intrinsics(fx=1100.0, fy=1100.0, cx=643.0, cy=477.0)
SIZE = (1280, 960)
REFINED = Pose.from_euler_xyz_deg((25.0, -35.0, 15.0), (40.0, -30.0, 500.0))
COARSE = Pose.from_euler_xyz_deg((25.0, -35.0, 15.0), (52.0, -30.0, 500.0))  # 12 mm ~ 26 px to the right
OTHER = Pose.from_euler_xyz_deg((-40.0, 10.0, 70.0), (-150.0, 60.0, 500.0))  # a second copy, ~400 px left


@pytest.fixture(scope="module")
def bank(tless06_mesh):
    from service.vision.model.templates import build_bank

    return build_bank(tless06_mesh, symmetry="none", grid={"render_px": 100, "supersample": 1,
                                                           "view_step_deg": 60.0})


def _pixels(img, bgr):
    return np.all(img == np.array(bgr, np.uint8), axis=2)


def _dilated(m):
    return cv2.dilate(m.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)


def _border_distance(bank, pose):
    m = render(bank.vertices_mm, bank.faces, pose, INTR, SIZE).mask.astype(np.uint8)
    border = m - cv2.erode(m, np.ones((3, 3), np.uint8))
    return cv2.distanceTransform((border == 0).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


def test_refined_contour_is_solid_on_the_silhouette_border(bank):
    grey = np.full((SIZE[1], SIZE[0]), 70, np.uint8)
    out = draw_overlay(grey, bank, INTR, COARSE, REFINED, thickness=1, axes=False)
    assert out.shape == (SIZE[1], SIZE[0], 3) and out.dtype == np.uint8
    red = _pixels(out, REFINED_BGR)
    d = _border_distance(bank, REFINED)
    assert red.sum() > 200
    assert np.all(d[red] <= OVERLAY_ON_BORDER_PX)
    # Solid: the refined border is covered almost everywhere (the coarse one may cross it).
    near = d <= 0.5
    assert _dilated(red)[near].mean() > 0.97


def test_coarse_contour_is_dashed_on_its_own_border(bank):
    grey = np.full((SIZE[1], SIZE[0]), 70, np.uint8)
    out = draw_overlay(grey, bank, INTR, COARSE, None, thickness=1, dash_px=8, axes=False)
    green = _pixels(out, COARSE_BGR)
    d = _border_distance(bank, COARSE)
    assert green.sum() > 100
    assert np.all(d[green] <= OVERLAY_ON_BORDER_PX)
    covered = _dilated(green)[d <= 0.5].mean()
    assert 0.3 < covered < 0.75  # dashes: about half the border is drawn
    assert not _pixels(out, REFINED_BGR).any()


def test_colour_input_is_kept_and_png_round_trips(bank):
    bgr = np.zeros((SIZE[1], SIZE[0], 3), np.uint8)
    bgr[..., 0] = 200
    out = draw_overlay(bgr, bank, INTR, None, REFINED, axes=False)
    assert out[0, 0].tolist() == [200, 0, 0]
    png = encode_png(out)
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    back = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    np.testing.assert_array_equal(back, out)


def test_deeper_colour_input_stays_colour(bank):
    bgr = np.zeros((SIZE[1], SIZE[0], 3), np.uint16)
    bgr[..., 2] = 4000  # a 12-bit camera's red
    out = draw_overlay(bgr, bank, INTR, None, None)
    assert out.dtype == np.uint8 and out[0, 0].tolist() == [0, 0, 255]


def test_estimate_draws_the_overlay_on_the_colour_image(bank):
    """The overlay a person reads is the colour frame the cell sent, not the grey the search reads."""
    from service.vision import pipeline

    bgr = np.empty((480, 640, 3), np.uint8)
    bgr[...] = (180, 90, 40)
    intr = Intrinsics(550.0, 550.0, 319.5, 239.5)
    out = pipeline.estimate(bank, bgr, intr, distance_mm=500.0, overlay=True)
    img = cv2.imdecode(np.frombuffer(out.overlay_png, np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (480, 640, 3)
    assert img[-1, -1].tolist() == [180, 90, 40]  # grey would have three equal channels


def test_other_instances_are_drawn_solid_and_every_instance_numbered(bank):
    grey = np.full((SIZE[1], SIZE[0]), 70, np.uint8)
    one = draw_overlay(grey, bank, INTR, None, REFINED, thickness=1, axes=False)
    two = draw_overlay(grey, bank, INTR, None, REFINED, thickness=1, axes=False, instances=[OTHER])
    d = _border_distance(bank, OTHER)
    assert _dilated(_pixels(two, REFINED_BGR))[d <= 0.5].mean() > 0.9  # solid (a number box may cover some)
    assert not _dilated(_pixels(one, REFINED_BGR))[d <= 0.5].any()
    # one light number box per instance, none for a single instance
    assert not _pixels(one, BANNER_BG_BGR).any()
    n_boxes, _ = cv2.connectedComponents(_pixels(two, BANNER_BG_BGR).astype(np.uint8))
    assert n_boxes - 1 == 2


def test_nothing_to_draw_returns_the_image_in_bgr(bank):
    grey = np.arange(SIZE[0] * SIZE[1], dtype=np.uint32).reshape(SIZE[1], SIZE[0]).astype(np.uint8)
    out = draw_overlay(grey, bank, INTR, None, None)
    np.testing.assert_array_equal(out[..., 0], grey)
    np.testing.assert_array_equal(out[..., 2], grey)


def _line_width_px(bank, intr, size, pose):
    """Mean width of the solid refined line: its pixel count over the silhouette's border length."""
    grey = np.full((size[1], size[0]), 70, np.uint8)
    out = draw_overlay(grey, bank, intr, None, pose, axes=False)
    m = render(bank.vertices_mm, bank.faces, pose, intr, size).mask.astype(np.uint8)
    cs, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    return _pixels(out, REFINED_BGR).sum() / sum(cv2.arcLength(c, True) for c in cs)


def test_lines_scale_with_the_image(bank):
    """The same view at 1x and 4x the resolution: lines of thickness 2 and 6 (line_thickness_px)."""
    assert line_thickness_px((640, 480)) == 2 and line_thickness_px((2560, 1920)) == 6
    assert line_thickness_px((1280, 960)) == 3
    small = Intrinsics(fx=550.0, fy=550.0, cx=321.5, cy=238.5)
    big = Intrinsics(fx=2200.0, fy=2200.0, cx=1286.0, cy=954.0)
    w_small = _line_width_px(bank, small, (640, 480), REFINED)
    w_big = _line_width_px(bank, big, (2560, 1920), REFINED)
    # cv2 draws a line of thickness t between t and t + 1 px wide (and the border's length is
    # measured along the pixel chain): allow [t, t + 1.5]
    assert 2 <= w_small <= 2 + 1.5
    assert 6 <= w_big <= 6 + 1.5


def test_axes_are_drawn_at_their_projections():
    """R = I at (0, 0, 500): the x axis runs right from (cx, cy), the y axis down, L * fx / 500 px long."""
    img = np.full((SIZE[1], SIZE[0], 3), 70, np.uint8)
    L = 100.0
    draw_axes(img, Pose(np.eye(3), np.array([0.0, 0.0, 500.0])), INTR, L, 3)
    reach = INTR.fx * L / 500.0  # 220 px
    u0, v0 = int(INTR.cx), int(INTR.cy)
    assert img[v0, int(u0 + reach / 2)].tolist() == list(AXES_BGR[0])  # x: red, half way out
    assert img[int(v0 + reach / 2), u0].tolist() == list(AXES_BGR[1])  # y: green, half way down
    assert img[v0, int(u0 - reach / 2)].tolist() == [70, 70, 70]  # nothing on the other side
    assert img[int(v0 - reach / 2), u0].tolist() == [70, 70, 70]


@pytest.mark.parametrize("found", [True, False])
def test_banner_says_the_verdict(bank, found):
    grey = np.full((SIZE[1], SIZE[0]), 70, np.uint8)
    out = draw_overlay(grey, bank, INTR, None, None, found=found, score=0.42)
    banner = out[: SIZE[1] // 8, : SIZE[0] // 2]
    assert _pixels(banner, FOUND_BGR if found else ABSENT_BGR).any()
    assert not _pixels(banner, ABSENT_BGR if found else FOUND_BGR).any()
    assert (out[SIZE[1] // 8:] == 70).all()  # the banner stays in the top left
