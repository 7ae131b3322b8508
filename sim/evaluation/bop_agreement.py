"""What BOP scores say about grasps: how pose errors and AR relate to grasp success.

Pure functions over `sim.evaluate` episodes and leaderboard cells (`sim.leaderboard`):

- `separation_auc`: how well one pose error separates the grasps that held from those that did
  not (the area under the ROC curve of "fails when the error is large", Mann-Whitney);
- `spearman_with_interval`: Spearman's rank correlation of AR against grasp success over cells,
  with a percentile bootstrap interval over the cells;
- `ar_for_success`: the AR at which a logistic fit of grasp success on AR reaches a target
  success (e.g. 95 %), per tier.

`study` applies them to `sim.evaluate` reports, each report one cell, and `format_study`
writes it as ``python -m sim.grasp_vs_bop`` prints it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from scipy.optimize import minimize
from scipy.stats import rankdata, spearmanr

from posegrasp.core.errors import InvalidArgumentError

#: The per-episode errors whose separation of success from failure is measured: name -> how to
#: read it from an episode (None when the episode has no estimate or lacks that error).
EPISODE_ERRORS: dict[str, Callable[[dict], float | None]] = {
    "MSSD": lambda e: _pose(e, "mssd_rel_diameter"),
    "MSPD": lambda e: _pose(e, "mspd_px"),
    "VSD": lambda e: None if e.get("vsd") is None else float(np.mean(e["vsd"])),
    "ADD-S": lambda e: _pose(e, "adi_m"),
    "along-ray": lambda e: _abs(_pose(e, "ray_m")),
    "across-ray": lambda e: _abs(_pose(e, "lateral_m")),
    "rotation": lambda e: _pose(e, "rotation_deg"),
}


def _pose(episode: dict, key: str) -> float | None:
    err = episode.get("pose_error")
    return None if not err or err.get(key) is None else float(err[key])


def _abs(v: float | None) -> float | None:
    return None if v is None else abs(v)


def separation_auc(errors: Sequence[float], success: Sequence[bool]) -> float | None:
    """The probability that a failed grasp's error exceeds a held grasp's (ties count half):
    1 when the error separates them perfectly, 0.5 when it says nothing.

    Args:
        errors: per episode, the pose error (larger is worse).
        success: per episode, whether the grasp held.

    Returns:
        The AUC, or None when either class is empty.

    Raises:
        InvalidArgumentError: the sequences differ in length.
    """
    if len(errors) != len(success):
        raise InvalidArgumentError(f"{len(errors)} errors for {len(success)} episodes")
    err = np.asarray(errors, float)
    held = np.asarray(success, bool)
    n_fail, n_held = int((~held).sum()), int(held.sum())
    if n_fail == 0 or n_held == 0:
        return None
    ranks = rankdata(err)
    # Mann-Whitney U of the failed episodes' errors against the held ones'.
    u = ranks[~held].sum() - n_fail * (n_fail + 1) / 2
    return float(u / (n_fail * n_held))


def episode_aucs(episodes: Sequence[dict]) -> dict[str, dict]:
    """`separation_auc` of each of `EPISODE_ERRORS` over the episodes that have it.

    Returns:
        error name -> ``{"auc": float | None, "episodes": n}``.
    """
    out = {}
    for name, read in EPISODE_ERRORS.items():
        pairs = [(v, bool(e["success"])) for e in episodes if (v := read(e)) is not None]
        auc = separation_auc([v for v, _ in pairs], [s for _, s in pairs]) if pairs else None
        out[name] = {"auc": auc, "episodes": len(pairs)}
    return out


def spearman_with_interval(
    x: Sequence[float], y: Sequence[float], boot: int = 2000, seed: int = 0
) -> dict[str, float | int | None]:
    """Spearman's rank correlation of x and y with a 95 % percentile bootstrap interval over the
    pairs (resamples whose ranks are constant are skipped).

    Returns:
        ``rho``, ``low``, ``high`` (None with fewer than 3 pairs or a constant side) and ``n``.
    """
    xa, ya = np.asarray(x, float), np.asarray(y, float)
    n = len(xa)
    none: dict[str, float | int | None] = {"rho": None, "low": None, "high": None, "n": n}
    if n < 3 or np.ptp(xa) == 0 or np.ptp(ya) == 0:
        return none
    rho = float(spearmanr(xa, ya).statistic)
    rng = np.random.default_rng(seed)
    draws = []
    for _ in range(boot):
        i = rng.integers(0, n, n)
        if np.ptp(xa[i]) > 0 and np.ptp(ya[i]) > 0:
            draws.append(spearmanr(xa[i], ya[i]).statistic)
    if not draws:
        return {**none, "rho": rho}
    low, high = np.percentile(draws, [2.5, 97.5])
    return {"rho": rho, "low": float(low), "high": float(high), "n": n}


def logistic_fit(ar: Sequence[float], successes: Sequence[int], episodes: Sequence[int]):
    """Maximum-likelihood fit of ``P(success) = 1 / (1 + exp(-(a + b * AR)))`` to binomial
    counts per cell. Returns (a, b)."""
    x = np.asarray(ar, float)
    k = np.asarray(successes, float)
    n = np.asarray(episodes, float)

    def nll(p: np.ndarray) -> float:
        z = p[0] + p[1] * x
        # -log-likelihood of k successes in n, written stably: log(1 + e^z) = logaddexp(0, z)
        return float(np.sum(n * np.logaddexp(0.0, z) - k * z))

    res = minimize(nll, np.zeros(2), method="Nelder-Mead", options={"xatol": 1e-8, "fatol": 1e-10})
    return float(res.x[0]), float(res.x[1])


def ar_for_success(
    ar: Sequence[float], successes: Sequence[int], episodes: Sequence[int], target: float = 0.95
) -> dict[str, float | str | None]:
    """The AR at which the logistic fit of success on AR over cells reaches `target`.

    Returns:
        ``ar`` (None when the fit does not reach the target within AR 0..1, or success does not
        rise with AR), ``a``, ``b`` (the fit) and ``note`` saying why there is no AR.
    """
    if len(ar) < 3 or np.ptp(np.asarray(ar, float)) == 0:
        return {"ar": None, "a": None, "b": None, "note": "fewer than 3 cells of distinct AR"}
    a, b = logistic_fit(ar, successes, episodes)
    if b <= 0:
        return {"ar": None, "a": a, "b": b, "note": "success does not rise with AR here"}
    need = (np.log(target / (1 - target)) - a) / b
    if not 0.0 <= need <= 1.0:
        note = (
            f"the fit stays below {target:.0%} up to AR 1"
            if need > 1
            else f"the fit is above {target:.0%} at every AR"
        )
        return {"ar": None, "a": a, "b": b, "note": note}
    return {"ar": float(need), "a": a, "b": b, "note": ""}


#: The reports' ARs (keys of a report's ``overall``) set against grasp success, and their names.
AR_NAMES: dict[str, str] = {"ar_mssd": "AR_MSSD", "ar_mspd": "AR_MSPD", "ar_vsd": "AR_VSD"}
#: The success whose AR is reported unless told otherwise.
DEFAULT_TARGET = 0.95
#: Bootstrap resamples of Spearman's interval unless told otherwise.
DEFAULT_BOOT = 2000


def cell_of(report: dict[str, Any], label: str) -> dict[str, Any]:
    """One report as a cell: what it ran, its successes and ARs, and its episodes' AUCs.

    Args:
        report: a `sim.evaluate` report (`sim.evaluation.report_schema`).
        label: how the study names it (its file).
    """
    g = report["overall"]
    return {
        "report": label,
        "estimator": report["estimator"],
        "tier": report["tier"],
        "sensor": report.get("sensor", "ideal"),
        "episodes": g["episodes"],
        "successes": g["successes"],
        "success_rate": g["success_rate"],
        **{key: g.get(key) for key in AR_NAMES},
        "auc": episode_aucs(report["episodes"]),
    }


def study(
    reports: Sequence[tuple[str, dict[str, Any]]],
    target: float = DEFAULT_TARGET,
    boot: int = DEFAULT_BOOT,
) -> dict[str, Any]:
    """What BOP scores say about the grasps of some `sim.evaluate` reports, each a cell.

    Args:
        reports: (label, report) pairs, at least one.
        target: the grasp success whose AR `ar_for_success` finds, in (0, 1).
        boot: bootstrap resamples of Spearman's interval.

    Returns:
        ``cells`` (`cell_of` of each report), ``pooled`` (the episodes of every report and their
        `episode_aucs`), and with several reports ``across_cells``: per AR, ``spearman``
        (`spearman_with_interval` of the AR against the success rate over the cells that have
        the AR) and ``ar_for_success`` (`ar_for_success` at `target`); None with one report.

    Raises:
        InvalidArgumentError: no report.
    """
    if not reports:
        raise InvalidArgumentError("no report to study; give one or more sim.evaluate reports")
    cells = [cell_of(report, label) for label, report in reports]
    pooled = [e for _, report in reports for e in report["episodes"]]
    across = None
    if len(cells) > 1:
        across = {}
        for key in AR_NAMES:
            pts = [c for c in cells if c[key] is not None]
            across[key] = {
                "spearman": spearman_with_interval(
                    [c[key] for c in pts], [c["success_rate"] for c in pts], boot
                ),
                "ar_for_success": ar_for_success(
                    [c[key] for c in pts],
                    [c["successes"] for c in pts],
                    [c["episodes"] for c in pts],
                    target,
                ),
            }
    return {
        "target": target,
        "cells": cells,
        "pooled": {"episodes": len(pooled), "auc": episode_aucs(pooled)},
        "across_cells": across,
    }


def _num(v: float | None, fmt: str = ".3f") -> str:
    return "-" if v is None else format(v, fmt)


def format_study(result: dict[str, Any]) -> str:
    """The study as text: the cells, the AUC table (cells and pooled) and, with several cells,
    Spearman's rho and the AR for the target success per AR."""
    cells = result["cells"]
    width = max(len("pooled"), *(len(c["report"]) for c in cells))
    lines = [
        f"{'report':<{width}}  {'estimator':<16} {'tier':<9} {'sensor':<16} episodes  success  "
        + "  ".join(f"{name:>7}" for name in AR_NAMES.values())
    ]
    for c in cells:
        lines.append(
            f"{c['report']:<{width}}  {c['estimator']:<16} {c['tier']:<9} {c['sensor']:<16} "
            f"{c['episodes']:>8}  {c['success_rate']:>7.3f}  "
            + "  ".join(f"{_num(c[key]):>7}" for key in AR_NAMES)
        )
    errors = list(EPISODE_ERRORS)
    lines += [
        "",
        "separation AUC of each pose error: the chance that a failed grasp's error exceeds a "
        "held one's (0.5: no separation; -: the error not measured, or no grasp failed or "
        "none held)",
        f"{'report':<{width}}  " + "  ".join(f"{name:>10}" for name in errors),
    ]
    rows = [(c["report"], c["auc"]) for c in cells]
    if len(cells) > 1:
        rows.append(("pooled", result["pooled"]["auc"]))
    for label, aucs in rows:
        lines.append(
            f"{label:<{width}}  " + "  ".join(f"{_num(aucs[e]['auc']):>10}" for e in errors)
        )
    across = result["across_cells"]
    if across is not None:
        target = result["target"]
        lines += ["", f"over the {len(cells)} reports as cells:"]
        for key, name in AR_NAMES.items():
            rho = across[key]["spearman"]
            interval = f" [{rho['low']:.2f}, {rho['high']:.2f}]" if rho["low"] is not None else ""
            spearman = (
                f"rho {rho['rho']:.2f}{interval} over {rho['n']} cells"
                if rho["rho"] is not None
                else f"rho - ({rho['n']} cells with this AR; needs 3 of varying AR and success)"
            )
            fit = across[key]["ar_for_success"]
            need = f"{fit['ar']:.2f}" if fit["ar"] is not None else f"- ({fit['note']})"
            lines.append(f"  {name:<8} {spearman}; AR for {target:.0%} success: {need}")
    return "\n".join(lines)
