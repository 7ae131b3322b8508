"""The GraspEval-v0 gymnasium env: contract, determinism, vectorisation, bad actions, and the
observation an estimator gets through it (`Observation.from_env`)."""

from __future__ import annotations

import warnings
from dataclasses import fields, replace
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import posegrasp  # noqa: F401  (registers the env)
from perception.estimators import LEARNED_ESTIMATORS
from posegrasp.core.contract import Estimate, Observation
from posegrasp.core.errors import InvalidArgumentError, PosegraspError, StateError, UnknownNameError
from posegrasp.world.scene import SceneConfig
from posegrasp.world.shifts import parse_shifts
from posegrasp.world.tiers import TIERS
from sim.env import MAX_NEIGHBOURS, GraspEvalEnv, pose_action
from sim.episodes.episode import PLACE_TOLERANCE, Episode, EpisodeConfig, play_episode
from sim.episodes.registry import make_estimator
from sim.evaluation import Protocol, evaluate_protocol

CRUDE = Path(__file__).resolve().parent.parent / "examples" / "crude-estimator"
#: sim.evaluate's first episode seed.
SEED = 1_000_000_000


def _truth(env: gym.Env) -> np.ndarray:
    return env.unwrapped._episode.T_C_O_true


@pytest.mark.parametrize("tier", TIERS)
def test_check_env_passes(tier: str) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # advisory warnings about unbounded Box spaces
        env = gym.make("GraspEval-v0", object="chair", render_mode="rgb_array", tier=tier)
        check_env(env.unwrapped)


def test_make_by_module_prefix_and_oracle_action_succeeds() -> None:
    env = gym.make("posegrasp:GraspEval-v0", object="phone", timings=True)
    obs, info = env.reset(seed=5)
    assert obs["rgb"].shape == (480, 640, 3) and obs["rgb"].dtype == np.uint8
    assert info["object"] == "phone"
    _, reward, terminated, truncated, info = env.step(pose_action(_truth(env)))
    assert reward == 1.0 and terminated and not truncated
    assert info["success"] and info["failure_reason"] is None
    assert info["pose_error"]["rotation_deg"] == pytest.approx(0.0, abs=1e-4)
    assert info["pose_correct"] is True and info["pose_error"]["mssd_m"] < 1e-6
    assert "plan" in info["timings_ms"]
    env.close()


def test_same_seed_same_outcome() -> None:
    outs = []
    for _ in range(2):
        env = GraspEvalEnv()
        obs, info = env.reset(seed=123)
        T = _truth(env).copy()
        T[:3, 3] += [0.01, 0.0, 0.02]
        _, r, *_, step_info = env.step(pose_action(T))
        outs.append((obs["rgb"], info, r, step_info["lift_height"], step_info["failure_reason"]))
        env.close()
    np.testing.assert_array_equal(outs[0][0], outs[1][0])
    assert outs[0][1:] == outs[1][1:]


@pytest.mark.parametrize(
    "mutate, reason",
    [
        (lambda a: a["position"].__setitem__(0, np.nan), "invalid_action"),
        (lambda a: a.__setitem__("quaternion", np.array([0.5, 0.5, 0.0, 0.0])), "invalid_action"),
        (lambda a: a.__setitem__("has_estimate", 0), "no_estimate"),
    ],
)
def test_bad_or_missing_estimate_is_a_failed_grasp(mutate, reason) -> None:
    env = GraspEvalEnv(object="faucet")
    env.reset(seed=1)
    action = pose_action(_truth(env))
    mutate(action)
    _, r, terminated, _, info = env.step(action)
    assert r == 0.0 and terminated
    assert info["failure_reason"] == reason
    if reason == "invalid_action":
        assert "error" in info
    env.close()


def test_wrong_action_shape_raises() -> None:
    env = GraspEvalEnv(object="faucet")
    env.reset(seed=1)
    action = pose_action(_truth(env))
    action["position"] = np.zeros(4)
    with pytest.raises(ValueError, match=r"shape \(3,\)"):
        env.step(action)
    env.close()


def test_unknown_object() -> None:
    with pytest.raises(UnknownNameError, match="valid objects: car"):
        GraspEvalEnv(object="teapot")


