"""The constant-distance baseline of studies/distance_baseline.py."""

from __future__ import annotations

import importlib.util

import numpy as np

from posegrasp.core.paths import REPO_ROOT

_spec = importlib.util.spec_from_file_location(
    "distance_baseline", REPO_ROOT / "studies" / "distance_baseline.py"
)
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)


def _mean_rel(d: np.ndarray, c: float) -> float:
    return float(np.mean(np.abs(d - c) / d))


def test_best_constant_minimises_the_mean_relative_error() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        d = rng.uniform(0.3, 1.2, rng.integers(1, 60))
        c = bench.best_constant(d)
        grid = np.linspace(0.2, 1.3, 2001)
        assert _mean_rel(d, c) <= min(_mean_rel(d, g) for g in grid) + 1e-12


def test_rows_of_a_net_that_knows_the_distance() -> None:
    rng = np.random.default_rng(4)
    d = rng.uniform(0.4, 0.9, 200)
    r = bench.rows(d * 1.01, d, np.full(200, 1.0), np.full(200, 0.25), bench.constant_errors(d))
    assert r["log_correlation"] > 0.999 and r["constant_distance_pct"] > 10
    assert r["diameters"] == [d.min() / 0.25, d.max() / 0.25] and r["crops"] == 200


def test_norm_ratios_bin_by_the_viewpoint_error() -> None:
    p = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 2.0], [1.0, 0.0, 0.0]])
    tilt = np.radians(30.0)
    p_hat = np.array([[0.0, 0.0, 0.8], [0.0, 2 * np.sin(tilt), 2 * np.cos(tilt)], [0.0, 0.0, 0.5]])
    r = bench.norm_ratios(p, p_hat)
    assert r == {
        "0-10": {"crops": 1, "median": 0.8},
        "20-40": {"crops": 1, "median": 1.0},
        "80-181": {"crops": 1, "median": 0.5},
    }
