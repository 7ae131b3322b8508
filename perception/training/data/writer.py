"""Writing a dataset folder: one image's files, the merged scene files, the models and camera.

Every file goes through the atomic writers of `perception.training.data.bop`. An image's record is
written last, so an image is done once its record exists; a scene's four BOP files are merged
from its records.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from perception.training.data.annotations import annotate, object_diameter, object_mesh
from perception.training.data.bop import (
    MM_PER_M,
    SCENE_FILES,
    mask_path,
    obj_id,
    png_bytes,
    read_json,
    record_path,
    rgb_path,
    scene_dir,
    split_index,
    write_bytes,
    write_json,
    write_ply,
    write_png,
    write_same,
)
from perception.training.data.distributions import RenderedImage
from posegrasp.world.distractor_bank import bank_id, bank_mesh
from posegrasp.world.meshes import Texture
from posegrasp.world.objects import OBJECT_NAMES, load_object


def write_sample(
    root: Path, split: str, index: int, seed: int, image: RenderedImage, dist: str
) -> None:
    """Write one image's files; the record goes last and marks the image as done.

    Args:
        root: dataset folder.
        split: its split.
        index: sample index in the split.
        seed: the seed it was rendered from.
        image: the rendered image with its instances.
        dist: its distribution.
    """
    scene_id, im_id = split_index(index)
    sdir = scene_dir(root, split, scene_id)
    record = annotate(image, seed, dist)
    write_png(rgb_path(sdir, im_id), image.rgb)
    for k, obj in enumerate(image.objects):
        full_path, visib_path = mask_path(sdir, im_id, k, False), mask_path(sdir, im_id, k, True)
        full = png_bytes(obj.mask.astype(np.uint8) * 255)
        write_bytes(full_path, full)
        if obj.mask_visib is obj.mask or np.array_equal(obj.mask_visib, obj.mask):
            write_same(visib_path, full_path, full)
        else:
            write_bytes(visib_path, png_bytes(obj.mask_visib.astype(np.uint8) * 255))
    write_json(record_path(sdir, im_id), record, indent=None)


def merge_scene(root: Path, split: str, scene_id: int) -> int:
    """Merge a scene's records into its four BOP scene files; returns the number of images."""
    sdir = scene_dir(root, split, scene_id)
    merged: dict[str, dict[str, Any]] = {k: {} for k in SCENE_FILES}
    records = sorted((sdir / "records").glob("*.json"))
    for path in records:
        rec = read_json(path, root, split)
        for k in SCENE_FILES:
            merged[k][str(int(path.stem))] = rec[k]
    for k in SCENE_FILES:
        write_json(sdir / f"{k}.json", merged[k])
    return len(records)


def _coloured_meshes(name: str) -> list[tuple[trimesh.Trimesh, np.ndarray]]:
    """An object's meshes in O [m] with their RGBA: a built-in object's parts, a user object's
    visual mesh, a bank mesh (in its file's colour)."""
    mesh_id = bank_id(name)
    if mesh_id is not None:
        return [(object_mesh(name), np.asarray(bank_mesh(mesh_id).rgba))]
    obj = load_object(name)
    if obj.geometry is not None:
        return [(obj.geometry.visual, np.asarray(obj.geometry.rgba))]
    return [(part.mesh(), np.asarray(part.rgba)) for part in obj.parts]


def _texture(name: str) -> Texture | None:
    """A user object's texture, with its mesh as drawn (None: none, or not a user object)."""
    if bank_id(name) is not None:
        return None
    geometry = load_object(name).geometry
    return None if geometry is None else geometry.texture


def _write_coloured(path: Path, name: str) -> np.ndarray:
    """Write an object's meshes into one PLY in [mm] with each mesh's colour on its vertices;
    returns the vertices written [mm]."""
    verts, normals, colours, faces = [], [], [], []
    offset = 0
    for m, rgba in _coloured_meshes(name):
        verts.append(np.asarray(m.vertices))
        normals.append(np.asarray(m.vertex_normals))
        rgb = np.clip(np.round(rgba[:3] * 255), 0, 255).astype(np.uint8)
        colours.append(np.tile(rgb, (len(m.vertices), 1)))
        faces.append(np.asarray(m.faces) + offset)
        offset += len(m.vertices)
    v = np.vstack(verts) * MM_PER_M
    write_ply(path, v, np.vstack(normals), np.vstack(colours), np.vstack(faces))
    return v


def write_models(root: Path, names: Sequence[str] = OBJECT_NAMES) -> None:
    """BOP models (PLY in mm with vertex colours; a textured user object's with its texture
    coordinates and its texture, ``obj_<id>.png``, beside it) and models_info.json for the
    objects `names` (the built-in ones by default; user objects and bank meshes, ``bank-NNN``,
    too)."""
    info = {}
    for name in names:
        path = root / "models" / f"obj_{obj_id(name):06d}.ply"
        texture = _texture(name)
        if texture is not None:  # the mesh as drawn, white, and its texture beside it
            m = trimesh.Trimesh(texture.vertices, texture.faces, process=False)
            v = np.asarray(m.vertices) * MM_PER_M
            white = np.full((len(v), 3), 255, np.uint8)
            png = path.with_suffix(".png")
            write_ply(path, v, m.vertex_normals, white, m.faces, (texture.uv, png.name))
            write_png(png, texture.image)
        else:
            v = _write_coloured(path, name)
        lo, size = v.min(axis=0), v.max(axis=0) - v.min(axis=0)
        entry: dict[str, Any] = {"diameter": object_diameter(name) * MM_PER_M}
        for i, axis in enumerate("xyz"):
            entry[f"min_{axis}"] = float(lo[i])
            entry[f"size_{axis}"] = float(size[i])
        syms = []
        for T in () if bank_id(name) is not None else load_object(name).symmetries:
            S = np.array(T, float)
            S[:3, 3] *= MM_PER_M
            syms.append([float(x) for x in S.reshape(-1)])
        if syms:
            entry["symmetries_discrete"] = syms
        info[str(obj_id(name))] = entry
    write_json(root / "models" / "models_info.json", info)


def write_camera(root: Path, split: str, width: int, height: int) -> None:
    """BOP camera.json, from the K of the split's first image (all images share it).

    Nothing is written while the split has no image.

    Args:
        root: dataset folder.
        split: the split whose first record gives K.
        width, height: image size [px].
    """
    first = next(iter(sorted((root / split).glob("*/records/*.json"))), None)
    if first is None:
        return
    K = np.asarray(read_json(first, root, split)["scene_camera"]["cam_K"]).reshape(3, 3)
    camera = {
        "cx": float(K[0, 2]),
        "cy": float(K[1, 2]),
        "fx": float(K[0, 0]),
        "fy": float(K[1, 1]),
        "width": width,
        "height": height,
        "depth_scale": 1.0,
    }
    write_json(root / "camera.json", camera)


#: Wall time [s] of each split's generation runs, summed over resumptions.
WALL_TIME_FILE = "wall_time.json"


def add_wall_time(out: Path, split: str, seconds: float) -> None:
    """Add seconds to the wall time the runs of a split have taken, in ``<out>/wall_time.json``
    (apart from info.json, whose bytes depend on the arguments alone)."""
    path = out / WALL_TIME_FILE
    times = read_json(path, out, split) if path.is_file() else {}
    times[split] = round(float(times.get(split, 0.0)) + seconds, 1)
    write_json(path, times)
