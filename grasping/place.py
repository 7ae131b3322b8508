"""Planning the place: carrying a held object to a goal pose and setting it down.

The robot knows where the object sits in its hand only through the estimate: the object-in-
gripper transform is the estimated pose at grasp time seen from the gripper as it closed
(`held_transform`), so every pose error, and any slip in the hand since, shows up where the
object ends. The set-down pose of the gripper puts the object, as the robot believes it lies
in the hand, at the goal, `PlaceConfig.drop` above it (`set_down_pose`); the arm reaches it from
straight above and leaves the same way.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from grasping.planner import GraspPlanner, NoConvergence, PlanningError
from posegrasp.core.errors import UnknownNameError

#: Where the robot's belief of the object in its hand comes from (`PlaceConfig.belief`).
BELIEFS = ("predicted", "estimate", "truth")
#: The belief of a place record that names none: every one made before ``predicted`` was.
UNNAMED_BELIEF = "estimate"


@dataclass(frozen=True)
class PlaceConfig:
    """Place settings. Lengths in [m].

    Attributes:
        hover_height: the gripper hovers this far above its set-down pose before descending
            and after releasing.
        drop: the object is released this far above where the robot believes the goal is, so
            that a belief a little low does not push it into the table.
        descent_waypoints: IK waypoints on the way down (the set-down pose the last).
        belief: where the robot believes the object lies in its hand, one of `BELIEFS`:
            ``predicted`` (the task as scored), the estimated pose at grasp time seen from the
            gripper as it closed (`held_transform`), moved in the hand as the physics check of
            the chosen grasp (`grasping.grasp_check.held_in_hand`) moves the object when its
            hand closes, lifts and holds (`predicted_hold`); ``estimate``, the same not moved;
            ``truth``, the true pose in the hand after the lift (privileged: what a perfect look
            at the object in the hand would give; it measures the place skill itself, without
            the estimate or the grasp's shift).
    """

    hover_height: float = 0.10
    drop: float = 0.008
    descent_waypoints: int = 3
    belief: str = "predicted"

    def __post_init__(self) -> None:
        if self.belief not in BELIEFS:
            raise UnknownNameError("place belief", self.belief, BELIEFS)


@dataclass(frozen=True)
class PlacePlan:
    """A planned place.

    Attributes:
        T_world_G: the grasp site's pose at the set-down (4, 4) [m].
        hover: planned joint values above the set-down (`grasping.planner.PLANNED_JOINTS`).
        descent: planned joint values on the way down, ending at the set-down.
        retreat: planned joint values after releasing, above the set-down.
        step_m: how far each descent waypoint lies below the one before [m].
        ik_ms: time spent in IK [ms].
    """

    T_world_G: np.ndarray
    hover: np.ndarray
    descent: list[np.ndarray]
    retreat: np.ndarray
    step_m: float
    ik_ms: float


def held_transform(T_world_G: np.ndarray, T_world_O_est: np.ndarray) -> np.ndarray:
    """The object-in-gripper transform T_G_O (4, 4) the robot believes: the estimated object
    pose T_world_O_est (4, 4) seen from the grasp site at T_world_G (4, 4), as it closed."""
    return np.linalg.inv(T_world_G) @ T_world_O_est


def predicted_hold(T_G_O: np.ndarray, T_O_G: np.ndarray, T_G_O_held: np.ndarray) -> np.ndarray:
    """The belief T_G_O (4, 4) moved in the hand as a check of its grasp moved the object: the
    check planned the hand at T_O_G (4, 4), the object at inv(T_O_G) in it, and left it at
    T_G_O_held (4, 4); the same motion, in the grasp site's frame, applied to the belief."""
    return T_G_O_held @ T_O_G @ T_G_O


def set_down_pose(T_world_goal: np.ndarray, T_G_O: np.ndarray, drop: float) -> np.ndarray:
    """The grasp site's pose (4, 4) that puts the object, held as T_G_O (4, 4), at the goal
    T_world_goal (4, 4) raised by `drop` [m]."""
    T_goal = T_world_goal.copy()
    T_goal[2, 3] += drop
    return T_goal @ np.linalg.inv(T_G_O)


class PlacePlanner:
    """Plans places with a grasp planner's IK (its tasks, limits and posture).

    Args:
        planner: the grasp planner of the scene.
        config: the place settings.
    """

    def __init__(self, planner: GraspPlanner, config: PlaceConfig | None = None) -> None:
        self.planner, self.cfg = planner, config or PlaceConfig()

    def plan(self, T_world_G: np.ndarray, q_now: np.ndarray) -> PlacePlan:
        """IK, from the full qpos `q_now` (the object held, after the lift), through hover,
        descent to the set-down pose T_world_G (4, 4) and back up.

        Raises:
            PlanningError: ``place_infeasible`` when a target's IK does not converge.
        """
        t0 = time.perf_counter()
        up = np.eye(4)
        up[2, 3] = self.cfg.hover_height
        T_hover = up @ T_world_G
        n = self.cfg.descent_waypoints
        p = self.planner
        p.configuration.update(q_now.copy())
        try:
            hover = p.reach(T_hover, "place hover")
            descent = []
            for k in range(1, n + 1):
                T_k = T_world_G.copy()
                T_k[2, 3] += (1 - k / n) * self.cfg.hover_height
                descent.append(p.reach(T_k, "set-down"))
            retreat = p.reach(T_hover, "retreat")
        except NoConvergence as exc:
            raise PlanningError("place_infeasible", str(exc)) from None
        step = self.cfg.hover_height / n
        return PlacePlan(
            T_world_G, hover, descent, retreat, step, (time.perf_counter() - t0) * 1000
        )
