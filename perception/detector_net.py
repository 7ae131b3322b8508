"""The object extractor's network: a small Mask R-CNN built from scratch (no pretrained weights)
and fast on a CPU (docs/DESIGN.md §7).

The model is torchvision's own `MaskRCNN` with a light backbone: a ResNet-style stack of basic
blocks (widths `DetectorConfig.widths`, strides 8, 16 and 32 feed a feature pyramid, plus the
usual max-pooled level at stride 64), narrow box and mask heads, few proposals, and a reduced
input size (a 640x480 image is resized to 320x240 inside the model). Label 0 is background and
label k the k-th of `DetectorConfig.classes`: the six built-in objects in
`posegrasp.world.objects.OBJECT_NAMES` order (their BOP object ids), then any user objects a
detector was fine-tuned on; or, for a detector of any object, one class, `ANY_OBJECT`, that every
annotated object is.

Inference on images, the box conventions and loading weights live in `perception.detector`.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from typing import Any

import torch
from torch import nn
from torchvision.models.detection import MaskRCNN
from torchvision.models.detection.anchor_utils import AnchorGenerator
from torchvision.models.detection.backbone_utils import BackboneWithFPN
from torchvision.models.detection.faster_rcnn import FastRCNNPredictor, TwoMLPHead
from torchvision.models.detection.mask_rcnn import MaskRCNNHeads, MaskRCNNPredictor
from torchvision.models.detection.transform import GeneralizedRCNNTransform
from torchvision.ops import MultiScaleRoIAlign

from posegrasp.core.errors import InvalidArgumentError
from posegrasp.world.objects import OBJECT_NAMES

#: The one class of a detector of any object (``train_detector --any-object``): every annotated
#: object, whatever it is, is one of these.
ANY_OBJECT = "object"


def class_label(classes: Sequence[str], name: str) -> int | None:
    """The label (1..) a detector of `classes` gives an object of class `name`: its place among
    the classes counted from 1; 1 for every object when the one class is `ANY_OBJECT`; None for
    an object it does not detect."""
    if tuple(classes) == (ANY_OBJECT,):
        return 1
    return list(classes).index(name) + 1 if name in classes else None


@dataclass(frozen=True)
class DetectorConfig:
    """Architecture and inference settings of the Mask R-CNN. Sizes in pixels of the resized
    model input unless stated.

    Attributes:
        n_classes: classes including background (1 + len(classes)).
        classes: the objects the labels 1.. name, in order.
        widths: channels of the backbone stages at strides 4, 8, 16 and 32 (stem: widths[0]).
        blocks: basic residual blocks per stage (the first of each stage has stride 2).
        fpn_channels: channels of every feature-pyramid level (and of the RPN and RoI heads).
        anchor_sizes: anchor side per pyramid level (strides 8, 16, 32, 64).
        aspect_ratios: anchor height / width ratios, shared by every level.
        min_size, max_size: the image is scaled so that its short side is min_size unless its
            long side would exceed max_size (640x480 -> 320x240).
        image_mean, image_std: per-channel normalisation of the [0, 1] RGB input.
        rpn_pre_nms_top_n_train, rpn_post_nms_top_n_train, rpn_pre_nms_top_n_test,
        rpn_post_nms_top_n_test: proposals kept before / after the RPN's NMS (per level before).
        representation_size: width of the box head's two fully connected layers.
        mask_layers: channels of the mask head's 3x3 convolutions.
        mask_dim_reduced: channels of the mask predictor's transposed convolution.
        box_score_thresh: the model drops detections scoring below this.
        box_nms_thresh: per-class NMS IoU of the final detections.
        box_detections_per_img: at most this many detections per image.
        box_batch_size_per_image: RoIs sampled per image for the box loss during training.
    """

    n_classes: int = 1 + len(OBJECT_NAMES)
    classes: tuple[str, ...] = OBJECT_NAMES
    widths: tuple[int, int, int, int] = (32, 48, 96, 160)
    blocks: tuple[int, int, int, int] = (1, 1, 2, 1)
    fpn_channels: int = 64
    anchor_sizes: tuple[int, ...] = (16, 32, 64, 128)
    aspect_ratios: tuple[float, ...] = (0.5, 1.0, 2.0)
    min_size: int = 240
    max_size: int = 320
    image_mean: tuple[float, float, float] = (0.45, 0.45, 0.45)
    image_std: tuple[float, float, float] = (0.25, 0.25, 0.25)
    rpn_pre_nms_top_n_train: int = 600
    rpn_post_nms_top_n_train: int = 300
    rpn_pre_nms_top_n_test: int = 150
    rpn_post_nms_top_n_test: int = 50
    representation_size: int = 256
    mask_layers: tuple[int, ...] = (64, 64)
    mask_dim_reduced: int = 64
    box_score_thresh: float = 0.05
    box_nms_thresh: float = 0.5
    box_detections_per_img: int = 10
    box_batch_size_per_image: int = 128

    def __post_init__(self) -> None:
        if self.n_classes < 2:
            raise InvalidArgumentError(f"n_classes must be >= 2, got {self.n_classes}")
        if self.n_classes != 1 + len(self.classes) or len(set(self.classes)) != len(self.classes):
            raise InvalidArgumentError(
                f"classes must be {self.n_classes - 1} distinct names, got {list(self.classes)}"
            )
        if len(self.widths) != 4 or len(self.blocks) != 4 or min(self.blocks) < 1:
            raise InvalidArgumentError("widths and blocks need 4 entries each, blocks >= 1")
        if len(self.anchor_sizes) != 4:
            raise InvalidArgumentError("anchor_sizes needs one size per pyramid level (4)")
        if not 0 < self.min_size <= self.max_size:
            raise InvalidArgumentError(
                f"need 0 < min_size <= max_size, got {self.min_size}, {self.max_size}"
            )

    @property
    def any_object(self) -> bool:
        """Whether this is a detector of any object: one class, `ANY_OBJECT`."""
        return self.classes == (ANY_OBJECT,)

    def label(self, name: str) -> int | None:
        """The label the detector gives an object of class `name` (`class_label`)."""
        return class_label(self.classes, name)

    def widened(self, names: Sequence[str]) -> DetectorConfig:
        """This config with `names` added to its classes (those it has already are kept)."""
        classes = (*self.classes, *(n for n in names if n not in self.classes))
        return replace(self, classes=classes, n_classes=1 + len(classes))

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (stored in checkpoints and weight files)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> DetectorConfig:
        """Inverse of `to_dict` (JSON or pickles turn tuples into lists)."""
        kwargs: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
        return cls(**kwargs)


# --- backbone ----------------------------------------------------------------------------------


class BasicBlock(nn.Module):
    """Two 3x3 convolutions with BN and a residual connection (1x1 projection when the shape
    changes)."""

    def __init__(self, cin: int, cout: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.relu = nn.ReLU(inplace=True)
        self.proj: nn.Module = nn.Identity()
        if stride != 1 or cin != cout:
            self.proj = nn.Sequential(
                nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout)
            )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, cin, H, W) -> (B, cout, H / stride, W / stride)."""
        y = self.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return self.relu(y + self.proj(x))


