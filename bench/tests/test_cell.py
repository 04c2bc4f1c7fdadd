"""The cell benchmark's own logic (``bench/cell.py``): queries per (image, model), the plane as the API
maps it, the greedy one-instance-per-copy matching and the counts it gives."""

from __future__ import annotations

import numpy as np
import pytest

from bench import cell


def test_greedy_match_takes_copies_by_score_one_instance_each():
    d = np.array([[3.0, 12.0],   # score 0.5: nearest copy 0, taken by instance 1 (higher): copy 1
                  [4.0, 30.0],   # score 0.9: copy 0
                  [25.0, 40.0]])  # score 0.7: nothing under 20 px
    assert cell.greedy_match(d, [0.5, 0.9, 0.7], 20.0) == [1, 0, None]
    assert cell.greedy_match(d, [0.5, 0.9, 0.7], 5.0) == [None, 0, None]
    assert cell.greedy_match(np.zeros((2, 0)), [0.9, 0.8], 20.0) == [None, None]  # no copy: all wrong


def test_queries_group_lines_per_image_and_model_with_stride_start_models_limit():
    gts = [{"image": f"images/{i}.png", "model": m} for i in range(4) for m in ("a", "b", "a")]
    q = cell.queries_of(gts)
    assert [(im, m, len(lines)) for im, m, lines in q[:2]] == [("images/0.png", "a", 2),
                                                                ("images/0.png", "b", 1)]
    assert len(q) == 8
    assert {im for im, _, _ in cell.queries_of(gts, stride=2, start=1)} == {"images/1.png", "images/3.png"}
    assert [m for _, m, _ in cell.queries_of(gts, models={"b"})] == ["b"] * 4
    assert len(cell.queries_of(gts, limit=3)) == 3


def test_plane_is_scaled_to_a_unit_normal_and_one_behind_the_camera_is_refused():
    p = cell.plane_of({"image": "x", "plane": {"normal": [0.0, 0.0, -2.0], "d_mm": -700.0}})
    assert np.allclose(p.normal, [0, 0, -1]) and p.d_mm == pytest.approx(-350.0)
    with pytest.raises(ValueError):
        cell.plane_of({"image": "x", "plane": {"normal": [0.0, 0.0, 1.0], "d_mm": 350.0}})


def test_summary_counts_wrong_instances_also_on_images_without_a_copy():
    recs = [{"model": "a", "ms": 100.0,
             "copies": [{"target": True, "right": True, "fine": False}, {"target": False, "right": False,
                                                                       "fine": False}],
             "instances": [{"right": True}, {"right": False}]},
            {"model": "a", "ms": 300.0, "copies": [], "instances": [{"right": False}]}]
    s = cell.summarise(recs)
    assert (s["queries"], s["copies"], s["targets"], s["found"], s["right"], s["wrong"]) == (2, 2, 1, 3, 1, 2)
    assert (s["recall20"], s["recall5"], s["precision"]) == (1.0, 0.0, pytest.approx(1 / 3))
    assert s["proposed"] == 0.0  # records made before the column read as never checked near


def test_checked_counts_targets_a_checked_candidate_lay_near_whatever_the_verdict():
    copies = [{"target": True, "right": False, "fine": False, "proposed": True},
              {"target": True, "right": True, "fine": True, "proposed": True},
              {"target": False, "right": False, "fine": False, "proposed": True},
              {"target": True, "right": False, "fine": False, "proposed": False}]
    s = cell.summarise([{"model": "a", "ms": 1.0, "copies": copies, "instances": [{"right": True}]}])
    assert s["proposed"] == pytest.approx(2 / 3) and s["recall20"] == pytest.approx(1 / 3)
