"""A whole estimator scored on the held-out test images: detection, hypotheses, refinement, all of
it, per object, with the metrics of the pose-net tables.

Every annotated object at least `MIN_VISIB` visible is one query: the estimator is handed the
image, K, the camera pose and the requested class, as an episode would hand it
(`posegrasp.core.contract.Observation`); a query without an estimate counts as missed.

A pose over `OUTLIER_DEG` may still be one the image cannot tell from the truth: a car seen from
below, turned end for end, is the same underside. Each such pose is also checked against the truth
by BOP's Visible Surface Discrepancy (`perception.metrics.vsd`, the object's mesh drawn alone at
the true pose as the test depth): below `ALIKE_VSD` at the strictest tolerance, 5 % of the
diameter, its surface lies where the true one does, and the row says so (``alike``).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from perception.crops import square_box
from perception.geometry import project
from perception.hybrid import DEFAULT_CROP_SCALE
from perception.metrics import render_depth, rotation_error_deg, translation_error_pct, vsd
from perception.nets import CROP
from perception.training.data.dataset import PoseDataset
from posegrasp.core.contract import Observation, PoseEstimator
from posegrasp.core.progress import progress_bar
from posegrasp.world.objects import OBJECT_NAMES, load_object

#: Objects less visible than this are not queried (as in the detector-box tables).
MIN_VISIB = 0.5
#: Rotation errors above this count as outliers [deg].
OUTLIER_DEG = 15.0
#: A pose over `OUTLIER_DEG` whose VSD error against the truth, at a tolerance of 5 % of the
#: diameter, is below this counts as alike in shape (BOP counts a pose correct below thresholds
#: of 0.05-0.5; this is their middle).
ALIKE_VSD = 0.3


def shape_alike(name: str, T: np.ndarray, G: np.ndarray, K: np.ndarray, size: tuple[int, int]):
    """Whether pose T of object `name` leaves its surface where the true pose G does, seen by a
    camera K of image `size` (width, height): the VSD error at tau = 0.05 of the diameter below
    `ALIKE_VSD`, with the object's mesh drawn alone at G as the test depth."""
    model = load_object(name)
    V, F = np.asarray(model.mesh.vertices), np.asarray(model.mesh.faces)
    depth = render_depth(V, F, G[:3, :3], G[:3, 3], K, *size)
    err = vsd(T[:3, :3], T[:3, 3], G[:3, :3], G[:3, 3], depth, K, V, F, model.diameter, taus=[0.05])
    return bool(err[0] < ALIKE_VSD)


def query_errors(
    estimator: PoseEstimator, root: Path, limit: int | None = None, targets_only: bool = False
) -> list[dict]:
    """One row per query of the test split under root (with `targets_only`, only each image's
    episode target where its record names one): object, image, ``found``, and when found
    ``centre_px`` (the origin's pixel), ``centre_crop_px`` (the same in pixels of the 64x64 crop
    the pose nets would see on the true visible box: `DEFAULT_CROP_SCALE` times its longer side,
    the unit of the paper's Tables 1-2), ``distance_pct``, ``translation_pct``,
    ``rotation_deg``, ``alike`` (over `OUTLIER_DEG` yet alike in shape, `shape_alike`) and
    ``ms`` (the estimate's wall time)."""
    ds = PoseDataset(root, "test")
    n = len(ds) if limit is None else min(limit, len(ds))
    rows = []
    for i in progress_bar(range(n), desc=f"{estimator.name} {Path(root).name}/test", leave=False):
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
                size = (s.rgb.shape[1], s.rgb.shape[0])
                row["alike"] = row["rotation_deg"] > OUTLIER_DEG and shape_alike(
                    obj.name, T, G, s.K, size
                )
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
    translation [%], rotation mean and median [deg], share over `OUTLIER_DEG` [%] and share over
    it yet alike in shape [%] (`shape_alike`; both of the found queries) and the median time per
    estimate [ms]."""
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
            "alike_pct": 100 * float(np.mean([r.get("alike", False) for r in hit]))
            if hit
            else float("nan"),
            "median_ms": float(np.median([r["ms"] for r in sel])),
        }
    return out


def format_summary(title: str, summary: dict[str, dict[str, float]]) -> str:
    """The summary as a plain-text table."""
    head = (
        f"{'object':8s} {'queries':>7s} {'found %':>7s} {'centre px':>9s} {'crop px':>7s} "
        f"{'dist %':>7s} "
        f"{'trans %':>7s} {'rot mean':>8s} {'rot med':>7s} {'>15 %':>6s} {'alike %':>7s} "
        f"{'ms':>6s}"
    )
    lines = [title, head]
    for name, m in summary.items():
        lines.append(
            f"{name:8s} {m['queries']:7d} {m['found_pct']:7.1f} {m['centre_px']:9.2f} "
            f"{m['centre_crop_px']:7.2f} "
            f"{m['distance_pct']:7.2f} {m['translation_pct']:7.2f} {m['rotation_mean_deg']:8.2f} "
            f"{m['rotation_median_deg']:7.2f} {m['over_15_deg_pct']:6.1f} {m['alike_pct']:7.1f} "
            f"{m['median_ms']:6.0f}"
        )
    return "\n".join(lines)
