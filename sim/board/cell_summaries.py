"""A cell's figures from its report (`cell_summary`), the cells' summaries by estimator, sensor
and tier on one track (`summaries`), and the wall time of reports' episodes (`run_time_s`).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable

import numpy as np

from sim.board.tracks import BASE_TASK, NO_SHIFT
from sim.evaluation.stats import risk_coverage, wilson_interval

#: The ARs reported per cell, and against success.
AR_KEYS: tuple[str, ...] = ("ar_mssd", "ar_mspd", "ar_vsd")
#: Failure reasons shown per cell.
TOP_REASONS = 2


def run_time_s(reports: Iterable[dict]) -> float:
    """The wall time the reports' episodes took on their workers [s]: each episode's own wall
    time, summed and shared over the workers that ran them side by side. A cell that resumed
    from its journal, or that was read back, counts the episodes it holds, not the reading."""
    return sum(
        sum(e.get("wall_ms") or 0.0 for e in r.get("episodes", []))
        / 1000.0
        / (r.get("workers") or 1)
        for r in reports
    )


def _times_ms(report: dict) -> list[float]:
    """The estimator's time per image [ms]: a live estimator's as the episodes timed it; a CSV
    row's as the method's results file states it (BOP's ``time`` column, seconds)."""
    eps = report["episodes"]
    if "poses" in report:
        times = [(e.get("estimate_info") or {}).get("time") for e in eps]
        return [1000.0 * t for t in times if isinstance(t, int | float) and t >= 0]
    return [e["timings_ms"]["estimate"] for e in eps if "estimate" in e.get("timings_ms", {})]


def place_figures(report: dict) -> dict:
    """A place cell's placement figures (empty for a lift cell): the episodes that lifted the
    object (``lifted``) and, over them, the median distance [mm] and turn [deg] of where it
    rests from its goal (symmetry-aware; None when none lifted)."""
    if report.get("task", BASE_TASK) != "place":
        return {}
    placed = [e["place"]["errors"] for e in report["episodes"] if e.get("place")]
    out: dict = {"lifted": len(placed)}
    for key, name, scale in (
        ("translation_m", "place_translation_mm_median", 1000.0),
        ("rotation_deg", "place_rotation_deg_median", 1.0),
    ):
        values = [p[key] * scale for p in placed]
        out[name] = float(np.median(values)) if values else None
    return out


def cell_summary(report: dict) -> dict:
    """A cell's figures from its report: success with its Wilson interval, pose-correct rate,
    grasped with a wrong pose, the ARs, time per image [ms], the leading failure reasons, its
    episodes' wall time [s] and, in a place cell, `place_figures`."""
    g = report["overall"]
    eps = report["episodes"]
    lo, hi = wilson_interval(g["successes"], g["episodes"])
    times = _times_ms(report)
    reasons = Counter(e["failure_reason"] for e in eps if not e["success"])
    rc = (
        g["risk_coverage"]  # reports hold it; a cell written before they did is read too
        if "risk_coverage" in g
        else risk_coverage([e.get("confidence") for e in eps], [bool(e["success"]) for e in eps])
    )
    return {
        "episodes": g["episodes"],
        "successes": g["successes"],
        "success_rate": g["success_rate"],
        "wilson": [lo, hi],
        "pose_correct_rate": g["pose_correct"] / g["episodes"] if g["episodes"] else None,
        "grasped_wrong_pose": g["grasped_wrong_pose"],
        **{k: g.get(k) for k in AR_KEYS},
        "time_ms_median": float(np.median(times)) if times else None,
        "time_ms_p90": float(np.percentile(times, 90)) if times else None,
        "failures": reasons.most_common(TOP_REASONS),
        "risk_coverage": rc,
        "wall_s": run_time_s([report]),
        **place_figures(report),
    }


def on_track(cell: dict, task: str = BASE_TASK, shifts: str = NO_SHIFT) -> bool:
    """Whether a board's cell is of the track (a cell of a board from before tracks is of
    today's: ``lift``, no shift)."""
    return (cell.get("task", BASE_TASK), cell.get("shifts", NO_SHIFT)) == (task, shifts)


def summaries(
    cells: list[dict], task: str = BASE_TASK, shifts: str = NO_SHIFT
) -> dict[tuple[str, str, str], dict]:
    """The summaries of the track's cells (today's unless told) by (estimator, sensor, tier);
    cells that could not run left out."""
    return {
        (c["estimator"], c["sensor"], c["tier"]): c["summary"]
        for c in cells
        if c.get("summary") and on_track(c, task, shifts)
    }
