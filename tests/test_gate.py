"""The grasp-success gate: its paired rule, failing closed, and the gate against its baseline."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from posegrasp.core.contract import Estimate
from posegrasp.core.errors import AssetError
from posegrasp.core.files import sha256_file
from posegrasp.core.paths import REPO_ROOT
from posegrasp.world.objects import OBJECT_NAMES
from posegrasp.world.shifts import parse_shifts
from sim import gate
from sim.episodes.episode import execution_settings

WEIGHTS = {"w.pt": "0123"}


class Plugin:
    """A plug-in estimator that does not say which weights it loads."""

    name = "plugin"

    def estimate(self, obs) -> Estimate:
        return Estimate(None)


class ReportingPlugin(Plugin):
    """A plug-in that reports its weights files (here: this test file and one that is absent)."""

    def weights_files(self) -> list[str]:
        return [__file__, "/nonexistent/w.pt"]


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
        "obs_mode": "rgb",
        "overall": {"successes": sum(e["success"] for e in eps)},
        "episodes": eps,
    }
    rep.update(protocol)
    return rep


@pytest.fixture
def baseline() -> dict:
    return gate.baseline_of(_report(), WEIGHTS)


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
    assert not ok and "other weights (w.pt ffff against 0123)" in verdict
    ok, verdict = gate.compare(_report(), baseline, {**WEIGHTS, "m.pt": "4567"})
    assert not ok and "m.pt 4567 against not recorded" in verdict


def test_a_baseline_of_another_observation_mode_is_refused(baseline: dict) -> None:
    assert baseline["obs_mode"] == "rgb"
    ok, verdict = gate.compare(_report(obs_mode="rgbd"), baseline, WEIGHTS)
    assert not ok and "mode (--obs-mode) ('rgbd') is not the baseline's ('rgb')" in verdict
    assert gate.compare(_report(), baseline, WEIGHTS)[0]


def test_the_gate_refuses_another_mode_before_running(
    tmp_path: Path, capsys, monkeypatch, baseline: dict
) -> None:
    """``--obs-mode rgbd`` against a baseline of rgb fails without running an episode."""
    base = {**baseline, **gate.gate_protocol("hybrid")}
    path = tmp_path / "b.json"
    path.write_text(json.dumps({"hybrid": base}))
    monkeypatch.setattr(gate, "estimator_fingerprint", lambda name: (WEIGHTS, None))

    def no_run(*args, **kwargs):
        raise AssertionError("the gate ran episodes against a baseline it must refuse")

    monkeypatch.setattr(gate, "run_gate", no_run)
    assert gate.main(["--baseline", str(path), "--obs-mode", "rgbd"]) == 1
    out = capsys.readouterr().out
    assert "hybrid: FAIL: the run's observation mode (--obs-mode) ('rgbd')" in out
    assert gate.main(["--baseline", str(path), "--obs-mode", "bad"]) == 2
    assert "valid observation modes: rgb, rgbd" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("run", "recorded", "flags"),
    [
        ({"task": "place"}, "the lift task under no scene shift", "--task place"),
        ({"shifts": ["camera:3"]}, "the lift task under no scene shift", "--shift camera:3"),
        ({}, "the place task under no scene shift", ""),
    ],
)
def test_a_baseline_of_another_task_or_shifts_is_refused_with_how_to_record_one(
    baseline: dict, run: dict, recorded: str, flags: str
) -> None:
    """A baseline is of one task under one set of shifts: a run of another is not paired, and
    the verdict names the command that records a baseline for it."""
    if not run:
        baseline = gate.baseline_of(_report(task="place"), WEIGHTS)
        assert baseline["task"] == "place"
    ok, verdict = gate.compare(_report(**run), baseline, WEIGHTS)
    assert not ok and "\n" not in verdict
    assert f"the baseline of hybrid was recorded for {recorded}, not the " in verdict
    command = f"`python -m sim.gate --write --estimator hybrid {flags}".rstrip()
    assert command + " --baseline PATH`" in verdict and "a file of its own" in verdict
    # A baseline of the run's own task and shifts pairs with it.
    own = gate.baseline_of(_report(**run), WEIGHTS)
    assert {k: own[k] for k in run} == run and gate.compare(_report(**run), own, WEIGHTS)[0]


def test_the_gate_protocol_records_task_and_shifts_as_reports_do() -> None:
    assert "task" not in gate.gate_protocol("hybrid") and "shifts" not in gate.gate_protocol("h")
    run = gate.gate_protocol("hybrid", task="place", shifts=parse_shifts("walls,camera:3"))
    assert run["task"] == "place" and run["shifts"] == ["walls:2", "camera:3"]
    protocol = gate.gate_run_protocol(task="place", shifts=parse_shifts("camera:3"))
    assert protocol.episode_config().task == "place"
    assert gate.gate_journal("hybrid", task="place") != gate.gate_journal("hybrid")


def test_the_gate_refuses_a_place_run_before_running(
    tmp_path: Path, capsys, monkeypatch, baseline: dict
) -> None:
    """``--task place`` against a lift baseline fails without running an episode, in one line
    that names how to record a place baseline; writing one into the shipped lift baselines is
    refused; a bad task or shift is one line naming the valid ones."""
    path = tmp_path / "b.json"
    path.write_text(json.dumps({"hybrid": {**baseline, **gate.gate_protocol("hybrid")}}))
    monkeypatch.setattr(gate, "estimator_fingerprint", lambda name: (WEIGHTS, None))

    def no_run(*args, **kwargs):
        raise AssertionError("the gate ran episodes against a baseline it must refuse")

    monkeypatch.setattr(gate, "run_gate", no_run)
    assert gate.main(["--baseline", str(path), "--task", "place"]) == 1
    (line,) = [ln for ln in capsys.readouterr().out.splitlines() if "FAIL" in ln]
    assert line.startswith("hybrid: FAIL: the baseline of hybrid was recorded for the lift task")
    assert "--write --estimator hybrid --task place --baseline PATH" in line
    assert gate.main(["--baseline", str(path), "--shift", "all:3"]) == 1
    assert "--shift light_colour:3,light_intensity:3," in capsys.readouterr().out
    for argv, says in [
        (["--write", "--task", "place"], "write the baseline of --task place to a file of its own"),
        (["--write", "--shift", "camera"], "of --shift camera:2 to a file of its own"),
        (["--task", "stack"], "valid tasks: lift, place"),
        (["--shift", "fog"], "valid scene shifts: light_colour"),
    ]:
        assert gate.main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert says in err and "\n" not in err, argv


def test_a_baseline_without_an_observation_mode_fails_closed(tmp_path: Path, baseline) -> None:
    path = tmp_path / "b.json"
    path.write_text(json.dumps({"hybrid": {k: v for k, v in baseline.items() if k != "obs_mode"}}))
    with pytest.raises(AssetError, match="lacks obs_mode"):
        gate.load_baselines(path)


def test_plugins_fingerprint_what_they_report() -> None:
    weights, note = gate.estimator_fingerprint("tests.test_gate:ReportingPlugin")
    assert note is None
    assert weights == {
        "tests/test_gate.py": sha256_file(Path(__file__))[:16],
        "/nonexistent/w.pt": "missing",
    }
    weights, note = gate.estimator_fingerprint("tests.test_gate:Plugin")
    assert weights == {} and "fingerprint is empty" in note
    assert gate.estimator_fingerprint("oracle") == ({}, None)


def test_the_committed_baseline_has_the_default_estimators_weights() -> None:
    """The fingerprint holds every file the default estimator loads (the mask net too), and
    the committed baseline is not refused for it."""
    weights, note = gate.estimator_fingerprint(gate.DEFAULT_ESTIMATOR)
    assert note is None and "perception/weights/tiers/masknet.pt" in weights
    assert all((REPO_ROOT / k).is_file() for k in weights)
    base = gate.load_baselines()[gate.DEFAULT_ESTIMATOR]
    assert gate.mismatch(gate.gate_protocol(gate.DEFAULT_ESTIMATOR), base, weights) is None


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


def test_a_place_baseline_made_on_another_belief_is_refused() -> None:
    """A place baseline from before the predicted belief (none recorded) is not paired with a
    place run today; a lift has no belief either side."""
    weights = gate.estimator_fingerprint(gate.DEFAULT_ESTIMATOR)[0]
    place = gate.gate_protocol(gate.DEFAULT_ESTIMATOR, task="place")
    assert place["belief"] == "predicted"
    before = {**place, "weights": weights}
    del before["belief"]
    said = "place belief (recorded on the place task) ('predicted') is not the baseline's (None)"
    assert said in gate.mismatch(place, before, weights)
    assert gate.mismatch(place, {**place, "weights": weights}, weights) is None
    assert "belief" not in gate.gate_protocol(gate.DEFAULT_ESTIMATOR)
