"""One grasp episode, written once: build a seeded scene, look, ask an estimator, grasp, score.

`Episode(object, seed)` builds the scene; `observe()` renders the head camera (colour, and depth
with ``obs_mode="rgbd"``) as the config's sensor returns it (`posegrasp.world.sensors`, ``ideal``:
unchanged); `act(T_C_O)` plans and executes a grasp on that *estimated* pose and
returns an `EpisodeResult`. A pose that is not valid (`posegrasp.core.contract.pose_problem`)
ends the episode as a failed grasp with ``invalid_action``. The gymnasium env and the CLIs wrap
this class.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from grasping.execute import ExecutionConfig, Executor, GraspOutcome
from grasping.grasp_check import held_in_hand
from grasping.place import (
    PlaceConfig,
    PlacePlanner,
    held_transform,
    predicted_hold,
    set_down_pose,
)
from grasping.planner import GraspPlan, GraspPlanner, PlannerConfig, PlanningError
from perception import metrics
from perception.metrics import Symmetry, error_components, identity_symmetry
from posegrasp.core.contract import (
    CONTRACT_VERSION,
    Estimate,
    Observation,
    PoseEstimator,
    as_pose_array,
    confidence_problem,
    pose_problem,
)
from posegrasp.core.errors import InvalidArgumentError, StateError, UnknownNameError
from posegrasp.core.failures import check_failure_reason
from posegrasp.world import constants as C
from posegrasp.world.camera import CameraRenderer, RenderOptions, T_world_cam, camera_intrinsics
from posegrasp.world.goals import TASKS, GoalConfig, PlaceGoal, draw_goal
from posegrasp.world.objects import ObjectModel, check_object
from posegrasp.world.scene import Scene, SceneConfig, build_scene
from posegrasp.world.sensors import SENSOR_NAMES, Sensor
from posegrasp.world.tiers import DEFAULT_TIER, tier_scene
from sim.episodes.registry import PrivilegedEstimator

#: What `Episode.observe` renders: ``rgb`` the colour image, ``rgbd`` also the depth image.
OBS_MODES = ("rgb", "rgbd")
#: A place succeeds when the object rests within this distance [m] and this rotation [deg] of
#: its goal (symmetry-aware, `pose_errors`): the play of a fixture or a shelf slot with a
#: centimetre to spare each side, and a turn that a chamfered slot still takes.
PLACE_TOLERANCE = (0.02, 10.0)
#: A placed object whose up axis is further than this from the goal's [deg] has tipped over.
TIPPED_DEG = 20.0
#: Physics time the placed object is left to settle after the gripper withdrew [s].
PLACE_SETTLE_S = 1.0
#: An estimate is correct (``EpisodeResult.pose_correct``) when its MSSD is below this fraction
#: of the object's diameter (BOP's MSSD, at the threshold of the ADD(-S) < 0.1 d test).
POSE_CORRECT_MSSD = 0.1


@dataclass(frozen=True)
class EpisodeConfig:
    """Everything that defines an episode besides object, seed and estimator.

    Attributes:
        width, height: head-camera resolution [px].
        shadows: render shadows.
        scene, planner, execution: the scene, planner and executor settings.
        tier: the scene preset (`posegrasp.world.tiers`) applied to `scene`.
        obs_mode: what the observation holds, one of `OBS_MODES`: ``rgb`` the colour image,
            ``rgbd`` also the depth image (`Observation.depth`).
        sensor: the head camera's sensor model, one of
            `posegrasp.world.sensors.SENSOR_NAMES`: what `Episode.observe` hands the estimator
            is the rendered images as that sensor returns them (``ideal``: unchanged).
        task: one of `posegrasp.world.goals.TASKS`: ``lift`` scores the lift; ``place`` then
            carries the object to a goal pose drawn from the seed (`goal`) and sets it down
            (`place`), scored by where it rests.

    Raises:
        UnknownNameError: an obs_mode not in `OBS_MODES`, a sensor not in `SENSOR_NAMES`, a
            task not in `TASKS`.
    """

    width: int = 640
    height: int = 480
    shadows: bool = False
    scene: SceneConfig = field(default_factory=SceneConfig)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    execution: ExecutionConfig = field(default_factory=ExecutionConfig)
    tier: str = DEFAULT_TIER
    obs_mode: str = "rgb"
    sensor: str = "ideal"
    task: str = "lift"
    goal: GoalConfig = field(default_factory=GoalConfig)
    place: PlaceConfig = field(default_factory=PlaceConfig)

    def __post_init__(self) -> None:
        if self.task not in TASKS:
            raise UnknownNameError("task", str(self.task), TASKS)
        if self.obs_mode not in OBS_MODES:
            raise UnknownNameError("observation mode", str(self.obs_mode), OBS_MODES)
        if self.sensor not in SENSOR_NAMES:
            raise UnknownNameError("sensor", str(self.sensor), SENSOR_NAMES)


@dataclass
class EpisodeResult:
    """The outcome of one episode (all lengths [m], angles in the error dict in [deg]).

    `pose_error` holds the estimate's errors (`pose_errors`), None without a valid estimate;
    `pose_correct` whether its MSSD is below `POSE_CORRECT_MSSD` times the object's diameter
    (None without a valid estimate); `vsd` BOP's VSD of the estimate against the head
    camera's ideal depth (BOP's ground-truth depth, whatever the sensor), one error in [0, 1]
    per tau of `perception.metrics.BOP_VSD_TAUS` (None without a valid estimate);
    `friction_margin` is the lowest sliding friction at which the grasp still held, when
    measured (`grasping.execute.Executor.friction_margin`); `sensor` the sensor the estimator
    observed through (`EpisodeConfig.sensor`).
    """

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
    pose_correct: bool | None = None
    vsd: list[float] | None = None
    sensor: str = "ideal"
    #: The estimate's confidence (contract version 3), None when it gives none.
    confidence: float | None = None
    #: The place task's record (`Episode.place_record`), None on the lift task.
    place: dict[str, Any] | None = None

    def to_json(self) -> dict[str, Any]:
        """A JSON-serialisable dict (strict JSON: an estimate with non-finite entries, which
        ends as ``invalid_action``, is written as null). ``sensor`` is left out for ``ideal``
        and ``confidence`` and ``place`` when None, as in the records written before them: a
        record without them observed the ideal camera, had no confidence and lifted."""
        d = asdict(self)
        if self.sensor == "ideal":
            del d["sensor"]
        if self.confidence is None:
            del d["confidence"]
        if self.place is None:
            del d["place"]
        d["T_C_O_true"] = self.T_C_O_true.tolist()
        est = self.T_C_O_est
        d["T_C_O_est"] = None if est is None or not np.all(np.isfinite(est)) else est.tolist()
        return d


def object_symmetries(model: ObjectModel) -> list[Symmetry]:
    """An object's symmetries in `perception.metrics`' convention: the identity, then each
    `ObjectModel.symmetries` T_O_O' as ``{"R": (3, 3), "t": (3, 1) [m]}``."""
    return identity_symmetry() + [{"R": T[:3, :3], "t": T[:3, 3:4]} for T in model.symmetries]


