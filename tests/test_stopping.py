"""Stopping is never an outcome: Ctrl-C or SIGTERM on a real `sim.evaluate` stops it in one line
that says how to resume; SIGTERM at random points of a run (one local worker, two, Ray)
and of a leaderboard, an export and the gate stops it with the command that resumes it, the
journal never holds a stopped episode, and the resumed run ends with what an unstopped one
gives, to the bit but for wall-clock times; a local worker killed under a run stops it the same
way."""

from __future__ import annotations

import functools
import json
import os
import random
import re
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from posegrasp.core.contract import Estimate
from posegrasp.core.journal import (
    INTERRUPTED_EXIT,
    Interrupted,
    Journal,
    interrupted,
    run_journaled,
)

REPO = Path(__file__).resolve().parent.parent
#: What differs between two runs of one protocol, stopped or not: wall-clock times, the worker
#: count, the Ray node, the command line the board was made by.
VARYING = {
    "wall_s",
    "wall_ms",
    "timings_ms",
    "workers",
    "node",
    "episode_wall_ms_median",
    "planning_ms_median",
    "time_ms_median",
    "time_ms_p90",
    "command",
}


def _strip(x):
    """`x` without the `VARYING` keys, at every depth."""
    if isinstance(x, dict):
        return {k: _strip(v) for k, v in x.items() if k not in VARYING}
    if isinstance(x, list):
        return [_strip(v) for v in x]
    return x


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _env() -> dict[str, str]:
    return {**os.environ, "MUJOCO_GL": "egl", "PYOPENGL_PLATFORM": "egl"}


def _units(journals: list[Path]) -> list[dict]:
    """Every finished unit the journals hold (a line cut short left out)."""
    out = []
    for path in journals:
        for line in path.read_text().splitlines()[1:] if path.is_file() else []:
            try:
                out.append(json.loads(line)["result"])
            except (ValueError, KeyError):
                pass
    return out


def stop_and_resume(
    cmd: list[str],
    journals: Callable[[], list[Path]],
    rng: random.Random,
    stops: int = 2,
    first_within: float = 1.0,
) -> list[str]:
    """Run `cmd` and SIGTERM it `stops` times: the first time at a random moment within
    `first_within` seconds of the first unit kept (so that the signal lands mid-run), later at
    random moments after the start; after each stop, run the command its last line prints, as
    printed, until it finishes.

    Returns:
        The stop lines, one per stop that landed (a run may finish before its stop).
    """
    current, lines = list(cmd), []
    for k in range(stops + 1):
        proc = subprocess.Popen(
            current,
            env=_env(),
            cwd=REPO,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            preexec_fn=_default_sigint,
        )
        if k < stops:
            deadline = time.monotonic() + 300
            if k == 0:  # under way: a unit kept
                while proc.poll() is None and not _units(journals()):
                    assert time.monotonic() < deadline, "no unit was kept"
                    time.sleep(0.05)
                delay = rng.uniform(0.0, first_within)
            else:
                delay = rng.uniform(0.5, 8.0)
            try:
                proc.wait(timeout=delay)
            except subprocess.TimeoutExpired:
                proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=600)
        assert "Traceback" not in err, err
        assert not any(interrupted(u) for u in _units(journals())), "a stopped unit was kept"
        if proc.returncode == 0:
            return lines
        if proc.returncode == -signal.SIGTERM:
            # Before the command listened (its imports: nothing done, the same command again),
            # or after its work, as Python exits.
            if out.strip().splitlines()[-1:] and out.strip().splitlines()[-1].startswith("wrote "):
                return lines
            continue
        assert proc.returncode == INTERRUPTED_EXIT, err
        last = err.strip().splitlines()[-1]
        lines.append(last)
        match = re.search(r"(?:resume|run again) with: (python .*)$", last)
        assert match, last
        current = [sys.executable, *shlex.split(match.group(1))[1:]]
    raise AssertionError(f"still stopped after {stops} resumes: {lines}")


def _evaluate_cmd(out: Path, *extra: str) -> list[str]:
    return [
        sys.executable,
        "-m",
        "sim.evaluate",
        "--estimator",
        "noisy-oracle",
        "--tier",
        "isolated",
        "--objects",
        "phone,car",
        "--episodes",
        "10",
        "--json",
        str(out),
        *extra,
    ]


@pytest.fixture(scope="module")
def unstopped(tmp_path_factory) -> dict:
    out = tmp_path_factory.mktemp("whole") / "whole.json"
    subprocess.run(_evaluate_cmd(out), env=_env(), cwd=REPO, check=True, capture_output=True)
    return json.loads(out.read_text())