class SmallResNet(nn.Module):
    """A ResNet-style trunk: stem (stride 2), then stages ``c2`` .. ``c5`` at strides 4..32.

    Its children are named so that torchvision's `IntermediateLayerGetter` can return the stages.
    """

    def __init__(self, widths: tuple[int, ...], blocks: tuple[int, ...]) -> None:
        super().__init__()
        w0 = widths[0]
        self.stem = nn.Sequential(
            nn.Conv2d(3, w0, 3, 2, 1, bias=False), nn.BatchNorm2d(w0), nn.ReLU(inplace=True)
        )
        cin = w0
        for i, (w, n) in enumerate(zip(widths, blocks, strict=True)):
            layers = [BasicBlock(cin, w, 2)] + [BasicBlock(w, w, 1) for _ in range(n - 1)]
            self.add_module(f"c{i + 2}", nn.Sequential(*layers))
            cin = w
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
        for m in self.modules():
            if isinstance(m, BasicBlock):
                nn.init.zeros_(m.bn2.weight)  # each block starts as the identity (plus projection)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) -> (B, widths[-1], H / 32, W / 32), the last stage's features."""
        x = self.stem(x)
        for name in ("c2", "c3", "c4", "c5"):
            x = getattr(self, name)(x)
        return x


def build_detector(cfg: DetectorConfig | None = None) -> MaskRCNN:
    """A randomly initialised torchvision `MaskRCNN` as `cfg` describes (nothing downloaded).

    Returns:
        The model in training mode; call ``.eval()`` for inference.
    """
    cfg = cfg or DetectorConfig()
    trunk = SmallResNet(cfg.widths, cfg.blocks)
    backbone = BackboneWithFPN(
        trunk,
        return_layers={"c3": "0", "c4": "1", "c5": "2"},
        in_channels_list=list(cfg.widths[1:]),
        out_channels=cfg.fpn_channels,
    )  # adds a max-pooled level "pool" at stride 64
    levels = ["0", "1", "2"]
    anchors = AnchorGenerator(
        sizes=tuple((s,) for s in cfg.anchor_sizes),
        aspect_ratios=(tuple(cfg.aspect_ratios),) * len(cfg.anchor_sizes),
    )
    box_pool = MultiScaleRoIAlign(featmap_names=levels, output_size=7, sampling_ratio=2)
    mask_pool = MultiScaleRoIAlign(featmap_names=levels, output_size=14, sampling_ratio=2)
    c = cfg.fpn_channels
    return MaskRCNN(
        backbone,
        num_classes=None,
        min_size=cfg.min_size,
        max_size=cfg.max_size,
        image_mean=list(cfg.image_mean),
        image_std=list(cfg.image_std),
        rpn_anchor_generator=anchors,
        rpn_pre_nms_top_n_train=cfg.rpn_pre_nms_top_n_train,
        rpn_post_nms_top_n_train=cfg.rpn_post_nms_top_n_train,
        rpn_pre_nms_top_n_test=cfg.rpn_pre_nms_top_n_test,
        rpn_post_nms_top_n_test=cfg.rpn_post_nms_top_n_test,
        box_roi_pool=box_pool,
        box_head=TwoMLPHead(c * 7 * 7, cfg.representation_size),
        box_predictor=FastRCNNPredictor(cfg.representation_size, cfg.n_classes),
        box_score_thresh=cfg.box_score_thresh,
        box_nms_thresh=cfg.box_nms_thresh,
        box_detections_per_img=cfg.box_detections_per_img,
        box_batch_size_per_image=cfg.box_batch_size_per_image,
        mask_roi_pool=mask_pool,
        mask_head=MaskRCNNHeads(c, list(cfg.mask_layers), 1),
        mask_predictor=MaskRCNNPredictor(cfg.mask_layers[-1], cfg.mask_dim_reduced, cfg.n_classes),
    )


def count_parameters(model: nn.Module) -> int:
    """Number of parameters (trainable or not)."""
    return sum(p.numel() for p in model.parameters())


def input_transform(cfg: DetectorConfig) -> GeneralizedRCNNTransform:
    """The model's own input transform (resize to `min_size`/`max_size`, normalisation), in eval
    mode: ``input_transform(cfg).resize(image, target)`` scales an image (and a training target's
    boxes and masks) exactly as the model would, so that it can be done ahead, e.g. in a
    data-loading process.
    """
    t = GeneralizedRCNNTransform(
        cfg.min_size, cfg.max_size, list(cfg.image_mean), list(cfg.image_std)
    )
    return t.eval()


def state_dict_fp16(model: nn.Module) -> OrderedDict[str, torch.Tensor]:
    """The model's state dict with floating-point tensors in float16 (for shipping)."""
    return OrderedDict(
        (k, v.detach().half() if v.is_floating_point() else v.detach())
        for k, v in model.state_dict().items()
    )
