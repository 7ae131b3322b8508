"""User objects: meshes made into posegrasp objects, one folder each in the user objects directory.

The directory is ``$POSEGRASP_OBJECTS`` when set, else ``$XDG_DATA_HOME/posegrasp/objects``, else
``~/.local/share/posegrasp/objects``; never inside the repository. ``python -m sim.add_object``
writes one folder per object::

    <objects dir>/<name>/
        object.json     the description (`DESCRIPTION_FILE`): units, scale, source file and its
                        SHA-256, mass, inertia, friction, colour, symmetries (BOP models_info
                        form), resting poses, grasp candidates per resting pose, the convex
                        decomposition's tool, version and parameters, timings
        visual.ply      the visual mesh in the object frame O [m] (origin at the bounding-box
                        centre, z up in the canonical resting pose)
        hull_000.ply    one convex collision hull a file, in O [m]
        ...
        texture.png     with a textured mesh: its texture, and
        textured.npz    the mesh as drawn with it: vertices in O [m], faces, texture coordinates
        preview.png     the object, its hulls and each resting pose with its grasps

Every length in the files is in metres except the BOP models_info block, whose translations,
offsets and sizes are in millimetres as BOP's are. This module reads and writes that layout; the
objects themselves are `posegrasp.world.objects.ObjectModel`.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from PIL import Image, UnidentifiedImageError

from posegrasp.core.errors import AssetError, InvalidArgumentError
from posegrasp.core.files import atomic_write_json, sha256_file
from posegrasp.world.meshes import Texture

#: The environment variable naming the user objects directory.
OBJECTS_ENV = "POSEGRASP_OBJECTS"
#: Version of the folder layout and description format.
FORMAT_VERSION = 1
DESCRIPTION_FILE = "object.json"
VISUAL_FILE = "visual.ply"
PREVIEW_FILE = "preview.png"
TEXTURE_FILES = {"mesh": "textured.npz", "image": "texture.png"}
#: Object names: lower-case letters, digits, '_' and '-', starting with a letter, at most 40.
NAME_PATTERN = re.compile(r"^[a-z][a-z0-9_-]{0,39}$")
#: Largest rotation step of a discretised continuous symmetry, as BOP's toolkit takes it
#: (``ceil(pi / step)`` rotations about the axis).
MAX_SYM_DISC_STEP = 0.01


def objects_dir() -> Path:
    """The user objects directory: ``$POSEGRASP_OBJECTS``, else
    ``$XDG_DATA_HOME/posegrasp/objects``, else ``~/.local/share/posegrasp/objects``."""
    env = os.environ.get(OBJECTS_ENV)
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_DATA_HOME")
    base = Path(xdg).expanduser() if xdg else Path.home() / ".local" / "share"
    return base / "posegrasp" / "objects"


def check_object_name(name: str) -> str:
    """`name` when it can name a user object (`NAME_PATTERN`).

    Raises:
        InvalidArgumentError: otherwise, saying what a name may hold.
    """
    if not isinstance(name, str) or not NAME_PATTERN.match(name) or name == "all":
        raise InvalidArgumentError(
            f"invalid object name {name!r}; valid: 1-40 lower-case letters, digits, '_' or '-', "
            "starting with a letter (not 'all')"
        )
    return name


def user_object_names() -> tuple[str, ...]:
    """Names of the user objects found in `objects_dir()` (folders holding an object.json with
    a valid name), sorted."""
    root = objects_dir()
    if not root.is_dir():
        return ()
    return tuple(
        sorted(
            p.name
            for p in root.iterdir()
            if NAME_PATTERN.match(p.name) and (p / DESCRIPTION_FILE).is_file()
        )
    )


def object_folder(name: str) -> Path:
    """The folder of user object `name` (it may not exist)."""
    return objects_dir() / name


def description_revision(name: str) -> str:
    """A token that changes whenever user object `name`'s description is rewritten (its
    SHA-256), for caches keyed by object.

    Raises:
        AssetError: the description cannot be read.
    """
    path = object_folder(name) / DESCRIPTION_FILE
    try:
        return sha256_file(path)
    except OSError as exc:
        raise AssetError(f"cannot read object description {path}: {exc.strerror}") from None


@dataclass(frozen=True)
class MeshGeometry:
    """The shape and mass distribution of a mesh object, in its frame O.

    Attributes:
        key: identifies these meshes (the description's SHA-256, shortened); MuJoCo mesh assets
            are named after it, so copies of one object in a scene share them.
        visual: the visual mesh [m] (need not be watertight).
        hulls: the convex collision hulls [m], one mesh each.
        rgba: colour of the visual mesh, shape (4,).
        com: centre of mass in O [m], shape (3,).
        inertia: inertia tensor about the centre of mass, O's axes [kg m^2], shape (3, 3).
        texture: the mesh as drawn with its texture, in O (None: drawn in `rgba`).
    """

    key: str
    visual: trimesh.Trimesh
    hulls: tuple[trimesh.Trimesh, ...]
    rgba: np.ndarray
    com: np.ndarray
    inertia: np.ndarray
    texture: Texture | None = None


@dataclass(frozen=True)
class StoredGrasp:
    """A grasp candidate of a mesh object, as stored in its description.

    Attributes:
        pose: the resting pose it was made for.
        T_O_G: pose of the gripper's grasp site in O (x approach, y closing), shape (4, 4) [m].
        width: extent of the object between the finger pads [m].
        score: the generator's quality, lower is better.
    """

    pose: str
    T_O_G: np.ndarray
    width: float
    score: float


@dataclass(frozen=True)
class UserObjectRecord:
    """What a user object's folder holds, read and checked (`read_user_object`).

    Attributes:
        name: the object's name (its folder's).
        folder: the folder.
        revision: the description's SHA-256.
        description: the parsed object.json.
        geometry: visual mesh, hulls, colour and mass distribution.
        mass: total mass [kg].
        friction: MuJoCo friction (sliding, torsional, rolling).
        symmetries: proper symmetries besides the identity, each T_O_O' (4, 4) [m]; a
            continuous one discretised as BOP's toolkit does (`symmetry_transforms`).
        resting_poses: name -> wxyz orientation of O resting on a plane, canonical first.
        ungraspable: resting poses no grasp candidate serves.
        grasps: the grasp candidates of every resting pose.
    """

    name: str
    folder: Path
    revision: str
    description: dict[str, Any]
    geometry: MeshGeometry
    mass: float
    friction: tuple[float, float, float]
    symmetries: tuple[np.ndarray, ...]
    resting_poses: dict[str, np.ndarray]
    ungraspable: tuple[str, ...]
    grasps: tuple[StoredGrasp, ...]


def _axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation by angle [rad] about a unit axis, shape (3, 3)."""
    x, y, z = axis
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def symmetry_transforms(models_info: dict[str, Any]) -> tuple[np.ndarray, ...]:
    """The symmetries of a BOP models_info entry as transforms T_O_O' (4, 4) [m], identity left
    out: each discrete one, each continuous one discretised into ``ceil(pi /
    MAX_SYM_DISC_STEP)`` rotations about its axis through its offset, and every discrete one
    composed with every such rotation (BOP's toolkit's set).

    Args:
        models_info: with optional ``symmetries_discrete`` (row-major 16-lists, translation in
            mm) and ``symmetries_continuous`` (``{"axis": [3], "offset": [3] mm}``).

    Raises:
        AssetError: a malformed symmetry.
    """
    try:
        disc = [np.eye(4)]
        for raw in models_info.get("symmetries_discrete", []):
            T = np.array(raw, float).reshape(4, 4)
            T[:3, 3] *= 1e-3
            disc.append(T)
        continuous = models_info.get("symmetries_continuous", [])
        cont = [] if continuous else [np.eye(4)]
        n = math.ceil(math.pi / MAX_SYM_DISC_STEP)
        for sym in continuous:
            axis = np.asarray(sym["axis"], float).reshape(3)
            offset = np.asarray(sym["offset"], float).reshape(3) * 1e-3
            for k in range(n):
                T = np.eye(4)
                T[:3, :3] = _axis_rotation(axis / np.linalg.norm(axis), 2 * math.pi * k / n)
                T[:3, 3] = offset - T[:3, :3] @ offset
                cont.append(T)
    except (KeyError, TypeError, ValueError) as exc:
        raise AssetError(f"malformed symmetry in models_info: {exc}") from None
    out = [Tc @ Td for Td in disc for Tc in cont]
    return tuple(T for T in out if not np.allclose(T, np.eye(4), atol=1e-12))


