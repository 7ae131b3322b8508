"""The hybrid pose estimator (docs/DESIGN.md §1): Mask R-CNN detections, 64x64 square crops, 2D/4D
pose nets, and the exact geometry that turns their outputs into T_C_O.

    est = HybridPoseEstimator.from_weights()  # perception/weights/: detector, posenet_ours(_hard)
    for d in est.estimate(rgb, K):  # rgb (H, W, 3) uint8, K (3, 3) [px]
        print(d.name, d.score, d.T_C_O, d.timings_ms)

Stages (each timed, in milliseconds, per image): ``detect`` (Mask R-CNN), ``crop`` (square boxes
around the detected boxes, resampled to 64x64), ``nets`` (one batched pass of each pose net over
every detection) and ``decode`` (crop -> image pixel of the origin, then
`perception.geometry.decode`, and with expert nets the choice between their poses).

Two pose nets ship: `ours` (`DEFAULT_POSENET`), trained on upright objects alone at 0.7-0.9 m,
and its expert (`HARD_POSENET`), fine-tuned on the hard tier's scenes as well (clutter, any
resting pose, 0.9-1.6 m, occlusion). Each detection gets both poses; the expert's wins when its
silhouette agrees with the detected mask, over the pixels no other detection covers, by at
least `SWITCH_IOU` more (`perception.overlay.silhouette_agreement`).

Crops match the pose nets' training: those crops were random squares of 0.95..1.35 times the
visible box's longer side, shifted by up to 0.1 of the side; here the square is centred on the
detected box with the mean scale, `DEFAULT_CROP_SCALE` = 1.15.
"""

from __future__ import annotations

import time
from collections.abc import Collection, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from perception.crops import crop_and_resize, crop_to_image, from_unit, square_box
from perception.detector import DEFAULT_WEIGHTS, Detection, Detector, check_rgb
from perception.detector_net import DetectorConfig
from perception.geometry import decode
from perception.nets import CROP, NetConfig, PoseNet, load_posenet, normalise
from perception.overlay import silhouette_agreement
from perception.refine import PoseRefiner
from perception.support import refine_on_support, refine_with_mask
from posegrasp.core.contract import Estimate, Observation
from posegrasp.core.errors import InvalidArgumentError, UnknownNameError
from posegrasp.core.paths import WEIGHTS_DIR
from posegrasp.core.transforms import check_intrinsics, rigid_problem
from posegrasp.world.objects import OBJECT_NAMES, check_object, load_object

DEFAULT_POSENET = WEIGHTS_DIR / "posenet_ours.pt"
#: The `paper` variant's shipped nets (estimator ``hybrid-paper``).
PAPER_POSENET = WEIGHTS_DIR / "posenet_paper.pt"
#: `ours` fine-tuned on the hard tier too: the expert net next to `DEFAULT_POSENET`.
HARD_POSENET = WEIGHTS_DIR / "posenet_ours_hard.pt"
#: Square crop side / longer side of the detected box: the mean of the training range 0.95..1.35.
DEFAULT_CROP_SCALE = 1.15
STAGES: tuple[str, ...] = ("detect", "crop", "nets", "decode")
#: Silhouette IoU an expert's pose must gain over the main net's to replace it.
SWITCH_IOU = 0.05


@dataclass
class PoseDetection:
    """One detected object with its estimated pose.

    Attributes:
        name: object class.
        score: detection score in [0, 1].
        box_xyxy: detected box (x0, y0, x1, y1) [px] (pixels as docs/DESIGN.md §4), shape (4,).
        mask: visible-part mask, shape (H, W), bool.
        T_C_O: pose of the object in the camera (OpenCV) frame, metres, shape (4, 4).
        uv: pixel where the object's origin projects (2D-NET's output in the image) [px], (2,).
        crop_box: the square crop (x0, y0, side) [px] the pose nets saw.
        timings_ms: the image's per-stage wall times [ms] (`STAGES` and ``total``), shared by
            every detection of the image.
    """

    name: str
    score: float
    box_xyxy: np.ndarray
    mask: np.ndarray = field(repr=False)
    T_C_O: np.ndarray
    uv: np.ndarray
    crop_box: tuple[float, float, float]
    timings_ms: dict[str, float] = field(repr=False)


