"""The evaluation report as text: the sensor observed through, a table per object and overall
(success, pose errors, BOP's average recalls, times, failures), the risk-coverage area of the
estimator's confidence, the most frequent notes of each failure reason, and the friction margins
when measured.
"""

from __future__ import annotations

import re
from collections import Counter

from posegrasp.world.tiers import DEFAULT_TIER
from sim.episodes.episode import PLACE_TOLERANCE


def _ar(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


#: Most notes the summary shows per failure reason, and most characters of each.
NOTES_SHOWN, NOTE_CHARS = 3, 110


def failure_notes(episodes: list[dict], top: int = NOTES_SHOWN) -> dict[str, list[tuple[str, int]]]:
    """Why the episodes failed: per failure reason, its most frequent notes and how many failed
    episodes carry each (notes alike but for their numbers count as one, shown by the first).

    Args:
        episodes: the report's episodes.
        top: most notes per reason.

    Returns:
        reason -> [(note, episodes), ...], most frequent first; reasons without notes are left
        out.
    """
    counts: dict[str, Counter] = {}
    example: dict[tuple[str, str], str] = {}
    for e in episodes:
        if e["success"]:
            continue
        reason = str(e["failure_reason"])
        seen = set()
        for note in e.get("notes") or []:
            key = re.sub(r"-?\d+(?:\.\d+)?(?:e[-+]?\d+)?", "#", str(note))
            if key in seen:
                continue
            seen.add(key)
            counts.setdefault(reason, Counter())[key] += 1
            example.setdefault((reason, key), str(note))
    return {
        reason: [(example[(reason, key)], n) for key, n in c.most_common(top)]
        for reason, c in sorted(counts.items())
    }


def _one_line(note: str) -> str:
    line = " ".join(note.split())
    return line if len(line) <= NOTE_CHARS else line[: NOTE_CHARS - 3] + "..."


def area_line(groups: list[tuple[str, dict]]) -> str | None:
    """The risk-coverage area of each group (`sim.evaluation.stats.risk_coverage`, ``-`` for a group
    without a confidence), or that the estimator gives none; None for a report written before
    the area was recorded."""
    recorded = [(name, g["risk_coverage"]) for name, g in groups if "risk_coverage" in g]
    if not recorded:
        return None
    if all(rc is None for _, rc in recorded):
        return "risk-coverage area: none, the estimator gives no confidence"
    return "risk-coverage area (success over the attempts ranked by confidence): " + ", ".join(
        f"{name} {_ar(None if rc is None else rc['area'])}" for name, rc in recorded
    )


def format_report(report: dict) -> str:
    """The report as a table, headed by the sensor the episodes were observed through (the
    report's ``sensor``; ``ideal`` when it records none): per object and overall, success, pose
    errors, BOP's AR_MSSD, AR_MSPD and AR_VSD, times and failures; then the risk-coverage area
    (`area_line`) and the most frequent notes of each failure reason (`failure_notes`)."""
    rows = [
        f"estimator {report['estimator']}, tier {report.get('tier', DEFAULT_TIER)}, "
        f"sensor {report.get('sensor', 'ideal')}"
        + (f", task {report['task']}" if report.get("task", "lift") != "lift" else "")
        + (f", shifts {','.join(report['shifts'])}" if report.get("shifts") else "")
        + f": {report['episodes_per_object']} episodes per object, "
        f"seeds from {report['seed_start']}, {report['workers']} worker(s), "
        f"{report['wall_s']:.1f} s wall",
        f"{'object':<8} {'success':>8} {'rate':>6} {'wilson 95%':>15} {'t med mm':>9} "
        f"{'r med deg':>9} {'AR_MSSD':>7} {'AR_MSPD':>7} {'AR_VSD':>7} {'plan ms':>8} "
        f"{'ep ms':>7}  failures",
    ]
    items = [*report["per_object"].items(), ("overall", report["overall"])]
    for name, g in items:
        tm = g.get("translation_m_median")
        rm = g.get("rotation_deg_median")
        rows.append(
            f"{name:<8} {g['successes']:>4}/{g['episodes']:<3} {g['success_rate']:>6.1%} "
            f"[{g['wilson_low']:.3f}, {g['wilson_high']:.3f}] "
            f"{'-' if tm is None else f'{tm * 1000:.1f}':>9} "
            f"{'-' if rm is None else f'{rm:.2f}':>9} "
            f"{_ar(g['ar_mssd']):>7} {_ar(g['ar_mspd']):>7} {_ar(g.get('ar_vsd')):>7} "
            f"{g['planning_ms_median'] or 0:>8.1f} {g['episode_wall_ms_median'] or 0:>7.0f}  "
            + ", ".join(f"{k}: {v}" for k, v in g["failure_reasons"].items())
        )
    o = report["overall"]
    rows.append(
        f"pose right (BOP MSSD < 0.1 diameter) in {o['pose_correct']} of {o['pose_judged']} "
        f"estimates; grasped with a wrong pose: {o['grasped_wrong_pose']}; missed with a right "
        f"pose: {o['missed_right_pose']}"
    )
    if "lifted" in o:
        rows.append(place_line(o))
    if (area := area_line(items)) is not None:
        rows.append(area)
    notes = failure_notes(report["episodes"])
    if notes:
        rows.append("why episodes failed (most frequent notes, episodes with each):")
        for reason, top in notes.items():
            rows.extend(f"  {reason}: {n}x {_one_line(note)}" for note, n in top)
    rows.extend(margin_lines(items, report["overall"]))
    return "\n".join(rows)


def place_line(overall: dict) -> str:
    """The place task's line: how many of the lifted objects were placed, and where they rest
    from their goals (median and p90 over the lifted episodes)."""
    tm, rm = overall["place_translation_m_median"], overall["place_rotation_deg_median"]
    head = (
        f"placed within {PLACE_TOLERANCE[0] * 100:g} cm and {PLACE_TOLERANCE[1]:g} deg of the "
        f"goal: {overall['successes']} of {overall['lifted']} lifted; "
    )
    if tm is None:
        return head + "none lifted"
    return head + (
        f"where they rest, median {tm * 1000:.1f} mm and {rm:.1f} deg from the goal "
        f"(p90 {overall['place_translation_m_p90'] * 1000:.1f} mm, "
        f"{overall['place_rotation_deg_p90']:.1f} deg)"
    )


def margin_lines(items: list[tuple[str, dict]], overall: dict) -> list[str]:
    """The friction margins per group with their bootstrap intervals, and their Spearman
    correlation with the pose error (none when no margin was measured)."""
    rows: list[str] = []
    margins = [(n, g) for n, g in items if "friction_margin_mean" in g]
    if margins:
        rows.append("friction margin (lowest sliding friction that still holds; lower is firmer):")
        rows.extend(
            f"  {n:<8} {g['friction_margin_mean']:.3f} "
            f"[{g['friction_margin_low']:.3f}, {g['friction_margin_high']:.3f}] (bootstrap 95 %)"
            for n, g in margins
        )
        rho = overall.get("margin_error_spearman") or {}
        if any(rho.get(k) is not None for k in ("translation_m", "rotation_deg", "add_m")):
            rows.append(
                f"margin vs pose error, Spearman over {rho['episodes']} grasped episodes: "
                + ", ".join(
                    f"{k} {rho[k]:+.2f}"
                    for k in ("translation_m", "rotation_deg", "add_m")
                    if rho.get(k) is not None
                )
            )
    return rows