@pytest.mark.slow
def test_runs_in_async_vector_env() -> None:
    envs = gym.vector.AsyncVectorEnv(
        [lambda: gym.make("posegrasp:GraspEval-v0", object="screen")] * 2, context="spawn"
    )
    try:
        obs, _ = envs.reset(seed=[7, 8])
        assert obs["rgb"].shape == (2, 480, 640, 3)
        actions = {
            "has_estimate": np.array([0, 0]),
            "position": np.zeros((2, 3)),
            "quaternion": np.tile([1.0, 0, 0, 0], (2, 1)),
            "neighbours": {
                "count": np.array([0, 0]),
                "object": np.zeros((2, MAX_NEIGHBOURS), int),
                "position": np.zeros((2, MAX_NEIGHBOURS, 3)),
                "quaternion": np.tile([1.0, 0, 0, 0], (2, MAX_NEIGHBOURS, 1)),
            },
        }
        _, rewards, terminated, _, infos = envs.step(actions)
        assert rewards.tolist() == [0.0, 0.0] and terminated.all()
        assert list(infos["failure_reason"]) == ["no_estimate", "no_estimate"]
    finally:
        envs.close()


def test_tier_is_an_argument_and_reported() -> None:
    env = GraspEvalEnv(object="phone", tier="clutter", width=64, height=48)
    env.reset(seed=3)
    assert len(env.unwrapped._episode.scene.objects) >= 4
    _, reward, *_, info = env.step(pose_action(_truth(env)))
    assert info["tier"] == "clutter" and reward in (0.0, 1.0)
    env.close()
    with pytest.raises(UnknownNameError, match="valid tiers"):
        GraspEvalEnv(tier="banana")


@pytest.mark.parametrize(
    "kwargs",
    [
        {"seed": -1},
        {"seed": 2**32},
        {"options": {"episode_seed": -5}},
        {"options": {"episode_seed": "7"}},
        {"options": {"object": "teapot"}},
        {"options": {"colour": "red"}},
        {"options": ["object"]},
    ],
)
def test_a_failed_reset_leaves_no_episode_and_step_asks_for_a_reset(kwargs) -> None:
    env = GraspEvalEnv(object="phone", width=64, height=48)
    with pytest.raises(PosegraspError):
        env.reset(**kwargs)
    with pytest.raises(StateError, match=r"call reset\(\) first"):
        env.step(pose_action(None))
    env.close()


@pytest.mark.parametrize(
    "key, value",
    [
        ("has_estimate", np.nan),
        ("has_estimate", "1"),
        ("has_estimate", np.array([1, 0])),
        ("has_estimate", 2),
        ("has_estimate", 1.0),
        ("position", np.array([0.1, 0.0, 0.5 + 1j])),
        ("position", "abc"),
        ("quaternion", [1, 0, 0]),
    ],
)
def test_the_action_contract_is_exact(key, value) -> None:
    env = GraspEvalEnv(object="phone", width=64, height=48)
    env.reset(seed=2)
    action = pose_action(_truth(env))
    action[key] = value
    with pytest.raises(InvalidArgumentError, match=key):
        env.step(action)
    env.close()


def test_neighbours_in_the_action_reach_the_planner(monkeypatch) -> None:
    env = GraspEvalEnv(object="phone", tier="clutter", width=64, height=48)
    env.reset(seed=3)
    ep = env.unwrapped._episode
    true = ep.true_neighbours()
    told = {}

    def act(T, estimator, recorder=None, neighbours=()):
        told["neighbours"] = list(neighbours)
        return type(ep).act(ep, None, estimator)

    monkeypatch.setattr(ep, "act", act)
    env.step(pose_action(_truth(env), true))
    assert [n for n, _ in told["neighbours"]] == [n for n, _ in true]
    for (_, a), (_, b) in zip(told["neighbours"], true, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-9)
    env.close()


def test_a_non_unit_neighbour_quaternion_is_an_invalid_action() -> None:
    env = GraspEvalEnv(object="phone", width=64, height=48)
    env.reset(seed=2)
    action = pose_action(_truth(env), [("car", np.eye(4))])
    action["neighbours"]["quaternion"][0] = [0.5, 0.5, 0.0, 0.0]
    _, reward, *_, info = env.step(action)
    assert reward == 0.0 and info["failure_reason"] == "invalid_action"
    assert "neighbour 0" in info["error"]
    env.close()


@pytest.mark.parametrize(
    ("obs_mode", "sensor"),
    [("rgb", "ideal"), ("rgbd", "ideal"), ("rgbd", "kinect-v1+camera"), ("rgb", "ideal+camera")],
)
def test_from_env_is_the_observation_an_episode_hands_an_estimator(
    obs_mode: str, sensor: str
) -> None:
    env = GraspEvalEnv(object="car", obs_mode=obs_mode, sensor=sensor)
    obs, info = env.reset(seed=SEED + 3)
    got = Observation.from_env(obs, info)
    assert env.observation_space.contains(obs)  # holes (0) inside the depth's Box(0, inf)
    env.close()
    episode = Episode("car", SEED + 3, EpisodeConfig(obs_mode=obs_mode, sensor=sensor))
    want = episode.observe()
    episode.close()
    assert isinstance(got.table_top_z, float) and (got.depth is None) == (obs_mode == "rgb")
    if sensor != "ideal":  # the sensor's images, not the renders
        assert "sensor" in episode.timings_ms
        assert obs_mode == "rgb" or (got.depth == 0).any()
    for f in fields(Observation):
        a, b = getattr(got, f.name), getattr(want, f.name)
        assert type(a) is type(b) and np.array_equal(a, b), f.name


