"""Any orientation: global hypotheses, each refined by render-and-compare, verified, the best kept.

The learned 4D-NET knows upright objects seen from the head camera; on any other orientation it
is far off. This estimator does not ask it to learn the sphere. Per detection of the requested
class (the shipped Mask R-CNN fine-tuned on the tiers' scenes, `TIERS_DETECTOR`):

1. **Hypotheses**: the viewpoint codebook (`perception.codebook`) matches the detected mask
   against silhouettes of the object over all of SO(3) and gives the `GlobalConfig.hypotheses`
   best poses that differ by at least `GlobalConfig.min_angle_deg`; the hybrid nets' own pose
   joins them. A mask another detection or the image's edge touches is also framed as if the
   object went on behind it (`GlobalConfig.occluded_grow`, `perception.codebook.occluded_views`).
2. **Refinement**: each is refined by the render-and-compare refiner (`perception.refine`)
   against the detected mask and the image (its basin is about 10-15 deg; the codebook's grid
   puts one hypothesis within it); after one run all are scored and the
   `GlobalConfig.keep_after_first` best get the further runs (`GlobalConfig.refine_passes` in
   all).
3. **Verification**: each refined pose is scored by its silhouette IoU with the visible mask,
   plus `GlobalConfig.appearance_weight` times the correlation of the parts' colours drawn at
   that pose with the image, plus `GlobalConfig.edge_weight` times the share of the parts'
   outlines that lie on image edges (both `perception.codebook.verification_scores`); the best
   one wins. Objects rest on something: with the camera's pose, a refined pose within
   `GlobalConfig.resting_tilt_deg` of one of the object's resting poses (any turn about the
   vertical) wins over one that is not; the best few that could be resting are turned onto
   their resting poses and refined once more turning about the vertical only, and the best of
   those wins (`GlobalConfig.snap_candidates`). The winner's
   score is reported as the estimate's confidence; below `GlobalConfig.min_score` the estimate
   is withheld (``no_estimate``).
4. **Support**: the visible part of a half-hidden object does not fix its distance along the
   viewing ray; the objects around it, which rest on the same table, do. When the best score
   is low (`GlobalConfig.second_look_below`), the neighbouring detections are verified the same
   way, and the target's pose slides along its ray onto the surface the confident ones rest on
   (`GlobalConfig.support_neighbours`).

Inputs are the image, K, the camera's pose (for gravity) and the requested class: no table
height, no depth.
Codebooks are built once per object and grid and cached under the data folder
(``$POSEGRASP_DATA/codebooks``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from scipy import ndimage

from perception.codebook import (
    Codebook,
    ConvexParts,
    MaskView,
    SilhouetteSource,
    frame_mask,
    hypothesis_pose,
    image_edges,
    occluded_views,
    resting_templates,
    rotation_cosines,
    top_hypotheses,
)
from perception.detector import TIERS_DETECTOR, Detection
from perception.hybrid import HybridPoseEstimator, PoseDetection, detect_target, occluder_of
from perception.mask_net import MaskRefiner
from perception.overlay import mask_box
from perception.refine import PoseRefiner, RefineConfig
from perception.support import refine_on_support, resting_surface_z, snap_to_resting
from perception.verification import (
    OnThisProcess,
    Start,
    Verified,
    VerifyHelper,
    VerifyJob,
    rank_verified,
)
from posegrasp.core.contract import Estimate, Observation
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.paths import data_root
from posegrasp.core.transforms import quat_to_mat
from posegrasp.world.objects import OBJECT_NAMES, ObjectModel, load_object


@dataclass(frozen=True)
class GlobalConfig:
    """Settings of `GlobalPoseEstimator`.

    Attributes:
        views: viewpoints of the codebook's sphere grid.
        inplane: in-plane turns per viewpoint.
        hypotheses: codebook hypotheses refined per detection (the nets' pose comes on top).
        min_angle_deg: hypotheses differ by at least this rotation [deg].
        refine_passes: refiner runs per hypothesis.
        keep_after_first: after the first refiner run and scoring, only this many of the best
            hypotheses get the further runs and are scored again (0: all of them).
        appearance_weight: weight of the colour correlation in the verification score.
        edge_weight: weight of the outlines' agreement with image edges in it.
        min_score: a best score below this withholds the estimate.
        occluded_grow: where another detection or the image's edge touches the mask, the
            codebook also matches it framed by boxes this many times its own, grown towards
            where it is cut off, with the occluder's pixels and those beyond the image not held
            against a template (empty: the mask's own box only).
        screen_iterations: refiner steps of the first run that every start gets, before the
            scoring that picks the `keep_after_first` best for the further runs (0: the
            refiner's full run; used only with `keep_after_first`).
        resting_tilt_deg: with the camera's pose known, refined starts within this rotation of
            one of the object's resting poses (any turn about the vertical) rank above the
            others, so a pose the object could not rest in wins only when no start could
            (None: no such preference, as for images without gravity).
        snap_candidates: with `resting_tilt_deg`, this many of the best refined starts within
            `snap_tilt_deg` of a resting pose are each turned onto it (heading kept) and refined
            again, one run, turning about the vertical only; the best of these wins (0: none)
            unless all of them score more than `SNAP_SCORE_DROP` below the best pose of all (the
            object is not resting). A start off by a few degrees is often mostly tilted, so it is
            snapped, not passed over.
        snap_tilt_deg: the largest tilt from a resting pose [deg] a start may have to be
            snapped.
        resting_hypotheses: with `resting_tilt_deg` and the camera's pose, this many more
            codebook hypotheses, the best among the templates that give a pose within
            `resting_tilt_deg` of resting (and `min_angle_deg` from the others): under
            occlusion a partial mask fits many poses an object could not rest in (0: none).
        snap_iterations: refiner steps of a snapped start's run (turning about the vertical
            only, it has four unknowns, not six).
        neighbour_experts: the other detections' poses (the planner's obstacles) come from the
            nets and their expert, as `hybrid`'s (False: from the main net alone, faster).
        mask_net: the requested object's mask is redrawn at the image's full resolution by the
            mask net (`perception.mask_net`) before its hypotheses and refinement: the
            detector's coarse mask loses thin parts and puts the outline a pixel or two off,
            which the fit turns into distance along the viewing ray (False: the detector's).
        second_look: when the best verified pose scores below `second_look_below`, this many
            more codebook hypotheses (the next best, `min_angle_deg` apart from the first ones)
            are refined and verified with the first ones, and the choice is made again: an
            ambiguous partial mask gets more starts, a clear one does not pay for them (0: none).
        second_look_below: the verification score under which the second look runs.
        second_look_resting: with `resting_tilt_deg` and the camera's pose, the second look
            also refines this many resting hypotheses (as `resting_hypotheses`).
        support_neighbours: when the best verified pose scores below `second_look_below` and
            is within `resting_tilt_deg` of resting, up to this many other detections of
            other classes (those touching the target's mask first, then the nearest) are
            verified in turn, until `SUPPORT_ENOUGH` of them give a confident resting pose
            (score at least `support_score`, within `resting_tilt_deg` of resting). The median
            height of the surface those rest on is the target's support: when the target's
            own pose puts it more than `support_tolerance_m` above or below it, the pose is
            slid along its camera ray onto it (`perception.support.refine_on_support`). The
            objects of a scene share their table; the outline of a half-hidden object does
            not fix its distance, a fully seen neighbour's does (0: none).
        support_score: the verification score a neighbour's pose needs to count.
        support_tolerance_m: how far [m] the target's own resting surface may lie from its
            neighbours' before its pose is moved.
        table: when the observation carries the table's height (`Observation.table_top_z`, a
            prior of the scene, not of the image), the verified pose is put onto it: its
            rotation snapped to the nearest resting pose and its origin slid along its camera
            ray until the object rests on the table (`perception.support.refine_on_support`, as
            `hybrid-table`); the silhouette does not fix the distance of a half-hidden object,
            the table does (False: RGB, K and the camera's pose only).
        target_score: the detector score a detection of the requested object needs (the
            other detections, the planner's obstacles and the occluders, need the detector's
            own threshold); a partly hidden object often scores lower, and the verification
            reports how well the pose fits (None: the detector's threshold for all).
        refine_max_shift: a refiner run that moves a start further than this fraction of its
            distance is rejected (`perception.refine.RefineConfig.max_shift`, there 0.1). A
            hypothesis framed as if the object went on behind an occluder, or drawn from a
            coarse template, often starts 15-25 % off in distance along its ray; the verification
            rejects a run that went astray, so the guard can be wider than for a single start.
        refine_max_rotation_deg: a refiner run that turns a start further is rejected (there
            20 deg) [deg].
        max_inplane_deg: a refined pose whose in-plane angle (the roll of the virtual camera
            C', `perception.geometry.encode`'s theta) lies within this many degrees of zero
            ranks above one that does not: a prior of the paper's protocol, whose views are
            drawn with the in-plane angle in -60..60 deg, as the gravity of `resting_tilt_deg`
            is the tiers'. A silhouette turned half way round about the viewing ray is the
            same silhouette; the protocol never shows it. Views within
            `perception.verification.POLE_DEG` of the object's z axis, where the angle is not
            defined, always count as within (None: no such preference).
        verify_processes: the processes that share the codebook matching and each batch of
            starts to refine and score: this one and, with 2, a helper process
            (`perception.verification.VerifyHelper`) that matches the later half of the
            templates and runs every other start, started in the second estimate (a process
            that makes one never starts it). The helper runs only while this process
            computes on more than one thread (torch's thread count): an evaluation's workers,
            one thread each, already fill the cores. Every result is the same on either
            process.
    """

    views: int = 1000
    inplane: int = 24
    hypotheses: int = 12
    min_angle_deg: float = 15.0
    refine_passes: int = 2
    keep_after_first: int = 2
    appearance_weight: float = 0.05
    edge_weight: float = 0.3
    min_score: float = 0.0
    occluded_grow: tuple[float, ...] = (1.3, 1.6)
    screen_iterations: int = 2
    resting_tilt_deg: float | None = 10.0
    snap_candidates: int = 5
    snap_tilt_deg: float = 25.0
    snap_iterations: int = 6
    resting_hypotheses: int = 0
    second_look: int = 12
    second_look_below: float = 1.15
    second_look_resting: int = 12
    support_neighbours: int = 3
    support_score: float = 1.15
    support_tolerance_m: float = 0.012
    table: bool = False
    target_score: float | None = 0.3
    neighbour_experts: bool = False
    mask_net: bool = True
    refine_max_shift: float = 0.3
    refine_max_rotation_deg: float = 30.0
    max_inplane_deg: float | None = None
    verify_processes: int = 2

    def __post_init__(self) -> None:
        for key in ("views", "inplane", "hypotheses", "refine_passes"):
            if int(getattr(self, key)) < 1:
                raise InvalidArgumentError(f"GlobalConfig.{key} must be >= 1")
        if min(int(self.resting_hypotheses), int(self.second_look), self.support_neighbours) < 0:
            raise InvalidArgumentError(
                "GlobalConfig.resting_hypotheses, second_look and support_neighbours must be >= 0"
            )
        if not (np.isfinite(self.support_tolerance_m) and self.support_tolerance_m >= 0):
            raise InvalidArgumentError("GlobalConfig.support_tolerance_m must be >= 0 [m]")
        if int(self.snap_iterations) < 1:
            raise InvalidArgumentError("GlobalConfig.snap_iterations must be >= 1")
        if int(self.screen_iterations) < 0:
            raise InvalidArgumentError("GlobalConfig.screen_iterations must be >= 0 (0: all)")
        if int(self.snap_candidates) < 0 or not 0 < self.snap_tilt_deg < 180:
            raise InvalidArgumentError(
                "GlobalConfig.snap_candidates must be >= 0 and snap_tilt_deg in (0, 180)"
            )
        if int(self.keep_after_first) < 0:
            raise InvalidArgumentError("GlobalConfig.keep_after_first must be >= 0 (0: all)")
        if not (0 <= self.min_angle_deg < 180 and np.isfinite(self.appearance_weight)):
            raise InvalidArgumentError("GlobalConfig.min_angle_deg must be in [0, 180)")
        if self.resting_tilt_deg is not None and not 0 < self.resting_tilt_deg < 180:
            raise InvalidArgumentError("GlobalConfig.resting_tilt_deg must be in (0, 180) or None")
        if self.target_score is not None and not 0 <= self.target_score <= 1:
            raise InvalidArgumentError("GlobalConfig.target_score must be in [0, 1] or None")
        if not (0 < self.refine_max_shift <= 1 and 0 < self.refine_max_rotation_deg <= 180):
            raise InvalidArgumentError(
                "GlobalConfig.refine_max_shift must be in (0, 1] and refine_max_rotation_deg in "
                "(0, 180]"
            )
        if self.max_inplane_deg is not None and not 0 < self.max_inplane_deg < 180:
            raise InvalidArgumentError("GlobalConfig.max_inplane_deg must be in (0, 180) or None")
        if self.verify_processes not in (1, 2):
            raise InvalidArgumentError("GlobalConfig.verify_processes must be 1 or 2")
        if not all(1 < g <= 4 for g in self.occluded_grow):
            raise InvalidArgumentError("GlobalConfig.occluded_grow factors must lie in (1, 4]")


#: A start snapped onto its resting pose is kept unless its verification score drops by more
#: (the score, not the IoU alone: the detector's mask is often fitted a little better by a tilt
#: that the image's edges refute); the snapped starts win only if the best of them scores
#: within this much of the best pose of all.
SNAP_SCORE_DROP = 0.05

#: Image edges are searched in the mask's box grown by this much [px].
EDGE_MARGIN_PX = 10

#: Neighbours are verified until this many give a confident resting pose
#: (`GlobalConfig.support_neighbours`).
SUPPORT_ENOUGH = 2

#: A neighbour whose mask comes this close to the target's [px] touches it.
NEIGHBOUR_TOUCH_PX = 6


def _grown(box: tuple[int, int, int, int], margin: int, shape: tuple[int, ...]):
    """`box` (x0, y0, x1, y1) grown by `margin` [px] on each side, inside an image of `shape`."""
    x0, y0, x1, y1 = box
    H, W = shape[:2]
    return max(0, x0 - margin), max(0, y0 - margin), min(W, x1 + margin), min(H, y1 + margin)


class CodebookCache:
    """Codebooks by object, built on first use and kept on disk (`folder`) and in memory."""

    def __init__(
        self,
        views: int,
        inplane: int,
        folder: Path | None = None,
        source: SilhouetteSource | None = None,
    ) -> None:
        self.views, self.inplane = views, inplane
        self.folder = folder if folder is not None else data_root() / "codebooks"
        self.source = source or ConvexParts()
        self._books: dict[str, Codebook] = {}

    def get(self, name: str) -> Codebook:
        """The codebook of object `name`."""
        if name not in self._books:
            path = self.folder / f"{name}_{self.views}x{self.inplane}.npz"
            try:
                book = Codebook.load(name, path)
            except (OSError, KeyError, ValueError):
                book = Codebook.build(name, self.views, self.inplane, self.source)
                try:
                    book.save(path)
                except OSError:
                    pass  # a read-only data folder: the codebook stays in memory
            self._books[name] = book
        return self._books[name]


class GlobalPoseEstimator:
    """The estimator ``hybrid-global`` (see the module docstring).

    Args:
        hybrid: the detector and pose nets (`HybridPoseEstimator.from_weights()`).
        config: the settings.
        codebooks: where codebooks come from (default: built from the convex parts and cached
            in the data folder).
        name: the name results carry.
        masks: the mask net that redraws the target's mask (`GlobalConfig.mask_net`; default:
            the shipped one when the config asks for it).
    """

    def __init__(
        self,
        hybrid: HybridPoseEstimator,
        config: GlobalConfig | None = None,
        codebooks: CodebookCache | None = None,
        name: str = "hybrid-global",
        masks: MaskRefiner | None = None,
    ) -> None:
        self.hybrid = hybrid
        self.config = config or GlobalConfig()
        self.masks = (masks or MaskRefiner.from_weights()) if self.config.mask_net else None
        self.codebooks = codebooks or CodebookCache(self.config.views, self.config.inplane)
        self.refiner = PoseRefiner(
            RefineConfig(
                max_shift=self.config.refine_max_shift,
                max_rotation_deg=self.config.refine_max_rotation_deg,
            )
        )
        self._verify_helper: VerifyHelper | None = None
        self._estimates = 0  # made so far (the helper starts in the second)
        self._no_helper = False  # a helper could not be started
        self.name = name
        self._colours: dict[str, np.ndarray] = {}

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

    def colours(self, name: str) -> np.ndarray:
        """RGB of each convex piece of `name` (`ObjectModel.convex_pieces`, the source's order),
        (pieces, 3) in [0, 1]."""
        if name not in self._colours:
            pieces = load_object(name).convex_pieces()
            self._colours[name] = np.array([rgba[:3] for _, rgba in pieces])
        return self._colours[name]

    def _resting_hypotheses(
        self,
        book: Codebook,
        model: ObjectModel,
        views: list[MaskView],
        scores: np.ndarray,
        top: list[int],
        K: np.ndarray,
        R_W_C: np.ndarray,
        count: int,
    ) -> list[int]:
        """The best `count` templates (of `scores`, every framing's in turn) that give a pose
        within `GlobalConfig.resting_tilt_deg` of resting, each `GlobalConfig.min_angle_deg`
        from the others and from those in `top`."""
        cfg = self.config
        n = len(book.rotations)
        ups = np.array([quat_to_mat(np.asarray(q, float))[2] for q in model.resting_poses.values()])
        assert cfg.resting_tilt_deg is not None
        keep = np.concatenate(
            [resting_templates(book, v, K, R_W_C[2], ups, cfg.resting_tilt_deg) for v in views]
        )
        if not keep.any():
            return []
        want = count + len(top)
        found = top_hypotheses(
            np.where(keep, scores, -np.inf), book.rotations, want, cfg.min_angle_deg
        )
        R = book.rotations
        found = [i for i in found if keep[i]]
        if not found or not top:
            return found[:count]
        near = rotation_cosines(R[np.array(found) % n], R[np.array(top) % n])
        new = np.array(found)[~(near > math.cos(math.radians(cfg.min_angle_deg))).any(1)]
        return [int(i) for i in new[:count]]

    def _helper(self) -> VerifyHelper | None:
        """The helper process that shares the codebook matching and each batch of starts
        (`GlobalConfig.verify_processes`), started in the second estimate (its start-up, about
        a second of one core, would only slow a process that makes one); None before, and
        while this process computes on one thread (as an evaluation's workers do: they already
        fill the cores)."""
        import torch

        if self.config.verify_processes < 2 or torch.get_num_threads() < 2:
            return None
        if self._verify_helper is None and (self._estimates < 2 or self._no_helper):
            return None
        if self._verify_helper is None:
            try:  # it is handed one end of a socket pair: POSIX systems
                self._verify_helper = VerifyHelper()
            except (OSError, ValueError):  # no process to start here: all of it on this one
                self._no_helper = True
                return None
        return self._verify_helper

    def verify(
        self,
        det: PoseDetection | Detection,
        K: np.ndarray,
        rgb: np.ndarray,
        occluder: np.ndarray | None,
        R_W_C: np.ndarray | None = None,
        second_look: bool = True,
    ) -> tuple[list[Verified], dict[str, float]]:
        """Every hypothesis of one detection, refined and scored, best first (with
        `GlobalConfig.keep_after_first`, the ones refined further first; with the camera's
        rotation in the world `R_W_C` and `GlobalConfig.resting_tilt_deg`, those near a resting
        pose before the others), and the stage times [ms] (``hypotheses``, ``verify``, and
        ``second_look`` within ``verify`` when `GlobalConfig.second_look` ran; with
        `second_look` False it never runs). A detection without the nets' pose (of an object
        they were not trained on) starts from the codebook alone."""
        cfg = self.config
        model = load_object(det.name)
        max_tilt = cfg.resting_tilt_deg if R_W_C is not None and model.resting_poses else None
        t0 = time.perf_counter()
        helper = self._helper() or OnThisProcess  # shares the matching and the starts
        starts: list[tuple[np.ndarray, str]] = []
        second: Callable[[], list[tuple[np.ndarray, str]]] | None = None  # drawn on demand
        if isinstance(det, PoseDetection):
            starts.append((det.T_C_O, "nets"))
        view = frame_mask(det.mask)
        if view is not None:
            book = self.codebooks.get(det.name)
            views = occluded_views(det.mask, occluder, view, cfg.occluded_grow) or [view]
            scores = helper.match(book, [(v.bits, v.hidden) for v in views])
            n = len(book.rotations)
            top = top_hypotheses(scores, book.rotations, cfg.hypotheses, cfg.min_angle_deg)
            if cfg.resting_hypotheses and max_tilt is not None:
                assert R_W_C is not None
                top += self._resting_hypotheses(
                    book, model, views, scores, top, K, R_W_C, cfg.resting_hypotheses
                )
            for i in top:
                starts.append((hypothesis_pose(book, i % n, views[i // n], K), "codebook"))

            def second_starts() -> list[tuple[np.ndarray, str]]:
                """The second look's hypotheses, drawn only when it runs."""
                found = cfg.hypotheses + cfg.second_look
                later = top_hypotheses(scores, book.rotations, found, cfg.min_angle_deg)
                later = [i for i in later[cfg.hypotheses :] if i not in top]
                if cfg.second_look_resting and max_tilt is not None:
                    assert R_W_C is not None
                    later += self._resting_hypotheses(
                        book, model, views, scores, top + later, K, R_W_C, cfg.second_look_resting
                    )
                return [(hypothesis_pose(book, i % n, views[i // n], K), "codebook") for i in later]

            second = second_starts
        t1 = time.perf_counter()
        tight = mask_box(det.mask) if view is not None else (0, 0, 1, 1)
        box = _grown(tight, EDGE_MARGIN_PX, det.mask.shape)
        job = VerifyJob(
            name=det.name,
            parts=self.refiner.part_vertices(det.name),
            pieces=self.codebooks.source.pieces(det.name),
            colours=self.colours(det.name),
            K=K,
            rgb=rgb,
            mask=det.mask,
            edge_distance=image_edges(rgb, box),
            box=box,
            target=self.refiner.prepare(K, det.mask, rgb, occluder),  # the shorter runs' too
            refine=self.refiner.config,
            appearance_weight=cfg.appearance_weight,
            edge_weight=cfg.edge_weight,
            max_tilt=max_tilt,
            R_W_C=R_W_C,
            model=model,
            max_inplane_deg=cfg.max_inplane_deg,
        )

        # The first run of every start: all of it, or (with keep_after_first) a short screening
        # one, the best few then refined further.
        first, screen = cfg.refine_passes, 0
        if cfg.keep_after_first:
            first, screen = 1, cfg.screen_iterations
        screen_full = job.steps(screen) == self.refiner.config.iterations
        further: dict[int, Verified | None] = {}  # by start: refined further
        snaps: dict[tuple[int, bool], Verified | None] = {}  # by start and stage: snapped

        def chosen(firsts: list[Verified]) -> list[Verified]:
            """The first runs' results ranked, the best few refined further and snapped."""
            out = rank_verified(firsts)
            if cfg.keep_after_first and (cfg.refine_passes > 1 or not screen_full):
                # The best few, refined further, rank above the rest (refined once), which stay
                # listed.
                kept, rest = out[: cfg.keep_after_first], out[cfg.keep_after_first :]
                more = cfg.refine_passes - screen_full
                todo = list({v.rank: v for v in kept if v.rank not in further}.values())
                batch = [Start(v.T_C_O, v.source, v.rank, more) for v in todo]
                further.update(zip([v.rank for v in todo], helper.map(job, batch), strict=True))
                again = [further[v.rank] for v in kept]
                out = rank_verified([v for v in again if v is not None]) + rest
            if cfg.snap_candidates and max_tilt is not None:
                # The best few that could be resting, each turned onto its resting pose (its
                # heading kept) and refined again, one run, turning about the vertical only;
                # one whose score drops by more than SNAP_SCORE_DROP is not kept. The snapped
                # ones then compete on their scores alone, ahead of the rest, unless every one
                # of them scores well below the best pose found (the object is not resting).
                assert R_W_C is not None
                pool = [v for v in out if v.tilt <= cfg.snap_tilt_deg][: cfg.snap_candidates]
                keys = [(v.rank, further.get(v.rank) is v) for v in pool]  # first or further
                new: dict[tuple[int, bool], Verified] = {}
                for k, v in zip(keys, pool, strict=True):
                    if k not in snaps:
                        new.setdefault(k, v)
                up = R_W_C[2].copy()  # the world's vertical in the camera frame
                batch = []
                for v in new.values():
                    T = v.T_C_O.copy()
                    T[:3, :3] = R_W_C.T @ snap_to_resting(R_W_C @ T[:3, :3], model)[0]
                    batch.append(Start(T, v.source, v.rank, 1, cfg.snap_iterations, up))
                for (k, v), s in zip(new.items(), helper.map(job, batch), strict=True):
                    snaps[k] = None if s is None or s.score < v.score - SNAP_SCORE_DROP else s
                snapped = [s for k in keys if (s := snaps[k]) is not None]
                best_score = max((v.score for v in out), default=0.0)
                if snapped and max(v.score for v in snapped) >= best_score - SNAP_SCORE_DROP:
                    out = rank_verified(snapped) + [v for v in out if all(v is not p for p in pool)]
            return out

        batch = [Start(T, s, r, first, screen) for r, (T, s) in enumerate(starts)]
        firsts = [v for v in helper.map(job, batch) if v is not None]
        out = chosen(firsts)
        times = {"hypotheses": (t1 - t0) * 1000}
        unsure = not out or out[0].score < cfg.second_look_below
        look = second_look and (cfg.second_look or cfg.second_look_resting)
        if second is not None and look and unsure:
            t_look = time.perf_counter()
            later = enumerate(second(), len(starts))
            batch = [Start(T, s, r, first, screen) for r, (T, s) in later]
            firsts += [v for v in helper.map(job, batch) if v is not None]
            out = chosen(firsts)
            times["second_look"] = (time.perf_counter() - t_look) * 1000
        times["verify"] = (time.perf_counter() - t1) * 1000
        return out, times

    def sharpened(self, det: PoseDetection | Detection, rgb: np.ndarray):
        """`det` with its mask redrawn by the mask net (`GlobalConfig.mask_net`; one of the
        built-in objects it was trained on), else as it is."""
        if self.masks is None or det.name not in OBJECT_NAMES:
            return det
        return replace(det, mask=self.masks.refine(rgb, det.mask, det.name))

    def _user_target(
        self, obs: Observation
    ) -> tuple[Detection | None, tuple[tuple[str, np.ndarray], ...], dict, list[Detection]]:
        """A user object's best detection (by a detector fine-tuned on it), the built-in
        neighbours' poses, the description so far and every detection."""
        dets, poses, timings = self.hybrid.detections_and_poses(obs.rgb, obs.K)
        mine = [d for d in dets if d.name == obs.object]
        best = max(mine, key=lambda d: d.score) if mine else None
        info: dict = {"detected": best is not None, "timings_ms": dict(timings)}
        if best is not None:
            info |= {"class": best.name, "score": best.score, "detections": len(dets)}
        neighbours = tuple((p.name, p.T_C_O.copy()) for p in poses)
        return best, neighbours, info, list(dets)

    def neighbours_support(
        self,
        target: PoseDetection | Detection,
        detections: list[PoseDetection | Detection],
        obs: Observation,
    ) -> tuple[float | None, list[dict]]:
        """The height of the surface the target's neighbours rest on
        (`GlobalConfig.support_neighbours`), or None when none gives a confident resting pose,
        and what each verified neighbour gave (``class``, ``score``, ``tilt_deg``,
        ``surface_z``, ``counted``).

        Args:
            target: the requested object's detection.
            detections: every detection of the image (the target's among them).
            obs: the observation (its image, K and camera pose).
        """
        cfg = self.config
        R_W_C = np.asarray(obs.T_world_cam, float)[:3, :3]
        grown = ndimage.binary_dilation(target.mask, iterations=NEIGHBOUR_TOUCH_PX)
        centre = np.argwhere(target.mask).mean(0)

        def order(d: PoseDetection | Detection) -> tuple[int, float]:
            pixels = np.argwhere(d.mask)
            far = float(np.hypot(*(pixels.mean(0) - centre))) if len(pixels) else math.inf
            return -int((grown & d.mask).sum()), far

        candidates = [
            d for d in detections if d.name != target.name and load_object(d.name).resting_poses
        ]
        heights: list[float] = []
        seen: list[dict] = []
        for found in sorted(candidates, key=order)[: cfg.support_neighbours]:
            d = self.sharpened(found, obs.rgb)
            occluder = occluder_of(detections, found)
            ranked, _ = self.verify(d, obs.K, obs.rgb, occluder, R_W_C, second_look=False)
            if not ranked:
                continue
            win = ranked[0]  # with R_W_C and resting poses, its tilt is from resting
            z = resting_surface_z(win.T_C_O, obs.T_world_cam, load_object(d.name))
            score, tilt = float(win.score), win.tilt
            counted = bool(score >= cfg.support_score and tilt <= (cfg.resting_tilt_deg or 0))
            seen.append(
                {
                    "class": d.name,
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

    def estimate(self, obs: Observation) -> Estimate:
        """The verified pose of obs.object (None when not detected or below `min_score`), the
        other detections and the description of the estimate."""
        cfg = self.config
        self._estimates += 1
        if obs.object not in OBJECT_NAMES and obs.object in self.hybrid.detector.cfg.classes:
            best, neighbours, info, detections = self._user_target(obs)
        else:
            target = detect_target(self.hybrid, obs, cfg.target_score, cfg.neighbour_experts)
            best, neighbours, info = target.best, target.neighbours, target.info
            detections = [*target.found, *target.others]
        occluder = occluder_of(detections, best)
        if best is None:
            return Estimate(None, neighbours, info)
        if self.masks is not None:
            t0 = time.perf_counter()
            best = self.sharpened(best, obs.rgb)
            info["timings_ms"]["mask"] = (time.perf_counter() - t0) * 1000
        R_W_C = np.asarray(obs.T_world_cam, float)[:3, :3]
        ranked, times = self.verify(best, obs.K, obs.rgb, occluder, R_W_C)
        info["timings_ms"] |= times
        if not ranked:
            return Estimate(None, neighbours, info | {"verify": {"hypotheses": 0}})
        win = ranked[0]
        info["verify"] = {
            "confidence": win.score,
            "iou": win.iou,
            "appearance": win.appearance,
            "edges": win.edges,
            "source": win.source,
            "tilt_deg": win.tilt,
            "hypotheses": len(ranked),
            "second_look": "second_look" in times,
            "config": asdict(self.config),
        }
        if win.score < cfg.min_score:
            return Estimate(None, neighbours, info)
        T = win.T_C_O.copy()
        model = load_object(best.name)
        tilt = cfg.resting_tilt_deg or 10.0
        if cfg.table and obs.table_top_z is not None and model.resting_poses:
            ref = refine_on_support(T, obs.T_world_cam, model, obs.table_top_z, tilt)
            T, info["support"] = ref.T_C_O, ref.description()
        elif (
            cfg.support_neighbours
            and cfg.resting_tilt_deg is not None
            and model.resting_poses
            and win.score < cfg.second_look_below
            and win.tilt <= cfg.resting_tilt_deg
        ):
            t0 = time.perf_counter()
            support_z, seen = self.neighbours_support(best, detections, obs)
            own_z = resting_surface_z(T, obs.T_world_cam, model)
            described: dict = {"source": "neighbours", "neighbours": seen, "own_z": own_z}
            if support_z is not None and abs(own_z - support_z) > cfg.support_tolerance_m:
                ref = refine_on_support(T, obs.T_world_cam, model, support_z, tilt)
                T, described = ref.T_C_O, described | ref.description()
            info["support"] = described | {"surface_z": support_z}
            info["timings_ms"]["support"] = (time.perf_counter() - t0) * 1000
        return Estimate(T, neighbours, info)
