"""The known objects: the six built-in ones, whose JSON definitions (`scenes/objects/`) drive both
the MuJoCo bodies and a trimesh mesh in the object's own frame, and the user objects made from
meshes (`posegrasp.world.user_objects`, ``python -m sim.add_object``).

The object frame O has its origin at the centre of the object's 3D bounding box, z up in its
canonical resting pose and x along its length (docs/DESIGN.md §4). Definitions may be written in any
frame with z up; loading shifts every part so that the bounding-box centre is the origin. A user
object's meshes are stored in O already.

`OBJECT_NAMES` are the built-in objects (the classes the learned estimators know); `object_names()`
adds the user objects found, and `check_object` and `load_object` take either kind.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass, field
from typing import Any, cast

import mujoco
import numpy as np
import trimesh

from posegrasp.core.errors import AssetError, UnknownNameError
from posegrasp.core.paths import SCENES_DIR
from posegrasp.core.transforms import quat_to_mat
from posegrasp.core.validate import check_names
from posegrasp.world.meshes import Texture, points_diameter
from posegrasp.world.robot import WORLD_CONAFFINITY, WORLD_CONTYPE
from posegrasp.world.user_objects import (
    MeshGeometry,
    StoredGrasp,
    description_revision,
    read_user_object,
    user_object_names,
)
from posegrasp.world.user_objects import objects_dir as user_objects_dir

#: The built-in objects, in their fixed order (class ids of the learned estimators and of BOP).
OBJECT_NAMES: tuple[str, ...] = ("car", "faucet", "chair", "phone", "screen", "pistol")
OBJECTS_DIR = SCENES_DIR / "objects"

#: Geom groups (MuJoCo Menagerie convention): visual 2, collision 3.
VISUAL_GROUP = 2
COLLISION_GROUP = 3


def object_names() -> tuple[str, ...]:
    """Every known object: the built-in ones (`OBJECT_NAMES`, in their order), then the user
    objects found in the user objects directory (`posegrasp.world.user_objects`), sorted. A user
    folder named like a built-in object is left out: a built-in name always means the built-in."""
    return OBJECT_NAMES + tuple(n for n in user_object_names() if n not in OBJECT_NAMES)


def check_object(name: str) -> str:
    """`name` when it is a known object class, built-in or user object.

    Raises:
        UnknownNameError: otherwise, listing the classes (`object_names()`).
    """
    if name in OBJECT_NAMES:
        return name
    names = object_names()
    if name not in names:
        raise UnknownNameError("object", str(name), names)
    return name


def check_objects(spec: str, option: str = "--objects") -> list[str]:
    """A list of objects from the command line: 'all' for the built-in ones (`OBJECT_NAMES`; a
    run's episodes never change with the user objects installed), or a comma list of distinct
    known objects, built-in or user objects, mixed.

    Raises:
        InvalidArgumentError, UnknownNameError: otherwise, in one line listing the objects.
    """
    if spec == "all":
        return list(OBJECT_NAMES)
    return check_names(spec, object_names(), "object", option)


@dataclass(frozen=True)
class Part:
    """One primitive of an object, in the object frame O.

    Attributes:
        name: part name, unique within its object.
        type: "box", "cylinder" or "sphere".
        pos: centre in O [m], shape (3,).
        quat: orientation in O, wxyz, shape (4,).
        size: box half-extents (3,), cylinder (radius, half-length) or sphere (radius,) [m].
        rgba: colour, shape (4,).
        collision: whether the part also gets a collision geom.
    """

    name: str
    type: str
    pos: np.ndarray
    quat: np.ndarray
    size: np.ndarray
    rgba: np.ndarray
    collision: bool = True

    @property
    def volume(self) -> float:
        """Volume [m^3]."""
        if self.type == "box":
            return float(8 * np.prod(self.size))
        if self.type == "cylinder":
            return float(np.pi * self.size[0] ** 2 * 2 * self.size[1])
        return float(4 / 3 * np.pi * self.size[0] ** 3)

    def transform(self) -> np.ndarray:
        """T_O_part, shape (4, 4)."""
        T = np.eye(4)
        T[:3, :3] = quat_to_mat(self.quat)
        T[:3, 3] = self.pos
        return T

    def mesh(self) -> trimesh.Trimesh:
        """The part as a triangle mesh in O."""
        if self.type == "box":
            m = trimesh.creation.box(extents=2 * self.size)
        elif self.type == "cylinder":
            m = trimesh.creation.cylinder(radius=self.size[0], height=2 * self.size[1], sections=32)
        else:
            m = trimesh.creation.icosphere(subdivisions=2, radius=self.size[0])
        m.apply_transform(self.transform())
        return m


def _parse_part(raw: dict[str, Any], obj: str) -> Part:
    kind = raw.get("type")
    name = raw.get("name", "?")
    where = f"object {obj!r} part {name!r}"
    quat = np.array(raw.get("quat", [1.0, 0.0, 0.0, 0.0]), dtype=float)
    if kind == "box":
        pos, size = np.array(raw["pos"], float), np.array(raw["size"], float)
    elif kind == "cylinder":
        a, b = np.split(np.array(raw["fromto"], float), 2)
        axis = b - a
        length = float(np.linalg.norm(axis))
        if length <= 0:
            raise AssetError(f"{where}: zero-length cylinder")
        pos, size = (a + b) / 2, np.array([raw["radius"], length / 2], float)
        quat = np.zeros(4)
        mujoco.mju_quatZ2Vec(quat, axis / length)
    elif kind == "sphere":
        pos, size = np.array(raw["pos"], float), np.array([raw["radius"]], float)
    else:
        raise AssetError(f"{where}: unknown type {kind!r}; valid types: box, cylinder, sphere")
    return Part(
        name=name,
        type=kind,
        pos=pos,
        quat=quat / np.linalg.norm(quat),
        size=size,
        rgba=np.array(raw.get("rgba", [0.5, 0.5, 0.5, 1.0]), float),
        collision=bool(raw.get("collision", True)),
    )


@dataclass(frozen=True)
class ObjectModel:
    """A known object: its shape in its own frame, physical properties, symmetries, resting poses.

    A built-in object is made of primitive `parts`; a user object (`geometry` set, `parts`
    empty) of a visual mesh and convex collision hulls with an explicit mass distribution, and
    carries its grasp candidates (`grasps`).

    Attributes:
        name: class name, one of `object_names()`.
        description: what it looks like, and which features make its pose observable.
        parts: primitives in O (origin at the bounding-box centre); empty for a user object.
        mass: total mass [kg].
        friction: MuJoCo friction (sliding, torsional, rolling).
        symmetries: proper rotational symmetries besides the identity, each a 4x4 T_O_O'
            (appearance included; every built-in object is designed to have none; a continuous
            symmetry of a user object is discretised, `user_objects.symmetry_transforms`).
        resting_poses: name -> orientation of O on a horizontal support, wxyz; the first is
            the canonical pose, the others were found by physics (`posegrasp.world.resting`).
        ungraspable: resting poses in which the Fetch gripper cannot take the object from above
            (no grasp candidate fits; `grasping.candidates` is tested against this list).
        geometry: a user object's meshes and mass distribution; None for a built-in object.
        grasps: a user object's grasp candidates, every resting pose's; () for a built-in one.
        revision: a user object's description hash (caches of it are keyed by it); "" for a
            built-in object.
    """

    name: str
    description: str
    parts: tuple[Part, ...]
    mass: float
    friction: tuple[float, float, float]
    symmetries: tuple[np.ndarray, ...] = ()
    resting_poses: dict[str, np.ndarray] = field(default_factory=dict)
    ungraspable: tuple[str, ...] = ()
    geometry: MeshGeometry | None = None
    grasps: tuple[StoredGrasp, ...] = ()
    revision: str = ""

    @functools.cached_property
    def mesh(self) -> trimesh.Trimesh:
        """The object as a triangle mesh in O [m]: a built-in object's parts concatenated (not
        fused), a user object's visual mesh."""
        if self.geometry is not None:
            return self.geometry.visual
        return cast(trimesh.Trimesh, trimesh.util.concatenate([p.mesh() for p in self.parts]))

    def convex_pieces(self) -> list[tuple[trimesh.Trimesh, np.ndarray]]:
        """The object as convex pieces in O [m], each with its RGBA (4,): a built-in object's
        primitive parts, a user object's collision hulls in the object's colour."""
        if self.geometry is not None:
            rgba = np.asarray(self.geometry.rgba, float)
            return [(h, rgba) for h in self.geometry.hulls]
        return [(p.mesh(), np.asarray(p.rgba, float)) for p in self.parts]

    @property
    def extents(self) -> np.ndarray:
        """Bounding-box size along x, y, z of O [m], shape (3,)."""
        return np.asarray(self.mesh.bounds[1] - self.mesh.bounds[0])

    @functools.cached_property
    def diameter(self) -> float:
        """Largest distance between two mesh vertices [m] (BOP's object diameter)."""
        return points_diameter(np.asarray(self.mesh.vertices))  # over their hull's vertices

    def resting_height(self, quat: np.ndarray) -> float:
        """Height of O's origin above a support plane when resting with orientation quat [m]."""
        R = quat_to_mat(quat)
        return float(-(np.asarray(self.mesh.vertices) @ R.T)[:, 2].min())

    def add_to_spec(
        self, spec: mujoco.MjSpec, instance: str, pos: np.ndarray, quat: np.ndarray
    ) -> mujoco.MjsBody:
        """Add the object as a free body to spec's worldbody.

        Visual geoms (group 2, no contact, no mass) carry the colours; collision geoms
        (group 3, hidden) carry friction and, for a built-in object, the mass (uniform
        density over its colliding parts). A user object's visual mesh and each of its convex
        hulls are mesh geoms (the assets are added once per spec and shared by its copies), and
        its body's mass, centre of mass and inertia are set explicitly from its hulls: MuJoCo's
        own inertia of a visual mesh that is not watertight would be wrong.

        Args:
            spec: the scene spec.
            instance: body name, unique in the scene.
            pos: initial position of O in the world [m].
            quat: initial orientation of O in the world, wxyz.

        Returns:
            The new body.
        """
        body = spec.worldbody.add_body()
        body.name = instance
        body.pos = list(map(float, pos))
        body.quat = list(map(float, quat))
        joint = body.add_freejoint()
        joint.name = instance + "/free"
        if self.geometry is not None:
            self._add_mesh_geoms(spec, body, instance)
            return body
        volume = sum(p.volume for p in self.parts if p.collision)
        density = self.mass / volume
        gtype = {
            "box": mujoco.mjtGeom.mjGEOM_BOX,
            "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER,
            "sphere": mujoco.mjtGeom.mjGEOM_SPHERE,
        }
        for part in self.parts:
            size = np.zeros(3)
            size[: len(part.size)] = part.size
            vis = body.add_geom()
            vis.name = f"{instance}/{part.name}"
            vis.type = gtype[part.type]
            vis.size, vis.pos, vis.quat = size, part.pos, part.quat
            vis.rgba = part.rgba
            vis.group, vis.contype, vis.conaffinity = VISUAL_GROUP, 0, 0
            vis.density = 0.0
            if part.collision:
                col = body.add_geom()
                col.name = f"{instance}/{part.name}_col"
                col.type = gtype[part.type]
                col.size, col.pos, col.quat = size, part.pos, part.quat
                col.rgba = [0.5, 0.5, 0.5, 0.0]
                col.group = COLLISION_GROUP
                col.contype, col.conaffinity = WORLD_CONTYPE, WORLD_CONAFFINITY
                col.density = density
                col.friction = list(self.friction)
                col.condim = 4
        return body

    def _add_mesh_geoms(self, spec: mujoco.MjSpec, body: mujoco.MjsBody, instance: str) -> None:
        """A user object's visual mesh, collision hulls and explicit inertia on `body`."""
        g = self.geometry
        assert g is not None
        prefix = f"{self.name}.{g.key}"
        if spec.mesh(prefix + "/visual") is None:
            if g.texture is None:
                _add_mesh_asset(spec, prefix + "/visual", g.visual)
            else:
                _add_textured_asset(spec, prefix, g.texture)
            for i, hull in enumerate(g.hulls):
                _add_mesh_asset(spec, f"{prefix}/hull{i:03d}", hull)
        vis = body.add_geom()
        vis.name = f"{instance}/visual"
        vis.type = mujoco.mjtGeom.mjGEOM_MESH
        vis.meshname = prefix + "/visual"
        vis.rgba = g.rgba
        if g.texture is not None:  # the texture's own colours, untinted
            vis.material, vis.rgba = prefix + "/material", [1.0, 1.0, 1.0, 1.0]
        vis.group, vis.contype, vis.conaffinity = VISUAL_GROUP, 0, 0
        vis.density = 0.0
        for i in range(len(g.hulls)):
            col = body.add_geom()
            col.name = f"{instance}/hull{i:03d}"
            col.type = mujoco.mjtGeom.mjGEOM_MESH
            col.meshname = f"{prefix}/hull{i:03d}"
            col.rgba = [0.5, 0.5, 0.5, 0.0]
            col.group = COLLISION_GROUP
            col.contype, col.conaffinity = WORLD_CONTYPE, WORLD_CONAFFINITY
            col.density = 0.0
            col.friction = list(self.friction)
            col.condim = 4
        inertia = g.inertia
        body.explicitinertial = True
        body.mass = float(self.mass)
        body.ipos = list(map(float, g.com))
        body.fullinertia = [
            float(inertia[i, j]) for i, j in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
        ]


