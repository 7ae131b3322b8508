"""The leaderboard's plots (`plots`), legible at every board size, from one cell to the full board:
success per cell, AR against success, success against coverage and, on a board with the place
task, lift and place success against the estimate's error.

Each plot is sized by what it holds (panels, groups, bars), keeps every estimator's full name in
a legend outside its panels, and is saved with its whole drawing (labels and legend) inside the
image. The oracle, the experiment's instrument, is drawn only where the page says so: on the
success plot, as the ceiling, and never among the estimators that AR or confidence rank.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sim.board.cell_summaries import AR_KEYS, summaries
from sim.board.pairs import ORACLE
from sim.board.tracks import BASE_TASK
from sim.evaluation.stats import wilson_interval

#: Resolution of the saved images [dots per inch].
DPI = 110

Summaries = dict[tuple[str, str, str], dict]


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path) -> None:
    """Save with the whole drawing inside the image (legends outside the axes included)."""
    fig.savefig(path, dpi=DPI, bbox_inches="tight", pad_inches=0.1)
    _pyplot().close(fig)


def _legend(fig: Any, handles: list, labels: list[str], anchor: Any) -> None:
    if handles:
        fig.legend(
            handles, labels, loc="upper left", bbox_to_anchor=anchor, fontsize=8, frameon=False
        )


def success_plot(
    by_key: Summaries,
    names: Sequence[str],
    colour: dict[str, str],
    sensors: Sequence[str],
    tiers: Sequence[str],
    path: Path,
) -> None:
    """Grasp success with its Wilson interval: a panel per sensor, the tiers as groups, a bar
    per estimator (the oracle among them, the ceiling)."""
    plt = _pyplot()
    width = min(0.3, 0.8 / max(1, len(names)))
    figsize = (max(4.0, 0.22 * len(tiers) * len(names) + 1.5), 2.4 * len(sensors) + 0.4)
    fig, axes = plt.subplots(len(sensors), 1, figsize=figsize, sharey=True, squeeze=False)
    drawn: dict[str, Any] = {}
    for ax, sensor in zip(axes[:, 0], sensors, strict=True):
        for i, name in enumerate(names):
            at = [
                (j, by_key[name, sensor, t])
                for j, t in enumerate(tiers)
                if (name, sensor, t) in by_key
            ]
            if not at:
                continue
            rates = [m["success_rate"] for _, m in at]
            drawn[name] = ax.bar(
                [j + (i - (len(names) - 1) / 2) * width for j, _ in at],
                rates,
                width,
                yerr=[
                    [r - m["wilson"][0] for r, (_, m) in zip(rates, at, strict=True)],
                    [m["wilson"][1] - r for r, (_, m) in zip(rates, at, strict=True)],
                ],
                capsize=1.5,
                color=colour[name],
                label=name,
            )
        ax.set_xticks(range(len(tiers)), tiers)
        ax.set_xlim(-0.6, len(tiers) - 0.4)
        ax.set_ylim(0, 1.05)
        ax.set_ylabel("grasp success")
        ax.set_title(f"sensor {sensor}", fontsize=10, loc="left")
    fig.tight_layout()
    _legend(fig, list(drawn.values()), list(drawn), (1.0, 0.98))
    _save(fig, path)


def ar_plot(
    cells: Sequence[dict],
    names: Sequence[str],
    colour: dict[str, str],
    ar_keys: Sequence[str],
    spearman: dict[str, dict],
    path: Path,
) -> None:
    """Each cell's grasp success against its AR, a panel per AR with Spearman's rho over the
    cells; the oracle left out."""
    plt = _pyplot()
    shown = [n for n in names if n != ORACLE]
    fig, axes = plt.subplots(1, len(ar_keys), figsize=(3.4 * len(ar_keys), 3.2), sharey=True)
    drawn: dict[str, Any] = {}
    for ax, key in zip(np.atleast_1d(axes), ar_keys, strict=True):
        for name in shown:
            pts = [
                c["summary"]
                for c in cells
                if c["estimator"] == name and c["summary"][key] is not None
            ]
            if pts:
                drawn[name] = ax.scatter(
                    [p[key] for p in pts],
                    [p["success_rate"] for p in pts],
                    s=18,
                    color=colour[name],
                    label=name,
                )
        rho = (spearman.get(key) or {}).get("rho")
        ax.set_title(f"{key.upper()}: rho {'-' if rho is None else format(rho, '.2f')}")
        ax.set_xlabel(key.upper())
        ax.set_xlim(-0.02, 1.02)
        ax.set_ylim(-0.02, 1.05)
    np.atleast_1d(axes)[0].set_ylabel("grasp success")
    fig.tight_layout()
    _legend(fig, list(drawn.values()), list(drawn), (1.0, 0.95))
    _save(fig, path)


def risk_coverage_plot(
    by_key: Summaries,
    names: Sequence[str],
    colour: dict[str, str],
    sensors: Sequence[str],
    tiers: Sequence[str],
    path: Path,
) -> None:
    """Success among the attempted episodes against the share attempted, the most confident
    first: a panel per (sensor, tier), a curve per estimator that gives a confidence; the oracle
    left out."""
    plt = _pyplot()
    shown = [n for n in names if n != ORACLE]
    fig, axes = plt.subplots(
        len(sensors),
        len(tiers),
        figsize=(2.6 * len(tiers) + 0.8, 2.4 * len(sensors) + 0.5),
        sharex=True,
        sharey=True,
        squeeze=False,
    )
    drawn: dict[str, Any] = {}
    for r, sensor in enumerate(sensors):
        for k, tier in enumerate(tiers):
            ax = axes[r, k]
            for name in shown:
                m = by_key.get((name, sensor, tier))
                rc = m and m["risk_coverage"]
                if rc:
                    (line,) = ax.step(
                        rc["coverage"], rc["success"], where="post", color=colour[name], lw=1.2
                    )
                    drawn[name] = line
            ax.set_title(f"{tier}, {sensor}", fontsize=9)
            ax.set_xlim(0, 1.02)
            ax.set_xticks([0, 0.5, 1])
            ax.set_ylim(0, 1.05)
            if r == len(sensors) - 1:
                ax.set_xlabel("coverage")
            if k == 0:
                ax.set_ylabel("success among attempted")
    if not drawn:
        axes[0, 0].text(
            0.5, 0.5, "no estimator here\ngives a confidence", ha="center", va="center", fontsize=9
        )
    fig.tight_layout()
    _legend(fig, list(drawn.values()), list(drawn), (1.0, 0.95))
    _save(fig, path)


def _bin_labels(edges: Sequence[float]) -> list[str]:
    """A bin's label per edge: ``lo-hi``, the last ``lo+``."""
    return [f"{lo:g}-{hi:g}" for lo, hi in itertools.pairwise(edges)] + [f"{edges[-1]:g}+"]


