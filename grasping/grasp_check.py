"""Grasp candidates checked in physics: the Fetch gripper alone closes on the object and lifts it.

Each candidate gets a copy of the object resting on a plane (the scenes' contact settings,
`posegrasp.world.resting.PLANE_XML`), settled first (0.5 s at the scene's 2 ms step), and a copy
of the converted Fetch gripper (its link, both fingers, their actuators; `posegrasp.world.robot`)
at the candidate's pre-grasp (0.10 m back along the approach), carried by stiff servoed slides as
an arm tracking its plan carries it. Copies stand apart and are simulated together, at the
executor's 5 ms step, through the stages of `grasping.execute`: the hand goes down at 0.08 m/s to
the grasp, the fingers close for 0.8 s, the hand lifts 0.18 m in 1 s and holds 2 s. Outcomes, as
an episode names them: ``collision`` (the hand touched the plane, or the object moved more than
2 cm before the fingers closed), ``missed`` (not both fingers on the object once closed),
``slipped`` (not held at least 0.10 m above the plane by both fingers after the hold), else
``success``.
"""

from __future__ import annotations

import functools
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import mujoco
import numpy as np

from posegrasp.core.progress import progress_bar
from posegrasp.core.transforms import mat_to_quat
from posegrasp.world import constants as C
from posegrasp.world.objects import ObjectModel
from posegrasp.world.resting import PLANE_XML
from posegrasp.world.robot import fetch_spec

#: Outcomes of a checked grasp.
OUTCOMES = ("success", "collision", "missed", "slipped")
#: The hand's servos along its own axes: stiffness [N/m], joint damping [N s/m], force limit [N].
HAND_KP = 2.0e4
HAND_DAMPING = 400.0
HAND_FORCE = 300.0


@dataclass(frozen=True)
class CheckConfig:
    """The stages of a checked grasp (lengths [m], times [s]).

    Attributes:
        settle: time the object is left to settle first, at `settle_timestep`.
        settle_timestep, timestep: physics steps while settling and while grasping.
        pregrasp: distance back along the approach the hand starts from.
        approach_speed: speed down the approach [m/s].
        close_time: time the fingers are given to close.
        lift, lift_time: how far and in what time the hand lifts.
        hold: time held after the lift.
        success_height: required clearance of the object's lowest point over the plane.
        knock_tolerance: object displacement before closing that counts as a collision.
        batch: candidates simulated together.
        threads: batches simulated at once, each in a thread of its own (MuJoCo steps without
            holding the GIL; every batch is its own model, so the outcomes do not depend on
            it).
    """

    settle: float = 0.5
    settle_timestep: float = 0.002
    timestep: float = 0.005
    pregrasp: float = 0.10
    approach_speed: float = 0.08
    close_time: float = 0.8
    lift: float = 0.18
    lift_time: float = 1.0
    hold: float = 2.0
    success_height: float = 0.10
    knock_tolerance: float = 0.02
    batch: int = 16
    threads: int = 1


@functools.cache
def _gripper_source() -> mujoco.MjSpec:
    """A spec holding the converted Fetch, whose gripper link subtree is copied per hand, with
    only the meshes that subtree uses: attaching copies every mesh of the spec, and compiling
    the robot's other meshes for every hand took most of a batch's set-up."""
    spec = fetch_spec()
    geoms = spec.body(C.GRIPPER_BODY).find_all(mujoco.mjtObj.mjOBJ_GEOM)
    used = {g.meshname for g in geoms if g.type == mujoco.mjtGeom.mjGEOM_MESH}
    for mesh in list(spec.meshes):
        if mesh.name not in used:
            spec.delete(mesh)
    return spec


def _smooth(s: float) -> float:
    return s * s * s * (10 - 15 * s + 6 * s * s)


