"""The contract between the experiment and any pose estimator.

Both sides import this module and nothing else of each other: the experiment
(`sim.episodes.episode`, `sim.env`) hands an estimator an `Observation`, the estimator answers with
an `Estimate`: the requested object's pose in the camera frame, the other objects it saw and a
description. An observation holds only what a real robot has: the head-camera image (and, when the
episode asks for it, its depth image), its intrinsics and pose, the requested class and the known
table height. No ground truth is part of it.

What makes a pose valid (`pose_problem`) is part of the contract: a pose that is not one ends
the episode as a failed grasp (``invalid_action``), so an estimator can check its answers with
the same function.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from posegrasp.core.errors import InvalidArgumentError

#: Version of this contract: raised when `Observation`, `Estimate` or `PoseEstimator` change in a
#: way an estimator must follow. 1: ``estimate(obs) -> Estimate``. 2: `Observation` gains the
#: optional ``depth`` (None unless the episode's ``obs_mode`` is ``"rgbd"``); nothing else
#: changed, so an estimator written for version 1 keeps working unchanged. 3: `Estimate` gains the
#: optional ``confidence`` (how sure the estimator is, higher is surer; None when it does not
#: say); estimators of versions 1 and 2 keep working unchanged.
CONTRACT_VERSION = 3

#: Largest deviation ``max |R^T R - I|`` of a pose's rotation block from orthonormality.
ROTATION_TOL = 1e-6
#: Farthest a pose's origin may be from the camera [m]: the whole scene (room included) lies
#: within a few metres of the head camera, so a pose beyond this is in other units.
MAX_POSE_DISTANCE = 10.0


@dataclass
class Observation:
    """What an estimator sees.

    Attributes:
        rgb: head-camera image, shape (H, W, 3), uint8.
        K: intrinsics, shape (3, 3) [px].
        T_world_cam: camera pose in the world (OpenCV convention), shape (4, 4).
        object: requested object class.
        seed: the episode's seed (estimators that randomise seed themselves from it).
        table_top_z: height of the table top the object rests on, in the world [m] (known scene
            geometry), or None when unknown.
        depth: depth image of the same camera at the same instant, shape (H, W), float32 [m]:
            the z coordinate along the optical axis in the OpenCV camera frame of the surface
            seen at each pixel (not the distance along the ray; BOP's convention, in metres), so
            pixel (u, v) with depth z back-projects to ``z * K^-1 (u, v, 1)``. None unless the
            episode renders it (``EpisodeConfig.obs_mode == "rgbd"``).
    """

    rgb: np.ndarray
    K: np.ndarray
    T_world_cam: np.ndarray
    object: str
    seed: int
    table_top_z: float | None = None
    depth: np.ndarray | None = None

    @classmethod
    def from_env(cls, obs: Mapping[str, Any], info: Mapping[str, Any]) -> Observation:
        """The observation an estimator gets from a ``GraspEval-v0`` reset: exactly what
        `sim.evaluate` and `sim.episodes.episode.play_episode` hand it for the same object and
        episode seed, so that an estimate through the env is the same to the bit.

        Args:
            obs: the env's observation: ``rgb`` (H, W, 3) uint8, ``K`` (3, 3) [px],
                ``T_world_cam`` (4, 4), ``table_top_z`` shape (1,) [m] and, with
                ``obs_mode="rgbd"``, ``depth`` (H, W) float32 [m]; ``object`` (a class index)
                is not read.
            info: the info of the same reset (or step), which names the ``object`` and its
                ``episode_seed``.

        Returns:
            The observation, ``table_top_z`` as a float and ``depth`` None without one.

        Raises:
            InvalidArgumentError: obs or info lacks a key it needs, or ``table_top_z`` is not
                one real number.
        """
        for what, given, keys in (
            ("observation", obs, ("rgb", "K", "T_world_cam", "table_top_z")),
            ("info", info, ("object", "episode_seed")),
        ):
            if missing := [k for k in keys if k not in given]:
                raise InvalidArgumentError(
                    f"env {what} lacks {', '.join(missing)}; it needs {', '.join(keys)} "
                    "(pass the obs and info of a GraspEval-v0 reset)"
                )
        z = np.asarray(obs["table_top_z"])
        if z.size != 1 or z.dtype.kind not in "iuf":
            raise InvalidArgumentError(
                f"env observation table_top_z must be one real number [m], got {z.dtype} {z.shape}"
            )
        return cls(
            obs["rgb"],
            obs["K"],
            obs["T_world_cam"],
            str(info["object"]),
            int(info["episode_seed"]),
            table_top_z=float(z.item()),
            depth=obs.get("depth"),
        )


@dataclass(frozen=True)
class Estimate:
    """What an estimator answers.

    Attributes:
        T_C_O: the requested object's pose in the camera frame, shape (4, 4), OpenCV camera
            convention, metres; None when it has no estimate (the episode fails as
            ``no_estimate``). A pose that is not valid (`pose_problem`) fails the episode as
            ``invalid_action``.
        neighbours: the other objects it saw, as (class, T_C_N) pairs in the same frame; the
            robot keeps its gripper clear of them and of nothing else.
        info: a JSON-serialisable description of the estimate (detection score, timings, ...),
            recorded in the episode as ``estimate_info``.
        confidence: how sure the estimator is of ``T_C_O``, any finite real scale on which
            higher is surer (a verification score, votes, a fitness), or None when it does not
            say (contract version 3). A robot may attempt only the grasps above a threshold:
            the reports' risk-coverage curve (`sim.evaluation.stats.risk_coverage`) says what that
            buys.
    """

    T_C_O: np.ndarray | None
    neighbours: tuple[tuple[str, np.ndarray], ...] = ()
    info: dict[str, Any] = field(default_factory=dict)
    confidence: float | None = None


class PoseEstimator(Protocol):
    """Anything with a ``name`` and ``estimate(obs) -> Estimate``: the whole contract of version
    `CONTRACT_VERSION`. Nothing else is read from an estimator."""

    name: str

    def estimate(self, obs: Observation) -> Estimate:
        """The requested object's pose, the neighbours seen and a description."""
        ...


def confidence_problem(confidence: object) -> str | None:
    """What keeps an estimate's ``confidence`` from being valid, or None when it is: None or one
    finite real number.

    Args:
        confidence: the estimate's confidence.

    Returns:
        One line naming the problem, or None.
    """
    if confidence is None:
        return None
    if isinstance(confidence, bool) or not isinstance(confidence, (int, float, np.number)):
        return f"confidence must be a real number or None, got {type(confidence).__name__}"
    if not np.isfinite(float(confidence)):
        return f"confidence must be finite, got {float(confidence)}"
    return None


def as_pose_array(T: object, what: str = "pose") -> np.ndarray:
    """``T`` as a float64 (4, 4) array, whatever its values.

    Args:
        T: a candidate pose.
        what: how messages name it.

    Raises:
        InvalidArgumentError: T is not a real-valued array of shape (4, 4).
    """
    try:
        arr = np.asarray(T)
    except (TypeError, ValueError):  # ragged nested sequences
        arr = None
    if arr is None or arr.dtype.kind not in "iuf" or arr.shape != (4, 4):
        got = type(T).__name__ if arr is None else f"{arr.dtype} array of shape {arr.shape}"
        raise InvalidArgumentError(f"{what} must be a real 4x4 array (a pose, metres), got {got}")
    return arr.astype(np.float64)


def transform_problem(T: np.ndarray) -> str | None:
    """What keeps a (4, 4) array from being a rigid transform, or None when it is one: finite
    entries, last row (0, 0, 0, 1) and a rotation block R with ``max |R^T R - I| <=
    ROTATION_TOL`` and det R = +1.

    Args:
        T: the transform, shape (4, 4) (`as_pose_array`).

    Returns:
        One line naming the problem and its measure, or None.
    """
    T = np.asarray(T, np.float64)
    if not np.all(np.isfinite(T)):
        return "contains NaN or infinite values"
    if np.abs(T[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-9:
        return f"last row is {np.round(T[3], 6).tolist()}, not [0, 0, 0, 1]"
    R = T[:3, :3]
    deviation = float(np.abs(R.T @ R - np.eye(3)).max())
    if deviation > ROTATION_TOL:
        return (
            f"rotation is not orthonormal (shear/scale): max |R^T R - I| = {deviation:.2e} > "
            f"{ROTATION_TOL:g}"
        )
    if np.linalg.det(R) < 0.0:
        return f"rotation is a reflection (det R = {np.linalg.det(R):.3f}), not a rotation"
    return None


def pose_problem(T: np.ndarray) -> str | None:
    """What keeps a (4, 4) pose from being a valid estimate, or None when it is one: a rigid
    transform (`transform_problem`) whose origin is at most `MAX_POSE_DISTANCE` from the camera
    (poses are in metres).

    Args:
        T: the pose, shape (4, 4) (`as_pose_array`), camera frame [m].

    Returns:
        One line naming the problem and its measure, or None.
    """
    problem = transform_problem(T)
    if problem is not None:
        return problem
    distance = float(np.linalg.norm(np.asarray(T, np.float64)[:3, 3]))
    if distance > MAX_POSE_DISTANCE:
        return (
            f"position is {distance:.4g} m from the camera, beyond {MAX_POSE_DISTANCE:g} m: poses "
            "are in metres; millimetres?"
        )
    return None
