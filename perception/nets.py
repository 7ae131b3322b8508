"""2D-NET and 4D-NET (docs/DESIGN.md §7) as one model: a shared convolutional backbone on the
64x64 crop, a 2D head for the object origin's position in the crop and a 4D head for the pose in
the virtual camera C', each with one output slice per object class.

Two variants:
- ``paper``: crop only, 4D output (p_x, p_y, p_z, theta), theta meant for -60..60 degrees.
- ``ours``: the crop's angular size ``s = side / f`` enters the 4D head, which predicts the
  direction of p, the scale-invariant distance ``log(|p| * s)`` and the roll as (cos, sin), so any
  roll works and distance no longer has to come from perspective cues alone. With
  ``rotation="6d"`` it predicts the rotation R_O_C' itself in the continuous 6D representation
  (two columns, Gram-Schmidt; Zhou et al., CVPR 2019) instead of direction and roll, whose roll
  reference turns abruptly where the view passes over the object's poles.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from torch import nn

from perception.geometry_torch import axes_from_p
from perception.integrity import load_checked
from posegrasp.core.errors import InvalidArgumentError, UnknownNameError

VARIANTS: tuple[str, ...] = ("paper", "ours")
#: Rotation outputs of "ours": viewpoint direction and roll, or the 6D representation.
ROTATIONS: tuple[str, ...] = ("view-roll", "6d")
CROP = 64


@dataclass(frozen=True)
class NetConfig:
    """Model configuration.

    Attributes:
        variant: "paper" or "ours".
        n_classes: number of object classes (one head slice each).
        width: channels of the first conv stage (the others have 2x and 4x).
        crop: side of the input crop [px], a multiple of 8 (the paper's is 64).
        rotation: "ours" rotation output, one of `ROTATIONS` ("paper" always has p and theta).
        hidden: width of the fully connected layer.
        dropout: dropout before the heads.
    """

    variant: str = "ours"
    n_classes: int = 6
    width: int = 16
    crop: int = CROP
    rotation: str = "view-roll"
    hidden: int = 512
    dropout: float = 0.5

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise UnknownNameError("variant", self.variant, VARIANTS)
        if not (isinstance(self.crop, int) and 16 <= self.crop <= 256 and self.crop % 8 == 0):
            raise InvalidArgumentError(f"crop must be a multiple of 8 in 16..256, got {self.crop}")
        if self.rotation not in ROTATIONS:
            raise UnknownNameError("rotation", self.rotation, ROTATIONS)
        if self.variant == "paper" and self.rotation != "view-roll":
            raise InvalidArgumentError(
                "the paper variant predicts p and theta (rotation view-roll)"
            )

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
            *_conv(3, w),
            *_conv(w, w),
            nn.MaxPool2d(2),
            *_conv(w, 2 * w),
            *_conv(2 * w, 2 * w),
            nn.MaxPool2d(2),
            *_conv(2 * w, 4 * w),
            *_conv(4 * w, 4 * w),
            nn.MaxPool2d(2),
            nn.Flatten(),
        )
        feat = 4 * w * (cfg.crop // 8) ** 2
        extra = 1 if cfg.variant == "ours" else 0
        self.fc = nn.Sequential(
            nn.Linear(feat + extra, cfg.hidden), nn.ReLU(True), nn.Dropout(cfg.dropout)
        )
        self.head2d = nn.Linear(cfg.hidden, 2 * cfg.n_classes)
        self.k4 = {"paper": 4, "ours": 7 if cfg.rotation == "6d" else 6}[cfg.variant]
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
            if cfg.rotation == "6d":
                # Columns x = (1, 0, 0), y = (0, 0, -1): a level view from -y, far from the
                # poles, where the roll's theta = 0 reference is singular.
                b[:, 0], b[:, 5] = 1.0, -1.0
                b[:, 6] = math.log(0.2)
            elif cfg.variant == "ours":
                b[:, 3] = math.log(0.2)  # |p| * side / f is about the object's size
                b[:, 4] = 1.0  # cos(theta) = 1

    def forward(self, crops: torch.Tensor, cls: torch.Tensor, scale: torch.Tensor) -> PoseOutput:
        """Predict for a batch.

        Args:
            crops: (B, 3, crop, crop) float, normalised as `normalise` does.
            cls: (B,) class indices.
            scale: (B,) crop angular size side / f (used by "ours").
        """
        if crops.shape[-2:] != (self.cfg.crop, self.cfg.crop):
            raise InvalidArgumentError(
                f"this net takes {self.cfg.crop}x{self.cfg.crop} crops, got "
                f"{tuple(crops.shape[-2:])}"
            )
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
        if self.cfg.rotation == "6d":
            p, cs = _from_6d(o4[:, :6], torch.exp(o4[:, 6].clamp(-6.0, 3.0)) / scale)
        elif self.cfg.variant == "ours":
            d = o4[:, :3] / torch.linalg.norm(o4[:, :3], dim=1, keepdim=True).clamp_min(1e-6)
            dist = torch.exp(o4[:, 3].clamp(-6.0, 3.0)) / scale
            p = d * dist.unsqueeze(1)
            cs = o4[:, 4:6]
        else:
            p = o4[:, :3]
            cs = torch.stack([torch.cos(o4[:, 3]), torch.sin(o4[:, 3])], dim=1)
        return PoseOutput(uv, p, cs)


def _from_6d(a: torch.Tensor, dist: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """p and the roll's (cos, sin) from 6D rotation outputs (B, 6) and distances (B,).

    R_O_C' = [b1 b2 b3] by Gram-Schmidt on the two predicted columns; the camera looks along b3
    at O's origin, so p = -dist * b3, and the roll is b1 seen in the theta = 0 axes of that p
    (`perception.geometry_torch.axes_from_p`, R_O_C' = [x y z] Rz(theta))."""
    b1 = a[:, :3] / torch.linalg.norm(a[:, :3], dim=1, keepdim=True).clamp_min(1e-6)
    a2 = a[:, 3:] - (b1 * a[:, 3:]).sum(1, keepdim=True) * b1
    b2 = a2 / torch.linalg.norm(a2, dim=1, keepdim=True).clamp_min(1e-6)
    b3 = torch.linalg.cross(b1, b2, dim=1)
    p = -b3 * dist.unsqueeze(1)
    x, y, _ = axes_from_p(p)
    return p, torch.stack([(x * b1).sum(1), (y * b1).sum(1)], dim=1)


def normalise(crops_uint8: torch.Tensor) -> torch.Tensor:
    """(B, S, S, 3) uint8 -> (B, 3, S, S) float in [-0.5, 0.5] (S: the crop side, 64 for the
    shipped nets)."""
    if (
        crops_uint8.dtype != torch.uint8
        or crops_uint8.ndim != 4
        or crops_uint8.shape[3] != 3
        or crops_uint8.shape[1] != crops_uint8.shape[2]
    ):
        raise InvalidArgumentError(
            f"crops must be uint8 of shape (B, S, S, 3), e.g. (B, {CROP}, {CROP}, 3), got "
            f"{crops_uint8.dtype} {tuple(crops_uint8.shape)}"
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

    def build(state: dict) -> PoseNet:
        model = PoseNet(NetConfig(**state["model_config"]))
        model.load_state_dict({k: v.float() for k, v in state["model"].items()})
        return model

    model = load_checked(Path(path), verify, build, "pose net weights", hint)
    model.eval()
    return model