class _Batch:
    """Copies of the object, settled, and a hand at the pre-grasp of each candidate, in one
    model. A hand is the gripper link carried by three slide joints along its own axes, each
    driven by a stiff position servo (as the arm's joints track its plan), under gravity
    compensation."""

    def __init__(
        self,
        obj: ObjectModel,
        poses: list[np.ndarray],
        grasps: list[np.ndarray],
        cfg: CheckConfig,
    ) -> None:
        self.obj = obj
        spec = mujoco.MjSpec.from_string(PLANE_XML)
        spec.copy_during_attach = True
        source = _gripper_source().body(C.GRIPPER_BODY)
        T_site_link = np.eye(4)
        T_site_link[:3, 3] = -np.asarray(C.GRASP_SITE_OFFSET)  # link origin in the site frame
        self.bodies = []
        self.T_pre: list[np.ndarray] = []
        for i, (T_world_O, T_O_G) in enumerate(zip(poses, grasps, strict=True)):
            self.bodies.append(f"obj{i}")
            obj.add_to_spec(spec, self.bodies[-1], T_world_O[:3, 3], mat_to_quat(T_world_O[:3, :3]))
            T = T_world_O @ T_O_G @ T_site_link
            T[:3, 3] -= cfg.pregrasp * T[:3, 0]
            self.T_pre.append(T)
            frame = spec.worldbody.add_frame()
            frame.pos, frame.quat = T[:3, 3], mat_to_quat(T[:3, :3])
            link = frame.attach_body(source, f"g{i}/", "")
            link.pos, link.quat = [0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]
            for k, axis in enumerate(np.eye(3)):
                joint = link.add_joint()
                joint.name = f"g{i}/slide{k}"
                joint.type = mujoco.mjtJoint.mjJNT_SLIDE
                joint.axis = axis
                joint.damping = [HAND_DAMPING, 0.0, 0.0]
                act = spec.add_actuator()
                act.name = f"g{i}/act_slide{k}"
                act.target = joint.name
                act.trntype = mujoco.mjtTrn.mjTRN_JOINT
                act.set_to_position(kp=HAND_KP)
                act.forcelimited = 1
                act.forcerange = [-HAND_FORCE, HAND_FORCE]
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        m = self.model
        n = len(grasps)
        self.slides = np.array(
            [m.actuator(f"g{i}/act_slide{k}").id for i in range(n) for k in range(3)]
        )
        self.fingers = [
            [m.actuator(f"g{i}/act_{j.removeprefix(C.PREFIX)}").id for j in C.FINGER_JOINTS]
            for i in range(n)
        ]
        self.obj_geoms, self.finger_geoms = [], []
        self.geom_hand = np.full(m.ngeom, -1)  # the hand each geom belongs to (-1: none)
        for i in range(n):
            self.obj_geoms.append(set(np.flatnonzero(m.geom_bodyid == m.body(f"obj{i}").id)))
            fingers = [m.body(f"g{i}/{b}").id for b in C.FINGER_BODIES]
            self.finger_geoms.append([set(np.flatnonzero(m.geom_bodyid == f)) for f in fingers])
            subtree = [b for b in range(m.nbody) if m.body(b).name.startswith(f"g{i}/")]
            self.geom_hand[np.isin(m.geom_bodyid, subtree)] = i
        self.plane = m.geom("plane").id
        # Each hand's third row of rotation: what a lift along world z is in its own axes.
        self.lift_axes = np.array([T[2, :3] for T in self.T_pre])
        for i in range(n):
            for j in C.FINGER_JOINTS:
                self.data.qpos[m.joint(f"g{i}/{j}").qposadr[0]] = C.FINGER_TRAVEL
            self.data.ctrl[self.fingers[i]] = C.FINGER_TRAVEL
        mujoco.mj_forward(m, self.data)

    def pose(self, i: int) -> np.ndarray:
        b = self.data.body(self.bodies[i])
        T = np.eye(4)
        T[:3, :3] = b.xmat.reshape(3, 3)
        T[:3, 3] = b.xpos
        return T

    def site(self, i: int) -> np.ndarray:
        """Hand i's grasp site pose (4, 4) in the world (its copy of the robot's site)."""
        site = self.data.site(f"g{i}/{C.GRASP_SITE}")
        T = np.eye(4)
        T[:3, :3] = site.xmat.reshape(3, 3)
        T[:3, 3] = site.xpos
        return T

    def lowest(self, i: int) -> float:
        T = self.pose(i)
        v = np.asarray(self.obj.mesh.vertices)
        return float((v @ T[2, :3] + T[2, 3]).min())

    def contacts(self) -> list[tuple[int, int]]:
        d = self.data
        if d.ncon == 0:
            return []
        c = d.contact
        return list(zip(c.geom1.tolist(), c.geom2.tolist(), strict=True))

    def touching(self, a: set, b: set, pairs: list[tuple[int, int]]) -> bool:
        return any((g1 in a and g2 in b) or (g1 in b and g2 in a) for g1, g2 in pairs)

    def held(self, i: int, pairs: list[tuple[int, int]]) -> bool:
        return all(self.touching(f, self.obj_geoms[i], pairs) for f in self.finger_geoms[i])

    def drive(self, along: float, lift: float) -> None:
        """Command every hand `along` [m] down its approach from the pre-grasp and `lift` [m]
        up (in each hand's own axes: R^T (0, 0, lift) is lift times R's third row)."""
        local = np.array([along, 0.0, 0.0]) + lift * self.lift_axes
        self.data.ctrl[self.slides] = local.ravel()

    def hands_on_plane(self) -> np.ndarray:
        """The hands (indices) that touch the plane now."""
        d = self.data
        if d.ncon == 0:
            return np.zeros(0, int)
        g1, g2 = d.contact.geom1, d.contact.geom2
        hands = np.concatenate(
            [self.geom_hand[g1[g2 == self.plane]], self.geom_hand[g2[g1 == self.plane]]]
        )
        return hands[hands >= 0]


