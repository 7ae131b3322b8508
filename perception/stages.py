"""The stages `perception.global_pose.GlobalPoseEstimator` is composed of (docs/DESIGN.md §7).

Each stage is a small object with one job, handed typed data and handing typed data on:

- detection (`TargetDetection`): an `Observation` -> `Detections` (the requested object's best
  detection, every detection, the neighbours' poses, the description so far);
- mask (`RedrawnMask`): a detection -> the same detection with its mask redrawn by the mask net;
- hypothesis sources: the nets' pose (`NetsPose`), the viewpoint codebook (`CodebookHypotheses`:
  a detection -> `CodebookMatch` -> template indices) and, with gravity, the codebook's templates
  that could rest (`RestingHypotheses`); each gives `perception.verification.Hypothesis` starts;
- refinement and scoring: `perception.verification` (a `Verification` of `VerifyJob` runs) and
  `perception.scoring`;
- priors: gravity and the in-plane range (`perception.priors`, applied while ranking), and,
  on the winner, the table (`TablePrior`) or the support of the neighbours (`NeighbourSupport`),
  each a pose -> `Placed`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from perception.codebook import (
    Codebook,
    CodebookCache,
    MaskView,
    TemplateMatch,
    frame_mask,
    hypothesis_pose,
    occluded_views,
    resting_templates,
    rotation_cosines,
    top_hypotheses,
)
from perception.detector import Detection
from perception.hybrid import HybridPoseEstimator, PoseDetection, detect_target, occluder_of
from perception.mask_net import MaskRefiner
from perception.parallel import Executor
from perception.priors import Gravity
from perception.support import refine_on_support, resting_surface_z
from perception.verification import Hypothesis, Verified
from posegrasp.core.contract import Observation
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.transforms import quat_to_mat
from posegrasp.world.objects import OBJECT_NAMES, ObjectModel, load_object

#: A detection of the requested object or a neighbour: with the nets' pose, or without (an
#: object the nets were not trained on).
AnyDetection = PoseDetection | Detection

#: Neighbours are verified until this many give a confident resting pose
#: (`SupportConfig.neighbours`).
SUPPORT_ENOUGH = 2

#: A neighbour whose mask comes this close to the target's [px] touches it.
NEIGHBOUR_TOUCH_PX = 6


# --- detection and mask ----------------------------------------------------------------------


@dataclass(frozen=True)
class DetectionConfig:
    """The detection stage.

    Attributes:
        target_score: the detector score a detection of the requested object needs, in [0, 1]
            (the other detections, the planner's obstacles and the occluders, need the
            detector's own threshold); a partly hidden object often scores lower, and the
            verification reports how well the pose fits (None: the detector's threshold).
        mask_net: the requested object's mask is redrawn at the image's full resolution by the
            mask net (`perception.mask_net`) before its hypotheses and refinement: the
            detector's coarse mask loses thin parts and puts the outline a pixel or two off,
            which the fit turns into distance along the viewing ray (False: the detector's).
    """

    target_score: float | None = 0.3
    mask_net: bool = True

    def __post_init__(self) -> None:
        if self.target_score is not None and not 0 <= self.target_score <= 1:
            raise InvalidArgumentError(
                f"DetectionConfig.target_score must be in [0, 1] or None, got {self.target_score}"
            )
        if not isinstance(self.mask_net, bool):
            raise InvalidArgumentError(
                f"DetectionConfig.mask_net must be True or False, got {self.mask_net!r}"
            )


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


class TargetDetection:
    """The detection stage: detect once and split the detections around the requested object.

    A user object the detector was fine-tuned on is taken from every detection, without the
    nets' pose; the six built-in objects come with the nets' poses (the neighbours' from the
    main net alone).

    Args:
        hybrid: the detector and the pose nets.
        config: the stage's settings.
    """

    def __init__(self, hybrid: HybridPoseEstimator, config: DetectionConfig) -> None:
        self.hybrid, self.config = hybrid, config

    def __call__(self, obs: Observation) -> Detections:
        """The observation's detections (see the class)."""
        if obs.object not in OBJECT_NAMES and obs.object in self.hybrid.detector.cfg.classes:
            return self._user_object(obs)
        found = detect_target(self.hybrid, obs, self.config.target_score, others_experts=False)
        return Detections(found.best, [*found.found, *found.others], found.neighbours, found.info)

    def _user_object(self, obs: Observation) -> Detections:
        """A user object's best detection, the built-in neighbours' poses."""
        dets, poses, timings = self.hybrid.detections_and_poses(obs.rgb, obs.K)
        mine = [d for d in dets if d.name == obs.object]
        best = max(mine, key=lambda d: d.score) if mine else None
        info: dict = {"detected": best is not None, "timings_ms": dict(timings)}
        if best is not None:
            info |= {"class": best.name, "score": best.score, "detections": len(dets)}
        neighbours = tuple((p.name, p.T_C_O.copy()) for p in poses)
        return Detections(best, list(dets), neighbours, info)


class RedrawnMask:
    """The mask stage: a detection of one of the built-in objects with its mask redrawn by the
    mask net; any other detection as it is.

    Args:
        masks: the mask net.
    """

    def __init__(self, masks: MaskRefiner) -> None:
        self.masks = masks

    def __call__(self, det: AnyDetection, rgb: np.ndarray) -> AnyDetection:
        """`det` with its mask redrawn from the image `rgb` (H, W, 3) uint8."""
        if det.name not in OBJECT_NAMES:
            return det
        return replace(det, mask=self.masks.refine(rgb, det.mask, det.name))


# --- hypothesis sources ----------------------------------------------------------------------


class NetsPose:
    """The hypothesis source of the nets: the detection's own pose, when it has one."""

    @staticmethod
    def hypotheses(det: AnyDetection) -> list[Hypothesis]:
        """[the nets' pose] for a detection with one, else []."""
        return [Hypothesis(det.T_C_O, "nets")] if isinstance(det, PoseDetection) else []


@dataclass(frozen=True)
class CodebookConfig:
    """The codebook's hypotheses.

    Attributes:
        views: viewpoints of the codebook's sphere grid, >= 1.
        inplane: in-plane turns per viewpoint, >= 1.
        hypotheses: codebook hypotheses refined per detection (the nets' pose comes on top),
            >= 1.
        min_angle_deg: hypotheses differ by at least this rotation [deg], in [0, 180).
        occluded_grow: where another detection or the image's edge touches the mask, the
            codebook also matches it framed by boxes this many times its own (each in (1, 4]),
            grown towards where it is cut off, with the occluder's pixels and those beyond the
            image not held against a template (empty: the mask's own box only).
        resting_hypotheses: with gravity, this many more hypotheses, the best among the
            templates that give a pose near resting (and `min_angle_deg` from the others):
            under occlusion a partial mask fits many poses an object could not rest in (0:
            none).
    """

    views: int = 1000
    inplane: int = 24
    hypotheses: int = 12
    min_angle_deg: float = 15.0
    occluded_grow: tuple[float, ...] = (1.3, 1.6)
    resting_hypotheses: int = 0

    def __post_init__(self) -> None:
        for key in ("views", "inplane", "hypotheses"):
            if getattr(self, key) < 1:
                raise InvalidArgumentError(
                    f"CodebookConfig.{key} must be >= 1, got {getattr(self, key)}"
                )
        if not 0 <= self.min_angle_deg < 180:
            raise InvalidArgumentError(
                f"CodebookConfig.min_angle_deg must be in [0, 180), got {self.min_angle_deg}"
            )
        if not all(1 < g <= 4 for g in self.occluded_grow):
            raise InvalidArgumentError(
                f"CodebookConfig.occluded_grow factors must lie in (1, 4], got {self.occluded_grow}"
            )
        if self.resting_hypotheses < 0:
            raise InvalidArgumentError(
                f"CodebookConfig.resting_hypotheses must be >= 0, got {self.resting_hypotheses}"
            )


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


class CodebookHypotheses:
    """The codebook's hypothesis source: a detection's mask matched against the silhouettes of
    its object over the whole rotation group, the best templates `min_angle_deg` apart.

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

    def best(self, match: CodebookMatch, skip: int, count: int, taken: list[int]) -> list[int]:
        """The templates ranked `skip` to `skip + count` by score after the suppression, those
        in `taken` left out."""
        found = top_hypotheses(
            match.scores, match.book.rotations, skip + count, self.config.min_angle_deg
        )
        return [i for i in found[skip:] if i not in taken]


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


@dataclass(frozen=True)
class SecondLookConfig:
    """The second look: when the best verified pose scores below `below`, more hypotheses are
    refined and verified with the first ones, and the choice is made again; an ambiguous
    partial mask gets more starts, a clear one does not pay for them.

    Attributes:
        hypotheses: more codebook hypotheses, the next best, >= 0.
        resting: with gravity, more resting hypotheses (`RestingHypotheses`), >= 0.
        below: the verification score under which it runs.
    """

    hypotheses: int = 12
    resting: int = 12
    below: float = 1.15

    def __post_init__(self) -> None:
        for key in ("hypotheses", "resting"):
            if getattr(self, key) < 0:
                raise InvalidArgumentError(
                    f"SecondLookConfig.{key} must be >= 0, got {getattr(self, key)}"
                )
        if not math.isfinite(self.below):
            raise InvalidArgumentError(f"SecondLookConfig.below must be finite, got {self.below}")


# --- priors on the winner --------------------------------------------------------------------


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
class TableConfig:
    """The table prior.

    Attributes:
        max_tilt_deg: a pose within this rotation [deg] of a resting pose is snapped onto it and
            slid onto the table; one further keeps its rotation and translation; in (0, 180).
    """

    max_tilt_deg: float = 10.0

    def __post_init__(self) -> None:
        if not 0 < self.max_tilt_deg < 180:
            raise InvalidArgumentError(
                f"TableConfig.max_tilt_deg must be in (0, 180), got {self.max_tilt_deg}"
            )


class TablePrior:
    """The table prior: when the observation carries the table's height
    (`Observation.table_top_z`, a prior of the scene, not of the image), the pose's rotation is
    snapped to the nearest resting pose and its origin slid along its camera ray until the
    object rests on the table (`perception.support.refine_on_support`, as `hybrid-table`); the
    silhouette does not fix the distance of a half-hidden object, the table does.

    Args:
        config: the prior's settings.
    """

    def __init__(self, config: TableConfig) -> None:
        self.config = config

    def place(self, T_C_O: np.ndarray, obs: Observation, model: ObjectModel) -> Placed | None:
        """T_C_O (4, 4) on the table; None without the table's height or resting poses."""
        if obs.table_top_z is None or not model.resting_poses:
            return None
        ref = refine_on_support(
            T_C_O, obs.T_world_cam, model, obs.table_top_z, self.config.max_tilt_deg
        )
        return Placed(ref.T_C_O, ref.description())


@dataclass(frozen=True)
class SupportConfig:
    """The support of the neighbours.

    Attributes:
        neighbours: up to this many other detections of other classes (those touching the
            target's mask first, then the nearest) are verified in turn, until
            `SUPPORT_ENOUGH` of them give a confident resting pose; >= 1.
        score: the verification score a neighbour's pose needs to count.
        tolerance_m: how far [m] the target's own resting surface may lie from its
            neighbours' before its pose is moved; >= 0.
        below: the support is sought only when the target's verification score is below this.
    """

    neighbours: int = 3
    score: float = 1.15
    tolerance_m: float = 0.012
    below: float = 1.15

    def __post_init__(self) -> None:
        if self.neighbours < 1:
            raise InvalidArgumentError(
                f"SupportConfig.neighbours must be >= 1, got {self.neighbours}"
            )
        if not math.isfinite(self.score):
            raise InvalidArgumentError(f"SupportConfig.score must be finite, got {self.score}")
        if not (math.isfinite(self.tolerance_m) and self.tolerance_m >= 0):
            raise InvalidArgumentError(
                f"SupportConfig.tolerance_m must be finite and >= 0 [m], got {self.tolerance_m}"
            )
        if not math.isfinite(self.below):
            raise InvalidArgumentError(f"SupportConfig.below must be finite, got {self.below}")


class NeighbourSupport:
    """The support of the neighbours: the visible part of a half-hidden object does not fix its
    distance along the viewing ray; the objects around it, which rest on the same table, do.
    When the target's winner scores below `SupportConfig.below` and is within the gravity
    prior's tilt of resting, the neighbouring detections are verified, and the median height
    of the surface the confident ones rest on is the target's support: when the target's own
    pose puts it more than `SupportConfig.tolerance_m` above or below it, the pose is slid along
    its camera ray onto it (`perception.support.refine_on_support`).

    Args:
        config: the prior's settings.
        tilt_deg: the gravity prior's tilt [deg] (`perception.priors.GravityConfig.tilt_deg`).
    """

    def __init__(self, config: SupportConfig, tilt_deg: float) -> None:
        self.config, self.tilt_deg = config, tilt_deg

    def wanted(self, win: Verified, model: ObjectModel) -> bool:
        """Whether the target's winner asks for support: unsure, yet near resting."""
        return bool(
            model.resting_poses and win.score < self.config.below and win.tilt <= self.tilt_deg
        )

    def place(
        self,
        T_C_O: np.ndarray,
        target: AnyDetection,
        every: list[AnyDetection],
        obs: Observation,
        verify: Callable[[AnyDetection], Verified | None],
    ) -> Placed:
        """T_C_O (4, 4) of `target` slid onto its neighbours' surface when they give one it is
        off from; `verify` gives a neighbour's best verified pose (None: none)."""
        model = load_object(target.name)
        support_z, seen = self.surface(target, every, obs, verify)
        own_z = resting_surface_z(T_C_O, obs.T_world_cam, model)
        described: dict = {"source": "neighbours", "neighbours": seen, "own_z": own_z}
        T = T_C_O
        if support_z is not None and abs(own_z - support_z) > self.config.tolerance_m:
            ref = refine_on_support(T, obs.T_world_cam, model, support_z, self.tilt_deg)
            T, described = ref.T_C_O, described | ref.description()
        return Placed(T, described | {"surface_z": support_z})

    def surface(
        self,
        target: AnyDetection,
        every: list[AnyDetection],
        obs: Observation,
        verify: Callable[[AnyDetection], Verified | None],
    ) -> tuple[float | None, list[dict]]:
        """The height of the surface the target's neighbours rest on, or None when none gives
        a confident resting pose, and what each verified neighbour gave (``class``, ``score``,
        ``tilt_deg``, ``surface_z``, ``counted``)."""
        grown = ndimage.binary_dilation(target.mask, iterations=NEIGHBOUR_TOUCH_PX)
        centre = np.argwhere(target.mask).mean(0)

        def order(d: AnyDetection) -> tuple[int, float]:
            pixels = np.argwhere(d.mask)
            far = float(np.hypot(*(pixels.mean(0) - centre))) if len(pixels) else math.inf
            return -int((grown & d.mask).sum()), far

        candidates = [
            d for d in every if d.name != target.name and load_object(d.name).resting_poses
        ]
        heights: list[float] = []
        seen: list[dict] = []
        for found in sorted(candidates, key=order)[: self.config.neighbours]:
            win = verify(found)
            if win is None:
                continue
            z = resting_surface_z(win.T_C_O, obs.T_world_cam, load_object(found.name))
            score, tilt = float(win.score), win.tilt
            counted = bool(score >= self.config.score and tilt <= self.tilt_deg)
            seen.append(
                {
                    "class": found.name,
                    "score": score,
                    "tilt_deg": tilt,
                    "surface_z": z,
                    "counted": counted,
                }
            )
            if counted:
                heights.append(z)
                if len(heights) >= SUPPORT_ENOUGH:
                    break
        return (float(np.median(heights)) if heights else None), seen
