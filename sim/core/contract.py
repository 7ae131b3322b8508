"""The contract between the experiment and any pose estimator.

Both sides import this module and nothing else of each other: the experiment (`sim.episode`,
`sim.env`) hands an estimator an `Observation`, the estimator answers with the requested object's
pose in the camera frame. An observation holds only what a real robot has: the head-camera image,
its intrinsics and pose, the requested class and the known table height. No ground truth is
part of it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np


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


class PoseEstimator(Protocol):
    """Anything with a ``name`` and ``estimate(obs) -> T_C_O or None``.

    ``T_C_O`` is the requested object's pose in the camera frame: (4, 4), OpenCV camera
    convention, metres. An estimator may also expose, after each call, ``last_info`` (a
    JSON-serialisable dict describing the estimate, which episodes record) and
    ``last_neighbours``: the other objects it saw, as (class, T_C_N) pairs in the same frame;
    the robot keeps its gripper clear of them and of nothing else.
    """

    name: str

    def estimate(self, obs: Observation) -> np.ndarray | None:
        """The requested object's pose in the camera frame, or None."""
        ...