def _add_mesh_asset(spec: mujoco.MjSpec, name: str, mesh: trimesh.Trimesh) -> None:
    """A mesh asset from a trimesh mesh [m]. Its inertia is taken as a shell: the asset's own
    volume is never used (the body's inertia is explicit) and need not be defined."""
    asset = spec.add_mesh()
    asset.name = name
    asset.uservert = np.asarray(mesh.vertices, np.float32).ravel()
    asset.userface = np.asarray(mesh.faces, np.int32).ravel()
    asset.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL


def _add_textured_asset(spec: mujoco.MjSpec, prefix: str, texture: Texture) -> None:
    """The mesh asset ``<prefix>/visual`` drawn with its texture (its coordinates per vertex),
    the texture ``<prefix>/texture`` and the material ``<prefix>/material`` that applies it."""
    asset = spec.add_mesh()
    asset.name = prefix + "/visual"
    asset.uservert = np.asarray(texture.vertices, np.float32).ravel()
    asset.userface = np.asarray(texture.faces, np.int32).ravel()
    # MuJoCo reads a texture's rows top first and its v from the top: OBJ's v is from the bottom.
    uv = np.asarray(texture.uv, np.float32).copy()
    uv[:, 1] = 1.0 - uv[:, 1]
    asset.usertexcoord = uv.ravel()
    asset.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL
    h, w = texture.image.shape[:2]
    tex = spec.add_texture()
    tex.name, tex.type = prefix + "/texture", mujoco.mjtTexture.mjTEXTURE_2D
    tex.width, tex.height, tex.nchannel = w, h, 3
    tex.data = np.ascontiguousarray(texture.image, np.uint8).tobytes()
    material = spec.add_material()
    material.name = prefix + "/material"
    material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = prefix + "/texture"


