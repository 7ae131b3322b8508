"""Sharper visible masks: a small U-Net redraws the detector's mask of one object at the image's
full resolution.

The detector (`perception.detector`) works on the image at half resolution and draws each mask
on a 28 x 28 grid over its box, so an object 60 px wide loses its thin parts (a chair's legs, a
faucet's spout) and its outline is a pixel or two off. Render-and-compare fits the pose to that
outline; along the viewing ray a pixel is a few per cent of the distance. This net sees the
full-resolution window around the mask (`window_of`), the image and the detector's mask in it,
and gives the object's visible mask in that window (docs/DESIGN.md §7, "Mask refinement").

It is trained on rendered scenes alone (`perception.training.train_masknet`): the coarse input
is the true visible mask degraded as the detector degrades it (drawn on a coarse grid, thin
parts opened away, shifted), so no detector runs while training.

    refiner = MaskRefiner.from_weights()
    sharp = refiner.refine(rgb, detection.mask, detection.name)
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch import nn

from perception.integrity import load_checked
from perception.overlay import mask_box
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.paths import WEIGHTS_DIR

DEFAULT_MASKNET = WEIGHTS_DIR / "tiers" / "masknet.pt"
#: `DEFAULT_MASKNET` trained further on windows of scenes in rooms drawn for training, for
#: ``hybrid-global-rooms``.
ROOMS_MASKNET = WEIGHTS_DIR / "rooms" / "masknet.pt"
#: `ROOMS_MASKNET` trained further on windows of bank scenes (meshes of every shape, none of the
#: six built-in objects), for ``hybrid-global-unseen``, which redraws any target's mask with it.
UNSEEN_MASKNET = WEIGHTS_DIR / "unseen" / "masknet.pt"
#: The mask net of the paper's protocol (256x256 studio images on random backgrounds), trained on
#: those images with the larger errors of that protocol's detector.
PAPER_MASKNET = WEIGHTS_DIR / "paper_protocol" / "masknet.pt"
#: Objects whose paper-protocol masks a later stage of the net redraws better than the protocol's
#: net does (`expert_path`; chosen on the protocol's validation images, docs/RESULTS.md).
PAPER_MASKNET_EXPERTS: tuple[str, ...] = ("faucet",)
REBUILD_HINT = (
    "rebuild it with `make weights` (or `python -m perception.training.train_masknet --export`)"
)
#: The image's normalisation (ImageNet's mean and spread, as the detector's).
RGB_MEAN = (0.485, 0.456, 0.406)
RGB_STD = (0.229, 0.224, 0.225)


@dataclass(frozen=True)
class MaskNetConfig:
    """The net and its window.

    Attributes:
        size: the window is resampled to size x size pixels.
        widths: channels of each level of the U-Net (each level halves the resolution).
        margin: the window is the mask's box, squared, grown by this fraction of its side on
            each side.
    """

    size: int = 96
    widths: tuple[int, ...] = (16, 32, 64, 128)
    margin: float = 0.25

    def __post_init__(self) -> None:
        levels = len(self.widths)
        if levels < 2 or any(int(w) < 1 for w in self.widths):
            raise InvalidArgumentError("MaskNetConfig.widths needs >= 2 positive widths")
        if self.size < 8 or self.size % (2 ** (levels - 1)):
            raise InvalidArgumentError(
                f"MaskNetConfig.size must be >= 8 and divisible by {2 ** (levels - 1)}"
            )
        if not 0 <= self.margin <= 2:
            raise InvalidArgumentError("MaskNetConfig.margin must lie in [0, 2]")

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> MaskNetConfig:
        return cls(int(d["size"]), tuple(int(w) for w in d["widths"]), float(d["margin"]))


def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


class MaskNet(nn.Module):
    """U-Net: (B, 4, S, S) image (normalised RGB) and coarse mask (in [-1, 1]) -> (B, 1, S, S)
    logits of the visible mask."""

    def __init__(self, cfg: MaskNetConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg or MaskNetConfig()
        w = self.cfg.widths
        self.down = nn.ModuleList(
            [_block(4, w[0])] + [_block(a, b) for a, b in itertools.pairwise(w)]
        )
        self.up = nn.ModuleList(
            [nn.ConvTranspose2d(b, a, 2, stride=2) for a, b in itertools.pairwise(w)]
        )
        self.merge = nn.ModuleList([_block(2 * a, a) for a in w[:-1]])
        self.head = nn.Conv2d(w[0], 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = []
        for i, block in enumerate(self.down):
            x = block(x if i == 0 else nn.functional.max_pool2d(x, 2))
            skips.append(x)
        for i in reversed(range(len(self.up))):
            x = self.merge[i](torch.cat([skips[i], self.up[i](x)], 1))
        return self.head(x)


def window_of(mask: np.ndarray, margin: float) -> tuple[int, int, int] | None:
    """The square window (x0, y0, side) [px] around a mask's box, grown by `margin` of its side
    on each side (it may reach beyond the image); None for an empty mask."""
    box = mask_box(mask)
    if box is None:
        return None
    x0, y0, x1, y1 = box
    side = max(x1 - x0, y1 - y0)
    grown = max(8, round(side * (1 + 2 * margin)))
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    return round(cx - grown / 2), round(cy - grown / 2), grown


def _overlap(
    window: tuple[int, int, int], shape: tuple[int, ...]
) -> tuple[tuple[slice, slice], tuple[slice, slice]] | None:
    """Where a window (x0, y0, side) and an image of `shape` (H, W, ...) overlap: the image's
    and the window's slices of it, (rows, columns) each; None when they do not."""
    x0, y0, side = window
    u0, v0, u1, v1 = max(x0, 0), max(y0, 0), min(x0 + side, shape[1]), min(y0 + side, shape[0])
    if u1 <= u0 or v1 <= v0:
        return None
    image = (slice(v0, v1), slice(u0, u1))
    return image, (slice(v0 - y0, v1 - y0), slice(u0 - x0, u1 - x0))


