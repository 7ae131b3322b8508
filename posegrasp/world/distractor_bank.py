"""Visual-only distractors of the `distractors` scene shift: meshes the estimators never saw.

The meshes are pybullet's procedurally made objects (`pybullet_data/random_urdfs/NNN/NNN.obj`,
zlib licence, shipped in the ``pybullet`` wheel: ``pip install pybullet``), at the scale and in
the colour their URDF gives, and, for training only, generated shapes (`SHAPE_IDS`: boxes,
cylinders, capsules, ellipsoids, cones and bottles of household sizes, `shape_mesh`). Only
`DISTRACTOR_IDS` are used here. A distractor is a mesh geom of
one static body with no contact and no mass, so it is drawn and never touched: the scene's physics
is the same with or without it.

Frames: a bank mesh is centred on its origin in x and y with its lowest vertex at z = 0, so
standing on the table top at (x, y) it sits at (x, y, table top z); lengths in [m].
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import mujoco
import numpy as np
import trimesh
from scipy.spatial import ConvexHull

from posegrasp.core.errors import AssetError
from posegrasp.core.transforms import mat_to_quat, quat_to_mat, rot_x, rot_y, rot_z
from posegrasp.world.layout import MIN_GAP, gap, on_table
from posegrasp.world.objects import VISUAL_GROUP

#: Ids of pybullet's random URDFs that are reserved for scene-shift distractors: never used for
#: training, so every estimator sees them for the first time. Ids 0-899 are left for training.
DISTRACTOR_IDS = range(900, 1000)
#: Ids left for training (the rooms of `perception.training.data.rooms`): 0-899 but 168, whose
#: mesh file holds no triangles.
TRAINING_IDS = tuple(i for i in range(900) if i != 168)
#: Ids of generated shapes (`shape_mesh`), for training: pybullet's meshes are small blocky
#: assemblies, and the objects on a real table are mostly larger, rounder boxes and bodies of
#: revolution.
SHAPE_IDS = range(1000, 2000)
#: The banks a scene's distractors may be drawn from, by name.
BANKS: dict[str, Sequence[int]] = {
    "held-out": DISTRACTOR_IDS,
    "training": TRAINING_IDS,
    "shapes": SHAPE_IDS,
}
#: The kinds of generated shape, drawn evenly.
SHAPE_KINDS = ("box", "cylinder", "capsule", "ellipsoid", "cone", "bottle")
#: Largest extent of a generated shape [m] (min, max); its other extents are 0.25-1 of it.
SHAPE_SIZE = (0.04, 0.2)
#: Name of the static body that holds the distractors, and the prefix of their geoms and meshes.
BODY = "shift_distractors"
#: A bank mesh annotated as an object (the training images of a detector of any object) is
#: called ``bank-NNN``; its BOP object id is this plus NNN, above every other object's.
BANK_PREFIX = "bank-"
BANK_OBJ_ID_BASE = 10_000
#: Distractor centres lie this far from the target's centre [m] (min, max).
RING = (0.1, 0.36)
#: Half-width of the sector towards the robot (-x from the target) kept free of distractors, so
#: they stand around the target rather than in front of it [rad].
FRONT_SECTOR = 0.6
#: The six axis-aligned orientations a bank mesh may stand in (which of its faces is down).
_TURNS = (
    np.eye(3),
    rot_x(np.pi),
    rot_x(np.pi / 2),
    rot_x(-np.pi / 2),
    rot_y(np.pi / 2),
    rot_y(-np.pi / 2),
)


@dataclass(frozen=True)
class BankMesh:
    """One bank mesh: vertices [m] (centred in x, y; lowest at z = 0), faces, colour (RGBA)."""

    id: int
    vertices: np.ndarray
    faces: np.ndarray
    rgba: tuple[float, ...]


def bank_name(mesh_id: int) -> str:
    """The object name of bank mesh `mesh_id` where it is annotated (``bank-NNN``, or
    ``bank-NNNN`` for a generated shape)."""
    return f"{BANK_PREFIX}{mesh_id:03d}"


def bank_id(name: str) -> int | None:
    """The bank mesh id an object name (`bank_name`) stands for; None for any other name."""
    digits = name[len(BANK_PREFIX) :]
    if not name.startswith(BANK_PREFIX) or not digits.isdigit():
        return None
    mesh_id = int(digits)
    return mesh_id if bank_name(mesh_id) == name and mesh_id < SHAPE_IDS.stop else None


def shape_mesh(mesh_id: int) -> BankMesh:
    """Generated shape `mesh_id` (one of `SHAPE_IDS`), drawn from ``default_rng(mesh_id)``: its
    kind from `SHAPE_KINDS`, its largest extent from `SHAPE_SIZE`, the others 0.25-1 of it; a
    bottle is a body with a neck a third as wide; its colour is drawn too."""
    if mesh_id not in SHAPE_IDS:
        first, last = SHAPE_IDS.start, SHAPE_IDS.stop - 1
        raise AssetError(f"no generated shape {mesh_id}: their ids are {first}-{last}")
    rng = np.random.default_rng(mesh_id)
    kind = SHAPE_KINDS[int(rng.integers(len(SHAPE_KINDS)))]
    size = float(rng.uniform(*SHAPE_SIZE))
    a, b = size * rng.uniform(0.25, 1.0, 2)
    if kind == "box":
        mesh = trimesh.creation.box([size, a, b])
    elif kind == "cylinder":
        mesh = trimesh.creation.cylinder(radius=a / 2, height=size, sections=32)
    elif kind == "capsule":
        mesh = trimesh.creation.capsule(height=max(size - a, 1e-3), radius=a / 2, count=[16, 16])
    elif kind == "ellipsoid":
        mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
        mesh.apply_scale([size, a, b])
    elif kind == "cone":
        mesh = trimesh.creation.cone(radius=a / 2, height=size, sections=32)
    else:
        body = trimesh.creation.cylinder(radius=a / 2, height=0.7 * size, sections=32)
        neck = trimesh.creation.cylinder(radius=a / 6, height=0.3 * size, sections=16)
        neck.apply_translation([0.0, 0.0, 0.5 * size])
        mesh = trimesh.util.concatenate([body, neck])
    v = np.asarray(mesh.vertices, np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    v -= [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]]
    rgba = (*(float(c) for c in rng.uniform(0.1, 0.9, 3)), 1.0)
    return BankMesh(mesh_id, v, np.asarray(mesh.faces, np.int32), rgba)


def bank_dir() -> Path:
    """The folder of pybullet's random URDFs.

    Raises:
        AssetError: pybullet is not installed (one line that says how to install it).
    """
    try:
        import pybullet_data  # the wheel's data package; importing it loads no simulator
    except ImportError:
        raise AssetError(
            "the distractors scene shift needs pybullet's meshes: pip install pybullet "
            "(or make setup)"
        ) from None
    return Path(pybullet_data.getDataPath()) / "random_urdfs"


@cache
def bank_mesh(mesh_id: int) -> BankMesh:
    """Bank mesh `mesh_id` (of a bank of `BANKS`), read (or generated) once per process.

    Raises:
        AssetError: pybullet is missing, or its files are.
    """
    if mesh_id in SHAPE_IDS:
        return shape_mesh(mesh_id)
    folder = bank_dir() / f"{mesh_id:03d}"
    try:
        urdf = (folder / f"{mesh_id:03d}.urdf").read_text(encoding="utf-8")
        mesh = trimesh.load(folder / f"{mesh_id:03d}.obj", force="mesh", process=True)
    except (OSError, ValueError) as exc:
        raise AssetError(f"pybullet's random URDF {mesh_id:03d} cannot be read: {exc}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise AssetError(f"pybullet's random URDF {mesh_id:03d} holds no triangles")
    scale = re.search(r'scale="([^"]+)"', urdf)
    colour = re.search(r'rgba="([^"]+)"', urdf)
    v = np.asarray(mesh.vertices, np.float64) * (
        np.array(scale.group(1).split(), float) if scale else 1.0
    )
    lo, hi = v.min(axis=0), v.max(axis=0)
    v -= [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]]
    rgba = tuple(float(x) for x in colour.group(1).split()) if colour else (0.6, 0.6, 0.6, 1.0)
    return BankMesh(mesh_id, v, np.asarray(mesh.faces, np.int32), rgba)


def _standing(mesh: BankMesh, turn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Offset (3,) that stands the turned mesh on its lowest point, centred in x and y, and
    its footprint seen from above, centred on its origin: (N, 2) [m]."""
    v = mesh.vertices @ turn.T
    lo, hi = v.min(axis=0), v.max(axis=0)
    offset = -np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    xy = (v + offset)[:, :2]
    return offset, xy[ConvexHull(xy).vertices]