def _is_pose_in_front(T: np.ndarray) -> bool:
    """A rigid transform whose origin lies in front of the camera."""
    return rigid_problem(T) is None and bool(T[2, 3] > 0)


class HybridPoseEstimator:
    """Detector + pose nets + geometry, weights loaded once.

    Args:
        detector: the object extractor.
        posenet: the 2D/4D pose nets (one class slice per object, index = obj_id - 1).
        crop_scale: square crop side as a multiple of the detected box's longer side.
        experts: more pose nets of the same classes. Each detection then gets every net's pose,
            and an expert's replaces `posenet`'s when its silhouette agrees better with the
            detected mask by at least `SWITCH_IOU` (`silhouette_agreement`).
    """

    def __init__(
        self,
        detector: Detector,
        posenet: PoseNet,
        crop_scale: float = DEFAULT_CROP_SCALE,
        experts: Sequence[PoseNet] = (),
    ) -> None:
        if not np.isfinite(crop_scale) or crop_scale <= 0:
            raise InvalidArgumentError(f"crop_scale must be positive, got {crop_scale}")
        if posenet.cfg.n_classes != len(OBJECT_NAMES):
            raise InvalidArgumentError(
                f"the pose nets have {posenet.cfg.n_classes} classes, need {len(OBJECT_NAMES)}"
            )
        for net in experts:
            if (net.cfg.n_classes, net.cfg.crop) != (posenet.cfg.n_classes, posenet.cfg.crop):
                raise InvalidArgumentError(
                    "the expert pose nets must have the same classes and crop size"
                )
        self.detector = detector
        self.posenet = posenet.eval()
        self.experts = [net.eval() for net in experts]
        self.crop_scale = float(crop_scale)

    @classmethod
    def from_weights(
        cls,
        detector_path: Path | str = DEFAULT_WEIGHTS,
        posenet_path: Path | str = DEFAULT_POSENET,
        score_threshold: float = 0.5,
        crop_scale: float = DEFAULT_CROP_SCALE,
        max_detections: int | None = None,
        verify: bool = True,
        expert_paths: Sequence[Path | str] | None = None,
    ) -> HybridPoseEstimator:
        """Load the shipped weights (defaults under perception/weights/); `expert_paths` are
        the weights of the expert pose nets (see the class); None: `HARD_POSENET` with the
        default `posenet_path`, none with another.

        `verify` checks each file against the hash its folder's manifest records; pass False
        (or set ``POSEGRASP_UNVERIFIED_WEIGHTS=1``) for weights you trained.

        Raises:
            AssetError: missing or corrupt weights, saying how to rebuild them;
                `WeightsMismatchError` when a manifest records another hash.
        """
        detector = Detector.from_weights(
            Path(detector_path),
            verify,
            score_threshold=score_threshold,
            max_detections=max_detections,
        )
        if expert_paths is None:
            expert_paths = (HARD_POSENET,) if Path(posenet_path) == DEFAULT_POSENET else ()
        experts = [load_posenet(Path(e), verify) for e in expert_paths]
        return cls(detector, load_posenet(Path(posenet_path), verify), crop_scale, experts)

    @classmethod
    def with_random_weights(
        cls,
        seed: int = 0,
        score_threshold: float = 0.0,
        max_detections: int | None = None,
        detector_config: DetectorConfig | None = None,
        posenet_config: NetConfig | None = None,
    ) -> HybridPoseEstimator:
        """Both networks with seeded random weights: for tests and for timing the architecture
        before any training (its poses are meaningless)."""
        detector = Detector.random(
            detector_config, seed, score_threshold=score_threshold, max_detections=max_detections
        )
        with torch.random.fork_rng():
            torch.manual_seed(seed + 1)
            posenet = PoseNet(posenet_config or NetConfig())
        return cls(detector, posenet)

    def estimate_timed(
        self, rgb: np.ndarray, K: np.ndarray, classes: Collection[str] | None = None
    ) -> tuple[list[PoseDetection], dict[str, float]]:
        """`estimate`, also returning the image's per-stage times [ms] (also when nothing is
        detected)."""
        found, _others, timings = self.estimate_split(rgb, K, classes)
        return found, timings

    def estimate_split(
        self,
        rgb: np.ndarray,
        K: np.ndarray,
        classes: Collection[str] | None = None,
        others: bool = False,
        wanted_score: float | None = None,
        others_experts: bool = True,
    ) -> tuple[list[PoseDetection], list[PoseDetection], dict[str, float]]:
        """Detect once; poses of the detections of `classes` (all when None) and, with `others`,
        of the remaining detections in a second pass of the nets. With `wanted_score`, a
        detection of `classes` needs that score and the others the detector's threshold.
        Without `others_experts`, the other detections get the main net's pose alone.

        Returns:
            (poses of `classes`, poses of the other detections (empty without `others`),
            per-stage times [ms] shared by both lists).
        """
        rgb = check_rgb(rgb)
        K = check_intrinsics(K)
        if classes is not None:
            for c in classes:
                if c not in OBJECT_NAMES:
                    raise UnknownNameError("object", c, OBJECT_NAMES)
        timings: dict[str, float] = dict.fromkeys(STAGES, 0.0)
        t0 = time.perf_counter()
        if wanted_score is None:
            dets = self.detector.detect(rgb)
        else:
            floor = self.detector.score_threshold
            dets = [
                d
                for d in self.detector.detect(rgb, min(floor, wanted_score))
                if d.score >= (wanted_score if classes is None or d.name in classes else floor)
            ]
        timings["detect"] = (time.perf_counter() - t0) * 1000.0
        wanted = dets if classes is None else [d for d in dets if d.name in classes]
        found = self._poses(rgb, K, wanted, timings, dets)
        rest = [d for d in dets if classes is not None and d.name not in classes] if others else []
        other = self._poses(rgb, K, rest, timings, dets, others_experts) if rest else []
        timings["total"] = float(sum(timings[k] for k in STAGES))
        return found, other, timings

    def detections_and_poses(
        self, rgb: np.ndarray, K: np.ndarray
    ) -> tuple[list[Detection], list[PoseDetection], dict[str, float]]:
        """Detect once: every detection, of any class the detector knows (user objects too when
        it was fine-tuned on them), the poses of those the nets know, and the stage times [ms].
        """
        rgb = check_rgb(rgb)
        K = check_intrinsics(K)
        timings: dict[str, float] = dict.fromkeys(STAGES, 0.0)
        t0 = time.perf_counter()
        dets = self.detector.detect(rgb)
        timings["detect"] = (time.perf_counter() - t0) * 1000.0
        poses = self._poses(rgb, K, dets, timings, dets)
        timings["total"] = float(sum(timings[k] for k in STAGES))
        return dets, poses, timings

    def _poses(
        self,
        rgb: np.ndarray,
        K: np.ndarray,
        dets: list[Detection],
        timings: dict[str, float],
        scene: Sequence[Detection] = (),
        experts: bool = True,
    ) -> list[PoseDetection]:
        """Crop, nets and decode for some detections (`scene`: all the image's detections, whose
        masks may hide an object); adds each stage's time to `timings`. A detection of a class
        the nets were not trained on (a detector fine-tuned on user objects) gets no pose."""
        t1 = time.perf_counter()
        kept: list[tuple[Detection, tuple[float, float, float]]] = []
        crops = []
        for d in dets:
            if d.name not in OBJECT_NAMES:
                continue
            x0, y0, x1, y1 = d.box_xyxy
            if not (np.all(np.isfinite(d.box_xyxy)) and x1 > x0 and y1 > y0):
                continue
            box = square_box(d.box_xyxy, scale=self.crop_scale)
            kept.append((d, box))
            crops.append(crop_and_resize(rgb, box, self.posenet.cfg.crop))
        t2 = time.perf_counter()
        outs = []
        if kept:
            x = normalise(torch.from_numpy(np.stack(crops)))
            cls = torch.tensor([OBJECT_NAMES.index(d.name) for d, _ in kept])
            size = torch.tensor([box[2] / K[0, 0] for _, box in kept], dtype=torch.float32)
            with torch.inference_mode():
                for net in (self.posenet, *(self.experts if experts else ())):
                    out = net(x, cls, size)
                    outs.append([t.double().numpy() for t in (out.uv_unit, out.p, out.theta)])
        t3 = time.perf_counter()
        results = []
        for i, (d, box) in enumerate(kept):
            cands = []
            for uv_unit, p, theta in outs:
                uv = crop_to_image(from_unit(uv_unit[i], CROP), box, CROP)
                if not np.all(np.isfinite(p[i])) or np.linalg.norm(p[i]) < 1e-9:
                    continue
                T = decode(p[i], float(theta[i]), uv, K)
                if _is_pose_in_front(T):
                    cands.append((T, uv))
            if not cands:
                continue
            T, uv = cands[0]
            if len(cands) > 1:
                hidden = [e.mask for e in scene if e is not d]
                iou = silhouette_agreement(d.name, [c[0] for c in cands], K, d.mask, hidden)
                if iou.max() >= iou[0] + SWITCH_IOU:
                    T, uv = cands[int(np.argmax(iou))]
            results.append(PoseDetection(d.name, d.score, d.box_xyxy, d.mask, T, uv, box, timings))
        t4 = time.perf_counter()
        for stage, dt in zip(STAGES[1:], np.diff([t1, t2, t3, t4]) * 1000.0, strict=True):
            timings[stage] += float(dt)
        return results

    def estimate(
        self, rgb: np.ndarray, K: np.ndarray, classes: Collection[str] | None = None
    ) -> list[PoseDetection]:
        """Detect every object in an image and estimate its pose.

        Args:
            rgb: image, shape (H, W, 3), uint8.
            K: intrinsics of the image, shape (3, 3) [px].
            classes: only these classes (None: all); the others skip the crop and nets stages.

        Returns:
            One `PoseDetection` per detection with a valid pose, highest score first; empty
            when nothing is detected. A pose that does not decode to a proper rigid transform
            in front of the camera is left out.

        Raises:
            InvalidArgumentError: rgb is not (H, W, 3) uint8 with H, W >= 1, or K is not a
                valid pinhole matrix.
            UnknownNameError: an unknown class in `classes`.
        """
        return self.estimate_timed(rgb, K, classes)[0]

    def as_episode_estimator(
        self,
        support: bool = False,
        mask_fit: bool = True,
        name: str | None = None,
        refine: bool = False,
    ) -> HybridEpisodeEstimator:
        """This estimator behind the episode interface (`posegrasp.core.contract.PoseEstimator`);
        `support` puts each pose onto the observation's table and, with `mask_fit`, fits its yaw
        and position on the table to the detected mask (`perception.support`); `refine` refines
        it against the detected mask and the image (`perception.refine`). `name` names it in
        results (default ``hybrid``, ``hybrid-table`` or ``hybrid-refine``)."""
        return HybridEpisodeEstimator(self, support, mask_fit, name, refine)


