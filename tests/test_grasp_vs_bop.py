"""What BOP scores say about grasps: separation AUC, Spearman's interval, the AR for 95 %."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import mannwhitneyu

from posegrasp.core.errors import InvalidArgumentError
from sim.grasp_vs_bop import (
    ar_for_success,
    episode_aucs,
    logistic_fit,
    separation_auc,
    spearman_with_interval,
)


def test_separation_auc_is_mann_whitney_u_over_the_pairs() -> None:
    rng = np.random.default_rng(0)
    err = rng.gamma(2.0, 1.0, 80).round(1)  # ties on purpose
    held = rng.random(80) < 1 / (1 + err)
    u = mannwhitneyu(err[~held], err[held]).statistic
    assert separation_auc(err, held) == pytest.approx(u / ((~held).sum() * held.sum()))


def test_perfect_useless_and_one_sided_separation() -> None:
    assert separation_auc([1, 2, 3, 4], [True, True, False, False]) == 1.0
    assert separation_auc([1, 2, 3, 4], [False, False, True, True]) == 0.0
    assert separation_auc([2, 2, 2, 2], [True, False, True, False]) == 0.5
    assert separation_auc([1, 2], [True, True]) is None
    with pytest.raises(InvalidArgumentError, match="3 errors for 2 episodes"):
        separation_auc([1, 2, 3], [True, False])


def test_episode_aucs_read_each_error_and_skip_episodes_without_a_pose() -> None:
    def ep(mssd: float, ok: bool) -> dict:
        pose = {
            "mssd_rel_diameter": mssd,
            "mspd_px": 1.0,
            "adi_m": mssd,
            "ray_m": -mssd,
            "lateral_m": 0.0,
            "rotation_deg": 10 * mssd,
        }
        return {"success": ok, "pose_error": pose, "vsd": [mssd] * 10}

    eps = [ep(0.01, True), ep(0.02, True), ep(0.3, False), {"success": False, "pose_error": None}]
    aucs = episode_aucs(eps)
    for name in ("MSSD", "VSD", "ADD-S", "along-ray", "rotation"):
        assert aucs[name] == {"auc": 1.0, "episodes": 3}, name
    assert aucs["MSPD"]["auc"] == 0.5 and aucs["across-ray"]["auc"] == 0.5


def test_spearman_interval_contains_rho_and_needs_three_varying_pairs() -> None:
    x = np.linspace(0, 1, 12)
    y = x + np.random.default_rng(1).normal(0, 0.2, 12)
    r = spearman_with_interval(x, y, boot=500)
    assert r["low"] <= r["rho"] <= r["high"] and r["n"] == 12 and r["rho"] > 0.5
    assert spearman_with_interval([1, 2], [1, 2])["rho"] is None
    assert spearman_with_interval([1, 2, 3], [5, 5, 5])["rho"] is None


def test_the_logistic_fit_recovers_its_parameters_and_inverts_to_the_target() -> None:
    ar = np.linspace(0.1, 0.9, 9)
    a, b = -4.0, 10.0
    n = np.full(9, 100_000)
    k = np.round(n / (1 + np.exp(-(a + b * ar)))).astype(int)
    fa, fb = logistic_fit(ar, k, n)
    assert (fa, fb) == pytest.approx((a, b), abs=0.02)
    got = ar_for_success(ar, k, n, 0.95)
    assert got["ar"] == pytest.approx((np.log(19) - a) / b, abs=0.005)


def test_no_ar_when_success_does_not_rise_or_never_reaches_the_target() -> None:
    ar = [0.2, 0.5, 0.8]
    assert "does not rise" in ar_for_success(ar, [9, 5, 1], [10, 10, 10])["note"]
    assert "below 95%" in ar_for_success(ar, [1, 2, 3], [10, 10, 10])["note"]
    assert ar_for_success([0.5, 0.5, 0.5], [1, 2, 3], [10] * 3)["ar"] is None


def test_spearman_without_a_varying_resample_has_rho_and_no_interval() -> None:
    # Seed 4's one resample of three pairs draws pair 2 thrice: constant ranks, so no interval.
    r = spearman_with_interval([1, 2, 3], [1, 3, 2], boot=1, seed=4)
    assert (r["rho"], r["low"], r["high"], r["n"]) == (pytest.approx(0.5), None, None, 3)
