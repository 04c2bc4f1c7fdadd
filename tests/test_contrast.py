"""Oriented region contrast for the proposal engine (contrast.py): known answers."""

from __future__ import annotations

import numpy as np

from service.vision.estimate.contrast import Contrast, ContrastParams, contrast_score, oriented_contrast

# BGR colours of equal grey level (0.114 B + 0.587 G + 0.299 R = 100): an outline in colour only.
FLOOR_BGR, PART_BGR = (100, 100, 100), (95, 50, 200)


def _rectangle(floor=FLOOR_BGR) -> np.ndarray:
    img = np.zeros((240, 320, 3), np.uint8)
    img[:] = floor
    img[80:160, 80:240] = PART_BGR  # rows v 80..159, columns u 80..239
    return img


def test_an_isoluminant_outline_contrasts_across_its_normal_in_its_orientation_channel():
    c = oriented_contrast(_rectangle(), 16, 0.25, 8.0)  # grid px = 4 full-res px
    top, left = (20, 40), (30, 20)  # grid pixels on the top side (v = 80) and the left side (u = 80)
    # the top side is horizontal (edge direction 0: channel 0), its normal vertical
    assert c[0][top] > 30 and c[8][top] < 1
    # the left side is vertical (channel 8)
    assert c[8][left] > 30 and c[0][left] < 1
    # inside and far outside the part there is no contrast in any direction
    assert c[:, 30, 40].max() < 1 and c[:, 5, 5].max() < 1


def test_an_edge_among_texture_scores_lower_than_the_same_edge_alone():
    img = np.full((240, 320, 3), 220, np.uint8)
    img[120:] = 40  # one horizontal step, dark below
    v, u = np.mgrid[:240, :320]
    checker = np.where((((u // 16) + (v // 16)) % 2 == 1)[..., None], 40, 220).astype(np.uint8).repeat(3, 2)
    cp = ContrastParams()
    alone = contrast_score(img, 16, cp, 100.0)[0][30, 40]  # on the step (v = 120), channel 0
    among = contrast_score(checker, 16, cp, 100.0)[0][28, 40]  # on a checker row boundary (v = 112)
    assert alone > 0.9
    assert among < alone - 0.2


def test_level_a_blend_keeps_the_dt3_at_weight_zero_and_costs_tau_without_contrast_at_weight_one():
    img = _rectangle()
    rng = np.random.default_rng(0)
    dt_q = rng.integers(0, 41, size=(30, 40, 16)).astype(np.uint8)  # level A's grid of a 320 x 240 frame
    keep = Contrast(img, 16, 0.125, ContrastParams(weight=0.0)).level_a(dt_q, 40, 10)
    assert np.array_equal(keep, dt_q)
    only = Contrast(img, 16, 0.125, ContrastParams(weight=1.0)).level_a(dt_q, 40, 10)
    assert only.shape == dt_q.shape
    assert np.all(only[3, 3] == 40)  # plain floor far from the part: no contrast, the full cost
    assert only[10, 15, 0] < 10  # on the top side (v = 80: level row 10), its own channel
