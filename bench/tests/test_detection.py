"""The detection benchmark's own logic: its policy options and each target's fate."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_each_bench_policy_option_sets_the_policy_field_it_names():
    """``bench/detection.py`` runs the estimate at another ``Policy``: each option sets its field, the
    taught-search options the uncalibrated part's search, and no option leaves the service's policy."""
    import argparse

    sys.path.insert(0, str(ROOT))
    from bench import detection
    from service.vision.pipeline import DEFAULT_POLICY

    argv, expected = [], {}
    for option, (field, kind, _) in detection.POLICY_OPTIONS.items():
        value = kind(getattr(DEFAULT_POLICY, field)) + kind(1)  # a renamed field fails here
        argv += [option, str(value)]
        expected[field] = value
    ap = argparse.ArgumentParser()
    detection.add_policy_options(ap)
    policy = detection.policy_of(ap.parse_args([*argv, "--colour-prior", "--scored-fits", "48"]))
    for field, value in expected.items():
        assert getattr(policy, field) == value, field
    assert policy.taught_search.colour_prior and policy.taught_search.scored_fits == 48
    assert policy.calibrated_search == DEFAULT_POLICY.calibrated_search
    assert detection.policy_of(ap.parse_args([])) == DEFAULT_POLICY


def test_each_target_s_fate_follows_from_its_record():
    sys.path.insert(0, str(ROOT))
    from bench import detection

    def rec(image, model, *, found=False, mspd=float("inf"), right=None, nearest=float("inf"), visible=1.0):
        return {"image": f"images/{image}.png", "model": model, "absent": False, "found": found,
                "mspd640": mspd, "visible": visible, "right_checked": right, "nearest_checked_px": nearest}

    just_right, just_wrong = detection.RIGHT_PX - 0.1, detection.RIGHT_PX
    recs = [rec("000001", "lmo_09", found=True, mspd=just_right, nearest=just_right),
            rec("000001", "lmo_12", found=True, mspd=just_wrong, nearest=just_wrong),
            rec("000001", "lmo_01", right={"score": 0.9712, "reason": "below_operating_point"}, nearest=3.0),
            rec("000002", "lmo_05", nearest=detection.NEAR_PX - 1, visible=detection.OCCLUDED_BELOW - 0.01),
            rec("000002", "lmo_11", nearest=detection.NEAR_PX),
            rec("000002", "lmo_10", visible=detection.MIN_VISIBLE - 0.01)]  # not a target: left out
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
