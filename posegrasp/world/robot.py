"""Fetch from the installed gymnasium-robotics package, converted at load time with MjSpec.

The shipped model drives the gripper with a mocap weld and carries the base on x/y/z slides. We
turn it into a holonomic mobile manipulator: base x, y and yaw; position actuators on the torso,
head, the seven arm joints and both fingers; gravity compensation on every robot body; no mocap
body and no weld. Assets are read from the installed package and never copied.
"""

from __future__ import annotations

import functools
import importlib.util
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from posegrasp.core.errors import AssetError
from posegrasp.world import constants as C

#: Collision bits: robot geoms collide with the world and objects, never with each other.
ROBOT_CONTYPE = 2
ROBOT_CONAFFINITY = 1
WORLD_CONTYPE = 1
WORLD_CONAFFINITY = 3


@dataclass(frozen=True)
class ActuatorGains:
    """Position-servo gains of one actuator group.

    Attributes:
        kp: stiffness [N/m] or [N m/rad].
        damping: joint damping set on the driven joints [N s/m] or [N m s/rad].
        force: symmetric force (torque) limit of the actuator [N] or [N m].
    """

    kp: float
    damping: float
    force: float


@dataclass(frozen=True)
class RobotConfig:
    """How the shipped Fetch is converted."""

    base_xy: ActuatorGains = ActuatorGains(kp=2.0e4, damping=4.0e3, force=2000.0)
    base_yaw: ActuatorGains = ActuatorGains(kp=4.0e3, damping=6.0e2, force=800.0)
    torso: ActuatorGains = ActuatorGains(kp=2.0e4, damping=3.0e3, force=2000.0)
    head: ActuatorGains = ActuatorGains(kp=300.0, damping=20.0, force=60.0)
    arm: ActuatorGains = ActuatorGains(kp=1500.0, damping=60.0, force=300.0)
    finger: ActuatorGains = ActuatorGains(kp=800.0, damping=40.0, force=40.0)
    #: Finger mass [kg]; the shipped 4 kg per finger is far from the real gripper.
    finger_mass: float = 0.1
    finger_armature: float = 0.1


def fetch_asset_dir() -> Path:
    """Folder of the Fetch MJCF inside the installed gymnasium-robotics package.

    Raises:
        AssetError: when gymnasium-robotics is not installed.
    """
    spec = importlib.util.find_spec("gymnasium_robotics")
    if spec is None or not spec.submodule_search_locations:
        raise AssetError("gymnasium-robotics is not installed; run `make setup` (pip install -e .)")
    root = Path(next(iter(spec.submodule_search_locations))) / "envs" / "assets"
    if not (root / "fetch" / "robot.xml").is_file():
        raise AssetError(f"Fetch model not found under {root}; reinstall gymnasium-robotics")
    return root


@functools.cache
def _shipped_fetch_xml(world: str | None) -> str:
    root = fetch_asset_dir()
    world_include = f'<include file="{world}"/>' if world else ""
    return (
        "<mujoco>"
        f"{world_include}"
        f'<compiler angle="radian" meshdir="{root / "stls" / "fetch"}" '
        f'texturedir="{root / "textures"}"/>'
        f'<include file="{root / "fetch" / "shared.xml"}"/>'
        f'<worldbody><include file="{root / "fetch" / "robot.xml"}"/></worldbody>'
        "</mujoco>"
    )


def _add_position_actuator(
    spec: mujoco.MjSpec,
    joint: mujoco.MjsJoint,
    gains: ActuatorGains,
    ctrlrange: tuple[float, float],
) -> None:
    joint.damping = [gains.damping, 0.0, 0.0]
    act = spec.add_actuator()
    act.name = "act_" + joint.name.removeprefix(C.PREFIX)
    act.target = joint.name
    act.trntype = mujoco.mjtTrn.mjTRN_JOINT
    act.set_to_position(kp=gains.kp)
    act.ctrllimited = 1
    act.ctrlrange = list(ctrlrange)
    act.forcelimited = 1
    act.forcerange = [-gains.force, gains.force]


def fetch_spec(config: RobotConfig | None = None, world: Path | None = None) -> mujoco.MjSpec:
    """The converted Fetch as an MjSpec, alone or inside a world.

    Args:
        config: gains and masses; defaults to `RobotConfig()`.
        world: an MJCF file whose elements (options, assets, worldbody ...) are included before
            the robot; None for the robot alone.

    Returns:
        A fresh spec (callers may modify it freely): a copy of one built once per (config,
        world) in this process, which costs a twentieth of building it.
    """
    return _fetch_template(config or RobotConfig(), str(world) if world else None).copy()


@functools.cache
def _fetch_template(cfg: RobotConfig, world: str | None) -> mujoco.MjSpec:
    """The spec `fetch_spec` copies; never modified."""
    spec = mujoco.MjSpec.from_string(_shipped_fetch_xml(world))
    _remove_gym_task_parts(spec)
    _make_base_holonomic(spec)
    _fix_cameras(spec)
    _add_grasp_site(spec)
    _lighten_fingers(spec, cfg)
    _set_gravcomp_and_contacts(spec)
    _add_actuators(spec, cfg)
    return spec


def _remove_gym_task_parts(spec: mujoco.MjSpec) -> None:
    """Delete what the shipped file carries for the gym task: the mocap weld and body, the
    skybox, the block texture and the scene materials."""
    for eq in list(spec.equalities):
        spec.delete(eq)
    spec.delete(spec.body(C.PREFIX + "mocap"))
    for name in ("floor_mat", "table_mat", "block_mat", "puck_mat"):
        if (mat := spec.material(name)) is not None:
            spec.delete(mat)
    for tex in list(spec.textures):
        if tex.name in ("", "texture_block"):
            spec.delete(tex)


