"""Grasp planning with mink: base, torso and arm together, on an *estimated* object pose.

For each candidate (best first) the planner solves differential IK for the pre-grasp pose
(backed off along the approach), a few waypoints down the approach line to the grasp pose, and
the lift pose, with a `FrameTask` on the grasp site, a `PostureTask` that keeps the robot near its
start (so the base moves only when the arm alone cannot reach), configuration limits and
collision avoidance between the gripper/forearm and the table. Head, fingers and every object's
free joint are frozen with a `DofFreezingTask` constraint.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import mink
import mujoco
import numpy as np

from grasping.candidates import GraspCandidate, grasp_candidates
from grasping.clearance import intrusion
from grasping.top_grasps import FINGER_OUTER_Y, FINGER_X, FINGER_Z
from posegrasp.core.errors import PosegraspError
from posegrasp.core.failures import check_failure_reason
from posegrasp.core.transforms import check_rigid
from posegrasp.world import constants as C

#: Accepted deviation of an estimated rotation from orthonormality (estimates come as float32).
POSE_TOL = 1e-4

#: Joints the planner moves, in this order.
PLANNED_JOINTS: tuple[str, ...] = (*C.BASE_JOINTS, C.TORSO_JOINT, *C.ARM_JOINTS)
#: Robot geoms kept away from the table by the collision-avoidance limit.
GUARDED_BODIES: tuple[str, ...] = (
    C.GRIPPER_BODY,
    *C.FINGER_BODIES,
    C.PREFIX + "wrist_roll_link",
    C.PREFIX + "wrist_flex_link",
    C.PREFIX + "forearm_roll_link",
)


#: Torso and arm posture the IK is pulled toward: torso up, upper arm forward, forearm and
#: gripper pointing down over the table.
READY_POSTURE = np.array([0.3, 0.0, -0.3, 0.0, 1.6, 0.0, 1.3, 0.0])
#: Transit from the tucked arm to above the table without sweeping through the objects: raise
#: the torso, lift the upper arm while it is still beside the robot, then swing it forward high
#: above the table (torso and arm joints; the IK starts from the last one).
TRANSIT_POSTURES = (
    np.array([0.38, 1.32, 1.40, -0.2, 1.72, 0.0, 1.66, 0.0]),
    np.array([0.38, 1.32, -0.9, -0.2, 1.72, 0.0, 1.66, 0.0]),
    np.array([0.38, 0.0, -0.9, 0.0, 1.8, 0.0, 0.7, 0.0]),
)


class PlanningError(PosegraspError):
    """No plan: `reason` is "unreachable", "no_grasp" or "ik_infeasible"."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = check_failure_reason(reason)


class NoConvergence(Exception):
    """One IK target of a candidate was not reached."""


@dataclass(frozen=True)
class PlannerConfig:
    """Planner settings. Lengths [m], angles [rad].

    Attributes:
        pregrasp_offset: distance backed off along the approach before the final approach.
        approach_waypoints: IK waypoints on the approach line (excluding the pre-grasp).
        lift_height: how far the grasp site rises for the lift.
        max_iters: IK iterations per target.
        pos_tol, rot_tol: IK convergence tolerances.
        dt: integration step of the differential IK [s].
        max_step: velocity limits of the IK iterations for (base xy [m/s], base yaw, torso [m/s],
            arm [rad/s]); with dt they bound each iteration's step so the solver stays near its
            seed instead of jumping to a distant solution.
        max_candidates: candidates tried before giving up.
        max_reach: horizontal distance from the base beyond which a grasp is unreachable.
        drive_beyond: horizontal distance from the base beyond which the base first drives
            (arm tucked) to `standoff` from the object, facing it.
        standoff: horizontal distance from the object at which a drive ends.
        max_drive: longest drive [m]; farther objects are unreachable.
        posture_cost: PostureTask cost per planned joint group (base xy, base yaw, torso, arm).
        max_approach_tilt: candidates whose approach, at the estimated pose, leans more than
            this from straight down are not tried [rad].
        candidates: where a built-in object's candidates come from
            (`grasping.candidates.CANDIDATE_SOURCES`: ``designed`` or ``generated``).
    """

    pregrasp_offset: float = 0.10
    approach_waypoints: int = 3
    lift_height: float = 0.18
    max_iters: int = 80
    hover_height: float = 0.15
    pos_tol: float = 2e-3
    rot_tol: float = 1.5e-2
    dt: float = 0.1
    max_step: tuple[float, float, float, float] = (0.5, 1.0, 0.5, 3.0)
    max_candidates: int = 4
    max_reach: float = 1.3
    drive_beyond: float = 0.9
    standoff: float = 0.62
    max_drive: float = 2.0
    posture_cost: tuple[float, float, float, float] = (0.05, 0.05, 0.01, 0.002)
    max_approach_tilt: float = float(np.deg2rad(30.0))
    candidates: str = "designed"


