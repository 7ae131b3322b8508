"""The on-disk pose dataset: BOP layout, writers, validating loaders and contact sheets.

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
ids are 1..6 in `sim.world.objects.OBJECT_NAMES` order.

Units: BOP files use millimetres for translations, sizes and diameters (``cam_t_m2c``,
``cam_t_w2c``, ``models_info``, the PLY vertices), as the BOP toolkit expects. Everything else, and
everything the loaders here return, is in metres (SPEC section 2): the conversion happens only in
this module. Pixel boxes: BOP's ``bbox_*`` are integer ``[x, y, w, h]`` with ``w = x_max - x_min``
(the BOP toolkit's convention); ``box_xyxy`` in ``scene_posegrasp.json`` is the continuous box
``(x_min - 0.5, y_min - 0.5, x_max + 0.5, y_max + 0.5)`` that encloses the visible mask pixels
(SPEC section 2: the centre of pixel (0, 0) is (0, 0)).

A sample is complete when its record file exists (it is written last, by atomic rename); the
scene files are merged from the records. `load_sample` checks every file it reads and raises
`AssetError` naming the file and the command that rebuilds the split.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sim.core.errors import AssetError, InvalidArgumentError, UnknownNameError
from sim.world.objects import OBJECT_NAMES, load_object

SPLITS: tuple[str, ...] = ("train", "val", "test")
DISTS: tuple[str, ...] = ("paper", "headcam")
IMAGES_PER_SCENE = 1000
MM_PER_M = 1000.0
#: Fixed PNG encoder settings (fast zlib level, run-length strategy): same image, same bytes.
PNG_PARAMS = [
    cv2.IMWRITE_PNG_COMPRESSION,
    1,
    cv2.IMWRITE_PNG_STRATEGY,
    cv2.IMWRITE_PNG_STRATEGY_RLE,
]
_PNG_END = b"IEND\xaeB`\x82"


# --- ids and paths ---------------------------------------------------------------------------


def obj_id(name: str) -> int:
    """BOP object id of a class: 1..6 in `OBJECT_NAMES` order."""
    if name not in OBJECT_NAMES:
        raise UnknownNameError("object", name, OBJECT_NAMES)
    return OBJECT_NAMES.index(name) + 1


def obj_name(oid: int) -> str:
    """Class of a BOP object id."""
    if not 1 <= oid <= len(OBJECT_NAMES):
        raise UnknownNameError("object id", str(oid), [str(i + 1) for i in range(6)])
    return OBJECT_NAMES[oid - 1]


def split_index(index: int) -> tuple[int, int]:
    """(scene_id, im_id) of sample index of a split."""
    return index // IMAGES_PER_SCENE, index % IMAGES_PER_SCENE


def scene_dir(root: Path, split: str, scene_id: int) -> Path:
    """Folder of one scene (a chunk of up to 1000 images)."""
    return Path(root) / split / f"{scene_id:06d}"


def rgb_path(sdir: Path, im_id: int) -> Path:
    return sdir / "rgb" / f"{im_id:06d}.png"


def mask_path(sdir: Path, im_id: int, gt_idx: int, visib: bool) -> Path:
    return sdir / ("mask_visib" if visib else "mask") / f"{im_id:06d}_{gt_idx:06d}.png"


def record_path(sdir: Path, im_id: int) -> Path:
    return sdir / "records" / f"{im_id:06d}.json"


SCENE_FILES = ("scene_gt", "scene_camera", "scene_gt_info", "scene_posegrasp")


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


def png_bytes(image: np.ndarray) -> bytes:
    """PNG encoding of an RGB (H, W, 3) or grey (H, W) uint8 image, with `PNG_PARAMS`."""
    img = image[..., ::-1] if image.ndim == 3 else image
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img), PNG_PARAMS)
    if not ok:
        raise AssetError(f"cannot encode an image of shape {image.shape} as PNG")
    return buf.tobytes()


def write_bytes(path: Path, payload: bytes) -> None:
    """Write bytes atomically (temporary file in the same folder, then rename)."""
    _atomic_write(Path(path), payload)


def write_png(path: Path, image: np.ndarray) -> None:
    """Write an RGB (H, W, 3) or grey (H, W) uint8 image as PNG, atomically."""
    _atomic_write(Path(path), png_bytes(image))


def write_ply(
    path: Path, vertices: np.ndarray, normals: np.ndarray, colours: np.ndarray, faces: np.ndarray
) -> None:
    """Binary little-endian PLY with vertex normals and colours (the BOP model format).

    Args:
        vertices: (N, 3) positions (BOP: [mm]).
        normals: (N, 3) unit normals.
        colours: (N, 3) uint8 RGB.
        faces: (M, 3) vertex indices.
    """
    n, m = len(vertices), len(faces)
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment posegrasp procedural model, units: mm\n"
        f"element vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        f"element face {m}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    vdt = np.dtype(
        [("p", "<f4", 3), ("n", "<f4", 3), ("c", "u1", 3)],
    )
    v = np.empty(n, vdt)
    v["p"], v["n"], v["c"] = vertices, normals, colours
    fdt = np.dtype([("k", "u1"), ("i", "<i4", 3)])
    f = np.empty(m, fdt)
    f["k"], f["i"] = 3, faces
    _atomic_write(Path(path), header.encode() + v.tobytes() + f.tobytes())


# --- BOP conversions (metres inside, millimetres in the files) -------------------------------


def pose_to_bop(T_C_O: np.ndarray) -> dict[str, list[float]]:
    """BOP's cam_R_m2c (row-major 9) and cam_t_m2c [mm] of T_C_O [m]."""
    return {
        "cam_R_m2c": [float(x) for x in T_C_O[:3, :3].reshape(-1)],
        "cam_t_m2c": [float(x) * MM_PER_M for x in T_C_O[:3, 3]],
    }


