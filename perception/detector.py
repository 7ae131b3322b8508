"""The object extractor at run time (docs/DESIGN.md §1): the Mask R-CNN of
`perception.detector_net` finds each object's class, box and visible mask in an RGB image.

Boxes: `Detection.box_xyxy` uses the pixel convention of docs/DESIGN.md §4 (the centre of
pixel (0, 0) is (0, 0)), like the dataset's ``box_xyxy``: a box that tightly encloses mask
pixels x_min..x_max is (x_min - 0.5, ..., x_max + 0.5). torchvision (and COCO) put pixel
(0, 0)'s centre at (0.5, 0.5), so ``box_torchvision = box_xyxy + 0.5``; `to_model_box` and
`from_model_box` convert.

Shipped weights: ``perception/weights/detector.pt`` (float16 state dict, the `DetectorConfig`),
written by ``python -m perception.training.train_detector --export``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import ArrayLike
from torchvision.models.detection import MaskRCNN
from torchvision.models.detection.transform import resize_boxes

from perception.detector_net import DetectorConfig, build_detector
from perception.integrity import load_checked
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.paths import WEIGHTS_DIR

DEFAULT_WEIGHTS = WEIGHTS_DIR / "detector.pt"
#: The detector fine-tuned on the tiers' scenes (any resting pose, partly hidden objects), in a
#: folder with a manifest of its own; the estimators other than ``hybrid-global`` keep the
#: head-camera one.
TIERS_DETECTOR = WEIGHTS_DIR / "tiers" / "detector.pt"
#: `TIERS_DETECTOR` fine-tuned further on scenes in rooms drawn for training (lights, surfaces,
#: object colours, camera, unseen distractors; `perception.training.data.rooms`), for
#: ``hybrid-global-rooms``.
ROOMS_DETECTOR = WEIGHTS_DIR / "rooms" / "detector.pt"
#: A detector of any object (`perception.detector_net.ANY_OBJECT`), trained on meshes of a bank
#: and generated shapes alone, never on an object it is asked for: ``hybrid-global-unseen``'s.
UNSEEN_DETECTOR = WEIGHTS_DIR / "unseen" / "detector.pt"
#: The detector of the paper's protocol: `DEFAULT_WEIGHTS` fine-tuned on its studio images too.
PAPER_DETECTOR = WEIGHTS_DIR / "paper_protocol" / "detector.pt"
REBUILD_HINT = (
    "rebuild it with `make weights` (or `python -m perception.training.train_detector --export`)"
)
#: Offset from our pixel coordinates (module docstring) to torchvision's:
#: box_torchvision = box_xyxy + 0.5.
PIXEL_OFFSET = 0.5


@dataclass
class Detection:
    """One detected object.

    Attributes:
        name: object class, one of the detector's `DetectorConfig.classes`.
        score: classification score in [0, 1].
        box_xyxy: (x0, y0, x1, y1) [px], pixel (0, 0) centred at (0, 0), float64, shape (4,).
        mask: visible-part mask of the image, shape (H, W), bool.
    """

    name: str
    score: float
    box_xyxy: np.ndarray
    mask: np.ndarray = field(repr=False)


def to_model_box(box_xyxy: ArrayLike) -> np.ndarray:
    """Box, pixel (0, 0) centred at (0, 0) -> torchvision's convention (centred at (0.5, 0.5))."""
    return np.asarray(box_xyxy, np.float64) + PIXEL_OFFSET


def from_model_box(box: np.ndarray) -> np.ndarray:
    """torchvision box -> box with pixel (0, 0) centred at (0, 0) (inverse of `to_model_box`)."""
    return np.asarray(box, np.float64) - PIXEL_OFFSET


def check_rgb(rgb: object) -> np.ndarray:
    """Validate an RGB image: numpy uint8 of shape (H, W, 3) with H, W >= 1.

    Raises:
        InvalidArgumentError: anything else, saying what was given.
    """
    if not isinstance(rgb, np.ndarray):
        raise InvalidArgumentError(
            f"rgb must be a numpy uint8 array of shape (H, W, 3), got {type(rgb).__name__}"
        )
    if rgb.dtype != np.uint8:
        raise InvalidArgumentError(f"rgb must have dtype uint8, got {rgb.dtype}")
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise InvalidArgumentError(f"rgb must have shape (H, W, 3), got {rgb.shape}")
    if rgb.shape[0] < 1 or rgb.shape[1] < 1:
        raise InvalidArgumentError(f"rgb is empty: shape {rgb.shape}")
    return rgb