def check_grasps_in_poses(
    obj: ObjectModel,
    jobs: list[tuple[np.ndarray, list[np.ndarray]]],
    config: CheckConfig | None = None,
    progress: bool = False,
) -> list[list[str]]:
    """Close the gripper on each grasp of an object resting in each of several orientations,
    and lift.

    Args:
        obj: the object (any `ObjectModel`, a mesh object being made included).
        jobs: per resting pose, (orientation of O resting on the plane, wxyz; grasp-site poses
            T_O_G (4, 4) [m] in O, approaching from above in that pose).
        config: the stages; `CheckConfig()` by default.
        progress: show a progress bar.

    A pose's grasps go in batches of `CheckConfig.batch` of their own, so its outcomes do not
    depend on the other poses; the batches of every pose share one pool of
    `CheckConfig.threads`, so that a pose whose last batch is short leaves no thread idle.

    Returns:
        One outcome per grasp, from `OUTCOMES`, per pose.
    """
    cfg = config or CheckConfig()
    batches: list[tuple[int, list[np.ndarray]]] = []
    settled: dict[tuple[int, int], list[np.ndarray]] = {}
    for k, (quat, grasps) in enumerate(jobs):
        q = np.asarray(quat, float)
        mine = [grasps[s : s + cfg.batch] for s in range(0, len(grasps), cfg.batch)]
        batches += [(k, b) for b in mine]
        # Copies placed alike settle alike: one settling per batch size serves every batch.
        for n in sorted({len(b) for b in mine}):
            settled[(k, n)] = _settled(obj, q, n, cfg)

    def check(job: tuple[int, list[np.ndarray]]) -> list[str]:
        k, batch = job
        return _run_batch(obj, settled[(k, len(batch))], batch, cfg)[0]

    hide = not progress or len(batches) < 2
    out: list[list[str]] = [[] for _ in jobs]
    pool = ThreadPoolExecutor(max_workers=cfg.threads)
    try:
        done = progress_bar(
            pool.map(check, batches), total=len(batches), desc="physics check", disable=hide
        )
        for (k, _), outcomes in zip(batches, done, strict=True):
            out[k] += outcomes
        return out
    finally:
        pool.shutdown(cancel_futures=True)  # stopped (Ctrl-C): the batches not begun are not run


#: Batches are built one at a time: their hands are copied from one spec (`_gripper_source`).
_BUILDING = threading.Lock()


