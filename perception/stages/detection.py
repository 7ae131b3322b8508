"""The detection stages: the requested object's detection among the others, and its mask
redrawn by the mask net."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from perception.detector import Detection
from perception.detector_net import ANY_OBJECT
from perception.hybrid import HybridPoseEstimator, detect_target
from perception.mask_net import MaskRefiner
from perception.stages.config import DetectionConfig, GlobalConfig
from perception.stages.hypotheses import CodebookHypotheses
from perception.stages.work import AnyDetection, Detections, Kit, Work
from perception.support import resting_surface_z
from posegrasp.core.contract import Observation
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.world.objects import OBJECT_NAMES, load_object


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
        """The stage of `config.detection`: `AnyObjectDetection` for a detector of any object."""
        if kit.hybrid.detector.cfg.any_object:
            codebook = CodebookHypotheses(kit.codebooks, config.codebook)
            return AnyObjectDetection(kit.hybrid, config.detection, codebook, kit)
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
            info["box_xyxy"] = [float(v) for v in best.box_xyxy]
        neighbours = tuple((p.name, p.T_C_O.copy()) for p in poses)
        return Detections(best, list(dets), neighbours, info)


class AnyObjectDetection(TargetDetection):
    """The detection stage of a detector of any object (`perception.detector_net.ANY_OBJECT`),
    which names no object: the requested one is told by its mesh.

    Every detection scoring at least `DetectionConfig.target_score` (below the detector's own
    threshold too) has its mask matched against the requested object's codebook (the best IoU
    of the mesh's silhouettes over the rotation group, `CodebookHypotheses`); the
    `DetectionConfig.shortlist` best matched are each verified as the target would be (its
    hypotheses refined and scored, without the second look, every other detection its occluder:
    `Kit.neighbour`), and the one whose best pose scores highest is the target, named as the
    requested object; where the observation gives the table's height, among those whose pose
    rests on the table (`DetectionConfig.table_tolerance_m`), if any does. The other detections
    that score the detector's threshold are its neighbours and occluders, without poses.

    Args:
        hybrid: the detector (the pose nets are not used).
        config: the stage's settings.
        codebook: the codebook's hypothesis source, whose matches rank the detections.
        kit: the estimator's pieces: where the matching runs, how a detection is verified.
    """

    def __init__(
        self,
        hybrid: HybridPoseEstimator,
        config: DetectionConfig,
        codebook: CodebookHypotheses,
        kit: Kit,
    ) -> None:
        super().__init__(hybrid, config)
        self.codebook, self.kit = codebook, kit

    def __call__(self, work: Work) -> Work:
        """`work` with the observation's detections, the target told by its mesh, and the
        target's occluder."""
        assert work.obs is not None
        floor = self.hybrid.detector.score_threshold
        threshold = floor if self.config.target_score is None else self.config.target_score
        t0 = time.perf_counter()
        # Any detection may be the target: detect down to its score, the others keep the floor.
        dets = self.hybrid.detector.detect(work.obs.rgb, min(floor, threshold))
        t1 = time.perf_counter()
        ranked, ious = self.ranked(dets, threshold, work.obs.object, work.obs.K)
        verified = {k: self.verified(work, dets, k) for k in ranked if len(ranked) > 1}
        scored = {k: v for k, v in verified.items() if v is not None}  # (score, surface z)
        table, tol = work.obs.table_top_z, self.config.table_tolerance_m
        choices = scored
        if table is not None and tol is not None:
            choices = {k: v for k, v in scored.items() if abs(v[1] - table) <= tol} or scored
        pick = max(choices, key=lambda k: choices[k][0]) if choices else next(iter(ranked), None)
        info: dict = {
            "detected": pick is not None,
            "detections": len(dets),
            "choice": {
                "match_iou": ious,
                "verified": {str(k): None if v is None else v[0] for k, v in verified.items()},
                "surface_z": {str(k): round(v[1], 4) for k, v in scored.items()},
            },
        }
        target, every = self.as_target(dets, pick, work.obs.object)
        if target is not None:
            info |= {"class": ANY_OBJECT, "score": target.score}
            info["box_xyxy"] = [float(v) for v in target.box_xyxy]
        t2 = time.perf_counter()
        info["timings_ms"] = {"detect": (t1 - t0) * 1000, "choose": (t2 - t1) * 1000}
        found = Detections(target, every, (), info)
        return work.given(found=found, target=target, occluder=found.occluder)

    def ranked(
        self, dets: list[Detection], threshold: float, name: str, K: np.ndarray
    ) -> tuple[list[int], list[float]]:
        """The indices of the `shortlist` detections scoring `threshold` whose masks the
        codebook of `name` matches best, best first, and every detection's best IoU (-1 for one
        under the threshold or with an empty mask)."""
        executor = self.kit.executor()
        ious = []
        for d in dets:
            match = None
            if d.score >= threshold:
                match = self.codebook.match(replace(d, name=name), None, K, executor)
            ious.append(-1.0 if match is None else round(float(match.scores.max()), 4))
        order = [int(k) for k in np.argsort(-np.asarray(ious), kind="stable") if ious[k] >= 0]
        return order[: self.config.shortlist], ious

    def as_target(
        self, dets: list[Detection], k: int | None, name: str
    ) -> tuple[Detection | None, list[AnyDetection]]:
        """Detection `k` named as the requested object `name` (None: no target), and the
        detections kept with it, in its place: those that score the detector's threshold (the
        others were candidates only)."""
        target = None if k is None else replace(dets[k], name=name)
        floor = self.hybrid.detector.score_threshold
        every: list[AnyDetection] = [
            target if j == k and target is not None else d
            for j, d in enumerate(dets)
            if j == k or d.score >= floor
        ]
        return target, every

    def verified(self, work: Work, dets: list[Detection], k: int) -> tuple[float, float] | None:
        """The score of the best verified pose of detection `k` taken as the target, and the
        height [m] in the world of the surface that pose rests on (None: none verifies)."""
        assert work.obs is not None
        as_target, every = self.as_target(dets, k, work.obs.object)
        assert as_target is not None
        trial = work.given(found=Detections(as_target, every, (), {}))
        best = self.kit.neighbour(as_target, trial)
        if best is None:
            return None
        z = resting_surface_z(best.T_C_O, work.obs.T_world_cam, load_object(work.obs.object))
        return round(float(best.score), 4), float(z)