def _load_mesh(path: Path) -> trimesh.Trimesh:
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except (OSError, ValueError) as exc:
        raise AssetError(f"cannot read mesh {path}: {exc}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise AssetError(f"mesh {path} holds no triangles")
    return mesh


def _matrix(raw: Any, shape: tuple[int, ...], what: str) -> np.ndarray:
    arr = np.asarray(raw, float)
    if arr.shape != shape or not np.all(np.isfinite(arr)):
        raise AssetError(f"{what} must be a finite array of shape {shape}")
    return arr


def read_user_object(name: str) -> UserObjectRecord:
    """Read and check the folder of user object `name`.

    Raises:
        AssetError: the folder, its description or a mesh is missing or malformed (the message
            names the file).
    """
    folder = object_folder(name)
    path = folder / DESCRIPTION_FILE
    revision = description_revision(name)
    try:
        raw = json.loads(path.read_text())
        if raw.get("format") != FORMAT_VERSION:
            raise AssetError(
                f"{path}: format {raw.get('format')!r}, this posegrasp reads format "
                f"{FORMAT_VERSION}; make the object again with python -m sim.add_object"
            )
        visual = _load_mesh(folder / raw["visual"])
        hulls = tuple(_load_mesh(folder / h) for h in raw["hulls"])
        if not hulls:
            raise AssetError(f"{path}: no collision hulls")
        geometry = MeshGeometry(
            key=revision[:12],
            visual=visual,
            hulls=hulls,
            rgba=_matrix(raw.get("rgba", [0.7, 0.7, 0.7, 1.0]), (4,), "rgba"),
            com=_matrix(raw["centre_of_mass"], (3,), "centre_of_mass"),
            inertia=_matrix(raw["inertia"], (3, 3), "inertia"),
            texture=_read_texture(folder, raw["texture"]) if "texture" in raw else None,
        )
        rest = {
            r["name"]: _matrix(r["quat"], (4,), "resting pose quat") for r in raw["resting_poses"]
        }
        if not rest:
            raise AssetError(f"{path}: no resting poses")
        ungraspable = tuple(r["name"] for r in raw["resting_poses"] if not r.get("graspable", 1))
        grasps = []
        for pose, entries in raw["grasps"].items():
            if pose not in rest:
                raise AssetError(f"{path}: grasps for an unknown resting pose {pose!r}")
            for g in entries:
                T = _matrix(g["T_O_G"], (4, 4), "T_O_G")
                grasps.append(StoredGrasp(pose, T, float(g["width"]), float(g.get("score", 0))))
        mass = float(raw["mass"])
        if not mass > 0:
            raise AssetError(f"{path}: mass must be positive, got {mass}")
        friction = tuple(float(v) for v in raw.get("friction", [1.0, 0.01, 0.0005]))
        if len(friction) != 3:
            raise AssetError(f"{path}: friction must hold 3 numbers")
        return UserObjectRecord(
            name=name,
            folder=folder,
            revision=revision,
            description=raw,
            geometry=geometry,
            mass=mass,
            friction=friction,
            symmetries=symmetry_transforms(raw.get("models_info", {})),
            resting_poses=rest,
            ungraspable=ungraspable,
            grasps=tuple(grasps),
        )
    except AssetError:
        raise
    except (OSError, KeyError, TypeError, ValueError, AttributeError) as exc:
        raise AssetError(f"cannot read object description {path}: {exc!r}") from None


def _read_texture(folder: Path, files: dict[str, str]) -> Texture:
    """A textured mesh's files (`TEXTURE_FILES`), read and checked.

    Raises:
        AssetError: a file is missing or malformed.
    """
    mesh, image = folder / files["mesh"], folder / files["image"]
    try:
        with np.load(mesh) as arrays:
            v, f, uv = (np.asarray(arrays[k]) for k in ("vertices", "faces", "uv"))
        with Image.open(image) as img:
            pixels = np.asarray(img.convert("RGB"), np.uint8)
    except (OSError, KeyError, ValueError, UnidentifiedImageError) as exc:
        raise AssetError(f"cannot read the texture of {folder.name}: {exc}") from None
    ok = v.ndim == 2 and v.shape[1] == 3 and uv.shape == (len(v), 2) and f.ndim == 2
    if not ok or f.shape[1] != 3 or len(f) == 0 or f.min() < 0 or f.max() >= len(v):
        raise AssetError(f"{mesh}: vertices, faces and texture coordinates do not fit together")
    return Texture(v.astype(float), f.astype(np.int64), uv.astype(float), pixels)


def write_object_folder(
    name: str,
    description: dict[str, Any],
    visual: trimesh.Trimesh,
    hulls: list[trimesh.Trimesh],
    preview_png: bytes | None = None,
    replace: bool = False,
    texture: Texture | None = None,
) -> Path:
    """Write user object `name`'s folder as a whole: into a temporary folder beside it, renamed
    into place at the end, so a failure leaves no half-written object.

    Args:
        name: the object's name (`check_object_name`).
        description: the object.json content; its ``visual`` and ``hulls`` entries are set
            here to the files written.
        visual: the visual mesh in O [m].
        hulls: the collision hulls in O [m].
        preview_png: the preview sheet's PNG bytes, if any.
        replace: replace an existing object of that name (refused otherwise).
        texture: the mesh as drawn with its texture, in O [m], if it has one.

    Returns:
        The object's folder.

    Raises:
        InvalidArgumentError: the object exists and `replace` is False.
    """
    check_object_name(name)
    root = objects_dir()
    final = root / name
    if final.exists() and not replace:
        raise InvalidArgumentError(
            f"a user object {name!r} exists in {root}; give --force to replace it"
        )
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{name}.", dir=root))
    try:
        visual.export(tmp / VISUAL_FILE)
        names = []
        for i, hull in enumerate(hulls):
            names.append(f"hull_{i:03d}.ply")
            hull.export(tmp / names[-1])
        description = {**description, "visual": VISUAL_FILE, "hulls": names}
        if texture is not None:
            np.savez(
                tmp / TEXTURE_FILES["mesh"],
                vertices=texture.vertices,
                faces=texture.faces,
                uv=texture.uv,
            )
            Image.fromarray(texture.image).save(tmp / TEXTURE_FILES["image"])
            description["texture"] = dict(TEXTURE_FILES)
        if preview_png is not None:
            (tmp / PREVIEW_FILE).write_bytes(preview_png)
            description["preview"] = PREVIEW_FILE
        atomic_write_json(tmp / DESCRIPTION_FILE, description)
        old = None
        if final.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{name}.old.", dir=root))
            os.replace(final, old / name)
        os.replace(tmp, final)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final
