"""Any orientation: global hypotheses, each refined by render-and-compare, verified, the best kept.

The learned 4D-NET knows upright objects seen from the head camera; on any other orientation it
is far off. This estimator does not ask it to learn the sphere. It is composed of stages
(`perception.stages`), each configured by its own part of `GlobalConfig`; per image:

1. **Detection** (`DetectionConfig`): the requested object's best detection (the shipped Mask
   R-CNN fine-tuned on the tiers' scenes, `TIERS_DETECTOR`), the others its neighbours and
   occluders.
2. **Mask**: the target's mask redrawn by the mask net (`DetectionConfig.mask_net`).
3. **Hypotheses** (`CodebookConfig`): the nets' pose and the viewpoint codebook's best
   templates over all of SO(3), the mask also framed as if the object went on behind an
   occluder; with gravity, templates that could rest.
4. **Refinement and scoring** (`RefinementConfig`, `ScoringConfig`; `perception.verification`):
   each hypothesis refined against the mask and the image, scored by its IoU, colours and
   edges, the best few refined further.
5. **Priors**: gravity (`GravityConfig`: poses near resting rank first, the best few snapped
   onto their resting pose) and the in-plane range (`InplaneConfig`) while ranking; when the
   best is unsure, a second look at more hypotheses (`SecondLookConfig`); on the winner, the
   known table (`TableConfig`) or, when unsure, the surface its neighbours rest on
   (`SupportConfig`).

The winner's score is reported as the estimate's confidence. Inputs are the image, K, the
camera's pose (for gravity) and the requested class; the table's height only with
`GlobalConfig.table`. Codebooks are built once per object and grid and cached under the data
folder (``$POSEGRASP_DATA/codebooks``).
"""

from __future__ import annotations

import functools
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

from perception.codebook import CodebookCache
from perception.detector import TIERS_DETECTOR
from perception.hybrid import HybridPoseEstimator, occluder_of
from perception.mask_net import MaskRefiner
from perception.parallel import Executor, OneProcess, TwoProcesses
from perception.parts import ConvexParts
from perception.priors import Gravity, GravityConfig, InplaneConfig, Plausibility
from perception.refine import PoseRefiner
from perception.scoring import Scorer, ScoringConfig
from perception.stages import (
    AnyDetection,
    CodebookConfig,
    CodebookHypotheses,
    DetectionConfig,
    NeighbourSupport,
    NetsPose,
    RedrawnMask,
    RestingHypotheses,
    SecondLookConfig,
    SupportConfig,
    TableConfig,
    TablePrior,
    TargetDetection,
)
from perception.verification import RefinementConfig, Verification, Verified, VerifyJob
from posegrasp.core.contract import Estimate, Observation
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.world.objects import load_object

__all__ = ["CodebookCache", "GlobalConfig", "GlobalPoseEstimator"]


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
            kind = {"processes": int}.get(f.name) or _STAGE_TYPES[f.name]
            if not (isinstance(value, kind) or (value is None and f.name in optional)):
                allowed = kind.__name__ + (" or None" if f.name in optional else "")
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


_STAGE_TYPES: dict[str, type] = {
    "detection": DetectionConfig,
    "codebook": CodebookConfig,
    "refinement": RefinementConfig,
    "scoring": ScoringConfig,
    "gravity": GravityConfig,
    "inplane": InplaneConfig,
    "second_look": SecondLookConfig,
    "support": SupportConfig,
    "table": TableConfig,
}


