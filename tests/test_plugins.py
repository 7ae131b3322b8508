"""Plug-in estimators (`sim.episodes.registry`): ``package.module:factory`` and the entry-point
group on every command that takes ``--estimator``, the Python `evaluate` taking an estimator
object, and the example package in examples/ installed and scored as a user would."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from posegrasp.core.contract import Estimate
from posegrasp.core.errors import InvalidArgumentError, UnknownNameError
from sim.episodes import registry as E
from sim.evaluation import Protocol, evaluate_protocol
from sim.evaluation.report_schema import validate_report

REPO = Path(__file__).resolve().parent.parent
EXAMPLE = REPO / "examples" / "crude-estimator"
SPEC = "posegrasp_crude:CrudeTableEstimator"
SEED = 1_000_000_000


class NoEstimate:
    name = "nothing"

    def estimate(self, obs) -> Estimate:
        return Estimate(None, info={"note": "never sees anything"})


def no_estimate() -> NoEstimate:
    return NoEstimate()


def wrong_kind() -> object:
    return object()


def failing() -> NoEstimate:
    raise RuntimeError("GPU not found")


@pytest.fixture
def example_on_path(monkeypatch):
    monkeypatch.syspath_prepend(str(EXAMPLE))


def test_a_factory_spec_makes_the_estimator(example_on_path) -> None:
    est = E.make_estimator(SPEC)
    assert est.name == "crude" and callable(est.estimate)
    assert E.check_estimator_spec(SPEC) == SPEC
    assert E.make_estimator("tests.test_plugins:no_estimate").name == "nothing"


@pytest.mark.parametrize(
    "spec, needle",
    [
        ("nope_pkg:Factory", "cannot import 'nope_pkg'"),
        ("tests.test_plugins:missing", "has no 'missing'"),
        ("tests.test_plugins:SEED", "is not callable"),
        ("tests.test_plugins:", "package.module:factory"),
        ("tests.test_plugins:wrong_kind", "without a callable estimate(obs) and a str name"),
        ("tests.test_plugins:failing", "its factory failed (RuntimeError: GPU not found)"),
    ],
)
def test_a_bad_plugin_is_one_line(spec: str, needle: str) -> None:
    with pytest.raises(InvalidArgumentError) as err:
        E.make_estimator(spec)
    assert needle in str(err.value) and "\n" not in str(err.value)


def test_an_unknown_name_lists_the_choices() -> None:
    with pytest.raises(UnknownNameError, match=r"package\.module:factory") as err:
        E.check_estimator_spec("myest")
    assert "hybrid-global" in str(err.value)


@pytest.mark.parametrize("module", ["sim.evaluate", "sim.run_episode", "sim.gate"])
def test_every_command_refuses_a_bad_plugin_in_one_line(module: str) -> None:
    run = subprocess.run(
        [sys.executable, "-m", module, "--estimator", "nope_pkg:Factory"],
        cwd=REPO,
        capture_output=True,
        text=True,
        env={**os.environ, "MUJOCO_GL": "egl"},
    )
    assert run.returncode == 2
    assert run.stderr.count("\n") == 1 and "cannot import 'nope_pkg'" in run.stderr


def test_evaluate_takes_an_estimator_object_and_a_spec_alike(example_on_path) -> None:
    from posegrasp_crude import CrudeTableEstimator

    two = Protocol(["phone"], 2, SEED, "isolated")
    by_object = evaluate_protocol(two, CrudeTableEstimator())
    by_spec = evaluate_protocol(two, SPEC)
    validate_report(by_object)
    assert by_object["estimator"] == "crude" and by_spec["estimator"] == SPEC

    def outcome(r: dict) -> list[dict]:
        return [{k: v for k, v in e.items() if k not in ("wall_ms", "timings_ms")} for e in r]

    assert outcome(by_object["episodes"]) == outcome(by_spec["episodes"])
    none = evaluate_protocol(Protocol(["car"], 1, SEED, "isolated"), NoEstimate())
    assert none["overall"]["failure_reasons"] == {"no_estimate": 1}


#: Runs ``python -m <args>`` and returns the finished process (`_module_runner`).
_Run = Callable[..., subprocess.CompletedProcess]


def _install_example(site: Path) -> None:
    """pip installs examples/crude-estimator into the folder `site`, as into any environment
    (no dependencies, no build isolation)."""
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--quiet",
            "--no-deps",
            "--no-build-isolation",
            "--target",
            str(site),
            str(EXAMPLE),
        ],
        check=True,
        capture_output=True,
    )


def _module_runner(site: Path, data: Path) -> _Run:
    """A runner of ``python -m <args>`` in the repository, with `site` on PYTHONPATH and
    `data` as the data folder; it returns the finished process, its output as text."""
    env = {
        **os.environ,
        "PYTHONPATH": str(site),
        "MUJOCO_GL": "egl",
        "POSEGRASP_DATA": str(data),
    }

    def run(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, "-m", *args], cwd=REPO, env=env, capture_output=True, text=True
        )

    return run


def _evaluate(run: _Run, estimator: str, out: Path, *extra: str) -> dict:
    """The report of ``sim.evaluate`` of `estimator` on 3 episodes each of the phone and the
    car, written to `out`; the command must succeed."""
    done = run(
        "sim.evaluate",
        "--estimator",
        estimator,
        "--objects",
        "phone,car",
        "--episodes",
        "3",
        "--json",
        str(out),
        *extra,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(out.read_text())


@pytest.mark.slow
def test_the_example_package_installs_and_is_scored_by_name(tmp_path: Path) -> None:
    """pip installs examples/crude-estimator (to a folder on PYTHONPATH, as into any
    environment); its entry point then names it on the command line, and evaluate and the gate
    score it with the episodes the factory spec gives."""
    site = tmp_path / "site"
    _install_example(site)
    run = _module_runner(site, tmp_path)
    a = _evaluate(run, "crude", tmp_path / "a.json")
    b = _evaluate(run, SPEC, tmp_path / "b.json", "--workers", "2")
    keep = ("object", "seed", "success", "failure_reason", "T_C_O_est", "pose_error")
    assert [{k: e[k] for k in keep} for e in a["episodes"]] == [
        {k: e[k] for k in keep} for e in b["episodes"]
    ]
    assert run("sim.compare", str(tmp_path / "a.json"), str(tmp_path / "b.json")).returncode == 0
    baseline = tmp_path / "gate.json"
    wrote = run(
        "sim.gate", "--write", "--estimator", "crude", "--baseline", str(baseline), "--workers", "2"
    )
    assert wrote.returncode == 0, wrote.stderr
    gated = run("sim.gate", "--estimator", "crude", "--baseline", str(baseline), "--workers", "2")
    assert gated.returncode == 0 and "crude: PASS" in gated.stdout, gated.stdout + gated.stderr


class SeesDepth:
    """Records whether the observation held a depth image of the image's size."""

    name = "sees-depth"

    def estimate(self, obs) -> Estimate:
        d = obs.depth
        ok = d is not None and d.shape == obs.rgb.shape[:2] and d.dtype.name == "float32"
        return Estimate(None, info={"depth": bool(ok)})


def test_rgbd_runs_hand_the_estimator_depth() -> None:
    from sim.episodes import episode

    assert E.OBS_MODES == episode.OBS_MODES
    rgb = evaluate_protocol(Protocol(["phone"], 1, SEED, "isolated"), SeesDepth())
    rgbd = evaluate_protocol(Protocol(["phone"], 1, SEED, "isolated", obs_mode="rgbd"), SeesDepth())
    assert rgb["episodes"][0]["estimate_info"] == {"depth": False}
    assert rgbd["episodes"][0]["estimate_info"] == {"depth": True}
    assert rgbd["obs_mode"] == "rgbd" and validate_report(rgbd)
