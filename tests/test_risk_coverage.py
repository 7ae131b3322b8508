"""Estimate confidence (contract version 3) and the risk-coverage curve it feeds."""

from __future__ import annotations

import numpy as np
import pytest

from posegrasp.core.contract import CONTRACT_VERSION, Estimate, confidence_problem
from posegrasp.core.errors import InvalidArgumentError
from sim.evaluation import Protocol, format_report, make_report
from sim.evaluation.report_schema import validate_report
from sim.evaluation.stats import paired_area_difference, risk_coverage


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


def _episode(obj: str, seed: int, confidence: float | None, held: bool) -> dict:
    """An episode record as `sim.evaluate` writes it (schema `sim.evaluation.report_schema`); a
    confidence of None is left out, as `sim.episodes.episode.EpisodeResult.to_json` leaves it."""
    e = {
        "object": obj,
        "seed": seed,
        "estimator": "x",
        "tier": "isolated",
        "success": held,
        "failure_reason": None if held else "missed",
        "pose_error": None,
        "notes": [],
        "timings_ms": {},
        "wall_ms": 1.0,
    }
    return e if confidence is None else {**e, "confidence": confidence}


#: (object, confidence, held) of a hand-made evaluation: the car's estimator says nothing.
HAND_MADE = [
    ("phone", 0.9, True),
    ("phone", 0.8, False),
    ("phone", 0.8, True),
    ("phone", 0.3, False),
    ("phone", None, True),
    ("car", None, True),
    ("car", None, False),
]


def _report(rows=HAND_MADE, sensor: str = "ideal") -> dict:
    eps = [_episode(o, s, c, h) for s, (o, c, h) in enumerate(rows)]
    protocol = Protocol(["phone", "car"], len(eps), seed_start=0, sensor=sensor)
    return make_report(eps, protocol, "x")


def test_every_report_holds_the_curve_and_its_area_by_hand() -> None:
    report = validate_report(_report())
    phone, car, overall = (
        report["per_object"]["phone"]["risk_coverage"],
        report["per_object"]["car"]["risk_coverage"],
        report["overall"]["risk_coverage"],
    )
    # Ranked 0.9 (held), 0.8 and 0.8 (tied: one held), 0.3 (dropped): the first attempt holds
    # 1 of 1, the tie 2 of 3 each, the last 2 of 4.
    assert phone["area"] == pytest.approx((1 + 2 / 3 + 2 / 3 + 2 / 4) / 4)
    assert phone["threshold"] == [0.9, 0.8, 0.3]
    assert phone["coverage"] == pytest.approx([1 / 5, 3 / 5, 4 / 5])
    assert phone["success"] == pytest.approx([1, 2 / 3, 2 / 4])
    assert car is None  # no confidence in any of its episodes
    assert overall["area"] == pytest.approx(phone["area"])
    assert overall["coverage"][-1] == pytest.approx(4 / 7)
    none = _report([(o, None, h) for o, _, h in HAND_MADE])
    assert none["overall"]["risk_coverage"] is None


def test_a_report_without_the_curve_still_reads() -> None:
    report = _report()
    for g in [report["overall"], *report["per_object"].values()]:
        del g["risk_coverage"]
    assert validate_report(report) is report
    assert "risk-coverage area" not in format_report(report)  # not recorded, so not claimed
    report["overall"]["risk_coverage"] = {"area": 0.5}
    with pytest.raises(
        InvalidArgumentError, match=r"lacks the field overall\.risk_coverage\.threshold"
    ):
        validate_report(report)


def test_the_summary_names_the_sensor_and_prints_the_area() -> None:
    text = format_report(_report(sensor="kinect-v1"))
    head = text.splitlines()[0]
    assert head.startswith("estimator x, tier isolated, sensor kinect-v1: ")
    area = (1 + 2 / 3 + 2 / 3 + 2 / 4) / 4
    line = next(x for x in text.splitlines() if x.startswith("risk-coverage area"))
    assert line.endswith(f"phone {area:.3f}, car -, overall {area:.3f}")
    # No sensor recorded is the ideal camera; no confidence anywhere is said in words.
    plain = format_report(_report([(o, None, h) for o, _, h in HAND_MADE]))
    assert ", sensor ideal: " in plain.splitlines()[0]
    assert "risk-coverage area: none, the estimator gives no confidence" in plain


def test_the_paired_area_difference_by_hand() -> None:
    rng = np.random.default_rng(0)
    held = [True] * 6 + [False] * 4
    ranked, flat = list(range(10, 0, -1)), [1.0] * 10
    same = paired_area_difference(ranked, held, ranked, held, 500, rng)
    assert same["difference"] == 0.0 and same["bootstrap_low"] == same["bootstrap_high"] == 0.0
    r = paired_area_difference(flat, held, ranked, held, 2000, rng)
    assert r["a"] == pytest.approx(0.6) and r["b"] == risk_coverage(ranked, held)["area"]
    assert r["difference"] == pytest.approx(r["b"] - 0.6) and r["episodes"] == 10
    assert 0 < r["bootstrap_low"] < r["difference"] < r["bootstrap_high"]
    silent = paired_area_difference([None] * 10, held, ranked, held, 100, rng)
    assert silent["a"] is None and silent["b"] == r["b"] and silent["difference"] is None
    with pytest.raises(InvalidArgumentError, match="pair the same episodes"):
        paired_area_difference(flat, held, flat[:9], held[:9], 100, rng)