class GlobalPoseEstimator:
    """The estimators ``hybrid-global`` and its variants (see the module docstring).

    Args:
        hybrid: the detector and pose nets (`HybridPoseEstimator.from_weights()`).
        config: the composition (default: `GlobalConfig()`, ``hybrid-global``'s).
        codebooks: where codebooks come from (default: built from the convex parts and cached
            in the data folder).
        name: the name results carry.
        masks: the mask net that redraws the target's mask (`DetectionConfig.mask_net`;
            default: the shipped one when the config asks for it).
    """

    def __init__(
        self,
        hybrid: HybridPoseEstimator,
        config: GlobalConfig | None = None,
        codebooks: CodebookCache | None = None,
        name: str = "hybrid-global",
        masks: MaskRefiner | None = None,
    ) -> None:
        self.hybrid, self.name = hybrid, name
        self.parts = ConvexParts()
        self._masks, self.codebooks = masks, codebooks
        self._workers: TwoProcesses | None = None
        self._no_workers = False  # a worker could not be started
        self._estimates = 0  # made so far (the worker starts in the second)
        self.config = config or GlobalConfig()

    def __getstate__(self) -> dict:
        """The estimator without its worker process (a copy on another process starts its
        own)."""
        state = dict(self.__dict__)
        state["_workers"], state["_no_workers"] = None, False
        return state

    @property
    def config(self) -> GlobalConfig:
        """The composition; setting it composes the stages anew (the nets, the mask net and
        the codebooks of the same grid are kept)."""
        return self._config

    @config.setter
    def config(self, cfg: GlobalConfig) -> None:
        self._config = cfg
        self.detection = TargetDetection(self.hybrid, cfg.detection)
        self.mask = None
        if cfg.detection.mask_net:
            self._masks = self._masks or MaskRefiner.from_weights()
            self.mask = RedrawnMask(self._masks)
        grid = (cfg.codebook.views, cfg.codebook.inplane)
        if self.codebooks is None:
            self.codebooks = CodebookCache(*grid)
        elif (self.codebooks.views, self.codebooks.inplane) != grid:
            self.codebooks = CodebookCache(*grid, self.codebooks.folder, self.codebooks.source)
        self.nets, self.codebook = NetsPose(), CodebookHypotheses(self.codebooks, cfg.codebook)
        self.resting = RestingHypotheses(cfg.codebook.min_angle_deg)
        self.refiner = PoseRefiner(cfg.refinement.refiner())
        self.table = None if cfg.table is None else TablePrior(cfg.table)
        self.support = None
        if cfg.support is not None and cfg.gravity is not None:
            self.support = NeighbourSupport(cfg.support, cfg.gravity.tilt_deg)

    @classmethod
    def from_weights(
        cls,
        config: GlobalConfig | None = None,
        detector_path: Path = TIERS_DETECTOR,
        name: str = "hybrid-global",
    ) -> GlobalPoseEstimator:
        """With the shipped nets and the detector fine-tuned on the tiers' scenes (or the one
        at `detector_path`)."""
        hybrid = HybridPoseEstimator.from_weights(detector_path=detector_path)
        return cls(hybrid, config, name=name)

    def estimate(self, obs: Observation) -> Estimate:
        """The verified pose of obs.object (None when not detected or nothing verifies), the
        other detections and the description of the estimate."""
        self._estimates += 1
        found = self.detection(obs)
        info, neighbours = found.info, found.neighbours
        if found.target is None:
            return Estimate(None, neighbours, info)
        target = found.target
        if self.mask is not None:
            t0 = time.perf_counter()
            target = self.mask(target, obs.rgb)
            info["timings_ms"]["mask"] = (time.perf_counter() - t0) * 1000
        R_W_C = np.asarray(obs.T_world_cam, float)[:3, :3]
        ranked, times = self.verify(target, obs.K, obs.rgb, found.occluder, R_W_C)
        info["timings_ms"] |= times
        if not ranked:
            return Estimate(None, neighbours, info | {"verify": {"hypotheses": 0}})
        win = ranked[0]
        info["verify"] = self._described(win, len(ranked), "second_look" in times)
        T = win.T_C_O.copy()
        model = load_object(target.name)
        placed = None if self.table is None else self.table.place(T, obs, model)
        if placed is None and self.support is not None and self.support.wanted(win, model):
            t0 = time.perf_counter()
            neighbour = functools.partial(self._neighbour, every=found.every, obs=obs)
            placed = self.support.place(T, target, found.every, obs, neighbour)
            info["timings_ms"]["support"] = (time.perf_counter() - t0) * 1000
        if placed is not None:
            T, info["support"] = placed.T_C_O, placed.description
        return Estimate(T, neighbours, info, confidence=float(win.score))

    def _described(self, win: Verified, hypotheses: int, second_look: bool) -> dict:
        """What the estimate reports of its verification (``info["verify"]``)."""
        return {
            "confidence": win.score,
            "iou": win.iou,
            "appearance": win.appearance,
            "edges": win.edges,
            "source": win.source,
            "tilt_deg": win.tilt,
            "hypotheses": hypotheses,
            "second_look": second_look,
            "config": asdict(self.config),
        }

    def _neighbour(
        self, d: AnyDetection, every: list[AnyDetection], obs: Observation
    ) -> Verified | None:
        """A neighbour's best pose (None: none), verified as the target's but without the
        second look, every other detection its occluder."""
        R_W_C = np.asarray(obs.T_world_cam, float)[:3, :3]
        occluder = occluder_of(every, d)
        got, _ = self.verify(self.sharpened(d, obs.rgb), obs.K, obs.rgb, occluder, R_W_C, False)
        return got[0] if got else None

    def verify(
        self,
        det: AnyDetection,
        K: np.ndarray,
        rgb: np.ndarray,
        occluder: np.ndarray | None,
        R_W_C: np.ndarray | None = None,
        second_look: bool = True,
    ) -> tuple[list[Verified], dict[str, float]]:
        """Every hypothesis of one detection, refined and scored, best first (see
        `perception.verification`; gravity with the camera's rotation in the world `R_W_C`),
        and the stage times [ms] (``hypotheses``, ``verify``, and ``second_look`` within
        ``verify`` when it ran; with `second_look` False it never runs). A detection without
        the nets' pose (of an object they were not trained on) starts from the codebook alone.
        """
        cfg = self.config
        t0 = time.perf_counter()
        executor = self._executor()
        priors = self._priors(det.name, R_W_C)
        gravity, book = priors.gravity, cfg.codebook
        match = self.codebook.match(det, occluder, K, executor)
        first = self.nets.hypotheses(det)
        taken: list[int] = []
        if match is not None:
            taken = self.codebook.best(match, 0, book.hypotheses, [])
            if gravity is not None and book.resting_hypotheses:
                taken += self.resting.best(match, gravity, book.resting_hypotheses, taken)
            first += match.hypotheses(taken)
        t1 = time.perf_counter()
        parts = self.parts.parts(det.name)
        target = self.refiner.prepare(K, det.mask, rgb, occluder)
        scorer = Scorer.of(parts, K, rgb, det.mask, cfg.scoring)
        job = VerifyJob(parts, target, self.refiner.config, scorer)
        verification = Verification(job, cfg.refinement, priors, executor)
        verification.add(first)
        ranked = verification.ranked()
        times = {"hypotheses": (t1 - t0) * 1000}
        look = cfg.second_look if second_look else None
        if look is not None and match is not None and (not ranked or ranked[0].score < look.below):
            t_look = time.perf_counter()
            later = self.codebook.best(match, book.hypotheses, look.hypotheses, taken)
            if gravity is not None and look.resting:
                later += self.resting.best(match, gravity, look.resting, taken + later)
            verification.add(match.hypotheses(later))
            ranked = verification.ranked()
            times["second_look"] = (time.perf_counter() - t_look) * 1000
        times["verify"] = (time.perf_counter() - t1) * 1000
        return ranked, times

    def sharpened(self, det: AnyDetection, rgb: np.ndarray) -> AnyDetection:
        """`det` with its mask redrawn by the mask stage, when there is one."""
        return det if self.mask is None else self.mask(det, rgb)

    def _priors(self, name: str, R_W_C: np.ndarray | None) -> Plausibility:
        """The priors of a detection of `name`: gravity with the camera's rotation and the
        object's resting poses, the in-plane range."""
        cfg = self.config
        model = load_object(name)
        gravity = None
        if cfg.gravity is not None and R_W_C is not None and model.resting_poses:
            gravity = Gravity(R_W_C, model, cfg.gravity)
        inplane = None if cfg.inplane is None else cfg.inplane.max_deg
        return Plausibility(gravity, inplane)

    def _executor(self) -> Executor:
        """Where batches run (`GlobalConfig.processes`): with two, a worker process started in
        the second estimate (its start-up would only slow a process that makes one), used while
        this process computes on more than one thread (an evaluation's workers, one thread
        each, already fill the cores); this process alone before, or where none can start."""
        import torch

        if self.config.processes < 2 or torch.get_num_threads() < 2:
            return OneProcess()
        if self._workers is None and (self._estimates < 2 or self._no_workers):
            return OneProcess()
        if self._workers is None:
            try:
                self._workers = TwoProcesses()
            except OSError:  # no process to start here: all of it on this one
                self._no_workers = True
                return OneProcess()
        return self._workers
