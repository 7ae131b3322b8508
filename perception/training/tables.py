"""Evaluation of the pose nets on the held-out test splits (`python -m perception.training.tables`).

For each dataset folder (`paper`, `headcam`, or a head-camera tier's `headcam_<tier>`) the test
images' boxes are perturbed as detections are (random shift and scale, seeded), the nets predict,
the exact geometry decodes, and the paper's Table 1 (centre error) and Table 2 (distance and
rotation error, IoU accuracy, invalid poses) are printed per object beside the paper's numbers,
with ADD(-S) recall at 0.1 d, 5 cm 5 deg recall, medians, 90th percentiles and the rotation
outlier rate. Which of our figures each paper figure is compared with, and why, is in
`perception.training.evals.paper_tables`: the centre error in 64x64 crop pixels (also given in
full-image pixels as rendered, and rescaled to the paper's 256x256 images: du * 256 / W,
dv * 256 / H, i.e. 0.4 and 0.5333 for the 640x480 head camera), "acc IoU" as the share of poses
with silhouette IoU > 0.5, invalid poses as IoU <= 0.5; ADD for objects without symmetries and
ADD-S for those with.

With ``--boxes detector`` the test splits are measured end to end instead, as the paper's Table 2
was: the shipped Mask R-CNN finds the objects, the crops are cut around its boxes as the
estimator cuts them, and the report adds COCO box and mask AP per class (pycocotools) and the
ratio of the pose errors to those from ground-truth boxes (keys ``detection``,
``detection_summary`` and ``detector_to_gt_ratio`` for the head camera, prefixed with the split's
name for the others).

    python -m perception.training.tables [--weights perception/weights/posenet_ours.pt] \
        --json out.json   (--json -: the report on standard output)
    python -m perception.training.tables --dists headcam,headcam_hard,headcam_far
    python -m perception.training.tables --boxes detector --json detector.json
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path
from typing import TextIO

import numpy as np

from perception import metrics
from perception.crops import square_box
from perception.detector import DEFAULT_WEIGHTS, Detector
from perception.estimators import LEARNED_ESTIMATORS
from perception.hybrid import DEFAULT_CROP_SCALE
from perception.metrics import box_iou
from perception.nets import CROP, PoseNet, load_posenet
from perception.overlay import silhouette
from perception.success_model import SuccessModel, components_of, load_models
from perception.training.data.crop_sets import CropConfig, CropSet, build_crops
from perception.training.data.dataset import DATASETS, PoseDataset, load_info
from perception.training.evals.detection_eval import coco_ap, visible_objects
from perception.training.evals.estimator_tables import (
    format_summary,
    query_errors,
    summarise_queries,
)
from perception.training.evals.paper_tables import READINGS, average, format_tables, summarise
from perception.training.evals.posenet_eval import (
    PAPER_IMAGE,
    decode_predictions,
    pose_metrics,
    predict,
)
from perception.training.shipping.record import (
    check_full_splits,
    check_record_request,
    record_command,
    record_in_manifest,
)
from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.errors import AssetError, InvalidArgumentError
from posegrasp.core.paths import WEIGHTS_DIR, data_root
from posegrasp.core.progress import progress_bar
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_choice, check_int, check_names
from posegrasp.world.objects import OBJECT_NAMES, load_object

#: Test boxes are perturbed like detections, with this seed.
TEST_CROPS = CropConfig(per_object=1, max_shift=0.05, scale_range=(1.0, 1.2), seed=12345)
BOXES: tuple[str, ...] = ("gt", "detector")
#: Errors compared between detector and ground-truth boxes.
RATIO_KEYS = ("center_px_mean", "distance_pct_mean", "rotation_deg_mean")
#: A detection used for a pose must score at least this (the estimator's default threshold).
MATCH_SCORE = 0.5
#: Largest --limit (a split never holds more images).
MAX_LIMIT = 100_000_000
#: Objects with fewer visible pixels count neither as misses nor as false positives in AP.
MIN_VISIBLE_PX = 100


def _iou(T_est: np.ndarray, T_gt: np.ndarray, K: np.ndarray, name: str) -> float:
    mesh = load_object(name).mesh
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    # Render both silhouettes in a window around the true projection.
    h, w = int(2 * K[1, 2] + 1), int(2 * K[0, 2] + 1)
    a = silhouette(T_est, K, v, f, (h, w))
    b = silhouette(T_gt, K, v, f, (h, w))
    return metrics.mask_iou(a, b)


def detector_crops(
    root: Path,
    detector: Detector,
    limit: int | None = None,
    min_visib: float = 0.5,
    size: int = CROP,
) -> tuple[dict, dict]:
    """Crops of a test split cut around detector boxes, as an end-to-end system would see them.

    Every annotated object at least `min_visib` visible is matched with the highest-scoring
    detection of its class whose box overlaps its visible box by IoU >= 0.5 and whose score is
    at least `MATCH_SCORE`; the crop is the square `perception.hybrid` cuts around that box,
    resampled to `size` x `size` (the pose net's input).

    Returns:
        The crop arrays in `perception.training.data.crop_sets.build_crops`' layout (matched
        objects only), and a detection report: ``detection`` (class name -> COCO ``box_ap``,
        ``box_ap50``, ``mask_ap``, ``mask_ap50`` over every object of the images), ``overall``
        (the same over all classes), ``objects`` and ``missed`` (per class: objects to match and
        objects without a matching detection), and ``targets`` and ``targets_missed``: of the
        images whose record names an episode target at least `min_visib` visible, how many, and
        in how many that target has no matching detection.
    """
    ds = PoseDataset(root, "test")
    n = len(ds) if limit is None else min(limit, len(ds))
    out = CropSet(size)
    gts, dets = [], []
    objects = dict.fromkeys(OBJECT_NAMES, 0)
    missed = dict.fromkeys(OBJECT_NAMES, 0)
    targets = targets_missed = 0
    for i in progress_bar(range(n), desc=f"detector {root.name}/test", leave=False):
        s = ds[i]
        found = detector.detect(s.rgb)
        gts.append(visible_objects(s))
        dets.append(found)
        for obj in s.objects:
            if obj.visib_fract < min_visib or obj.T_C_O[2, 3] <= 0:
                continue
            objects[obj.name] += 1
            is_target = bool(obj.extra.get("target"))
            targets += is_target
            cands = [
                d
                for d in found
                if d.name == obj.name
                and d.score >= MATCH_SCORE
                and box_iou(d.box_xyxy, obj.box_xyxy) >= 0.5
            ]
            if not cands:
                missed[obj.name] += 1
                targets_missed += is_target
                continue
            d = max(cands, key=lambda d: d.score)
            out.add(s.rgb, s.K, obj, square_box(d.box_xyxy, scale=DEFAULT_CROP_SCALE))
    arrays = out.arrays()
    per_class: dict[str, dict[str, float]] = {}
    overall = coco_ap(gts, dets, MIN_VISIBLE_PX, per_class)
    return arrays, {
        "detection": per_class,
        "overall": overall,
        "objects": objects,
        "missed": missed,
        "targets": targets,
        "targets_missed": targets_missed,
        "images": n,
    }


def _symmetry_set(name: str) -> list[metrics.Symmetry]:
    """The object's symmetry set in `perception.metrics`' convention (identity included)."""
    syms = metrics.identity_symmetry()
    syms += [{"R": T[:3, :3], "t": T[:3, 3:4]} for T in load_object(name).symmetries]
    return syms


def datagen_command(dataset: str) -> str:
    """The command that generates the test split of a dataset folder of `DATASETS`."""
    dist, _, tier = dataset.partition("_")
    tier_arg = f" --tier {tier}" if tier else ""
    return f"python -m perception.training.datagen --dist {dist}{tier_arg} --split test --count N"


def check_test_split(dataset: str) -> Path:
    """The folder of a dataset's test split under the data root.

    Raises:
        AssetError: the folder has no test split; the message names the command making it.
    """
    root = data_root() / dataset
    if not (root / "test").is_dir():
        raise AssetError(
            f"no test split of {dataset} in {root}; generate it with `{datagen_command(dataset)}`"
        )
    return root


def _success_models(success: dict[str, SuccessModel], dataset: str) -> dict[str, SuccessModel]:
    """The success models of a head-camera dataset's tier (isolated for the mixed `headcam`)."""
    if not dataset.startswith("headcam"):
        return {}
    tier = dataset.partition("_")[2] or "isolated"
    return {o: success[k] for o in OBJECT_NAMES if (k := f"{o}/{tier}") in success}


