"""2D-NET and 4D-NET (docs/DESIGN.md §7) as one model: a shared convolutional backbone on the
64x64 crop, a 2D head for the object origin's position in the crop and a 4D head for the pose in
the virtual camera C', each with one output slice per object class.

Two variants:
- ``paper``: crop only, 4D output (p_x, p_y, p_z, theta), theta meant for -60..60 degrees.
- ``ours``: the crop's angular size ``s = side / f`` enters the 4D head, which predicts the
  direction of p, the scale-invariant distance ``log(|p| * s)`` and the roll as (cos, sin), so any
  roll works and distance no longer has to come from perspective cues alone.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from torch import nn

from perception.integrity import verify_weights
from sim.core.errors import AssetError, InvalidArgumentError, UnknownNameError

VARIANTS: tuple[str, ...] = ("paper", "ours")
CROP = 64


@dataclass(frozen=True)
class NetConfig:
    """Model configuration.

    Attributes:
        variant: "paper" or "ours".
        n_classes: number of object classes (one head slice each).
        width: channels of the first conv stage (the others have 2x and 4x).
        hidden: width of the fully connected layer.
        dropout: dropout before the heads.
    """

    variant: str = "ours"
    n_classes: int = 6
    width: int = 16
    hidden: int = 512
    dropout: float = 0.5

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise UnknownNameError("variant", self.variant, VARIANTS)

    def to_dict(self) -> dict:
        """Plain dict (stored in checkpoints)."""
        return asdict(self)


def _conv(i: int, o: int) -> list[nn.Module]:
    return [nn.Conv2d(i, o, 3, stride=1, padding=1, bias=False), nn.BatchNorm2d(o), nn.ReLU(True)]


@dataclass
class PoseOutput:
    """Decoded network outputs for a batch (one class each).

    Attributes:
        uv_unit: origin in the crop, normalised to [0, 1], (B, 2).
        p: position of C' in O [m], (B, 3).
        cs: roll as (cos, sin), (B, 2).
    """

    uv_unit: torch.Tensor
    p: torch.Tensor
    cs: torch.Tensor

    @property
    def theta(self) -> torch.Tensor:
        """Roll [rad], (B,)."""
        return torch.atan2(self.cs[:, 1], self.cs[:, 0])


class PoseNet(nn.Module):
    """Backbone (6 conv 3x3 stride 1 with BN/ReLU, 3 max-pools), FC, and the 2D and 4D heads."""

    def __init__(self, cfg: NetConfig) -> None:
        super().__init__()
        self.cfg = cfg
        w = cfg.width
        self.backbone = nn.Sequential(
            *_conv(3, w), *_conv(w, w), nn.MaxPool2d(2),
            *_conv(w, 2 * w), *_conv(2 * w, 2 * w), nn.MaxPool2d(2),
            *_conv(2 * w, 4 * w), *_conv(4 * w, 4 * w), nn.MaxPool2d(2),
            nn.Flatten(),
        )  # fmt: skip
        feat = 4 * w * (CROP // 8) ** 2
        extra = 1 if cfg.variant == "ours" else 0
        self.fc = nn.Sequential(
            nn.Linear(feat + extra, cfg.hidden), nn.ReLU(True), nn.Dropout(cfg.dropout)
        )
        self.head2d = nn.Linear(cfg.hidden, 2 * cfg.n_classes)
        self.k4 = 6 if cfg.variant == "ours" else 4
        self.head4d = nn.Linear(cfg.hidden + extra, self.k4 * cfg.n_classes)
        for m in self.modules():
            if isinstance(m, (nn.Linear, nn.Conv2d)):
                nn.init.xavier_uniform_(m.weight)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
        with torch.no_grad():
            # Small initial head outputs: predictions start near the biases below.
            self.head4d.weight.mul_(0.1)
            self.head2d.weight.mul_(0.1)
            b = self.head4d.bias.view(cfg.n_classes, self.k4)
            if cfg.variant == "ours":
                b[:, 3] = math.log(0.2)  # |p| * side / f is about the object's size
                b[:, 4] = 1.0  # cos(theta) = 1

    def forward(self, crops: torch.Tensor, cls: torch.Tensor, scale: torch.Tensor) -> PoseOutput:
        """Predict for a batch.

        Args:
            crops: (B, 3, 64, 64) float, normalised as `normalise` does.
            cls: (B,) class indices.
            scale: (B,) crop angular size side / f (used by "ours").
        """
        f = self.backbone(crops)
        if self.cfg.variant == "ours":
            ls = torch.log(scale).unsqueeze(1)
            h = self.fc(torch.cat([f, ls], dim=1))
            h4 = torch.cat([h, ls], dim=1)
        else:
            h = self.fc(f)
            h4 = h
        idx = torch.arange(len(cls), device=crops.device)
        o2 = self.head2d(h).view(-1, self.cfg.n_classes, 2)[idx, cls]
        o4 = self.head4d(h4).view(-1, self.cfg.n_classes, self.k4)[idx, cls]
        uv = torch.sigmoid(o2) * 1.5 - 0.25  # the origin may lie a little outside the crop
        if self.cfg.variant == "ours":
            d = o4[:, :3] / torch.linalg.norm(o4[:, :3], dim=1, keepdim=True).clamp_min(1e-6)
            dist = torch.exp(o4[:, 3].clamp(-6.0, 3.0)) / scale
            p = d * dist.unsqueeze(1)
            cs = o4[:, 4:6]
        else:
            p = o4[:, :3]
            cs = torch.stack([torch.cos(o4[:, 3]), torch.sin(o4[:, 3])], dim=1)
        return PoseOutput(uv, p, cs)


def normalise(crops_uint8: torch.Tensor) -> torch.Tensor:
    """(B, 64, 64, 3) uint8 -> (B, 3, 64, 64) float in [-0.5, 0.5]."""
    if (
        crops_uint8.dtype != torch.uint8
        or crops_uint8.ndim != 4
        or crops_uint8.shape[1:] != (CROP, CROP, 3)
    ):
        raise InvalidArgumentError(
            f"crops must be uint8 of shape (B, {CROP}, {CROP}, 3), got {crops_uint8.dtype} "
            f"{tuple(crops_uint8.shape)}"
        )
    return crops_uint8.permute(0, 3, 1, 2).float() / 255.0 - 0.5


def load_posenet(path: Path, verify: bool = True) -> PoseNet:
    """A trained PoseNet from a checkpoint or shipped weights file.

    Args:
        path: the weights file.
        verify: check the file against the hash its folder's manifest records
            (`perception.integrity.verify_weights`); False for weights you trained.

    Raises:
        AssetError: the file is missing or corrupt (the message says how to rebuild it).
        WeightsMismatchError: the manifest next to it records another hash.
    """
    hint = "rebuild it with `make weights` (or python -m perception.training.train_posenet)"
    path = Path(path)
    if not path.is_file():
        raise AssetError(f"weights file {path} is missing; {hint}")
    verify_weights(path, verify)
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
        model = PoseNet(NetConfig(**state["model_config"]))
        model.load_state_dict({k: v.float() for k, v in state["model"].items()})
    except Exception as exc:  # any unpickling or shape error means a bad file
        raise AssetError(f"weights file {path} is corrupt ({exc}); {hint}") from exc
    model.eval()
    return model
