"""The runnable examples in examples/ run as scripts and print what they promise."""

from __future__ import annotations

import re
import runpy
import sys
from pathlib import Path

import numpy as np
import pytest

from posegrasp.core.failures import FAILURE_REASONS
from sim.episodes.episode import Episode

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
SEED = 1_000_000_000


def _run(name: str, capsys: pytest.CaptureFixture[str]) -> str:
    """What running examples/<name> as a script, with no arguments, prints."""
    capsys.readouterr()
    argv, sys.argv = sys.argv, [str(EXAMPLES / name)]
    try:
        runpy.run_path(str(EXAMPLES / name), run_name="__main__")
    finally:
        sys.argv = argv
    return capsys.readouterr().out


def test_the_env_route_example_grasps_the_phone_on_the_default_estimate(
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = _run("env_route.py", capsys)
    first = r"reward 1\.0, failure reason None, correct True\n"
    m = re.fullmatch(first + r"position error (\S+) mm\n", out)
    assert m is not None, out
    assert 0.0 <= float(m[1]) < 10.0


def test_the_plugin_example_is_scored_by_evaluate(capsys: pytest.CaptureFixture[str]) -> None:
    out = _run("plugin.py", capsys)
    m = re.fullmatch(r"mine: success (True|False), (\w+)\nposition error (\S+) mm\n", out)
    assert m is not None, out
    assert m[2] in FAILURE_REASONS
    episode = Episode("phone", SEED)  # the plug-in's guess: 0.8 m straight ahead
    t_true = episode.T_C_O_true[:3, 3]
    episode.close()
    assert m[3] == f"{np.linalg.norm(t_true - [0.0, 0.0, 0.8]) * 1000:.1f}"
