"""The grasp-success gate: its paired rule, failing closed, and the gate against its baseline."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from posegrasp.core.errors import AssetError
from posegrasp.world.objects import OBJECT_NAMES
from sim import gate
from sim.evaluate import execution_settings

WEIGHTS = {"w.pt": "0123"}


def _report(lost: int = 0, won: int = 0, margin_shift: float = 0.0, **protocol) -> dict:
    """A 60-episode gate report; the baseline grasped all but episodes 0-1 (lost/won relative
    to that)."""
    eps = []
    for i in range(60):
        base_ok = i >= 2
        ok = (base_ok and i >= 2 + lost) or (not base_ok and i < won)
        eps.append(
            {
                "object": "phone",
                "seed": gate.GATE_SEED_START + i,
                "success": ok,
                "failure_reason": None if ok else "missed",
                "friction_margin": (0.2 + 0.001 * i + margin_shift) if ok else None,
            }
        )
    rep = {
        "estimator": "hybrid",
        "tier": gate.GATE_TIER,
        "seed_start": gate.GATE_SEED_START,
        "episodes_per_object": 10,
        "execution": execution_settings(),
        "overall": {"successes": sum(e["success"] for e in eps)},
        "episodes": eps,
    }
    rep.update(protocol)
    return rep


@pytest.fixture
def baseline(monkeypatch) -> dict:
    monkeypatch.setattr(gate, "weights_fingerprint", lambda: WEIGHTS)
    return gate.baseline_of(_report())


@pytest.mark.parametrize(
    "lost, won, shift, passed",
    [
        (0, 0, 0.0, True),  # unchanged code and weights: identical episodes
        (2, 1, 0.0, True),  # a few flips either way: not significant
        (4, 0, 0.0, True),  # 4 lost, none won: one-sided p = 0.0625
        (5, 0, 0.0, False),  # 5 lost, none won: p = 0.031
        (5, 2, 0.0, True),  # 5 lost, 2 won: p = 0.23
        (0, 2, 0.0, True),  # only gains: never a regression
        (0, 0, 0.01, True),  # a small margin rise
        (0, 0, 0.05, False),  # looser grasps everywhere
    ],
)
def test_paired_rule(baseline: dict, lost: int, won: int, shift: float, passed: bool) -> None:
    ok, verdict = gate.compare(_report(lost, won, shift), baseline, WEIGHTS)
    assert ok is passed
    assert verdict.startswith("PASS" if passed else "FAIL")


def test_a_run_of_another_protocol_or_other_weights_fails(baseline: dict) -> None:
    ok, verdict = gate.compare(_report(tier="isolated"), baseline, WEIGHTS)
    assert not ok and "gate --write" in verdict
    # The same scenes grasped with other physics (here: a simulated transit) are not paired.
    other = {**execution_settings(), "transit": "dynamic"}
    ok, verdict = gate.compare(_report(execution=other), baseline, WEIGHTS)
    assert not ok and "execution settings" in verdict
    ok, verdict = gate.compare(_report(), baseline, {"w.pt": "ffff"})
    assert not ok and "other weights" in verdict


@pytest.mark.parametrize("content", ["", "[]", "{}", '{"hybrid": {"estimator": "hybrid"}}'])
def test_a_bad_baseline_fails_closed(tmp_path: Path, capsys, content: str) -> None:
    path = tmp_path / "b.json"
    path.write_text(content)
    with pytest.raises(AssetError, match="gate --write"):
        gate.load_baselines(path)
    assert gate.main(["--baseline", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--write" in err


def test_gate_cli_names_the_missing_baseline(tmp_path: Path, capsys, baseline: dict) -> None:
    path = tmp_path / "b.json"
    path.write_text(json.dumps({"hybrid": baseline}))
    assert gate.main(["--baseline", str(path), "--estimator", "oracle"]) == 2
    assert "no baseline for oracle" in capsys.readouterr().err


def test_baseline_covers_the_gate_estimators() -> None:
    base = gate.load_baselines()
    assert set(base) == set(gate.GATE_ESTIMATORS)
    for rec in base.values():
        assert rec["tier"] == gate.GATE_TIER
        assert len(rec["episodes"]) == gate.GATE_EPISODES * len(OBJECT_NAMES)


@pytest.mark.slow
@pytest.mark.parametrize("estimator", gate.GATE_ESTIMATORS)
def test_grasp_success_gate(estimator: str) -> None:
    """The regression gate: each gate estimator on 10 held-out hard episodes per object,
    paired with its committed baseline by the rule documented in `sim.gate`."""
    base = gate.load_baselines()[estimator]
    report = gate.run_gate(estimator, base["episodes_per_object"], workers=2)
    ok, verdict = gate.compare(report, base)
    assert ok, verdict + "\n" + gate.format_report(report)
