"""One grasp episode, written once: build a seeded scene, look, ask an estimator, grasp, score.

`Episode(object, seed)` builds the scene; `observe()` renders the head camera; `act(T_C_O)`
plans and executes a grasp on that *estimated* pose and returns an `EpisodeResult`. The
gymnasium env and the CLIs wrap this class.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from grasping.execute import ExecutionConfig, Executor
from grasping.planner import POSE_TOL, GraspPlanner, PlannerConfig, PlanningError
from perception.metrics import error_components
from posegrasp.core.contract import CONTRACT_VERSION, Estimate, Observation, PoseEstimator
from posegrasp.core.errors import InvalidArgumentError, StateError
from posegrasp.core.failures import check_failure_reason
from posegrasp.core.transforms import check_rigid
from posegrasp.world import constants as C
from posegrasp.world.camera import CameraRenderer, RenderOptions, T_world_cam, camera_intrinsics
from posegrasp.world.objects import check_object
from posegrasp.world.scene import Scene, SceneConfig, build_scene
from posegrasp.world.tiers import DEFAULT_TIER, tier_scene
from sim.estimators import PrivilegedEstimator


@dataclass(frozen=True)
class EpisodeConfig:
    """Everything that defines an episode besides object, seed and estimator; `tier` names the
    scene preset (`posegrasp.world.tiers`) applied to `scene`."""

    width: int = 640
    height: int = 480
    shadows: bool = False
    scene: SceneConfig = field(default_factory=SceneConfig)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    execution: ExecutionConfig = field(default_factory=ExecutionConfig)
    tier: str = DEFAULT_TIER


@dataclass
class EpisodeResult:
    """The outcome of one episode (all lengths [m], angles in the error dict in [deg]);
    `friction_margin` is the lowest sliding friction at which the grasp still held, when
    measured (`grasping.execute.Executor.friction_margin`)."""

    object: str
    seed: int
    estimator: str
    tier: str
    success: bool
    failure_reason: str | None
    T_C_O_true: np.ndarray
    T_C_O_est: np.ndarray | None
    pose_error: dict[str, float] | None
    lift_height: float
    grasp_part: str | None
    timings_ms: dict[str, float]
    notes: list[str] = field(default_factory=list)
    estimate_info: dict[str, Any] = field(default_factory=dict)
    friction_margin: float | None = None
    scene: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """A JSON-serialisable dict."""
        d = asdict(self)
        d["T_C_O_true"] = self.T_C_O_true.tolist()
        d["T_C_O_est"] = None if self.T_C_O_est is None else self.T_C_O_est.tolist()
        return d


def pose_errors(T_est: np.ndarray, T_true: np.ndarray, pts: np.ndarray, diameter: float) -> dict:
    """Pose errors of an estimate: translation [m] and [%], rotation [deg], ADD and ADD-S [m]."""
    from perception import metrics

    R_e, t_e, R_g, t_g = T_est[:3, :3], T_est[:3, 3], T_true[:3, :3], T_true[:3, 3]
    return {
        "translation_m": float(np.linalg.norm(t_e - t_g)),
        "translation_pct": float(metrics.translation_error_pct(t_e, t_g)),
        "rotation_deg": float(metrics.rotation_error_deg(R_e, R_g)),
        "add_m": float(metrics.add(R_e, t_e, R_g, t_g, pts)),
        "adi_m": float(metrics.adi(R_e, t_e, R_g, t_g, pts)),
        "add_rel_diameter": float(metrics.add(R_e, t_e, R_g, t_g, pts) / diameter),
        **error_components(T_est, T_true),
    }


class Episode:
    """A seeded grasp episode of one target object."""

    def __init__(self, obj: str, seed: int, config: EpisodeConfig | None = None) -> None:
        self.cfg = config or EpisodeConfig()
        self.object = obj
        self.seed = seed
        self.timings_ms: dict[str, float] = {}
        t = time.perf_counter()
        self.scene: Scene = build_scene(obj, seed, tier_scene(self.cfg.tier, self.cfg.scene))
        self.timings_ms["scene"] = (time.perf_counter() - t) * 1000
        self.renderer = CameraRenderer(
            self.scene.model,
            self.cfg.width,
            self.cfg.height,
            RenderOptions(shadows=self.cfg.shadows),
        )
        m, d = self.scene.model, self.scene.data
        self.K = camera_intrinsics(m, C.HEAD_CAMERA, self.cfg.width, self.cfg.height)
        self.T_world_cam = T_world_cam(m, d, C.HEAD_CAMERA)
        self.T_C_O_true = np.linalg.inv(self.T_world_cam) @ self.scene.object_pose()
        self._done = False
        self.frames: list[np.ndarray] = []

    def scene_info(self) -> dict[str, Any]:
        """What makes this scene hard: the target's resting pose and, when the tier bounds
        it, the share of its silhouette hidden by other objects."""
        info: dict[str, Any] = {"resting_pose": self.scene.target.resting}
        if self.scene.occlusion is not None:
            info["occlusion"] = round(self.scene.occlusion, 4)
        return info

    def observe(self) -> Observation:
        """Render the head camera and return what an estimator may see."""
        t = time.perf_counter()
        rgb = self.renderer.rgb(self.scene.data, C.HEAD_CAMERA)
        self.timings_ms["render"] = (time.perf_counter() - t) * 1000
        return Observation(
            rgb,
            self.K.copy(),
            self.T_world_cam.copy(),
            self.object,
            self.seed,
            table_top_z=float(self.scene.table_top_z),
        )

    def act(
        self,
        T_C_O_est: np.ndarray | None,
        estimator: str = "external",
        recorder=None,
        neighbours: Sequence[tuple[str, np.ndarray]] = (),
    ) -> EpisodeResult:
        """Grasp on an estimated pose (camera frame) and score it.

        Args:
            T_C_O_est: estimated pose of the target in the camera frame, or None (no estimate).
            estimator: name recorded in the result.
            recorder: optional callable(scene) -> frame, called during execution.
            neighbours: the other objects the estimator reports, (class, T_C_N) pairs in the
                camera frame; the planner keeps the gripper clear of them.

        Raises:
            InvalidArgumentError: the estimate or a neighbour's pose is not a finite rigid
                transform.
            UnknownNameError: a neighbour of an unknown class.
            StateError: the episode was already acted on.
        """
        if self._done:
            raise StateError("this episode is over; build a new one")
        if T_C_O_est is not None:
            check_rigid(T_C_O_est, "estimated pose T_C_O", tol=POSE_TOL)
        neighbours = [
            (check_object(n), check_rigid(T, f"pose of neighbour {n!r}", tol=POSE_TOL))
            for n, T in neighbours
        ]
        self._done = True
        timings = self.timings_ms
        notes: list[str] = []
        errors = None
        if T_C_O_est is not None:
            obj = self.scene.target.model
            pts = np.asarray(obj.mesh.vertices)
            errors = pose_errors(T_C_O_est, self.T_C_O_true, pts, obj.diameter)

        def result(success: bool, reason: str | None, part: str | None = None) -> EpisodeResult:
            lift = self.scene.object_lowest_z() - self.scene.table_top_z
            timings["total"] = sum(v for k, v in timings.items() if k not in ("total", "ik"))
            return EpisodeResult(
                self.object,
                self.seed,
                estimator,
                self.cfg.tier,
                success,
                check_failure_reason(reason),
                self.T_C_O_true,
                None if T_C_O_est is None else np.asarray(T_C_O_est, float),
                errors,
                float(lift),
                part,
                dict(timings),
                notes,
                scene=self.scene_info(),
            )

        if T_C_O_est is None:
            return result(False, "no_estimate")
        T_world_O = self.T_world_cam @ np.asarray(T_C_O_est, float)
        t = time.perf_counter()
        try:
            planner = GraspPlanner(self.scene.model, config=self.cfg.planner)
            told = [(n, self.T_world_cam @ T) for n, T in neighbours]
            plan = planner.plan(self.object, T_world_O, self.scene.data.qpos.copy(), told)
        except PlanningError as exc:
            timings["plan"] = (time.perf_counter() - t) * 1000
            notes.append(str(exc))
            return result(False, exc.reason)
        timings["plan"] = (time.perf_counter() - t) * 1000
        timings["ik"] = plan.ik_ms
        executor = Executor(self.scene, self.cfg.execution, recorder=recorder)
        outcome = executor.execute(plan)
        for k, v in outcome.timings_ms.items():
            timings[f"exec_{k}"] = v
        notes.extend(executor.events)
        self.frames = outcome.frames
        res = result(outcome.success, outcome.failure_reason, plan.candidate.part)
        res.friction_margin = outcome.friction_margin
        return res

    def estimate(
        self, estimator: PoseEstimator | PrivilegedEstimator, obs: Observation
    ) -> Estimate:
        """Ask the estimator for the target's pose in obs (timed as ``estimate``). Only a
        `PrivilegedEstimator` (an oracle) is handed the true pose and the true neighbours.

        Raises:
            InvalidArgumentError: the estimator answered something other than an `Estimate`.
        """
        t = time.perf_counter()
        if isinstance(estimator, PrivilegedEstimator):
            est = estimator.estimate_from_truth(obs, self.T_C_O_true.copy(), self.true_neighbours())
        else:
            est = estimator.estimate(obs)
        self.timings_ms["estimate"] = (time.perf_counter() - t) * 1000
        if not isinstance(est, Estimate):
            raise InvalidArgumentError(
                f"estimator {estimator.name!r} returned {type(est).__name__}, not an Estimate "
                f"(posegrasp.core.contract, version {CONTRACT_VERSION})"
            )
        return est

    def run(
        self, estimator: PoseEstimator | PrivilegedEstimator, recorder=None
    ) -> tuple[Observation, EpisodeResult]:
        """Observe, ask the estimator (`estimate`), act; the result carries the estimate's
        ``info`` as ``estimate_info``."""
        obs = self.observe()
        est = self.estimate(estimator, obs)
        res = self.act(est.T_C_O, estimator.name, recorder=recorder, neighbours=est.neighbours)
        res.estimate_info = dict(est.info)
        return obs, res

    def true_neighbours(self) -> list[tuple[str, np.ndarray]]:
        """The other objects' true poses in the camera frame, (class, T_C_N) pairs (what the
        oracles report)."""
        T_cam_world = np.linalg.inv(self.T_world_cam)
        return [
            (o.name, T_cam_world @ self.scene.object_pose(o.body)) for o in self.scene.objects[1:]
        ]

    def close(self) -> None:
        """Free the renderer."""
        self.renderer.close()


def play_episode(
    obj: str,
    seed: int,
    estimator: PoseEstimator | PrivilegedEstimator,
    config: EpisodeConfig | None = None,
    recorder=None,
) -> EpisodeResult:
    """Build, observe, estimate, grasp and score one episode."""
    ep = Episode(obj, seed, config)
    try:
        return ep.run(estimator, recorder)[1]
    finally:
        ep.close()
