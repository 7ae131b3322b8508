"""The detector's training images and targets, and their photometric augmentation.

Targets come from the *visible* masks (docs/DESIGN.md §7): boxes enclose
them (`perception.training.data.bop.box_xyxy`), labels are BOP object ids. Augmentation is
photometric only: no flips, since some objects are chiral (the faucet's spout, the pistol's grip).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from perception.detector import image_tensor, load_detector_model, to_model_box
from perception.detector_net import DetectorConfig, input_transform
from perception.training.data.bop import box_xyxy
from perception.training.data.dataset import PoseDataset, load_info
from perception.training.trainers.ddp import Ranks
from posegrasp.core.errors import AssetError, InvalidArgumentError
from posegrasp.core.paths import data_root


class DetectionSet(torch.utils.data.Dataset):
    """Images of one split with Mask R-CNN targets from the visible masks.

    An item is ``(image, target)`` already scaled to the model's input size as the model's own
    transform would (`input_transform`), so that the work happens in the loading process:
    image (3, h, w) float32 in [0, 1], target a dict with ``boxes`` (N, 4) float32 in
    torchvision's pixel convention, ``labels`` (N,) int64, the objects' places in
    `DetectorConfig.classes` counted from 1 (for the built-in objects their BOP object ids;
    `DetectorConfig.label`), and
    ``masks`` (N, h, w) uint8. Instances with fewer than `min_visible_px` visible pixels (at full
    resolution), and objects not among the classes, are left out (N may be 0: a negative
    image).
    """

    def __init__(
        self,
        root: Path,
        split: str,
        min_visible_px: int,
        cfg: DetectorConfig,
        limit: int | None = None,
    ) -> None:
        self.data = PoseDataset(root, split)
        self.n = len(self.data) if limit is None else min(limit, len(self.data))
        self.min_visible_px = min_visible_px
        self.cfg = cfg
        self.transform = input_transform(cfg)

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        s = self.data[i]
        keep = [
            o
            for o in s.objects
            if self.cfg.label(o.name) is not None and int(o.mask_visib.sum()) >= self.min_visible_px
        ]
        h, w = s.rgb.shape[:2]
        boxes = np.array([to_model_box(box_xyxy(o.mask_visib)) for o in keep]).reshape(-1, 4)
        masks = np.array([o.mask_visib for o in keep], np.uint8).reshape(-1, h, w)
        target = {
            "boxes": torch.from_numpy(boxes).float(),
            "labels": torch.tensor([self.cfg.label(o.name) for o in keep], dtype=torch.int64),
            "masks": torch.from_numpy(masks),
        }
        return self.transform.resize(image_tensor(s.rgb), target)


def collate_list(batch: list) -> list:
    """A batch as the list of its ``(image, target)`` items (images differ in size)."""
    return batch


def augment(x: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """Photometric jitter of one (3, H, W) image in [0, 1]: brightness, contrast, saturation,
    per-channel gain and pixel noise. Geometry is untouched (no flips: some objects are chiral).
    """
    r = torch.rand(6, generator=g)
    grey = x.mean(dim=0, keepdim=True)
    x = grey + (x - grey) * (0.6 + 0.8 * r[0])  # saturation
    x = (x - x.mean()) * (0.7 + 0.6 * r[1]) + x.mean()  # contrast
    x = x * (0.9 + 0.2 * torch.rand(3, 1, 1, generator=g)) + (r[2] - 0.5) * 0.2  # gain, bright
    x = x + torch.randn(x.shape, generator=g) * (0.03 * r[3])  # noise
    return x.clamp(0.0, 1.0)


def augment_shard(images: list[torch.Tensor], g: torch.Generator, ranks: Ranks) -> list:
    """This rank's images jittered as in one process: the jitter of every image of the global
    batch is drawn in order (those of other ranks' images, of the same size, are dropped)."""
    out = []
    for j in range(len(images) * ranks.world):
        x = augment(images[j // ranks.world], g)
        if j % ranks.world == ranks.rank:
            out.append(x.to(ranks.device))
    return out


def training_images(
    root: Path,
    also: tuple[str, ...],
    min_visible_px: int,
    cfg: DetectorConfig,
    limits: tuple[int | None, ...],
) -> tuple[DetectionSet | torch.utils.data.ConcatDataset[Any], list[DetectionSet]]:
    """The train images of root and of the dataset folders `also` (under the data root), at
    most `limits[i]` of the i-th of them (None: all): (the mix, its parts).

    Raises:
        AssetError: a folder without a train split.
        InvalidArgumentError: a folder's train split rendered for objects `cfg` has no class
            for (`DetectionSet` would leave every one of them out, silently).
    """
    _check_classes(root, cfg)
    parts = [DetectionSet(root, "train", min_visible_px, cfg, limits[0])]
    for name, limit in zip(also, limits[1:], strict=True):
        extra = data_root() / name
        if not (extra / "train").is_dir():
            raise AssetError(
                f"no train split under {extra}; build it with `python -m "
                "perception.training.datagen` (see its --dist and --tier)"
            )
        _check_classes(extra, cfg)
        parts.append(DetectionSet(extra, "train", min_visible_px, cfg, limit))
    return (parts[0] if len(parts) == 1 else torch.utils.data.ConcatDataset(parts)), parts


def _check_classes(folder: Path, cfg: DetectorConfig) -> None:
    """Raise `InvalidArgumentError` when the train split of `folder` was rendered for objects
    (its info's ``objects``: the targets asked for) that `cfg` has no class for."""
    split = load_info(folder).get("splits", {}).get("train", {})
    unknown = sorted({n for n in split.get("objects", []) if cfg.label(n) is None})
    if unknown:
        names = ",".join(unknown)
        raise InvalidArgumentError(
            f"the training images under {folder} were rendered for {names}, which the detector "
            f"has no class for (its classes: {', '.join(cfg.classes)}); give --objects "
            f"{names} to add them, or --any-object"
        )


def start_from(model: torch.nn.Module, path: Path, cfg: DetectorConfig) -> None:
    """Load the weights of a shipped detector or a detector checkpoint into model (float32).

    A detector of more classes starts from its first classes' heads; a detector of any object
    (`ANY_OBJECT`) from a detector of named classes takes everything but the per-class layers
    (scores, box offsets and mask logits), which start afresh.

    Raises:
        AssetError: the file is missing or corrupt, or holds another architecture.
    """
    parent, parent_cfg, _ = load_detector_model(Path(path), verify=False)
    n = len(parent_cfg.classes)
    anew = cfg.any_object and not parent_cfg.any_object
    if anew:
        same = replace(cfg, classes=parent_cfg.classes, n_classes=parent_cfg.n_classes)
    else:
        same = replace(cfg, classes=cfg.classes[:n], n_classes=1 + n)
    if parent_cfg != same or (not anew and cfg.classes[:n] != parent_cfg.classes):
        raise AssetError(f"{path} holds another detector architecture than this run's")
    state = model.state_dict()
    for k, v in parent.state_dict().items():
        v = v.float() if v.is_floating_point() else v
        if v.shape != state[k].shape and anew:  # a per-class layer: left as initialised
            continue
        if v.shape != state[k].shape:  # a class head widened for new classes: its first rows
            rows = v.shape[0]
            v = torch.cat([v, state[k][rows:]]) if v.shape[1:] == state[k].shape[1:] else None
            if v is None:
                raise AssetError(f"{path}: {k} does not fit this run's detector")
        state[k] = v
    model.load_state_dict(state)