def _centred(parts: list[Part]) -> list[Part]:
    lo = np.min([p.mesh().bounds[0] for p in parts], axis=0)
    hi = np.max([p.mesh().bounds[1] for p in parts], axis=0)
    c = (lo + hi) / 2
    return [Part(p.name, p.type, p.pos - c, p.quat, p.size, p.rgba, p.collision) for p in parts]


def load_object(name: str) -> ObjectModel:
    """The object called name: a built-in one read from `scenes/objects/<name>.json`, or a user
    object read from its folder (`posegrasp.world.user_objects`). The same model is returned
    while the files are unchanged.

    Raises:
        UnknownNameError: name is not one of `object_names()`.
        AssetError: the definition file is missing or malformed.
    """
    if name in OBJECT_NAMES:
        return _load_builtin(name)
    check_object(name)
    return _load_user(name, str(user_objects_dir()), description_revision(name))


@functools.lru_cache(maxsize=32)
def _load_user(name: str, folder: str, revision: str) -> ObjectModel:
    """A user object's model; the arguments besides `name` key the cache (a rewritten
    description, or another objects directory, is read afresh)."""
    del folder
    rec = read_user_object(name)
    return ObjectModel(
        name=name,
        description=str(rec.description.get("description", "")),
        parts=(),
        mass=rec.mass,
        friction=rec.friction,
        symmetries=rec.symmetries,
        resting_poses=rec.resting_poses,
        ungraspable=rec.ungraspable,
        geometry=rec.geometry,
        grasps=rec.grasps,
        revision=revision,
    )


