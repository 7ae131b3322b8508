"""Fuzzing every command line and the env with generated input (hypothesis).

A CLI given any argument list exits 0 or 2, never with a traceback, and on a refusal prints one
`error:` line and writes nothing. The work each command would start is replaced by a stub, so
the fuzzing covers parsing and validation only and stays fast; `-m slow` runs more examples.
The env given any reset options and action either works, fails the grasp with a documented
reason or raises a PosegraspError, and a valid reset always works afterwards.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import os
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from grasping.planner import PlanningError
from posegrasp.core.errors import PosegraspError
from posegrasp.core.failures import FAILURE_REASONS
from sim.env import MAX_NEIGHBOURS, GraspEvalEnv, pose_action

#: Values that sit on or past the edge of every option's range.
VALUES = [
    "-1",
    "0",
    "1",
    "2",
    "3",
    "64",
    "65",
    "100",
    "4294967295",
    "4294967296",
    "99999999999",
    "1.5",
    "nan",
    "inf",
    "-inf",
    "",
    " ",
    "abc",
    "all",
    "phone",
    "phone,phone",
    "car,teapot",
    ",",
    "x/",
    "out/",
    "p.xyz",
    "p.png",
    "r.json",
    "1e30,1,1,1",
    "500,500,31,23",
    "paper",
    "headcam",
    "gt",
    "detector",
    "clutter",
    "far",
    "oracle",
    "hybrid",
    "--help-me",
    "-",
]


class _WorkStarted(Exception):
    """Raised by the stubs: the command line passed validation and the work would start."""


def _stub(*args, **kwargs):
    raise _WorkStarted


#: Each CLI, its options, and the functions that would start real work.
CLIS: dict[str, tuple[list[str], list[str]]] = {
    "sim.run_episode": (
        ["--object", "--seed", "--estimator", "--tier", "--noise", "--json", "--out", "--save"],
        ["_run", "make_estimator"],
    ),
    "sim.evaluate": (
        [
            "--objects",
            "--episodes",
            "--estimator",
            "--seed-start",
            "--workers",
            "--tier",
            "--noise",
            "--margin",
            "--json",
            "--plot",
            "--tolerance",
            "--backend",
        ],
        ["evaluate_protocol", "cached_estimator", "make_estimator"],
    ),
    "sim.tolerance": (
        [
            "--object",
            "--objects",
            "--episodes",
            "--seed-start",
            "--workers",
            "--tier",
            "--json",
            "--plot",
            "--backend",
        ],
        ["study"],
    ),
    "sim.render_scene": (
        [
            "--object",
            "--seed",
            "--png",
            "--sheet",
            "--external",
            "--width",
            "--height",
            "--distractors",
            "--tier",
            "--estimator",
        ],
        ["render", "render_sheet"],
    ),
    "sim.gate": (["--write", "--baseline", "--workers", "--estimator"], ["run_gate"]),
    "sim.compare": (["--json", "--boot", "--curve", "--plot"], []),
    "sim.fit_success": (
        ["--objects", "--episodes", "--tier", "--task", "--workers", "--models"],
        ["sample"],
    ),
    "perception.training.datagen": (
        [
            "--dist",
            "--split",
            "--count",
            "--out",
            "--objects",
            "--width",
            "--height",
            "--preview",
            "--workers",
            "--tier",
            "--views",
        ],
        ["generate"],
    ),
    "perception.training.overlays": (
        ["--dist", "--split", "--images", "--image", "--K", "--out", "--save"],
        ["HybridPoseEstimator", "PoseDataset"],
    ),
    "perception.training.tables": (
        ["--weights", "--dists", "--limit", "--json", "--boxes", "--record"],
        ["load_posenet", "check_full_splits", "record_in_manifest", "evaluate_split"],
    ),
    "perception.training.export": (["--checkpoints", "--plot"], ["export"]),
}


def _argv(options: list[str]) -> st.SearchStrategy[list[str]]:
    token = st.one_of(st.sampled_from(options), st.sampled_from(VALUES), st.text(max_size=6))
    return st.lists(token, max_size=8)


def _files(folder: Path) -> list[tuple[str, int]]:
    return sorted((str(p.relative_to(folder)), p.stat().st_size) for p in folder.rglob("*"))


def _run_cli(main, argv: list[str]) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            status = main(argv)
        except SystemExit as exc:  # argparse's refusal (2) or --help (0)
            status = exc.code
        except _WorkStarted:
            status = 0
    return status, err.getvalue()


def _fuzz_cli(module_name: str, examples: int, monkeypatch) -> None:
    module = importlib.import_module(module_name)
    options, work = CLIS[module_name]
    for name in work:
        monkeypatch.setattr(module, name, _stub)
    home = Path.cwd()

    @settings(
        max_examples=examples, deadline=None, database=None, suppress_health_check=list(HealthCheck)
    )
    @given(argv=_argv(options))
    def check(argv: list[str]) -> None:
        with tempfile.TemporaryDirectory() as d:
            os.chdir(d)
            try:
                status, err = _run_cli(module.main, argv)
                assert status in (0, 2), (argv, status, err)
                assert "Traceback" not in err, (argv, err)
                if status == 2:
                    assert err.count("error:") == 1 and err.endswith("\n"), (argv, err)
                    assert _files(Path(d)) == [], (argv, _files(Path(d)))
            finally:
                os.chdir(home)

    check()


@pytest.mark.parametrize("module_name", sorted(CLIS))
def test_cli_fuzz(module_name: str, monkeypatch) -> None:
    _fuzz_cli(module_name, 25, monkeypatch)


@pytest.mark.slow
@pytest.mark.parametrize("module_name", sorted(CLIS))
def test_cli_fuzz_long(module_name: str, monkeypatch) -> None:
    _fuzz_cli(module_name, 400, monkeypatch)


# --- the env -------------------------------------------------------------------------------------

_numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-(2**40), 2**40),
    st.complex_numbers(max_magnitude=10),
    st.text(max_size=3),
    st.none(),
)
_scalar = st.one_of(st.integers(-3, 3), st.booleans(), _numbers)


def _vectors(n: int) -> st.SearchStrategy:
    return st.one_of(
        st.lists(_numbers, min_size=n, max_size=n),
        st.lists(st.floats(-1, 1), min_size=0, max_size=n + 1),
        st.just([1.0, 0.0, 0.0, 0.0][:n] + [0.0] * max(0, n - 4)),
        _numbers,
    )


_neighbours = st.one_of(
    st.none(),
    st.fixed_dictionaries(
        {
            "count": _scalar,
            "object": st.one_of(
                st.just(np.zeros(MAX_NEIGHBOURS, np.int64)), _vectors(MAX_NEIGHBOURS)
            ),
            "position": st.just(np.zeros((MAX_NEIGHBOURS, 3))),
            "quaternion": st.sampled_from(
                [np.tile([1.0, 0, 0, 0], (MAX_NEIGHBOURS, 1)), np.zeros((MAX_NEIGHBOURS, 4))]
            ),
        }
    ),
)
_actions = st.one_of(
    st.fixed_dictionaries(
        {"has_estimate": _scalar, "position": _vectors(3), "quaternion": _vectors(4)},
        optional={"neighbours": _neighbours, "extra": _scalar},
    ),
    _numbers,
)
_options = st.one_of(
    st.none(),
    st.dictionaries(
        st.sampled_from(["object", "episode_seed", "colour"]),
        st.one_of(st.sampled_from(["phone", "teapot", None]), st.integers(-5, 2**33), _numbers),
        max_size=2,
    ),
    _numbers,
)
_seeds = st.one_of(st.none(), st.integers(-5, 2**33), _numbers)
#: What a step may report instead of success.
REASONS = set(FAILURE_REASONS)


def _fuzz_env(examples: int, monkeypatch) -> None:
    def unreachable(self, *args, **kwargs):
        raise PlanningError("unreachable", "stubbed planner: no grasp is executed here")

    monkeypatch.setattr("sim.episodes.episode.GraspPlanner.plan", unreachable)
    env = GraspEvalEnv(object="phone", width=64, height=48)

    @settings(
        max_examples=examples, deadline=None, database=None, suppress_health_check=list(HealthCheck)
    )
    @given(seed=_seeds, options=_options, action=_actions)
    def check(seed, options, action) -> None:
        try:
            env.reset(seed=seed, options=options)
        except PosegraspError:
            pass
        try:
            _, reward, terminated, _, info = env.step(action)
            assert terminated and reward in (0.0, 1.0)
            assert info["success"] or info["failure_reason"] in REASONS
        except PosegraspError as exc:
            assert str(exc) and "\n" not in str(exc)
        env.reset(seed=0)  # never wedged
        _, _, terminated, _, info = env.step(pose_action(None))
        assert terminated and info["failure_reason"] == "no_estimate"

    try:
        check()
    finally:
        env.close()


def test_env_fuzz(monkeypatch) -> None:
    _fuzz_env(20, monkeypatch)


@pytest.mark.slow
def test_env_fuzz_long(monkeypatch) -> None:
    _fuzz_env(300, monkeypatch)