def add_distractors(
    spec: mujoco.MjSpec,
    count: int,
    footprints: list[np.ndarray],
    table_top_z: float,
    rng: np.random.Generator,
    tries: int = 60,
    ids: Sequence[int] = DISTRACTOR_IDS,
) -> int:
    """Stand up to `count` bank meshes on the table around the target, as visual-only geoms of
    one static body (added last to the worldbody, so every other body keeps its id).

    Each distractor's footprint lies on the table and at least `posegrasp.world.layout.MIN_GAP`
    from every object's footprint and every other distractor's; one that finds no such spot in
    `tries` draws is left out.

    Args:
        spec: the scene spec, before compiling.
        count: how many distractors to stand.
        footprints: the placed objects' footprints in world xy, the target first: (N, 2) each [m].
        table_top_z: height of the table top [m].
        rng: the shift's own random stream.
        tries: positions drawn per distractor.
        ids: the bank's ids to draw from (`BANKS`).

    Returns:
        How many distractors were placed.

    Raises:
        AssetError: pybullet's meshes are missing.
    """
    bank_dir()
    drawn = rng.choice(np.asarray(ids), size=count, replace=False)
    centre = footprints[0].mean(axis=0)
    body = spec.worldbody.add_body()
    body.name = BODY
    taken = list(footprints)
    for mesh_id in drawn:
        mesh = bank_mesh(int(mesh_id))
        turn = _TURNS[int(rng.integers(len(_TURNS)))]
        for _ in range(tries):
            yaw = float(rng.uniform(-np.pi, np.pi))
            offset, shape = _standing(mesh, rot_z(yaw) @ turn)
            angle = np.pi + float(rng.uniform(FRONT_SECTOR, 2 * np.pi - FRONT_SECTOR))
            xy = centre + float(rng.uniform(*RING)) * np.array([np.cos(angle), np.sin(angle)])
            F = shape + xy
            if on_table(F) and all(gap(F, G) >= MIN_GAP for G in taken):
                break
        else:
            continue
        taken.append(F)
        name = f"{BODY}/{mesh.id:03d}"
        asset = spec.add_mesh()
        asset.name = name
        asset.uservert = mesh.vertices.astype(np.float32).ravel()
        asset.userface = mesh.faces.ravel()
        asset.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL
        geom = body.add_geom()
        geom.name = name
        geom.type = mujoco.mjtGeom.mjGEOM_MESH
        geom.meshname = name
        geom.pos = [float(xy[0] + offset[0]), float(xy[1] + offset[1]), table_top_z + offset[2]]
        geom.quat = list(map(float, mat_to_quat(rot_z(yaw) @ turn)))
        geom.rgba = list(mesh.rgba)
        geom.group, geom.contype, geom.conaffinity = VISUAL_GROUP, 0, 0
        geom.density = 0.0
    return len(taken) - len(footprints)


