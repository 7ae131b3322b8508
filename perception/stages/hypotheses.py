"""The hypothesis stage: where a detection's first poses come from (the nets' pose, the
viewpoint codebook's best templates and, with gravity, the templates that could rest), with the
detection's priors."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from perception.codebook import (
    CodebookCache,
    TemplateMatch,
    frame_mask,
    occluded_views,
    resting_templates,
    rotation_cosines,
    top_hypotheses,
)
from perception.hybrid import PoseDetection
from perception.parallel import Executor
from perception.priors import Gravity, GravityConfig, InplaneConfig, Plausibility
from perception.stages.config import CodebookConfig, GlobalConfig
from perception.stages.work import AnyDetection, CodebookMatch, Kit, Work
from perception.verification import Hypothesis
from posegrasp.core.transforms import quat_to_mat
from posegrasp.world.objects import load_object


class NetsPose:
    """The hypothesis source of the nets: the detection's own pose, when it has one."""

    @staticmethod
    def hypotheses(det: AnyDetection) -> list[Hypothesis]:
        """[the nets' pose] for a detection with one, else []."""
        return [Hypothesis(det.T_C_O, "nets")] if isinstance(det, PoseDetection) else []


class CodebookHypotheses:
    """The codebook's hypothesis source: a detection's mask matched against the silhouettes of
    its object over the whole rotation group (`CodebookMatch.best` ranks the templates).

    Args:
        codebooks: where the codebooks come from.
        config: the source's settings.
    """

    def __init__(self, codebooks: CodebookCache, config: CodebookConfig) -> None:
        self.codebooks, self.config = codebooks, config
        self._jobs: dict[str, TemplateMatch] = {}  # by object: one job per codebook

    def match(
        self,
        det: AnyDetection,
        occluder: np.ndarray | None,
        K: np.ndarray,
        executor: Executor,
    ) -> CodebookMatch | None:
        """`det`'s mask, and its framings as if it went on behind `occluder` or the image's
        edge, matched against its object's codebook; None for an empty mask."""
        view = frame_mask(det.mask)
        if view is None:
            return None
        if det.name not in self._jobs:
            self._jobs[det.name] = TemplateMatch(self.codebooks.get(det.name))
        job = self._jobs[det.name]
        views = occluded_views(det.mask, occluder, view, self.config.occluded_grow) or [view]
        scores = job.scores([(v.bits, v.hidden) for v in views], executor)
        return CodebookMatch(job.book, views, scores, K)


class RestingHypotheses:
    """The resting poses' hypothesis source: the best codebook templates that give a pose near
    resting (with gravity).

    Args:
        min_angle_deg: each at least this rotation [deg] from the others and those taken.
    """

    def __init__(self, min_angle_deg: float) -> None:
        self.min_angle_deg = min_angle_deg

    def best(
        self, match: CodebookMatch, gravity: Gravity, count: int, taken: list[int]
    ) -> list[int]:
        """The best `count` templates (every framing's in turn) within the gravity prior's tilt
        of resting, each `min_angle_deg` from the others and from those in `taken`."""
        book, n = match.book, len(match.book.rotations)
        model = gravity.model
        ups = np.array([quat_to_mat(np.asarray(q, float))[2] for q in model.resting_poses.values()])
        keep = np.concatenate(
            [
                resting_templates(book, v, match.K, gravity.R_W_C[2], ups, gravity.config.tilt_deg)
                for v in match.views
            ]
        )
        if not keep.any():
            return []
        want = count + len(taken)
        found = top_hypotheses(
            np.where(keep, match.scores, -np.inf), book.rotations, want, self.min_angle_deg
        )
        R = book.rotations
        found = [i for i in found if keep[i]]
        if not found or not taken:
            return found[:count]
        near = rotation_cosines(R[np.array(found) % n], R[np.array(taken) % n])
        new = np.array(found)[~(near > math.cos(math.radians(self.min_angle_deg))).any(1)]
        return [int(i) for i in new[:count]]


class Hypotheses:
    """The hypothesis stage: the target's priors, its mask matched against its codebook, and
    its first hypotheses (the nets' pose, the best codebook templates, with gravity those that
    could rest).

    Args:
        codebook: the codebook's settings.
        codebooks: where the codebooks come from.
        gravity: the gravity prior (None: none).
        inplane: the in-plane prior (None: none).
        executor: where the matching of an image runs (chosen once per image).
    """

    name = "hypotheses"

    def __init__(
        self,
        codebook: CodebookConfig,
        codebooks: CodebookCache,
        gravity: GravityConfig | None,
        inplane: InplaneConfig | None,
        executor: Callable[[], Executor],
    ) -> None:
        self.config, self.gravity, self.inplane = codebook, gravity, inplane
        self.codebook = CodebookHypotheses(codebooks, codebook)
        self.resting = RestingHypotheses(codebook.min_angle_deg)
        self.executor = executor

    @classmethod
    def build(cls, config: GlobalConfig, kit: Kit) -> Hypotheses:
        """The stage of `config.codebook` with its priors."""
        return cls(config.codebook, kit.codebooks, config.gravity, config.inplane, kit.executor)

    @staticmethod
    def wanted(work: Work) -> bool:
        """Whether there is a target, not verified yet."""
        return work.target is not None and work.verification is None

    def __call__(self, work: Work) -> Work:
        """`work` with where its batches run, its target's priors, codebook match and first
        hypotheses."""
        det, book = work.target, self.config
        assert det is not None
        executor = self.executor()
        priors = self.priors(det.name, work.R_W_C)
        match = self.codebook.match(det, work.occluder, work.K, executor)
        first = NetsPose.hypotheses(det)
        taken: list[int] = []
        if match is not None:
            taken = match.best(0, book.hypotheses, [], book.min_angle_deg)
            if priors.gravity is not None and book.resting_hypotheses:
                taken += self.resting.best(match, priors.gravity, book.resting_hypotheses, taken)
            first += match.hypotheses(taken)
        return work.given(
            executor=executor,
            priors=priors,
            match=match,
            taken=tuple(taken),
            hypotheses=tuple(first),
        )

    def priors(self, name: str, R_W_C: np.ndarray | None) -> Plausibility:
        """The priors of a detection of `name`: gravity with the camera's rotation in the world
        `R_W_C` (3, 3) and the object's resting poses, the in-plane range."""
        model = load_object(name)
        gravity = None
        if self.gravity is not None and R_W_C is not None and model.resting_poses:
            gravity = Gravity(R_W_C, model, self.gravity)
        inplane = None if self.inplane is None else self.inplane.max_deg
        return Plausibility(gravity, inplane)
