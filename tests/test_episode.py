"""Episodes with the oracle and the noisy oracle, determinism, the CLIs and the statistics."""

from __future__ import annotations

import json

import numpy as np
import pytest

from posegrasp.core.errors import InvalidArgumentError
from posegrasp.world import constants as C
from posegrasp.world.objects import OBJECT_NAMES
from sim import evaluate, run_episode
from sim.episode import Episode
from sim.episode import play_episode as run
from sim.estimators import NoisyOracleEstimator, OracleEstimator, make_estimator
from sim.pose_noise import PoseNoise, perturb_pose


@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_oracle_episode_succeeds(name: str) -> None:
    r = run(name, 1, OracleEstimator())
    assert r.success, (r.failure_reason, r.notes)
    assert r.failure_reason is None
    assert r.pose_error["translation_m"] == pytest.approx(0.0, abs=1e-12)
    assert r.lift_height >= 0.10


def test_same_seed_same_outcome() -> None:
    a = run("pistol", 4, NoisyOracleEstimator())
    b = run("pistol", 4, NoisyOracleEstimator())
    assert a.success == b.success
    np.testing.assert_array_equal(a.T_C_O_est, b.T_C_O_est)
    assert a.lift_height == b.lift_height
    c = run("pistol", 5, NoisyOracleEstimator())
    assert not np.array_equal(a.T_C_O_est, c.T_C_O_est)


def test_no_estimate_is_a_reported_failure() -> None:
    ep = Episode("phone", 2)
    try:
        ep.observe()
        r = ep.act(None, "none")
    finally:
        ep.close()
    assert not r.success and r.failure_reason == "no_estimate"


def test_invalid_estimate_is_rejected() -> None:
    ep = Episode("phone", 2)
    try:
        T = np.eye(4)
        T[1, 1] = np.nan
        with pytest.raises(InvalidArgumentError):
            ep.act(T)
    finally:
        ep.close()


def test_fixed_noise_has_exact_magnitudes() -> None:
    rng = np.random.default_rng(0)
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.05, 0.8]
    ray = perturb_pose(T, PoseNoise(ray=0.02, mode="fixed"), rng)
    d = ray[:3, 3] - T[:3, 3]
    assert np.linalg.norm(d) == pytest.approx(0.02)
    assert abs(d @ T[:3, 3]) / np.linalg.norm(T[:3, 3]) == pytest.approx(0.02)
    lat = perturb_pose(T, PoseNoise(lateral=0.01, mode="fixed"), rng)
    d = lat[:3, 3] - T[:3, 3]
    assert np.linalg.norm(d) == pytest.approx(0.01)
    assert d @ T[:3, 3] == pytest.approx(0.0, abs=1e-12)
    for kind in ("inplane", "outplane"):
        rot = perturb_pose(T, PoseNoise(**{kind: np.deg2rad(7)}, mode="fixed"), rng)
        angle = np.arccos((np.trace(rot[:3, :3]) - 1) / 2)
        assert np.rad2deg(angle) == pytest.approx(7.0)
        np.testing.assert_allclose(rot[:3, 3], T[:3, 3])


def test_wilson_interval_matches_hand_values() -> None:
    lo, hi = evaluate.wilson_interval(8, 10)
    assert lo == pytest.approx(0.4902, abs=1e-4)
    assert hi == pytest.approx(0.9433, abs=1e-4)
    assert evaluate.wilson_interval(0, 0) == (0.0, 1.0)
    lo, hi = evaluate.wilson_interval(50, 50)
    assert hi == pytest.approx(1.0) and lo == pytest.approx(0.9287, abs=1e-4)


def test_unknown_estimator() -> None:
    with pytest.raises(ValueError, match="valid estimators: oracle, noisy-oracle"):
        make_estimator("magic")


def test_run_episode_cli_json_to_stdout(capsys) -> None:
    argv = ["--object", "faucet", "--seed", "2", "--json", "-", "--estimator", "oracle"]
    assert run_episode.main(argv) == 0
    captured = capsys.readouterr()
    d = json.loads(captured.out)  # standard output holds the JSON and nothing else
    assert "episode  object=faucet" in captured.err  # the summary went to standard error
    for key in (
        "object",
        "seed",
        "estimator",
        "success",
        "failure_reason",
        "pose_error",
        "timings_ms",
    ):
        assert key in d
    assert set(d["pose_error"]) >= {
        "translation_m",
        "translation_pct",
        "rotation_deg",
        "ray_m",
        "lateral_m",
        "inplane_deg",
        "outplane_deg",
    }


def test_run_episode_cli_json_to_a_file(tmp_path, capsys) -> None:
    out = tmp_path / "sub" / "episode.json"
    argv = ["--object", "faucet", "--seed", "2", "--json", str(out), "--estimator", "oracle"]
    assert run_episode.main(argv) == 0
    printed = capsys.readouterr().out
    assert "episode  object=faucet" in printed and f"wrote {out}" in printed
    d = json.loads(out.read_text())
    assert d["object"] == "faucet" and d["seed"] == 2 and d["estimator"] == "oracle"
    assert d["success"] is True and d["pose_error"]["translation_m"] == pytest.approx(0.0)


class _Started(Exception):
    """Raised by a stub in place of the episode: the arguments it was given."""


@pytest.mark.parametrize("option", ["--out", "--save"])
def test_run_episode_out_folder_and_its_former_name(option, tmp_path, monkeypatch) -> None:
    def started(*args):
        raise _Started(args)

    monkeypatch.setattr(run_episode, "_run", started)
    with pytest.raises(_Started) as exc:
        run_episode.main(["--estimator", "oracle", option, str(tmp_path / "o")])
    assert exc.value.args[0][3] == tmp_path / "o"  # the folder the episode saves into
    assert not (tmp_path / "o").exists()  # created only when the episode writes


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--object", "teapot"], "valid objects: car, faucet"),
        (["--estimator", "magic"], "valid estimators: oracle"),
        (["--seed", "x"], "invalid --seed"),
        (["--noise", "1,2"], "--noise must be"),
        (["--tier", "nope"], "valid tiers: isolated"),
        (["--json", "{tmp}"], "it is a folder"),
        (["--out", "{tmp}/file/sub"], "is a file, not a folder"),
    ],
)
def test_run_episode_cli_bad_input(argv, needle, tmp_path, capsys) -> None:
    (tmp_path / "file").write_text("")
    status = run_episode.main([a.replace("{tmp}", str(tmp_path)) for a in argv])
    err = capsys.readouterr().err
    assert status == 2
    assert needle in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_evaluate_cli(tmp_path, capsys) -> None:
    out, png = tmp_path / "r.json", tmp_path / "r.png"
    argv = ["--objects", "chair", "--episodes", "2", "--json", str(out), "--plot", str(png)]
    assert evaluate.main([*argv, "--estimator", "noisy-oracle"]) == 0
    assert png.stat().st_size > 10_000  # a real figure, not an empty file
    d = json.loads(out.read_text())
    assert d["seed_start"] == C.EVAL_SEED_BASE
    g = d["per_object"]["chair"]
    for key in (
        "episodes",
        "successes",
        "success_rate",
        "wilson_low",
        "wilson_high",
        "failure_reasons",
    ):
        assert key in g and key in d["overall"]
    assert g["episodes"] == 2
    capsys.readouterr()
    assert evaluate.main(["--objects", "teapot"]) == 2  # refused while parsing, before any work
    assert "valid objects: car" in capsys.readouterr().err
