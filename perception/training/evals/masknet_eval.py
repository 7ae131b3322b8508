"""The mask net measured on held-out images: the masks a detector finds, and the shipped net's
redrawing of them, against the true visible masks (``train_masknet --evaluate``)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from perception.detector import Detection, Detector
from perception.mask_net import MaskRefiner, cut, window_of
from perception.metrics import mask_iou
from perception.training.data.dataset import PoseDataset
from posegrasp.core.paths import data_root
from posegrasp.core.progress import progress_bar

#: Objects with fewer visible pixels are neither measured nor given a training window.
MIN_VISIBLE_PX = 100


def best_detection(
    dets: list[Detection], name: str, truth: np.ndarray, least: float
) -> tuple[Detection | None, float]:
    """Of the detections `dets` of class `name`, the one whose mask overlaps the true visible
    mask `truth` most, with that mask IoU; (None, `least`) when none reaches `least`."""
    best, best_iou = None, least
    for d in dets:
        if d.name == name and (iou := mask_iou(d.mask, truth)) >= best_iou:
            best, best_iou = d, iou
    return best, best_iou


def evaluate(
    folder: str,
    split: str,
    images: int,
    detector_path: Path,
    weights: Path,
    experts: tuple[str, ...] = (),
    examples: list | None = None,
) -> dict[str, Any]:
    """A detector's masks of the `images` first images of a split of a dataset folder (every
    visible object it finds, mask IoU >= 0.5 with the truth) against a shipped mask net's
    redrawing of them, by IoU with the true visible mask, per class and overall.

    Args:
        folder: the dataset folder under the data root (a protocol's validation folder).
        split: ``val`` or ``test``.
        images: the images measured.
        detector_path: the detector's weights.
        weights: the mask net's (with `experts`, the objects that have a net of their own).
        examples: when given, receives the first object of each class: (name, image window,
            detector's, mask net's and true mask in it, both IoUs).
    """
    detector = Detector.from_weights(detector_path)
    refiner = MaskRefiner.from_weights(weights, experts=experts)
    data = PoseDataset(data_root() / folder, split)
    rows: list[tuple[str, float, float]] = []
    spent = 0.0
    for i in progress_bar(
        range(min(images, len(data))), desc=f"masks of {folder}/{split}", mininterval=5
    ):
        sample = data[i]
        dets = detector.detect(sample.rgb, 0.3)
        for obj in sample.objects:
            truth = obj.mask_visib
            if int(truth.sum()) < MIN_VISIBLE_PX:
                continue
            best, best_iou = best_detection(dets, obj.name, truth, 0.5)
            if best is None:
                continue
            t0 = time.perf_counter()
            sharp = refiner.refine(sample.rgb, best.mask, obj.name)
            spent += time.perf_counter() - t0
            after = mask_iou(sharp, truth)
            rows.append((obj.name, best_iou, after))
            if examples is not None and all(e[0] != obj.name for e in examples):
                win = window_of(truth, refiner.cfg.margin)
                assert win is not None
                S = 4 * refiner.cfg.size
                cuts = [cut(m.astype(np.float32), win, S) >= 0.5 for m in (best.mask, sharp, truth)]
                examples.append((obj.name, cut(sample.rgb, win, S), *cuts, best_iou, after))
    names = sorted({r[0] for r in rows})
    per = {
        n: {
            "objects": sum(r[0] == n for r in rows),
            "detector_iou": float(np.mean([r[1] for r in rows if r[0] == n])),
            "refined_iou": float(np.mean([r[2] for r in rows if r[0] == n])),
        }
        for n in names
    }
    return {
        "split": f"{folder}/{split}",
        "images": min(images, len(data)),
        "objects": len(rows),
        "detector_iou": float(np.mean([r[1] for r in rows])),
        "refined_iou": float(np.mean([r[2] for r in rows])),
        "refined_better": float(np.mean([r[2] > r[1] for r in rows])),
        "ms_per_mask": 1000 * spent / max(1, len(rows)),
        "per_class": per,
    }


def plot_examples(examples: list, path: Path) -> None:
    """One row per class: the window, then the detector's, the mask net's and the true mask's
    outlines drawn on it."""
    import cv2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(examples), 4, figsize=(8, 2.1 * len(examples)), squeeze=False)
    for row, (name, rgb, det, sharp, truth, before, after) in zip(axes, examples, strict=True):
        titles = (name, f"detector: IoU {before:.3f}", f"mask net: IoU {after:.3f}", "truth")
        colours = (None, (255, 60, 60), (60, 255, 60), (255, 255, 255))
        for ax, mask, title, colour in zip(
            row, (None, det, sharp, truth), titles, colours, strict=True
        ):
            img = rgb.copy()
            if mask is not None:
                edges = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3)))
                img[edges.astype(bool)] = colour
            ax.imshow(img)
            ax.set_title(title, fontsize=8)
            ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print(f"wrote {path}")