def bank_geoms(model: mujoco.MjModel) -> list[tuple[int, int]]:
    """The distractors of a compiled scene: (geom id, bank mesh id) of each, in the order they
    were placed; none when the scene has no `BODY`."""
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, BODY)
    if body < 0:
        return []
    return [
        (int(g), int(model.geom(int(g)).name.rsplit("/", 1)[-1]))
        for g in np.flatnonzero(model.geom_bodyid == body)
    ]


def bank_pose(model: mujoco.MjModel, data: mujoco.MjData, geom: int) -> np.ndarray:
    """World pose (4, 4) [m] of a distractor's mesh in the frame of its bank file (`bank_mesh`):
    the compiler moves a mesh geom's frame to the mesh's own centre and axes
    (``mesh_pos``, ``mesh_quat``), which this undoes."""
    T_W_geom = np.eye(4)
    T_W_geom[:3, :3] = data.geom_xmat[geom].reshape(3, 3)
    T_W_geom[:3, 3] = data.geom_xpos[geom]
    mesh = int(model.geom_dataid[geom])
    T_file_geom = np.eye(4)
    T_file_geom[:3, :3] = quat_to_mat(model.mesh_quat[mesh])
    T_file_geom[:3, 3] = model.mesh_pos[mesh]
    return T_W_geom @ np.linalg.inv(T_file_geom)