def execution_settings() -> dict[str, Any]:
    """The grasp execution's settings every episode runs with (`ExecutionConfig`, without the
    margin switch, which reports record apart), as they read back from JSON: two reports with
    different settings are different experiments and do not pair."""
    import json

    settings = asdict(ExecutionConfig())
    del settings["measure_margin"]
    return json.loads(json.dumps(settings))


def pose_errors(
    T_est: np.ndarray,
    T_true: np.ndarray,
    pts: np.ndarray,
    diameter: float,
    K: np.ndarray | None = None,
    syms: list[Symmetry] | None = None,
) -> dict[str, float]:
    """Pose errors of an estimate against the truth, both T_C_O (4, 4) in the camera frame [m].

    For an object with symmetries every error is measured against the equivalent true pose
    ``T_true S`` the estimate is closest to, S the symmetry of least MSSD
    (`perception.metrics.closest_symmetry`, the first on a tie): an estimate that differs from
    the truth only by a symmetry has no error. For an object without, that is the truth itself
    and the errors are the plain ones.

    Args:
        T_est, T_true: the estimated and the true pose.
        pts: the object's model points in O, (N, 3) [m] (its mesh vertices).
        diameter: the object's diameter [m].
        K: the camera intrinsics (3, 3) [px]; without them no MSPD.
        syms: the object's symmetry set (`object_symmetries`); None for none but the identity.

    Returns:
        ``translation_m``, ``translation_pct``, ``rotation_deg``, ``add_m``, ``adi_m`` (ADD-S),
        ``add_rel_diameter``, the components of `perception.metrics.error_components`, BOP's
        ``mssd_m`` and ``mssd_rel_diameter`` and, with K, ``mspd_px`` (left out when a model
        point of either pose lies at or behind the camera plane, where BOP's MSPD is infinite);
        for a symmetry set of more than the identity also ``symmetry_index``, the index in syms
        of the S measured against.
    """
    R_e, t_e, R_g, t_g = T_est[:3, :3], T_est[:3, 3], T_true[:3, :3], T_true[:3, 3]
    syms = identity_symmetry() if syms is None else syms
    index, mssd = metrics.closest_symmetry(R_e, t_e, R_g, t_g, pts, syms)
    T_ref = metrics.symmetric_pose(T_true, syms[index])
    R_r, t_r = T_ref[:3, :3], T_ref[:3, 3]
    add = metrics.add(R_e, t_e, R_r, t_r, pts)
    errors = {
        "translation_m": float(np.linalg.norm(t_e - t_r)),
        "translation_pct": float(metrics.translation_error_pct(t_e, t_r)),
        "rotation_deg": float(metrics.rotation_error_deg(R_e, R_r)),
        "add_m": float(add),
        "adi_m": float(metrics.adi(R_e, t_e, R_g, t_g, pts)),
        "add_rel_diameter": float(add / diameter),
        **error_components(T_est, T_ref),
        "mssd_m": float(mssd),
        "mssd_rel_diameter": float(mssd / diameter),
    }
    if K is not None:
        mspd = metrics.mspd(R_e, t_e, R_g, t_g, K, pts, syms)
        if np.isfinite(mspd):
            errors["mspd_px"] = float(mspd)
    if len(syms) > 1:
        errors["symmetry_index"] = index
    return errors