@pytest.mark.slow
@pytest.mark.parametrize(
    "workers, backend", [(1, "local"), (2, "local"), (2, "ray")], ids=["one", "pool", "ray"]
)
def test_sigterm_at_random_points_resumes_to_the_unstopped_report(
    tmp_path, unstopped, workers, backend
) -> None:
    out = tmp_path / "cut.json"
    journal = tmp_path / "cut.journal.jsonl"
    cmd = _evaluate_cmd(out, "--workers", str(workers), "--backend", backend)
    lines = stop_and_resume(cmd, lambda: [journal], random.Random(workers * 7 + len(backend)))
    # The first stop lands mid-run and says what it kept; a later one may land where no unit is
    # under way (a resumed run reading its journal, the report being written) and says so, with
    # the same command to go on.
    assert lines and "resume with:" in lines[0], lines
    assert all(re.search(r"(?:resume|run again) with: python .* --resume$", ln) for ln in lines)
    assert out.is_file() and not journal.exists()
    assert _strip(json.loads(out.read_text())) == _strip(unstopped)


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_an_interrupted_evaluation_resumes_to_the_uninterrupted_report(tmp_path, sig) -> None:
    env = {**_env(), "POSEGRASP_DATA": str(tmp_path)}
    whole = tmp_path / "whole.json"
    subprocess.run(_evaluate_cmd(whole), env=env, cwd=REPO, check=True, capture_output=True)
    out = tmp_path / "cut.json"
    journal = tmp_path / "cut.journal.jsonl"
    proc = subprocess.Popen(
        _evaluate_cmd(out, "--workers", "2"),
        env=env,
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        # A shell without job control starts background jobs with SIGINT ignored, and Python
        # then leaves it ignored: give the run the default disposition a terminal gives it.
        preexec_fn=_default_sigint,
    )
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None:
        if journal.is_file() and len(journal.read_text().splitlines()) >= 3:  # 2 episodes kept
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before it could be interrupted"
    sent = time.monotonic()
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert time.monotonic() - sent < 15, "the run took too long to stop"
    assert proc.returncode == INTERRUPTED_EXIT
    lines = [ln for ln in err.replace("\r", "\n").splitlines() if ln and "episodes" not in ln[:9]]
    assert len(lines) == 1 and "resume with:" in lines[0] and "--resume" in lines[0], err
    assert "Traceback" not in err and not out.exists()
    kept = len(journal.read_text().splitlines()) - 1
    assert 2 <= kept < 20
    # Starting anew over the unfinished run is refused; --resume finishes it.
    again = subprocess.run(_evaluate_cmd(out), env=env, cwd=REPO, capture_output=True, text=True)
    assert again.returncode == 2 and "--resume" in again.stderr
    subprocess.run(
        _evaluate_cmd(out, "--resume"), env=env, cwd=REPO, check=True, capture_output=True
    )
    assert not journal.exists()
    assert _strip(json.loads(out.read_text())) == _strip(json.loads(whole.read_text()))


def _board_cmd(out: Path) -> list[str]:
    return [
        sys.executable,
        "-m",
        "sim.leaderboard",
        "--estimators",
        "oracle,noisy-oracle",
        "--tiers",
        "isolated",
        "--sensors",
        "ideal",
        "--objects",
        "phone,car",
        # 24 episodes: with 12, the board was done about 2 s after its first episode was kept,
        # too soon for a stop drawn within 1 s of it to land while it still ran.
        "--episodes",
        "6",
        "--workers",
        "1",
        "--out",
        str(out),
    ]


@pytest.mark.slow
def test_a_stopped_leaderboard_resumes_by_its_printed_line_to_the_unstopped_board(
    tmp_path,
) -> None:
    """The board's resume line is run as printed (the board has no --resume: its own command
    resumes it) and the board it ends with is the unstopped one's."""
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    subprocess.run(_board_cmd(whole), env=_env(), cwd=REPO, check=True, capture_output=True)
    lines = stop_and_resume(
        _board_cmd(cut), lambda: sorted((cut / "cells").glob("*.journal.jsonl")), random.Random(3)
    )
    assert lines and all("--resume" not in ln and "resume with:" in ln for ln in lines), lines
    assert _strip(json.loads((cut / "leaderboard.json").read_text())) == _strip(
        json.loads((whole / "leaderboard.json").read_text())
    )
    for report in sorted((whole / "cells").glob("*.json")):
        if not report.name.endswith(".settings.json"):
            theirs = json.loads((cut / "cells" / report.name).read_text())
            assert _strip(theirs) == _strip(json.loads(report.read_text()))


