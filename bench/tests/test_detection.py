"""The detection benchmark's own logic: its policy options (``bench/lib/policy.py``), the verdict weights
it passes as a ``Policy``, and each target's fate."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from bench import detection
from bench.lib.data import MIN_VISIBLE, RIGHT_PX
from bench.lib.policy import POLICY_OPTIONS, add_policy_options, policy_of
from bench.lib.scenes import l_block_bank
from service.vision import pipeline
from service.vision.estimate.evidence import colour_frame
from service.vision.estimate.verdict import FEATURES, WEIGHTS
from service.vision.geometry.camera import Intrinsics
from service.vision.geometry.frames import Pose, Rx, Ry, Rz
from service.vision.geometry.render import render_shaded
from service.vision.pipeline import DEFAULT_POLICY, Policy


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser()
    add_policy_options(ap)
    return ap


def test_each_bench_policy_option_sets_the_policy_field_it_names():
    """``bench/detection.py`` runs the estimate at another ``Policy``: each option sets its field, the
    taught-search options the uncalibrated part's search, and no option leaves the service's policy."""
    argv, expected = [], {}
    for option, (field, kind, _) in POLICY_OPTIONS.items():
        value = kind(getattr(DEFAULT_POLICY, field)) + kind(1)  # a renamed field fails here
        argv += [option, str(value)]
        expected[field] = value
    policy = policy_of(_parser().parse_args([*argv, "--colour-prior", "--scored-fits", "48"]))
    for field, value in expected.items():
        assert getattr(policy, field) == value, field
    assert policy.taught_search.colour_prior and policy.taught_search.scored_fits == 48
    assert policy.calibrated_search == DEFAULT_POLICY.calibrated_search
    assert policy_of(_parser().parse_args([])) == DEFAULT_POLICY


def test_weights_become_the_policy_s_verdict_weights_and_leave_the_service_s_alone(tmp_path):
    service_weights = dict(WEIGHTS)
    path = tmp_path / "w.json"
    path.write_text(json.dumps({"bias": -1.0, "region_global": 2.0}))
    policy = policy_of(_parser().parse_args(["--weights", str(path)]))
    assert dict(policy.verdict_weights) == {"bias": -1.0, "region_global": 2.0}
    assert service_weights == WEIGHTS
    path.write_text(json.dumps({"bias": -1.0, "shading_r2_robust": 2.0}))  # evidence no longer measured
    with pytest.raises(ValueError, match="shading_r2_robust"):
        policy_of(_parser().parse_args(["--weights", str(path)]))


def test_the_policy_s_verdict_weights_judge_an_untaught_candidate():
    """The same refined pose of a rendered block: found under weights that always accept, refused under
    weights that never do, and judged as the service judges it by default."""
    bank = l_block_bank()
    intr = Intrinsics(600.0, 600.0, 319.5, 239.5)
    truth = Pose(Rx(35.0) @ Ry(-20.0) @ Rz(15.0), np.array([10.0, -5.0, 430.0]))
    grey = render_shaded(bank.vertices_mm, bank.faces, truth, intr.K, (640, 480), background=70)
    img = np.repeat(grey[..., None], 3, axis=2)

    def check(policy):
        cand = pipeline.PoseCandidate(truth, 0.0, 0.0)
        return pipeline.check_candidate(bank, cand, grey, colour_frame(img), intr, distance_mm=None,
                                        distance_range_mm=None, min_score=None,
                                        n_channels=DEFAULT_POLICY.search_params.n_channels, policy=policy)

    service = check(DEFAULT_POLICY)
    assert service.verdict.found
    accept = check(Policy(verdict_weights=(("bias", 20.0),)))
    refuse = check(Policy(verdict_weights=(("bias", -20.0),)))
    assert accept.verdict.found and accept.verdict.score > 0.999
    assert not refuse.verdict.found and refuse.verdict.score < 0.001
    # the same evidence judged (a found answer's twin check adds its twin's score)
    same = [{k: c.verdict.evidence.get(k) for k in FEATURES} for c in (service, accept, refuse)]
    assert same[0] == same[1] == same[2]


def test_each_target_s_fate_follows_from_its_record():
    def rec(image, model, *, found=False, mspd=float("inf"), right=None, nearest=float("inf"), visible=1.0):
        return {"image": f"images/{image}.png", "model": model, "absent": False, "found": found,
                "mspd640": mspd, "visible": visible, "right_checked": right, "nearest_checked_px": nearest}

    just_right, just_wrong = RIGHT_PX - 0.1, RIGHT_PX
    recs = [rec("000001", "lmo_09", found=True, mspd=just_right, nearest=just_right),
            rec("000001", "lmo_12", found=True, mspd=just_wrong, nearest=just_wrong),
            rec("000001", "lmo_01", right={"score": 0.9712, "reason": "below_operating_point"}, nearest=3.0),
            rec("000002", "lmo_05", nearest=detection.NEAR_PX - 1, visible=detection.OCCLUDED_BELOW - 0.01),
            rec("000002", "lmo_11", nearest=detection.NEAR_PX),
            rec("000002", "lmo_10", visible=MIN_VISIBLE - 0.01)]  # not a target: left out
    assert [detection.fate(r) for r in recs[:5]] == list(detection.FATES)
    table = detection.per_image_table(recs).splitlines()
    assert table[2] == "| 000001 | 3 | duck | holepuncher | ape 0.971 | - | - |"
    assert table[3] == "| 000002 | 2 | - | - | - | can* 49 px | glue |"
    assert table[4] == "| **all** | 5 | **1** | **1** | **1** | **1** | **1** |"
    assert detection.per_image_table([dict(recs[0], absent=True)]) == ""  # an absent set has no targets

    passes = {"score": 0.985, "found": True, "mspd640": just_right, "reason": "found"}
    refined_away = dict(passes, mspd640=just_wrong)  # found, but the refinement left the truth
    recs[3]["truth_checked"], recs[4]["truth_checked"] = passes, refined_away
    table = detection.per_image_table(recs).splitlines()
    assert table[3] == "| 000002 | 2 | - | - | - | can* 49 px (truth 0.985, passes) | glue (truth 0.985) |"
    assert table[-1].endswith("near miss 1 of 1, not proposed 0 of 1")