def pose_from_bop(entry: dict[str, Any]) -> np.ndarray:
    """T_C_O [m], shape (4, 4), of a scene_gt entry (cam_t_m2c in mm)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(entry["cam_R_m2c"], float).reshape(3, 3)
    T[:3, 3] = np.asarray(entry["cam_t_m2c"], float) / MM_PER_M
    return T


def bbox_xywh(mask: np.ndarray) -> list[int]:
    """BOP box [x, y, w, h] (w = x_max - x_min) of a mask's pixels; [-1, -1, 0, 0] if empty."""
    x, y, w, h = cv2.boundingRect(np.asarray(mask, np.uint8))
    if w == 0:
        return [-1, -1, 0, 0]
    return [int(x), int(y), int(w) - 1, int(h) - 1]


def box_xyxy(mask: np.ndarray) -> list[float]:
    """Continuous box (x0, y0, x1, y1) [px] enclosing a non-empty mask's pixels."""
    x, y, w, h = bbox_xywh(mask)
    return [x - 0.5, y - 0.5, x + w + 0.5, y + h + 0.5]


# --- loading ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class GtObject:
    """One annotated object instance of an image. Metres, radians, pixels.

    Attributes:
        obj_id: BOP object id (1..6).
        name: class name.
        T_C_O: pose in the camera (OpenCV), shape (4, 4) [m].
        mask: full silhouette (occluders ignored), shape (H, W), bool.
        mask_visib: visible pixels, shape (H, W), bool.
        uv: pixel where the object origin projects, shape (2,).
        box_xyxy: continuous box around the visible pixels, shape (4,).
        visib_fract: visible fraction of the silhouette (pixels outside the image count as
            not visible).
        info: the BOP scene_gt_info entry (boxes, pixel counts).
        extra: the rest of the posegrasp entry.
    """

    obj_id: int
    name: str
    T_C_O: np.ndarray
    mask: np.ndarray
    mask_visib: np.ndarray
    uv: np.ndarray
    box_xyxy: np.ndarray
    visib_fract: float
    info: dict[str, Any]
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Sample:
    """One image with its annotations.

    Attributes:
        split, scene_id, im_id: where it is stored.
        seed: the seed it was generated from.
        rgb: image, shape (H, W, 3), uint8.
        K: intrinsics, shape (3, 3) [px].
        objects: annotated instances (for the paper protocol exactly one).
        extra: per-image posegrasp fields (distribution, roll, ...).
    """

    split: str
    scene_id: int
    im_id: int
    seed: int
    rgb: np.ndarray
    K: np.ndarray
    objects: list[GtObject]
    extra: dict[str, Any]


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
    """Read and check a PNG written by `write_png` (RGB or grey), or raise AssetError."""
    try:
        raw = Path(path).read_bytes()
    except FileNotFoundError:
        raise AssetError(f"missing dataset file {path}; {rebuild_hint(root, split)}") from None
    # A PNG ends with the IEND chunk; a file cut short does not (cv2 may still decode part).
    img = None
    if raw.startswith(b"\x89PNG\r\n\x1a\n") and raw.endswith(_PNG_END):
        flag = cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR
        img = cv2.imdecode(np.frombuffer(raw, np.uint8), flag)
    if img is None:
        raise AssetError(f"corrupt PNG {path}; {rebuild_hint(root, split)}")
    return img if grey else np.ascontiguousarray(img[..., ::-1])


