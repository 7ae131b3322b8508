"""Pictures of a dataset: a sample's annotations drawn on its image, and contact sheets."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from perception.training.data.annotations import object_diameter
from perception.training.data.dataset import PoseDataset, Sample
from posegrasp.core.errors import AssetError, InvalidArgumentError


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
        length = axis_lengths[k] if axis_lengths is not None else object_diameter(obj.name) / 2
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
    """Images in a grid, each scaled to fit tile x tile [px].

    Args:
        images: RGB images, each shape (H, W, 3), uint8, all of the first one's size.
        cols: images per row.
        tile: side of the square each image is scaled to fit [px].

    Returns:
        RGB sheet, shape (rows * th, cols * tw, 3), uint8.
    """
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


def write_preview(root: Path, split: str, dist: str, path: Path, n: int = 24) -> None:
    """Contact sheet of a split's first n images with axes, boxes and origins drawn.

    Raises:
        AssetError: the PNG cannot be written.
    """
    data = PoseDataset(root, split)
    images = [draw_annotations(data[i]) for i in range(min(n, len(data)))]
    cols = 6 if dist == "paper" else 4
    sheet = contact_sheet(images, cols=cols, tile=256 if dist == "paper" else 320)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), sheet[..., ::-1]):
        raise AssetError(f"cannot write preview {path}")
