"""A whole estimator scored on test images (`perception.training.evals.estimator_tables`, behind
``tables --estimator``): every visible object is one query, its errors are those of the pose it
answered, a query without a pose counts as not found."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from perception.metrics import rotation_error_deg
from perception.training.data.dataset import PoseDataset
from perception.training.datagen import main as datagen_main
from perception.training.evals.estimator_tables import (
    MIN_VISIB,
    query_errors,
    shape_alike,
    summarise_queries,
)
from posegrasp.core.contract import Estimate, Observation
from posegrasp.core.transforms import intrinsics, rot_x, rot_z


class _Fixed:
    """Answers one fixed pose for phones and nothing for anything else."""

    name = "fixed"

    def __init__(self) -> None:
        self.T = np.eye(4)
        self.T[:3, 3] = [0.0, 0.0, 1.0]
        self.seen: list[Observation] = []

    def estimate(self, obs: Observation) -> Estimate:
        self.seen.append(obs)
        return Estimate(self.T.copy() if obs.object == "phone" else None)


@pytest.fixture(scope="module")
def split(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("data") / "headcam"
    args = [
        "--dist",
        "headcam",
        "--split",
        "test",
        "--count",
        "3",
        "--width",
        "320",
        "--height",
        "240",
        "--out",
        str(root),
        "--quiet",
    ]
    assert datagen_main(args) == 0
    return root


def test_every_visible_object_is_one_query_with_its_own_errors(split: Path) -> None:
    est = _Fixed()
    rows = query_errors(est, split)
    ds = PoseDataset(split, "test")
    expected = [
        (o.name, i)
        for i in range(len(ds))
        for o in ds[i].objects
        if o.visib_fract >= MIN_VISIB and o.T_C_O[2, 3] > 0
    ]
    assert [(r["object"], r["image"]) for r in rows] == expected
    assert [o.object for o in est.seen] == [name for name, _ in expected]
    for r in rows:
        assert r["found"] == (r["object"] == "phone")
        if r["found"]:
            G = next(o for o in ds[r["image"]].objects if o.name == r["object"]).T_C_O
            assert r["rotation_deg"] == pytest.approx(rotation_error_deg(np.eye(3), G[:3, :3]))
            d = np.linalg.norm(G[:3, 3])
            assert r["distance_pct"] == pytest.approx(100 * abs(1.0 - d) / d)
            # the centre in the crop's pixels: the pose nets' 64 px over 1.15 x the true
            # visible box's longer side
            box = next(o for o in ds[r["image"]].objects if o.name == r["object"]).box_xyxy
            side = 1.15 * max(box[2] - box[0], box[3] - box[1])
            assert r["centre_crop_px"] == pytest.approx(r["centre_px"] * 64 / side)


def test_the_summary_counts_misses_and_outliers() -> None:
    rows = [
        {
            "object": "car",
            "found": True,
            "centre_px": 1.0,
            "centre_crop_px": 0.5,
            "distance_pct": 2.0,
            "translation_pct": 3.0,
            "rotation_deg": 1.0,
            "ms": 10.0,
        },
        {
            "object": "car",
            "found": True,
            "centre_px": 3.0,
            "centre_crop_px": 1.0,
            "distance_pct": 4.0,
            "translation_pct": 5.0,
            "rotation_deg": 30.0,
            "alike": True,
            "ms": 30.0,
        },
        {"object": "car", "found": False, "ms": 20.0},
    ]
    s = summarise_queries(rows)
    assert set(s) == {"car", "all"}
    car = s["car"]
    assert car["queries"] == 3 and car["found_pct"] == pytest.approx(200 / 3)
    assert car["centre_px"] == 2.0 and car["centre_crop_px"] == 0.75
    assert car["rotation_mean_deg"] == 15.5
    assert car["rotation_median_deg"] == 15.5 and car["over_15_deg_pct"] == 50.0
    assert car["alike_pct"] == 50.0
    assert car["median_ms"] == 20.0


def test_a_car_turned_end_for_end_seen_from_below_is_alike_in_shape() -> None:
    """Seen straight from below, a car turned half way round about its vertical shows the same
    underside where the true one is: alike. Tipped a quarter turn onto its side, it is not."""
    K = intrinsics(np.deg2rad(50), 320, 240)
    G = np.eye(4)
    G[:3, :3] = rot_x(np.pi) @ rot_z(0.3)  # the camera's axis along the car's +z: from below
    G[:3, 3] = [0.0, 0.0, 0.6]
    turned, tipped = G.copy(), G.copy()
    turned[:3, :3] = G[:3, :3] @ rot_z(np.pi)
    tipped[:3, :3] = G[:3, :3] @ rot_x(np.pi / 2)
    assert shape_alike("car", turned, G, K, (320, 240))
    assert not shape_alike("car", tipped, G, K, (320, 240))
    assert shape_alike("car", G, G, K, (320, 240))
