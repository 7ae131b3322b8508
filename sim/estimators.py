"""Pose estimators an episode can ask: the interface, the oracle and the noisy oracle.

An estimator maps an `Observation` (head-camera RGB, K, T_world_cam, the requested class) to the
requested object's pose in the camera frame, `T_C_O` (4x4, OpenCV camera frame, metres), or None
when it has no estimate. The oracles read the privileged ground truth the episode attaches to the
observation; real estimators must ignore it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from sim.errors import InvalidArgumentError, UnknownNameError


@dataclass
class Observation:
    """What an estimator sees.

    Attributes:
        rgb: head-camera image, shape (H, W, 3), uint8.
        K: intrinsics, shape (3, 3) [px].
        T_world_cam: camera pose in the world (OpenCV convention), shape (4, 4).
        object: requested object class.
        seed: the episode's seed (estimators that randomise seed themselves from it).
        truth_T_C_O: privileged ground truth for the oracles; never part of the gym observation.
    """

    rgb: np.ndarray
    K: np.ndarray
    T_world_cam: np.ndarray
    object: str
    seed: int
    truth_T_C_O: np.ndarray | None = field(default=None, repr=False)


class PoseEstimator(Protocol):
    """Anything with `estimate(obs) -> T_C_O or None`."""

    name: str

    def estimate(self, obs: Observation) -> np.ndarray | None:
        """The requested object's pose in the camera frame, or None."""
        ...


def axis_angle_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix of `angle` [rad] about unit `axis` (Rodrigues)."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    Kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * Kx + (1 - np.cos(angle)) * Kx @ Kx


@dataclass(frozen=True)
class PoseNoise:
    """Controlled pose errors in the camera frame, magnitudes in [m] and [rad].

    Attributes:
        ray: translation along the camera ray through the object origin.
        lateral: translation perpendicular to that ray, in a random direction.
        inplane: rotation about the camera ray (in-plane).
        outplane: rotation about a random axis perpendicular to the ray (out-of-plane).
        mode: "gaussian" draws each error from N(0, magnitude^2); "fixed" applies exactly the
            magnitude with a random sign (ray, in-plane) or direction (lateral, out-of-plane).
    """

    ray: float = 0.0
    lateral: float = 0.0
    inplane: float = 0.0
    outplane: float = 0.0
    mode: str = "gaussian"

    def __post_init__(self) -> None:
        if self.mode not in ("gaussian", "fixed"):
            raise UnknownNameError("noise mode", self.mode, ("gaussian", "fixed"))
        vals = (self.ray, self.lateral, self.inplane, self.outplane)
        if not all(np.isfinite(v) and v >= 0 for v in vals):
            raise InvalidArgumentError("noise magnitudes must be finite and non-negative")


def perturb_pose(T_C_O: np.ndarray, noise: PoseNoise, rng: np.random.Generator) -> np.ndarray:
    """T_C_O with the errors of `noise` applied (rotations about the object's origin)."""
    T = np.array(T_C_O, dtype=float)
    t = T[:3, 3]
    u = t / np.linalg.norm(t)
    # A random unit vector perpendicular to the ray.
    w = np.cross(u, rng.normal(size=3))
    w /= np.linalg.norm(w)
    if noise.mode == "gaussian":
        e_ray, e_lat = rng.normal(0, noise.ray), rng.normal(0, noise.lateral)
        e_in, e_out = rng.normal(0, noise.inplane), rng.normal(0, noise.outplane)
    else:
        sign = rng.choice([-1.0, 1.0], size=2)
        e_ray, e_lat = sign[0] * noise.ray, noise.lateral
        e_in, e_out = sign[1] * noise.inplane, noise.outplane
    w2 = np.cross(u, w)  # a second perpendicular direction for the out-of-plane axis
    out = T.copy()
    out[:3, 3] = t + e_ray * u + e_lat * w
    R = axis_angle_matrix(u, e_in) @ axis_angle_matrix(w2, e_out) @ T[:3, :3]
    out[:3, :3] = R
    return out


class OracleEstimator:
    """The true pose."""

    name = "oracle"

    def estimate(self, obs: Observation) -> np.ndarray | None:
        if obs.truth_T_C_O is None:
            raise InvalidArgumentError("the oracle needs the observation's ground truth")
        return obs.truth_T_C_O.copy()


class NoisyOracleEstimator:
    """The true pose with seeded, controlled errors (see `PoseNoise`)."""

    name = "noisy-oracle"

    def __init__(self, noise: PoseNoise | None = None) -> None:
        self.noise = noise or PoseNoise(
            ray=0.01, lateral=0.005, inplane=np.deg2rad(3), outplane=np.deg2rad(3)
        )

    def estimate(self, obs: Observation) -> np.ndarray | None:
        truth = OracleEstimator().estimate(obs)
        rng = np.random.default_rng([obs.seed, 7919])
        return perturb_pose(truth, self.noise, rng)


def _hybrid() -> PoseEstimator:
    """The hybrid estimator with the shipped weights (imports torch: call before rendering)."""
    from perception.estimator import HybridPoseEstimator

    return HybridPoseEstimator.from_weights().as_episode_estimator()


#: Estimator factories by name.
ESTIMATORS: dict[str, Callable[[], PoseEstimator]] = {
    "oracle": OracleEstimator,
    "noisy-oracle": NoisyOracleEstimator,
    "hybrid": _hybrid,
}


def make_estimator(name: str) -> PoseEstimator:
    """The estimator called name.

    Raises:
        UnknownNameError: name is not registered.
    """
    if name not in ESTIMATORS:
        raise UnknownNameError("estimator", name, ESTIMATORS)
    return ESTIMATORS[name]()
