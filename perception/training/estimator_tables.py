"""A whole estimator scored on the held-out test images: detection, hypotheses, refinement, all of
it, per object, with the metrics of the pose-net tables.

Every annotated object at least `MIN_VISIB` visible is one query: the estimator is handed the
image, K, the camera pose and the requested class, as an episode would hand it
(`posegrasp.core.contract.Observation`); a query without an estimate counts as missed.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from perception.crops import square_box
from perception.geometry import project
from perception.hybrid import DEFAULT_CROP_SCALE
from perception.metrics import rotation_error_deg, translation_error_pct
from perception.nets import CROP
from perception.training.dataset import PoseDataset
from posegrasp.core.contract import Observation, PoseEstimator
from posegrasp.world.objects import OBJECT_NAMES

#: Objects less visible than this are not queried (as in the detector-box tables).
MIN_VISIB = 0.5
#: Rotation errors above this count as outliers [deg].
OUTLIER_DEG = 15.0


def query_errors(
    estimator: PoseEstimator, root: Path, limit: int | None = None, targets_only: bool = False
) -> list[dict]:
    """One row per query of the test split under root (with `targets_only`, only each image's
    episode target where its record names one): object, image, ``found``, and when found
    ``centre_px`` (the origin's pixel), ``centre_crop_px`` (the same in pixels of the 64x64 crop
    the pose nets would see on the true visible box: `DEFAULT_CROP_SCALE` times its longer side,
    the unit of the paper's Tables 1-2), ``distance_pct``, ``translation_pct``,
    ``rotation_deg`` and ``ms`` (the estimate's wall time)."""
    ds = PoseDataset(root, "test")
    n = len(ds) if limit is None else min(limit, len(ds))
    rows = []
    for i in tqdm(range(n), desc=f"{estimator.name} {Path(root).name}/test", leave=False):
        s = ds[i]
        T_W_C = np.asarray(s.extra.get("T_W_C", np.eye(4)), float)
        for obj in s.objects:
            if obj.visib_fract < MIN_VISIB or obj.T_C_O[2, 3] <= 0:
                continue
            if targets_only and obj.name != s.extra.get("target", obj.name):
                continue
            obs = Observation(s.rgb, s.K, T_W_C, obj.name, int(s.seed))
            t0 = time.perf_counter()
            est = estimator.estimate(obs)
            row: dict = {
                "object": obj.name,
                "image": i,
                "found": est.T_C_O is not None,
                "ms": (time.perf_counter() - t0) * 1000,
            }
            if est.T_C_O is not None:
                T, G = est.T_C_O, obj.T_C_O
                centre = float(np.linalg.norm(project(s.K, T[:3, 3]) - obj.uv))
                side = square_box(obj.box_xyxy, DEFAULT_CROP_SCALE)[2]
                row |= {
                    "centre_px": centre,
                    "centre_crop_px": centre * CROP / max(side, 1.0),
                    "distance_pct": float(
                        100
                        * abs(np.linalg.norm(T[:3, 3]) - np.linalg.norm(G[:3, 3]))
                        / np.linalg.norm(G[:3, 3])
                    ),
                    "translation_pct": float(translation_error_pct(T[:3, 3], G[:3, 3])),
                    "rotation_deg": float(rotation_error_deg(T[:3, :3], G[:3, :3])),
                }
            rows.append(row)
    return rows


def rotation_summary(errors: np.ndarray) -> dict[str, float]:
    """Mean and median [deg] and the share over `OUTLIER_DEG` [%] of rotation errors (NaN when
    there are none)."""
    if len(errors) == 0:
        nan = float("nan")
        return {"rotation_mean_deg": nan, "rotation_median_deg": nan, "over_15_deg_pct": nan}
    return {
        "rotation_mean_deg": float(np.mean(errors)),
        "rotation_median_deg": float(np.median(errors)),
        "over_15_deg_pct": float(100 * np.mean(errors > OUTLIER_DEG)),
    }


def summarise_queries(rows: list[dict]) -> dict[str, dict[str, float]]:
    """Per object and ``all``: queries, found share [%], mean centre [px and crop px], distance and
    translation [%], rotation mean and median [deg], share over `OUTLIER_DEG` [%] (of the found
    queries) and the median time per estimate [ms]."""
    out = {}
    for name in (*OBJECT_NAMES, "all"):
        sel = [r for r in rows if name in ("all", r["object"])]
        if not sel:
            continue
        hit = [r for r in sel if r["found"]]
        rot = np.array([r["rotation_deg"] for r in hit])

        def mean(key: str, hit=hit) -> float:
            return float(np.mean([r[key] for r in hit])) if hit else float("nan")

        out[name] = {
            "queries": len(sel),
            "found_pct": 100 * len(hit) / len(sel),
            "centre_px": mean("centre_px"),
            "centre_crop_px": mean("centre_crop_px"),
            "distance_pct": mean("distance_pct"),
            "translation_pct": mean("translation_pct"),
            **rotation_summary(rot),
            "median_ms": float(np.median([r["ms"] for r in sel])),
        }
    return out


def format_summary(title: str, summary: dict[str, dict[str, float]]) -> str:
    """The summary as a plain-text table."""
    head = (
        f"{'object':8s} {'queries':>7s} {'found %':>7s} {'centre px':>9s} {'crop px':>7s} "
        f"{'dist %':>7s} "
        f"{'trans %':>7s} {'rot mean':>8s} {'rot med':>7s} {'>15 %':>6s} {'ms':>6s}"
    )
    lines = [title, head]
    for name, m in summary.items():
        lines.append(
            f"{name:8s} {m['queries']:7d} {m['found_pct']:7.1f} {m['centre_px']:9.2f} "
            f"{m['centre_crop_px']:7.2f} "
            f"{m['distance_pct']:7.2f} {m['translation_pct']:7.2f} {m['rotation_mean_deg']:8.2f} "
            f"{m['rotation_median_deg']:7.2f} {m['over_15_deg_pct']:6.1f} {m['median_ms']:6.0f}"
        )
    return "\n".join(lines)
