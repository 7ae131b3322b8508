"""Test-time augmentation of the pose nets: does fusing the poses of several crops help?

    python studies/tta_ablation.py [--weights perception/weights/posenet_ours.pt]
        [--dataset headcam] [--limit N] [--json PATH]

On a test split, each object gets the crop `perception.training.tables` scores it with (a
ground-truth box perturbed like a detection, `TEST_CROPS`), plus variants of that crop: its
side scaled by 0.92 or 1.08, its centre moved by 4 % of the side along x or y. Every crop is run
through the net and decoded to a full pose; a set of variants is fused into one pose: the
origin pixel and the translation by their per-axis medians, the rotation by the chordal mean of
the rotations within 15 deg of the medoid (the rotation closest, in sum, to the others).

Prints centre [px, 640x480], distance [%], rotation [deg] and the share of rotations over
15 deg for: the single crop (what `tables` reports), the three scales, the five shifts, and all
fifteen; and the nets' time per object for each.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from perception.nets import load_posenet
from perception.training.data.crop_sets import CropSet, random_boxes
from perception.training.data.dataset import DATASETS, PoseDataset
from perception.training.evals.posenet_eval import decode_predictions, pose_metrics, predict
from perception.training.tables import TEST_CROPS
from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.paths import WEIGHTS_DIR, data_root
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_choice, check_int

SCALES = (1.0, 0.92, 1.08)
SHIFTS = ((0.0, 0.0), (0.04, 0.0), (-0.04, 0.0), (0.0, 0.04), (0.0, -0.04))
#: Variant index = scale index * len(SHIFTS) + shift index; 0 is the crop itself.
SETS = {
    "single crop": [0],
    "3 scales": [s * len(SHIFTS) for s in range(len(SCALES))],
    "5 shifts": list(range(len(SHIFTS))),
    "all 15": list(range(len(SCALES) * len(SHIFTS))),
}
OUTLIER_DEG = 15.0


def _variant(box: tuple[float, float, float], scale: float, shift: tuple[float, float]):
    x0, y0, side = box
    cx, cy = x0 + side / 2 + shift[0] * side, y0 + side / 2 + shift[1] * side
    s = side * scale
    return (cx - s / 2, cy - s / 2, s)


def crops_with_variants(root: Path, limit: int | None) -> tuple[dict, int]:
    """The test crops of `tables` (same seeds, same order) and their variants, variant-major:
    row v * n + i is variant v of crop i. Returns (arrays, n)."""
    ds = PoseDataset(root, "test")
    n_img = len(ds) if limit is None else min(limit, len(ds))
    per_variant = [CropSet() for _ in range(len(SCALES) * len(SHIFTS))]
    for sample, obj, box in random_boxes(ds, TEST_CROPS, n_img):
        for k, (sc, sh) in enumerate((a, b) for a in SCALES for b in SHIFTS):
            per_variant[k].add(sample.rgb, sample.K, obj, _variant(box, sc, sh))
    parts = [c.arrays() for c in per_variant]
    n = len(parts[0]["cls"])
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}, n


def _geodesic(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    cos = (np.einsum("...ij,...ij->...", Ra, Rb) - 1) / 2
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def fuse(uv: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One pose from V variants: uv (V, 2), T (V, 4, 4) -> uv (2,), T (4, 4)."""
    R = T[:, :3, :3]
    d = _geodesic(R[:, None], R[None, :])
    medoid = int(np.argmin(d.sum(axis=1)))
    inliers = d[medoid] <= OUTLIER_DEG
    u, _, vt = np.linalg.svd(R[inliers].sum(axis=0))
    Rm = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    out = np.eye(4)
    out[:3, :3] = Rm
    out[:3, 3] = np.median(T[:, :3, 3], axis=0)
    return np.median(uv, axis=0), out


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(prog="python studies/tta_ablation.py", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--weights",
        type=Path,
        default=WEIGHTS_DIR / "posenet_ours.pt",
        metavar="PATH",
        help="pose net weights (default: the shipped ours)",
    )
    p.add_argument(
        "--dataset",
        default="headcam",
        type=arg(check_choice, DATASETS, "dataset"),
        help=f"dataset folder under the data root, one of: {', '.join(DATASETS)}",
    )
    p.add_argument(
        "--limit",
        type=arg(check_int, 1, 100_000_000, "--limit", base=int),
        default=None,
        help="first N test images",
    )
    add_json_argument(p, "the figures")
    a = p.parse_args(argv)
    setup_rendering()
    log = summary_stream(a.json)
    model = load_posenet(a.weights)
    data, n = crops_with_variants(data_root() / a.dataset, a.limit)
    t = time.perf_counter()
    pred = predict(model, data["crops"], data["cls"], data["scale"])
    per_crop_ms = (time.perf_counter() - t) * 1000 / len(data["cls"])
    dec = decode_predictions(pred, data)
    V = len(data["cls"]) // n
    uv, T = dec["uv"].reshape(V, n, 2), dec["T_C_O"].reshape(V, n, 4, 4)
    truth = {k: v[:n] for k, v in data.items()}
    rows = {}
    for name, idx in SETS.items():
        fused = [fuse(uv[idx, i], T[idx, i]) for i in range(n)]
        m = pose_metrics(
            {"uv": np.array([f[0] for f in fused]), "T_C_O": np.array([f[1] for f in fused])}, truth
        )
        rows[name] = {k: float(np.mean(v)) for k, v in m.items()} | {
            "outlier_rate": float(np.mean(m["rotation_deg"] > OUTLIER_DEG)),
            "crops": len(idx),
            "nets_ms_per_object": per_crop_ms * len(idx),
        }
    print(
        f"{a.weights.name} on {a.dataset}/test: {n} objects (ground-truth boxes perturbed "
        "like detections)",
        file=log,
    )
    print(
        f"{'crops':<12} {'centre px':>9} {'distance %':>10} {'rotation':>9} "
        f"{'> 15 deg':>8} {'nets ms':>8}",
        file=log,
    )
    for name, r in rows.items():
        print(
            f"{name:<12} {r['center_px']:9.2f} {r['distance_pct']:10.2f} "
            f"{r['rotation_deg']:9.2f} {100 * r['outlier_rate']:7.2f}% "
            f"{r['nets_ms_per_object']:8.2f}",
            file=log,
        )
    if a.json is not None:
        write_json(a.json, {"objects": n, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
