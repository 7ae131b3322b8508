"""The BOP layout of a dataset folder and its files: paths, atomic writers and checked readers.

Layout of a dataset folder ``<root>`` (one distribution, built by
``python -m perception.training.datagen``)::

    <root>/info.json                      generator, version, arguments, counts, seed ranges
    <root>/camera.json                    BOP camera (fx, fy, cx, cy, width, height, depth_scale)
    <root>/models/models_info.json        BOP: diameter, min_x.., size_x.. [mm], symmetries
    <root>/models/obj_000001.ply          BOP: mesh in O [mm], vertex normals and colours
    <root>/<split>/<scene_id:06d>/rgb/<im_id:06d>.png
    <root>/<split>/<scene_id:06d>/mask/<im_id:06d>_<gt_idx:06d>.png        full silhouette
    <root>/<split>/<scene_id:06d>/mask_visib/<im_id:06d>_<gt_idx:06d>.png  visible part
    <root>/<split>/<scene_id:06d>/scene_gt.json         BOP: cam_R_m2c, cam_t_m2c [mm], obj_id
    <root>/<split>/<scene_id:06d>/scene_camera.json     BOP: cam_K, depth_scale, cam_R_w2c ..
    <root>/<split>/<scene_id:06d>/scene_gt_info.json    BOP: bbox_obj, bbox_visib, px_count_*..
    <root>/<split>/<scene_id:06d>/scene_posegrasp.json  ours: class, seed, T_C_O [m], uv, box..
    <root>/<split>/<scene_id:06d>/records/<im_id:06d>.json  one image's entries of all the above

Sample ``index`` of a split is image ``im_id = index % 1000`` of scene ``index // 1000``. Object
ids are 1..6 in `posegrasp.world.objects.OBJECT_NAMES` order, user objects after them, and bank
meshes annotated as objects (``--bank``) 10000 + their mesh id.

Units: BOP files use millimetres for translations, sizes and diameters (``cam_t_m2c``,
``cam_t_w2c``, ``models_info``, the PLY vertices), as the BOP toolkit expects. Everything else is
in metres (docs/DESIGN.md §4): `MM_PER_M` converts at the BOP boundary.
Pixel boxes: BOP's ``bbox_*`` are integer ``[x, y, w, h]`` with ``w = x_max - x_min`` (the BOP
toolkit's convention); ``box_xyxy`` in ``scene_posegrasp.json`` is the continuous box
``(x_min - 0.5, y_min - 0.5, x_max + 0.5, y_max + 0.5)`` that encloses the visible mask pixels
(docs/DESIGN.md §4: the centre of pixel (0, 0) is (0, 0)).

Every file is written to a temporary name and renamed, with deterministic bytes (sorted JSON keys,
fixed PNG encoder settings). The readers check what they read and raise `AssetError` naming the
file and the command that rebuilds the split.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from posegrasp.core.errors import AssetError, UnknownNameError
from posegrasp.core.transforms import make_transform
from posegrasp.world.distractor_bank import BANK_OBJ_ID_BASE, SHAPE_IDS, bank_id, bank_name
from posegrasp.world.objects import object_names

IMAGES_PER_SCENE = 1000
MM_PER_M = 1000.0
#: zlib level of the PNGs written (`png_bytes`): fast, and a fixed level gives the same bytes
#: for the same image.
PNG_LEVEL = 2
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_END = b"IEND\xaeB`\x82"
#: The four per-scene files (``<name>.json``), merged from the image records.
SCENE_FILES = ("scene_gt", "scene_camera", "scene_gt_info", "scene_posegrasp")


# --- ids and paths ---------------------------------------------------------------------------


def obj_id(name: str) -> int:
    """BOP object id of a class: 1..6 for the built-in objects in `OBJECT_NAMES` order, then the
    user objects installed, 7 upward in `object_names()` order (an export records its own); a
    bank mesh annotated as an object (``bank-NNN``) `BANK_OBJ_ID_BASE` + NNN."""
    mesh_id = bank_id(name)
    if mesh_id is not None:
        return BANK_OBJ_ID_BASE + mesh_id
    names = object_names()
    if name not in names:
        raise UnknownNameError("object", name, names)
    return names.index(name) + 1


def obj_name(oid: int) -> str:
    """Class of a BOP object id (`obj_id`)."""
    if BANK_OBJ_ID_BASE <= oid < BANK_OBJ_ID_BASE + SHAPE_IDS.stop:
        return bank_name(oid - BANK_OBJ_ID_BASE)
    names = object_names()
    if not 1 <= oid <= len(names):
        raise UnknownNameError("object id", str(oid), [str(i + 1) for i in range(len(names))])
    return names[oid - 1]


def split_index(index: int) -> tuple[int, int]:
    """(scene_id, im_id) of sample index of a split."""
    return index // IMAGES_PER_SCENE, index % IMAGES_PER_SCENE


def scene_dir(root: Path, split: str, scene_id: int) -> Path:
    """Folder of one scene (a chunk of up to 1000 images)."""
    return Path(root) / split / f"{scene_id:06d}"


def rgb_path(sdir: Path, im_id: int) -> Path:
    """RGB image of image im_id of the scene folder sdir."""
    return sdir / "rgb" / f"{im_id:06d}.png"


def mask_path(sdir: Path, im_id: int, gt_idx: int, visib: bool) -> Path:
    """Full (visib False) or visible mask of instance gt_idx of image im_id."""
    return sdir / ("mask_visib" if visib else "mask") / f"{im_id:06d}_{gt_idx:06d}.png"


def record_path(sdir: Path, im_id: int) -> Path:
    """Record of image im_id: its entries of the four scene files; it marks the image as done."""
    return sdir / "records" / f"{im_id:06d}.json"


# --- atomic writers --------------------------------------------------------------------------


def _atomic_write(path: Path, payload: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    try:
        f = open(tmp, "wb")
    except FileNotFoundError:
        path.parent.mkdir(parents=True, exist_ok=True)
        f = open(tmp, "wb")
    with f:
        f.write(payload)
    os.replace(tmp, path)


def json_bytes(obj: Any, indent: int | None = 1) -> bytes:
    """Deterministic JSON: sorted keys, fixed indentation (None: one line), trailing newline."""
    return (json.dumps(obj, sort_keys=True, indent=indent) + "\n").encode()


def write_json(path: Path, obj: Any, indent: int | None = 1) -> None:
    """Write obj as deterministic JSON, atomically (temporary file, then rename)."""
    _atomic_write(Path(path), json_bytes(obj, indent))


def _png_chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def png_bytes(image: np.ndarray) -> bytes:
    """PNG encoding of an RGB (H, W, 3) or grey (H, W) uint8 image: 8 bits per channel, every
    row unfiltered, one zlib stream at `PNG_LEVEL`.

    Rendered images compress about as well without PNG's row filters as libpng does with its
    adaptive filter choice (67 against 63 kB for a 640x480 head-camera image), in a quarter of
    the time; masks, mostly zeros, compress to about 1.5 kB.
    """
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise AssetError(
            f"cannot encode an image of shape {img.shape} and type {img.dtype} as PNG: "
            "expected (H, W) or (H, W, 3) uint8"
        )
    h, w = img.shape[:2]
    if h == 0 or w == 0:
        raise AssetError(f"cannot encode an empty image of shape {img.shape} as PNG")
    rows = np.zeros((h, 1 + img[0].size), np.uint8)  # leading 0: filter type None
    rows[:, 1:] = img.reshape(h, -1)
    header = struct.pack(">IIBBBBB", w, h, 8, 2 if img.ndim == 3 else 0, 0, 0, 0)
    return (
        _PNG_SIGNATURE
        + _png_chunk(b"IHDR", header)
        + _png_chunk(b"IDAT", zlib.compress(rows.tobytes(), PNG_LEVEL))
        + _png_chunk(b"IEND", b"")
    )


def write_bytes(path: Path, payload: bytes) -> None:
    """Write bytes atomically (temporary file in the same folder, then rename)."""
    _atomic_write(Path(path), payload)


def write_same(path: Path, written: Path, payload: bytes) -> None:
    """Write at path the bytes already written at `written` (payload): as a hard link to it,
    which costs far less than a new file on most file systems, or as a copy where hard links
    are not supported. Replaces whatever was at path."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.unlink(missing_ok=True)
        os.link(written, tmp)
    except OSError:
        write_bytes(path, payload)
        return
    os.replace(tmp, path)


