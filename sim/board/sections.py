"""The page's paired sections (`sim.board.pairs`): each pair of estimators in each cell, each
estimator under each scene shift against itself unshifted with the oracle's check, and success
against the estimate's error on the lift and place tracks.
"""

from __future__ import annotations

from sim.board.pairs import ALPHA, CEILING, ORACLE
from sim.board.tracks import NO_SHIFT, track_title


def _p(p: float) -> str:
    return f"{p:.2g}" if p >= 0.001 else "<0.001"


def pair_section(board: dict) -> list[str]:
    """A table per track: every pair of estimators but the oracle in each (tier, sensor) cell,
    their successes, the discordant episodes, McNemar's p and, on the place task, the
    signed-rank test of placement errors, and the verdict."""
    pairs = board["analysis"].get("pairs")
    if pairs is None:  # a board from before pairs
        return []
    if not pairs:
        return ["## Pairs of estimators", "", "No cell holds two estimators but the oracle.", ""]
    lines = [
        "## Pairs of estimators",
        "",
        "Each pair of estimators (the oracle left out) in each cell, on the same episodes: A > B",
        f"where McNemar's exact test of their paired successes gives p < {ALPHA} (on the place",
        f"task also the Wilcoxon signed-rank test of their placement errors, p < {ALPHA}, the same",
        "way; where only one test is, the verdict says which), else tied; tied at the ceiling",
        f"where both succeed on at least {CEILING * 120:.0f}/120 of the episodes. The placement",
        "error is the MSSD of where the object rests from its goal; an episode that never lifted",
        "the object ranks worst (a pair where both never lifted it is a tie).",
        "",
    ]
    for track in dict.fromkeys((r["task"], r["shifts"]) for r in pairs):
        place = track[0] == "place"
        rank_head = " rank p (R-, R+) |" if place else ""
        lines += [
            f"### {track_title(*track)}",
            "",
            f"| tier | sensor | A | B | successes A, B | only A, only B | McNemar p |{rank_head} "
            "verdict |",
            "|" + "---|" * (9 if place else 8),
        ]
        for r in pairs:
            if (r["task"], r["shifts"]) != track:
                continue
            m, rank = r["mcnemar"], r["rank"]
            ranked = f" {_p(rank['p'])} ({rank['r_minus']:g}, {rank['r_plus']:g}) |" if rank else ""
            lines.append(
                f"| {r['tier']} | {r['sensor']} | {r['a']} | {r['b']} "
                f"| {m['a']}, {m['b']} of {m['episodes']} | {m['a_only']}, {m['b_only']} "
                f"| {_p(m['p'])} |{ranked} {r['verdict']} |"
            )
        lines.append("")
    return lines


def _oracle_line(check: dict) -> str:
    if not check["rows"]:
        return "The board has no oracle row under a shift to check the shifts by."
    if not check["changed"]:
        return (
            f"The oracle's row shows no change: in all {check['rows']} of its shifted cells every "
            "episode ends as it does unshifted (a shift changes only what the camera sees)."
        )
    return (
        "Warning: the oracle's episodes change under a shift, which should change only what the "
        f"camera sees: {'; '.join(check['changed'])}."
    )


def drop_section(board: dict) -> list[str]:
    """A table per (task, sensor, tier): each estimator's success unshifted and under each
    shift on the same seeds, with the drop and McNemar's p; then whether the oracle's row is
    unchanged."""
    drops = board["analysis"].get("drops") or []
    if not drops:
        return []
    lines = [
        "## Scene shifts: the drop per factor",
        "",
        "Each estimator's success under each scene shift against its own without it, on the same",
        "seeds: successes, the drop in percentage points (positive: the shift hurts) and",
        "McNemar's exact p of the paired episodes.",
        "",
        _oracle_line(board["analysis"]["oracle_shifts"]),
        "",
    ]
    for task, sensor, tier in dict.fromkeys((d["task"], d["sensor"], d["tier"]) for d in drops):
        rows = [d for d in drops if (d["task"], d["sensor"], d["tier"]) == (task, sensor, tier)]
        shifts = list(dict.fromkeys(d["shifts"] for d in rows))
        lines += [
            f"### {task}, {tier}, sensor `{sensor}`",
            "",
            f"| estimator | {NO_SHIFT} | " + " | ".join(shifts) + " |",
            "|---|---|" + "---|" * len(shifts),
        ]
        for name in dict.fromkeys(d["estimator"] for d in rows):
            mine = {d["shifts"]: d for d in rows if d["estimator"] == name}
            first = next(iter(mine.values()))
            cols = [
                "-"
                if s not in mine
                else f"{mine[s]['shifted']}/{mine[s]['episodes']}, drop "
                f"{100 * mine[s]['drop']:.0f} pp, p {_p(mine[s]['p'])}"
                for s in shifts
            ]
            label = f"{name} (instrument)" if name == ORACLE else name
            lines.append(
                f"| {label} | {first['base']}/{first['episodes']} | " + " | ".join(cols) + " |"
            )
        lines.append("")
    return lines


def error_section(board: dict, plots: str) -> list[str]:
    """Lift and place success against the estimate's error, on a board with the place task."""
    if "place" not in (board["analysis"].get("success_by_error") or {}):
        return []
    return [
        "## Lift and place against the estimate's error",
        "",
        f"![success against the estimate's error]({plots}/success_vs_error.png)",
        "",
        "Success against the estimate's translation and rotation error, binned, over every",
        "estimator's episodes but the oracle's (95 % Wilson intervals): lift (held) beside place",
        "(resting within 2 cm and 10 deg of the goal). The place task asks more of the same pose:",
        "the robot carries the object as the estimate says it lies in the hand.",
        "",
    ]