def _describe(item: object) -> str:
    """A short description of a value that should have been a (class, pose) pair."""
    if isinstance(item, np.ndarray):
        return f"a bare array of shape {item.shape}"
    if isinstance(item, (tuple, list)):
        kinds = ", ".join(type(x).__name__ for x in item[:3]) + (", ..." if len(item) > 3 else "")
        return f"a {type(item).__name__} of {len(item)} ({kinds})"
    return type(item).__name__


def check_estimate(
    T_C_O: object, neighbours: Iterable[tuple[str, object]] = ()
) -> tuple[np.ndarray | None, list[tuple[str, np.ndarray]], str | None]:
    """An estimate and its neighbours as float64 poses, and the first problem that makes them
    an invalid action (`posegrasp.core.contract.pose_problem`), or None.

    Args:
        T_C_O: the target's estimated pose (4, 4) in the camera frame [m], or None.
        neighbours: the other objects reported, (class, T_C_N) pairs in the camera frame.

    Returns:
        (T_C_O as float64 or None, [(class, T_C_N as float64)], one line naming the pose at
        fault and what is wrong with it, or None).

    Raises:
        InvalidArgumentError: a pose that is not a real 4x4 array, or a neighbour that is not
            a (class, pose) pair.
        UnknownNameError: a neighbour of an unknown class.
    """
    T = None if T_C_O is None else as_pose_array(T_C_O, "estimated pose T_C_O")
    problems = [] if T is None else [("estimated pose T_C_O", pose_problem(T))]
    if isinstance(neighbours, (str, bytes, np.ndarray)) or not isinstance(neighbours, Iterable):
        got = type(neighbours).__name__
        raise InvalidArgumentError(
            f"neighbours must be a sequence of (class, T_C_N) pairs, got {got}"
        )
    told = []
    for i, item in enumerate(neighbours):
        if not isinstance(item, (tuple, list)) or len(item) != 2 or not isinstance(item[0], str):
            raise InvalidArgumentError(
                f"neighbour {i} must be a (class, T_C_N) pair, got {_describe(item)}"
            )
        name = check_object(item[0])
        what = f"pose of neighbour {i} ({name!r})"
        told.append((name, as_pose_array(item[1], what)))
        problems.append((what, pose_problem(told[-1][1])))
    problem = next((f"{what}: {p}" for what, p in problems if p is not None), None)
    return T, told, problem


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
        self.sensor = Sensor.parse(self.cfg.sensor)
        self.T_world_cam = T_world_cam(m, d, C.HEAD_CAMERA)
        self.T_C_O_true = np.linalg.inv(self.T_world_cam) @ self.scene.object_pose()
        self._done = False
        self.frames: list[np.ndarray] = []
        self.goal: PlaceGoal | None = None
        if self.cfg.task == "place":
            self.goal = draw_goal(self.scene, self.cfg.goal)
        self._planner: GraspPlanner | None = None
        self._executor: Executor | None = None
        self._grasp: GraspPlan | None = None  # the plan executed

    def scene_info(self) -> dict[str, Any]:
        """What makes this scene hard: the target's resting pose and, when the tier bounds
        it, the share of its silhouette hidden by other objects."""
        info: dict[str, Any] = {"resting_pose": self.scene.target.resting}
        if self.scene.occlusion is not None:
            info["occlusion"] = round(self.scene.occlusion, 4)
        return info

    def observe(self) -> Observation:
        """Render the head camera and return what an estimator may see: the colour image
        (timed as ``render``) and, with ``obs_mode="rgbd"``, the depth image of the same camera
        and state (`CameraRenderer.depth`, z along the optical axis [m], float32; timed as
        ``render_depth``), both as the config's sensor returns them.

        A sensor other than ``ideal`` (`posegrasp.world.sensors.Sensor.apply`, timed as
        ``sensor``) changes the colour image always and the depth image when there is one
        (float32, 0 where it returns nothing); its noise is frame 0's of the episode's seed,
        on streams of its own, so the scene is the same under every sensor and the same seed
        observes the same noise. ``ideal`` hands over the rendered images unchanged. The colour
        image is the same in both modes."""
        t = time.perf_counter()
        rgb = self.renderer.rgb(self.scene.data, C.HEAD_CAMERA)
        self.timings_ms["render"] = (time.perf_counter() - t) * 1000
        depth = None
        if self.cfg.obs_mode == "rgbd":
            t = time.perf_counter()
            depth = self.renderer.depth(self.scene.data, C.HEAD_CAMERA)
            self.timings_ms["render_depth"] = (time.perf_counter() - t) * 1000
        if self.sensor.name != "ideal":
            t = time.perf_counter()
            rgb, depth = self.sensor.apply(rgb, depth, self.K, self.seed)
            self.timings_ms["sensor"] = (time.perf_counter() - t) * 1000
        return Observation(
            rgb,
            self.K.copy(),
            self.T_world_cam.copy(),
            self.object,
            self.seed,
            table_top_z=float(self.scene.table_top_z),
            depth=depth,
        )

    def act(
        self,
        T_C_O_est: np.ndarray | None,
        estimator: str = "external",
        recorder=None,
        neighbours: Iterable[tuple[str, np.ndarray]] = (),
    ) -> EpisodeResult:
        """Grasp on an estimated pose (camera frame) and score it.

        An estimate or a neighbour's pose that is not valid (`pose_problem`: non-finite, a
        rotation block off orthonormal by more than 1e-6 or a reflection, an origin beyond 10 m
        of the camera) ends the episode as a failed grasp with ``invalid_action`` and the
        problem as its first note; nothing is planned.

        Args:
            T_C_O_est: estimated pose of the target in the camera frame (4, 4) [m], or None (no
                estimate).
            estimator: name recorded in the result.
            recorder: optional callable(scene) -> frame, called during execution.
            neighbours: the other objects the estimator reports, (class, T_C_N) pairs in the
                camera frame; the planner keeps the gripper clear of them.

        Raises:
            InvalidArgumentError: a pose that is not a real 4x4 array, or a neighbour that is
                not a (class, pose) pair.
            UnknownNameError: a neighbour of an unknown class.
            StateError: the episode was already acted on.
        """
        if self._done:
            raise StateError("this episode is over; build a new one")
        T_C_O_est, neighbours, problem = check_estimate(T_C_O_est, neighbours)
        if problem is not None:
            return self.reject(problem, estimator, T_C_O_est)
        self._done = True
        notes: list[str] = []
        errors = correct = vsd = None
        if T_C_O_est is not None:
            errors = self.pose_errors(T_C_O_est)
            correct = errors["mssd_rel_diameter"] < POSE_CORRECT_MSSD
            vsd = self._vsd(T_C_O_est)

        def result(success: bool, reason: str | None, part: str | None = None) -> EpisodeResult:
            res = self._result(estimator, success, reason, T_C_O_est, errors, notes, part)
            res.pose_correct = correct
            res.vsd = vsd
            return res

        if T_C_O_est is None:
            return result(False, "no_estimate")
        try:
            plan = self._plan(T_C_O_est, neighbours)
        except PlanningError as exc:
            notes.append(str(exc))
            return result(False, exc.reason)
        outcome, events = self._execute(plan, recorder)
        notes.extend(events)
        res = result(outcome.success, outcome.failure_reason, plan.candidate.part)
        res.friction_margin = outcome.friction_margin
        if self.goal is not None and outcome.success:
            res.lift_height = outcome.lift_height
            self._place(res, self.T_world_cam @ T_C_O_est)
        return res

    def _vsd(self, T_C_O_est: np.ndarray) -> list[float]:
        """BOP's VSD of an estimate (4, 4, camera frame [m]) at each of its tolerances (timed
        as ``vsd``), against the ideal depth the head camera sees now, before anything moves
        (BOP's ground-truth depth; what sim.export_bop writes with the ideal sensor), whatever
        the sensor: it scores the pose, not the sensor. No surface is missing depth (0)."""
        t = time.perf_counter()
        depth = self.renderer.depth(self.scene.data, C.HEAD_CAMERA).astype(np.float64)
        depth[~(np.isfinite(depth) & (depth > 0))] = 0.0
        model = self.scene.target.model
        vsd = metrics.vsd(
            T_C_O_est[:3, :3],
            T_C_O_est[:3, 3],
            self.T_C_O_true[:3, :3],
            self.T_C_O_true[:3, 3],
            depth,
            self.K,
            np.asarray(model.mesh.vertices),
            np.asarray(model.mesh.faces),
            model.diameter,
        ).tolist()
        self.timings_ms["vsd"] = (time.perf_counter() - t) * 1000
        return vsd

    def _plan(self, T_C_O_est: np.ndarray, neighbours: list[tuple[str, np.ndarray]]) -> GraspPlan:
        """Plan a grasp of the target at its estimate (4, 4, camera frame [m]), clear of the
        `neighbours` ((class, T_C_N) pairs, camera frame); timed as ``plan``, its IK as
        ``ik``.

        Raises:
            PlanningError: no plan (`GraspPlanner.plan`).
        """
        T_world_O = self.T_world_cam @ T_C_O_est
        t = time.perf_counter()
        try:
            planner = self._planner = GraspPlanner(self.scene.model, config=self.cfg.planner)
            told = [(n, self.T_world_cam @ T) for n, T in neighbours]
            plan = planner.plan(self.object, T_world_O, self.scene.data.qpos.copy(), told)
        except PlanningError:
            self.timings_ms["plan"] = (time.perf_counter() - t) * 1000
            raise
        self.timings_ms["plan"] = (time.perf_counter() - t) * 1000
        self.timings_ms["ik"] = plan.ik_ms
        return plan

    def _execute(self, plan: GraspPlan, recorder=None) -> tuple[GraspOutcome, list[str]]:
        """Execute the plan in the scene (each of its stages timed as ``exec_<stage>``, its
        frames kept as `frames`); the outcome and the executor's events, in order."""
        self._grasp = plan
        executor = self._executor = Executor(self.scene, self.cfg.execution, recorder=recorder)
        outcome = executor.execute(plan)
        for k, v in outcome.timings_ms.items():
            self.timings_ms[f"exec_{k}"] = v
        self.frames = outcome.frames
        return outcome, executor.events

    def _place(self, res: EpisodeResult, T_world_O_est: np.ndarray) -> None:
        """Carry the lifted object to the goal, set it down and score where it rests, into
        `res`: the robot places it as the estimate T_world_O_est (4, 4) [m] says it lies in
        the hand (`grasping.place.held_transform`); the set-down's planning is timed as
        ``place_plan``, its execution's stages as ``exec_<stage>``."""
        assert self.goal is not None and self._planner is not None
        executor = self._executor
        assert executor is not None and executor.T_world_G_closed is not None
        T_G_O = held_transform(executor.T_world_G_closed, T_world_O_est)
        if self.cfg.place.belief == "predicted":
            T_G_O = self._predicted(T_G_O, res)
        elif self.cfg.place.belief == "truth":
            T_G_O = held_transform(executor.grasp_site_pose(), self.scene.object_pose())
        T_set = set_down_pose(self.goal.T_world_O, T_G_O, self.cfg.place.drop)
        t = time.perf_counter()
        try:
            plan = PlacePlanner(self._planner, self.cfg.place).plan(T_set, self.scene.data.qpos)
        except PlanningError as exc:
            res.notes.append(str(exc))
            reason: str | None = exc.reason
        else:
            self.timings_ms["place_plan"] = (time.perf_counter() - t) * 1000
            before = len(executor.events)
            outcome = executor.place(plan, PLACE_SETTLE_S)
            self.timings_ms |= {f"exec_{k}": v for k, v in outcome.timings_ms.items()}
            self.frames = executor.frames
            res.notes.extend(executor.events[before:])
            reason = outcome.failure_reason
        res.place = self.place_record(reason)
        res.success, res.failure_reason = res.place["placed"], res.place["failure_reason"]
        res.timings_ms = self._totalled()

    def _predicted(self, T_G_O: np.ndarray, res: EpisodeResult) -> np.ndarray:
        """The belief T_G_O (4, 4) moved in the hand as a physics check of the executed grasp
        moves the object (`grasping.place.predicted_hold`), on the object resting in the pose
        the grasp was made for; unmoved, with a note, where the check does not hold it. Timed as
        ``place_predict``."""
        assert self._grasp is not None
        t = time.perf_counter()
        cand = self._grasp.candidate
        obj = self.scene.target.model
        outcome, held = held_in_hand(obj, obj.resting_poses[cand.pose], cand.T_O_G)
        self.timings_ms["place_predict"] = (time.perf_counter() - t) * 1000
        if outcome != "success":
            res.notes.append(f"place: the grasp's physics check ends {outcome}; belief not moved")
            return T_G_O
        return predicted_hold(T_G_O, cand.T_O_G, held)

    def _totalled(self) -> dict[str, float]:
        """The episode's timings so far [ms] with their ``total`` (every stage's, ``ik`` being
        part of ``plan``) last, anew."""
        self.timings_ms.pop("total", None)
        self.timings_ms["total"] = sum(v for k, v in self.timings_ms.items() if k != "ik")
        return dict(self.timings_ms)

    def place_record(self, reason: str | None) -> dict[str, Any]:
        """Where the target rests now against its goal: the goal, the final pose T_world_O,
        the errors (`place_errors`), whether it is placed and, if not, why: `reason` when the
        place failed on the way, else ``tipped`` or ``off_target`` by `TIPPED_DEG` and
        `PLACE_TOLERANCE`."""
        assert self.goal is not None
        final = self.scene.object_pose()
        errors = self.place_errors(final)
        if reason is None and errors["tilt_deg"] > TIPPED_DEG:
            reason = "tipped"
        far = errors["translation_m"] > PLACE_TOLERANCE[0]
        if reason is None and (far or errors["rotation_deg"] > PLACE_TOLERANCE[1]):
            reason = "off_target"
        return {
            "goal": self.goal.to_json(),
            "T_world_O_final": final.tolist(),
            "errors": errors,
            "placed": reason is None,
            "failure_reason": check_failure_reason(reason),
        }

    def place_errors(self, T_world_O: np.ndarray) -> dict[str, float]:
        """The errors of a resting pose T_world_O (4, 4) from the goal: the symmetry-aware
        ``translation_m``, ``rotation_deg``, ``mssd_m`` and ``mssd_rel_diameter``
        (`pose_errors`), and ``tilt_deg``, the angle between the goal's up axis and where the
        object's now points."""
        assert self.goal is not None
        T_cam_world = np.linalg.inv(self.T_world_cam)
        obj = self.scene.target.model
        every = pose_errors(
            T_cam_world @ T_world_O,
            T_cam_world @ self.goal.T_world_O,
            np.asarray(obj.mesh.vertices),
            obj.diameter,
            None,
            object_symmetries(obj),
        )
        up = self.goal.T_world_O[:3, :3].T[:, 2]  # the world's up in the object's frame
        tilt = float(np.degrees(np.arccos(np.clip((T_world_O[:3, :3] @ up)[2], -1.0, 1.0))))
        keys = ("translation_m", "rotation_deg", "mssd_m", "mssd_rel_diameter")
        return {k: every[k] for k in keys} | {"tilt_deg": tilt}

    def reject(
        self, problem: str, estimator: str = "external", T_C_O_est: np.ndarray | None = None
    ) -> EpisodeResult:
        """End the episode as a failed grasp with ``invalid_action`` (nothing is planned): the
        answer could not be grasped on, for the reason `problem` (the result's first note).

        Args:
            problem: one line saying what was wrong with the answer.
            estimator: name recorded in the result.
            T_C_O_est: the estimate as given (4, 4), recorded in the result, or None.

        Raises:
            StateError: the episode was already acted on.
        """
        if self._done:
            raise StateError("this episode is over; build a new one")
        self._done = True
        return self._result(estimator, False, "invalid_action", T_C_O_est, None, [problem])

    def pose_errors(self, T_C_O_est: np.ndarray) -> dict[str, float]:
        """`pose_errors` of an estimate (4, 4) against this episode's true pose, with the
        target's mesh vertices, diameter and symmetries and the head camera's K."""
        obj = self.scene.target.model
        pts = np.asarray(obj.mesh.vertices)
        return pose_errors(
            T_C_O_est, self.T_C_O_true, pts, obj.diameter, self.K, object_symmetries(obj)
        )

    def _result(
        self,
        estimator: str,
        success: bool,
        reason: str | None,
        T_C_O_est: np.ndarray | None,
        errors: dict[str, float] | None,
        notes: list[str],
        part: str | None = None,
    ) -> EpisodeResult:
        lift = self.scene.object_lowest_z() - self.scene.table_top_z
        timings = self._totalled()
        return EpisodeResult(
            self.object,
            self.seed,
            estimator,
            self.cfg.tier,
            success,
            check_failure_reason(reason),
            self.T_C_O_true,
            None if T_C_O_est is None else np.array(T_C_O_est, float),
            errors,
            float(lift),
            part,
            timings,
            notes,
            scene=self.scene_info(),
            sensor=self.sensor.name,
        )

    def estimate(
        self, estimator: PoseEstimator | PrivilegedEstimator, obs: Observation
    ) -> Estimate:
        """Ask the estimator for the target's pose in obs (timed as ``estimate``). Only a
        `PrivilegedEstimator` (an oracle) is handed the true pose and the true neighbours.

        Raises:
            InvalidArgumentError: the estimator raised, whatever the exception (the message is
                ``estimator <name> raised <Type>: <message>``, the exception its cause), or
                answered something other than an `Estimate`.
        """
        t = time.perf_counter()
        try:
            if isinstance(estimator, PrivilegedEstimator):
                T_true, neighbours = self.T_C_O_true.copy(), self.true_neighbours()
                est = estimator.estimate_from_truth(obs, T_true, neighbours)
            else:
                est = estimator.estimate(obs)
        except Exception as exc:  # any error of the estimator's own code, not only ours
            raise InvalidArgumentError(
                f"estimator {estimator.name} raised {type(exc).__name__}: {exc}"
            ) from exc
        finally:
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
        ``info`` as ``estimate_info``, and the ``note`` of an estimate without a pose among its
        notes.

        An estimator that raises (any exception) or answers something other than an `Estimate`
        ends the episode as a failed grasp with ``error``, nothing planned: its note says what
        happened (``estimator <name> raised <Type>: <message>``), and the scene, true pose and
        timings are recorded as for any failure.

        Raises:
            StateError: the episode was already acted on.
        """
        obs = self.observe()
        try:
            est = self.estimate(estimator, obs)
        except InvalidArgumentError as exc:
            if self._done:
                raise StateError("this episode is over; build a new one") from None
            self._done = True
            return obs, self._result(estimator.name, False, "error", None, None, [str(exc)])
        res = self.act(est.T_C_O, estimator.name, recorder=recorder, neighbours=est.neighbours)
        res.estimate_info = dict(est.info)
        if est.T_C_O is None and isinstance(est.info.get("note"), str):
            res.notes.append(est.info["note"])
        if est.T_C_O is not None:
            if (problem := confidence_problem(est.confidence)) is not None:
                res.notes.append(f"estimator {estimator.name}: {problem}; recorded as none")
            elif est.confidence is not None:
                res.confidence = float(est.confidence)
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