def evaluate_split(
    model: PoseNet,
    root: Path,
    limit: int | None = None,
    data: dict | None = None,
    success: dict[str, SuccessModel] | None = None,
) -> dict:
    """Metrics on one dataset's test split, per object and averaged over objects.

    `data` gives the crops (e.g. from `detector_crops`); by default the ground-truth boxes are
    perturbed like detections (`TEST_CROPS`). With `success` (models by object, see
    `perception.success_model`), each object also gets ``expected_success``: the mean predicted
    probability that a grasp planned on its test poses succeeds.

    Returns:
        ``per_object`` (name -> `paper_tables.summarise`' figures), ``average`` (`average`),
        ``image_size`` (W, H) [px] of the split's images, ``center_256_scale`` (256 / W,
        256 / H), the factors of ``center_256_px``, and ``paper_readings`` (the paper's figure
        -> the key of ours it is compared with).
    """
    if data is None:
        data = build_crops(root, "test", replace(TEST_CROPS, size=model.cfg.crop), limit)
    if len(data["crops"]) == 0:
        raise AssetError(f"no test crops under {root}")
    info = load_info(root)
    size = (int(info["width"]), int(info["height"]))
    pred = predict(model, data["crops"], data["cls"], data["scale"])
    dec = decode_predictions(pred, data)
    m = pose_metrics(dec, data, size)
    n = len(data["cls"])
    extra = {k: np.zeros(n) for k in ("iou", "add_rel", "adi_rel", "trans_m")}
    p_success = np.full(n, np.nan)
    pts = {o: np.asarray(load_object(o).mesh.vertices) for o in OBJECT_NAMES}
    add_metric = {o: metrics.add_metric_name(_symmetry_set(o)) for o in OBJECT_NAMES}
    for i in range(n):
        name = OBJECT_NAMES[int(data["cls"][i])]
        Te, Tg = dec["T_C_O"][i], data["T_C_O"][i]
        d = load_object(name).diameter
        pose = (Te[:3, :3], Te[:3, 3], Tg[:3, :3], Tg[:3, 3], pts[name])
        extra["iou"][i] = _iou(Te, Tg, data["K"][i], name)
        extra["adi_rel"][i] = metrics.adi(*pose) / d
        chosen = metrics.add(*pose) / d if add_metric[name] == "ADD" else extra["adi_rel"][i]
        extra["add_rel"][i] = chosen
        extra["trans_m"][i] = np.linalg.norm(Te[:3, 3] - Tg[:3, 3])
        if success is not None and name in success:
            p_success[i] = success[name].predict(components_of(metrics.error_components(Te, Tg)))
    per_object = {}
    for c, name in enumerate(OBJECT_NAMES):
        sel = data["cls"] == c
        if sel.any():
            errors = {k: v[sel] for k, v in (m | extra).items()}
            per_object[name] = summarise(errors, add_metric[name])
            if not np.all(np.isnan(p_success[sel])):
                per_object[name]["expected_success"] = float(np.nanmean(p_success[sel]))
    return {
        "per_object": per_object,
        "average": average(per_object, n),
        "image_size": list(size),
        "center_256_scale": [PAPER_IMAGE[0] / size[0], PAPER_IMAGE[1] / size[1]],
        "paper_readings": dict(READINGS),
    }


