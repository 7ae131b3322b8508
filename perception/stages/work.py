"""What the stages share: one image's work as it goes through them, and the stage interface.

A stage is a small object with one job (`Stage`): it says whether it has anything to do for
the work so far (`Stage.wanted`) and returns the work with its own part filled in
(`Stage.__call__`); it never changes what an earlier stage gave. An estimator is a declared
list of stages, each built from its part of the config and the loaded pieces (`Kit`), run in
order by `run_stages`, which times each stage it enters.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np

from perception.codebook import (
    Codebook,
    CodebookCache,
    MaskView,
    hypothesis_pose,
    top_hypotheses,
)
from perception.detector import Detection
from perception.hybrid import HybridPoseEstimator, PoseDetection, occluder_of
from perception.mask_net import MaskRefiner
from perception.parallel import Executor
from perception.parts import ConvexParts
from perception.priors import Plausibility
from perception.verification import Hypothesis, Verification, Verified
from posegrasp.core.contract import Observation

#: A detection of the requested object or a neighbour: with the nets' pose, or without (an
#: object the nets were not trained on).
AnyDetection = PoseDetection | Detection


@dataclass(frozen=True)
class Detections:
    """One image's detections around the requested object.

    Attributes:
        target: the requested object's best detection, or None.
        every: every detection of the image (the target's among them).
        neighbours: the other objects' poses, (class, T_C_N (4, 4)) pairs.
        info: the estimate's description so far (``detected``, ``timings_ms``, ...).
    """

    target: AnyDetection | None
    every: list[AnyDetection]
    neighbours: tuple[tuple[str, np.ndarray], ...]
    info: dict

    @property
    def occluder(self) -> np.ndarray | None:
        """Where another detection may hide the target: the union of every other mask."""
        return occluder_of(self.every, self.target)


@dataclass(frozen=True)
class CodebookMatch:
    """A detected mask matched against an object's codebook.

    Attributes:
        book: the codebook.
        views: the mask's framings (its own box first, then the grown ones).
        scores: each framing's IoUs with every template, framing-major, (framings x N,).
        K: the intrinsics (3, 3) [px].
    """

    book: Codebook
    views: list[MaskView]
    scores: np.ndarray
    K: np.ndarray

    def hypotheses(self, indices: list[int]) -> list[Hypothesis]:
        """The pose each index of `scores` gives (its template framed by its framing)."""
        n = len(self.book.rotations)
        return [
            Hypothesis(hypothesis_pose(self.book, i % n, self.views[i // n], self.K), "codebook")
            for i in indices
        ]

    def best(self, skip: int, count: int, taken: list[int], min_angle_deg: float) -> list[int]:
        """The templates ranked `skip` to `skip + count` by score after the suppression
        (`min_angle_deg` [deg] apart), those in `taken` left out."""
        found = top_hypotheses(self.scores, self.book.rotations, skip + count, min_angle_deg)
        return [i for i in found[skip:] if i not in taken]


@dataclass(frozen=True)
class Placed:
    """A pose a prior put somewhere, and what it did (``info["support"]``).

    Attributes:
        T_C_O: the pose (4, 4) [m].
        description: what the prior did and saw.
    """

    T_C_O: np.ndarray
    description: dict


@dataclass(frozen=True)
class Work:
    """One image's work, as far as the stages have taken it.

    Attributes:
        K: the intrinsics (3, 3) [px].
        rgb: the image (H, W, 3) uint8.
        R_W_C: the camera's rotation in the world (3, 3), for gravity (None: unknown).
        obs: the observation (None where a detection is verified on its own).
        second_look: whether the second look may run (False for the neighbours).
        found: the detection stage's detections (None: not run yet).
        target: the detection being estimated (None: none).
        occluder: where other detections may hide the target (None: nowhere).
        executor: where the batches of this image run (None: not chosen yet).
        priors: the target's priors.
        match: the target's mask matched against its codebook (None: not matched).
        taken: the codebook templates made hypotheses so far (indices into `match.scores`).
        hypotheses: the first hypotheses, in their order of refinement.
        verification: the hypotheses' refinement and scoring so far.
        ranked: the verified poses, best first.
        looked_again: whether the second look ran.
        placed: where a prior on the winner put it (None: nowhere).
    """

    K: np.ndarray
    rgb: np.ndarray
    R_W_C: np.ndarray | None
    obs: Observation | None = None
    second_look: bool = True
    found: Detections | None = None
    target: AnyDetection | None = None
    occluder: np.ndarray | None = None
    executor: Executor | None = None
    priors: Plausibility = field(default_factory=Plausibility)
    match: CodebookMatch | None = None
    taken: tuple[int, ...] = ()
    hypotheses: tuple[Hypothesis, ...] = ()
    verification: Verification | None = None
    ranked: tuple[Verified, ...] = ()
    looked_again: bool = False
    placed: Placed | None = None

    @classmethod
    def of(cls, obs: Observation) -> Work:
        """The work on one observation, before any stage."""
        R_W_C = np.asarray(obs.T_world_cam, float)[:3, :3]
        return cls(obs.K, obs.rgb, R_W_C, obs)

    @classmethod
    def on(
        cls,
        det: AnyDetection,
        K: np.ndarray,
        rgb: np.ndarray,
        occluder: np.ndarray | None,
        R_W_C: np.ndarray | None = None,
        second_look: bool = True,
    ) -> Work:
        """The work on one detection (its mask as it is), from the hypotheses on."""
        return cls(K, rgb, R_W_C, second_look=second_look, target=det, occluder=occluder)

    def given(self, **parts: object) -> Work:
        """This work with a stage's parts filled in."""
        return replace(self, **parts)  # type: ignore[arg-type]

    @property
    def winner(self) -> Verified | None:
        """The best verified pose (None: none)."""
        return self.ranked[0] if self.ranked else None


class Stage(Protocol):
    """One stage of an estimator.

    Attributes:
        name: its name, the key of its time in ``info["timings_ms"]``.
    """

    name: str

    def wanted(self, work: Work) -> bool:
        """Whether the stage has anything to do for `work`."""
        ...

    def __call__(self, work: Work) -> Work:
        """`work` with this stage's part filled in."""
        ...


class StageKind(Protocol):
    """A stage's class: it builds the stage from an estimator's config and its loaded pieces."""

    def build(self, config: Any, kit: Kit) -> Stage | None:
        """The stage `config` asks for (None: left out)."""
        ...


@dataclass
class Kit:
    """The loaded pieces the stages are built from, shared by every composition of one
    estimator (nothing here is loaded by a stage).

    Attributes:
        hybrid: the detector and the pose nets.
        masks: the mask net (None: not loaded, for compositions that do not redraw masks).
        codebooks: the codebooks of the composition's grid.
        parts: the objects' convex pieces.
        executor: where the batches of the next image run (chosen once per image).
        as_target: a detection within an image taken through the stages as the target would
            be, up to its verification (without the second look): the work they leave (a
            neighbour's best verified pose is its winner).
    """

    hybrid: HybridPoseEstimator
    masks: MaskRefiner | None
    codebooks: CodebookCache
    parts: ConvexParts
    executor: Callable[[], Executor]
    as_target: Callable[[AnyDetection, Work], Work]


def run_stages(stages: Sequence[Stage], work: Work, times: dict[str, float]) -> Work:
    """`work` through each stage in order, those with nothing to do left out, until detection
    leaves no target; each stage entered is timed into `times` [ms] under its name."""
    for stage in stages:
        if work.target is None and work.found is not None:
            break
        if not stage.wanted(work):
            continue
        t0 = time.perf_counter()
        work = stage(work)
        times[stage.name] = (time.perf_counter() - t0) * 1000
    return work
