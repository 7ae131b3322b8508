"""Episodes with the oracle and the noisy oracle, determinism, the CLIs and the statistics."""

from __future__ import annotations

import dataclasses
import json
import re

import numpy as np
import pytest

from posegrasp.core.contract import Estimate, Observation
from posegrasp.core.errors import UnknownNameError
from posegrasp.core.transforms import axis_angle
from posegrasp.world import constants as C
from posegrasp.world.objects import OBJECT_NAMES, load_object
from sim import evaluate, run_episode
from sim.episodes.episode import (
    POSE_CORRECT_MSSD,
    Episode,
    EpisodeConfig,
    object_symmetries,
    pose_errors,
)
from sim.episodes.episode import play_episode as run
from sim.episodes.pose_noise import PoseNoise, perturb_pose
from sim.episodes.registry import NoisyOracleEstimator, OracleEstimator, make_estimator
from sim.evaluation.stats import wilson_interval


@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_oracle_episode_succeeds(name: str) -> None:
    r = run(name, 1, OracleEstimator())
    assert r.success, (r.failure_reason, r.notes)
    assert r.failure_reason is None
    assert r.pose_error["translation_m"] == pytest.approx(0.0, abs=1e-12)
    assert r.pose_error["mssd_m"] == pytest.approx(0.0, abs=1e-9)
    assert r.pose_error["mspd_px"] == pytest.approx(0.0, abs=1e-6)
    assert r.pose_correct is True and r.to_json()["pose_correct"] is True
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


def test_invalid_estimate_is_a_failed_grasp() -> None:
    ep = Episode("phone", 2)
    try:
        T = np.eye(4)
        T[1, 1] = np.nan
        r = ep.act(T)
    finally:
        ep.close()
    assert not r.success and r.failure_reason == "invalid_action"
    assert "NaN" in r.notes[0] and r.pose_error is None and r.pose_correct is None