#: The errors of the error plot: the key of `sim.board.pairs.ERROR_BINS` and the axis' label.
ERROR_AXES = (
    ("translation_mm", "estimate's translation error [mm]"),
    ("rotation_deg", "estimate's rotation error [deg]"),
)


def error_plot(by_task: dict[str, dict], path: Path) -> None:
    """Success against the estimate's translation and rotation error, binned: a panel per
    error, a line per task (lift: held; place: placed within tolerance) with the Wilson
    interval of each bin that holds episodes; the oracle left out
    (`sim.board.pairs.success_by_error`)."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, len(ERROR_AXES), figsize=(4.2 * len(ERROR_AXES), 3.2), sharey=True)
    drawn: dict[str, Any] = {}
    for ax, (key, label) in zip(np.atleast_1d(axes), ERROR_AXES, strict=True):
        edges = next(iter(by_task.values()))[key]["edges"]
        for i, (task, bins) in enumerate(by_task.items()):
            counts = zip(bins[key]["successes"], bins[key]["episodes"], strict=True)
            at = [(j, k, n) for j, (k, n) in enumerate(counts) if n]
            if not at:
                continue
            rates = np.array([k / n for _, k, n in at])
            wil = np.array([wilson_interval(k, n) for _, k, n in at])
            drawn[task] = ax.errorbar(
                [j + 0.08 * (i - 0.5) for j, _, _ in at],
                rates,
                yerr=[rates - wil[:, 0], wil[:, 1] - rates],
                marker="o",
                ms=4,
                capsize=2,
                color=f"C{i}",
                label=task,
            )
        ax.set_xticks(range(len(edges)), _bin_labels(edges), rotation=30, fontsize=8)
        ax.set_xlim(-0.5, len(edges) - 0.5)
        ax.set_ylim(-0.02, 1.05)
        ax.set_xlabel(label)
    np.atleast_1d(axes)[0].set_ylabel("success")
    fig.tight_layout()
    _legend(fig, list(drawn.values()), list(drawn), (1.0, 0.95))
    _save(fig, path)


def plots(board: dict, folder: Path) -> None:
    """success.png, ar_vs_success.png and risk_coverage.png in folder (of today's track: lift,
    no shift; the AR plot over every lift cell) and, on a board with the place task,
    success_vs_error.png."""
    folder.mkdir(parents=True, exist_ok=True)
    cells = [c for c in board["cells"] if c.get("summary")]
    names = list(dict.fromkeys(c["estimator"] for c in cells))
    colour = {n: f"C{i % 10}" for i, n in enumerate(names)}
    by_key = summaries(cells)
    sensors, tiers = board["sensors"], board["tiers"]
    success_plot(by_key, names, colour, sensors, tiers, folder / "success.png")
    ar_plot(
        [c for c in cells if c.get("task", BASE_TASK) == BASE_TASK],
        names,
        colour,
        AR_KEYS,
        board["analysis"]["spearman"],
        folder / "ar_vs_success.png",
    )
    risk_coverage_plot(by_key, names, colour, sensors, tiers, folder / "risk_coverage.png")
    by_task = board["analysis"].get("success_by_error") or {}
    if "place" in by_task:
        error_plot(by_task, folder / "success_vs_error.png")
