"""The contract between the experiment and any pose estimator.

Both sides import this module and nothing else of each other: the experiment (`sim.episode`,
`sim.env`) hands an estimator an `Observation`, the estimator answers with an `Estimate`: the
requested object's pose in the camera frame, the other objects it saw and a description. An
observation holds only what a real robot has: the head-camera image, its intrinsics and pose,
the requested class and the known table height. No ground truth is part of it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

#: Version of this contract: raised when `Observation`, `Estimate` or `PoseEstimator` change in a
#: way an estimator must follow. 1: ``estimate(obs) -> Estimate``.
CONTRACT_VERSION = 1


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
    """

    rgb: np.ndarray
    K: np.ndarray
    T_world_cam: np.ndarray
    object: str
    seed: int
    table_top_z: float | None = None


@dataclass(frozen=True)
class Estimate:
    """What an estimator answers.

    Attributes:
        T_C_O: the requested object's pose in the camera frame, shape (4, 4), OpenCV camera
            convention, metres; None when it has no estimate (the episode fails as
            ``no_estimate``).
        neighbours: the other objects it saw, as (class, T_C_N) pairs in the same frame; the
            robot keeps its gripper clear of them and of nothing else.
        info: a JSON-serialisable description of the estimate (detection score, timings, ...),
            recorded in the episode as ``estimate_info``.
    """

    T_C_O: np.ndarray | None
    neighbours: tuple[tuple[str, np.ndarray], ...] = ()
    info: dict[str, Any] = field(default_factory=dict)


class PoseEstimator(Protocol):
    """Anything with a ``name`` and ``estimate(obs) -> Estimate``: the whole contract of version
    `CONTRACT_VERSION`. Nothing else is read from an estimator."""

    name: str

    def estimate(self, obs: Observation) -> Estimate:
        """The requested object's pose, the neighbours seen and a description."""
        ...