class _Digest:
    """An estimator of the contract that answers no pose and records a digest of every image it
    is handed in its ``info`` (which the episode records as ``estimate_info``)."""

    name = "digest"

    def estimate(self, obs: Observation) -> Estimate:
        import hashlib

        images = {"rgb": obs.rgb, "depth": obs.depth}
        return Estimate(
            None,
            info={
                k: None if v is None else hashlib.sha256(v.tobytes()).hexdigest()
                for k, v in images.items()
            },
        )


def test_evaluate_and_the_env_hand_an_estimator_the_same_sensor_images() -> None:
    sensor = "azure-tof+camera"
    protocol = Protocol(["car"], 1, SEED + 3, obs_mode="rgbd", sensor=sensor)
    report = evaluate_protocol(protocol, _Digest())
    (episode,) = report["episodes"]
    seen = {}
    for name in (sensor, "ideal"):
        env = GraspEvalEnv(object="car", obs_mode="rgbd", sensor=name)
        obs, info = env.reset(seed=SEED + 3)
        env.close()
        seen[name] = _Digest().estimate(Observation.from_env(obs, info)).info
    assert episode["estimate_info"] == seen[sensor] and episode["sensor"] == sensor
    assert all(seen["ideal"][k] != seen[sensor][k] for k in ("rgb", "depth"))


def test_an_unknown_sensor_is_one_line() -> None:
    with pytest.raises(UnknownNameError) as info:
        GraspEvalEnv(sensor="kinect-v2")
    assert "\n" not in str(info.value)
    assert "valid sensors: ideal, kinect-v1, azure-tof" in str(info.value)
    base = EpisodeConfig(sensor="azure-tof")
    assert GraspEvalEnv(config=base).config.sensor == "azure-tof"  # the config's, unless named
    assert GraspEvalEnv(config=base, sensor="ideal").config.sensor == "ideal"


def test_check_env_passes_on_the_place_task_under_shifts() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # advisory warnings about unbounded Box spaces
        env = gym.make("GraspEval-v0", object="phone", task="place", shifts="camera:3,walls:1")
        check_env(env.unwrapped)
    assert env.unwrapped.task == "place" and env.unwrapped.shifts == parse_shifts(
        "walls:1,camera:3"
    )


def test_the_place_task_reports_its_record_in_info() -> None:
    """The oracle's pose is placed on its goal; the place record is in `info`; a lift env's
    info has none, and a failed lift has nothing placed."""
    env = GraspEvalEnv(object="phone", task="place")
    env.reset(seed=SEED)
    _, reward, terminated, _, info = env.step(pose_action(_truth(env)))
    assert reward == 1.0 and terminated and info["success"] and info["failure_reason"] is None
    record = info["place"]
    assert record["placed"] is True and record["failure_reason"] is None
    assert set(record) >= {"goal", "T_world_O_final", "errors", "placed"}
    assert record["errors"]["translation_m"] < PLACE_TOLERANCE[0]
    assert record["errors"]["rotation_deg"] < PLACE_TOLERANCE[1]
    # The episode's own record: the same goal as `play_episode` draws for the seed.
    want = play_episode("phone", SEED, make_estimator("oracle"), EpisodeConfig(task="place"))
    assert want.place is not None and record["goal"] == want.place["goal"]
    env.reset(seed=SEED)
    _, reward, *_, info = env.step(pose_action(None))
    assert reward == 0.0 and info["failure_reason"] == "no_estimate" and info["place"] is None
    env.close()
    env = GraspEvalEnv(object="phone")
    env.reset(seed=SEED)
    assert "place" not in env.step(pose_action(_truth(env)))[-1]
    env.close()