def load_info(root: Path) -> dict[str, Any]:
    """The dataset's info.json."""
    root = Path(root)
    return read_json(root / "info.json", root, None)


class PoseDataset:
    """The images of one split of a dataset folder, read through the merged scene files.

    Args:
        root: dataset folder (``--out`` of the generator).
        split: one of `SPLITS`.

    Raises:
        UnknownNameError: unknown split.
        AssetError: missing or corrupt scene files.
    """

    def __init__(self, root: str | os.PathLike[str], split: str) -> None:
        if split not in SPLITS:
            raise UnknownNameError("split", split, SPLITS)
        self.root = Path(root)
        self.split = split
        self._scenes: dict[int, dict[str, Any]] = {}
        self.index: list[tuple[int, int]] = []
        base = self.root / split
        if not base.is_dir():
            raise AssetError(f"no split {split!r} in {self.root}; {rebuild_hint(self.root, split)}")
        for sdir in sorted(p for p in base.iterdir() if p.is_dir() and p.name.isdigit()):
            gt_path = sdir / "scene_gt.json"
            if not gt_path.exists():
                continue
            ids = sorted(int(k) for k in read_json(gt_path, self.root, split))
            self.index.extend((int(sdir.name), i) for i in ids)

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> Sample:
        scene_id, im_id = self.index[i]
        return self.load(scene_id, im_id)

    def __iter__(self) -> Iterator[Sample]:
        for i in range(len(self)):
            yield self[i]

    def _scene(self, scene_id: int) -> dict[str, Any]:
        if scene_id not in self._scenes:
            sdir = scene_dir(self.root, self.split, scene_id)
            self._scenes[scene_id] = {
                k: read_json(sdir / f"{k}.json", self.root, self.split) for k in SCENE_FILES
            }
        return self._scenes[scene_id]

    def load(self, scene_id: int, im_id: int) -> Sample:
        """Load and check one image and its annotations (metres)."""
        sdir = scene_dir(self.root, self.split, scene_id)
        scene = self._scene(scene_id)
        key = str(im_id)
        try:
            gts, cam = scene["scene_gt"][key], scene["scene_camera"][key]
            infos, pg = scene["scene_gt_info"][key], scene["scene_posegrasp"][key]
            K = np.asarray(cam["cam_K"], float).reshape(3, 3)
            if not len(gts) == len(infos) == len(pg["objects"]):
                raise InvalidArgumentError("entries of the scene files disagree")
        except (KeyError, TypeError, ValueError) as exc:
            raise AssetError(
                f"corrupt annotations of image {im_id} in {sdir} ({exc!r}); "
                f"{rebuild_hint(self.root, self.split)}"
            ) from None
        rgb = read_png(rgb_path(sdir, im_id), self.root, self.split)
        objects = []
        for k, (gt, info, extra) in enumerate(zip(gts, infos, pg["objects"], strict=True)):
            masks = [
                read_png(mask_path(sdir, im_id, k, v), self.root, self.split, grey=True) > 0
                for v in (False, True)
            ]
            for m in masks:
                if m.shape != rgb.shape[:2]:
                    raise AssetError(
                        f"mask of image {im_id} object {k} in {sdir} has shape {m.shape}, "
                        f"image {rgb.shape[:2]}; {rebuild_hint(self.root, self.split)}"
                    )
            objects.append(
                GtObject(
                    obj_id=int(gt["obj_id"]),
                    name=obj_name(int(gt["obj_id"])),
                    T_C_O=pose_from_bop(gt),
                    mask=masks[0],
                    mask_visib=masks[1],
                    uv=np.asarray(extra["uv"], float),
                    box_xyxy=np.asarray(extra["box_xyxy"], float),
                    visib_fract=float(info["visib_fract"]),
                    info=info,
                    extra=extra,
                )
            )
        extra = {k: v for k, v in pg.items() if k != "objects"}
        return Sample(self.split, scene_id, im_id, int(pg["seed"]), rgb, K, objects, extra)


