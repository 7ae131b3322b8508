"""Any orientation: global hypotheses, each refined by render-and-compare, verified, the best kept.

The learned 4D-NET knows upright objects seen from the head camera; on any other orientation it
is far off. This estimator does not ask it to learn the sphere. It is the list of stages
`STAGES` (`perception.stages`, one interface), each built from its own part of `GlobalConfig`
and left out where that part is None; per image, in order:

1. **detection** (`DetectionConfig`): the requested object's best detection (the shipped Mask
   R-CNN fine-tuned on the tiers' scenes, `TIERS_DETECTOR`), the others its neighbours and
   occluders;
2. **mask**: the target's mask redrawn by the mask net (`DetectionConfig.mask_net`);
3. **hypotheses** (`CodebookConfig`, `GravityConfig`, `InplaneConfig`): the nets' pose and the
   viewpoint codebook's best templates over all of SO(3), the mask also framed as if the object
   went on behind an occluder; with gravity, templates that could rest;
4. **verify** (`RefinementConfig`, `ScoringConfig`; `perception.verification`): each hypothesis
   refined against the mask and the image, scored by its IoU, colours and edges, the best few
   refined further; gravity ranks poses near resting first and snaps the best few onto their
   resting pose;
5. **second_look** (`SecondLookConfig`): when the best is unsure, more hypotheses;
6. **table** (`TableConfig`) or, when unsure, **support** (`SupportConfig`): the winner placed
   on the known table or on the surface its neighbours rest on.

The winner's score is reported as the estimate's confidence, and each stage's time in
``info["timings_ms"]``. Inputs are the image, K, the camera's pose (for gravity) and the
requested class; the table's height only with `GlobalConfig.table`. Codebooks are built once
per object and grid and cached under the data folder (``$POSEGRASP_DATA/codebooks``).
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np

from perception.codebook import CodebookCache
from perception.detector import TIERS_DETECTOR
from perception.hybrid import HybridPoseEstimator, occluder_of
from perception.mask_net import MaskRefiner
from perception.parallel import Executor, OneProcess, TwoProcesses
from perception.parts import ConvexParts
from perception.stages import (
    AnyDetection,
    GlobalConfig,
    Hypotheses,
    Kit,
    NeighbourSupport,
    RedrawnMask,
    SecondLook,
    Stage,
    StageKind,
    TablePrior,
    TargetDetection,
    Verify,
    Work,
    run_stages,
)
from perception.verification import Verified
from posegrasp.core.contract import Estimate, Observation
from posegrasp.core.errors import InvalidArgumentError

__all__ = ["CodebookCache", "GlobalConfig", "GlobalPoseEstimator"]


#: The stages of `GlobalPoseEstimator`, in the order an image goes through them; each is built
#: from its part of `GlobalConfig` (a stage whose part is None is left out). A new stage is
#: its class (`perception.stages.Stage`, with ``build``), its place here and its config's field.
STAGES: tuple[StageKind, ...] = (
    TargetDetection,
    RedrawnMask,
    Hypotheses,
    Verify,
    SecondLook,
    TablePrior,
    NeighbourSupport,
)

#: The stages that verify one detection, from its hypotheses to its ranking.
VERIFY_STAGES: tuple[StageKind, ...] = (Hypotheses, Verify, SecondLook)


class GlobalPoseEstimator:
    """The estimators ``hybrid-global`` and its variants (see the module docstring): the
    stages of `STAGES` its config keeps, run in order on each image.

    Args:
        hybrid: the detector and pose nets (`HybridPoseEstimator.from_weights()`).
        config: the composition (default: `GlobalConfig()`, ``hybrid-global``'s).
        codebooks: where codebooks come from (default: built from the convex parts and cached
            in the data folder).
        name: the name results carry.
        masks: the mask net that redraws the target's mask (`DetectionConfig.mask_net`;
            default: the shipped one, loaded here when the config asks for it).
    """

    def __init__(
        self,
        hybrid: HybridPoseEstimator,
        config: GlobalConfig | None = None,
        codebooks: CodebookCache | None = None,
        name: str = "hybrid-global",
        masks: MaskRefiner | None = None,
    ) -> None:
        cfg = config or GlobalConfig()
        if masks is None and cfg.detection.mask_net:
            masks = MaskRefiner.from_weights()
        grid = (cfg.codebook.views, cfg.codebook.inplane)
        if codebooks is None:
            codebooks = CodebookCache(*grid)
        elif (codebooks.views, codebooks.inplane) != grid:
            codebooks = CodebookCache(*grid, codebooks.folder, codebooks.source)
        self.name, self._config = name, cfg
        self.kit = Kit(hybrid, masks, codebooks, ConvexParts(), self._executor, self._as_target)
        built = (stage.build(cfg, self.kit) for stage in STAGES)
        self.stages: tuple[Stage, ...] = tuple(s for s in built if s is not None)
        self._verifying = tuple(s for s in self.stages if type(s) in VERIFY_STAGES)
        self._workers: TwoProcesses | None = None
        self._no_workers = False  # a worker could not be started
        self._estimates = 0  # made so far (the worker starts in the second)

    def __getstate__(self) -> dict:
        """The estimator without its worker process (a copy on another process starts its
        own)."""
        state = dict(self.__dict__)
        state["_workers"], state["_no_workers"] = None, False
        return state

    @property
    def config(self) -> GlobalConfig:
        """The composition."""
        return self._config

    @property
    def hybrid(self) -> HybridPoseEstimator:
        """The detector and the pose nets."""
        return self.kit.hybrid

    @property
    def codebooks(self) -> CodebookCache:
        """Where the codebooks come from."""
        return self.kit.codebooks

    def with_config(self, config: GlobalConfig) -> GlobalPoseEstimator:
        """This estimator composed anew of `config`'s stages, with the same nets, mask net,
        codebooks (of the same grid), name and worker process (handed over: use the new one)."""
        other = GlobalPoseEstimator(self.hybrid, config, self.codebooks, self.name, self.kit.masks)
        other._workers, other._no_workers = self._workers, self._no_workers
        other._estimates, self._workers = self._estimates, None
        return other

    def stage(self, name: str) -> Stage:
        """The stage called `name`.

        Raises:
            InvalidArgumentError: this composition has no such stage.
        """
        for s in self.stages:
            if s.name == name:
                return s
        names = ", ".join(s.name for s in self.stages)
        raise InvalidArgumentError(f"no stage {name!r} in {self.name}; stages: {names}")

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
        times: dict[str, float] = {}
        work = run_stages(self.stages, Work.of(obs), times)
        assert work.found is not None
        info, neighbours = work.found.info, work.found.neighbours
        if work.target is None:
            return Estimate(None, neighbours, info)
        info["timings_ms"] |= times
        win = work.winner
        if win is None:
            return Estimate(None, neighbours, info | {"verify": {"hypotheses": 0}})
        info["verify"] = self._described(win, len(work.ranked), work.looked_again)
        T = win.T_C_O.copy()
        if work.placed is not None:
            T, info["support"] = work.placed.T_C_O, work.placed.description
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

    def _as_target(self, d: AnyDetection, work: Work) -> Work:
        """Detection `d` of the image of `work` taken through the stages as the target would
        be, its mask redrawn, but without the second look, every other detection its occluder:
        the work as verification leaves it."""
        assert work.found is not None
        occluder = occluder_of(work.found.every, d)
        start = Work.on(self.sharpened(d, work.rgb), work.K, work.rgb, occluder, work.R_W_C, False)
        return run_stages(self._verifying, start, {})

    def verify(
        self,
        det: AnyDetection,
        K: np.ndarray,
        rgb: np.ndarray,
        occluder: np.ndarray | None,
        R_W_C: np.ndarray | None = None,
        second_look: bool = True,
    ) -> tuple[list[Verified], dict[str, float]]:
        """Every hypothesis of one detection, refined and scored, best first: the stages of
        `VERIFY_STAGES` this composition has (gravity with the camera's rotation in the world
        `R_W_C`; with `second_look` False the second look never runs), and the times [ms] of
        those entered. A detection without the nets' pose (of an object they were not trained
        on) starts from the codebook alone."""
        times: dict[str, float] = {}
        work = Work.on(det, K, rgb, occluder, R_W_C, second_look)
        work = run_stages(self._verifying, work, times)
        return list(work.ranked), times

    def sharpened(self, det: AnyDetection, rgb: np.ndarray) -> AnyDetection:
        """`det` with its mask redrawn by the mask stage, when there is one."""
        for s in self.stages:
            if isinstance(s, RedrawnMask):
                return s.redraw(det, rgb)
        return det

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
