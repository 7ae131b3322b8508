"""What BOP scores say about grasps: separation AUC, Spearman's interval, the AR for 95 %."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import mannwhitneyu

from posegrasp.core.errors import InvalidArgumentError
from sim.evaluation.bop_agreement import (
    ar_for_success,
    episode_aucs,
    logistic_fit,
    separation_auc,
    spearman_with_interval,
)
from sim.grasp_vs_bop import main

REPO = Path(__file__).resolve().parent.parent


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


# --- the command ---------------------------------------------------------------------------------


def _episode(i: int, success: bool, mssd: float | None) -> dict:
    """One episode of a hand-made report; `mssd` None: no estimate."""
    pose = None
    if mssd is not None:
        pose = {
            "mssd_rel_diameter": mssd,
            "mspd_px": 100 * mssd,
            "adi_m": mssd / 10,
            "ray_m": mssd / 10,
            "lateral_m": 0.0,
            "rotation_deg": 30 * mssd,
        }
    return {
        "object": "phone",
        "seed": 1_000_000_000 + i,
        "estimator": "hand",
        "tier": "isolated",
        "success": success,
        "failure_reason": None if success else ("slipped" if pose else "no_estimate"),
        "pose_error": pose,
        "notes": [],
        "timings_ms": {"total": 1.0},
        "wall_ms": 1.0,
    }


def _report(estimator: str, outcomes: list[tuple[bool, float | None]], ar: float) -> dict:
    """A small report of `sim.evaluate` made by hand: its episodes, and `ar` as every AR."""
    episodes = [_episode(i, ok, mssd) for i, (ok, mssd) in enumerate(outcomes)]
    n, k = len(episodes), sum(ok for ok, _ in outcomes)
    group = {
        "episodes": n,
        "successes": k,
        "success_rate": k / n,
        "wilson_low": 0.0,
        "wilson_high": 1.0,
        "failure_reasons": {},
        "pose_judged": n,
        "pose_correct": k,
        "grasped_wrong_pose": 0,
        "missed_right_pose": 0,
        "ar_mssd": ar,
        "ar_mspd": ar,
        "ar_vsd": ar,
        "episode_wall_ms_median": 1.0,
        "planning_ms_median": 1.0,
    }
    return {
        "schema": "posegrasp-evaluate-report-1",
        "estimator": estimator,
        "tier": "isolated",
        "noise": None,
        "obs_mode": "rgb",
        "execution": {},
        "seed_start": 1_000_000_000,
        "episodes_per_object": n,
        "workers": 1,
        "wall_s": 1.0,
        "per_object": {"phone": group},
        "overall": group,
        "episodes": episodes,
    }


#: Three cells: the better the AR, the more grasps hold; within each, the failed grasps' MSSD
#: above the held ones' (a perfect separation).
CELLS = {
    "low.json": _report("low", [(True, 0.05), (False, 0.4), (False, 0.5), (False, None)], 0.2),
    "mid.json": _report("mid", [(True, 0.05), (True, 0.08), (False, 0.3), (False, 0.6)], 0.5),
    "high.json": _report("high", [(True, 0.01), (True, 0.02), (True, 0.04), (False, 0.2)], 0.8),
}


def _write(folder: Path) -> list[str]:
    paths = []
    for name, report in CELLS.items():
        (folder / name).write_text(json.dumps(report))
        paths.append(str(folder / name))
    return paths


def test_the_command_studies_each_report_pooled_and_across_cells(tmp_path, capsys) -> None:
    paths = _write(tmp_path)
    assert main([*paths, "--json", "-", "--boot", "200"]) == 0
    captured = capsys.readouterr()
    got = json.loads(captured.out)  # the JSON alone on standard output
    assert [c["report"] for c in got["cells"]] == list(CELLS)
    for cell, report in zip(got["cells"], CELLS.values(), strict=True):
        assert cell["auc"] == episode_aucs(report["episodes"])
        assert cell["auc"]["MSSD"]["auc"] == 1.0
    pooled = [e for r in CELLS.values() for e in r["episodes"]]
    assert got["pooled"] == {"episodes": 12, "auc": episode_aucs(pooled)}
    ar = got["across_cells"]["ar_mssd"]
    assert ar["spearman"]["rho"] == pytest.approx(1.0) and ar["spearman"]["n"] == 3
    want = ar_for_success([0.2, 0.5, 0.8], [1, 2, 3], [4, 4, 4], 0.95)
    assert ar["ar_for_success"] == pytest.approx(want)
    text = captured.err  # the summary, on standard error
    assert "pooled" in text and "over the 3 reports as cells" in text and "rho 1.00" in text


def test_one_report_is_studied_alone_and_printed(tmp_path, capsys) -> None:
    path = _write(tmp_path)[1]
    assert main([path]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert lines[0].startswith("report") and "AR_MSSD" in lines[0]
    (auc_row,) = [x for x in lines if x.startswith("mid.json") and "1.000" in x]
    assert "pooled" not in out and "cells" not in out
    assert auc_row.split()[1] == "1.000"  # MSSD separates this report's grasps perfectly


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        ([], "the following arguments are required: REPORT"),
        (["{tmp}/missing.json"], "invalid report '{tmp}/missing.json': no such file"),
        (["{tmp}"], "a folder"),
        (["{tmp}/bad.json"], "{tmp}/bad.json is not a report of python -m sim.evaluate --json"),
        (["{tmp}/other.json"], "other.json names no schema"),
        (["{tmp}/low.json", "{tmp}/cut.json"], "cut.json lacks the field episodes[2].success"),
        (["{tmp}/stopped.json"], "stopped.json holds 1 episodes stopped by an interruption"),
        (["{tmp}/low.json", "--target", "1.5"], "--target"),
    ],
)
def test_the_command_refuses_bad_input_in_one_line(argv, needle, tmp_path, capsys) -> None:
    _write(tmp_path)
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "other.json").write_text('{"episodes": []}')
    cut = json.loads(json.dumps(CELLS["mid.json"]))
    del cut["episodes"][2]["success"]
    (tmp_path / "cut.json").write_text(json.dumps(cut))
    stopped = json.loads(json.dumps(CELLS["mid.json"]))
    stopped["episodes"][1] |= {"failure_reason": "error", "notes": ["Interrupted: SIGTERM"]}
    (tmp_path / "stopped.json").write_text(json.dumps(stopped))
    tmp = str(tmp_path)
    assert main([a.replace("{tmp}", tmp) for a in argv]) == 2
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and captured.out == ""
    assert needle.replace("{tmp}", tmp) in lines[0]


def test_the_command_as_a_process_answers_help_and_a_missing_file(tmp_path) -> None:
    def run(*args: str) -> subprocess.CompletedProcess[str]:
        cmd = [sys.executable, "-m", "sim.grasp_vs_bop", *args]
        return subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=120)

    helped = run("--help")
    assert helped.returncode == 0 and "separates held grasps from failed ones" in helped.stdout
    missing = run(str(tmp_path / "none.json"))
    assert missing.returncode == 2 and missing.stdout == ""
    assert missing.stderr.startswith("error: ") and len(missing.stderr.splitlines()) == 1
