"""The found/absent decision table (estimate/verdict.py): each threshold decides on its side of it."""

from __future__ import annotations

import pytest

from service.vision.estimate.verdict import (
    FOUND_MAX_UNEXPLAINED,
    FOUND_MIN_REFINED_SCORE,
    FOUND_MIN_SCORE,
    decide,
    needs_refined_check,
    screen,
)

EPS = 1e-6


def test_no_candidate_or_a_low_coarse_score_is_decided_by_the_coarse_stage():
    assert screen(None).found is False and screen(None).evidence == {}
    low = screen(FOUND_MIN_SCORE - EPS)
    assert low.found is False and low.evidence == {"coarse_score": pytest.approx(FOUND_MIN_SCORE - EPS)}
    assert screen(FOUND_MIN_SCORE) is None  # at the bar: checked further
    assert decide(FOUND_MIN_SCORE - EPS, verified_score=1.0, unexplained=0.0).found is False


def test_the_refinement_is_the_check_unless_the_coarse_score_is_already_as_high():
    assert needs_refined_check(FOUND_MIN_REFINED_SCORE - EPS, refine=False)
    assert not needs_refined_check(FOUND_MIN_REFINED_SCORE, refine=False)
    assert needs_refined_check(1.0, refine=True)


@pytest.mark.parametrize(("verified", "unexplained", "found"), [
    (FOUND_MIN_REFINED_SCORE, FOUND_MAX_UNEXPLAINED, True),
    (FOUND_MIN_REFINED_SCORE - EPS, 0.0, False),
    (1.0, FOUND_MAX_UNEXPLAINED + EPS, False),
])
def test_verified_score_and_unexplained_edges_decide_on_their_side_of_the_bar(verified, unexplained, found):
    v = decide(0.7, verified_score=verified, unexplained=unexplained)
    assert v.found is found
    assert v.score == pytest.approx(verified)  # the full-resolution score, not the coarse one
    assert v.evidence["coarse_score"] == pytest.approx(0.7)
    assert v.evidence["verified_score"] == pytest.approx(verified)


def test_without_the_refinement_the_inside_alone_decides():
    assert decide(0.9, unexplained=0.1).found
    v = decide(0.9, unexplained=FOUND_MAX_UNEXPLAINED + EPS)
    assert not v.found and "verified_score" not in v.evidence and v.score == pytest.approx(0.9)
    with pytest.raises(ValueError):
        decide(0.9)  # over the bar, the inside must have been measured
