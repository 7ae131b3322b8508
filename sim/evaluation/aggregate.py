"""The evaluation report of finished episodes: per object and overall, success with its Wilson
interval, pose errors, BOP's average recalls, the risk-coverage curve of the estimator's
confidence, friction margins and times.

Pure functions of the episode records (`sim.episodes.episode.EpisodeResult.to_json` plus
``wall_ms``); nothing here runs an episode.
"""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np

from perception import metrics
from sim.episodes.episode import execution_settings
from sim.evaluation.protocol import Protocol
from sim.evaluation.report_schema import REPORT_SCHEMA, validate_report
from sim.evaluation.stats import (
    BOOTSTRAP,
    bootstrap_means,
    margin_error_correlation,
    risk_coverage,
    wilson_interval,
)

#: The head camera's width the episodes render at [px] (BOP scales MSPD's thresholds by it).
IMAGE_WIDTH = 640


def bop_scores(episodes: list[dict]) -> dict[str, float | None]:
    """BOP 2019's average recalls of the episodes' estimates: AR_MSSD (thresholds 0.05..0.5 of
    the diameter), AR_MSPD (5..50 px at 640 px width) and AR_VSD (the episodes' ``vsd``, taus
    and thresholds 0.05..0.5); an episode without an estimate, whose MSPD is infinite or
    without ``vsd`` counts as a miss. None for no episodes (AR_VSD also when no episode has a
    ``vsd``, as in reports written before episodes recorded it)."""
    if not episodes:
        return {"ar_mssd": None, "ar_mspd": None, "ar_vsd": None}

    def err(e: dict, key: str) -> float | None:
        return (e.get("pose_error") or {}).get(key)

    vsd = [e.get("vsd") for e in episodes]
    return {
        "ar_mssd": metrics.ar_mssd([err(e, "mssd_rel_diameter") for e in episodes], 1.0),
        "ar_mspd": metrics.ar_mspd([err(e, "mspd_px") for e in episodes], IMAGE_WIDTH),
        "ar_vsd": metrics.ar_vsd(vsd) if any(v is not None for v in vsd) else None,
    }


def group_summary(episodes: list[dict], task: str = "lift") -> dict[str, Any]:
    """The aggregates of a group of episodes (one object's, or all): successes, rate and Wilson
    95 % interval, failure reasons, median and 90th-percentile pose errors ([m], [deg]), friction
    margin mean with its bootstrap 95 % interval and its Spearman correlation with the pose
    error (when measured), how often pose and grasp disagree, `bop_scores`, on the place `task`
    `place_summary`,
    the risk-coverage
    curve of the estimates' confidences with its area (``risk_coverage``,
    `sim.evaluation.stats.risk_coverage`; None when no episode has a confidence), and the median
    episode wall time and planning time [ms]."""
    n = len(episodes)
    k = sum(bool(e["success"]) for e in episodes)
    lo, hi = wilson_interval(k, n)
    reasons = Counter(e["failure_reason"] for e in episodes if not e["success"])
    out: dict[str, Any] = {
        "episodes": n,
        "successes": k,
        "success_rate": k / n if n else 0.0,
        "wilson_low": lo,
        "wilson_high": hi,
        "failure_reasons": dict(sorted(reasons.items())),
    }
    errs = [e["pose_error"] for e in episodes if e.get("pose_error")]
    if errs:
        for key in ("translation_m", "rotation_deg"):
            v = np.array([x[key] for x in errs])
            out[f"{key}_median"] = float(np.median(v))
            out[f"{key}_p90"] = float(np.percentile(v, 90))
    margins = np.array([e["friction_margin"] for e in episodes if e.get("friction_margin")])
    if margins.size:
        boot = bootstrap_means(margins, BOOTSTRAP, np.random.default_rng(0))
        out["friction_margin_mean"] = float(margins.mean())
        out["friction_margin_low"], out["friction_margin_high"] = (
            float(v) for v in np.percentile(boot, [2.5, 97.5])
        )
        out["margin_error_spearman"] = margin_error_correlation(episodes)
    judged = [e for e in episodes if e.get("pose_correct") is not None]
    out["pose_judged"] = len(judged)
    out["pose_correct"] = sum(bool(e["pose_correct"]) for e in judged)
    # The grasp and the pose disagree: held on a wrong pose, or dropped on a right one.
    out["grasped_wrong_pose"] = sum(bool(e["success"]) and not e["pose_correct"] for e in judged)
    out["missed_right_pose"] = sum(not e["success"] and bool(e["pose_correct"]) for e in judged)
    out.update(bop_scores(episodes))
    if task == "place":
        out.update(place_summary(episodes))
    out["risk_coverage"] = risk_coverage(
        [e.get("confidence") for e in episodes], [bool(e["success"]) for e in episodes]
    )
    walls = [e["wall_ms"] for e in episodes]
    plans = [e["timings_ms"]["ik"] for e in episodes if "ik" in e.get("timings_ms", {})]
    out["episode_wall_ms_median"] = float(np.median(walls)) if walls else None
    out["planning_ms_median"] = float(np.median(plans)) if plans else None
    return out


def place_summary(episodes: list[dict]) -> dict[str, Any]:
    """The place task's aggregates: how many episodes lifted the object (``lifted``: those
    that went on to place it), and over them the median and 90th percentile of where it came to
    rest against its goal, symmetry-aware (``place_translation_m_*`` [m],
    ``place_rotation_deg_*`` [deg]; None when none lifted)."""
    placed = [e["place"] for e in episodes if e.get("place")]
    out: dict[str, Any] = {"lifted": len(placed)}
    for key in ("translation_m", "rotation_deg"):
        v = np.array([p["errors"][key] for p in placed])
        out[f"place_{key}_median"] = float(np.median(v)) if v.size else None
        out[f"place_{key}_p90"] = float(np.percentile(v, 90)) if v.size else None
    return out


def make_report(
    episodes: list[dict],
    protocol: Protocol,
    estimator: str,
    workers: int = 1,
    wall_s: float = 0.0,
) -> dict[str, Any]:
    """The report (schema `sim.evaluation.report_schema.REPORT_SCHEMA`, checked) of finished
    episodes.

    Args:
        episodes: the episode records, in run order.
        protocol: the evaluation they belong to; its objects name the ``per_object`` groups.
        estimator: what the report calls the estimator (`sim.evaluation.harness.estimator_label`).
        workers: the processes (or Ray CPUs) that ran them.
        wall_s: the evaluation's wall time [s].

    Returns:
        The protocol (``distractor_pool``, ``candidates`` and ``sensor`` only away from their
        defaults, `Protocol.recorded_apart`), the aggregates per object and overall
        (`group_summary`) and the episodes.
    """
    return validate_report(
        {
            "schema": REPORT_SCHEMA,
            "estimator": estimator,
            "tier": protocol.tier,
            "noise": protocol.noise,
            "obs_mode": protocol.obs_mode,
            "execution": execution_settings(),
            "seed_start": protocol.seed_start,
            "episodes_per_object": protocol.episodes,
            "workers": workers,
            "wall_s": wall_s,
            "per_object": {
                o: group_summary([e for e in episodes if e["object"] == o], protocol.task)
                for o in protocol.objects
            },
            "overall": group_summary(episodes, protocol.task),
            "episodes": episodes,
            **protocol.recorded_apart(),
        },
        "the evaluation's report",
    )
