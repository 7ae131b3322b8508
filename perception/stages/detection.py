"""The detection stages: the requested object's detection among the others, and its mask
redrawn by the mask net."""

from __future__ import annotations

import itertools
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from perception.detector import Detection
from perception.detector_net import ANY_OBJECT
from perception.hybrid import HybridPoseEstimator, detect_target
from perception.mask_net import MaskRefiner
from perception.overlay import mask_box
from perception.stages.config import CodebookConfig, DetectionConfig, GlobalConfig
from perception.stages.hypotheses import CodebookHypotheses
from perception.stages.work import AnyDetection, CodebookMatch, Detections, Kit, Work
from perception.support import resting_surface_z
from posegrasp.core.contract import Observation
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.world.objects import OBJECT_NAMES, ObjectModel, load_object


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
    threshold too) is a candidate, and so are up to `DetectionConfig.joined` of them whose masks
    touch, taken together (`Candidate`: a detector of any object parts an object of several
    colours along its colours). Each candidate's mask is matched against the requested object's
    codebook (the best IoU of the mesh's silhouettes over the rotation group,
    `CodebookHypotheses`); those that fit the mesh resting on the table rank first (`on_table`),
    then by match, and the `DetectionConfig.shortlist` first are each verified as the target
    would be (its hypotheses refined and scored, without the second look, every other
    detection its occluder: `Kit.as_target`), and the one whose best pose scores highest is the
    target, named as the requested object; where the observation gives the table's height,
    among those whose pose rests on the table (`DetectionConfig.table_tolerance_m`), if any
    does. Its verification stands: the mask, hypotheses and verification stages do not run
    again (the second look and the priors after it do). The other detections that score the
    detector's threshold are its neighbours and occluders, without poses.

    Args:
        hybrid: the detector (the pose nets are not used).
        config: the stage's settings.
        codebook: the codebook's hypothesis source, whose matches rank the candidates.
        kit: the estimator's pieces: where the matching runs, how a candidate is verified.
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
        cands = candidates(dets, threshold, self.config.joined)
        T_W_C = work.obs.T_world_cam
        ranked, ious = self.ranked(cands, work)
        model = load_object(work.obs.object)
        table, tol = work.obs.table_top_z, self.config.table_tolerance_m

        def on_it(z: float) -> bool:
            return table is None or tol is None or abs(z - table) <= tol

        done: dict[int, Work] = {}
        scored: dict[int, tuple[float, float]] = {}  # score, height [m] of what the pose rests on
        sure = self.config.sure
        for k in ranked if len(ranked) > 1 else []:
            done[k] = w = self.verified(work, dets, cands[k])
            if w.winner is None:
                continue
            z = float(resting_surface_z(w.winner.T_C_O, T_W_C, model))
            scored[k] = (round(float(w.winner.score), 4), z)
            if sure is not None and w.winner.score >= sure and on_it(z):
                break  # sure of it, and on the table: the rest need no verifying
        choices = {k: v for k, v in scored.items() if on_it(v[1])} or scored
        pick = max(choices, key=lambda k: choices[k][0]) if choices else next(iter(ranked), None)
        info: dict = {
            "detected": pick is not None,
            "detections": len(dets),
            "choice": {
                "picked": pick,
                "match_iou": ious,
                "joined": {str(k): list(c.members) for k, c in enumerate(cands) if c.joined},
                "verified": {str(k): scored[k][0] if k in scored else None for k in done},
                "surface_z": {str(k): round(v[1], 4) for k, v in scored.items()},
            },
        }
        target, every = self.as_target(dets, None if pick is None else cands[pick], work.obs.object)
        if target is not None:
            info |= {"class": ANY_OBJECT, "score": target.score}
            info["box_xyxy"] = [float(v) for v in target.box_xyxy]
        t2 = time.perf_counter()
        info["timings_ms"] = {"detect": (t1 - t0) * 1000, "choose": (t2 - t1) * 1000}
        found = Detections(target, every, (), info)
        out = work.given(found=found, target=target, occluder=found.occluder)
        if pick in done:  # verified as the target already: the stages go on from there
            w = done[pick]
            out = out.given(
                target=w.target,
                executor=w.executor,
                priors=w.priors,
                match=w.match,
                taken=w.taken,
                hypotheses=w.hypotheses,
                verification=w.verification,
                ranked=w.ranked,
            )
        return out

    def ranked(
        self, cands: list[Candidate], work: Work
    ) -> tuple[list[int], Sequence[float | None]]:
        """The indices of the `shortlist` candidates whose masks the codebook of the requested
        object matches best, best first, and every candidate's best IoU (-1 for an empty mask).
        Where the observation gives the table's height, the candidates one of whose best
        templates (`CodebookConfig.hypotheses`) would rest on it (`on_table`) come first. A
        lone candidate is not matched (None): there is nothing to choose."""
        obs = work.obs
        assert obs is not None
        if len(cands) == 1:
            return ([0] if cands[0].detection.mask.any() else []), [None]
        executor, book = self.kit.executor(), self.codebook.config
        model = load_object(obs.object)
        ious, off = [], []
        for c in cands:
            match = self.codebook.match(
                replace(c.detection, name=obs.object), None, obs.K, executor
            )
            ious.append(-1.0 if match is None else round(float(match.scores.max()), 4))
            off.append(match is None or not on_table(match, book, model, obs, self.config))
        found = [k for k in range(len(cands)) if ious[k] >= 0]
        order = sorted(found, key=lambda k: (off[k], -ious[k]))  # stable: ties keep their order
        return order[: self.config.shortlist], ious

    def as_target(
        self, dets: list[Detection], cand: Candidate | None, name: str
    ) -> tuple[Detection | None, list[AnyDetection]]:
        """Candidate `cand` named as the requested object `name` (None: no target), and the
        detections kept with it, in place of its first: those that score the detector's
        threshold (the others were candidates only), but for the candidate's own."""
        target = None if cand is None else replace(cand.detection, name=name)
        own = () if cand is None else cand.members
        floor = self.hybrid.detector.score_threshold
        every: list[AnyDetection] = []
        for j, d in enumerate(dets):
            if target is not None and j == own[0]:
                every.append(target)
            elif j not in own and d.score >= floor:
                every.append(d)
        return target, every

    def verified(self, work: Work, dets: list[Detection], cand: Candidate) -> Work:
        """Candidate `cand` taken as the target through the stages up to its verification
        (`Kit.as_target`), the detections kept with it its occluders: the work they leave."""
        assert work.obs is not None
        as_target, every = self.as_target(dets, cand, work.obs.object)
        assert as_target is not None
        return self.kit.as_target(as_target, work.given(found=Detections(as_target, every, (), {})))