def cut(img: np.ndarray, window: tuple[int, int, int], size: int) -> np.ndarray:
    """The window (x0, y0, side) of an image (H, W[, C]), zero beyond its edges, resampled to
    size x size (area averaging when shrinking, bilinear when enlarging)."""
    side = window[2]
    out = np.zeros((side, side, *img.shape[2:]), img.dtype)
    if (both := _overlap(window, img.shape)) is not None:
        out[both[1]] = img[both[0]]
    inter = cv2.INTER_AREA if side > size else cv2.INTER_LINEAR
    return cv2.resize(out, (size, size), interpolation=inter)


def paste(prob: np.ndarray, window: tuple[int, int, int], shape: tuple[int, int]) -> np.ndarray:
    """A window's (size, size) probabilities drawn back into an image of `shape` (H, W),
    bilinearly; zero outside the window."""
    side = window[2]
    big = cv2.resize(prob.astype(np.float32), (side, side), interpolation=cv2.INTER_LINEAR)
    out = np.zeros(shape, np.float32)
    if (both := _overlap(window, shape)) is not None:
        out[both[0]] = big[both[1]]
    return out


def net_input(rgb: np.ndarray, coarse: np.ndarray) -> torch.Tensor:
    """Windows (B, S, S, 3) uint8 and coarse masks (B, S, S) in [0, 1] -> the net's input
    (B, 4, S, S) float32."""
    x = torch.as_tensor(rgb).permute(0, 3, 1, 2).float().div_(255.0)
    mean = torch.tensor(RGB_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(RGB_STD).view(1, 3, 1, 1)
    m = torch.as_tensor(coarse, dtype=torch.float32)[:, None] * 2 - 1
    return torch.cat([(x - mean) / std, m], 1)


def expert_path(weights: Path, name: str) -> Path:
    """Where the net that serves object `name` alone lies beside the protocol's net `weights`:
    ``masknet_<name>.pt``."""
    return Path(weights).with_name(f"{Path(weights).stem}_{name}.pt")


class MaskRefiner:
    """A trained `MaskNet` applied to one detection's mask at a time.

    Args:
        net: the net (put in eval mode here).
        threshold: a pixel is in the mask when its probability is at least this.
        experts: refiners that redraw the masks of the objects they are keyed by instead
            (`expert_path`).
    """

    def __init__(
        self,
        net: MaskNet,
        threshold: float = 0.5,
        experts: dict[str, MaskRefiner] | None = None,
    ) -> None:
        if not 0 < threshold < 1:
            raise InvalidArgumentError(f"threshold must lie in (0, 1), got {threshold}")
        self.net = net.eval()
        self.cfg = net.cfg
        self.threshold = float(threshold)
        self.experts = dict(experts or {})

    @classmethod
    def from_weights(
        cls, path: Path = DEFAULT_MASKNET, verify: bool = True, experts: tuple[str, ...] = ()
    ) -> MaskRefiner:
        """The net stored at `path`, with the nets of the `experts` objects beside it
        (`expert_path`); each file's hash is checked against its folder's manifest unless
        `verify` is False.

        Raises:
            AssetError: a file is missing or corrupt, with the command that rebuilds it.
        """

        def build(state: dict) -> MaskNet:
            net = MaskNet(MaskNetConfig.from_dict(state["model_config"]))
            net.load_state_dict({k: v.float() for k, v in state["model"].items()})
            return net

        def load(p: Path) -> MaskNet:
            return load_checked(p, verify, build, "mask net weights", REBUILD_HINT)

        own = {name: cls(load(expert_path(path, name))) for name in experts}
        return cls(load(Path(path)), experts=own)

    @torch.inference_mode()
    def refine(self, rgb: np.ndarray, mask: np.ndarray, name: str | None = None) -> np.ndarray:
        """The object's visible mask, redrawn from the detector's `mask` (H, W) bool and the
        image `rgb` (H, W, 3) uint8 (by the net of object `name` when there is one); an empty
        mask comes back as it is.

        Raises:
            InvalidArgumentError: arrays of the wrong shape or type.
        """
        if name in self.experts:
            return self.experts[name].refine(rgb, mask)
        rgb, mask = np.asarray(rgb), np.asarray(mask)
        if mask.ndim != 2 or mask.dtype != bool or rgb.shape != (*mask.shape, 3):
            raise InvalidArgumentError(
                f"need an (H, W) bool mask and an (H, W, 3) image, got {mask.shape} "
                f"{mask.dtype} and {rgb.shape}"
            )
        if rgb.dtype != np.uint8:
            raise InvalidArgumentError(f"rgb must be uint8, got {rgb.dtype}")
        window = window_of(mask, self.cfg.margin)
        if window is None:
            return mask.copy()
        S = self.cfg.size
        x = net_input(cut(rgb, window, S)[None], cut(mask.astype(np.float32), window, S)[None])
        prob = torch.sigmoid(self.net(x))[0, 0].numpy()
        return paste(prob, window, mask.shape) >= self.threshold