def write_png(path: Path, image: np.ndarray) -> None:
    """Write an RGB (H, W, 3) or grey (H, W) uint8 image as PNG, atomically."""
    _atomic_write(Path(path), png_bytes(image))


def write_ply(
    path: Path,
    vertices: np.ndarray,
    normals: np.ndarray,
    colours: np.ndarray,
    faces: np.ndarray,
    texture: tuple[np.ndarray, str] | None = None,
) -> None:
    """Binary little-endian PLY with vertex normals and colours (the BOP model format).

    Args:
        vertices: (N, 3) positions (BOP: [mm]).
        normals: (N, 3) unit normals.
        colours: (N, 3) uint8 RGB.
        faces: (M, 3) vertex indices.
        texture: the vertices' texture coordinates (N, 2) (v up from the image's bottom row)
            and the texture's file name beside the PLY, as BOP's textured models give them
            (``texture_u``, ``texture_v`` and a ``TextureFile`` comment); None: no texture.
    """
    n, m = len(vertices), len(faces)
    tex = "" if texture is None else f"comment TextureFile {texture[1]}\n"
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment posegrasp procedural model, units: mm\n"
        f"{tex}element vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        + ("" if texture is None else "property float texture_u\nproperty float texture_v\n")
        + f"element face {m}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    fields = [("p", "<f4", 3), ("n", "<f4", 3), ("c", "u1", 3)]
    vdt = np.dtype(fields if texture is None else [*fields, ("t", "<f4", 2)])
    v = np.empty(n, vdt)
    v["p"], v["n"], v["c"] = vertices, normals, colours
    if texture is not None:
        v["t"] = texture[0]
    fdt = np.dtype([("k", "u1"), ("i", "<i4", 3)])
    f = np.empty(m, fdt)
    f["k"], f["i"] = 3, faces
    _atomic_write(Path(path), header.encode() + v.tobytes() + f.tobytes())


