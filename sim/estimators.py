"""The estimator registry of the experiment: the oracles and the learned estimators by name
(`perception.estimators`).

Real estimators implement `posegrasp.core.contract.PoseEstimator`. The oracles are the experiment's
own instruments, not estimators a robot could run: they implement `PrivilegedEstimator` and are
handed the true pose by the episode, which no other estimator ever sees.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from perception.estimators import LEARNED_ESTIMATORS
from posegrasp.core.contract import Estimate, Observation, PoseEstimator
from posegrasp.core.errors import InvalidArgumentError, UnknownNameError
from posegrasp.core.validate import arg, check_choice
from sim.pose_noise import NOISE_FORMAT, PoseNoise, parse_noise, perturb_pose

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


#: Estimator factories by name.
ESTIMATORS: dict[str, Callable[[], PoseEstimator | PrivilegedEstimator]] = {
    "oracle": OracleEstimator,
    "noisy-oracle": NoisyOracleEstimator,
    **LEARNED_ESTIMATORS,
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


def check_noise(spec: str) -> str:
    """A ``--noise`` value (`sim.pose_noise.NOISE_FORMAT`), returned as given once it parses.

    Raises:
        InvalidArgumentError: not of the format.
    """
    parse_noise(spec)
    return spec


def add_estimator_arguments(
    parser: argparse.ArgumentParser,
    default: str | None = DEFAULT_ESTIMATOR,
    noise: bool = True,
    purpose: str | None = None,
    also: Sequence[str] = (),
) -> None:
    """Add ``--estimator NAME`` (one of `ESTIMATORS`) and, with `noise`, ``--noise SIGMAS``
    (noisy-oracle's errors), both checked while parsing; `make_estimator` refuses ``--noise``
    for another estimator.

    Args:
        parser: the command line.
        default: the estimator unless told otherwise (None: none).
        noise: add ``--noise``.
        purpose: what the estimator is for, shown before the list of names.
        also: further names the command accepts beside `ESTIMATORS`.
    """
    names = [*ESTIMATORS, *also]
    lead = f"{purpose}; " if purpose else ""
    tail = "" if default is None else f" (default {default})"
    parser.add_argument(
        "--estimator",
        default=default,
        type=arg(check_choice, names, "estimator"),
        metavar="NAME",
        help=f"{lead}one of: {', '.join(names)}{tail}",
    )
    if noise:
        parser.add_argument(
            "--noise",
            default=None,
            type=arg(check_noise),
            metavar="SIGMAS",
            help=f"noisy-oracle's Gaussian sigmas: {NOISE_FORMAT}",
        )