def test_the_env_observes_the_shifted_scene_an_episode_observes() -> None:
    shifts = "light_colour:3,camera:3"
    env = GraspEvalEnv(object="car", shifts=shifts)
    obs, info = env.reset(seed=SEED + 3)
    env.close()
    cfg = EpisodeConfig(scene=SceneConfig(shifts=parse_shifts(shifts)))
    episode = Episode("car", SEED + 3, cfg)
    want = episode.observe()
    episode.close()
    got = Observation.from_env(obs, info)
    for f in fields(Observation):
        a, b = getattr(got, f.name), getattr(want, f.name)
        assert type(a) is type(b) and np.array_equal(a, b), f.name
    plain = GraspEvalEnv(object="car")
    unshifted, _ = plain.reset(seed=SEED + 3)
    plain.close()
    assert not np.array_equal(unshifted["rgb"], obs["rgb"])
    # Shift values and a spec give the same env; the config's shifts and task hold unless named.
    assert GraspEvalEnv(shifts=list(parse_shifts(shifts))).shifts == parse_shifts(shifts)
    base = EpisodeConfig(task="place", scene=SceneConfig(shifts=parse_shifts("walls")))
    assert (GraspEvalEnv(config=base).task, GraspEvalEnv(config=base).shifts) == (
        "place",
        parse_shifts("walls"),
    )
    assert GraspEvalEnv(config=base, task="lift", shifts="").config == replace(
        base, task="lift", scene=SceneConfig()
    )


@pytest.mark.parametrize(
    ("kwargs", "error", "says"),
    [
        ({"task": "stack"}, UnknownNameError, "valid tasks: lift, place"),
        ({"shifts": "fog"}, UnknownNameError, "valid scene shifts: light_colour, "),
        ({"shifts": "camera:4"}, InvalidArgumentError, "levels 1 mild, 2 medium, 3 strong"),
        ({"shifts": "camera,camera:3"}, InvalidArgumentError, "camera asked for more than once"),
        ({"shifts": 3}, InvalidArgumentError, "shifts must be a spec such as"),
        ({"shifts": ["camera"]}, InvalidArgumentError, "are Shift values"),
    ],
)
def test_a_bad_task_or_shift_is_one_line_naming_the_valid_ones(
    kwargs: dict, error: type, says: str
) -> None:
    with pytest.raises(error) as info:
        GraspEvalEnv(**kwargs)
    assert says in str(info.value) and "\n" not in str(info.value)


def test_from_env_names_what_it_lacks() -> None:
    env = GraspEvalEnv(object="phone")
    obs, info = env.reset(seed=SEED)
    env.close()
    with pytest.raises(InvalidArgumentError, match="lacks episode_seed; it needs object, episode"):
        Observation.from_env(obs, {"object": "phone"})
    with pytest.raises(InvalidArgumentError, match="lacks table_top_z"):
        Observation.from_env({k: v for k, v in obs.items() if k != "table_top_z"}, info)
    with pytest.raises(InvalidArgumentError, match="one real number"):
        Observation.from_env({**obs, "table_top_z": np.zeros(2)}, info)


#: Three estimators in the fast tier; every other built-in one in the slow tier.
ENV_ROUTE_FAST = ("posegrasp_crude:CrudeTableEstimator", "hybrid-global-table", "hybrid")
#: Needs a detector trained on user objects, which the tests' empty objects directory lacks;
#: tests/test_user_training.py trains one and runs it.
ENV_ROUTE_NEEDS_USER_DETECTOR = ("hybrid-global-user",)


@pytest.mark.parametrize(
    "spec",
    [
        *ENV_ROUTE_FAST,
        *(
            pytest.param(name, marks=pytest.mark.slow)
            for name in LEARNED_ESTIMATORS
            if name not in ENV_ROUTE_FAST + ENV_ROUTE_NEEDS_USER_DETECTOR
        ),
    ],
)
def test_the_env_route_estimates_as_evaluate_does(
    spec: str, monkeypatch: pytest.MonkeyPatch, torch_one_thread: None
) -> None:
    """Through the env with `Observation.from_env`, an estimator answers exactly the pose it
    answers in `sim.evaluate`'s episode of the same seed, and the grasp on it ends alike."""
    monkeypatch.syspath_prepend(str(CRUDE))
    estimator = make_estimator(spec)
    episode = evaluate_protocol(Protocol(["phone"], 1, SEED), estimator)["episodes"][0]
    env = GraspEvalEnv(object="phone")
    obs, info = env.reset(seed=SEED)
    est = estimator.estimate(Observation.from_env(obs, info))
    _, reward, *_, step_info = env.step(pose_action(est.T_C_O, est.neighbours))
    env.close()
    assert est.T_C_O is not None and np.array_equal(est.T_C_O, np.array(episode["T_C_O_est"]))
    # The action carries the pose as a position and a quaternion, so the grasp's pose is the
    # estimate to rounding only.
    assert step_info["pose_error"] == pytest.approx(episode["pose_error"], rel=1e-9, abs=1e-12)
    assert (reward == 1.0, step_info["failure_reason"]) == (
        episode["success"],
        episode["failure_reason"],
    )
