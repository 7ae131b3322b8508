"""Where the place task puts the target: a goal pose on the table, drawn from the episode seed.

The goal is the target as it rests now, moved across the table and turned about the vertical:
the same resting face down, so physics can hold it there. It is drawn on a random stream of
its own (the episode seed and `GOAL_STREAM`), after the scene has settled, so a scene is the
same with and without a goal and every estimator of an episode gets the same goal.

A goal is accepted when the target's footprint there lies inside `GoalConfig.region` (on the
table, within the arm's reach from the base without driving) and clear of every other
object's footprint by `GoalConfig.clearance`; draws are repeated from the same stream until
one is. On a table too crowded for that, the gap kept is halved, and then the goal is the
target turned where it stands.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from posegrasp.core.errors import InvalidArgumentError
from posegrasp.world.scene import Scene

#: What the robot does with the object: ``lift`` it and hold it, or lift it and ``place`` it at
#: a goal pose on the table (`draw_goal`).
TASKS = ("lift", "place")
#: The second word of the goal's random stream, ``default_rng([seed, GOAL_STREAM])``.
GOAL_STREAM = 0x601
#: Draws before giving up on a goal.
GOAL_ATTEMPTS = 500


@dataclass(frozen=True)
class GoalConfig:
    """How goals are drawn. Lengths in [m], angles in [deg], world frame.

    Attributes:
        distance: the range of the horizontal move of the target's origin.
        turn_deg: the range of the magnitude of the turn about the vertical (either way).
        region: the x and y ranges the goal's origin lies in (the table's reachable part).
        clearance: the least gap between the goal's footprint and any other object's (their
            mesh points' nearest pair, on the table) [m]: room for the gripper's palm and its
            open fingers, which reach up to 5 cm beyond a held object's sides.
        edge: the least distance of the goal's footprint from the table top's edge [m].
    """

    distance: tuple[float, float] = (0.06, 0.30)
    turn_deg: tuple[float, float] = (20.0, 90.0)
    region: tuple[tuple[float, float], tuple[float, float]] = ((0.45, 0.9), (-0.4, 0.4))
    clearance: float = 0.05
    edge: float = 0.03

    def __post_init__(self) -> None:
        lo, hi = self.distance
        if not 0 < lo <= hi:
            raise InvalidArgumentError(f"GoalConfig.distance must be 0 < lo <= hi, got {lo, hi}")
        lo, hi = self.turn_deg
        if not 0 <= lo <= hi <= 180:
            raise InvalidArgumentError(
                f"GoalConfig.turn_deg must be 0 <= lo <= hi <= 180, got {lo, hi}"
            )


@dataclass(frozen=True)
class PlaceGoal:
    """A goal of the place task.

    Attributes:
        T_world_O: the target's goal pose (4, 4) [m].
        moved_m: the horizontal move of its origin from where it rests [m].
        turned_deg: the signed turn about the vertical [deg].
        clearance_m: the gap kept from the other objects [m] (`GoalConfig.clearance`, or half
            of it on a crowded table).
    """

    T_world_O: np.ndarray
    moved_m: float
    turned_deg: float
    clearance_m: float

    def to_json(self) -> dict:
        """The goal as JSON: the pose as nested lists, the move and the turn."""
        return {
            "T_world_O": self.T_world_O.tolist(),
            "moved_m": self.moved_m,
            "turned_deg": self.turned_deg,
            "clearance_m": self.clearance_m,
        }


#: Mesh points per object that stand for its footprint.
FOOTPRINT_POINTS = 400


def footprint(vertices: np.ndarray, T_world_O: np.ndarray) -> np.ndarray:
    """An object's footprint on the table: its mesh `vertices` (N, 3) [m], at most
    `FOOTPRINT_POINTS` of them evenly taken, in the pose T_world_O (4, 4), as world xy (M, 2)."""
    v = np.asarray(vertices, float)
    v = v[:: max(1, len(v) // FOOTPRINT_POINTS)]
    return (v @ T_world_O[:3, :3].T + T_world_O[:3, 3])[:, :2]


def table_top_bounds(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """The table top's extent in world xy [m]: its lowest and highest corner, (2,) each (the
    top is an axis-aligned box, the geom ``table_top``)."""
    m, d = scene.model, scene.data
    g = m.geom("table_top")
    centre, half = (
        d.geom_xpos[g.id][:2],
        np.abs(d.geom_xmat[g.id].reshape(3, 3)[:2, :2]) @ g.size[:2],
    )
    return centre - half, centre + half


def turned(T_world_O: np.ndarray, xy: np.ndarray, yaw: float) -> np.ndarray:
    """T_world_O (4, 4) turned by `yaw` [rad] about the vertical through its origin, the origin
    then put at `xy` (2,) [m], its height kept."""
    c, s = math.cos(yaw), math.sin(yaw)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    T = T_world_O.copy()
    T[:3, :3] = Rz @ T_world_O[:3, :3]
    T[:2, 3] = xy
    return T


def draw_goal(scene: Scene, config: GoalConfig | None = None) -> PlaceGoal:
    """The goal of the scene's target (see the module docstring), drawn from its seed.

    Raises:
        InvalidArgumentError: no draw of `GOAL_ATTEMPTS` is clear and reachable (a crowded
            table); the message names the seed.
    """
    cfg = config or GoalConfig()
    rng = np.random.default_rng([scene.seed, GOAL_STREAM])
    T0 = scene.object_pose()
    target = scene.target
    vertices = np.asarray(target.model.mesh.vertices)
    others = [
        footprint(np.asarray(o.model.mesh.vertices), scene.object_pose(o.body))
        for o in scene.objects[1:]
    ]
    tree = cKDTree(np.concatenate(others)) if others else None
    (x0, x1), (y0, y1) = cfg.region
    lo, hi = table_top_bounds(scene)

    def clear(T: np.ndarray, clearance: float) -> bool:
        xy = footprint(vertices, T)
        if (xy < lo + cfg.edge).any() or (xy > hi - cfg.edge).any():
            return False
        return tree is None or bool(tree.query(xy)[0].min() >= clearance)

    # Full clearance first, then half of it, then the target turned where it stands.
    tries = [(cfg.clearance, True), (cfg.clearance / 2, True), (cfg.clearance / 2, False)]
    for clearance, move in tries:
        for _ in range(GOAL_ATTEMPTS):
            distance = rng.uniform(*cfg.distance) if move else 0.0
            heading = rng.uniform(-math.pi, math.pi)
            turn = math.radians(rng.uniform(*cfg.turn_deg)) * rng.choice((-1.0, 1.0))
            xy = T0[:2, 3] + distance * np.array([math.cos(heading), math.sin(heading)])
            if not (x0 <= xy[0] <= x1 and y0 <= xy[1] <= y1):
                continue
            T = turned(T0, xy, turn)
            if clear(T, clearance):
                return PlaceGoal(T, float(distance), math.degrees(turn), clearance)
    raise InvalidArgumentError(
        f"no goal of seed {scene.seed} for the {target.name} is clear of the other objects "
        f"within {cfg.region} in {len(tries) * GOAL_ATTEMPTS} draws; use fewer objects"
    )
