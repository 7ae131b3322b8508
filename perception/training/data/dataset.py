"""Reading the on-disk pose dataset: validating loaders of one split's images and annotations.

The layout, units and file formats are those of `perception.training.data.bop` (BOP layout, BOP
files in millimetres); everything the loaders here return is in metres (docs/DESIGN.md §4), with
pixel (0, 0) centred at (0, 0).

A sample is complete when its record file exists (it is written last, by atomic rename); the
scene files are merged from the records. `load_sample` checks every file it reads and raises
`AssetError` naming the file and the command that rebuilds the split.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from perception.training.data.bop import (
    SCENE_FILES,
    mask_path,
    obj_name,
    pose_from_bop,
    read_json,
    read_png,
    rebuild_hint,
    rgb_path,
    scene_dir,
    split_index,
)
from perception.training.data.rooms import FAMILIES, folder_suffix
from posegrasp.core.errors import AssetError, InvalidArgumentError, UnknownNameError
from posegrasp.world.tiers import TIERS

SPLITS: tuple[str, ...] = ("train", "val", "test")
DISTS: tuple[str, ...] = ("paper", "headcam")
#: Dataset folders under the data root: each distribution's, the head camera's per scene tier
#: (``headcam_<tier>``, made by ``datagen --dist headcam --tier <tier>``), and the head camera's
#: in rooms drawn for training (``..._rooms`` and ``..._rooms_<family>``, ``datagen --rooms``), and
#: the head camera's scenes of a bank's meshes (``headcam_bank[_held-out|_shapes][_rooms...]``,
#: ``datagen --bank``).
_HEADCAM: tuple[str, ...] = ("headcam", *(f"headcam_{t}" for t in TIERS))
DATASETS: tuple[str, ...] = (
    *DISTS,
    *_HEADCAM[1:],
    *(d + folder_suffix(f) for f in FAMILIES for d in _HEADCAM),
    *(
        bank + suffix
        for bank in ("headcam_bank", "headcam_bank_held-out", "headcam_bank_shapes")
        for suffix in ("", *(folder_suffix(f) for f in FAMILIES))
    ),
)


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

    def _annotations(self, scene_id: int, im_id: int) -> tuple[list, np.ndarray, list, dict]:
        """The scene files' entries of one image, checked: (gt, K, gt_info, posegrasp)."""
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
                f"corrupt annotations of image {im_id} in "
                f"{scene_dir(self.root, self.split, scene_id)} ({exc!r}); "
                f"{rebuild_hint(self.root, self.split)}"
            ) from None
        return gts, K, infos, pg

    def crop_labels(self, i: int) -> list[tuple[float, float, np.ndarray]]:
        """(visible fraction, depth of the origin [m], visible box xyxy) of every object of image
        i, from the scene files alone: no image or mask is read."""
        gts, _, infos, pg = self._annotations(*self.index[i])
        return [
            (
                float(info["visib_fract"]),
                float(pose_from_bop(gt)[2, 3]),
                np.asarray(extra["box_xyxy"], float),
            )
            for gt, info, extra in zip(gts, infos, pg["objects"], strict=True)
        ]

    def load(self, scene_id: int, im_id: int) -> Sample:
        """Load and check one image and its annotations (metres)."""
        sdir = scene_dir(self.root, self.split, scene_id)
        gts, K, infos, pg = self._annotations(scene_id, im_id)
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


def parse_limit(text: str | None) -> tuple[int | None, tuple[tuple[str, int], ...]]:
    """`--limit`: "N" (every distribution) or "dist=N,..." -> (limit, dist_limits)."""
    if text is None:
        return None, ()
    limit, per = None, []
    for item in text.split(","):
        name, _, num = item.rpartition("=")
        if name and name not in DATASETS:
            raise InvalidArgumentError(
                f"unknown dataset {name!r} in --limit; valid: {', '.join(DATASETS)}"
            )
        if not num.isdigit() or int(num) < 1:
            raise InvalidArgumentError(f"--limit wants N or dist=N with N >= 1, got {item!r}")
        if name:
            per.append((name, int(num)))
        else:
            limit = int(num)
    return limit, tuple(per)


def parse_data(text: str, folder_first: bool = False) -> tuple[tuple[str, int | None], ...]:
    """`--data`, the trainers' one way to name their training images: "NAME[=COUNT],..." ->
    ((name, images or None for all), ...) in the order given.

    Args:
        text: the option's value.
        folder_first: the first NAME may also be a folder path (a dataset of one's own, not under
            the data root); the others are always dataset folders under the data root.

    Raises:
        InvalidArgumentError: an empty list, an unknown dataset, a name twice or a count < 1.
    """
    out: list[tuple[str, int | None]] = []
    for i, item in enumerate(text.split(",") if text else []):
        name, sep, num = item.rpartition("=")
        if not sep:
            name, num = item, ""
        if name not in DATASETS and not (folder_first and i == 0 and name):
            raise InvalidArgumentError(
                f"unknown dataset {name!r} in --data; valid: {', '.join(DATASETS)}"
            )
        if sep and (not num.isdigit() or int(num) < 1):
            raise InvalidArgumentError(f"--data wants NAME or NAME=N with N >= 1, got {item!r}")
        if name in (n for n, _ in out):
            raise InvalidArgumentError(f"invalid --data {text!r}: {name} twice")
        out.append((name, int(num) if sep else None))
    if not out:
        raise InvalidArgumentError("--data wants NAME[=N],... of: " + ", ".join(DATASETS))
    return tuple(out)


def format_data(data: tuple[tuple[str, int | None], ...]) -> str:
    """The `--data` value of `parse_data`'s pairs."""
    return ",".join(name if n is None else f"{name}={n}" for name, n in data)
