"""The grasp-success gate: its margin rule, and the gate itself against the committed baseline."""

from __future__ import annotations

import json

import pytest

from sim import gate


def _report(k: int, n: int = 60, estimator: str = "hybrid", seed: int = gate.GATE_SEED_START):
    return {
        "estimator": estimator,
        "episodes_per_object": n // 6,
        "seed_start": seed,
        "overall": {"episodes": n, "successes": k, "success_rate": k / n},
        "per_object": {},
    }


def test_margin_is_the_wilson_half_width_below_the_rate() -> None:
    # 57/60: Wilson 95 % interval [0.8629, 0.9829] -> 8.71 points below 0.95.
    assert gate.margin(57, 60) == pytest.approx(0.95 - 0.8629, abs=2e-4)
    assert gate.margin(60, 60) == pytest.approx(1 - 0.9398, abs=2e-4)


@pytest.mark.parametrize("k, passed", [(60, True), (57, True), (52, True), (51, False), (0, False)])
def test_compare_fails_only_below_the_floor(k: int, passed: bool) -> None:
    base = gate.baseline_of(_report(57))
    ok, verdict = gate.compare(_report(k), base)
    assert ok is passed
    assert verdict.startswith("PASS" if passed else "FAIL")


def test_compare_rejects_a_different_protocol() -> None:
    base = gate.baseline_of(_report(57))
    ok, verdict = gate.compare(_report(57, seed=0), base)
    assert not ok and "gate --write" in verdict


def test_baseline_covers_the_gate_estimators() -> None:
    assert set(gate.load_baselines()) == set(gate.GATE_ESTIMATORS)


def test_a_single_record_baseline_is_read_by_its_estimator(tmp_path) -> None:
    path = tmp_path / "b.json"
    path.write_text(json.dumps(gate.baseline_of(_report(57))))
    assert list(gate.load_baselines(path)) == ["hybrid"]


def test_gate_cli_names_the_missing_baseline(tmp_path, capsys) -> None:
    path = tmp_path / "b.json"
    path.write_text(json.dumps({"hybrid": gate.baseline_of(_report(57))}))
    assert gate.main(["--baseline", str(path), "--estimator", "oracle"]) == 2
    assert "no baseline for oracle" in capsys.readouterr().err


@pytest.mark.parametrize("estimator", gate.GATE_ESTIMATORS)
def test_grasp_success_gate(estimator: str) -> None:
    """The regression gate: each gate estimator on 10 held-out episodes per object must not
    fall below its committed baseline by more than the margin documented in `sim.gate`."""
    base = gate.load_baselines()[estimator]
    report = gate.run_gate(estimator, base["episodes_per_object"], workers=2)
    ok, verdict = gate.compare(report, base)
    assert ok, verdict + "\n" + gate.format_report(report)