@dataclass
class GraspPlan:
    """A planned grasp.

    Attributes:
        candidate: the chosen candidate.
        T_world_G: grasp-site pose at the grasp, shape (4, 4).
        transit: joint values that bring the arm from its tucked start to above the table.
        hover: planned joint values above the pre-grasp (PLANNED_JOINTS order).
        pregrasp: planned joint values at the pre-grasp.
        approach: joint values along the approach, ending at the grasp.
        lift: joint values after lifting.
        ik_ms: time spent in IK [ms].
        tried: how many candidates were tried.
    """

    candidate: GraspCandidate
    T_world_G: np.ndarray
    transit: list[np.ndarray]
    hover: np.ndarray
    pregrasp: np.ndarray
    approach: list[np.ndarray]
    lift: np.ndarray
    ik_ms: float
    tried: int
    notes: list[str] = field(default_factory=list)


def _se3(T: np.ndarray) -> mink.SE3:
    return mink.SE3.from_matrix(T)


class GraspPlanner:
    """Plans grasps in one scene model (built once per scene)."""

    def __init__(
        self,
        model: mujoco.MjModel,
        table_geom: str = "table_top",
        config: PlannerConfig | None = None,
    ) -> None:
        self.model = model
        self.table_geom = table_geom
        self.cfg = config or PlannerConfig()
        self.configuration = mink.Configuration(model)
        self.qadr = np.array([model.joint(j).qposadr[0] for j in PLANNED_JOINTS])
        planned_dofs = {int(model.joint(j).dofadr[0]) for j in PLANNED_JOINTS}
        frozen = [i for i in range(model.nv) if i not in planned_dofs]
        self.freeze = mink.DofFreezingTask(model, dof_indices=frozen)
        self.frame_task = mink.FrameTask(
            C.GRASP_SITE, "site", position_cost=1.0, orientation_cost=0.5, lm_damping=1e-3
        )
        self.posture = mink.PostureTask(model, cost=1e-3)
        cost = np.full(model.nv, 1e-3)
        pc = self.cfg.posture_cost
        for j, c in zip(PLANNED_JOINTS, (pc[0], pc[0], pc[1], pc[2], *[pc[3]] * 7), strict=True):
            cost[model.joint(j).dofadr[0]] = c
        self.posture.set_cost(cost)
        guarded = [
            model.geom(g).name
            for g in range(model.ngeom)
            if model.body(model.geom_bodyid[g]).name in GUARDED_BODIES
            and model.geom_contype[g] != 0
        ]
        ms = self.cfg.max_step
        vel = dict(zip(PLANNED_JOINTS, (ms[0], ms[0], ms[1], ms[2], *[ms[3]] * 7), strict=True))
        self.limits: list[mink.Limit] = [
            mink.ConfigurationLimit(model),
            mink.VelocityLimit(model, vel),
            mink.CollisionAvoidanceLimit(
                model,
                [(guarded, [table_geom])],
                minimum_distance_from_collisions=0.005,
                collision_detection_distance=0.05,
            ),
        ]

    def _solve(self, T_target: np.ndarray) -> tuple[bool, float, float]:
        self.frame_task.set_target(_se3(T_target))
        cfg = self.cfg
        pe = re = np.inf
        for _ in range(cfg.max_iters):
            err = self.frame_task.compute_error(self.configuration)
            pe, re = float(np.linalg.norm(err[:3])), float(np.linalg.norm(err[3:]))
            if pe < cfg.pos_tol and re < cfg.rot_tol:
                return True, pe, re
            try:
                v = mink.solve_ik(
                    self.configuration,
                    [self.frame_task, self.posture],
                    cfg.dt,
                    "daqp",
                    damping=1e-4,
                    limits=self.limits,
                    constraints=[self.freeze],
                )
            except mink.exceptions.NoSolutionFound:
                return False, pe, re
            self.configuration.integrate_inplace(v, cfg.dt)
        return pe < cfg.pos_tol and re < cfg.rot_tol, pe, re

    def reach(self, T_target: np.ndarray, stage: str) -> np.ndarray:
        """Solve IK for a grasp-site pose from the current configuration; planned joints."""
        ok, pe, re = self._solve(T_target)
        if not ok:
            raise NoConvergence(
                f"{stage} IK did not converge ({pe * 1000:.1f} mm, {np.rad2deg(re):.1f} deg)"
            )
        return self.configuration.q[self.qadr].copy()

    @functools.cached_property
    def table_top_z(self) -> float:
        """Height of the table's top surface in the world [m] (the table does not move)."""
        data = mujoco.MjData(self.model)
        mujoco.mj_kinematics(self.model, data)
        g = self.model.geom(self.table_geom)
        R = data.geom_xmat[g.id].reshape(3, 3)
        return float(data.geom_xpos[g.id][2] + np.abs(R[2]) @ g.size)

    def _tips_low(self, T: np.ndarray, margin: float) -> bool:
        """Whether the open fingertips at grasp pose T (4, 4) come within margin of the table."""
        corners = np.array(
            [[FINGER_X[1], sy * FINGER_OUTER_Y, sz * FINGER_Z] for sy in (-1, 1) for sz in (-1, 1)]
        )
        z = corners @ T[2, :3] + T[2, 3]
        return bool(z.min() < self.table_top_z + margin)

    def order_candidates(
        self,
        T_world_O: np.ndarray,
        candidates: tuple[GraspCandidate, ...],
        q: np.ndarray,
        neighbours: Sequence[tuple[str, np.ndarray]] = (),
    ) -> list[tuple[GraspCandidate, np.ndarray]]:
        """Candidates in world frame that approach from above (within `max_approach_tilt`) and,
        those with a `GraspCandidate.table_margin`, keep the open fingertips that far above
        the table; best first: those clear of the known `neighbours` ((class, T_world_N) pairs,
        `grasping.clearance`) before the others; among them the gripper's z axis pointing away
        from the robot (no wrist flip needed), then the grasp point nearest the robot."""
        base_xy = q[self.qadr[:2]]
        scored = []
        min_down = float(np.cos(self.cfg.max_approach_tilt))
        for c in candidates:
            T = T_world_O @ c.T_O_G
            if -T[2, 0] < min_down:
                continue
            if c.table_margin is not None and self._tips_low(T, c.table_margin):
                continue
            radial = T[:2, 3] - base_xy
            dist = float(np.linalg.norm(radial))
            radial = radial / max(dist, 1e-9)
            align = float(T[:2, 2] @ radial)
            down = float(-T[2, 0])  # approach pointing down
            blocked = intrusion(T, neighbours) > 0
            scored.append(((blocked, -(align + 2 * down) + 0.5 * dist), c, T))
        scored.sort(key=lambda s: s[0])
        return [(c, T) for _, c, T in scored]

    def _drive(
        self, T_world_O: np.ndarray, q_start: np.ndarray
    ) -> tuple[np.ndarray, list[np.ndarray]]:
        """The configuration to plan from and the drive that gets there (empty when the object is
        within `drive_beyond`): the base moves, arm tucked, to `standoff` from the object."""
        cfg = self.cfg
        base_xy = q_start[self.qadr[:2]]
        offset = T_world_O[:2, 3] - base_xy
        horiz = float(np.linalg.norm(offset))
        if horiz <= cfg.drive_beyond:
            return q_start, []
        if horiz - cfg.standoff > cfg.max_drive:
            raise PlanningError(
                "unreachable",
                f"object is {horiz:.2f} m from the base; the base drives at most {cfg.max_drive} m",
            )
        u = offset / horiz
        q = q_start.copy()
        q[self.qadr[:2]] = T_world_O[:2, 3] - cfg.standoff * u
        q[self.qadr[2]] = float(np.arctan2(u[1], u[0]))
        return q, [q[self.qadr].copy()]

    def plan(
        self,
        name: str,
        T_world_O: np.ndarray,
        q_start: np.ndarray,
        neighbours: Sequence[tuple[str, np.ndarray]] = (),
    ) -> GraspPlan:
        """Plan a grasp of object class `name` at the (estimated) pose T_world_O.

        Args:
            name: object class.
            T_world_O: estimated object pose in the world, shape (4, 4).
            q_start: current full qpos of the scene model.
            neighbours: the other objects the robot knows of, (class, T_world_N) pairs; grasps
                clear of them are tried first.

        Returns:
            The plan.

        Raises:
            InvalidArgumentError: T_world_O is not a finite rigid transform.
            PlanningError: "unreachable" when the object is beyond reach even with base motion;
                "no_grasp" when no candidate approaches from above at this pose (the object
                lies in a pose the gripper cannot take it in); "ik_infeasible" when no
                candidate's IK converges.
        """
        check_rigid(T_world_O, "estimated object pose", tol=POSE_TOL)
        t0 = time.perf_counter()
        q_start, transit = self._drive(T_world_O, q_start)
        self._check_reach(T_world_O, q_start)
        seed = self._prepare_transit(q_start, transit)
        tried = 0
        last = ""
        cands = grasp_candidates(name, self.cfg.candidates)
        ordered = self.order_candidates(T_world_O, cands, q_start, neighbours)
        if not ordered:
            raise PlanningError(
                "no_grasp", f"no grasp of the {name} approaches from above in this pose"
            )
        for cand, T_grasp in ordered:
            if tried >= self.cfg.max_candidates:
                break
            tried += 1
            try:
                q_hover, q_pre, waypoints, q_lift = self._reach_grasp(T_grasp, seed)
            except NoConvergence as exc:
                last = str(exc)
                continue
            return GraspPlan(
                cand,
                T_grasp,
                transit,
                q_hover,
                q_pre,
                waypoints,
                q_lift,
                (time.perf_counter() - t0) * 1000,
                tried,
            )
        raise PlanningError("ik_infeasible", f"no grasp candidate is feasible: {last}")

    def _check_reach(self, T_world_O: np.ndarray, q_start: np.ndarray) -> None:
        """Fail with "unreachable" when the object at T_world_O (4, 4) lies farther than
        `max_reach` [m], horizontally, from the base in the full qpos `q_start` (after the
        drive)."""
        base_xy = q_start[self.qadr[:2]]
        horiz = float(np.linalg.norm(T_world_O[:2, 3] - base_xy))
        if horiz > self.cfg.max_reach:
            raise PlanningError(
                "unreachable",
                f"object is {horiz:.2f} m from the base; reach limit is {self.cfg.max_reach} m",
            )

    def _prepare_transit(self, q_start: np.ndarray, transit: list[np.ndarray]) -> np.ndarray:
        """Append the `TRANSIT_POSTURES` to `transit` (planned joints, from the full qpos
        `q_start` after the drive), pull the posture task toward `READY_POSTURE`, and return
        the full qpos every candidate's IK starts from: the last transit posture."""
        for posture in TRANSIT_POSTURES:
            q = q_start[self.qadr].copy()
            q[3:] = posture
            transit.append(q)
        seed = q_start.copy()
        seed[self.qadr] = transit[-1]
        target = q_start.copy()
        target[self.qadr[3:]] = READY_POSTURE
        self.posture.set_target(target)
        return seed

    def _grasp_targets(
        self, T_grasp: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], np.ndarray]:
        """The grasp-site poses (world, (4, 4) each) of a grasp at T_grasp: hover (above the
        pre-grasp by `hover_height`), pre-grasp (backed off `pregrasp_offset` along the
        approach), the `approach_waypoints` on the approach line ending at T_grasp, and lift
        (`lift_height` above T_grasp)."""
        approach_dir = T_grasp[:3, 0]
        T_pre = T_grasp.copy()
        T_pre[:3, 3] -= self.cfg.pregrasp_offset * approach_dir
        T_hover = T_pre.copy()
        T_hover[2, 3] += self.cfg.hover_height
        n = self.cfg.approach_waypoints
        T_approach = []
        for k in range(1, n + 1):
            T_k = T_grasp.copy()
            T_k[:3, 3] -= (1 - k / n) * self.cfg.pregrasp_offset * approach_dir
            T_approach.append(T_k)
        T_lift = T_grasp.copy()
        T_lift[2, 3] += self.cfg.lift_height
        return T_hover, T_pre, T_approach, T_lift

    def _reach_grasp(
        self, T_grasp: np.ndarray, seed: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], np.ndarray]:
        """IK, from the full qpos `seed`, through the targets of a grasp at T_grasp (4, 4,
        world; `_grasp_targets`) in turn; planned joints at hover, pre-grasp, each approach
        waypoint and lift.

        Raises:
            NoConvergence: a target was not reached.
        """
        self.configuration.update(seed.copy())
        T_hover, T_pre, T_approach, T_lift = self._grasp_targets(T_grasp)
        q_hover = self.reach(T_hover, "hover")
        q_pre = self.reach(T_pre, "pre-grasp")
        waypoints = [self.reach(T_k, "approach") for T_k in T_approach]
        q_lift = self.reach(T_lift, "lift")
        return q_hover, q_pre, waypoints, q_lift
