"""The mask net's training windows: cut once around each object (its true visible mask's
window, jittered as a detector's box would be, or the window of a detector's own mask) and kept
in ``$POSEGRASP_DATA/masknet``, and the coarse masks drawn from the truth for each batch
(`degrade`), as a detector draws them."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch

from perception.detector import Detector
from perception.mask_net import MaskNetConfig, cut, window_of
from perception.training.data.dataset import PoseDataset
from perception.training.evals.masknet_eval import MIN_VISIBLE_PX, best_detection
from posegrasp.core.errors import AssetError
from posegrasp.core.files import sha256_file
from posegrasp.core.paths import data_root
from posegrasp.core.progress import progress_bar

#: `detector_windows` keeps its windows in blocks of this many images.
DETECTED_BLOCK = 10000

#: A detection counts as an object's (`detector_windows`) from this score and mask IoU with it.
DETECTED_SCORE = 0.3
DETECTED_IOU = 0.3


def _jittered_window(
    mask: np.ndarray, margin: float, rng: np.random.Generator, spread: float = 1.0
) -> tuple[int, int, int] | None:
    """`window_of` the mask, its centre moved by about `spread` x 5 % of its side and its side
    scaled by about `spread` x 8 % at random (a detector's box is a little off)."""
    win = window_of(mask, margin)
    if win is None:
        return None
    x0, y0, side = win
    new = max(8, round(side * math.exp(rng.normal(0, 0.08 * spread))))
    dx, dy = rng.normal(0, 0.05 * spread * side, 2)
    return (
        round(x0 + (side - new) / 2 + dx),
        round(y0 + (side - new) / 2 + dy),
        new,
    )


def _kept(name: str) -> dict[str, np.ndarray] | None:
    """The windows kept as ``$POSEGRASP_DATA/masknet/<name>.npz``, None when not kept yet."""
    path = data_root() / "masknet" / f"{name}.npz"
    if not path.is_file():
        return None
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def _keep(name: str, cache: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Write `cache` as `_kept` reads it (whole or not at all) and return it."""
    path = data_root() / "masknet" / f"{name}.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **cast("dict[str, Any]", cache))  # NumPy: a key could be allow_pickle
    tmp.replace(path)
    return cache


def _split(root: Path, split: str) -> PoseDataset:
    """The rendered split under `root`.

    Raises:
        AssetError: it is missing (the message names ``make data``).
    """
    try:
        return PoseDataset(root, split)
    except (OSError, KeyError, ValueError) as exc:
        raise AssetError(
            f"no {split} split in {root} ({exc}); render it with `make data`"
        ) from None


def build_cache(
    folder: str, split: str, images: int, net: MaskNetConfig, seed: int, spread: float = 1.0
) -> dict[str, np.ndarray]:
    """The windows of the first `images` images of a split (jittered by `spread`,
    `_jittered_window`), cut once and kept in ``$POSEGRASP_DATA/masknet``: ``rgb`` (N, S, S, 3)
    uint8, ``target`` (N, S, S) uint8 (the true visible mask's coverage of each pixel, 0-255)
    and ``cls`` (N,) the class names.

    Raises:
        AssetError: the split is missing (the message names ``make data``).
    """
    root = data_root() / folder
    S = net.size
    name = f"{folder}_{split}_{images}_{S}_{net.margin}_{seed}" + (
        f"_{spread}" if spread != 1 else ""
    )
    if (kept := _kept(name)) is not None:
        return kept
    data = _split(root, split)
    n = min(images, len(data))
    rgbs, targets, names = [], [], []
    for i in progress_bar(range(n), desc=f"windows of {folder}/{split}", mininterval=5):
        sample = data[i]
        rng = np.random.default_rng([seed, i])
        for obj in sample.objects:
            if int(obj.mask_visib.sum()) < MIN_VISIBLE_PX:
                continue
            win = _jittered_window(obj.mask_visib, net.margin, rng, spread)
            assert win is not None
            rgbs.append(cut(sample.rgb, win, S))
            cover = cut(obj.mask_visib.astype(np.float32), win, S)
            targets.append(np.round(cover * 255).astype(np.uint8))
            names.append(obj.name)
    cache = {"rgb": np.stack(rgbs), "target": np.stack(targets), "cls": np.array(names)}
    return _keep(name, cache)


def detector_windows(
    folder: str,
    split: str,
    first: int,
    images: int,
    net: MaskNetConfig,
    detector_path: Path | None,
) -> dict[str, np.ndarray]:
    """Windows of images ``first .. first + images - 1`` of a split as the estimator cuts them:
    around the mask of the detector's detection of each visible object (the same class, score
    >= `DETECTED_SCORE`, the largest mask IoU with the truth, at least `DETECTED_IOU`), with
    that mask as the coarse input. Kept in ``$POSEGRASP_DATA/masknet`` as `build_cache`'s, with
    ``coarse`` (N, S, S) uint8 in {0, 1}, in blocks of `DETECTED_BLOCK` images from `first`: a
    longer run reuses the blocks of a shorter one, and an interrupted one keeps the blocks it
    finished. Objects the detector misses give no window.

    Raises:
        AssetError: the split is missing (the message names ``make data``), the detector's
            weights are, or the detector found no object at all.
    """
    from perception.detector import TIERS_DETECTOR

    path_of_detector = detector_path or TIERS_DETECTOR
    tag = sha256_file(path_of_detector)[:12] if path_of_detector.is_file() else "missing"
    data = _split(data_root() / folder, split)
    last = min(first + images, len(data))
    detector, desc = None, f"detections of {folder}/{split}"
    blocks = []
    for start in range(first, last, DETECTED_BLOCK):
        images_here = range(start, min(start + DETECTED_BLOCK, last))
        name = f"{folder}_{split}_{start}+{len(images_here)}_{net.size}_{net.margin}_detected_{tag}"
        if (kept := _kept(name)) is None:
            detector = detector or Detector.from_weights(path_of_detector)
            kept = _keep(name, _detected_block(data, images_here, net, detector, desc))
        blocks.append(kept)
    out = {k: np.concatenate([b[k] for b in blocks]) for k in blocks[0]} if blocks else {}
    if not out or not len(out["cls"]):
        raise AssetError(f"the detector found no object in {folder}/{split} {first}+{images}")
    return out


def _detected_block(
    data: PoseDataset, images: range, net: MaskNetConfig, detector: Detector, desc: str
) -> dict[str, np.ndarray]:
    """`detector_windows` of the `images` of `data` (empty arrays when the detector finds none
    of their objects)."""
    S = net.size
    rgbs, coarse, targets, names = [], [], [], []
    for i in progress_bar(images, desc=desc, mininterval=5):
        sample = data[i]
        dets = detector.detect(sample.rgb, DETECTED_SCORE)
        for obj in sample.objects:
            truth = obj.mask_visib
            if int(truth.sum()) < MIN_VISIBLE_PX:
                continue
            best, _ = best_detection(dets, obj.name, truth, DETECTED_IOU)
            win = None if best is None else window_of(best.mask, net.margin)
            if win is None:
                continue
            assert best is not None  # win is None when best is
            rgbs.append(cut(sample.rgb, win, S))
            coarse.append((cut(best.mask.astype(np.float32), win, S) >= 0.5).astype(np.uint8))
            cover = cut(truth.astype(np.float32), win, S)
            targets.append(np.round(cover * 255).astype(np.uint8))
            names.append(obj.name)
    return {
        "rgb": np.asarray(rgbs, np.uint8).reshape(-1, S, S, 3),
        "coarse": np.asarray(coarse, np.uint8).reshape(-1, S, S),
        "target": np.asarray(targets, np.uint8).reshape(-1, S, S),
        "cls": np.array(names, dtype=str),
    }


def _lose_and_gain(coarse: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """Coarse masks (B, 1, S, S) with, each with probability one half, a disc cut out of the
    object and a disc of background added beside it: centred 0.5-1.3 of the object's radius
    (that of a disc of its area) from its centre, in a random direction, with a radius of
    0.3-0.8 of it."""
    B, _, S, _ = coarse.shape
    yy, xx = torch.meshgrid(torch.arange(S).float(), torch.arange(S).float(), indexing="ij")
    draws = torch.rand(B, 2, 4, generator=g)
    out = coarse.clone()
    for b in range(B):
        pixels = out[b, 0].nonzero().float()
        if len(pixels) == 0:
            continue
        cy, cx = pixels.mean(0)
        extent = math.sqrt(len(pixels) / math.pi)
        for k, cut_out in enumerate((True, False)):
            on, turn, away, size = (float(v) for v in draws[b, k])
            if on < 0.5:
                continue
            angle, dist = 2 * math.pi * turn, extent * (0.5 + 0.8 * away)
            y, x = cy + dist * math.sin(angle), cx + dist * math.cos(angle)
            disc = (yy - y) ** 2 + (xx - x) ** 2 <= (extent * (0.3 + 0.5 * size)) ** 2
            out[b, 0] = out[b, 0] * ~disc if cut_out else torch.maximum(out[b, 0], disc.float())
    return out


def degrade(target: torch.Tensor, g: torch.Generator, heavy: bool = False) -> torch.Tensor:
    """Coarse masks (B, S, S) in {0, 1} drawn from true coverages (B, S, S) in [0, 1], as the
    detector draws them: averaged onto a grid of 10-32 cells across the window and drawn back
    bilinearly, thresholded at 0.35-0.65, thin parts opened away (kernel 1, 3 or 5 px) in half
    of them, shifted by up to 2 px. With `heavy`, whole parts are also lost and gained
    (`_lose_and_gain`) before the shift, which goes up to 4 px."""
    B, S, _ = target.shape
    x = target[:, None].float()
    out = torch.empty_like(x)
    groups = torch.randint(0, 4, (B,), generator=g)
    for k in range(4):  # a few grid sizes per batch
        idx = (groups == k).nonzero()[:, 0]
        if len(idx) == 0:
            continue
        cells = int(torch.randint(10, 33, (1,), generator=g))
        low = torch.nn.functional.adaptive_avg_pool2d(x[idx], cells)
        out[idx] = torch.nn.functional.interpolate(
            low, size=(S, S), mode="bilinear", align_corners=False
        )
    level = 0.35 + 0.3 * torch.rand(B, 1, 1, 1, generator=g)
    coarse = (out >= level).float()
    opened = torch.rand(B, generator=g) < 0.5
    kernel = int(torch.randint(0, 3, (1,), generator=g)) * 2 + 1
    if kernel > 1 and opened.any():
        pad = kernel // 2
        sub = coarse[opened]
        eroded = -torch.nn.functional.max_pool2d(-sub, kernel, 1, pad)
        coarse[opened] = torch.nn.functional.max_pool2d(eroded, kernel, 1, pad)
    if heavy:
        coarse = _lose_and_gain(coarse, g)
    reach = 4 if heavy else 2
    dx, dy = (int(v) for v in torch.randint(-reach, reach + 1, (2,), generator=g))
    return torch.roll(coarse[:, 0], shifts=(dy, dx), dims=(1, 2))
