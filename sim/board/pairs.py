"""What the board's cells say paired episode by episode (every cell plays the same seeds): each
pair of estimators in a cell (`pair_tables`), each estimator under each shift against itself
unshifted (`drop_table`, with the oracle's rows checked by `oracle_under_shifts`), and success
against the estimate's error on the lift and place tracks (`success_by_error`).

An episode's placement error is the MSSD [m] of where the object rests from its goal
(symmetry-aware, the place record's ``errors.mssd_m``); an episode that never lifted the object
has none and counts as the worst (``inf``, `sim.evaluation.stats.wilcoxon_worst_ranked`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from sim.board.tracks import BASE_TASK, NO_SHIFT
from sim.evaluation.stats import mcnemar_paired, wilcoxon_worst_ranked

#: Significance level of the pair and drop tables.
ALPHA = 0.05
#: Two estimators that both succeed on at least this share of episodes (119 of 120) are tied at
#: the ceiling.
CEILING = 119 / 120
#: The estimator that is the experiment's instrument: never paired, its shifts checked.
ORACLE = "oracle"
#: Bin edges of the estimate's translation error [mm] and rotation error [deg] of
#: `success_by_error`; the last bin is open.
ERROR_BINS = {
    "translation_mm": (0.0, 5.0, 10.0, 20.0, 40.0, 80.0),
    "rotation_deg": (0.0, 2.0, 5.0, 10.0, 20.0, 45.0, 90.0),
}

Outcomes = dict[tuple[str, int], tuple[bool, float]]


def episode_outcomes(report: dict) -> Outcomes:
    """Per (object, seed): whether the episode succeeded and its placement error [m] (the MSSD
    of where the object rests from its goal; ``inf`` where it was never lifted, or on the lift
    task)."""
    out: Outcomes = {}
    for e in report["episodes"]:
        place = e.get("place")
        error = place["errors"]["mssd_m"] if place else math.inf
        out[e["object"], int(e["seed"])] = (bool(e["success"]), float(error))
    return out


def compare_pair(a: Outcomes, b: Outcomes, place: bool) -> dict:
    """A against B on the episodes both played: McNemar's exact test of their successes and, on
    the place task, the signed-rank test of their placement errors (failures ranked worst).

    Returns:
        ``mcnemar`` (`sim.evaluation.stats.mcnemar_paired`) and ``rank``
        (`sim.evaluation.stats.wilcoxon_worst_ranked`; None on the lift task).
    """
    keys = sorted(set(a) & set(b))
    ok_a, ok_b = [a[k][0] for k in keys], [b[k][0] for k in keys]
    rank = None
    if place:
        rank = wilcoxon_worst_ranked([a[k][1] for k in keys], [b[k][1] for k in keys])
    return {"mcnemar": mcnemar_paired(ok_a, ok_b), "rank": rank}


def verdict(name_a: str, name_b: str, test: dict) -> str:
    """What a pair's tests (`compare_pair`) say: ``A > B`` where A is significantly better
    (McNemar p < `ALPHA`, and on the place task also the rank test's, the same way), else
    ``tied``, ``tied at the ceiling`` (both at least `CEILING`), or, on the place task where
    one test alone is significant, which way and by which test."""
    m, r = test["mcnemar"], test["rank"]
    n = m["episodes"]

    def better(a_wins: bool) -> str:
        return f"{name_a} > {name_b}" if a_wins else f"{name_b} > {name_a}"

    by_success = better(m["a_only"] > m["b_only"]) if m["p"] < ALPHA else None
    by_rank = better(r["r_minus"] > r["r_plus"]) if r and r["p"] < ALPHA else None
    if r is None and by_success:
        return by_success
    if by_success and by_rank:
        if by_success == by_rank:
            return by_success
        return f"mixed: {by_success} in successes, {by_rank} in error"
    if by_success or by_rank:
        return f"{by_success} in successes only" if by_success else f"{by_rank} in error only"
    if n and min(m["a"], m["b"]) >= CEILING * n:
        return "tied at the ceiling"
    return "tied"


def _groups(cells: list[dict]) -> dict[tuple[str, str, str, str], list[dict]]:
    """The cells that ran, by (tier, sensor, task, shifts), in board order."""
    out: dict[tuple[str, str, str, str], list[dict]] = {}
    for c in cells:
        if c.get("summary"):
            key = (c["tier"], c["sensor"], c.get("task", BASE_TASK), c.get("shifts", NO_SHIFT))
            out.setdefault(key, []).append(c)
    return out


def pair_tables(cells: list[dict], reports: dict[str, dict]) -> list[dict]:
    """Every pair of estimators but the oracle in each cell: (tier, sensor, task, shifts), the
    pair ``a`` and ``b``, their tests (`compare_pair`) and `verdict`."""
    out = []
    for (tier, sensor, task, shifts), group in _groups(cells).items():
        shown = [c for c in group if c["estimator"] != ORACLE]
        runs = {c["estimator"]: episode_outcomes(reports[c["run_key"]]) for c in shown}
        names = list(runs)
        for i, a in enumerate(names):
            for b in names[i + 1 :]:
                test = compare_pair(runs[a], runs[b], task == "place")
                out.append(
                    {"tier": tier, "sensor": sensor, "task": task, "shifts": shifts}
                    | {"a": a, "b": b, **test, "verdict": verdict(a, b, test)}
                )
    return out


def drop_table(cells: list[dict], reports: dict[str, dict]) -> list[dict]:
    """Each estimator (the oracle too) under each shift against itself without it, on the same
    seeds, per (tier, sensor, task): successes unshifted (``base``) and shifted, the ``drop``
    in success rate (base - shifted; positive: the shift hurts) and McNemar's p of the pairs."""
    out = []
    groups = _groups(cells)
    for (tier, sensor, task, shifts), group in groups.items():
        if shifts == NO_SHIFT:
            continue
        base = {c["estimator"]: c for c in groups.get((tier, sensor, task, NO_SHIFT), [])}
        for c in group:
            if c["estimator"] not in base:
                continue
            before = episode_outcomes(reports[base[c["estimator"]]["run_key"]])
            after = episode_outcomes(reports[c["run_key"]])
            m = compare_pair(before, after, place=False)["mcnemar"]
            out.append(
                {"tier": tier, "sensor": sensor, "task": task, "shifts": shifts}
                | {"estimator": c["estimator"], "episodes": m["episodes"]}
                | {"base": m["a"], "shifted": m["b"], "base_only": m["a_only"]}
                | {"shifted_only": m["b_only"], "p": m["p"]}
                | {"drop": (m["a"] - m["b"]) / m["episodes"] if m["episodes"] else None}
            )
    return out


def oracle_under_shifts(drops: list[dict]) -> dict:
    """Whether the oracle's episodes are the same under every shift as without (they must be:
    a shift changes what the camera sees, and the oracle does not look): the oracle's rows of
    the drop table (``rows``) and those where an episode's outcome changed (``changed``)."""
    rows = [d for d in drops if d["estimator"] == ORACLE]
    changed = [
        f"{d['tier']}, {d['sensor']}, {d['task']}, {d['shifts']} "
        f"({d['base_only'] + d['shifted_only']} episodes differ)"
        for d in rows
        if d["base_only"] or d["shifted_only"]
    ]
    return {"rows": len(rows), "changed": changed}


def _binned(values: Iterable[tuple[float, bool]], edges: tuple[float, ...]) -> dict:
    """Episodes and successes per bin of `edges` (the last bin open)."""
    episodes, successes = [0] * len(edges), [0] * len(edges)
    for value, ok in values:
        i = int(np.searchsorted(edges, value, side="right")) - 1
        episodes[max(i, 0)] += 1
        successes[max(i, 0)] += int(ok)
    return {"edges": list(edges), "episodes": episodes, "successes": successes}


def success_by_error(cells: list[dict], reports: dict[str, dict]) -> dict:
    """Success against the estimate's error per task, over every estimator's episodes but the
    oracle's (each run once) that have an estimate: per task, per error of `ERROR_BINS`, the
    episodes and successes per bin (success: held on the lift task, placed on the place
    task)."""
    out: dict = {}
    for task in dict.fromkeys(c.get("task", BASE_TASK) for c in cells):
        runs = {
            c["run_key"]
            for c in cells
            if c.get("summary") and c["estimator"] != ORACLE and c.get("task", BASE_TASK) == task
        }
        eps = [e for k in sorted(runs) for e in reports[k]["episodes"] if e.get("pose_error")]
        errs = [(e["pose_error"], bool(e["success"])) for e in eps]
        pts = {
            "translation_mm": [(1000 * err["translation_m"], ok) for err, ok in errs],
            "rotation_deg": [(err["rotation_deg"], ok) for err, ok in errs],
        }
        out[task] = {k: _binned(v, ERROR_BINS[k]) for k, v in pts.items()}
    return out