def format_detection(det: dict) -> str:
    """Per-class COCO AP and match counts of `detector_crops`' report."""
    rows = [
        f"== detection on {det['images']} test images (COCO AP, pycocotools) ==",
        f"{'class':<10}{'box AP':>9}{'box AP50':>10}{'mask AP':>9}{'mask AP50':>11}"
        f"{'objects':>9}{'missed':>8}",
    ]
    for name in OBJECT_NAMES:
        a = det["detection"].get(name, {})
        rows.append(
            f"{name:<10}{a.get('box_ap', -1):>9.3f}{a.get('box_ap50', -1):>10.3f}"
            f"{a.get('mask_ap', -1):>9.3f}{a.get('mask_ap50', -1):>11.3f}"
            f"{det['objects'][name]:>9}{det['missed'][name]:>8}"
        )
    o = det["overall"]
    rows.append(
        f"{'all':<10}{o['box_ap']:>9.3f}{o['box_ap50']:>10.3f}{o['mask_ap']:>9.3f}"
        f"{o['mask_ap50']:>11.3f}{sum(det['objects'].values()):>9}"
        f"{sum(det['missed'].values()):>8}"
    )
    if det.get("targets"):
        found = det["targets"] - det["targets_missed"]
        rows.append(
            f"episode targets found (IoU >= 0.5): {found} of {det['targets']} "
            f"({100 * found / det['targets']:.1f} %)"
        )
    return "\n".join(rows)


def _estimator_tables(
    name: str, roots: dict[str, Path], limit: int | None, targets: bool, json_path, log
) -> int:
    """`--estimator`: the whole estimator on each split, per object (`estimator_tables`)."""
    from perception.estimators import LEARNED_ESTIMATORS

    estimator = LEARNED_ESTIMATORS[name]()
    report: dict = {"estimator": name}
    for d, root in roots.items():
        rows = query_errors(estimator, root, limit, targets)
        report[d] = {"summary": summarise_queries(rows), "queries": rows}
        print(format_summary(f"{name} on {d}/test", report[d]["summary"]), file=log)
    if json_path is not None:
        write_json(json_path, report)
    return 0


