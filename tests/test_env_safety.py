"""The safe paths: poses that are not poses end an episode as invalid_action, wrong types raise in
one line, the env recovers from a refused reset through gymnasium.make, and env seeds are the
episode seeds `sim.evaluate` plays."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import posegrasp  # noqa: F401  (registers the env)
from posegrasp.core.contract import MAX_POSE_DISTANCE, ROTATION_TOL, pose_problem
from posegrasp.core.errors import InvalidArgumentError, StateError, UnknownNameError
from posegrasp.core.transforms import axis_angle
from posegrasp.world import constants as C
from sim.env import GraspEvalEnv, pose_action
from sim.episodes.episode import Episode, EpisodeConfig, play_episode
from sim.episodes.registry import OracleEstimator

SMALL = EpisodeConfig(width=64, height=48)


def _pose(t=(0.05, -0.02, 0.8)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = axis_angle(np.array([0.3, -1.0, 0.5]), 0.7)
    T[:3, 3] = t
    return T


def _sheared() -> np.ndarray:
    T = _pose()
    shear = np.eye(3)
    shear[0, 1] = 1e-3  # R^T R = S^T S: off the identity by 1e-3
    T[:3, :3] = T[:3, :3] @ shear
    return T


def _reflected() -> np.ndarray:
    T = _pose()
    T[:3, 0] *= -1
    return T


def _nan() -> np.ndarray:
    T = _pose()
    T[1, 1] = np.nan
    return T


#: (pose, a phrase the note must hold)
BAD_POSES = {
    "shear": (_sheared(), "shear/scale"),
    "reflection": (_reflected(), "reflection"),
    "millimetres": (_pose((50.0, -20.0, 800.0)), "poses are in metres; millimetres?"),
    "nan": (_nan(), "NaN"),
}


def test_pose_problem_measures_what_is_wrong() -> None:
    assert pose_problem(_pose()) is None
    assert "max |R^T R - I| = 1.00e-03" in pose_problem(_sheared())
    assert "det R = -1.000" in pose_problem(_reflected())
    assert "801.8 m from the camera" in pose_problem(BAD_POSES["millimetres"][0])
    assert pose_problem(_pose((0.0, 0.0, MAX_POSE_DISTANCE * 0.99))) is None


def test_float32_rotations_are_poses() -> None:
    rng = np.random.default_rng(0)
    worst = 0.0
    for _ in range(200):
        T = _pose()
        T[:3, :3] = axis_angle(rng.normal(size=3), rng.uniform(0, np.pi))
        T32 = T.astype(np.float32)
        R = T32[:3, :3].astype(float)
        worst = max(worst, float(np.abs(R.T @ R - np.eye(3)).max()))
        assert pose_problem(T32) is None
    assert worst < ROTATION_TOL / 3


@pytest.mark.parametrize("case", sorted(BAD_POSES))
def test_a_bad_estimate_ends_the_episode_as_invalid_action(case: str) -> None:
    T, phrase = BAD_POSES[case]
    ep = Episode("phone", 2, SMALL)
    try:
        r = ep.act(T, "test")
    finally:
        ep.close()
    assert not r.success and r.failure_reason == "invalid_action"
    assert phrase in r.notes[0] and r.notes[0].startswith("estimated pose T_C_O: ")
    assert r.pose_error is None and r.pose_correct is None
    assert "plan" not in r.timings_ms  # nothing was planned
    d = r.to_json()
    assert d["failure_reason"] == "invalid_action" and d["pose_correct"] is None
    if case == "nan":
        assert d["T_C_O_est"] is None  # strict JSON has no NaN


def test_a_bad_neighbour_pose_ends_the_episode_as_invalid_action() -> None:
    ep = Episode("phone", 2, SMALL)
    try:
        r = ep.act(ep.T_C_O_true, "test", neighbours=[("car", _pose()), ("chair", _sheared())])
        with pytest.raises(StateError):
            ep.act(None)
    finally:
        ep.close()
    assert r.failure_reason == "invalid_action"
    assert r.notes[0].startswith("pose of neighbour 1 ('chair'): rotation is not orthonormal")


@pytest.mark.parametrize(
    "T, neighbours, error, match",
    [
        (np.eye(3), (), InvalidArgumentError, r"must be a real 4x4 array .* shape \(3, 3\)"),
        ("eye", (), InvalidArgumentError, "must be a real 4x4 array"),
        (np.eye(4, dtype=complex), (), InvalidArgumentError, "complex128"),
        (np.eye(4), [np.eye(4)], InvalidArgumentError, "neighbour 0 must be a .class, T_C_N. pair"),
        (np.eye(4), np.eye(4), InvalidArgumentError, "neighbours must be a sequence"),
        (np.eye(4), [("car",)], InvalidArgumentError, "a tuple of 1"),
        (np.eye(4), [("teapot", np.eye(4))], UnknownNameError, "valid objects: car"),
        (np.eye(4), [("car", np.zeros(3))], InvalidArgumentError, "neighbour 0 .'car'. must be"),
    ],
)
def test_a_wrong_type_or_shape_raises_in_one_line(T, neighbours, error, match) -> None:
    ep = Episode("phone", 2, SMALL)
    try:
        with pytest.raises(error, match=match) as exc:
            ep.act(T, "test", neighbours=neighbours)
        assert "\n" not in str(exc.value)
        assert ep.act(None).failure_reason == "no_estimate"  # a refused act does not end it
    finally:
        ep.close()
    with pytest.raises(error, match=match):
        pose_action(T, neighbours)


@pytest.mark.parametrize(
    "T, match",
    [
        (_sheared(), "shear/scale"),
        (_reflected(), "reflection"),
        (_nan(), "NaN"),
        (np.vstack([_pose()[:3], [0, 0, 1, 1]]), "last row"),
    ],
)
def test_pose_action_refuses_what_no_quaternion_represents(T, match) -> None:
    with pytest.raises(InvalidArgumentError, match=match):
        pose_action(T)
    with pytest.raises(InvalidArgumentError, match=f"neighbour 0 .'pistol'.: .*{match}"):
        pose_action(_pose(), [("pistol", T)])


def test_pose_action_keeps_a_pose_in_millimetres_for_the_env_to_judge() -> None:
    action = pose_action(BAD_POSES["millimetres"][0])
    np.testing.assert_array_equal(action["position"], [50.0, -20.0, 800.0])


@pytest.mark.parametrize("where", ["estimate", "neighbour"])
def test_env_position_in_millimetres_is_an_invalid_action(where: str) -> None:
    env = GraspEvalEnv(object="phone", width=64, height=48)
    env.reset(seed=2)
    true = env.unwrapped._episode.T_C_O_true
    mm = true.copy()
    mm[:3, 3] *= 1000
    action = pose_action(mm) if where == "estimate" else pose_action(true, [("car", mm)])
    _, reward, terminated, _, info = env.step(action)
    env.close()
    assert reward == 0.0 and terminated and info["failure_reason"] == "invalid_action"
    assert "poses are in metres; millimetres?" in info["error"]
    assert ("neighbour 0" in info["error"]) == (where == "neighbour")


def test_a_refused_reset_through_gym_make_leaves_the_env_usable() -> None:
    env = gym.make("posegrasp:GraspEval-v0", object="phone", width=64, height=48)
    with pytest.raises(InvalidArgumentError, match="invalid seed -3"):
        env.reset(seed=-3)
    with pytest.raises(StateError, match=r"call reset\(\) first"):
        env.step(pose_action(None))
    with pytest.raises(InvalidArgumentError, match="unknown options"):
        env.reset(options={"colour": "red"})
    obs, info = env.reset(seed=4)
    assert obs in env.observation_space and info["episode_seed"] == 4
    _, reward, terminated, _, info = env.step(pose_action(None))
    assert reward == 0.0 and terminated and info["failure_reason"] == "no_estimate"
    env.reset()
    assert env.step(pose_action(None))[4]["episode_seed"] == 5
    env.close()


def test_env_seeds_are_episode_seeds_and_count_on() -> None:
    env = GraspEvalEnv(object="car", width=64, height=48)
    seeds = [env.reset(seed=40)[1]["episode_seed"]]
    seeds += [env.reset()[1]["episode_seed"] for _ in range(2)]
    seeds.append(env.reset(options={"episode_seed": 7})[1]["episode_seed"])
    seeds.append(env.reset()[1]["episode_seed"])
    seeds.append(env.reset(seed=3, options={"episode_seed": 90})[1]["episode_seed"])
    assert seeds == [40, 41, 42, 7, 8, 90]
    fresh = GraspEvalEnv(object="car", width=64, height=48)
    drawn = fresh.reset()[1]["episode_seed"]  # never seeded: drawn from np_random
    assert fresh.reset()[1]["episode_seed"] == drawn + 1
    for e in (env, fresh):
        e.close()


def test_same_seed_sequences_replay_identically() -> None:
    images = []
    for _ in range(2):
        env = GraspEvalEnv(width=64, height=48)  # the class drawn from np_random too
        a, ia = env.reset(seed=11)
        b, ib = env.reset()
        images.append((a["rgb"], b["rgb"], ia, ib))
        env.close()
    (a1, b1, *i1), (a2, b2, *i2) = images
    assert i1 == i2 and i1[1]["episode_seed"] == 12
    np.testing.assert_array_equal(a1, a2)
    np.testing.assert_array_equal(b1, b2)


def test_an_env_episode_is_the_evaluate_episode_of_its_seed() -> None:
    """`sim.evaluate --objects pistol --seed-start S` plays scene seed S + i as episode i."""
    seed = C.EVAL_SEED_BASE + 1
    env = gym.make("posegrasp:GraspEval-v0", object="pistol")
    env.reset(seed=C.EVAL_SEED_BASE)
    _, info = env.reset()  # the episode after S: S + 1
    ep = env.unwrapped._episode
    T_true = ep.T_C_O_true.copy()
    _, reward, *_, step_info = env.step(pose_action(T_true, ep.true_neighbours()))
    env.close()
    r = play_episode("pistol", seed, OracleEstimator())
    assert info["episode_seed"] == seed == r.seed
    np.testing.assert_array_equal(T_true, r.T_C_O_true)
    assert bool(reward) == r.success and step_info["failure_reason"] == r.failure_reason
    assert step_info["lift_height"] == pytest.approx(r.lift_height, abs=2e-3)
    assert step_info["pose_correct"] is True and r.pose_correct is True