@dataclass(frozen=True)
class TargetDetections:
    """The detections of one image, split around the requested object.

    Attributes:
        best: the highest-scoring detection of the requested class, or None.
        found: every detection of that class.
        others: the detections of the other classes.
        info: the estimate's description so far: ``detected``, ``timings_ms`` and, when found,
            ``class``, ``score``, ``box_xyxy``, ``uv`` and ``detections``; for a class the nets
            were not trained on, ``note`` says so.
        neighbours: the other classes' poses, (class, T_C_N) pairs.
    """

    best: PoseDetection | None
    found: list[PoseDetection]
    others: list[PoseDetection]
    info: dict
    neighbours: tuple[tuple[str, np.ndarray], ...]

    def occluder(self) -> np.ndarray | None:
        """Where another detection may hide the target: the union of every other mask."""
        return occluder_of([*self.found, *self.others], self.best)


def occluder_of(detections: list, hidden: object) -> np.ndarray | None:
    """Where the other detections may hide `hidden` (one of `detections`, or None): the union
    of every other one's mask, or None when there is no other."""
    masks = [d.mask for d in detections if d is not hidden]
    return np.logical_or.reduce(masks) if masks else None


def detect_target(
    estimator: HybridPoseEstimator,
    obs: Observation,
    target_score: float | None = None,
    others_experts: bool = True,
) -> TargetDetections:
    """Detect once and split the detections around ``obs.object`` (a detection of it needs
    `target_score`, when given, and the others the detector's threshold; without
    `others_experts` the others get the main net's pose alone); an object the nets were not
    trained on (a user object) is not looked for, and ``info["note"]`` says why.

    Raises:
        UnknownNameError: obs.object is no known object at all.
    """
    if obs.object not in OBJECT_NAMES:
        check_object(obs.object)
        note = (
            f"the learned estimators know the six objects they were trained on "
            f"({', '.join(OBJECT_NAMES)}), not {obs.object!r}"
        )
        return TargetDetections(None, [], [], {"detected": False, "note": note}, ())
    found, others, timings = estimator.estimate_split(
        obs.rgb,
        obs.K,
        classes=(obs.object,),
        others=True,
        wanted_score=target_score,
        others_experts=others_experts,
    )
    info: dict = {"detected": bool(found), "timings_ms": dict(timings)}
    neighbours = tuple((d.name, d.T_C_O.copy()) for d in others)
    best = max(found, key=lambda d: d.score) if found else None
    if best is not None:
        info |= {
            "class": best.name,
            "score": float(best.score),
            "box_xyxy": [float(v) for v in best.box_xyxy],
            "uv": [float(v) for v in best.uv],
            "detections": len(found),
        }
    return TargetDetections(best, found, others, info, neighbours)


