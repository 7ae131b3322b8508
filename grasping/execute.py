"""Executing a grasp plan in MuJoCo physics through the position actuators, and the success check.

Stages: pre-grasp (gripper open), approach, close (until the fingers stop on the object), lift,
hold. Success (docs/DESIGN.md §10): after the hold the object's lowest point is at least
0.10 m above the table top and the object touches both fingers.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import mujoco
import numpy as np

from grasping.place import PlacePlan
from grasping.planner import PLANNED_JOINTS, GraspPlan
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.failures import check_failure_reason
from posegrasp.world import constants as C
from posegrasp.world.scene import Scene

#: The carry to the goal takes this many times the transit's time for the same motion: a held
#: object slips less under a gentler acceleration.
PLACE_CARRY_SLOWDOWN = 2.0
#: How the arm travels to the pre-grasp (`ExecutionConfig.transit`).
TRANSIT_MODES: tuple[str, ...] = ("kinematic", "dynamic")


@dataclass(frozen=True)
class ExecutionConfig:
    """Execution settings.

    Attributes:
        control_dt: period of control updates [s].
        timestep: physics step while the grasp is executed [s] (the scene is built and settled
            at the world's 2 ms, so what the camera sees does not depend on it).
        max_speed: joint speed limits for (base xy [m/s], base yaw, torso [m/s], arm [rad/s]).
        approach_speed: grasp-site speed on the approach [m/s].
        close_time: maximum time for the fingers to close [s].
        hold_time: hold after the lift [s].
        success_height: required clearance of the object's lowest point over the table [m].
        knock_tolerance: object displacement before closing that counts as a collision [m].
        disturb_tolerance: displacement of any other object that makes a grasp unclean [m].
        knock_over_deg: tilt of any other object that counts as knocking it over [deg].
        measure_margin: after a success, measure the grasp's friction margin
            (`Executor.friction_margin`).
        margin_steps: bisection steps of the margin (resolution: nominal friction / 2^steps).
        transit: how the arm travels through free space to the pre-grasp: "kinematic" (the
            planned path is played back joint by joint and checked for contact at every control
            tick; physics resumes from the last contact-free tick if anything is touched) or
            "dynamic" (simulated throughout).
    """

    control_dt: float = 0.01
    timestep: float = 0.005
    max_speed: tuple[float, float, float, float] = (0.4, 0.8, 0.15, 1.2)
    approach_speed: float = 0.08
    close_time: float = 0.8
    hold_time: float = 2.0
    success_height: float = 0.10
    knock_tolerance: float = 0.02
    disturb_tolerance: float = 0.03
    knock_over_deg: float = 30.0
    measure_margin: bool = False
    margin_steps: int = 7
    transit: str = "kinematic"

    def __post_init__(self) -> None:
        steps = self.control_dt / self.timestep if self.timestep > 0 else 0.0
        if steps < 1 or abs(steps - round(steps)) > 1e-6:
            raise InvalidArgumentError(
                f"timestep must divide control_dt = {self.control_dt} s into whole steps "
                f"(e.g. {self.control_dt / 2:g} or {self.control_dt / 4:g}), got {self.timestep}"
            )
        if self.transit not in TRANSIT_MODES:
            raise InvalidArgumentError(
                f"unknown transit {self.transit!r}; valid: {', '.join(TRANSIT_MODES)}"
            )


@dataclass
class GraspOutcome:
    """What happened when a plan was executed.

    Attributes:
        success: the object is lifted and held.
        failure_reason: one of `posegrasp.core.failures.FAILURE_REASONS`, or None on success.
        lift_height: final clearance of the object's lowest point over the table [m].
        timings_ms: wall time per stage [ms].
        friction_margin: lowest sliding friction coefficient at which the same grasp still holds
            (`Executor.friction_margin`), when measured; None otherwise.
        frames: external-camera frames if recording was requested.
    """

    success: bool
    failure_reason: str | None
    lift_height: float
    timings_ms: dict[str, float] = field(default_factory=dict)
    frames: list[np.ndarray] = field(default_factory=list)
    friction_margin: float | None = None


@dataclass
class PlaceOutcome:
    """What happened when a place was executed.

    Attributes:
        failure_reason: ``dropped`` when the object left the hand before the set-down, else
            None (where it came to rest is scored by the caller).
        timings_ms: wall time per stage [ms].
    """

    failure_reason: str | None
    timings_ms: dict[str, float] = field(default_factory=dict)


def _smoothstep(s: float) -> float:
    return s * s * s * (10 - 15 * s + 6 * s * s)


class Executor:
    """Runs plans in a scene; `recorder(scene)` is called at ~`record_fps` if given."""

    def __init__(
        self,
        scene: Scene,
        config: ExecutionConfig | None = None,
        recorder=None,
        record_fps: float = 10.0,
    ) -> None:
        self.scene = scene
        self.cfg = config or ExecutionConfig()
        m = scene.model
        m.opt.timestep = self.cfg.timestep
        self.act = np.array(
            [m.actuator("act_" + j.removeprefix(C.PREFIX)).id for j in PLANNED_JOINTS]
        )
        self.fingers = np.array(
            [m.actuator("act_" + j.removeprefix(C.PREFIX)).id for j in C.FINGER_JOINTS]
        )
        self.finger_qadr = np.array([m.joint(j).qposadr[0] for j in C.FINGER_JOINTS])
        self.qadr = np.array([m.joint(j).qposadr[0] for j in PLANNED_JOINTS])
        robot_joints = [*PLANNED_JOINTS, *C.FINGER_JOINTS]
        self.dofadr = np.array([m.joint(j).dofadr[0] for j in robot_joints])
        self.finger_geoms = [
            set(np.flatnonzero(m.geom_bodyid == m.body(b).id).tolist()) for b in C.FINGER_BODIES
        ]
        target = m.body(scene.target.body).id
        self.object_geoms = set(np.flatnonzero(m.geom_bodyid == target).tolist())
        robot_bodies = [i for i in range(m.nbody) if m.body(i).name.startswith(C.PREFIX)]
        self.robot_geoms = set(np.flatnonzero(np.isin(m.geom_bodyid, robot_bodies)).tolist())
        self.scene_geoms = set(range(m.ngeom)) - self.robot_geoms
        table = m.body("table").id
        self.table_geoms = set(np.flatnonzero(m.geom_bodyid == table).tolist())
        self.recorder = recorder
        self.record_every = max(1, round(1.0 / (record_fps * self.cfg.control_dt)))
        self._tick = 0
        self.frames: list[np.ndarray] = []
        self.table_hit = False
        self.events: list[str] = []
        self._kinematic = False  # playing the transit back without physics (see `_transit`)
        self.T_world_G_closed: np.ndarray | None = None  # the grasp site as the fingers closed

    # -- low level ---------------------------------------------------------------------------
    def _advance(self, seconds: float) -> None:
        m, d = self.scene.model, self.scene.data
        n = max(1, round(self.cfg.control_dt / m.opt.timestep))
        for _ in range(max(1, round(seconds / self.cfg.control_dt))):
            if not (self._kinematic and self._kinematic_tick()):
                mujoco.mj_step(m, d, nstep=n)
            if not self.table_hit and self._touching(self.robot_geoms, self.table_geoms):
                self.table_hit = True
                self.events.append(f"robot touched the table at t={d.time:.2f} s")
            self._tick += 1
            if self.recorder is not None and self._tick % self.record_every == 0:
                self.frames.append(self.recorder(self.scene))

    def _kinematic_tick(self) -> bool:
        """Put the robot where the controls command it and look for contact; True if the tick
        is done, False (and physics from the last contact-free configuration from now on) if
        the robot touched anything there."""
        m, d = self.scene.model, self.scene.data
        q_prev = d.qpos.copy()
        d.qpos[self.qadr] = d.ctrl[self.act]
        d.qpos[self.finger_qadr] = d.ctrl[self.fingers]
        d.qvel[self.dofadr] = 0.0
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        if self._touching(self.robot_geoms, self.scene_geoms):
            d.qpos[:] = q_prev
            mujoco.mj_forward(m, d)
            self._kinematic = False
            self.events.append(
                f"transit touched the scene at t={d.time:.2f} s; the rest of it is simulated"
            )
            return False
        d.time += self.cfg.control_dt
        return True

    def _transit(self, plan: GraspPlan) -> None:
        """Travel through free space to the pre-grasp (`ExecutionConfig.transit`)."""
        self._kinematic = self.cfg.transit == "kinematic"
        for q in plan.transit:
            self.move(q)
        self.move(plan.hover)
        self.move(plan.pregrasp)
        if self._kinematic:
            self._kinematic = False
            mujoco.mj_forward(self.scene.model, self.scene.data)

    def _duration(self, q0: np.ndarray, q1: np.ndarray) -> float:
        s = self.cfg.max_speed
        speeds = np.array([s[0], s[0], s[1], s[2], *[s[3]] * 7])
        return float(max(0.3, np.max(np.abs(q1 - q0) / speeds)))

    def move(self, q_target: np.ndarray, duration: float | None = None) -> None:
        """Drive the planned joints to q_target along a minimum-jerk profile."""
        d = self.scene.data
        q0 = d.ctrl[self.act].copy()
        T = duration if duration is not None else self._duration(q0, q_target)
        steps = max(1, round(T / self.cfg.control_dt))
        for k in range(1, steps + 1):
            d.ctrl[self.act] = q0 + _smoothstep(k / steps) * (q_target - q0)
            self._advance(self.cfg.control_dt)

    def set_fingers(self, opening: float) -> None:
        """Command each finger to `opening` [m] (0 closed, FINGER_TRAVEL open)."""
        self.scene.data.ctrl[self.fingers] = opening

    def _touching(self, a: set[int], b: set[int]) -> bool:
        """Some contact of the current step is between a geom of a and one of b."""
        if self.scene.data.ncon == 0:
            return False
        contact = self.scene.data.contact  # one view: its fields are read once per call
        for g1, g2 in zip(contact.geom1.tolist(), contact.geom2.tolist(), strict=True):
            if (g1 in a and g2 in b) or (g1 in b and g2 in a):
                return True
        return False

    def held(self) -> bool:
        """Both fingers touch the target object."""
        return all(self._touching(f, self.object_geoms) for f in self.finger_geoms)

    def grasp_site_pose(self) -> np.ndarray:
        """The grasp site's pose in the world now, T_world_G (4, 4) [m] (what the robot's own
        kinematics tell it)."""
        site = self.scene.data.site(C.GRASP_SITE)
        T = np.eye(4)
        T[:3, :3] = site.xmat.reshape(3, 3)
        T[:3, 3] = site.xpos
        return T

    def lift_height(self) -> float:
        """Clearance of the target's lowest point over the table top [m]."""
        return self.scene.object_lowest_z() - self.scene.table_top_z

    def disturbed(self, poses0: dict[str, np.ndarray]) -> list[str]:
        """The other objects moved more than `disturb_tolerance` or tilted more than
        `knock_over_deg` since `poses0` (body -> T_world_O), each as "body (how much)"."""
        out = []
        for body, T0 in poses0.items():
            T = self.scene.object_pose(body)
            moved = float(np.linalg.norm(T[:3, 3] - T0[:3, 3]))
            # Tilt: the angle between the object's z axis before and after.
            tilt = float(np.degrees(np.arccos(np.clip(T[:3, 2] @ T0[:3, 2], -1.0, 1.0))))
            if moved > self.cfg.disturb_tolerance or tilt > self.cfg.knock_over_deg:
                out.append(f"{body} ({moved * 1000:.0f} mm, {tilt:.0f} deg)")
        return out

    def _holds(self) -> bool:
        return self.lift_height() >= self.cfg.success_height and self.held()

    def friction_margin(self) -> float:
        """The lowest sliding friction coefficient at which the current grasp still holds.

        From the grasped state (object lifted and held), the hold is re-run with the friction of
        the object's and the fingers' geoms scaled down (all three MuJoCo coefficients, in
        proportion); bisection between 0 and the nominal coefficient finds where the object
        stops being held after `hold_time` (GraspNet-1Billion's grading, measured in physics).
        The scene's state and friction are restored afterwards.

        Returns:
            The margin, in the units of the sliding coefficient (lower: a firmer grasp).
        """
        m, d = self.scene.model, self.scene.data
        geoms = sorted(self.object_geoms | set().union(*self.finger_geoms))
        nominal = m.geom_friction[geoms].copy()
        mu0 = float(nominal[:, 0].max())
        start = mujoco.MjData(m)
        mujoco.mj_copyData(start, m, d)
        lo, hi = 0.0, mu0
        recorder, self.recorder = self.recorder, None  # the re-runs are not part of the film
        try:
            for _ in range(self.cfg.margin_steps):
                mid = (lo + hi) / 2
                m.geom_friction[geoms] = nominal * (mid / mu0)
                mujoco.mj_copyData(d, m, start)
                self._advance(self.cfg.hold_time)
                if self._holds():
                    hi = mid
                else:
                    lo = mid
        finally:
            m.geom_friction[geoms] = nominal
            mujoco.mj_copyData(d, m, start)
            self.recorder = recorder
        return hi

    # -- the grasp ---------------------------------------------------------------------------
    def execute(self, plan: GraspPlan) -> GraspOutcome:
        """Run pre-grasp, approach, close, lift and hold; score the result."""
        cfg = self.cfg
        d = self.scene.data
        timings: dict[str, float] = {}
        obj0 = self.scene.object_pose()[:3, 3].copy()
        others0 = {o.body: self.scene.object_pose(o.body) for o in self.scene.objects[1:]}

        def fail(reason: str) -> GraspOutcome:
            return GraspOutcome(
                False, check_failure_reason(reason), self.lift_height(), timings, self.frames
            )

        t = time.perf_counter()
        self.set_fingers(C.FINGER_TRAVEL)
        self._transit(plan)
        self._advance(0.2)
        timings["pregrasp"] = (time.perf_counter() - t) * 1000
        t = time.perf_counter()
        seg = 0.0 if not plan.approach else 1.0
        step_len = seg * 0.10 / max(1, len(plan.approach))
        for q in plan.approach:
            self.move(q, duration=max(0.15, step_len / cfg.approach_speed))
        self._advance(0.3)
        timings["approach"] = (time.perf_counter() - t) * 1000
        moved = float(np.linalg.norm(self.scene.object_pose()[:3, 3] - obj0))
        if self.table_hit or moved > cfg.knock_tolerance:
            return fail("collision")

        t = time.perf_counter()
        self.set_fingers(0.0)
        elapsed = 0.0
        prev = d.qpos[self.finger_qadr].copy()
        while elapsed < cfg.close_time:
            self._advance(0.05)
            elapsed += 0.05
            now = d.qpos[self.finger_qadr].copy()
            if elapsed > 0.2 and np.max(np.abs(now - prev)) < 2e-4:
                break
            prev = now
        timings["close"] = (time.perf_counter() - t) * 1000
        self.T_world_G_closed = self.grasp_site_pose()
        if not self.held():
            return fail("missed")

        t = time.perf_counter()
        self.move(plan.lift, duration=max(1.0, self._duration(d.ctrl[self.act], plan.lift)))
        timings["lift"] = (time.perf_counter() - t) * 1000
        t = time.perf_counter()
        self._advance(cfg.hold_time)
        timings["hold"] = (time.perf_counter() - t) * 1000
        h = self.lift_height()
        if self._holds():
            disturbed = self.disturbed(others0)
            if disturbed:
                self.events.append("disturbed: " + ", ".join(disturbed))
                return fail("disturbed")
            margin = None
            if cfg.measure_margin:
                t = time.perf_counter()
                margin = self.friction_margin()
                timings["margin"] = (time.perf_counter() - t) * 1000
            return GraspOutcome(True, None, h, timings, self.frames, margin)
        return fail("slipped")

    # -- the place ---------------------------------------------------------------------------
    def place(self, plan: PlacePlan, settle_time: float) -> PlaceOutcome:
        """From the held lift: carry the object to above its set-down at `PLACE_CARRY_SLOWDOWN`
        times the transit's time, descend until the object touches the table (a guarded move:
        the arm feels the table through its joint efforts) or the set-down is reached, release,
        retreat straight up and let the object settle for `settle_time` [s]."""
        timings: dict[str, float] = {}
        t = time.perf_counter()
        q0 = self.scene.data.ctrl[self.act].copy()
        self.move(plan.hover, duration=PLACE_CARRY_SLOWDOWN * self._duration(q0, plan.hover))
        self._advance(0.2)
        timings["carry"] = (time.perf_counter() - t) * 1000
        if not self.held():
            self.events.append("the object left the hand on the way to the goal")
            return PlaceOutcome(check_failure_reason("dropped"), timings)
        t = time.perf_counter()
        touched = self._guarded_descent(plan)
        if touched is not None:
            self.events.append(f"the object touched the table {touched * 1000:.0f} mm early")
        timings["set_down"] = (time.perf_counter() - t) * 1000
        t = time.perf_counter()
        self.set_fingers(C.FINGER_TRAVEL)
        self._advance(0.4)
        self.move(plan.retreat)
        self._advance(settle_time)
        timings["release"] = (time.perf_counter() - t) * 1000
        return PlaceOutcome(None, timings)

    def _guarded_descent(self, plan: PlacePlan) -> float | None:
        """Lower the held object through the plan's descent at the approach speed, stopping
        where it first touches the table; how far above the set-down [m] it stopped (None: it
        reached the set-down without touching)."""
        d = self.scene.data
        q_prev = d.ctrl[self.act].copy()
        duration = max(0.15, plan.step_m / self.cfg.approach_speed)
        steps = max(1, round(duration / self.cfg.control_dt))
        for q in plan.descent:
            for k in range(1, steps + 1):
                d.ctrl[self.act] = q_prev + _smoothstep(k / steps) * (q - q_prev)
                self._advance(self.cfg.control_dt)
                if self._touching(self.object_geoms, self.table_geoms):
                    d.ctrl[self.act] = d.qpos[self.qadr]
                    return max(0.0, float(self.grasp_site_pose()[2, 3] - plan.T_world_G[2, 3]))
            q_prev = q
        self._advance(0.2)
        return None
