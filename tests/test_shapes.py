"""The canonical-frame silhouette comparison and the generic look-alike family (``shapes``): known
answers from geometry."""

import math

import cv2
import numpy as np
import pytest

from service.vision.estimate import shapes

GENERIC_MIN = 0.93  # a family member drawn anew (another aspect, angle, size) is fitted at least this well


def _ellipse(a, b, angle_deg, size=(400, 300), centre=(210, 140)):
    m = np.zeros(size[::-1], np.uint8)
    cv2.ellipse(m, centre, (a, b), angle_deg, 0, 360, 1, -1)
    return m


def _polygon(pts, size=(400, 300)):
    m = np.zeros(size[::-1], np.uint8)
    cv2.fillPoly(m, [np.round(np.asarray(pts, float)).astype(np.int32)], 1)
    return m


@pytest.mark.parametrize("a,b,angle", [(90, 20, 0), (70, 55, 33), (40, 40, 0), (100, 12, 71)])
def test_an_ellipse_is_generic(a, b, angle):
    assert shapes.genericity(_ellipse(a, b, angle)) >= GENERIC_MIN


@pytest.mark.parametrize("w,h,angle", [(160, 60, 20), (100, 90, -50), (180, 25, 80)])
def test_a_rectangle_is_generic(w, h, angle):
    c, s = math.cos(math.radians(angle)), math.sin(math.radians(angle))
    corners = np.array([[-w, -h], [w, -h], [w, h], [-w, h]], float) / 2 @ np.array([[c, s], [-s, c]])
    assert shapes.genericity(_polygon(corners + [200, 150])) >= GENERIC_MIN


def test_a_cross_is_not_generic():
    # A plus of five unit squares (area 5): a convex shape covering all four arms' ends contains their
    # hull (area 7; IoU at most 5/7), and one leaving an arm's end out loses part of that arm, so no
    # convex shape reaches 0.8.
    u = 40.0
    arm = [(-0.5, -1.5), (0.5, -1.5), (0.5, -0.5), (1.5, -0.5), (1.5, 0.5), (0.5, 0.5), (0.5, 1.5),
           (-0.5, 1.5), (-0.5, 0.5), (-1.5, 0.5), (-1.5, -0.5), (-0.5, -0.5)]
    assert shapes.genericity(_polygon(np.array(arm) * u + [200, 150])) < 0.8


def test_genericity_does_not_depend_on_position_scale_or_in_plane_angle():
    l_shape = np.array([(0, 0), (3, 0), (3, 1), (1, 1), (1, 2.2), (0, 2.2)], float)
    base = shapes.genericity(_polygon(l_shape * 50 + [60, 60]))
    c, s = math.cos(0.65), math.sin(0.65)
    moved = (l_shape * 80) @ np.array([[c, s], [-s, c]]) + [250, 60]
    assert shapes.genericity(_polygon(moved, size=(640, 480))) == pytest.approx(base, abs=0.02)


def test_a_speck_says_nothing():
    m = np.zeros((50, 50), np.uint8)
    m[10:13, 10:13] = 1
    assert shapes.genericity(m) == 1.0


def test_distinct_px_is_the_mean_gap_between_two_near_outlines():
    # A disc of radius r inside a concentric disc of radius r + w: IoU r^2 / (r + w)^2, and the band
    # between the two outlines is w wide everywhere, so the measure must give back w.
    r, w = 60, 1.5
    disc = _ellipse(r, r, 0)
    iou = r * r / (r + w) ** 2
    assert shapes.distinct_px(disc, iou) == pytest.approx(w, rel=0.08)  # a digital disc's perimeter: ~3 %
    assert shapes.distinct_px(np.zeros((20, 20), np.uint8), 0.5) == 0.0


def test_an_outline_a_plain_shape_has_is_within_a_pixel_and_a_cross_is_not():
    disc = _ellipse(45, 45, 0)
    assert shapes.distinct_px(disc, shapes.genericity(disc)) < 0.5
    u = 40.0
    arm = [(-0.5, -1.5), (0.5, -1.5), (0.5, -0.5), (1.5, -0.5), (1.5, 0.5), (0.5, 0.5), (0.5, 1.5),
           (-0.5, 1.5), (-0.5, 0.5), (-1.5, 0.5), (-1.5, -0.5), (-0.5, -0.5)]
    cross = _polygon(np.array(arm) * u + [200, 150])
    # generic < 0.8 (above): (1 - 0.8) x area 5 u^2 / perimeter 12 u = u / 12 = 3.3 px at least
    assert shapes.distinct_px(cross, shapes.genericity(cross)) > u / 12.0
