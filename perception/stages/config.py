"""The settings of the estimator's stages and their composition, `GlobalConfig`: one part per
stage, None where an optional stage is left out."""

from __future__ import annotations

import math
import typing
from dataclasses import dataclass, field, fields

from perception.priors import GravityConfig, InplaneConfig
from perception.scoring import ScoringConfig
from perception.verification import RefinementConfig
from posegrasp.core.errors import InvalidArgumentError


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
        shortlist: with a detector of any object (`perception.detector_net.ANY_OBJECT`), the
            detections whose masks the requested object's codebook matches best, this many,
            are each verified as the target, and the best verified is taken (`AnyObjectDetection`).
        table_tolerance_m: with a detector of any object and an observation that gives the
            table's height, a shortlisted detection whose verified pose rests more than this [m]
            above or below the table is taken only when none rests on it: a silhouette says
            nothing of size, so another object, nearer or farther, can fit the mesh as well,
            but not at the height of the table it stands on (None: the table is not used).
        joined: with a detector of any object, up to this many detections whose masks touch
            are also a candidate together, their masks joined: a detector of any object
            parts an object of several colours along its colours, so the whole of it may be
            no single detection (1: each detection alone).
        sure: with a detector of any object, the shortlist is verified in its order and the
            first candidate whose best pose scores at least this (and rests on the table, where
            the observation gives it) is taken without verifying the rest (None: every
            shortlisted candidate is verified).
    """

    target_score: float | None = 0.3
    mask_net: bool = True
    shortlist: int = 3
    table_tolerance_m: float | None = 0.03
    joined: int = 3
    sure: float | None = None

    def __post_init__(self) -> None:
        if (
            not isinstance(self.shortlist, int)
            or isinstance(self.shortlist, bool)
            or self.shortlist < 1
        ):
            raise InvalidArgumentError(
                f"DetectionConfig.shortlist must be >= 1, got {self.shortlist}"
            )
        if not isinstance(self.joined, int) or isinstance(self.joined, bool) or self.joined < 1:
            raise InvalidArgumentError(f"DetectionConfig.joined must be >= 1, got {self.joined}")
        if self.table_tolerance_m is not None and not (
            math.isfinite(self.table_tolerance_m) and self.table_tolerance_m > 0
        ):
            raise InvalidArgumentError(
                "DetectionConfig.table_tolerance_m must be positive [m] or None, got "
                f"{self.table_tolerance_m}"
            )
        if self.sure is not None and (
            isinstance(self.sure, bool) or not (math.isfinite(self.sure) and self.sure > 0)
        ):
            raise InvalidArgumentError(
                f"DetectionConfig.sure must be a positive score or None, got {self.sure}"
            )
        if self.target_score is not None and not 0 <= self.target_score <= 1:
            raise InvalidArgumentError(
                f"DetectionConfig.target_score must be in [0, 1] or None, got {self.target_score}"
            )
        if not isinstance(self.mask_net, bool):
            raise InvalidArgumentError(
                f"DetectionConfig.mask_net must be True or False, got {self.mask_net!r}"
            )


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


@dataclass(frozen=True)
class GlobalConfig:
    """The composition of `GlobalPoseEstimator`: each stage's settings, None where an optional
    stage is left out.

    Attributes:
        detection: which detections count; whether the target's mask is redrawn.
        codebook: the codebook's hypotheses.
        refinement: how each hypothesis is refined.
        scoring: the verification score's weights.
        gravity: the gravity prior (None: none, as for images without gravity).
        inplane: the in-plane prior (None: none).
        second_look: the second look at more hypotheses (None: none).
        support: the neighbours' support of an unsure pose (None: none; needs `gravity`).
        table: the table prior, used where the observation gives the table's height (None:
            none); it replaces the neighbours' support there.
        processes: the processes that share the codebook matching and each batch of starts:
            1, or 2 (a worker process, `perception.parallel.TwoProcesses`, started in the
            second estimate, used while this process computes on more than one thread).
    """

    detection: DetectionConfig = field(default_factory=DetectionConfig)
    codebook: CodebookConfig = field(default_factory=CodebookConfig)
    refinement: RefinementConfig = field(default_factory=RefinementConfig)
    scoring: ScoringConfig = field(default_factory=ScoringConfig)
    gravity: GravityConfig | None = field(default_factory=GravityConfig)
    inplane: InplaneConfig | None = None
    second_look: SecondLookConfig | None = field(default_factory=SecondLookConfig)
    support: SupportConfig | None = field(default_factory=SupportConfig)
    table: TableConfig | None = None
    processes: int = 2

    def __post_init__(self) -> None:
        optional = {"gravity", "inplane", "second_look", "support", "table"}
        for f in fields(self):
            value = getattr(self, f.name)
            kinds = _allowed(f.name)
            if not (isinstance(value, kinds) or (value is None and f.name in optional)):
                allowed = kinds[0].__name__ + (" or None" if f.name in optional else "")
                raise InvalidArgumentError(
                    f"GlobalConfig.{f.name} must be a {allowed}, got {type(value).__name__}"
                )
        if self.support is not None and self.gravity is None:
            raise InvalidArgumentError(
                "GlobalConfig.support needs GlobalConfig.gravity (the neighbours' surface is "
                "found from their resting poses); set support=None without gravity"
            )
        if self.processes not in (1, 2):
            raise InvalidArgumentError(
                f"GlobalConfig.processes must be 1 or 2, got {self.processes}"
            )


def _allowed(name: str) -> tuple[type, ...]:
    """The types `GlobalConfig`'s field `name` takes, None's left out (from its annotation)."""
    hint = typing.get_type_hints(GlobalConfig)[name]
    return tuple(t for t in typing.get_args(hint) or (hint,) if t is not type(None))
