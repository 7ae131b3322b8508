"""COCO box and mask AP of the detector (pycocotools' COCOeval; docs/DESIGN.md §9)."""

from __future__ import annotations

import contextlib
import io
from collections.abc import Sequence
from typing import Any

import numpy as np

from perception.detector import Detection, Detector, to_model_box
from perception.detector_net import class_label
from perception.training.data.bop import obj_name
from perception.training.data.dataset import PoseDataset, Sample
from posegrasp.core.errors import AssetError
from posegrasp.world.objects import OBJECT_NAMES


def pycocotools_api() -> tuple[Any, Any, Any]:
    """pycocotools' ``COCO``, ``COCOeval`` and ``mask`` module, imported on first use.

    Raises:
        AssetError: pycocotools is not installed, saying how to install it.
    """
    try:
        from pycocotools import mask as mask_utils
        from pycocotools.coco import COCO
        from pycocotools.cocoeval import COCOeval
    except ImportError as exc:
        raise AssetError(
            "the detector's AP evaluation needs pycocotools: pip install pycocotools "
            "(a dependency in pyproject.toml; reinstall with `make setup`)"
        ) from exc
    return COCO, COCOeval, mask_utils


def coco_ap(
    gts: list[list[tuple[int, np.ndarray]]],
    dets: list[list[Detection]],
    min_visible_px: int,
    per_class: dict[str, dict[str, float]] | None = None,
    classes: Sequence[str] = OBJECT_NAMES,
) -> dict[str, float]:
    """COCO box and mask AP of detections against ground truth, by pycocotools' COCOeval.

    Args:
        gts: per image, (obj_id, visible mask (H, W) bool) of every object; objects with fewer
            than `min_visible_px` pixels are marked crowd, so that they count neither as misses
            nor (when detected) as false positives.
        dets: per image, the detections (scores from low thresholds give the full curve).
        min_visible_px: see gts.
        per_class: when given, filled with class name -> ``box_ap``, ``box_ap50``, ``mask_ap``,
            ``mask_ap50`` of that class alone.
        classes: the categories (the detector's classes); ground truth of other objects is
            left out.

    Returns:
        ``box_ap50``, ``box_ap`` (IoU 0.5:0.95), ``mask_ap50``, ``mask_ap`` in [0, 1]; 0 when
        there is no detection; -1 when there is no ground truth (pycocotools' convention).
    """
    COCO, COCOeval, mask_utils = pycocotools_api()
    images, anns, box_res, seg_res = _coco_records(gts, dets, min_visible_px, classes, mask_utils)
    cats = [{"id": k + 1, "name": n} for k, n in enumerate(classes)]
    out: dict[str, float] = {}
    with contextlib.redirect_stdout(io.StringIO()):  # pycocotools prints progress
        gt_api = COCO()
        gt_api.dataset = {"images": images, "annotations": anns, "categories": cats}
        gt_api.createIndex()
        for kind, res in (("box", box_res), ("mask", seg_res)):
            if not res:
                out[f"{kind}_ap50"] = out[f"{kind}_ap"] = 0.0 if anns else -1.0
                continue
            ev = COCOeval(gt_api, gt_api.loadRes(res), "bbox" if kind == "box" else "segm")
            ev.evaluate()
            ev.accumulate()
            ev.summarize()
            out[f"{kind}_ap"] = float(ev.stats[0])
            out[f"{kind}_ap50"] = float(ev.stats[1])
            if per_class is not None:
                for name, (ap, ap50) in _per_class_ap(ev, classes).items():
                    per_class.setdefault(name, {})[f"{kind}_ap"] = ap
                    per_class[name][f"{kind}_ap50"] = ap50
    return out


def _coco_records(
    gts: list[list[tuple[int, np.ndarray]]],
    dets: list[list[Detection]],
    min_visible_px: int,
    classes: Sequence[str],
    mask_utils: Any,
) -> tuple[list[dict], list[dict], list[dict], list[dict]]:
    """`coco_ap`'s ground truth and detections as COCO records: the images, the annotations
    (small objects marked crowd), the box results and the mask results."""

    def rle(mask: np.ndarray) -> dict:
        return mask_utils.encode(np.asfortranarray(mask.astype(np.uint8)))

    anns: list[dict[str, Any]]
    images, anns, box_res, seg_res = [], [], [], []
    for i, (gt, dd) in enumerate(zip(gts, dets, strict=True)):
        h, w = gt[0][1].shape if gt else (dd[0].mask.shape if dd else (1, 1))
        images.append({"id": i, "height": int(h), "width": int(w)})
        for oid, m in gt:
            if (label := class_label(classes, obj_name(int(oid)))) is None:
                continue
            r = rle(m)
            area = int(m.sum())
            anns.append(
                {
                    "id": len(anns) + 1,
                    "image_id": i,
                    "category_id": label,
                    "segmentation": r,
                    "area": float(area),
                    "bbox": mask_utils.toBbox(r).tolist(),
                    "iscrowd": int(area < min_visible_px),
                }
            )
        for d in dd:
            x0, y0, x1, y1 = to_model_box(d.box_xyxy)
            common = {"image_id": i, "category_id": class_label(classes, d.name), "score": d.score}
            box_res.append({**common, "bbox": [x0, y0, x1 - x0, y1 - y0]})
            seg_res.append({**common, "segmentation": rle(d.mask)})
    return images, anns, box_res, seg_res


def _per_class_ap(ev: Any, classes: Sequence[str]) -> dict[str, tuple[float, float]]:
    """(AP at IoU 0.5:0.95, AP50) per class from an accumulated COCOeval: the mean of its
    precision table over IoU thresholds and recall points, all areas, at most 100 detections;
    -1 for a class without ground truth (pycocotools' convention)."""
    prec = ev.eval["precision"]  # (IoU thresholds, recall points, classes, areas, max dets)
    out = {}
    for k, cat in enumerate(ev.params.catIds):
        pk = prec[:, :, k, 0, -1]
        valid = pk > -1
        ap = float(pk[valid].mean()) if valid.any() else -1.0
        p50 = pk[0][pk[0] > -1]
        out[classes[cat - 1]] = (ap, float(p50.mean()) if p50.size else -1.0)
    return out


def visible_objects(sample: Sample) -> list[tuple[int, np.ndarray]]:
    """`coco_ap`'s ground truth of one image: (obj_id, visible mask (H, W) bool) of every object
    with at least one visible pixel."""
    return [(o.obj_id, o.mask_visib) for o in sample.objects if o.mask_visib.any()]


def evaluate_detector(
    detector: Detector, data: PoseDataset, n_images: int, min_visible_px: int
) -> dict[str, float]:
    """COCO AP (`coco_ap`) of a detector on the first n_images of a split."""
    gts, dets = [], []
    for i in range(min(n_images, len(data))):
        s = data[i]
        gts.append(visible_objects(s))
        dets.append(detector.detect(s.rgb))
    classes = detector.cfg.classes
    return coco_ap(gts, dets, min_visible_px, classes=classes) | {"images": len(gts)}
