"""`GraspEval-v0`: a gymnasium env in which one step is one grasp episode.

Any pose estimator can be scored through it: the observation is the head-camera image (and,
with ``obs_mode="rgbd"``, its depth image), as the sensor model ``sensor`` returns it, with its
intrinsics and pose, the requested object
class and the height of the table top the object rests on (known scene geometry, in the world
frame); the action is the estimated pose of that object in the camera frame (or "no estimate");
the step executes the grasp on that pose and, on the place task (``task="place"``), carries the
object to a goal pose and sets it down. Scene shifts (``shifts``) change what the head camera
sees and nothing of the physics. `posegrasp.core.contract.Observation.from_env(obs,
info)` turns a reset's observation and info into the `Observation` an estimator takes, the one
`sim.evaluate` hands it for the same episode (examples/env_route.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from posegrasp.core.contract import transform_problem
from posegrasp.core.errors import InvalidArgumentError, StateError, UnknownNameError
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.transforms import mat_to_quat, quat_to_mat
from posegrasp.core.validate import SEED_LIMIT, check_seed
from posegrasp.world.camera import CameraRenderer, external_renderer
from posegrasp.world.constants import EXTERNAL_CAMERA
from posegrasp.world.objects import OBJECT_NAMES, object_names
from posegrasp.world.shifts import Shift, canonical, parse_shifts
from posegrasp.world.tiers import check_tier
from sim.episodes.episode import Episode, EpisodeConfig, check_estimate

#: Tolerance on the norm of the action's quaternion.
UNIT_QUAT_TOL = 1e-3
#: Most neighbour poses an action may report.
MAX_NEIGHBOURS = 8
#: Keys of `reset`'s options.
OPTIONS = ("object", "episode_seed")
#: Keys every action holds; ``neighbours`` is optional.
ACTION_KEYS = ("has_estimate", "position", "quaternion")


def pose_action(
    T_C_O: np.ndarray | None, neighbours: Sequence[tuple[str, np.ndarray]] = ()
) -> dict[str, Any]:
    """The action that reports a pose, or no estimate, and the other objects seen.

    Args:
        T_C_O: the target's pose (4, 4) in the camera frame [m], or None for no estimate.
        neighbours: the other objects seen, (class, T_C_N) pairs in the camera frame, at most
            `MAX_NEIGHBOURS`.

    Returns:
        An action of `GraspEvalEnv.action_space` (``neighbours`` only when some are given).

    Raises:
        InvalidArgumentError: a pose that is not a finite 4x4 rigid transform (a rotation block
            off orthonormal by more than `posegrasp.core.contract.ROTATION_TOL`, a reflection,
            a last row other than (0, 0, 0, 1)), which no quaternion represents; a neighbour
            that is not a (class, pose) pair; more than `MAX_NEIGHBOURS` neighbours.
        UnknownNameError: a neighbour of an unknown class.
    """
    T, told, _ = check_estimate(T_C_O, neighbours)
    poses = [("pose T_C_O", T)] if T is not None else []
    poses += [(f"pose of neighbour {i} ({n!r})", pose) for i, (n, pose) in enumerate(told)]
    for what, pose in poses:
        if (problem := transform_problem(pose)) is not None:
            raise InvalidArgumentError(f"{what}: {problem}")
    if len(told) > MAX_NEIGHBOURS:
        raise InvalidArgumentError(f"at most {MAX_NEIGHBOURS} neighbours, got {len(told)}")
    action: dict[str, Any] = {
        "has_estimate": 0,
        "position": np.zeros(3),
        "quaternion": np.array([1.0, 0, 0, 0]),
    }
    if T is not None:
        action |= {
            "has_estimate": 1,
            "position": T[:3, 3].copy(),
            "quaternion": mat_to_quat(T[:3, :3]),
        }
    if told:
        classes = object_names()
        quats = np.tile([1.0, 0.0, 0.0, 0.0], (MAX_NEIGHBOURS, 1))
        pos = np.zeros((MAX_NEIGHBOURS, 3))
        ids = np.zeros(MAX_NEIGHBOURS, np.int64)
        for i, (name, pose) in enumerate(told):
            ids[i] = classes.index(name)
            pos[i], quats[i] = pose[:3, 3], mat_to_quat(pose[:3, :3])
        action["neighbours"] = {
            "count": len(told),
            "object": ids,
            "position": pos,
            "quaternion": quats,
        }
    return action


def _real(value: Any, shape: tuple[int, ...], name: str) -> np.ndarray:
    a = np.asarray(value)
    if a.dtype.kind not in "iuf" or a.shape != shape:
        raise InvalidArgumentError(
            f"action {name} must be a real array of shape {shape}, got {a.dtype} {a.shape}"
        )
    return a.astype(float)


def _count(value: Any, hi: int, name: str) -> int:
    """An int or bool (Python or numpy, or a 0-d array of one) in 0..hi."""
    if isinstance(value, np.ndarray) and value.shape == () and value.dtype.kind in "biu":
        value = value.item()
    if isinstance(value, (bool, np.bool_)):
        value = int(value)
    if not isinstance(value, (int, np.integer)) or not 0 <= value <= hi:
        raise InvalidArgumentError(
            f"action {name} must be an int or bool in 0..{hi}, got {value!r}"
        )
    return int(value)


def _pose(pos: np.ndarray, quat: np.ndarray, what: str) -> tuple[np.ndarray | None, str | None]:
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(quat))):
        return None, f"{what} contains NaN or infinite values"
    if abs(np.linalg.norm(quat) - 1.0) > UNIT_QUAT_TOL:
        return None, f"{what} quaternion is not unit norm (|q| = {np.linalg.norm(quat):.4f})"
    T = np.eye(4)
    T[:3, :3] = quat_to_mat(quat / np.linalg.norm(quat))
    T[:3, 3] = pos
    return T, None


def env_config(
    base: EpisodeConfig,
    width: int,
    height: int,
    tier: str | None = None,
    obs_mode: str | None = None,
    sensor: str | None = None,
    task: str | None = None,
    shifts: str | Sequence[Shift] | None = None,
) -> EpisodeConfig:
    """The episode config of an env: `base` at the resolution width x height, with each of
    tier, obs_mode, sensor, task and shifts that is given in place of the base's (shifts as a
    `posegrasp.world.shifts.parse_shifts` spec such as ``"camera:3,light_colour"`` or as
    `Shift` values).

    Raises:
        UnknownNameError: a tier, observation mode, sensor, task or scene shift that does not
            exist, listing the valid ones.
        InvalidArgumentError: a bad shift level, a factor given twice, or shifts that are
            neither text nor `Shift` values.
    """
    if shifts is None:
        scene = base.scene
    elif isinstance(shifts, str):
        scene = replace(base.scene, shifts=parse_shifts(shifts))
    elif isinstance(shifts, (list, tuple)):
        scene = replace(base.scene, shifts=canonical(shifts))
    else:
        raise InvalidArgumentError(
            f"shifts must be a spec such as 'camera:3,light_colour' or Shift values, got "
            f"{type(shifts).__name__}"
        )
    return replace(
        base,
        width=width,
        height=height,
        scene=scene,
        tier=check_tier(tier if tier is not None else base.tier),
        obs_mode=obs_mode if obs_mode is not None else base.obs_mode,
        sensor=sensor if sensor is not None else base.sensor,
        task=task if task is not None else base.task,
    )


class GraspEvalEnv(gym.Env):
    """Score a 6D pose estimate by a simulated Fetch grasping the object on it.

    ## Description
    Each episode builds a seeded MuJoCo scene (Fetch in front of a table with one object),
    renders the head camera and asks the agent for the pose of the requested object. The single
    step plans a grasp with mink on that pose and executes it in physics; on the place task it
    then carries the object to a goal pose on the table drawn from the episode seed
    (`posegrasp.world.goals`), placing it as the agent's pose says it lies in the hand, sets it
    down and lets it settle. An episode is
    `sim.episodes.episode.Episode` itself: with the same object, episode seed, tier and config, an
    env episode and `sim.episodes.episode.play_episode` build the same scene, render the same image
    and, on the same pose, grasp the same way.

    ## Action Space
    `Dict`: `has_estimate` (`Discrete(2)`, 0 = no estimate), `position` (`Box(3,)`, object
    origin in the OpenCV camera frame [m]), `quaternion` (`Box(4,)`, object orientation in the
    camera frame, w x y z, unit norm) and, optionally, `neighbours`: the other objects the
    estimator saw, which the planner keeps the gripper clear of: `Dict` of `count`
    (`Discrete(MAX_NEIGHBOURS + 1)`), `object` (`MultiDiscrete`, class indices), `position`
    (`Box(MAX_NEIGHBOURS, 3)`) and `quaternion` (`Box(MAX_NEIGHBOURS, 4)`); the first `count`
    rows are used (`pose_action(T, neighbours)` builds it from 4x4 poses). `has_estimate` must be
    0 or 1 (an int or bool); positions and quaternions real arrays of their shapes.

    ## Observation Space
    `Dict`: `rgb` (`Box(H, W, 3)`, uint8), `K` (`Box(3, 3)`, intrinsics [px]), `T_world_cam`
    (`Box(4, 4)`, camera pose in the world, OpenCV convention), `object` (`Discrete(n)`, index
    into `GraspEvalEnv.classes`: the six built-in objects in `OBJECT_NAMES` order, then the user
    objects installed when the env was made), `table_top_z` (`Box(1,)`, the table top's
    height in the world [m]) and, with ``obs_mode="rgbd"``, `depth` (`Box(0, inf, (H, W))`,
    float32: per pixel the z coordinate along the optical axis of the surface seen [m], as
    `posegrasp.core.contract.Observation.depth`). The colour image is the same in both modes.
    Both are the images as the env's sensor returns them (`sensor`, `posegrasp.world.sensors`):
    under ``ideal`` the rendered ones; under another, the colour image with that sensor's noise
    and, in ``rgbd``, its depth image, with 0 where it returns nothing (holes). The noise is the
    episode seed's, the same on every reset with that seed.
    ``Observation.from_env(obs, info)`` (`posegrasp.core.contract`) makes of a reset's
    observation and info the `Observation` a pose estimator takes, the table height as a float
    and the depth included: the one `sim.evaluate` and `sim.episodes.episode.play_episode` hand it
    for the same object and episode seed, so its estimate is the same to the bit.

    ## Rewards
    Lift task (default): 1.0 when the object is lifted at least 0.10 m above the table and still
    held after a 2 s hold, else 0.0. Place task: 1.0 when, after that lift, the object comes to
    rest within `sim.episodes.episode.PLACE_TOLERANCE` (2 cm and 10 deg, symmetry-aware) of its
    goal, else 0.0. `info` repeats it as `success` with `failure_reason` (the place task's own:
    ``place_infeasible``, ``dropped``, ``tipped``, ``off_target``), the pose errors
    (`pose_error`, with BOP's MSSD and MSPD), `pose_correct` (MSSD below 10 % of the diameter;
    None without a valid estimate), `lift_height`, on the place task `place` (the goal, the
    final pose ``T_world_O_final``, the `errors` from the goal, `placed` and its own
    `failure_reason`: `sim.episodes.episode.Episode.place_record`; None when the lift failed,
    as nothing was placed), and with `timings=True` the wall-clock `timings_ms` (off by default:
    wall-clock times differ between runs, and same-seed rollouts are identical).

    ## Starting State
    The object at a random position and yaw on the table, the robot's base at a random pose
    facing it, the head aimed at it: the scene of the episode seed (below), built by
    `posegrasp.world.scene.build_scene`, seen under the env's scene shifts (`shifts`), which
    change lights, textures, colours, visual-only distractors and the head camera's pose in its
    link, never the layout or the physics. The place task's goal is drawn from the episode
    seed on a stream of its own.

    ## Seeding
    Every episode plays one *episode seed*, reported as ``info["episode_seed"]`` by `reset` and
    `step`; the scene depends on the object, that seed, the tier and the config alone.

    * ``reset(seed=s)`` plays episode seed ``s`` and reseeds `np_random` with ``s``.
    * A later ``reset()`` without a seed plays the seed after the previous episode's:
      ``s + 1``, ``s + 2``, ... (modulo 2**32).
    * The first ``reset()`` of an env that was never given a seed draws its episode seed from
      `np_random` (unseeded: fresh entropy); the later ones count on from it.
    * ``options={"episode_seed": e}`` plays episode seed ``e`` whatever the seed (which still
      reseeds `np_random`); the resets after it count on from ``e``.
    * With ``object=None`` the class is drawn from `np_random`, after it is reseeded.

    Hence `sim.evaluate`'s episode ``i`` of object ``X`` (``--objects X --seed-start S``, which
    plays scene seed ``S + i``) is ``GraspEvalEnv(object=X).reset(seed=S + i)``, or the
    ``i``-th reset after ``reset(seed=S)``, of an env with the same tier and the default
    config and resolution; the env's ``success`` and ``T_C_O_true`` then match the report's for
    the same pose. In a vector env, sub-env ``k`` of ``reset(seed=s)`` starts at ``s + k`` and
    counts on by one, so sub-envs replay each other's seeds: give each its episodes with
    ``options={"episode_seed": e}`` to cover seeds without repeats.

    ## Episode End
    Terminated after the one step. An action that is not a finite pose with a unit quaternion,
    or whose position lies beyond `posegrasp.core.contract.MAX_POSE_DISTANCE` (10 m) of the
    camera (poses are in metres), ends the episode as a failed grasp with
    `failure_reason = "invalid_action"` (and the problem in `info["error"]`), as does such a
    neighbour pose; an action of the wrong structure, shape or type (a string, NaN or 2 as
    `has_estimate`, complex numbers) raises `InvalidArgumentError` (a ValueError). A bad `seed`
    (not in 0..2**32-1) or bad `options` make `reset` raise before it builds anything; the env
    then has no episode and `step` raises `StateError` until a reset succeeds (through
    `gymnasium.make` too: its env checker then checks that later reset instead).

    ## Arguments
    `object`: a class name, built-in or user object (`python -m sim.add_object`), or None to
    draw one of the built-in ones per episode; `width`, `height`: head camera
    resolution; `render_mode`: None or "rgb_array" (external camera view); `config`: an
    `EpisodeConfig`; `timings`: add per-stage wall-clock timings to `info`; `tier`: the scene
    tier (`posegrasp.world.tiers.TIERS`, default ``isolated``, or the config's); `obs_mode`:
    ``rgb`` or ``rgbd`` (`sim.episodes.episode.OBS_MODES`; default ``rgb``, or the config's);
    `sensor`: the head camera's sensor model (`posegrasp.world.sensors.SENSOR_NAMES`; default
    ``ideal``, or the config's). The env and `sim.evaluate` observe alike when both name the same
    sensor. `task`: ``lift`` or ``place`` (`posegrasp.world.goals.TASKS`; default ``lift``, or
    the config's); `shifts`: the scene shifts, a spec of `posegrasp.world.shifts.parse_shifts`
    (``"camera:3,light_colour"``, ``"all:3"``) or `Shift` values (default none, or the
    config's); both as `sim.evaluate`'s ``--task`` and ``--shift``.

    ## Version History
    * v0: first version; the depth observation (``obs_mode``), the sensor models (``sensor``),
      the episode-seed mapping above, `pose_correct` and the units check on positions were
      added without a version change (the defaults observe and act as before).
    * v0: the place task (``task``, `info["place"]`) and the scene shifts (``shifts``) were
      added without a version change (the defaults lift and observe as before).
    """

    # gymnasium declares metadata an instance attribute with a class default; so does this.
    metadata: dict[str, Any] = {"render_modes": ["rgb_array"], "render_fps": 10}  # noqa: RUF012

    def __init__(
        self,
        object: str | None = None,
        width: int = 640,
        height: int = 480,
        render_mode: str | None = None,
        config: EpisodeConfig | None = None,
        timings: bool = False,
        tier: str | None = None,
        obs_mode: str | None = None,
        sensor: str | None = None,
        task: str | None = None,
        shifts: str | Sequence[Shift] | None = None,
    ) -> None:
        #: The class indices of the observation and of neighbours: the built-in objects, then
        #: the user objects installed when the env was made (`object_names()`).
        self.classes = object_names()
        if object is not None and object not in self.classes:
            raise UnknownNameError("object", object, self.classes)
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise UnknownNameError("render mode", str(render_mode), self.metadata["render_modes"])
        base = config or EpisodeConfig()
        self.config = env_config(base, width, height, tier, obs_mode, sensor, task, shifts)
        self.tier, self.obs_mode = self.config.tier, self.config.obs_mode
        #: What the robot does with the object (``lift`` or ``place``) and the scene shifts.
        self.task, self.shifts = self.config.task, self.config.scene.shifts
        setup_rendering()
        self.object = object
        self.timings = timings
        self.render_mode = render_mode
        observations: dict[str, spaces.Space] = {
            "rgb": spaces.Box(0, 255, (height, width, 3), np.uint8),
            "K": spaces.Box(-np.inf, np.inf, (3, 3), np.float64),
            "T_world_cam": spaces.Box(-np.inf, np.inf, (4, 4), np.float64),
            "object": spaces.Discrete(len(self.classes)),
            "table_top_z": spaces.Box(-np.inf, np.inf, (1,), np.float64),
        }
        if self.obs_mode == "rgbd":
            observations["depth"] = spaces.Box(0.0, np.inf, (height, width), np.float32)
        self.observation_space = spaces.Dict(observations)
        m = MAX_NEIGHBOURS
        neighbours = {
            "count": spaces.Discrete(m + 1),
            "object": spaces.MultiDiscrete([len(self.classes)] * m),
            "position": spaces.Box(-10.0, 10.0, (m, 3), np.float64),
            "quaternion": spaces.Box(-1.0, 1.0, (m, 4), np.float64),
        }
        self.action_space = spaces.Dict(
            {
                "has_estimate": spaces.Discrete(2),
                "position": spaces.Box(-10.0, 10.0, (3,), np.float64),
                "quaternion": spaces.Box(-1.0, 1.0, (4,), np.float64),
                "neighbours": spaces.Dict(neighbours),
            }
        )
        self._episode: Episode | None = None
        self._obs: dict[str, Any] = {}
        self._external: CameraRenderer | None = None
        self._next_seed: int | None = None

    def _close_episode(self) -> None:
        if self._episode is not None:
            self._episode.close()
            self._episode = None
        if self._external is not None:
            self._external.close()
            self._external = None

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        """Start an episode (which episode seed it plays: the class docstring's Seeding).

        Args:
            seed: the episode seed, and the seed of `np_random`; None for the seed after the
                previous episode's.
            options: may set `object` (a class name) and `episode_seed` (overrides `seed` as the
                episode seed).

        Returns:
            The observation and ``{"object": class, "episode_seed": seed}``; an estimator's
            `Observation` is ``Observation.from_env(obs, info)``.

        Raises:
            InvalidArgumentError, UnknownNameError: a bad seed or options, found before any state
                changes; a later `step` then asks for a reset.
        """
        return self._reset(seed, options)

    def _reset(
        self, seed: int | None, options: dict[str, Any] | None
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        self._close_episode()
        if seed is not None:
            check_seed(seed, "seed")
        if options is not None and not isinstance(options, dict):
            raise InvalidArgumentError(f"options must be a dict or None, got {type(options)}")
        options = options or {}
        if unknown := sorted(map(str, set(options) - set(OPTIONS))):
            raise InvalidArgumentError(f"unknown options {unknown}; valid: {', '.join(OPTIONS)}")
        obj = options.get("object", self.object)
        if obj is not None and (not isinstance(obj, str) or obj not in self.classes):
            raise UnknownNameError("object", str(obj), self.classes)
        if "episode_seed" in options:
            check_seed(options["episode_seed"], "episode_seed")
        super().reset(seed=seed)
        if obj is None:
            obj = OBJECT_NAMES[int(self.np_random.integers(len(OBJECT_NAMES)))]
        if "episode_seed" in options:
            ep_seed = int(options["episode_seed"])
        elif seed is not None:
            ep_seed = int(seed)
        elif self._next_seed is not None:
            ep_seed = self._next_seed
        else:
            ep_seed = int(self.np_random.integers(2**31 - 1))
        self._next_seed = (ep_seed + 1) % SEED_LIMIT
        self._episode = Episode(obj, ep_seed, self.config)
        o = self._episode.observe()
        obs = {
            "rgb": o.rgb,
            "K": o.K,
            "T_world_cam": o.T_world_cam,
            "object": self.classes.index(obj),
            "table_top_z": np.array([o.table_top_z], np.float64),
        }
        if o.depth is not None:
            obs["depth"] = o.depth
        self._obs = obs
        return self._copy_obs(), {"object": obj, "episode_seed": ep_seed}

    def _copy_obs(self) -> dict[str, Any]:
        return {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in self._obs.items()}

    def _parse_action(
        self, action: dict[str, Any]
    ) -> tuple[np.ndarray | None, list[tuple[str, np.ndarray]], str | None]:
        if not isinstance(action, dict) or not (
            set(ACTION_KEYS) <= set(action) <= {*ACTION_KEYS, "neighbours"}
        ):
            raise InvalidArgumentError(
                "action must be a dict with keys has_estimate, position, quaternion and optionally "
                "neighbours; see GraspEvalEnv.action_space or sim.env.pose_action()"
            )
        has = _count(action["has_estimate"], 1, "has_estimate")
        pos = _real(action["position"], (3,), "position")
        quat = _real(action["quaternion"], (4,), "quaternion")
        told = self._parse_neighbours(action.get("neighbours"))
        if isinstance(told, str):
            return None, [], told
        if has == 0:
            return None, told, None
        T, error = _pose(pos, quat, "action")
        return T, told, error

    def _parse_neighbours(self, value: Any) -> list[tuple[str, np.ndarray]] | str:
        """The neighbour poses of an action, or why they are invalid (a failed grasp)."""
        if value is None:
            return []
        keys = {"count", "object", "position", "quaternion"}
        if not isinstance(value, dict) or set(value) != keys:
            raise InvalidArgumentError(f"action neighbours must be a dict with keys {sorted(keys)}")
        m = MAX_NEIGHBOURS
        n = _count(value["count"], m, "neighbours count")
        ids = np.asarray(value["object"])
        if ids.dtype.kind not in "iu" or ids.shape != (m,):
            raise InvalidArgumentError(
                f"action neighbours object must be integers of shape ({m},), got {ids.dtype} "
                f"{ids.shape}"
            )
        pos = _real(value["position"], (m, 3), "neighbours position")
        quat = _real(value["quaternion"], (m, 4), "neighbours quaternion")
        out = []
        for i in range(n):
            if not 0 <= ids[i] < len(self.classes):
                raise InvalidArgumentError(
                    f"action neighbours object {int(ids[i])} is not a class index "
                    f"0..{len(self.classes) - 1}"
                )
            T, error = _pose(pos[i], quat[i], f"neighbour {i}")
            if T is None:
                return error or f"neighbour {i} has no pose"
            out.append((self.classes[int(ids[i])], T))
        return out

    def step(self, action: dict[str, Any]):
        """Grasp on the estimated pose; the episode ends.

        Raises:
            InvalidArgumentError: an action of the wrong structure, shape or type.
            StateError: no episode (no reset yet, or the last one was refused).
        """
        if self._episode is None:
            raise StateError("no episode to act on: call reset() first")
        T, neighbours, error = self._parse_action(action)
        if error is None:
            error = check_estimate(T, neighbours)[2]  # e.g. a position in millimetres
        ep = self._episode
        if error is not None:
            result = ep.reject(error, "env", T)
        else:
            result = ep.act(T, "env", neighbours=neighbours)
        info = {
            "success": result.success,
            "failure_reason": result.failure_reason,
            "pose_error": result.pose_error,
            "pose_correct": result.pose_correct,
            "lift_height": result.lift_height,
            "object": result.object,
            "episode_seed": result.seed,
            "tier": result.tier,
        }
        if self.task == "place":
            info["place"] = result.place
        if self.timings:
            info["timings_ms"] = result.timings_ms
        if error is not None:
            info["error"] = error
        return self._copy_obs(), float(result.success), True, False, info

    def render(self) -> np.ndarray | None:
        """External-camera view of the current state (render_mode "rgb_array")."""
        if self.render_mode != "rgb_array" or self._episode is None:
            return None
        if self._external is None:
            self._external = external_renderer(self._episode.scene.model)
        return self._external.rgb(self._episode.scene.data, EXTERNAL_CAMERA)

    def close(self) -> None:
        self._close_episode()
