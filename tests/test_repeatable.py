"""The same frame gets the same answer: whether the process's tables were made yet (cold or warm memos)
and how many threads numba runs must change no candidate, pose or verdict (no deadline given)."""

from __future__ import annotations

import gc
import json

import cv2
import numpy as np
import pytest
import trimesh

from service.vision import pipeline, threads
from service.vision.geometry.camera import Intrinsics
from service.vision.memo import Memo


def _clear_memos() -> None:
    """Every memo of the process emptied: the next estimate makes its tables as a fresh process would."""
    for memo in [o for o in gc.get_objects() if isinstance(o, Memo)]:
        memo.clear()


def _answer(out: pipeline.EstimateOutput) -> tuple:
    """Everything an estimate answers, exactly: the candidates' poses, costs and scores, the verdict, the
    refined pose."""
    cands = [(c.pose.R.tobytes(), c.pose.t_mm.tobytes(), c.cost, c.score) for c in out.candidates]
    refined = None if out.refined is None else (out.refined.pose.R.tobytes(), out.refined.pose.t_mm.tobytes())
    return out.found, out.verdict.reason, out.verdict.score, refined, cands


@pytest.mark.slow
def test_a_clutter_frame_gets_one_answer_cold_warm_and_on_any_thread_count(data_dir):
    """clutter 0002 (the flange among distractors, no distance given): its level-B scans gave other
    candidates from run to run on two threads (the shared bound read as the threads ran)."""
    gt = json.loads((data_dir / "clutter" / "gt.jsonl").read_text().splitlines()[1])
    assert gt["image"] == "images/0002.png"
    mesh = trimesh.load(data_dir / "clutter" / "models" / "flange.stl", force="mesh")
    bank = pipeline.build_templates(mesh)
    image = cv2.imread(str(data_dir / "clutter" / gt["image"]), cv2.IMREAD_UNCHANGED)
    intr = Intrinsics.from_K(np.asarray(gt["K"], float))
    try:
        threads.configure(None)  # every core numba has
        _clear_memos()
        cold = _answer(pipeline.estimate(bank, image, intr))
        warm = _answer(pipeline.estimate(bank, image, intr))
        threads.configure(1)
        one_thread = _answer(pipeline.estimate(bank, image, intr))
    finally:
        threads.configure(None)
    assert len(cold[4]) > 1  # several candidates to compare
    assert warm == cold
    assert one_thread == cold
