"""Scene assembly from a seed: the world of `scenes/world.xml`, the converted Fetch, the objects.

`build_scene(["phone"], seed=0)` puts the target object (the first name) and any distractors on
the table at random positions and yaws within the arm's reach, places the robot's base at a random
pose facing the table, aims the head camera at the target and lets physics settle.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import mujoco
import numpy as np

from posegrasp.core.errors import InvalidArgumentError, UnknownNameError
from posegrasp.core.paths import SCENES_DIR
from posegrasp.core.transforms import quat_mul, yaw_quat
from posegrasp.world import constants as C
from posegrasp.world.distractor_bank import BANKS
from posegrasp.world.layout import footprint, sample_layout
from posegrasp.world.objects import (
    OBJECT_NAMES,
    ObjectModel,
    check_object,
    load_object,
    object_names,
)
from posegrasp.world.occlusion import occlusion
from posegrasp.world.robot import RobotConfig, fetch_spec, home_qpos_ctrl
from posegrasp.world.shifts import Shift, apply_shifts, canonical, shift_spec

WORLD_XML = SCENES_DIR / "world.xml"
#: Layouts drawn at most for a scene whose occlusion is bounded. The draws are the seed's, in
#: order, so a scene found in fewer draws is the same whatever this limit; a flat phone behind
#: small neighbours can take a few dozen (train seed 6441 of the hard tier: 38).
OCCLUSION_ATTEMPTS = 200


@dataclass(frozen=True)
class SceneConfig:
    """How scenes are sampled. Lengths in [m], angles in [rad], world frame.

    Attributes:
        n_distractors: extra objects of other classes on the table.
        base_x, base_y, base_yaw: ranges of the robot base pose.
        target_x, target_y: region of the table where the target object is placed.
        distractor_x, distractor_y: region for distractors.
        aim_jitter: half-range of a random offset of the head's aim point around the target.
        settle_time: physics time run after placing everything [s].
        resting_pose: "canonical" puts every object in its first (canonical) resting pose;
            "random" draws each object's pose uniformly among its resting poses; "graspable"
            does the same but draws the target's among the poses the gripper can take it in
            (`ObjectModel.ungraspable` excluded).
        randomize_appearance: randomise lights and surface colours (for data generation).
        distractor_count: when set, the number of distractors is drawn uniformly from this
            inclusive range instead of `n_distractors`.
        near_distractors: how many distractors stand next to the target, their footprints
            `near_gap` apart from its footprint (edge to edge) [m].
        camera_distance: when set, the base is placed so that the head camera is this far from
            the target (drawn uniformly from the range) [m], facing it; `base_x`, `base_y` and
            `base_yaw` then jitter that pose.
        occluders: how many of the near distractors stand on the robot's side of the target,
            between it and the head camera.
        occlusion: when set, the accepted range of the share of the target's silhouette that
            the other objects hide from the head camera (`posegrasp.world.occlusion`); layouts are
            drawn again (from the same seed's stream) until one falls in it.
        distractor_pool: the classes distractors are drawn from (built-in or user objects);
            empty for the built-in ones (`OBJECT_NAMES`). The target's own classes are left out.
        shifts: purely visual scene shifts (`posegrasp.world.shifts.parse_shifts`), drawn from
            their own streams of the seed: the layout and the physics are the same with or
            without them, only the images change.
        distractor_bank: the bank the `distractors` shift draws its meshes from
            (`posegrasp.world.distractor_bank.BANKS`): ``held-out`` for scoring, ``training``
            for the training data's rooms.
    """

    n_distractors: int = 0
    base_x: tuple[float, float] = (-0.02, 0.06)
    base_y: tuple[float, float] = (-0.08, 0.08)
    base_yaw: tuple[float, float] = (-0.15, 0.15)
    target_x: tuple[float, float] = (0.55, 0.68)
    target_y: tuple[float, float] = (-0.2, 0.2)
    distractor_x: tuple[float, float] = (0.5, 0.95)
    distractor_y: tuple[float, float] = (-0.4, 0.4)
    aim_jitter: float = 0.05
    settle_time: float = 0.5
    resting_pose: str = "canonical"
    randomize_appearance: bool = False
    distractor_count: tuple[int, int] | None = None
    near_distractors: int = 0
    near_gap: tuple[float, float] = (0.03, 0.08)
    camera_distance: tuple[float, float] | None = None
    occluders: int = 0
    occlusion: tuple[float, float] | None = None
    distractor_pool: tuple[str, ...] = ()
    robot: RobotConfig = field(default_factory=RobotConfig)
    shifts: tuple[Shift, ...] = ()
    distractor_bank: str = "held-out"

    def __post_init__(self) -> None:
        if self.distractor_bank not in BANKS:
            raise UnknownNameError("distractor bank", self.distractor_bank, BANKS)


@dataclass
class PlacedObject:
    """An object instance in a scene: its class, body name, model and the resting pose it was
    placed in."""

    name: str
    body: str
    model: ObjectModel
    resting: str = ""


@dataclass
class Scene:
    """A compiled scene with its state.

    Attributes:
        model, data: the MuJoCo model and state.
        seed: the seed it was built from.
        objects: placed objects, the target first.
        table_top_z: height of the table's top surface [m].
        ctrl_home: the control vector that holds the robot's posture.
        occlusion: share of the target's silhouette the other objects hide from the head
            camera, when the scene's config bounds it.
    """

    model: mujoco.MjModel
    data: mujoco.MjData
    seed: int
    objects: list[PlacedObject]
    table_top_z: float
    ctrl_home: np.ndarray
    occlusion: float | None = None

    @property
    def target(self) -> PlacedObject:
        """The object the episode is about."""
        return self.objects[0]

    def object_pose(self, body: str | None = None) -> np.ndarray:
        """T_world_O of an object body (the target by default), shape (4, 4)."""
        b = self.data.body(body or self.target.body)
        T = np.eye(4)
        T[:3, :3] = b.xmat.reshape(3, 3)
        T[:3, 3] = b.xpos
        return T

    def object_lowest_z(self, body: str | None = None) -> float:
        """World height of the lowest mesh vertex of an object [m]."""
        placed = next(o for o in self.objects if o.body == (body or self.target.body))
        T = self.object_pose(placed.body)
        v = np.asarray(placed.model.mesh.vertices) @ T[:3, :3].T + T[:3, 3]
        return float(v[:, 2].min())

    def step(self, seconds: float) -> None:
        """Advance physics by seconds with the current controls."""
        n = round(seconds / self.model.opt.timestep)
        mujoco.mj_step(self.model, self.data, nstep=n) if n else None


def _footprint_radius(obj: ObjectModel) -> float:
    return float(np.hypot(*obj.extents[:2]) / 2)


def _sample_positions(
    objs: list[ObjectModel], cfg: SceneConfig, rng: np.random.Generator
) -> list[np.ndarray]:
    # Greedy placement; when an object finds no free spot, start the whole layout again (the
    # first attempt draws exactly what a single pass would, so seeds that fit keep their scene).
    for _attempt in range(50):
        placed: list[tuple[np.ndarray, float]] = []
        for i, obj in enumerate(objs):
            xr, yr = (
                (cfg.target_x, cfg.target_y) if i == 0 else (cfg.distractor_x, cfg.distractor_y)
            )
            r = _footprint_radius(obj)
            for _ in range(200):
                xy = np.array([rng.uniform(*xr), rng.uniform(*yr)])
                if all(np.linalg.norm(xy - q) > r + rq + 0.02 for q, rq in placed):
                    placed.append((xy, r))
                    break
            else:
                break
        else:
            return [p for p, _ in placed]
    raise InvalidArgumentError(
        f"cannot place {len(objs)} objects on the table without overlap; "
        "use fewer or smaller distractors (the most crowded layouts do not always fit)"
    )


RESTING_MODES = ("canonical", "random", "graspable")


def _resting(
    obj: ObjectModel, cfg: SceneConfig, rng: np.random.Generator, target: bool
) -> tuple[str, np.ndarray]:
    """The resting pose (name, wxyz orientation) an object is placed in."""
    names = list(obj.resting_poses)
    if cfg.resting_pose == "graspable" and target:
        names = [n for n in names if n not in obj.ungraspable]
    if cfg.resting_pose != "canonical":
        name = names[rng.integers(len(names))]
        return name, obj.resting_poses[name]
    return names[0], obj.resting_poses[names[0]]


def _near_layout(
    objs: list[ObjectModel], cfg: SceneConfig, rng: np.random.Generator
) -> list[tuple[np.ndarray, tuple[str, np.ndarray], float]]:
    """(xy, resting orientation, yaw) per object with `cfg.near_distractors` neighbours beside
    the target (`posegrasp.world.layout`)."""
    rests = [_resting(o, cfg, rng, i == 0) for i, o in enumerate(objs)]
    near = min(cfg.near_distractors, len(objs) - 1)
    quats = [q for _, q in rests]
    layout = sample_layout(
        objs, quats, near, cfg.near_gap, (cfg.target_x, cfg.target_y), rng, occluders=cfg.occluders
    )
    if layout is None:
        raise InvalidArgumentError(
            f"cannot place {len(objs)} objects with {near} beside the target; use fewer distractors"
        )
    return [(xy, rest, yaw) for (xy, yaw), rest in zip(layout, rests, strict=True)]


def _set_base(
    model: mujoco.MjModel, data: mujoco.MjData, ctrl: np.ndarray, base: tuple[float, ...]
) -> None:
    """Put the base at (x, y, yaw) and hold it there; runs kinematics."""
    for name, v in zip(C.BASE_JOINTS, base, strict=True):
        data.qpos[model.joint(name).qposadr[0]] = v
        ctrl[model.actuator("act_" + name).id] = v
    mujoco.mj_kinematics(model, data)


def _stand_back(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    ctrl: np.ndarray,
    aim: np.ndarray,
    distance: float,
    jitter: tuple[float, ...],
) -> None:
    """Move the base back from `aim` along -x until the head camera, aimed at it, is
    `distance` [m] away; `jitter` = (x, y, yaw) of the sampled base pose, whose y and yaw are
    kept as offsets (the base then faces the aim point up to that yaw)."""
    cam = model.camera(C.HEAD_CAMERA).id
    x = float(aim[0]) - distance
    for _ in range(4):
        dy = float(aim[1]) - jitter[1]
        yaw = float(np.arctan2(dy, float(aim[0]) - x)) + jitter[2]
        _set_base(model, data, ctrl, (x, jitter[1], yaw))
        aim_head(model, data, aim)
        mujoco.mj_camlight(model, data)
        now = float(np.linalg.norm(data.cam_xpos[cam] - aim))
        x -= (distance - now) * distance / max(np.hypot(aim[0] - x, dy), 1e-6)


def aim_head(model: mujoco.MjModel, data: mujoco.MjData, point: np.ndarray) -> tuple[float, float]:
    """Head pan and tilt that put a world point on the head camera's optical axis.

    Sets the head joints in data.qpos (and runs kinematics); returns (pan, tilt) [rad], clipped
    to the joint ranges.
    """
    pan_j, tilt_j = (model.joint(n) for n in C.HEAD_JOINTS)
    cam = model.camera(C.HEAD_CAMERA).id
    for _ in range(6):
        mujoco.mj_kinematics(model, data)
        mujoco.mj_camlight(model, data)
        # Camera frame, MuJoCo convention: optical axis is -z.
        R = data.cam_xmat[cam].reshape(3, 3)
        d = R.T @ (point - data.cam_xpos[cam])
        # Pan turns about world z (the head is level); tilt pitches the camera down.
        pan_err = np.arctan2(-d[0], -d[2])
        tilt_err = np.arctan2(-d[1], np.hypot(d[0], d[2]))
        data.qpos[pan_j.qposadr[0]] += pan_err
        data.qpos[tilt_j.qposadr[0]] += tilt_err
        for j in (pan_j, tilt_j):
            data.qpos[j.qposadr[0]] = np.clip(data.qpos[j.qposadr[0]], *j.range)
    mujoco.mj_kinematics(model, data)
    return float(data.qpos[pan_j.qposadr[0]]), float(data.qpos[tilt_j.qposadr[0]])


def randomize_appearance(model: mujoco.MjModel, rng: np.random.Generator) -> None:
    """Randomise lights and the colours of the room's surfaces in place (domain randomisation)."""
    for i in range(model.nlight):
        model.light_diffuse[i] = rng.uniform(0.2, 0.8) * np.ones(3) + rng.uniform(-0.05, 0.05, 3)
        model.light_pos[i] += rng.uniform(-0.5, 0.5, 3)
    for i in range(model.nmat):
        if model.material(i).name.startswith("room_"):
            model.mat_rgba[i, :3] = rng.uniform(0.3, 1.0, 3)
    model.vis.headlight.ambient[:] = rng.uniform(0.1, 0.4)


def build_scene(
    objects: str | Sequence[str],
    seed: int,
    config: SceneConfig | None = None,
    distractors: Sequence[str] | None = None,
) -> Scene:
    """Build and settle a seeded scene.

    Args:
        objects: the target object's class, or several classes (the first is the target);
            built-in or user objects (`posegrasp.world.objects.object_names()`).
        seed: seed of every random choice; the same seed gives the same scene.
        config: sampling ranges; `SceneConfig()` by default.
        distractors: explicit distractor classes; None draws `config.n_distractors` classes
            from `config.distractor_pool` (the built-in ones when empty) other than the
            requested ones.

    Returns:
        The settled scene, robot holding its home posture with the head aimed at the target.

    Raises:
        UnknownNameError: an unknown object class.
        InvalidArgumentError: the objects do not fit on the table; shifts that are not `Shift`
            values or name a factor twice.
        AssetError: the `distractors` shift without pybullet installed.
    """
    cfg = config or SceneConfig()
    shifts = canonical(cfg.shifts)
    if cfg.resting_pose not in RESTING_MODES:
        raise UnknownNameError("resting pose mode", cfg.resting_pose, RESTING_MODES)
    names = [objects] if isinstance(objects, str) else list(objects)
    if not names:
        raise InvalidArgumentError(f"no object given; valid objects: {', '.join(object_names())}")
    for n in [*names, *(distractors or []), *cfg.distractor_pool]:
        check_object(n)
    rng = np.random.default_rng(seed)
    if distractors is None:
        pool = [n for n in (cfg.distractor_pool or OBJECT_NAMES) if n not in names]
        want = cfg.n_distractors
        if cfg.distractor_count is not None:
            want = int(rng.integers(cfg.distractor_count[0], cfg.distractor_count[1] + 1))
        k = min(want, len(pool))
        distractors = [pool[i] for i in rng.permutation(len(pool))[:k]]
    names = [*names, *distractors]
    models = [load_object(n) for n in names]
    if cfg.occlusion is None:
        return _assemble(models, cfg, rng, seed, shifts)
    lo, hi = cfg.occlusion
    for _attempt in range(OCCLUSION_ATTEMPTS):
        # The occlusion is measured without the shifts (visual distractors, a moved camera), so
        # they never change which layout is taken; the one taken is then built again with them
        # from the same draws (not shifted in place: the occlusion's render context, reused for
        # the same model, would keep its unshifted textures).
        state = rng.bit_generator.state
        scene = _assemble(models, cfg, rng, seed)
        hidden = occlusion(
            scene.model, scene.data, scene.target.body, [o.body for o in scene.objects[1:]]
        )
        if lo <= hidden <= hi:
            if shifts:
                rng.bit_generator.state = state
                scene = _assemble(models, cfg, rng, seed, shifts)
            scene.occlusion = hidden
            return scene
    raise InvalidArgumentError(
        f"no layout of seed {seed} hides {lo:.0%}-{hi:.0%} of the {names[0]} in "
        f"{OCCLUSION_ATTEMPTS} draws; widen the occlusion range"
    )


def _assemble(
    models: list[ObjectModel],
    cfg: SceneConfig,
    rng: np.random.Generator,
    seed: int,
    shifts: tuple[Shift, ...] = (),
) -> Scene:
    """Lay out the objects, compile the scene, place the robot and let physics settle; then
    apply the visual `shifts` (`posegrasp.world.shifts`), which change no physics."""
    spec = fetch_spec(cfg.robot, world=WORLD_XML)
    table_top = spec.geom("table_top")
    table_top_z = float(spec.body("table").pos[2] + table_top.pos[2] + table_top.size[2])

    if cfg.near_distractors > 0:
        poses = _near_layout(models, cfg, rng)
    else:  # the original sampling order: positions first, then resting pose and yaw per object
        positions = _sample_positions(models, cfg, rng)
        poses = []
        for i, (obj, xy) in enumerate(zip(models, positions, strict=True)):
            resting = _resting(obj, cfg, rng, i == 0)
            poses.append((xy, resting, float(rng.uniform(-np.pi, np.pi))))
    placed: list[PlacedObject] = []
    counts: dict[str, int] = {}
    footprints: list[np.ndarray] = []
    for obj, (xy, (rest_name, rest), yaw) in zip(models, poses, strict=True):
        k = counts.get(obj.name, 0)
        counts[obj.name] = k + 1
        body = f"{obj.name}_{k}"
        quat = quat_mul(yaw_quat(yaw), rest)
        z = table_top_z + obj.resting_height(rest) + 0.001
        obj.add_to_spec(spec, body, np.array([xy[0], xy[1], z]), quat)
        placed.append(PlacedObject(obj.name, body, obj, rest_name))
        if shifts:
            footprints.append(footprint(obj, rest, yaw) + xy)
    if shifts:
        shift_spec(spec, shifts, seed, footprints, table_top_z, BANKS[cfg.distractor_bank])

    model = spec.compile()
    if cfg.randomize_appearance:
        randomize_appearance(model, rng)
    data = mujoco.MjData(model)
    qpos, ctrl = home_qpos_ctrl(model)
    for adr, v in qpos.items():
        data.qpos[adr] = v
    base = (rng.uniform(*cfg.base_x), rng.uniform(*cfg.base_y), rng.uniform(*cfg.base_yaw))
    _set_base(model, data, ctrl, base)
    aim = data.body(placed[0].body).xpos + rng.uniform(-cfg.aim_jitter, cfg.aim_jitter, 3)
    if cfg.camera_distance is not None:
        _stand_back(model, data, ctrl, aim, float(rng.uniform(*cfg.camera_distance)), base)
    pan, tilt = aim_head(model, data, aim)
    ctrl[model.actuator("act_head_pan_joint").id] = pan
    ctrl[model.actuator("act_head_tilt_joint").id] = tilt
    data.ctrl[:] = ctrl
    mujoco.mj_forward(model, data)
    scene = Scene(model, data, seed, placed, table_top_z, ctrl.copy())
    scene.step(cfg.settle_time)
    mujoco.mj_forward(model, data)
    if shifts:
        apply_shifts(model, data, shifts, seed, placed[0].body)
    return scene
