"""The pose nets' crops of a split and their labels (docs/DESIGN.md §7).

Crops are cut with the paper's imprecise boxes (random shift and scale of the visible box),
several per object instance, and cached next to the data (``crops_*.npz``); the test evaluation
cuts them the same way with its own `CropConfig`, or collects crops around detector boxes with a
`CropSet`.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np

from perception.crops import crop_and_resize, image_to_crop, random_square_box, to_unit
from perception.geometry import encode
from perception.nets import CROP
from perception.training.data.dataset import PoseDataset, load_info
from posegrasp.core.errors import AssetError
from posegrasp.core.paths import data_root
from posegrasp.core.progress import progress_bar


@dataclass(frozen=True)
class CropConfig:
    """How crops are cut from a split.

    Attributes:
        per_object: crops per annotated object instance (each with its own random box).
        max_shift: random shift of the box centre, as a fraction of its side.
        scale_range: random scale of the square box side relative to the box's longer side.
        min_visib: instances less visible than this are skipped.
        seed: seed of the random boxes.
        size: side the crops are resampled to [px] (the nets' input; 64 as in the paper).
    """

    per_object: int = 2
    max_shift: float = 0.1
    scale_range: tuple[float, float] = (0.95, 1.35)
    min_visib: float = 0.5
    seed: int = 0
    size: int = CROP


def data_seed_ranges(
    dists: Sequence[str], limits: dict[str, int] | None = None
) -> dict[str, dict[str, list[int]]]:
    """Seed range [first, end) of every generated split of each distribution, from its
    info.json: dist -> split -> range. `limits` (dist -> images) shortens the ranges to the first
    images of each split, as training with that limit uses them."""
    out: dict[str, dict[str, list[int]]] = {}
    for d in dists:
        splits = load_info(data_root() / d).get("splits", {})
        out[d] = {}
        for s, v in splits.items():
            if "seed_range" not in v:
                continue
            first, end = v["seed_range"]
            if limits and d in limits:
                end = min(end, first + limits[d])
            out[d][s] = [first, end]
    return out


class CropSet:
    """Crops of annotated objects and their labels, collected one at a time."""

    KEYS = ("crops", "cls", "uv_unit", "p", "theta", "scale", "box", "K", "T_C_O", "uv")

    def __init__(self, size: int = CROP) -> None:
        self.size = size
        self.rows: dict[str, list] = {k: [] for k in self.KEYS}

    def add(self, rgb: np.ndarray, K: np.ndarray, obj, box: tuple[float, float, float]) -> None:
        """Cut the square `box` (x0, y0, side) of `rgb` around annotated object `obj`."""
        p, theta, uv = encode(obj.T_C_O, K)
        r = self.rows
        r["crops"].append(crop_and_resize(rgb, box, self.size))
        r["cls"].append(obj.obj_id - 1)
        r["uv_unit"].append(to_unit(image_to_crop(uv, box, self.size), self.size))
        r["p"].append(p)
        r["theta"].append(theta)
        r["scale"].append(box[2] / K[0, 0])
        r["box"].append(np.asarray(box, float))
        r["K"].append(K)
        r["T_C_O"].append(obj.T_C_O)
        r["uv"].append(uv)

    def arrays(self) -> dict[str, np.ndarray]:
        """The layout `build_crops` returns (empty arrays of the right shapes when no crop)."""
        r = self.rows
        return {
            "crops": np.asarray(r["crops"], np.uint8).reshape(-1, self.size, self.size, 3),
            "cls": np.asarray(r["cls"], np.int64),
            "uv_unit": np.asarray(r["uv_unit"], np.float32).reshape(-1, 2),
            "p": np.asarray(r["p"], np.float32).reshape(-1, 3),
            "theta": np.asarray(r["theta"], np.float32),
            "scale": np.asarray(r["scale"], np.float32),
            "box": np.asarray(r["box"], np.float64).reshape(-1, 3),
            "K": np.asarray(r["K"], np.float64).reshape(-1, 3, 3),
            "T_C_O": np.asarray(r["T_C_O"], np.float64).reshape(-1, 4, 4),
            "uv": np.asarray(r["uv"], np.float64).reshape(-1, 2),
        }


def random_boxes(ds: PoseDataset, cfg: CropConfig, n: int, start: int = 0):
    """(sample, object, square box) of every crop `build_crops` cuts from the first n images of
    ds, in its order, with its seeded random boxes (a progress bar shows the images). Images
    before `start` only advance the random stream (their labels are read, not their pixels), so
    the crops from `start` on are those a run from image 0 cuts there."""
    rng = np.random.default_rng([cfg.seed, ("train", "val", "test").index(ds.split)])
    for i in progress_bar(range(n), desc=f"crops {ds.root.name}/{ds.split}", leave=False):
        boxes = [
            (k, random_square_box(box_xyxy, rng, cfg.max_shift, cfg.scale_range))
            for k, (visib, depth, box_xyxy) in enumerate(ds.crop_labels(i))
            if visib >= cfg.min_visib and depth > 0
            for _ in range(cfg.per_object)
        ]
        if i < start or not boxes:
            continue
        s = ds[i]
        for k, box in boxes:
            yield s, s.objects[k], box


def _cache_name(split: str, cfg: CropConfig, n: str) -> str:
    """File name of the crop cache of the first n images (n: a number, or a regex group)."""
    side = "" if cfg.size == CROP else f"_s{cfg.size}"
    return f"crops_{split}_{cfg.per_object}_{cfg.seed}_{n}{side}.npz"


def _cache_path(root: Path, split: str, cfg: CropConfig, n: int) -> Path:
    return root / _cache_name(split, cfg, str(n))


def _load_cache(cache: Path) -> dict:
    try:
        with np.load(cache) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise AssetError(f"corrupt crop cache {cache}: {exc}; delete it to rebuild") from exc


def _largest_prefix(root: Path, split: str, cfg: CropConfig, n: int) -> int:
    """The most images (< n) a cached crop set of the same config was cut from (0: none)."""
    name = re.compile(_cache_name(split, cfg, "(\\d+)").replace(".npz", "\\.npz"))
    sizes = [int(m[1]) for p in root.glob("crops_*.npz") if (m := name.fullmatch(p.name))]
    return max((k for k in sizes if k < n), default=0)


def build_crops(root: Path, split: str, cfg: CropConfig, limit: int | None = None) -> dict:
    """Cut (or load cached) training crops and labels of one split of one dataset.

    A cache of the first m < n images of the same config is extended rather than cut again:
    the crops are identical to a build from scratch.

    Returns:
        dict of arrays: crops (N, S, S, 3) uint8 (S = cfg.size), cls (N,), uv_unit (N, 2), p (N, 3),
        theta (N,), scale (N,) = side / f, box (N, 3) square boxes (x0, y0, side), K (N, 3, 3),
        T_C_O (N, 4, 4), uv (N, 2) true origin pixel.
    """
    ds = PoseDataset(root, split)
    n = len(ds) if limit is None else min(limit, len(ds))
    cache = _cache_path(root, split, cfg, n)
    if cache.is_file():
        return _load_cache(cache)
    m = _largest_prefix(root, split, cfg, n)
    out = CropSet(cfg.size)
    for sample, obj, box in random_boxes(ds, cfg, n, start=m):
        out.add(sample.rgb, sample.K, obj, box)
    arrays = out.arrays()
    if m:
        arrays = concat([_load_cache(_cache_path(root, split, cfg, m)), arrays])
    tmp = cache.with_suffix(".tmp.npz")
    np.savez(tmp, **cast("dict[str, Any]", arrays))  # NumPy: a key could be allow_pickle
    tmp.replace(cache)
    return arrays


def split_crops(
    dists: tuple[str, ...], split: str, cfg: CropConfig, limits: dict[str, int | None]
) -> dict:
    """The crops of `split` of each distribution in `dists` (`build_crops`, with at most
    limits[dist] images; None: all), concatenated."""
    parts = []
    for d in dists:
        root = data_root() / d
        if not (root / split).is_dir():
            raise AssetError(
                f"no {d} {split} data under {root}; build it with "
                f"`python -m perception.training.datagen --dist {d} --split {split} --count N` "
                "(or `make data`)"
            )
        parts.append(build_crops(root, split, cfg, limits.get(d)))
    return concat(parts)


def concat(parts: list[dict]) -> dict:
    """Concatenate crop dicts."""
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