class RedrawnMask:
    """The mask stage: the target's mask redrawn by the mask net, for the built-in objects it
    was trained on (any other detection keeps the detector's); behind a detector of any object
    (`perception.detector_net.ANY_OBJECT`), every target's, the mask net then being one trained
    on bank scenes of objects of every shape (``hybrid-global-unseen``'s).

    Args:
        masks: the mask net.
        any_object: redraw the mask of whatever object is asked for.
    """

    name = "mask"

    def __init__(self, masks: MaskRefiner, any_object: bool = False) -> None:
        self.masks, self.any_object = masks, any_object

    @classmethod
    def build(cls, config: GlobalConfig, kit: Kit) -> RedrawnMask | None:
        """The stage when `config.detection` asks for the mask net (None: left out)."""
        if not config.detection.mask_net:
            return None
        if kit.masks is None:
            raise InvalidArgumentError(
                "DetectionConfig.mask_net asks for the mask net, and none is loaded (Kit.masks)"
            )
        return cls(kit.masks, kit.hybrid.detector.cfg.any_object)

    def knows(self, name: str) -> bool:
        """Whether the mask net redraws the masks of object `name`."""
        return self.any_object or name in OBJECT_NAMES

    def wanted(self, work: Work) -> bool:
        """Whether the target is one of the objects the mask net knows."""
        return work.target is not None and self.knows(work.target.name)

    def __call__(self, work: Work) -> Work:
        """`work` with its target's mask redrawn."""
        assert work.target is not None
        return work.given(target=self.redraw(work.target, work.rgb))

    def redraw(self, det: AnyDetection, rgb: np.ndarray) -> AnyDetection:
        """`det` with its mask redrawn from the image `rgb` (H, W, 3) uint8 (as it is for an
        object the mask net does not know)."""
        if not self.knows(det.name):
            return det
        return replace(det, mask=self.masks.refine(rgb, det.mask, det.name))
