"""The estimator registry of the experiment: the oracles and the hybrid estimators by name.

Real estimators implement `posegrasp.core.contract.PoseEstimator`. The oracles are the experiment's
own instruments, not estimators a robot could run: they implement `PrivilegedEstimator` and are
handed the true pose by the episode, which no other estimator ever sees.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from posegrasp.core.contract import Estimate, Observation, PoseEstimator
from posegrasp.core.errors import InvalidArgumentError, UnknownNameError
from sim.pose_noise import PoseNoise, perturb_pose

#: Other objects' poses: (class, T_C_N) pairs in the camera frame.
Neighbours = Sequence[tuple[str, np.ndarray]]


@runtime_checkable
class PrivilegedEstimator(Protocol):
    """An instrument of the experiment that is given the true pose (the oracles)."""

    name: str

    def estimate_from_truth(
        self, obs: Observation, T_C_O_true: np.ndarray, neighbours: Neighbours
    ) -> Estimate:
        """The estimate to grasp on, derived from the true pose T_C_O_true (4, 4) and the other
        objects' true poses `neighbours`, (class, T_C_N) pairs in the camera frame."""
        ...


class OracleEstimator:
    """The true pose and the true neighbours."""

    name = "oracle"

    def estimate_from_truth(
        self, obs: Observation, T_C_O_true: np.ndarray, neighbours: Neighbours
    ) -> Estimate:
        return Estimate(np.array(T_C_O_true, dtype=float), tuple(neighbours))


class NoisyOracleEstimator:
    """The true pose with seeded, controlled errors (see `PoseNoise`), and the true neighbours.

    The errors of an episode come from its seed alone: at every noise level a seed draws the same
    standard-normal numbers, scaled by the level's sigmas (common random numbers), so runs at
    different levels are paired.
    """

    name = "noisy-oracle"

    def __init__(self, noise: PoseNoise | None = None) -> None:
        self.noise = noise or PoseNoise(
            ray=0.01, lateral=0.005, inplane=np.deg2rad(3), outplane=np.deg2rad(3)
        )

    def estimate_from_truth(
        self, obs: Observation, T_C_O_true: np.ndarray, neighbours: Neighbours
    ) -> Estimate:
        T = perturb_pose(np.array(T_C_O_true, dtype=float), self.noise, self.noise.rng(obs.seed))
        return Estimate(T, tuple(neighbours))


def _hybrid() -> PoseEstimator:
    """The hybrid estimator with the shipped weights: the detector, `ours` and its expert
    fine-tuned on the hard tier (per detection, the pose whose silhouette agrees better with the
    detected mask wins). Imports torch: call before rendering."""
    from perception import HybridPoseEstimator

    return HybridPoseEstimator.from_weights().as_episode_estimator()


def _hybrid_table() -> PoseEstimator:
    """The hybrid estimator, its poses then put onto the known table (`perception.support`)."""
    from perception import HybridPoseEstimator

    return HybridPoseEstimator.from_weights().as_episode_estimator(support=True)


def _hybrid_paper() -> PoseEstimator:
    """The hybrid estimator with the `paper` variant's nets (the published 4D output, trained on
    the paper's protocol) in place of ours."""
    from perception import HybridPoseEstimator
    from perception.hybrid import PAPER_POSENET

    est = HybridPoseEstimator.from_weights(posenet_path=PAPER_POSENET, expert_paths=())
    return est.as_episode_estimator(name="hybrid-paper")


def _hybrid_refine() -> PoseEstimator:
    """The hybrid estimator, its pose then refined by render-and-compare against the detected
    mask and the image (`perception.refine`)."""
    from perception import HybridPoseEstimator

    return HybridPoseEstimator.from_weights().as_episode_estimator(refine=True)


#: Estimator factories by name.
ESTIMATORS: dict[str, Callable[[], PoseEstimator | PrivilegedEstimator]] = {
    "oracle": OracleEstimator,
    "noisy-oracle": NoisyOracleEstimator,
    "hybrid": _hybrid,
    "hybrid-table": _hybrid_table,
    "hybrid-paper": _hybrid_paper,
    "hybrid-refine": _hybrid_refine,
}


#: What the CLIs use unless told otherwise.
DEFAULT_ESTIMATOR = "hybrid"


def make_estimator(
    name: str, noise: PoseNoise | None = None
) -> PoseEstimator | PrivilegedEstimator:
    """The estimator called name; `noise` sets the errors of ``noisy-oracle``.

    Raises:
        UnknownNameError: name is not registered.
        InvalidArgumentError: `noise` given for another estimator.
    """
    if name not in ESTIMATORS:
        raise UnknownNameError("estimator", name, ESTIMATORS)
    if noise is not None:
        if name != "noisy-oracle":
            raise InvalidArgumentError(f"--noise applies to noisy-oracle only, not to {name}")
        return NoisyOracleEstimator(noise)
    return ESTIMATORS[name]()
