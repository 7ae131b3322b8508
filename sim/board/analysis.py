"""What the leaderboard says: what BOP scores tell of grasps over its lift cells, its cells
paired episode by episode (`sim.board.pairs`) (`analyse`), and its findings in plain words
(`findings`), every figure read from the board.
"""

from __future__ import annotations

from sim.board.cell_summaries import AR_KEYS, summaries
from sim.board.pairs import (
    ALPHA,
    ORACLE,
    drop_table,
    oracle_under_shifts,
    pair_tables,
    success_by_error,
)
from sim.board.tracks import BASE_TASK
from sim.episodes.registry import CLASSICAL_PEERS
from sim.episodes.registry import DEFAULT_ESTIMATOR as OURS
from sim.evaluation.bop_agreement import ar_for_success, episode_aucs, spearman_with_interval

#: The success a method should reach; the AR that predicts it is reported per tier.
TARGET_SUCCESS = 0.95


def analyse(cells: list[dict], reports: dict[str, dict]) -> dict:
    """What the board says. What BOP scores say about grasps, over the lift cells (every shift;
    a place cell's success is more than the grasp's): per AR, Spearman's rho of AR against
    success over the cells; per tier, each error's separation AUC over the episodes of every
    estimator but the oracle, and the AR that a logistic fit says gives `TARGET_SUCCESS`. Then
    the paired tables of `sim.board.pairs`: ``pairs`` (`pair_tables`), ``drops``
    (`drop_table`), ``oracle_shifts`` (`oracle_under_shifts`) and ``success_by_error``."""
    scored = [
        c
        for c in cells
        if c.get("summary") and c["estimator"] != ORACLE and c.get("task", BASE_TASK) == BASE_TASK
    ]
    drops = drop_table(cells, reports)
    out: dict = {
        "spearman": {},
        "auc": {},
        "ar_for_success": {},
        "pairs": pair_tables(cells, reports),
        "drops": drops,
        "oracle_shifts": oracle_under_shifts(drops),
        "success_by_error": success_by_error(cells, reports),
    }
    for key in AR_KEYS:
        pts = [c for c in scored if c["summary"][key] is not None]
        out["spearman"][key] = spearman_with_interval(
            [c["summary"][key] for c in pts], [c["summary"]["success_rate"] for c in pts]
        )
    for tier in dict.fromkeys(c["tier"] for c in scored):
        in_tier = [c for c in scored if c["tier"] == tier]
        runs = dict.fromkeys(c["run_key"] for c in in_tier)
        episodes = [e for k in runs for e in reports[k]["episodes"]]
        out["auc"][tier] = episode_aucs(episodes)
        out["ar_for_success"][tier] = {}
        for key in AR_KEYS:
            pts = [c["summary"] for c in in_tier if c["summary"][key] is not None]
            out["ar_for_success"][tier][key] = ar_for_success(
                [p[key] for p in pts],
                [p["successes"] for p in pts],
                [p["episodes"] for p in pts],
                TARGET_SUCCESS,
            )
    return out


def findings(board: dict) -> list[str]:
    """The board's findings in plain words, every figure read from the board: `OURS` against
    the classical depth peers per sensor (success and time per image), how closely the ARs rank
    the cells, which per-episode error separates grasps best and worst, and the AR needed."""
    by = summaries(board["cells"])
    out = ["## In short", ""]
    for sensor in board["sensors"]:
        groups = [(t, by[OURS, sensor, t]) for t in board["tiers"] if (OURS, sensor, t) in by]
        peers = [p for p in CLASSICAL_PEERS if any((p, sensor, t) in by for t, _ in groups)]
        if not groups or not peers:
            continue
        lost: list[str] = []
        ratios: dict[str, list[float]] = {p: [] for p in peers}
        for tier, ours in groups:
            theirs = {p: by[p, sensor, tier] for p in peers if (p, sensor, tier) in by}
            best = max(theirs, key=lambda p: theirs[p]["successes"])
            if theirs[best]["successes"] > ours["successes"]:
                lost.append(
                    f"{tier} ({best} {theirs[best]['successes']} against {ours['successes']})"
                )
            for p, m in theirs.items():
                if m["time_ms_median"]:
                    ratios[p].append(ours["time_ms_median"] / m["time_ms_median"])
        wins = len(groups) - len(lost)
        spans = [f"{p}'s {min(r):.2f}-{max(r):.2f}" for p, r in ratios.items() if r]
        out.append(
            f"- Under `{sensor}`, `{OURS}` (RGB only) grasps at least as often as every classical "
            f"depth peer on {wins} of {len(groups)} tiers"
            + (f"; a peer grasps more on {'; '.join(lost)}" if lost else "")
            + ". Its median time per image, as a share of each peer's over the tiers: "
            + ", ".join(spans)
            + "."
        )
    if len(out) == 2:
        out.append(f"- No classical depth peer shares a sensor with `{OURS}` on this board.")
    a = board["analysis"]
    rhos = [(k, r) for k, r in a["spearman"].items() if r["rho"] is not None]
    if rhos:
        out.append(
            f"- Over {rhos[0][1]['n']} cells, BOP's ARs rank the cells by grasp success closely: "
            + ", ".join(f"{k.upper()} rho {r['rho']:.2f}" for k, r in rhos)
            + "."
        )
    for tier, aucs in a["auc"].items():
        known = {e: v["auc"] for e, v in aucs.items() if v["auc"] is not None}
        if known:
            hi, lo = max(known, key=known.__getitem__), min(known, key=known.__getitem__)
            out.append(
                f"- On {tier}, the per-episode error that separates held grasps from failed ones "
                f"best is {hi} (AUC {known[hi]:.2f}), the worst {lo} ({known[lo]:.2f})."
            )
    need = {
        t: f["ar_mssd"]["ar"]
        for t, f in a["ar_for_success"].items()
        if f["ar_mssd"]["ar"] is not None
    }
    if need:
        lo_t, hi_t = min(need, key=need.__getitem__), max(need, key=need.__getitem__)
        out.append(
            f"- For {TARGET_SUCCESS:.0%} grasps a method needs AR_MSSD of about {need[lo_t]:.2f} "
            f"({lo_t}) to {need[hi_t]:.2f} ({hi_t})."
        )
    return [*out, *paired_findings(a), ""]


def paired_findings(a: dict) -> list[str]:
    """The paired tables in plain words (none on a board without them): how many pairs of
    estimators differ and how many are tied (at the ceiling), and the largest drop under a
    scene shift with its McNemar p."""
    out = []
    if pairs := a.get("pairs"):
        verdicts = [p["verdict"] for p in pairs]
        ceiling = verdicts.count("tied at the ceiling")
        tied = verdicts.count("tied") + ceiling
        out.append(
            f"- Of {len(pairs)} pairs of estimators in the cells, {len(pairs) - tied} differ on "
            f"the same episodes (McNemar p < {ALPHA}; on the place task with the rank test), "
            f"{tied} are tied ({ceiling} at the ceiling)."
        )
    shown = [d for d in a.get("drops") or [] if d["estimator"] != ORACLE and d["drop"]]
    if shown:
        d = max(shown, key=lambda d: d["drop"])
        out.append(
            f"- The largest drop under a scene shift: {d['estimator']} under {d['shifts']} "
            f"({d['task']}, {d['tier']}, `{d['sensor']}`) from {d['base']} to {d['shifted']} of "
            f"{d['episodes']} (McNemar p {d['p']:.2g})."
        )
    return out