def load_sample(root: str | os.PathLike[str], split: str, index: int) -> Sample:
    """Load sample index of a split (image index % 1000 of scene index // 1000)."""
    scene_id, im_id = split_index(index)
    return PoseDataset(root, split).load(scene_id, im_id)


# --- drawing ---------------------------------------------------------------------------------


def draw_annotations(
    sample: Sample, axis_lengths: Sequence[float] | None = None, thickness: int = 2
) -> np.ndarray:
    """The sample's image with each object's axes (x red, y green, z blue), box and origin.

    Args:
        sample: a loaded sample.
        axis_lengths: axis length per object [m]; half the object's diameter by default.
        thickness: line width [px].

    Returns:
        RGB image, shape (H, W, 3), uint8.
    """
    img = np.ascontiguousarray(sample.rgb.copy())
    for k, obj in enumerate(sample.objects):
        length = axis_lengths[k] if axis_lengths is not None else load_object(obj.name).diameter / 2
        x0, y0, x1, y1 = obj.box_xyxy
        cv2.rectangle(img, (round(x0), round(y0)), (round(x1), round(y1)), (255, 220, 0), 1)
        pts = np.vstack([np.zeros(3), np.eye(3) * length]) @ obj.T_C_O[:3, :3].T + obj.T_C_O[:3, 3]
        if np.any(pts[:, 2] <= 1e-3):
            continue
        uv = pts[:, :2] / pts[:, 2:3] * [sample.K[0, 0], sample.K[1, 1]] + sample.K[:2, 2]
        o = tuple(round(float(c)) for c in uv[0])
        for j, colour in enumerate(((255, 0, 0), (0, 200, 0), (0, 80, 255))):
            e = tuple(round(float(c)) for c in uv[j + 1])
            cv2.line(img, o, e, colour, thickness, cv2.LINE_AA)
        cv2.circle(img, o, 3, (255, 255, 255), -1)
    return img


def contact_sheet(images: Sequence[np.ndarray], cols: int = 6, tile: int = 256) -> np.ndarray:
    """Images in a grid, each scaled to fit tile x tile; returns RGB uint8."""
    if not images:
        raise InvalidArgumentError("contact_sheet needs at least one image")
    rows = -(-len(images) // cols)
    h, w = images[0].shape[:2]
    s = tile / max(h, w)
    th, tw = round(h * s), round(w * s)
    sheet = np.zeros((rows * th, cols * tw, 3), np.uint8)
    for i, img in enumerate(images):
        r, c = divmod(i, cols)
        sheet[r * th : (r + 1) * th, c * tw : (c + 1) * tw] = cv2.resize(
            img, (tw, th), interpolation=cv2.INTER_AREA
        )
    return sheet
