"""Estimate confidence (contract version 3) and the risk-coverage curve it feeds."""

from __future__ import annotations

import numpy as np
import pytest

from posegrasp.core.contract import CONTRACT_VERSION, Estimate, confidence_problem
from posegrasp.core.errors import InvalidArgumentError
from sim.stats import risk_coverage


def test_an_estimate_of_an_older_contract_has_no_confidence() -> None:
    assert CONTRACT_VERSION == 3
    assert Estimate(np.eye(4)).confidence is None
    assert Estimate(np.eye(4), (), {}, 0.5).confidence == 0.5


@pytest.mark.parametrize(
    ("value", "words"),
    [(float("nan"), "finite"), (float("inf"), "finite"), ("high", "str"), (True, "bool")],
)
def test_a_confidence_that_is_not_one_finite_number_is_named(value, words) -> None:
    assert words in confidence_problem(value)


@pytest.mark.parametrize("value", [None, 0, -3.5, np.float32(0.2)])
def test_none_and_finite_numbers_are_confidences(value) -> None:
    assert confidence_problem(value) is None


def test_the_curve_attempts_the_surest_first_against_a_brute_force_count() -> None:
    rng = np.random.default_rng(3)
    conf = [None if rng.random() < 0.2 else float(rng.integers(0, 6)) for _ in range(60)]
    held = [bool(b) for b in rng.random(60) < 0.6]
    rc = risk_coverage(conf, held)
    assert rc is not None
    for t, cov, succ in zip(rc["threshold"], rc["coverage"], rc["success"], strict=True):
        attempted = [h for c, h in zip(conf, held, strict=True) if c is not None and c >= t]
        assert cov == pytest.approx(len(attempted) / 60)
        assert succ == pytest.approx(sum(attempted) / len(attempted))
    assert rc["threshold"] == sorted({c for c in conf if c is not None}, reverse=True)
    assert rc["coverage"][-1] == pytest.approx(sum(c is not None for c in conf) / 60)


def test_the_area_rewards_a_confidence_that_ranks_the_held_grasps_first() -> None:
    held = [True] * 6 + [False] * 4
    ranked = risk_coverage(list(range(10, 0, -1)), held)
    reversed_ = risk_coverage(list(range(1, 11)), held)
    flat = risk_coverage([1.0] * 10, held)
    assert ranked["area"] > flat["area"] > reversed_["area"]
    assert flat["area"] == pytest.approx(0.6)
    # attempting the 6 surest holds every time: the first six points are all successes
    assert ranked["success"][:6] == [1.0] * 6


def test_no_confidence_is_no_curve_and_lengths_must_agree() -> None:
    assert risk_coverage([None, None], [True, False]) is None
    with pytest.raises(InvalidArgumentError, match="3 confidences for 2 episodes"):
        risk_coverage([1.0, 2.0, 3.0], [True, False])