def _settled(obj: ObjectModel, quat: np.ndarray, n: int, cfg: CheckConfig) -> list[np.ndarray]:
    """Poses T_world_O (4, 4) of n copies of the object placed in orientation quat on the plane
    after `settle` seconds, each copy `spacing` from the last."""
    spec = mujoco.MjSpec.from_string(PLANE_XML)
    spacing = 1.5 * obj.diameter + 0.3
    side = int(np.ceil(np.sqrt(n)))
    for i in range(n):
        xy = spacing * np.array([i % side, i // side], float)
        z = obj.resting_height(quat) + 0.001
        obj.add_to_spec(spec, f"obj{i}", np.array([xy[0], xy[1], z]), quat)
    model = spec.compile()
    model.opt.timestep = cfg.settle_timestep
    data = mujoco.MjData(model)
    mujoco.mj_step(model, data, nstep=round(cfg.settle / cfg.settle_timestep))
    poses = []
    for i in range(n):
        b = data.body(f"obj{i}")
        T = np.eye(4)
        T[:3, :3] = b.xmat.reshape(3, 3)
        T[:3, 3] = b.xpos
        poses.append(T)
    return poses


def held_in_hand(
    obj: ObjectModel, quat: np.ndarray, T_O_G: np.ndarray, config: CheckConfig | None = None
) -> tuple[str, np.ndarray]:
    """One grasp checked as `check_grasps_in_poses` checks it, on the object resting in
    orientation quat (wxyz): its outcome (`OUTCOMES`) and where the object then lies in the
    hand, T_G_O (4, 4) [m], the grasp site to the object after the hold (the planned grasp
    holds it at inv(T_O_G)): how closing, lifting and holding move it in the fingers."""
    cfg = config or CheckConfig()
    q = np.asarray(quat, float)
    outcomes, held = _run_batch(obj, _settled(obj, q, 1, cfg), [np.asarray(T_O_G, float)], cfg)
    return outcomes[0], held[0]


def _run_batch(
    obj: ObjectModel, poses: list[np.ndarray], grasps: list[np.ndarray], cfg: CheckConfig
) -> tuple[list[str], list[np.ndarray]]:
    """The outcomes of grasps on copies of the object settled at `poses` (`_settled`), and
    each copy's pose in its hand's grasp site frame after the hold, T_G_O (4, 4)."""
    n = len(grasps)
    with _BUILDING:
        b = _Batch(obj, poses, grasps, cfg)
    m, d = b.model, b.data
    m.opt.timestep = cfg.timestep
    start = [b.pose(i)[:3, 3].copy() for i in range(n)]
    outcome: list[str | None] = [None] * n
    hit = np.zeros(n, bool)

    def run(seconds: float, along, lift) -> None:
        steps = max(1, round(seconds / cfg.timestep))
        for k in range(1, steps + 1):
            s = _smooth(k / steps)
            b.drive(along(s), lift(s))
            mujoco.mj_step(m, d)
            hit[b.hands_on_plane()] = True

    pre = cfg.pregrasp
    run(0.2, lambda s: 0.0, lambda s: 0.0)
    run(pre / cfg.approach_speed, lambda s: pre * s, lambda s: 0.0)
    run(0.3, lambda s: pre, lambda s: 0.0)
    for i in range(n):
        if hit[i] or np.linalg.norm(b.pose(i)[:3, 3] - start[i]) > cfg.knock_tolerance:
            outcome[i] = "collision"
    for acts in b.fingers:
        d.ctrl[acts] = 0.0
    run(cfg.close_time, lambda s: pre, lambda s: 0.0)
    pairs = b.contacts()
    for i in range(n):
        if outcome[i] is None and not b.held(i, pairs):
            outcome[i] = "missed"
    run(cfg.lift_time, lambda s: pre, lambda s: cfg.lift * s)
    run(cfg.hold, lambda s: pre, lambda s: cfg.lift)
    pairs = b.contacts()
    for i in range(n):
        if outcome[i] is None:
            up = b.lowest(i) >= cfg.success_height
            outcome[i] = "success" if up and b.held(i, pairs) else "slipped"
    held = [np.linalg.inv(b.site(i)) @ b.pose(i) for i in range(n)]
    return [str(o) for o in outcome], held