class HybridEpisodeEstimator:
    """`posegrasp.core.contract.PoseEstimator` for episodes: the pose of the highest-scoring
    detection of the requested class, or None when it is not detected. Ignores the privileged
    ground truth.

    With `support` (name ``hybrid-table``) the pose is then moved onto the known table top
    (`perception.support.refine_on_support`): nearest resting pose, and the distance along the
    origin's ray at which the object touches the table; with `mask_fit` its yaw and position on
    the table are then fitted to the detected mask (`perception.support.refine_with_mask`).
    Without a known table (``obs.table_top_z`` None) the network pose is kept.

    With `refine` (name ``hybrid-refine``) the pose is then refined by render-and-compare against
    the detected mask and the image (`perception.refine.PoseRefiner`), with the other detections'
    masks as possible occluders.

    Each `Estimate`'s ``info`` holds ``detected``, ``class``, ``score``, ``box_xyxy``, ``uv``,
    ``timings_ms`` (per stage), with `support`, ``support`` (resting pose, tilt removed [deg],
    shift along the ray [m], what was applied), with `refine`, ``refine`` (the refiner's info)
    and the stage ``refine`` in ``timings_ms``; its ``neighbours`` are the other detected objects
    as (class, T_C_N) pairs.
    """

    def __init__(
        self,
        estimator: HybridPoseEstimator,
        support: bool = False,
        mask_fit: bool = True,
        name: str | None = None,
        refine: bool = False,
    ) -> None:
        self.estimator = estimator
        self.support = bool(support)
        self.mask_fit = bool(mask_fit)
        self.refiner = PoseRefiner() if refine else None
        default = "hybrid-table" if self.support else "hybrid-refine" if refine else "hybrid"
        self.name = name or default

    def estimate(self, obs: Observation) -> Estimate:
        """T_C_O (4, 4) of obs.object in obs.rgb (None when not detected), the other detections
        and the description of the estimate."""
        target = detect_target(self.estimator, obs)
        info, neighbours, best = target.info, target.neighbours, target.best
        if best is None:
            return Estimate(None, neighbours, info)
        T = best.T_C_O.copy()
        if self.support and obs.table_top_z is not None:
            t0 = time.perf_counter()
            model = load_object(best.name)
            ref = refine_on_support(T, obs.T_world_cam, model, obs.table_top_z)
            sup = ref.description()
            T = ref.T_C_O
            if self.mask_fit and "translation" in ref.applied:
                fit = refine_with_mask(T, obs.T_world_cam, obs.K, model, best.mask)
                T = fit.T_C_O
                sup |= {
                    "mask_iou_before": fit.iou_before,
                    "mask_iou_after": fit.iou_after,
                    "mask_yaw_deg": fit.yaw_deg,
                    "mask_shift_m": list(fit.shift_m),
                }
                sup["applied"].append("mask_fit")
            info["timings_ms"]["support"] = (time.perf_counter() - t0) * 1000
            info["support"] = sup
        if self.refiner is not None:
            t0 = time.perf_counter()
            occluder = target.occluder()
            T, ref_info = self.refiner.refine(best.name, T, obs.K, best.mask, obs.rgb, occluder)
            info["timings_ms"]["refine"] = (time.perf_counter() - t0) * 1000
            info["refine"] = ref_info
        return Estimate(T, neighbours, info)