def _parser() -> ArgumentParser:
    """The command line."""
    p = ArgumentParser(
        prog="python -m perception.training.tables", description=__doc__.split("\n")[0]
    )
    p.add_argument(
        "--weights",
        type=Path,
        default=WEIGHTS_DIR / "posenet_ours.pt",
        metavar="PATH",
        help="pose net weights (default: the shipped ours)",
    )
    p.add_argument(
        "--dists",
        default="headcam,paper",
        type=arg(check_names, DATASETS, "distribution", "--dists"),
        help=f"comma list of dataset folders under the data root, of: {', '.join(DATASETS)} "
        "(default: headcam,paper)",
    )
    p.add_argument(
        "--limit",
        type=arg(check_int, 1, MAX_LIMIT, "--limit", base=int),
        default=None,
        help=f"at most this many test images, 1..{MAX_LIMIT}",
    )
    add_json_argument(p, "the report")
    p.add_argument(
        "--boxes",
        default="gt",
        type=arg(check_choice, BOXES, "box source"),
        help="crop boxes: gt (ground truth perturbed like detections) or detector (the shipped "
        "Mask R-CNN, head-camera split only; adds COCO detection AP and the ratio of the errors "
        "to those from ground-truth boxes)",
    )
    p.add_argument(
        "--detector", type=Path, default=DEFAULT_WEIGHTS, metavar="PATH", help="detector weights"
    )
    p.add_argument(
        "--success-model",
        type=Path,
        default=None,
        metavar="PATH",
        help="models of python -m sim.fit_success: adds the expected grasp success of the "
        "head-camera test poses (a tier's models for headcam_<tier>, isolated for headcam)",
    )
    p.add_argument(
        "--estimator",
        default=None,
        metavar="NAME",
        type=arg(check_choice, list(LEARNED_ESTIMATORS), "learned estimator"),
        help="score this whole estimator instead (detection included), per object, one of: "
        f"{', '.join(LEARNED_ESTIMATORS)}",
    )
    p.add_argument(
        "--targets",
        action="store_true",
        help="with --estimator: query only each image's episode target (the tier splits name one)",
    )
    p.add_argument(
        "--record",
        action="store_true",
        help="store the test averages in perception/weights/manifest.json: only the shipped "
        "weights on the full shipped test splits of the default data folder",
    )
    return p


def _split_tables(d: str, root: Path, model: PoseNet, models: dict, args, log: TextIO) -> dict:
    """The report entries of one test split: its tables (and, with detector boxes, the
    detection figures and the ratio of the errors to those from ground-truth boxes)."""
    report: dict = {}
    data = None
    # Keys without the split's name are the head camera's (the manifest's record).
    tag = "" if d == "headcam" else f"{d}_"
    if args.boxes == "detector":
        detector = Detector.from_weights(args.detector, score_threshold=0.05)
        data, det = detector_crops(root, detector, args.limit, size=model.cfg.crop)
        report[f"{tag}detection"] = det["detection"]
        report[f"{tag}detection_summary"] = {k: v for k, v in det.items() if k != "detection"}
        print(format_detection(det), file=log)
    report[d] = evaluate_split(model, root, args.limit, data, _success_models(models, d))
    if args.boxes == "detector":
        report[d]["boxes"] = "detector"
        gt = evaluate_split(model, root, args.limit)
        report[f"{d}_gt_boxes"] = gt
        report[f"{tag}detector_to_gt_ratio"] = {
            k: report[d]["average"][k] / gt["average"][k] for k in RATIO_KEYS
        }
    title = d if args.boxes == "gt" else f"{d} (detector boxes)"
    print(format_tables(title, report[d]), file=log)
    if args.boxes == "detector":
        print(
            "detector boxes / ground-truth boxes (average): "
            + ", ".join(f"{k} {v:.2f}x" for k, v in report[f"{tag}detector_to_gt_ratio"].items()),
            file=log,
        )
    return report


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    args = _parser().parse_args(argv)
    setup_rendering()
    log = summary_stream(args.json)
    dists = args.dists
    if args.record and args.estimator is not None:
        raise InvalidArgumentError(
            "--record stores pose-net figures; it does not apply to --estimator"
        )
    if args.record:
        check_record_request(args, dists)
        check_full_splits(dists)
    roots = {d: check_test_split(d) for d in dists}
    if args.estimator is not None:
        return _estimator_tables(args.estimator, roots, args.limit, args.targets, args.json, log)
    model = load_posenet(args.weights)
    models = {} if args.success_model is None else load_models(args.success_model)
    report: dict = {}
    for d in dists:
        report |= _split_tables(d, roots[d], model, models, args, log)
    if args.record:
        variant = record_in_manifest(report, args.weights, args.boxes, record_command(args))
        print(f"recorded the test figures of {variant} in the manifest", file=log)
    if args.json is not None:
        write_json(args.json, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
