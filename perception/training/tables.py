"""Evaluation of the pose nets on the held-out test splits (`python -m perception.training.tables`).

For each data distribution (`headcam`, `paper`) the test images' boxes are perturbed as
detections are (random shift and scale, seeded), the nets predict, the exact geometry decodes,
and the paper's Table 1 (centre error) and Table 2 (distance and rotation error, IoU accuracy)
are printed per object beside the paper's numbers, with ADD-S recall at 0.1 d, 5 cm 5 deg
recall, medians, 90th percentiles and the outlier rate (rotation > 15 deg).

With ``--boxes detector`` the head-camera test split is measured end to end instead: the shipped
Mask R-CNN finds the objects, the crops are cut around its boxes as the estimator cuts them, and
the report adds COCO box and mask AP per class (pycocotools) and the ratio of the pose errors to
those from ground-truth boxes.

    python -m perception.training.tables [--weights perception/weights/posenet_ours.pt] \
        --json out.json
    python -m perception.training.tables --boxes detector --json detector.json
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from perception import metrics, summaries
from perception.crops import square_box
from perception.detector import DEFAULT_WEIGHTS, Detector
from perception.hybrid import DEFAULT_CROP_SCALE
from perception.metrics import box_iou
from perception.nets import PoseNet, load_posenet
from perception.overlay import silhouette
from perception.success_model import SuccessModel, components_of, load_models
from perception.training.crop_sets import CropConfig, CropSet, build_crops
from perception.training.dataset import DISTS, PoseDataset
from perception.training.detection_eval import coco_ap, visible_objects
from perception.training.posenet_eval import decode_predictions, pose_metrics, predict
from perception.training.record import (
    check_full_splits,
    check_record_request,
    record_command,
    record_in_manifest,
)
from sim.core.cli import ArgumentParser, fail, write_json
from sim.core.errors import AssetError, PosegraspError
from sim.core.paths import WEIGHTS_DIR, data_root
from sim.core.validate import arg, check_choice, check_int, check_names, check_output_file
from sim.world.objects import OBJECT_NAMES, load_object

#: The paper's Tables 1 and 2 (Staszak & Belter 2019), per object and average.
PAPER = {
    "center_px_mean": {"car": 1.89, "chair": 1.77, "faucet": 1.07, "screen": 1.75, "phone": 1.64,
                       "pistol": 2.17, "average": 1.72},
    "center_px_std": {"car": 1.53, "chair": 1.45, "faucet": 1.06, "screen": 1.60, "phone": 1.55,
                      "pistol": 2.10, "average": 1.55},
    "distance_pct_mean": {"car": 5.43, "chair": 6.19, "faucet": 5.87, "screen": 6.59,
                          "phone": 7.12, "pistol": 5.57, "average": 6.12},
    "distance_pct_std": {"car": 5.12, "chair": 5.79, "faucet": 6.27, "screen": 7.04,
                         "phone": 7.53, "pistol": 5.23, "average": 6.16},
    "rotation_deg_mean": {"car": 2.83, "chair": 3.19, "faucet": 3.03, "screen": 3.76,
                          "phone": 4.22, "pistol": 3.58, "average": 3.43},
    "rotation_deg_std": {"car": 3.21, "chair": 3.68, "faucet": 3.46, "screen": 4.15,
                         "phone": 4.59, "pistol": 4.01, "average": 3.85},
    "iou_acc": {"car": 0.972, "chair": 0.956, "faucet": 0.964, "screen": 0.961, "phone": 0.958,
                "pistol": 0.961, "average": 0.964},
}  # fmt: skip
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


def _summary(m: dict[str, np.ndarray], extra: dict[str, np.ndarray]) -> dict[str, float]:
    out: dict[str, float] = {"count": len(m["center_px"])}
    for key, arr in (
        ("center_px", m["center_px"]),
        ("center_crop_px", m["center_crop_px"]),
        ("distance_pct", m["distance_pct"]),
        ("rotation_deg", m["rotation_deg"]),
    ):
        s = summaries.summary_stats(arr)
        out |= {f"{key}_mean": s["mean"], f"{key}_std": s["std"],
                f"{key}_median": s["median"], f"{key}_p90": s["p90"]}  # fmt: skip
    out["iou_acc"] = float(np.mean(extra["iou"]))
    out["outlier_rate"] = summaries.outlier_rate(m["rotation_deg"])
    out["add_s_recall"] = float(np.mean(extra["adi_rel"] < 0.1))
    out["recall_5cm5deg"] = summaries.recall_5cm5deg(extra["trans_m"], m["rotation_deg"])
    return out


def detector_crops(
    root: Path, detector: Detector, limit: int | None = None, min_visib: float = 0.5
) -> tuple[dict, dict]:
    """Crops of a test split cut around detector boxes, as an end-to-end system would see them.

    Every annotated object at least `min_visib` visible is matched with the highest-scoring
    detection of its class whose box overlaps its visible box by IoU >= 0.5 and whose score is
    at least `MATCH_SCORE`; the crop is the square `perception.hybrid` cuts around that box.

    Returns:
        The crop arrays in `perception.training.crop_sets.build_crops`' layout (matched
        objects only), and a detection report: ``detection`` (class name -> COCO ``box_ap``,
        ``box_ap50``, ``mask_ap``, ``mask_ap50`` over every object of the images), ``overall``
        (the same over all classes), ``objects`` and ``missed`` (per class: objects to match and
        objects without a matching detection).
    """
    ds = PoseDataset(root, "test")
    n = len(ds) if limit is None else min(limit, len(ds))
    out = CropSet()
    gts, dets = [], []
    objects = dict.fromkeys(OBJECT_NAMES, 0)
    missed = dict.fromkeys(OBJECT_NAMES, 0)
    for i in tqdm(range(n), desc=f"detector {root.name}/test", leave=False):
        s = ds[i]
        found = detector.detect(s.rgb)
        gts.append(visible_objects(s))
        dets.append(found)
        for obj in s.objects:
            if obj.visib_fract < min_visib or obj.T_C_O[2, 3] <= 0:
                continue
            objects[obj.name] += 1
            cands = [d for d in found if d.name == obj.name and d.score >= MATCH_SCORE
                     and box_iou(d.box_xyxy, obj.box_xyxy) >= 0.5]  # fmt: skip
            if not cands:
                missed[obj.name] += 1
                continue
            d = max(cands, key=lambda d: d.score)
            out.add(s.rgb, s.K, obj, square_box(d.box_xyxy, scale=DEFAULT_CROP_SCALE))
    arrays = out.arrays()
    per_class: dict[str, dict[str, float]] = {}
    overall = coco_ap(gts, dets, MIN_VISIBLE_PX, per_class)
    return arrays, {"detection": per_class, "overall": overall, "objects": objects,
                    "missed": missed, "images": n}  # fmt: skip


def evaluate_split(
    model: PoseNet,
    root: Path,
    limit: int | None = None,
    data: dict | None = None,
    success: dict[str, SuccessModel] | None = None,
) -> dict:
    """Metrics on one distribution's test split, per object and averaged over objects.

    `data` gives the crops (e.g. from `detector_crops`); by default the ground-truth boxes are
    perturbed like detections (`TEST_CROPS`). With `success` (models by object, see
    `perception.success_model`), each object also gets ``expected_success``: the mean predicted
    probability that a grasp planned on its test poses succeeds."""
    if data is None:
        data = build_crops(root, "test", TEST_CROPS, limit)
    if len(data["crops"]) == 0:
        raise AssetError(f"no test crops under {root}")
    pred = predict(model, data["crops"], data["cls"], data["scale"])
    dec = decode_predictions(pred, data)
    m = pose_metrics(dec, data)
    n = len(data["cls"])
    iou, adi_rel, trans, p_success = np.zeros(n), np.zeros(n), np.zeros(n), np.full(n, np.nan)
    pts = {o: np.asarray(load_object(o).mesh.vertices) for o in OBJECT_NAMES}
    for i in range(n):
        name = OBJECT_NAMES[int(data["cls"][i])]
        Te, Tg = dec["T_C_O"][i], data["T_C_O"][i]
        iou[i] = _iou(Te, Tg, data["K"][i], name)
        adi = metrics.adi(Te[:3, :3], Te[:3, 3], Tg[:3, :3], Tg[:3, 3], pts[name])
        adi_rel[i] = adi / load_object(name).diameter
        trans[i] = np.linalg.norm(Te[:3, 3] - Tg[:3, 3])
        if success is not None and name in success:
            p_success[i] = success[name].predict(components_of(metrics.error_components(Te, Tg)))
    extra = {"iou": iou, "adi_rel": adi_rel, "trans_m": trans}
    per_object = {}
    for c, name in enumerate(OBJECT_NAMES):
        sel = data["cls"] == c
        if sel.any():
            per_object[name] = _summary({k: v[sel] for k, v in m.items()},
                                        {k: v[sel] for k, v in extra.items()})  # fmt: skip
            if not np.all(np.isnan(p_success[sel])):
                per_object[name]["expected_success"] = float(np.nanmean(p_success[sel]))
    keys = [k for k in next(iter(per_object.values())) if k != "count"]
    keys = [k for k in keys if all(k in po for po in per_object.values())]
    average = {k: float(np.mean([po[k] for po in per_object.values()])) for k in keys}
    average["count"] = n
    return {"per_object": per_object, "average": average}


def format_tables(name: str, res: dict) -> str:
    """The paper's Table 1 and 2 layout, ours beside the paper's."""
    cols = [*OBJECT_NAMES, "average"]
    rows = [f"== {name} test split ({res['average']['count']} crops) ==",
            f"{'metric':<26}" + "".join(f"{c:>16}" for c in cols)]  # fmt: skip

    def row(label: str, key: str, scale: float = 1.0, paper: bool = True) -> None:
        vals = []
        for c in cols:
            src = res["average"] if c == "average" else res["per_object"].get(c)
            ours = "-" if src is None or key not in src else f"{src[key] * scale:.2f}"
            ref = PAPER.get(key, {}).get(c)
            cell = f"{ours} ({ref * scale:.2f})" if paper and ref is not None else ours
            vals.append(f"{cell:>16}")
        rows.append(f"{label:<26}" + "".join(vals))

    rows.append("Table 1: centre (ours (paper))")
    row("e_centre [px]", "center_px_mean")
    row("e_centre std [px]", "center_px_std")
    row("e_centre [64x64 crop px]", "center_crop_px_mean", paper=False)
    rows.append("Table 2: pose (ours (paper))")
    row("e_distance [%]", "distance_pct_mean")
    row("e_distance std [%]", "distance_pct_std")
    row("e_rotation [deg]", "rotation_deg_mean")
    row("e_rotation std [deg]", "rotation_deg_std")
    row("acc_IoU [%]", "iou_acc", 100)
    rows.append("Beyond the paper")
    row("e_distance median [%]", "distance_pct_median", paper=False)
    row("e_distance p90 [%]", "distance_pct_p90", paper=False)
    row("e_rotation median [deg]", "rotation_deg_median", paper=False)
    row("e_rotation p90 [deg]", "rotation_deg_p90", paper=False)
    row("outliers (>15 deg) [%]", "outlier_rate", 100, paper=False)
    row("ADD-S < 0.1d recall [%]", "add_s_recall", 100, paper=False)
    row("5cm 5deg recall [%]", "recall_5cm5deg", 100, paper=False)
    if "expected_success" in res["average"]:
        row("expected grasp success [%]", "expected_success", 100, paper=False)
    return "\n".join(rows)


def format_detection(det: dict) -> str:
    """Per-class COCO AP and match counts of `detector_crops`' report."""
    rows = [f"== detection on {det['images']} test images (COCO AP, pycocotools) ==",
            f"{'class':<10}{'box AP':>9}{'box AP50':>10}{'mask AP':>9}{'mask AP50':>11}"
            f"{'objects':>9}{'missed':>8}"]  # fmt: skip
    for name in OBJECT_NAMES:
        a = det["detection"].get(name, {})
        rows.append(
            f"{name:<10}{a.get('box_ap', -1):>9.3f}{a.get('box_ap50', -1):>10.3f}"
            f"{a.get('mask_ap', -1):>9.3f}{a.get('mask_ap50', -1):>11.3f}"
            f"{det['objects'][name]:>9}{det['missed'][name]:>8}"
        )
    o = det["overall"]
    rows.append(f"{'all':<10}{o['box_ap']:>9.3f}{o['box_ap50']:>10.3f}{o['mask_ap']:>9.3f}"
                f"{o['mask_ap50']:>11.3f}{sum(det['objects'].values()):>9}"
                f"{sum(det['missed'].values()):>8}")  # fmt: skip
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(
        prog="python -m perception.training.tables", description=__doc__.split("\n")[0]
    )
    p.add_argument("--weights", type=Path, default=WEIGHTS_DIR / "posenet_ours.pt")
    p.add_argument(
        "--dists",
        default=None,
        help="comma list of: headcam, paper (default: both; headcam with --boxes detector)",
    )
    p.add_argument(
        "--limit",
        type=arg(check_int, 1, MAX_LIMIT, "--limit", base=int),
        default=None,
        help=f"at most this many test images, 1..{MAX_LIMIT}",
    )
    p.add_argument("--json", type=arg(check_output_file, "--json"), default=None)
    p.add_argument(
        "--boxes",
        default="gt",
        help="crop boxes: gt (ground truth perturbed like detections) or detector (the shipped "
        "Mask R-CNN, head-camera split only; adds COCO detection AP and the ratio of the errors "
        "to those from ground-truth boxes)",
    )
    p.add_argument("--detector", type=Path, default=DEFAULT_WEIGHTS, help="detector weights")
    p.add_argument(
        "--success-model",
        type=Path,
        default=None,
        help="models of python -m sim.fit_success: adds the expected grasp success of the "
        "head-camera test poses (isolated-tier models)",
    )
    p.add_argument(
        "--record",
        action="store_true",
        help="store the test averages in perception/weights/manifest.json: only the shipped "
        "weights on the full shipped test splits of the default data folder",
    )
    args = p.parse_args(argv)
    try:
        check_choice(args.boxes, BOXES, "box source")
        spec = args.dists or ("headcam" if args.boxes == "detector" else "headcam,paper")
        dists = check_names(spec, DISTS, "distribution", "--dists")
        if args.boxes == "detector" and dists != ["headcam"]:
            return fail("--boxes detector works on the head-camera split only; valid: headcam")
        if args.record:
            check_record_request(args, dists)
            check_full_splits(dists)
        model = load_posenet(args.weights)
        success = None
        if args.success_model is not None:
            models = load_models(args.success_model)
            success = {o: models[k] for o in OBJECT_NAMES if (k := f"{o}/isolated") in models}
        report: dict = {}
        for d in dists:
            data = None
            if args.boxes == "detector":
                detector = Detector.from_weights(args.detector, score_threshold=0.05)
                data, det = detector_crops(data_root() / d, detector, args.limit)
                report["detection"] = det["detection"]
                report["detection_summary"] = {k: v for k, v in det.items() if k != "detection"}
                print(format_detection(det))
            report[d] = evaluate_split(
                model, data_root() / d, args.limit, data, success if d == "headcam" else None
            )
            if args.boxes == "detector":
                report[d]["boxes"] = "detector"
                gt = evaluate_split(model, data_root() / d, args.limit)
                report[f"{d}_gt_boxes"] = gt
                report["detector_to_gt_ratio"] = {
                    k: report[d]["average"][k] / gt["average"][k] for k in RATIO_KEYS
                }
            print(format_tables(d if args.boxes == "gt" else f"{d} (detector boxes)", report[d]))
            if args.boxes == "detector":
                print(
                    "detector boxes / ground-truth boxes (average): "
                    + ", ".join(f"{k} {v:.2f}x" for k, v in report["detector_to_gt_ratio"].items())
                )
        if args.record:
            variant = record_in_manifest(report, args.weights, args.boxes, record_command(args))
            print(f"recorded the test figures of {variant} in the manifest")
    except PosegraspError as exc:
        return fail(str(exc))
    if args.json is not None:
        write_json(args.json, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