def image_tensor(rgb: np.ndarray) -> torch.Tensor:
    """(H, W, 3) uint8 -> (3, H, W) float32 in [0, 1], the model's input."""
    return torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).float().div_(255.0)


def load_detector_model(
    path: Path, verify: bool = True
) -> tuple[MaskRCNN, DetectorConfig, dict[str, Any]]:
    """Rebuild the model stored in a weights file or a training checkpoint.

    Args:
        path: the weights file.
        verify: check the file against the hash its folder's manifest records
            (`perception.integrity.verify_weights`); False for weights you trained.

    Returns:
        (model in eval mode with float32 weights, its config, the file's other entries).

    Raises:
        AssetError: the file is missing or corrupt; the message says how to rebuild it.
        WeightsMismatchError: the manifest next to it records another hash.
    """

    def build(state: dict) -> tuple:
        cfg = DetectorConfig.from_dict(state["model_config"])
        model = build_detector(cfg)
        model.load_state_dict(
            {k: v.float() if v.is_floating_point() else v for k, v in state["model"].items()}
        )
        return model, cfg, state

    model, cfg, state = load_checked(Path(path), verify, build, "detector weights", REBUILD_HINT)
    model.eval()
    meta = {k: v for k, v in state.items() if k not in ("model", "optimizer")}
    return model, cfg, meta


class Detector:
    """Mask R-CNN inference on single RGB images.

    Args:
        model: a model from `build_detector` (put in eval mode here).
        cfg: its config.
        score_threshold: detections scoring below this are dropped (> 1 drops everything).
        mask_threshold: a pixel belongs to the mask when the soft mask is >= this.
        max_detections: keep at most this many detections (highest scores first); None keeps
            what the model returns (at most `DetectorConfig.box_detections_per_img`).
    """

    def __init__(
        self,
        model: MaskRCNN,
        cfg: DetectorConfig,
        score_threshold: float = 0.5,
        mask_threshold: float = 0.5,
        max_detections: int | None = None,
    ) -> None:
        if not np.isfinite(score_threshold) or not 0.0 <= mask_threshold <= 1.0:
            raise InvalidArgumentError(
                f"score_threshold must be finite and mask_threshold in [0, 1], got "
                f"{score_threshold}, {mask_threshold}"
            )
        if max_detections is not None and max_detections < 1:
            raise InvalidArgumentError(f"max_detections must be >= 1, got {max_detections}")
        self.model = model.eval()
        self.cfg = cfg
        self.score_threshold = float(score_threshold)
        self.mask_threshold = float(mask_threshold)
        self.max_detections = max_detections
        self._model_threshold(self.score_threshold)
        self.model.roi_heads.detections_per_img = min(
            cfg.box_detections_per_img, max_detections or cfg.box_detections_per_img
        )

    def _model_threshold(self, score_threshold: float) -> None:
        """Low-scoring boxes are dropped inside the model, before the mask head runs."""
        self.model.roi_heads.score_thresh = max(self.cfg.box_score_thresh, score_threshold)

    @classmethod
    def from_weights(
        cls, path: Path | str = DEFAULT_WEIGHTS, verify: bool = True, **kwargs: Any
    ) -> Detector:
        """Load shipped weights (or a training checkpoint); kwargs as in the constructor.

        `verify` checks the file against its manifest's hash (False: weights you trained).

        Raises:
            AssetError: missing or corrupt weights, with the command that rebuilds them;
                `WeightsMismatchError` when the manifest records another hash.
        """
        model, cfg, _ = load_detector_model(Path(path), verify)
        return cls(model, cfg, **kwargs)

    @classmethod
    def random(cls, cfg: DetectorConfig | None = None, seed: int = 0, **kwargs: Any) -> Detector:
        """A detector with random weights (seeded): for tests and timing the architecture."""
        cfg = cfg or DetectorConfig()
        with torch.random.fork_rng():
            torch.manual_seed(seed)
            model = build_detector(cfg)
        return cls(model, cfg, **kwargs)

    def _forward(self, rgb: np.ndarray, paste: bool = True) -> dict[str, torch.Tensor]:
        """`MaskRCNN.forward` in eval mode, with the resize moved before the normalisation.

        The model's transform normalises the full image and then resizes it; both are linear
        (bilinear weights sum to 1), so resizing first with the transform's own `resize` gives
        the same input while normalising 4x fewer pixels. The second resize inside the transform
        is then the identity. Boxes come back at the original resolution; masks too with
        `paste`, else as the mask head's (N, 1, M, M) probabilities (`paste_mask` places one).
        """
        m = self.model
        small, _ = m.transform.resize(image_tensor(rgb), None)
        images, _ = m.transform([small])
        features = m.backbone(images.tensors)
        proposals, _ = m.rpn(images, features)
        dets, _ = m.roi_heads(features, proposals, images.image_sizes)
        if paste:
            return m.transform.postprocess(dets, images.image_sizes, [rgb.shape[:2]])[0]
        out = dict(dets[0])
        out["boxes"] = resize_boxes(out["boxes"], images.image_sizes[0], rgb.shape[:2])
        return out

    @torch.inference_mode()
    def detect(self, rgb: np.ndarray, score_threshold: float | None = None) -> list[Detection]:
        """Find the objects in an image.

        Args:
            rgb: image, shape (H, W, 3), uint8.
            score_threshold: this call's threshold instead of the detector's.

        Returns:
            Detections sorted by decreasing score; empty when nothing scores above the threshold.

        Raises:
            InvalidArgumentError: rgb is not an (H, W, 3) uint8 array with H, W >= 1, or the
                score_threshold is not finite.
        """
        rgb = check_rgb(rgb)
        threshold = self.score_threshold if score_threshold is None else float(score_threshold)
        if not np.isfinite(threshold):
            raise InvalidArgumentError(f"score_threshold must be finite, got {score_threshold}")
        self._model_threshold(threshold)
        try:
            out = self._forward(rgb, paste=False)
        finally:
            self._model_threshold(self.score_threshold)
        scores = out["scores"].numpy()
        order = np.argsort(-scores, kind="stable")
        order = order[scores[order] >= threshold]
        if self.max_detections is not None:
            order = order[: self.max_detections]
        boxes = out["boxes"].numpy()
        labels = out["labels"].numpy()
        masks = out["masks"]
        dets = []
        for i in order:
            label = int(labels[i])
            if not 1 <= label <= len(self.cfg.classes):
                continue
            dets.append(
                Detection(
                    name=self.cfg.classes[label - 1],
                    score=float(scores[i]),
                    box_xyxy=from_model_box(boxes[i]),
                    mask=paste_mask(masks[i, 0], out["boxes"][i], rgb.shape[:2])
                    >= self.mask_threshold,
                )
            )
        return dets


