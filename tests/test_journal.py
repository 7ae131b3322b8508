"""Runs that survive interruption (`posegrasp.core.journal`): the journal keeps what finished,
a resumed map runs only the rest, a unit kept as an interruption runs again and a report that
holds one is refused (real commands stopped by signals: tests/test_stopping.py)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.journal import (
    Interrupted,
    Journal,
    interrupted,
    journal_path,
    run_journaled,
)
from sim.evaluation.report_schema import read_report

REPO = Path(__file__).resolve().parent.parent
PROTOCOL = {"estimator": "oracle", "seeds": [1, 2, 3]}


def _square(x: int) -> dict:
    return {"x": x, "y": x * x}


def test_a_journal_keeps_units_and_resumes_past_a_cut_line(tmp_path: Path) -> None:
    path = tmp_path / "run.journal.jsonl"
    j = Journal(path, "evaluate", PROTOCOL)
    assert j.start(resume=False) == []
    j.append({"key": 0, "result": 1})
    j.append({"key": 1, "result": 2})
    j.close()
    with path.open("a") as f:
        f.write('{"key": 2, "res')  # the interruption cut this line short
    again = Journal(path, "evaluate", PROTOCOL)
    assert [u["key"] for u in again.start(resume=True)] == [0, 1]
    again.append({"key": 2, "result": 3})
    again.close()
    lines = path.read_text().splitlines()
    assert len(lines) == 4 and json.loads(lines[-1]) == {"key": 2, "result": 3}
    again.finish()
    assert not path.exists()


def test_a_journal_is_never_overwritten_or_mixed(tmp_path: Path) -> None:
    path = tmp_path / "run.jsonl"
    first = Journal(path, "evaluate", {**PROTOCOL, "seeds": [7]})
    first.start(resume=False)
    first.close()
    # A run stopped before its first unit left nothing to lose: a new run replaces it.
    j = Journal(path, "evaluate", PROTOCOL)
    j.start(resume=False)
    j.append({"key": 0, "result": 1})
    j.close()
    assert json.loads(path.read_text().splitlines()[0])["protocol"] == PROTOCOL
    with pytest.raises(InvalidArgumentError, match="--resume"):
        Journal(path, "evaluate", PROTOCOL).start(resume=False)
    with pytest.raises(InvalidArgumentError, match="differs in seeds"):
        Journal(path, "evaluate", {**PROTOCOL, "seeds": [4]}).start(resume=True)
    with pytest.raises(InvalidArgumentError, match="not a journal of a tolerance run"):
        Journal(path, "tolerance", PROTOCOL).start(resume=True)
    with pytest.raises(InvalidArgumentError, match="nothing to resume"):
        Journal(tmp_path / "none.jsonl", "evaluate", PROTOCOL).start(resume=True)


def test_journal_paths_sit_beside_the_report_or_in_the_data_folder(tmp_path, monkeypatch) -> None:
    assert journal_path(tmp_path / "out.json", "evaluate", PROTOCOL) == tmp_path / (
        "out.journal.jsonl"
    )
    monkeypatch.setenv("POSEGRASP_DATA", str(tmp_path))
    p = journal_path("-", "evaluate", PROTOCOL)
    assert p.parent == tmp_path / "runs" and p == journal_path(None, "evaluate", PROTOCOL)
    assert p != journal_path(None, "evaluate", {**PROTOCOL, "seeds": [9]})


def test_a_resumed_map_runs_only_the_rest(tmp_path: Path) -> None:
    path = tmp_path / "j.jsonl"
    full = run_journaled(_square, range(6), 6)
    j = Journal(path, "square", PROTOCOL)
    j.start(resume=False)
    for k in (0, 1, 4):
        j.append({"key": k, "result": _square(k)})
    j.close()
    calls = []

    def counted(x: int) -> dict:
        calls.append(x)
        return _square(x)

    resumed = run_journaled(counted, range(6), 6, Journal(path, "square", PROTOCOL), resume=True)
    assert resumed == full and calls == [2, 3, 5]


def test_a_run_that_fails_before_anything_finished_leaves_no_journal(tmp_path: Path) -> None:
    """An error before the first result (an unreachable cluster, say) leaves nothing to resume,
    so the same command can run again; one after it keeps what finished."""

    def failing_jobs(after: int):
        yield from range(after)
        raise InvalidArgumentError("cannot reach the cluster")

    path = tmp_path / "j.jsonl"
    with pytest.raises(InvalidArgumentError):
        run_journaled(_square, failing_jobs(0), 3, Journal(path, "square", PROTOCOL))
    assert not path.exists()
    with pytest.raises(InvalidArgumentError):
        run_journaled(_square, failing_jobs(2), 3, Journal(path, "square", PROTOCOL))
    assert path.exists()


def test_an_interrupt_inside_a_journaled_map_names_the_resume(tmp_path: Path) -> None:
    def stop(x: int) -> dict:
        if x == 2:
            raise KeyboardInterrupt
        return _square(x)

    path = tmp_path / "j.jsonl"
    with pytest.raises(Interrupted, match=r"2 of 5 finished .* resume with: .*--resume"):
        run_journaled(stop, range(5), 5, Journal(path, "square", PROTOCOL))
    assert len(path.read_text().splitlines()) == 3  # the header and two units


def test_a_unit_kept_as_an_interruption_runs_again_on_resume(tmp_path: Path) -> None:
    """Runs before an interruption passed the episode's error handling kept it as a failed
    episode; a resume plays it again instead of keeping it."""
    path = tmp_path / "j.jsonl"
    j = Journal(path, "square", PROTOCOL)
    j.start(resume=False)
    j.append({"key": 0, "result": _square(0)})
    stopped = {"failure_reason": "error", "notes": ["Interrupted: SIGTERM"], "success": False}
    j.append({"key": 1, "result": stopped})
    j.close()
    calls = []

    def counted(x: int) -> dict:
        calls.append(x)
        return _square(x)

    out = run_journaled(counted, range(3), 3, Journal(path, "square", PROTOCOL), resume=True)
    assert out == [_square(0), _square(1), _square(2)] and calls == [1, 2]
    assert interrupted(stopped) and not interrupted({**stopped, "notes": ["Interrupted: nah"]})


def test_a_report_that_holds_a_stopped_episode_is_refused_with_the_redo(tmp_path, capsys) -> None:
    from sim import compare
    from sim.evaluation import Protocol, make_report

    golden = json.loads((REPO / "tests" / "golden" / "reports" / "oracle.json").read_text())
    episodes = [e | {"wall_ms": 1.0, "timings_ms": {}} for e in golden["episodes"]]
    objects = tuple(dict.fromkeys(e["object"] for e in episodes))
    protocol = Protocol(
        objects, len(episodes) // len(objects), golden["seed_start"], golden["tier"]
    )
    report = make_report(episodes, protocol, "oracle")
    good = tmp_path / "good.json"
    good.write_text(json.dumps(report))
    report["episodes"][0].update(
        success=False, failure_reason="error", notes=["Interrupted: SIGTERM"]
    )
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(report))
    with pytest.raises(InvalidArgumentError, match="stopped by an interruption") as exc:
        read_report(bad)
    redo = str(exc.value).split("redo the run: ")[1]
    assert redo.startswith("python -m sim.evaluate --estimator oracle --objects ")
    assert redo.endswith(f"--json {bad}")
    assert compare.main([str(good), str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "redo the run: python -m sim.evaluate" in err