def _pose(t=(0.02, -0.01, 0.9)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = axis_angle(np.array([1.0, 0.4, -0.2]), 1.1)
    T[:3, 3] = t
    return T


def test_pose_errors_hold_bop_mssd_and_mspd() -> None:
    obj = load_object("car")
    pts, K = np.asarray(obj.mesh.vertices), np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    T_true = _pose()
    T_est = T_true.copy()
    T_est[:3, 3] += [0.004, 0.0, 0.0]  # 4 mm along the camera's x at 0.9 m: 500 * 4 / z px
    e = pose_errors(T_est, T_true, pts, obj.diameter, K, object_symmetries(obj))
    assert e["mssd_m"] == pytest.approx(0.004)
    assert e["mssd_rel_diameter"] == pytest.approx(0.004 / obj.diameter)
    z = (pts @ T_true[:3, :3].T + T_true[:3, 3])[:, 2]
    assert e["mspd_px"] == pytest.approx(500 * 0.004 / z.min())
    assert "mspd_px" not in pose_errors(T_est, T_true, pts, obj.diameter)  # no K, no MSPD
    behind = T_est.copy()
    behind[2, 3] = -0.9
    assert "mspd_px" not in pose_errors(behind, T_true, pts, obj.diameter, K)  # BOP's inf


def test_mssd_takes_the_symmetries_and_sets_pose_correct() -> None:
    obj = load_object("phone")
    flip = np.eye(4)
    flip[:3, :3] = axis_angle(np.array([0.0, 0.0, 1.0]), np.pi)
    symmetric = dataclasses.replace(obj, symmetries=(flip,))
    syms = object_symmetries(symmetric)
    assert len(syms) == 2 and syms[1]["t"].shape == (3, 1)
    pts, T_true = np.asarray(obj.mesh.vertices), _pose()
    T_est = T_true @ flip  # the same appearance, if the object had that symmetry
    plain = pose_errors(T_est, T_true, pts, obj.diameter, syms=object_symmetries(obj))
    sym = pose_errors(T_est, T_true, pts, obj.diameter, syms=syms)
    assert sym["mssd_m"] == pytest.approx(0.0, abs=1e-9) and plain["mssd_m"] > 0.1
    ep = Episode("phone", 2)
    try:
        near, far = ep.T_C_O_true.copy(), ep.T_C_O_true.copy()
        near[:3, 3] += [0.0, 0.0, 0.9 * POSE_CORRECT_MSSD * ep.scene.target.model.diameter]
        far[:3, 3] += [0.0, 0.0, 1.1 * POSE_CORRECT_MSSD * ep.scene.target.model.diameter]
        assert ep.pose_errors(near)["mssd_rel_diameter"] == pytest.approx(0.09)
        r = ep.act(far, "test")
    finally:
        ep.close()
    assert r.pose_error["mssd_rel_diameter"] == pytest.approx(0.11)
    assert r.pose_correct is False and r.to_json()["pose_correct"] is False


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
    lo, hi = wilson_interval(8, 10)
    assert lo == pytest.approx(0.4902, abs=1e-4)
    assert hi == pytest.approx(0.9433, abs=1e-4)
    assert wilson_interval(0, 0) == (0.0, 1.0)
    lo, hi = wilson_interval(50, 50)
    assert hi == pytest.approx(1.0) and lo == pytest.approx(0.9287, abs=1e-4)


def test_wilson_interval_holds_the_rate_itself() -> None:
    """At 4/4 the upper bound rounds below 1 unless it is held at the rate: an error bar drawn
    from it would then be negative, which matplotlib refuses."""
    for n in range(1, 301):
        for k in range(n + 1):
            lo, hi = wilson_interval(k, n)
            assert 0.0 <= lo <= k / n <= hi <= 1.0, (k, n)


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
        "pose_correct",
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
        (["--sensor", "lidar"], "valid sensors: ideal, kinect-v1, azure-tof"),
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


def test_the_printed_timings_add_up_to_the_printed_total() -> None:
    r = run("phone", 1, OracleEstimator())
    (line,) = [x for x in run_episode.summary(r).splitlines() if x.startswith("  timings")]
    assert "estimate" in line and "(ik " in line  # ik is printed as part of plan
    values = dict(re.findall(r"(\w+) (\d+) ms", re.sub(r"\(ik \d+ ms\)", "", line)))
    total = int(values.pop("total"))
    assert abs(sum(map(int, values.values())) - total) <= len(values)  # each rounded to 1 ms
    assert total == round(r.timings_ms["total"])


def test_the_estimators_stage_times_are_printed_as_parts_of_the_estimate() -> None:
    timings = {"scene": 100.0, "estimate": 2000.0, "plan": 80.0, "ik": 70.0, "total": 2180.0}
    stages = {"detect": 120.0, "nets": 30.0, "total": 150.0, "hypotheses": 1800.0}
    line = run_episode._timing_lines(timings, stages)[1]
    assert "total" not in line  # the nets' subtotal is not a second total
    assert "detect 120.0 ms" in line and "hypotheses 1800.0 ms" in line
    assert line.endswith("(parts of the estimate's 2000 ms)")


def test_building_a_codebook_says_so_once(tmp_path, capsys) -> None:
    from perception.global_pose import CodebookCache

    books = CodebookCache(12, 4, folder=tmp_path)
    books.get("car")
    books.get("car")
    CodebookCache(12, 4, folder=tmp_path).get("car")  # read from the cache
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1
    assert "building the car's silhouette codebook" in err[0] and "cached in" in err[0]


def test_an_object_made_again_from_another_mesh_gets_a_codebook_of_its_own(tmp_path) -> None:
    from perception.global_pose import CodebookCache
    from perception.parts import ConvexParts, Parts

    class Stretched(ConvexParts):
        """The car's pieces, twice as long in x: the same name, another mesh."""

        def parts(self, name: str) -> Parts:
            own = super().parts(name)
            return Parts(name, [p * [2.0, 1.0, 1.0] for p in own.pieces], own.colours)

    first = CodebookCache(12, 4, folder=tmp_path).get("car")
    again = CodebookCache(12, 4, folder=tmp_path, source=Stretched()).get("car")
    assert len(list(tmp_path.glob("car_12x4_*.npz"))) == 2
    assert not np.array_equal(first.side, again.side)
    assert np.array_equal(CodebookCache(12, 4, folder=tmp_path).get("car").bits, first.bits)


def test_an_episode_without_a_grasp_writes_no_film(tmp_path, capsys) -> None:
    argv = ["--object", "phone", "--estimator", "noisy-oracle", "--noise", "1000,1000,0,0"]
    assert run_episode.main([*argv, "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "no grasp was executed (failed: " in out
    assert (tmp_path / "head.png").is_file() and not (tmp_path / "grasp_strip.png").exists()


class _Seeing:
    """An estimator of the contract that keeps every observation it is handed and answers no
    pose."""

    name = "seeing"

    def __init__(self) -> None:
        self.seen: list[Observation] = []

    def estimate(self, obs: Observation) -> Estimate:
        self.seen.append(obs)
        return Estimate(None)


def _seen(sensor: str, obs_mode: str = "rgbd", seed: int = 3):
    """What an estimator is handed in an episode under `sensor`, the episode's result, its true
    pose, and the head camera's rendered (ideal) colour and depth images."""
    ep = Episode(
        "phone", seed, EpisodeConfig(width=320, height=240, obs_mode=obs_mode, sensor=sensor)
    )
    estimator = _Seeing()
    try:
        _, result = ep.run(estimator)
        rgb = ep.renderer.rgb(ep.scene.data, C.HEAD_CAMERA)
        depth = ep.renderer.depth(ep.scene.data, C.HEAD_CAMERA)
        truth = ep.T_C_O_true.copy()
    finally:
        ep.close()
    (obs,) = estimator.seen
    return obs, result, truth, rgb, depth


def test_the_sensor_reaches_the_estimator_through_observe() -> None:
    ideal, r_ideal, truth, rgb, depth = _seen("ideal")
    # The ideal sensor hands over the renders themselves and records nothing of itself.
    assert ideal.rgb.tobytes() == rgb.tobytes() and ideal.depth.tobytes() == depth.tobytes()
    assert "sensor" not in r_ideal.to_json() and "sensor" not in r_ideal.timings_ms
    kinect, r_kinect, truth_k, _, _ = _seen("kinect-v1")
    again = _seen("kinect-v1")[0]
    np.testing.assert_array_equal(truth_k, truth)  # the same scene under every sensor
    d = kinect.depth
    assert d.dtype == np.float32 and d.shape == depth.shape
    assert (d == 0).mean() > 0.001 and not (depth == 0).any()  # holes: exactly 0
    assert not np.array_equal(d, depth)
    seen = d > 0
    assert np.median(np.abs(d[seen] - depth[seen])) < 0.005  # noise on the same surfaces
    assert d.tobytes() == again.depth.tobytes()  # the same noise for the same seed
    assert kinect.rgb.tobytes() == rgb.tobytes()  # kinect-v1's colour model is the ideal one
    assert r_kinect.to_json()["sensor"] == "kinect-v1" and r_kinect.sensor == "kinect-v1"
    assert r_kinect.timings_ms["sensor"] > 0
    # A colour model changes the colour image in either mode, the same bytes in both.
    noisy, result, _, _, _ = _seen("azure-tof+camera", obs_mode="rgb")
    assert noisy.depth is None and noisy.rgb.shape == rgb.shape
    assert np.abs(noisy.rgb.astype(int) - rgb.astype(int)).mean() > 0.5
    assert noisy.rgb.tobytes() == _seen("azure-tof+camera")[0].rgb.tobytes()
    assert result.to_json()["sensor"] == "azure-tof+camera"


@pytest.mark.parametrize("sensor", ["lidar", " kinect-v1", "camera", "kinect-v1+ideal"])
def test_an_unknown_sensor_is_one_line_naming_the_valid_ones(sensor: str) -> None:
    with pytest.raises(UnknownNameError) as info:
        EpisodeConfig(sensor=sensor)
    message = str(info.value)
    assert "\n" not in message and "valid sensors: ideal, kinect-v1, azure-tof" in message


def test_run_episode_cli_observes_through_the_sensor(capsys) -> None:
    argv = ["--object", "phone", "--seed", "2", "--estimator", "oracle", "--json", "-"]
    assert run_episode.main([*argv, "--obs-mode", "rgbd", "--sensor", "kinect-v1+camera"]) == 0
    captured = capsys.readouterr()
    d = json.loads(captured.out)
    assert d["sensor"] == "kinect-v1+camera" and d["success"] is True
    assert "sensor" in d["timings_ms"]
    assert "tier=isolated  sensor=kinect-v1+camera" in captured.err
