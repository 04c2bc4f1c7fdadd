"""The verdict-at-the-truth table (``bench/at_truth.py``): which targets read over their point, and how a
run left them."""

from __future__ import annotations

import json

from bench import at_truth


def _row(model, image, copy, agreement, point, distinct=True):
    return {"model": model, "image": image, "copy": copy, "agreement": agreement, "point": point,
            "distinct": distinct}


def test_targets_over_their_point_split_by_how_the_run_left_them(tmp_path):
    rows = [_row("a", "i0", 0, 0.9, 0.8),            # over, found
            _row("a", "i0", 1, 0.85, 0.8),           # over, checked, not found
            _row("a", "i1", 0, 0.81, 0.8),           # over, not reached
            _row("a", "i1", 1, 0.7, 0.8),            # under its point
            _row("a", "i2", 0, 0.99, 0.8, False),    # a plain outline: never over
            _row("a", "i2", 1, 0.99, None)]          # not calibrated: never over
    run = [{"image": "i0", "model": "a", "copies": [{"right": True, "proposed": True},
                                                    {"right": False, "proposed": True}]},
           {"image": "i1", "model": "a", "copies": [{"right": False, "proposed": False},
                                                    {"right": False, "proposed": True}]}]
    path = tmp_path / "run.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in run))
    states = at_truth.run_states(path)
    assert states[("i0", "a", 0)] == "found" and states[("i1", "a", 0)] == "missed"
    line = at_truth.table(rows, states).splitlines()[2]  # median of +0.10, +0.05, +0.01, -0.10
    assert line == "| a | 6 | 1 | 1 | 3 (50%) | +0.030 | 1 | 1 | 1 |"