# --- checked readers -------------------------------------------------------------------------


def rebuild_hint(root: Path, split: str | None = None) -> str:
    """The command that rebuilds (part of) a dataset, read from its info.json if possible."""
    root = Path(root)
    try:
        info = json.loads((root / "info.json").read_text())
        split = split or next(iter(info["splits"]))
        cmd = info["splits"][split]["command"]
        return f"rebuild with: {cmd} --out {root}"
    except (OSError, ValueError, KeyError, StopIteration):
        return (
            "rebuild with: python -m perception.training.datagen --dist ... --split ... "
            f"--out {root}"
        )


def read_json(path: Path, root: Path, split: str | None) -> Any:
    """Parse a dataset JSON file, or raise AssetError naming it and the rebuild command."""
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise AssetError(f"missing dataset file {path}; {rebuild_hint(root, split)}") from None
    except (OSError, ValueError) as exc:
        raise AssetError(
            f"corrupt dataset file {path} ({exc}); {rebuild_hint(root, split)}"
        ) from None


def read_png(path: Path, root: Path, split: str | None, grey: bool = False) -> np.ndarray:
    """Read and check a PNG written by `write_png` (RGB or grey), or raise AssetError.

    Returns:
        RGB image, shape (H, W, 3), or grey image if grey, shape (H, W); uint8.
    """
    try:
        raw = Path(path).read_bytes()
    except FileNotFoundError:
        raise AssetError(f"missing dataset file {path}; {rebuild_hint(root, split)}") from None
    # A PNG ends with the IEND chunk; a file cut short does not (cv2 may still decode part).
    img = None
    if raw.startswith(_PNG_SIGNATURE) and raw.endswith(_PNG_END):
        flag = cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR
        img = cv2.imdecode(np.frombuffer(raw, np.uint8), flag)
    if img is None:
        raise AssetError(f"corrupt PNG {path}; {rebuild_hint(root, split)}")
    return img if grey else np.ascontiguousarray(img[..., ::-1])


# --- BOP conversions (metres inside, millimetres in the files) -------------------------------


def pose_to_bop(T_C_O: np.ndarray) -> dict[str, list[float]]:
    """BOP's cam_R_m2c (row-major 9) and cam_t_m2c [mm] of T_C_O [m], shape (4, 4)."""
    return {
        "cam_R_m2c": [float(x) for x in T_C_O[:3, :3].reshape(-1)],
        "cam_t_m2c": [float(x) * MM_PER_M for x in T_C_O[:3, 3]],
    }


def pose_from_bop(entry: dict[str, Any]) -> np.ndarray:
    """T_C_O [m], shape (4, 4), of a scene_gt entry (cam_t_m2c in mm)."""
    R = np.asarray(entry["cam_R_m2c"], float).reshape(3, 3)
    return make_transform(R, np.asarray(entry["cam_t_m2c"], float) / MM_PER_M)


def bbox_xywh(mask: np.ndarray) -> list[int]:
    """BOP box [x, y, w, h] [px] (w = x_max - x_min) of a mask's pixels; [-1, -1, 0, 0] if empty.

    Args:
        mask: shape (H, W), bool or uint8.
    """
    x, y, w, h = cv2.boundingRect(np.asarray(mask, np.uint8))
    if w == 0:
        return [-1, -1, 0, 0]
    return [int(x), int(y), int(w) - 1, int(h) - 1]


def box_xyxy(mask: np.ndarray) -> list[float]:
    """Continuous box (x0, y0, x1, y1) [px] enclosing a non-empty mask's pixels, shape (H, W)."""
    x, y, w, h = bbox_xywh(mask)
    return [x - 0.5, y - 0.5, x + w + 0.5, y + h + 0.5]