@functools.cache
def _load_builtin(name: str) -> ObjectModel:
    """A built-in object, read from `scenes/objects/<name>.json`."""
    path = OBJECTS_DIR / f"{name}.json"
    try:
        raw = json.loads(path.read_text())
        parts = _centred([_parse_part(p, name) for p in raw["parts"]])
        syms = []
        for s in raw.get("symmetries", []):
            T = np.eye(4)
            axis = np.asarray(s["axis"], float)
            mujoco.mju_axisAngle2Quat(q := np.zeros(4), axis / np.linalg.norm(axis), s["angle"])
            T[:3, :3] = quat_to_mat(q)
            syms.append(T)
        rest = {r["name"]: np.asarray(r["quat"], float) for r in raw["resting_poses"]}
        ungraspable = tuple(r["name"] for r in raw["resting_poses"] if not r.get("graspable", 1))
        return ObjectModel(
            name=name,
            description=raw.get("description", ""),
            parts=tuple(parts),
            mass=float(raw["mass"]),
            friction=tuple(raw.get("friction", [1.0, 0.01, 0.0005])),
            symmetries=tuple(syms),
            resting_poses=rest,
            ungraspable=ungraspable,
        )
    except (OSError, KeyError, TypeError, ValueError) as exc:
        raise AssetError(f"cannot read object definition {path}: {exc}") from exc
