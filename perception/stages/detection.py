"""The detection stages: the requested object's detection among the others, and its mask
redrawn by the mask net."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from perception.hybrid import HybridPoseEstimator, detect_target
from perception.mask_net import MaskRefiner
from perception.stages.config import DetectionConfig, GlobalConfig
from perception.stages.work import AnyDetection, Detections, Kit, Work
from posegrasp.core.contract import Observation
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.world.objects import OBJECT_NAMES


class TargetDetection:
    """The detection stage: detect once and split the detections around the requested object.

    A user object the detector was fine-tuned on is taken from every detection, without the
    nets' pose; the six built-in objects come with the nets' poses (the neighbours' from the
    main net alone).

    Args:
        hybrid: the detector and the pose nets.
        config: the stage's settings.
    """

    name = "detection"

    def __init__(self, hybrid: HybridPoseEstimator, config: DetectionConfig) -> None:
        self.hybrid, self.config = hybrid, config

    @classmethod
    def build(cls, config: GlobalConfig, kit: Kit) -> TargetDetection:
        """The stage of `config.detection`."""
        return cls(kit.hybrid, config.detection)

    @staticmethod
    def wanted(work: Work) -> bool:
        """Whether there is an observation to detect in."""
        return work.obs is not None

    def __call__(self, work: Work) -> Work:
        """`work` with the observation's detections, its target and the target's occluder."""
        assert work.obs is not None
        found = self.detect(work.obs)
        return work.given(found=found, target=found.target, occluder=found.occluder)

    def detect(self, obs: Observation) -> Detections:
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
    """The mask stage: the target's mask redrawn by the mask net, for the built-in objects it
    was trained on (any other detection keeps the detector's).

    Args:
        masks: the mask net.
    """

    name = "mask"

    def __init__(self, masks: MaskRefiner) -> None:
        self.masks = masks

    @classmethod
    def build(cls, config: GlobalConfig, kit: Kit) -> RedrawnMask | None:
        """The stage when `config.detection` asks for the mask net (None: left out)."""
        if not config.detection.mask_net:
            return None
        if kit.masks is None:
            raise InvalidArgumentError(
                "DetectionConfig.mask_net asks for the mask net, and none is loaded (Kit.masks)"
            )
        return cls(kit.masks)

    @staticmethod
    def wanted(work: Work) -> bool:
        """Whether the target is one of the objects the mask net knows."""
        return work.target is not None and work.target.name in OBJECT_NAMES

    def __call__(self, work: Work) -> Work:
        """`work` with its target's mask redrawn."""
        assert work.target is not None
        return work.given(target=self.redraw(work.target, work.rgb))

    def redraw(self, det: AnyDetection, rgb: np.ndarray) -> AnyDetection:
        """`det` with its mask redrawn from the image `rgb` (H, W, 3) uint8 (as it is for an
        object the mask net does not know)."""
        if det.name not in OBJECT_NAMES:
            return det
        return replace(det, mask=self.masks.refine(rgb, det.mask, det.name))