@pytest.mark.slow
def test_a_stopped_export_resumes_to_the_same_bytes(tmp_path) -> None:
    def export(out: Path) -> list[str]:
        return [
            sys.executable,
            "-m",
            "sim.export_bop",
            "--tier",
            "isolated",
            "--objects",
            "phone,car",
            "--episodes",
            "3",
            "--out",
            str(out),
        ]

    whole, cut = tmp_path / "whole", tmp_path / "cut"
    subprocess.run(export(whole), env=_env(), cwd=REPO, check=True, capture_output=True)
    lines = stop_and_resume(
        export(cut), lambda: [cut / ".export.journal.jsonl"], random.Random(5), 1, 0.3
    )
    assert lines
    files = sorted(p.relative_to(whole) for p in whole.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(cut) for p in cut.rglob("*") if p.is_file())
    for f in files:
        assert (whole / f).read_bytes() == (cut / f).read_bytes(), f


# --- the gate, and a worker killed under a run, in this process -----------------------------


class _StoppingOracle:
    """The true pose; sends this process SIGTERM while estimating its `stop_at`-th episode."""

    name = "stopping-oracle"
    stop_at: int | None = None
    calls = 0

    def estimate_from_truth(self, obs, T_C_O_true, neighbours) -> Estimate:
        type(self).calls += 1
        if type(self).calls == self.stop_at:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1.0)  # the handler raises here, mid-episode
        return Estimate(np.array(T_C_O_true, dtype=float), tuple(neighbours))


def stopping_oracle() -> _StoppingOracle:
    return _StoppingOracle()


@pytest.mark.slow
def test_a_stopped_gate_resumes_to_the_unstopped_baseline(tmp_path, monkeypatch, capsys) -> None:
    from sim import gate

    monkeypatch.setattr(gate, "GATE_EPISODES", 1)
    monkeypatch.setenv("POSEGRASP_DATA", str(tmp_path / "data"))
    spec = f"{__name__}:stopping_oracle"
    argv = ["--write", "--estimator", spec, "--workers", "1"]
    whole, cut = tmp_path / "whole.json", tmp_path / "cut.json"
    assert gate.main([*argv, "--baseline", str(whole)]) == 0
    _StoppingOracle.calls, _StoppingOracle.stop_at = 0, 4
    capsys.readouterr()
    assert gate.main([*argv, "--baseline", str(cut)]) == INTERRUPTED_EXIT
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert "3 of 6 finished" in line and line.endswith("--resume"), line
    assert not cut.exists()
    _StoppingOracle.stop_at = None
    assert gate.main([*argv, "--baseline", str(cut), "--resume"]) == 0
    assert json.loads(cut.read_text()) == json.loads(whole.read_text())
    assert not list((tmp_path / "data" / "runs").glob("gate-*.jsonl"))


def _square(x: int) -> dict:
    return {"x": x, "y": x * x}


def _die_at(marker: str, x: int) -> dict:
    """Kill this worker process (SIGKILL) at job 3, the first time."""
    if x == 3 and not os.path.exists(marker):
        Path(marker).touch()
        os.kill(os.getpid(), signal.SIGKILL)
    time.sleep(0.05)
    return _square(x)


@pytest.mark.slow
def test_a_local_worker_killed_under_a_run_stops_it_and_it_resumes(tmp_path) -> None:
    """The pool does not wait forever for the dead worker's job, nor record it: the run stops
    with the line that resumes it, and the resumed run is whole."""
    path = tmp_path / "j.jsonl"
    fn = functools.partial(_die_at, str(tmp_path / "killed"))
    protocol = {"jobs": 12}
    with pytest.raises(
        Interrupted, match=r"a worker process was killed by SIG[A-Z]+.* resume with: .*--resume"
    ) as exc:
        run_journaled(fn, range(12), 12, Journal(path, "square", protocol), workers=2)
    assert exc.value.done < 12 and all(u["x"] != 3 for u in _units([path]))
    out = run_journaled(fn, range(12), 12, Journal(path, "square", protocol), True, workers=2)
    assert out == [_square(x) for x in range(12)]


RAY_START_STOP = """
import os, signal, sys, threading, time
from posegrasp.core.backends import run_map
from posegrasp.core.journal import Interrupted, interruptible
import ray

threading.Timer(1.0, lambda: os.kill(os.getpid(), signal.SIGTERM)).start()  # while Ray starts
try:
    with interruptible():
        list(run_map(time.sleep, [0.2] * 4, backend="ray", workers=2))
except Interrupted as exc:
    print("stopped:", exc, "; Ray left running:", ray.is_initialized())
    sys.exit(130)
"""


@pytest.mark.slow
def test_a_sigterm_while_ray_starts_stops_the_run_as_any_other() -> None:
    """Ray's start-up takes SIGTERM over (it exits at once, and a Ray stopped half-started can
    abort the process): the signal waits until Ray has started, then stops the run through the
    run's own handler, with Ray shut down."""
    run = subprocess.run(
        [sys.executable, "-c", RAY_START_STOP],
        env=_env(),
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 130, run.stdout + run.stderr
    assert "stopped: SIGTERM ; Ray left running: False" in run.stdout
    assert "SIGTERM received" not in run.stderr
