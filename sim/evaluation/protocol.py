"""What defines an evaluation's results: the `Protocol`, handed whole to the harness, the journal
and the report.

An evaluation plays, for each object X of the protocol and each i below its episode count, the
episode of scene seed ``seed_start + i``, every one with the same episode settings
(`Protocol.episode_config`). What runs the episodes (workers, backend, journal) is not part of
it: it changes no result.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from grasping.candidates import CANDIDATE_SOURCES
from grasping.execute import ExecutionConfig
from grasping.place import UNNAMED_BELIEF, PlaceConfig
from grasping.planner import PlannerConfig
from posegrasp.core.validate import check_choice
from posegrasp.world import constants as C
from posegrasp.world.scene import SceneConfig
from posegrasp.world.shifts import Shift, canonical
from posegrasp.world.tiers import DEFAULT_TIER, check_tier
from sim.episodes.episode import EpisodeConfig, execution_settings


@dataclass(frozen=True)
class Protocol:
    """One evaluation's episodes and the settings every one of them runs with.

    Attributes:
        objects: the target classes, built-in or user objects; a list is kept as a tuple.
        episodes: episodes per object; episode i of object X plays scene seed
            ``seed_start + i``.
        seed_start: the first scene seed (default `posegrasp.world.constants.EVAL_SEED_BASE`:
            held-out scenes, never rendered as training data).
        tier: the scene tier (`posegrasp.world.tiers.TIERS`).
        noise: the errors of ``noisy-oracle`` (`sim.episodes.pose_noise.NOISE_FORMAT`), None for the
            estimator's own.
        margin: measure each successful grasp's friction margin
            (`grasping.execute.ExecutionConfig.measure_margin`).
        obs_mode: what the estimator sees (`sim.episodes.episode.OBS_MODES`): ``rgbd`` adds depth.
        pool: the classes the tier's distractors are drawn from, built-in or user objects
            (`posegrasp.world.scene.SceneConfig.distractor_pool`); empty for the built-in ones.
        candidates: where the built-in objects' grasp candidates come from
            (`grasping.candidates.CANDIDATE_SOURCES`).
        sensor: the head camera's sensor model the estimator observes through
            (`sim.episodes.episode.EpisodeConfig.sensor`; ``ideal``: the rendered images).
        task: what the robot does with the object (`posegrasp.world.goals.TASKS`): ``lift``
            it, or lift it and ``place`` it at a goal drawn from the seed.
        shifts: the scene shifts every episode is seen under (`posegrasp.world.shifts`:
            purely visual; none: the room as it is).
        belief: on the place task, where the robot believes the object lies in its hand
            (`grasping.place.BELIEFS`; ``truth`` is privileged, for measuring the place itself).

    Raises:
        UnknownNameError: a tier, observation mode, candidate source, sensor, task or scene
            shift that does not exist, listing the valid ones.
    """

    objects: tuple[str, ...]
    episodes: int
    seed_start: int = C.EVAL_SEED_BASE
    tier: str = DEFAULT_TIER
    noise: str | None = None
    margin: bool = False
    obs_mode: str = "rgb"
    pool: tuple[str, ...] = ()
    candidates: str = "designed"
    sensor: str = "ideal"
    task: str = "lift"
    shifts: tuple[Shift, ...] = ()
    belief: str = PlaceConfig.belief

    def __post_init__(self) -> None:
        object.__setattr__(self, "objects", tuple(self.objects))
        object.__setattr__(self, "pool", tuple(self.pool))
        object.__setattr__(self, "shifts", canonical(self.shifts))
        check_tier(self.tier)
        check_choice(self.candidates, CANDIDATE_SOURCES, "candidate source")
        self.episode_config()  # checks the observation mode and the sensor as an episode does

    @property
    def total(self) -> int:
        """Episodes of the whole evaluation (objects x episodes)."""
        return len(self.objects) * self.episodes

    def seeds(self) -> Iterator[tuple[str, int]]:
        """(object, scene seed) of every episode, in run order: object by object, seeds up."""
        for obj in self.objects:
            for i in range(self.episodes):
                yield obj, self.seed_start + i

    def episode_config(self) -> EpisodeConfig:
        """The settings every episode of the protocol plays with
        (`sim.episodes.episode.EpisodeConfig`)."""
        return EpisodeConfig(
            scene=SceneConfig(distractor_pool=self.pool, shifts=self.shifts),
            planner=PlannerConfig(candidates=self.candidates),
            tier=self.tier,
            execution=ExecutionConfig(measure_margin=self.margin),
            obs_mode=self.obs_mode,
            sensor=self.sensor,
            task=self.task,
            place=PlaceConfig(belief=self.belief),
        )

    def recorded_apart(self) -> dict[str, Any]:
        """The entries a record holds only away from their defaults, so that records written
        before they existed read the same: ``distractor_pool`` (a pool of the caller's),
        ``candidates`` (other than ``designed``), ``sensor`` (other than ``ideal``), ``task``
        (other than ``lift``), ``shifts`` (any, as ``NAME:LEVEL`` items) and, on the place task,
        ``belief`` (other than ``estimate``, what every place record before ``predicted``
        was played with)."""
        out: dict[str, Any] = {"distractor_pool": list(self.pool)} if self.pool else {}
        if self.candidates != "designed":
            out["candidates"] = self.candidates
        if self.sensor != "ideal":
            out["sensor"] = self.sensor
        if self.task == "place" and self.belief != UNNAMED_BELIEF:
            out["belief"] = self.belief
        if self.task != "lift":
            out["task"] = self.task
        if self.shifts:
            out["shifts"] = [str(s) for s in self.shifts]
        return out


def run_protocol(protocol: Protocol, estimator: str) -> dict[str, Any]:
    """The protocol with the estimator's label (`sim.evaluation.harness.estimator_label`) and
    the execution settings (`sim.episodes.episode.execution_settings`), as JSON: what a journal's
    header holds, so a resumed run must have the same."""
    return {
        "objects": list(protocol.objects),
        "episodes_per_object": protocol.episodes,
        "estimator": estimator,
        "seed_start": protocol.seed_start,
        "tier": protocol.tier,
        "noise": protocol.noise,
        "margin": protocol.margin,
        "obs_mode": protocol.obs_mode,
        "execution": execution_settings(),
        **protocol.recorded_apart(),
    }
