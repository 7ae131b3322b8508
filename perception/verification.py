"""One detection's pose hypotheses refined, scored and ranked (docs/DESIGN.md §7).

Each hypothesis is a start: a `VerifyJob` refines it by render-and-compare (`perception.refine`)
and scores the result (`perception.scoring`), independently of every other start, so a batch of
starts may run on any `perception.parallel` executor with the same results. A `Verification`
keeps one detection's runs:

1. every start gets a first run: all of the refinement, or (`RefinementConfig.keep_after_first`)
   a short screening run of `RefinementConfig.screen_iterations` steps;
2. the results are ranked, plausible poses first (`perception.priors.Plausibility`), each group
   by score; the best `keep_after_first` get the further runs and are ranked again, above the
   rest;
3. with gravity, the best few near a resting pose are snapped onto it and refined once more
   turning about the vertical only (`perception.priors.GravityConfig`); the snapped poses
   compete on their scores alone, ahead of the rest, unless all of them score well below the
   best pose of all.

More starts can join later (the second look): the ranking is made again over all of them, and
no run is made twice.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from perception.parallel import Executor
from perception.parts import Parts
from perception.priors import SNAP_SCORE_DROP, Plausibility
from perception.refine import PoseRefiner, RefineConfig, RefineTarget
from perception.scoring import Scorer
from posegrasp.core.errors import InvalidArgumentError


@dataclass(frozen=True)
class RefinementConfig:
    """How a detection's starts are refined.

    Attributes:
        passes: full refiner runs a start gets in all; >= 1.
        keep_after_first: after every start's first run and the ranking, only this many of the
            best get the further runs and are ranked again (0: every start gets all its runs).
        screen_iterations: refiner steps of the first run, with `keep_after_first` (0: the
            refiner's full run).
        max_shift: a refiner run that moves a start further than this fraction of its distance
            is rejected (`perception.refine.RefineConfig.max_shift`, there 0.1); in (0, 1]. A
            hypothesis framed as if the object went on behind an occluder, or drawn from a
            coarse template, often starts 15-25 % off in distance along its ray; the
            verification rejects a run that went astray, so the guard can be wider than for a
            single start.
        max_rotation_deg: a refiner run that turns a start further [deg] is rejected (there
            20 deg); in (0, 180].
    """

    passes: int = 2
    keep_after_first: int = 2
    screen_iterations: int = 2
    max_shift: float = 0.3
    max_rotation_deg: float = 30.0

    def __post_init__(self) -> None:
        if self.passes < 1:
            raise InvalidArgumentError(f"RefinementConfig.passes must be >= 1, got {self.passes}")
        for key in ("keep_after_first", "screen_iterations"):
            if getattr(self, key) < 0:
                raise InvalidArgumentError(
                    f"RefinementConfig.{key} must be >= 0 (0: all), got {getattr(self, key)}"
                )
        if not 0 < self.max_shift <= 1:
            raise InvalidArgumentError(
                f"RefinementConfig.max_shift must be in (0, 1], got {self.max_shift}"
            )
        if not 0 < self.max_rotation_deg <= 180:
            raise InvalidArgumentError(
                "RefinementConfig.max_rotation_deg must be in (0, 180], got "
                f"{self.max_rotation_deg}"
            )

    def refiner(self) -> RefineConfig:
        """The render-and-compare refiner's settings, with these guards."""
        return RefineConfig(max_shift=self.max_shift, max_rotation_deg=self.max_rotation_deg)


@dataclass(frozen=True)
class Hypothesis:
    """A pose to start refining from.

    Attributes:
        T_C_O: the pose (4, 4) in the camera frame [m].
        source: where it came from: ``nets`` or ``codebook``.
    """

    T_C_O: np.ndarray
    source: str


@dataclass(frozen=True)
class Verified:
    """One refined, scored hypothesis.

    Attributes:
        T_C_O: the refined pose (4, 4).
        score: the verification score.
        iou: silhouette IoU with the visible mask.
        appearance: the colour correlation.
        edges: the share of the parts' outlines on image edges.
        source: ``codebook`` or ``nets``.
        rank: which start it came from, in the order the starts joined.
        tilt: rotation to the nearest resting pose [deg] (0 without gravity).
        plausible: within the detection's priors (`perception.priors.Plausibility`); plausible
            poses rank first.
    """

    T_C_O: np.ndarray
    score: float
    iou: float
    appearance: float
    edges: float
    source: str
    rank: int
    tilt: float = 0.0
    plausible: bool = True


def rank_verified(verified: list[Verified]) -> list[Verified]:
    """Best first: the plausible ones (`Verified.plausible`) before the others, each group by
    decreasing score (ties keep their order)."""
    return sorted(verified, key=lambda v: (v.plausible, v.score), reverse=True)


class Start(NamedTuple):
    """One start to refine and score (`VerifyJob.run`).

    Attributes:
        T_C_O: the starting pose (4, 4).
        source: ``codebook`` or ``nets``, as the result carries it.
        rank: which start it is (`Verified.rank`).
        passes: refiner runs.
        iterations: refiner steps per run (0: the job's full refiner).
        axis: turn only about this unit axis in the camera frame (None: any rotation).
    """

    T_C_O: np.ndarray
    source: str
    rank: int
    passes: int
    iterations: int = 0
    axis: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class VerifyJob:
    """Everything one detection's starts are refined and scored against; it pickles, so a start
    runs the same on any process.

    Attributes:
        parts: the object's convex parts.
        target: the refiner's prepared target (`perception.refine.PoseRefiner.prepare`).
        refine: the full refiner's settings (a start's `iterations` shortens its runs).
        scorer: what the refined poses are scored against.
    """

    parts: Parts
    target: RefineTarget
    refine: RefineConfig
    scorer: Scorer

    def steps(self, iterations: int) -> int:
        """Refiner steps per run of a start of `iterations` (0, or more than the full
        refiner's: the full refiner's)."""
        full = self.refine.iterations
        return full if iterations <= 0 or iterations >= full else iterations

    def run(self, start: Start) -> Verified | None:
        """`start` refined (`Start.passes` runs) and scored, with no priors (`Verified.tilt` 0,
        plausible); None when a run finds it behind the camera (not a pose to verify)."""
        steps = self.steps(start.iterations)
        cfg = (
            self.refine
            if steps == self.refine.iterations
            else replace(self.refine, iterations=steps)
        )
        refiner = PoseRefiner(cfg)
        T, info = start.T_C_O, {"iou_after": 0.0}
        try:
            for _ in range(start.passes):
                T, info = refiner.refine_parts(self.parts, T, self.target, start.axis)
        except InvalidArgumentError:
            return None
        s = self.scorer.score(T, float(info["iou_after"]))
        return Verified(T, s.score, s.iou, s.appearance, s.edges, start.source, start.rank)


class Verification:
    """One detection's starts, refined, scored and ranked (see the module docstring); each run
    is made once, however often the ranking is made again.

    Args:
        job: what the starts are refined and scored against.
        refinement: how they are refined.
        priors: the detection's priors (gravity snaps the best few when given).
        executor: where each batch of starts runs.
    """

    def __init__(
        self,
        job: VerifyJob,
        refinement: RefinementConfig,
        priors: Plausibility,
        executor: Executor,
    ) -> None:
        self.job, self.refinement, self.priors, self.executor = job, refinement, priors, executor
        self.firsts: list[Verified] = []  # every start's first run
        self._starts = 0  # starts so far (the next one's rank)
        self._further: dict[int, Verified | None] = {}  # by start: refined further
        self._snaps: dict[tuple[int, bool], Verified | None] = {}  # by start, first or further

    def _runs(self, batch: Sequence[Start]) -> list[Verified | None]:
        """The batch's starts refined and scored on the executor, then judged by the priors."""
        out = []
        for v in self.executor.map(self.job, batch):
            if v is not None:
                tilt, plausible = self.priors.judge(v.T_C_O)
                v = replace(v, tilt=tilt, plausible=plausible)
            out.append(v)
        return out

    def add(self, hypotheses: Sequence[Hypothesis]) -> None:
        """Give each hypothesis its first run; ranks continue from the starts so far."""
        cfg = self.refinement
        passes, screen = (1, cfg.screen_iterations) if cfg.keep_after_first else (cfg.passes, 0)
        batch = [
            Start(h.T_C_O, h.source, r, passes, screen)
            for r, h in enumerate(hypotheses, self._starts)
        ]
        self._starts += len(hypotheses)
        self.firsts += [v for v in self._runs(batch) if v is not None]

    def ranked(self) -> list[Verified]:
        """Every start's best result, best first: the first runs ranked, the best few refined
        further, then snapped (see the module docstring)."""
        out = rank_verified(self.firsts)
        cfg = self.refinement
        screen_full = self.job.steps(cfg.screen_iterations) == self.job.refine.iterations
        if cfg.keep_after_first and (cfg.passes > 1 or not screen_full):
            out = self._refined_further(out, cfg.passes - screen_full)
        gravity = self.priors.gravity
        if gravity is not None and gravity.config.snap_candidates:
            out = self._snapped(out)
        return out

    def _refined_further(self, out: list[Verified], passes: int) -> list[Verified]:
        """The best `keep_after_first` of `out` refined further (`passes` full runs) and ranked,
        above the rest (refined once), which stay listed."""
        keep = self.refinement.keep_after_first
        kept, rest = out[:keep], out[keep:]
        todo = list({v.rank: v for v in kept if v.rank not in self._further}.values())
        batch = [Start(v.T_C_O, v.source, v.rank, passes) for v in todo]
        self._further.update(zip([v.rank for v in todo], self._runs(batch), strict=True))
        again = [self._further[v.rank] for v in kept]
        return rank_verified([v for v in again if v is not None]) + rest

    def _snapped(self, out: list[Verified]) -> list[Verified]:
        """The best few of `out` that could be resting, each turned onto its resting pose (its
        heading kept) and refined again, one run, turning about the vertical only; one whose
        score drops by more than `SNAP_SCORE_DROP` is not kept. The snapped ones then compete
        on their scores alone, ahead of the rest, unless every one of them scores well below
        the best pose found (the object is not resting)."""
        gravity = self.priors.gravity
        assert gravity is not None
        cfg = gravity.config
        pool = [v for v in out if v.tilt <= cfg.snap_tilt_deg][: cfg.snap_candidates]
        keys = [(v.rank, self._further.get(v.rank) is v) for v in pool]  # first or further
        new: dict[tuple[int, bool], Verified] = {}
        for k, v in zip(keys, pool, strict=True):
            if k not in self._snaps:
                new.setdefault(k, v)
        up = gravity.up
        batch = [
            Start(gravity.snapped(v.T_C_O), v.source, v.rank, 1, cfg.snap_iterations, up)
            for v in new.values()
        ]
        for (k, v), s in zip(new.items(), self._runs(batch), strict=True):
            self._snaps[k] = None if s is None or s.score < v.score - SNAP_SCORE_DROP else s
        snapped = [s for k in keys if (s := self._snaps[k]) is not None]
        best_score = max((v.score for v in out), default=0.0)
        if snapped and max(v.score for v in snapped) >= best_score - SNAP_SCORE_DROP:
            return rank_verified(snapped) + [v for v in out if all(v is not p for p in pool)]
        return out