#: Pixels between two masks that still touch: the detector's outlines fall a pixel or two off.
TOUCH_PX = 3


@dataclass(frozen=True)
class Candidate:
    """What may be the requested object: one detection, or several whose masks touch, taken
    together (their masks and boxes joined, the lowest score).

    Attributes:
        detection: the candidate as one detection.
        members: the indices of the detections it is made of, in order.
    """

    detection: Detection
    members: tuple[int, ...]

    @property
    def joined(self) -> bool:
        """Whether it joins several detections."""
        return len(self.members) > 1


def on_table(
    match: CodebookMatch,
    book: CodebookConfig,
    model: ObjectModel,
    obs: Observation,
    config: DetectionConfig,
) -> bool:
    """Whether one of the best `book.hypotheses` templates of a candidate's `match` puts the
    requested object (`model`) at rest within `config.table_tolerance_m` of the table's height
    (True where the observation does not give it, or the tolerance is None): a silhouette fits
    any object nearer or farther, scaled, but the table fixes how far the requested one is, so
    a candidate of another size fits it nowhere on the table."""
    table, tol = obs.table_top_z, config.table_tolerance_m
    if table is None or tol is None:
        return True
    best = match.hypotheses(match.best(0, book.hypotheses, [], book.min_angle_deg))
    return any(abs(resting_surface_z(h.T_C_O, obs.T_world_cam, model) - table) <= tol for h in best)


def candidates(dets: list[Detection], threshold: float, joined: int) -> list[Candidate]:
    """Every detection scoring `threshold`, alone, then every connected group of 2 to `joined`
    of them whose masks touch (`TOUCH_PX`), by size then by index."""
    kept = [k for k, d in enumerate(dets) if d.score >= threshold]
    out = [Candidate(dets[k], (k,)) for k in kept]
    if joined < 2 or len(kept) < 2:
        return out
    near = touching([dets[k].mask for k in kept])
    for size in range(2, joined + 1):
        for group in itertools.combinations(range(len(kept)), size):
            if _connected(group, near):
                members = tuple(kept[i] for i in group)
                out.append(Candidate(_joined([dets[k] for k in members]), members))
    return out


def touching(masks: list[np.ndarray], gap: int = TOUCH_PX) -> set[tuple[int, int]]:
    """The pairs (i, j), i < j, of masks that come within `gap` pixels of each other."""
    boxes = [mask_box(m) for m in masks]  # (x0, y0, x1, y1), the ends exclusive
    kernel = np.ones((2 * gap + 1, 2 * gap + 1), np.uint8)
    out = set()
    for i, j in itertools.combinations(range(len(masks)), 2):
        a, b = boxes[i], boxes[j]
        if a is None or b is None:
            continue
        x0, y0 = max(a[0], b[0]) - gap, max(a[1], b[1]) - gap
        x1, y1 = min(a[2], b[2]) + gap, min(a[3], b[3]) + gap
        if y0 >= y1 or x0 >= x1:
            continue  # the boxes, grown by the gap, do not meet
        y0, x0 = max(y0 - gap, 0), max(x0 - gap, 0)
        grown = cv2.dilate(masks[i][y0 : y1 + gap, x0 : x1 + gap].astype(np.uint8), kernel)
        if (grown.astype(bool) & masks[j][y0 : y1 + gap, x0 : x1 + gap]).any():
            out.add((i, j))
    return out


def _connected(group: tuple[int, ...], near: set[tuple[int, int]]) -> bool:
    """Whether the members of `group` are connected by `near`'s pairs."""
    reached, todo = {group[0]}, [group[0]]
    while todo:
        i = todo.pop()
        for j in group:
            if j not in reached and ((i, j) in near or (j, i) in near):
                reached.add(j)
                todo.append(j)
    return len(reached) == len(group)


def _joined(dets: list[Detection]) -> Detection:
    """Detections taken as one: the union of their masks and boxes, their lowest score."""
    boxes = np.array([d.box_xyxy for d in dets], np.float64)
    box = np.concatenate([boxes[:, :2].min(0), boxes[:, 2:].max(0)])
    mask = np.logical_or.reduce([d.mask for d in dets])
    return Detection(dets[0].name, min(d.score for d in dets), box, mask)


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
        """Whether the target is one of the objects the mask net knows, and not verified yet
        (a target the detection stage verified had its mask redrawn first)."""
        return (
            work.target is not None and work.verification is None and self.knows(work.target.name)
        )

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
