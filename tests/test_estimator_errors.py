"""Errors in the middle of an evaluation. An estimator that raises, whatever it raises, fails
its own episode as ``error`` with the exception in its notes; the episode keeps its scene, true
pose and timings, and the evaluation goes on to the next episode. A run that dies all the same
keeps what finished and says how to resume it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from posegrasp.core.contract import Estimate, Observation
from posegrasp.core.journal import Journal, run_journaled
from sim.episodes.episode import Episode, play_episode
from sim.evaluate import main as evaluate_main
from sim.evaluation import EpisodeJob, Protocol, run_job
from sim.evaluation.report_schema import validate_report

SEED = 1_000_000_000


class Dividing:
    """An estimator with a bug of its own."""

    name = "dividing"

    def estimate(self, obs: Observation) -> Estimate:
        pixels_on_target = 0
        return Estimate(None, info={"score": 1 / pixels_on_target})


class Tuple:
    """An estimator that answers a bare tuple, not an `Estimate`."""

    name = "tuple"

    def estimate(self, obs: Observation) -> tuple:
        return (np.eye(4), ())


def test_an_estimator_that_raises_fails_its_episode_as_error() -> None:
    result = play_episode("phone", SEED, Dividing())
    assert (result.success, result.failure_reason) == (False, "error")
    assert result.notes == ["estimator dividing raised ZeroDivisionError: division by zero"]
    truth = Episode("phone", SEED)
    np.testing.assert_array_equal(result.T_C_O_true, truth.T_C_O_true)
    truth.close()
    assert result.T_C_O_est is None and result.pose_error is None and result.pose_correct is None
    assert {"scene", "render", "estimate", "total"} <= set(result.timings_ms)
    assert result.scene["resting_pose"] is not None and result.estimator == "dividing"


def test_an_answer_that_is_not_an_estimate_fails_its_episode_as_error() -> None:
    result = play_episode("car", SEED, Tuple())
    assert result.failure_reason == "error"
    assert result.notes == [
        "estimator 'tuple' returned tuple, not an Estimate (posegrasp.core.contract, version 3)"
    ]


def test_an_evaluation_records_every_raising_episode_and_exits_0(tmp_path: Path) -> None:
    out = tmp_path / "report.json"
    args = ["--estimator", "tests.test_estimator_errors:Dividing", "--objects", "phone"]
    assert evaluate_main([*args, "--episodes", "2", "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    validate_report(report)
    episodes = report["episodes"]
    assert [e["seed"] for e in episodes] == [SEED, SEED + 1]
    assert [e["failure_reason"] for e in episodes] == ["error", "error"]
    assert all("raised ZeroDivisionError" in e["notes"][0] for e in episodes)
    assert all(e["T_C_O_true"] is not None for e in episodes)
    assert report["overall"]["failure_reasons"] == {"error": 2}
    assert not out.with_name("report.journal.jsonl").exists()


@pytest.mark.parametrize(
    "error, note",
    [(KeyError("qpos"), "KeyError: 'qpos'"), (MemoryError(), "MemoryError: ")],
)
def test_any_exception_of_an_episode_is_recorded_not_raised(
    monkeypatch: pytest.MonkeyPatch, error: Exception, note: str
) -> None:
    def broken(*args: object, **kwargs: object) -> None:
        raise error

    monkeypatch.setattr("sim.episodes.episode.play_episode", broken)
    d = run_job(EpisodeJob("phone", SEED, "oracle", Protocol(["phone"], 1, SEED, "isolated")))
    assert (d["success"], d["failure_reason"], d["notes"]) == (False, "error", [note])


def test_a_run_that_dies_after_some_work_says_how_to_resume(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def crash(x: int) -> dict:
        if x == 2:
            raise RuntimeError("worker lost")
        return {"x": x}

    path = tmp_path / "run.journal.jsonl"
    with pytest.raises(RuntimeError, match="worker lost"):
        run_journaled(crash, range(5), 5, Journal(path, "square", {"jobs": 5}))
    hints = [line for line in capsys.readouterr().err.splitlines() if "resume with:" in line]
    assert len(hints) == 1, hints
    assert hints[0].startswith(f"stopped by RuntimeError: 2 of 5 finished and kept in {path}; ")
    assert hints[0].endswith(" --resume") and len(path.read_text().splitlines()) == 3