def _make_base_holonomic(spec: mujoco.MjSpec) -> None:
    """Replace the base's x/y/z slides by x, y slides and a yaw hinge (`C.BASE_JOINTS`,
    armature 1), the base at the origin of its parent."""
    base = spec.body(C.BASE_BODY)
    for j in list(base.joints):
        spec.delete(j)
    for name, axis, jtype in (
        ("base_x", (1, 0, 0), mujoco.mjtJoint.mjJNT_SLIDE),
        ("base_y", (0, 1, 0), mujoco.mjtJoint.mjJNT_SLIDE),
        ("base_yaw", (0, 0, 1), mujoco.mjtJoint.mjJNT_HINGE),
    ):
        j = base.add_joint()
        j.name, j.type, j.axis, j.armature = name, jtype, list(axis), 1.0
    base.pos = [0.0, 0.0, 0.0]


def _fix_cameras(spec: mujoco.MjSpec) -> None:
    """Turn the head camera by exactly pi (the shipped file has 3.1415) and delete the gym
    env's external camera, which is not ours."""
    cam = spec.camera(C.HEAD_CAMERA)
    cam.alt.euler = [np.pi, 0.0, 0.0]
    spec.delete(spec.camera("external_camera_0"))


def _add_grasp_site(spec: mujoco.MjSpec) -> None:
    """Add the grasp site between the finger pads (`C.GRASP_SITE`, at `C.GRASP_SITE_OFFSET`
    [m] in the gripper body; invisible, group 4)."""
    grip = spec.body(C.GRIPPER_BODY)
    site = grip.add_site()
    site.name = C.GRASP_SITE
    site.pos = list(C.GRASP_SITE_OFFSET)
    site.size = [0.005, 0.005, 0.005]
    site.rgba = [1, 0, 0, 0]
    site.group = 4


def _lighten_fingers(spec: mujoco.MjSpec, cfg: RobotConfig) -> None:
    """Saner fingers: light (`RobotConfig.finger_mass` [kg]), with little armature, so the
    gripper closes in a fraction of a second."""
    for name in C.FINGER_BODIES:
        finger = spec.body(name)
        finger.mass = cfg.finger_mass
        finger.inertia = [1e-4, 1e-4, 1e-4]
        finger.first_joint().armature = cfg.finger_armature


def _set_gravcomp_and_contacts(spec: mujoco.MjSpec) -> None:
    """Gravity compensation and the robot's collision bits on every robot body; the base and
    the links fixed on it never touch anything (the base slides holonomically above the
    floor)."""
    robot_bodies = [b for b in spec.bodies if b.name.startswith(C.PREFIX)]
    for body in robot_bodies:
        body.gravcomp = 1.0
        for g in body.geoms:
            g.contype, g.conaffinity = ROBOT_CONTYPE, ROBOT_CONAFFINITY
    for g in spec.body(C.BASE_BODY).geoms:
        g.contype, g.conaffinity = 0, 0
    for child in ("estop_link", "laser_link", "torso_fixed_link"):
        for g in spec.body(C.PREFIX + child).geoms:
            g.contype, g.conaffinity = 0, 0


def _add_actuators(spec: mujoco.MjSpec, cfg: RobotConfig) -> None:
    """Position servos on the base (x, y within 5 m, yaw within pi), torso, head, arm and
    fingers (within their joint ranges), with `cfg`'s gains; the continuous arm rolls are
    limited to one turn, and the forearm roll's spring is removed (the servo holds it)."""
    for name in C.BASE_JOINTS[:2]:
        _add_position_actuator(spec, spec.joint(name), cfg.base_xy, (-5.0, 5.0))
    _add_position_actuator(spec, spec.joint("base_yaw"), cfg.base_yaw, (-np.pi, np.pi))
    groups = (
        ((C.TORSO_JOINT,), cfg.torso),
        (C.HEAD_JOINTS, cfg.head),
        (C.ARM_JOINTS, cfg.arm),
        (C.FINGER_JOINTS, cfg.finger),
    )
    for names, gains in groups:
        for name in names:
            joint = spec.joint(name)
            if name in (C.ARM_JOINTS[2], C.ARM_JOINTS[4], C.ARM_JOINTS[6]):
                # Continuous rolls: limit joint and servo to one turn so planning and control agree.
                joint.limited = 1
                joint.range = [-np.pi, np.pi]
            lo, hi = joint.range
            _add_position_actuator(spec, joint, gains, (float(lo), float(hi)))
    # Shipped forearm roll has a spring; the servo holds it instead.
    spec.joint(C.ARM_JOINTS[4]).stiffness = [0.0, 0.0, 0.0]


def home_qpos_ctrl(model: mujoco.MjModel) -> tuple[dict[int, float], np.ndarray]:
    """qpos addresses and the control vector of `constants.HOME_POSTURE`.

    Returns:
        (qpos address -> value for each actuated joint, ctrl vector of length model.nu).
    """
    qpos: dict[int, float] = {}
    ctrl = np.zeros(model.nu)
    for joint, actuator in zip(C.ACTUATED_JOINTS, C.ACTUATORS, strict=True):
        value = C.HOME_POSTURE[joint]
        qpos[int(model.joint(joint).qposadr[0])] = value
        ctrl[model.actuator(actuator).id] = value
    return qpos, ctrl