def paste_mask(mask: torch.Tensor, box: torch.Tensor, shape: tuple[int, int]) -> np.ndarray:
    """One mask head output (M, M) placed in an image of `shape` (H, W) as torchvision's
    ``paste_masks_in_image`` places it (padded by one cell, the box grown to match, resized
    bilinearly to the box's whole pixels), drawn only for this detection and without the
    image-sized float copies: (H, W) float32 probabilities, zero outside the box."""
    M = mask.shape[-1]
    scale = (M + 2) / M
    padded = torch.nn.functional.pad(mask[None, None], (1, 1, 1, 1))
    cx, cy = (box[0] + box[2]) * 0.5, (box[1] + box[3]) * 0.5
    hw, hh = (box[2] - box[0]) * 0.5 * scale, (box[3] - box[1]) * 0.5 * scale
    x0, y0, x1, y1 = (int(v) for v in torch.stack([cx - hw, cy - hh, cx + hw, cy + hh]).long())
    w, h = max(x1 - x0 + 1, 1), max(y1 - y0 + 1, 1)
    drawn = torch.nn.functional.interpolate(
        padded, size=(h, w), mode="bilinear", align_corners=False
    )
    H, W = shape
    out = np.zeros((H, W), np.float32)
    u0, u1, v0, v1 = max(x0, 0), min(x1 + 1, W), max(y0, 0), min(y1 + 1, H)
    if u1 > u0 and v1 > v0:
        out[v0:v1, u0:u1] = drawn[0, 0, v0 - y0 : v1 - y0, u0 - x0 : u1 - x0].numpy()
    return out
