"""The leaderboard: every (estimator, tier, sensor) cell on the same held-out episodes.

    python -m sim.leaderboard [--estimators LIST] [--tiers LIST] [--sensors LIST] \
        [--objects all] [--episodes N] [--workers N] [--backend local|ray] [--out DIR] \
        [--markdown docs/LEADERBOARD.md] [--plots docs/leaderboard] [--json PATH]

Each cell is one `sim.evaluate` run (its report and journal under ``--out``/cells), so an
interrupted leaderboard resumes where it stopped: a finished cell is read back, a started one
resumes from its journal. A cell records the estimator's settings and weights it ran with
(`sim.estimators.estimator_settings`); where they are not today's, the board refuses to run and
names the cells, rather than mix runs of other settings into it. An estimator that needs depth
(`sim.estimators.needs_depth`) sees ``rgbd`` observations, every other one ``rgb``; an RGB-only
estimator sees only the sensor's colour model, so its cells under sensors that differ only in
depth are one run, shown under each. A cell that cannot run (an estimator whose extra is not
installed) is reported as such, not dropped. Then it writes the whole board as JSON, the
Markdown page (`docs/LEADERBOARD.md` is its output, never edited by hand) and three plots:
success per cell, AR against success, and success against coverage for the estimators that give
a confidence.
"""

from __future__ import annotations

import json
import re
import sys
import time
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from posegrasp.core.backends import add_backend_arguments, check_backend
from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    add_out_argument,
    add_workers_argument,
    command,
    write_json,
)
from posegrasp.core.errors import InvalidArgumentError, PosegraspError
from posegrasp.core.files import atomic_write_bytes, atomic_write_json
from posegrasp.core.paths import DOCS_DIR, in_repo
from posegrasp.core.validate import arg, check_int, check_names
from posegrasp.world.constants import EVAL_SEED_BASE
from posegrasp.world.objects import OBJECT_NAMES
from posegrasp.world.sensors import SENSOR_NAMES, Sensor
from posegrasp.world.tiers import TIERS
from sim.grasp_vs_bop import ar_for_success, episode_aucs, spearman_with_interval
from sim.stats import risk_coverage, wilson_interval

#: The rows, in order: the true pose, our estimators, the classical peers, the crude example.
ESTIMATORS: tuple[str, ...] = (
    "oracle",
    "hybrid-global",
    "hybrid",
    "hybrid-global-icp",
    "ppf",
    "ppf-det",
    "fpfh-icp",
    "fpfh-icp-det",
    "crude",
)
#: Our RGB-only estimator, and the classical depth peers the board holds it against.
OURS = "hybrid-global"
CLASSICAL: tuple[str, ...] = ("ppf", "ppf-det", "fpfh-icp", "fpfh-icp-det")
#: The default sensors: the ideal camera and a structured-light depth camera.
SENSORS: tuple[str, ...] = ("ideal", "kinect-v1")
#: The ARs reported per cell, and against success.
AR_KEYS: tuple[str, ...] = ("ar_mssd", "ar_mspd", "ar_vsd")
#: Failure reasons shown per cell.
TOP_REASONS = 2
#: The success a method should reach; the AR that predicts it is reported per tier.
TARGET_SUCCESS = 0.95


@dataclass(frozen=True)
class Cell:
    """One leaderboard cell and the run that fills it."""

    estimator: str
    tier: str
    sensor: str
    obs_mode: str
    #: The sensor the run actually uses: an RGB-only estimator's ignores the depth model.
    run_sensor: str

    @property
    def run_key(self) -> str:
        """File stem of the run (shared by cells that are the same run)."""
        return _safe(f"{self.tier}__{self.run_sensor}__{self.estimator}")


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", name)


def cells_of(estimators: Sequence[str], tiers: Sequence[str], sensors: Sequence[str]) -> list[Cell]:
    """Every (estimator, tier, sensor) cell, with the observation mode and sensor it runs in."""
    from sim.estimators import needs_depth

    out = []
    for sensor in sensors:
        parsed = Sensor.parse(sensor)
        for tier in tiers:
            for est in estimators:
                depth = needs_depth(est)
                run_sensor = parsed.name if depth else Sensor("ideal", parsed.rgb).name
                out.append(Cell(est, tier, parsed.name, "rgbd" if depth else "rgb", run_sensor))
    return out


def _cell_files(cells_dir: Path, cell: Cell) -> tuple[Path, Path, Path]:
    """A cell's report, its journal and the settings it ran with."""
    key = cell.run_key
    return (
        cells_dir / f"{key}.json",
        cells_dir / f"{key}.journal.jsonl",
        cells_dir / f"{key}.settings.json",
    )


def stale_cells(
    cells: Sequence[Cell], cells_dir: Path, settings: dict[str, dict | None]
) -> list[str]:
    """The cells with files in `cells_dir` (a report or a journal) whose recorded estimator
    settings are not `settings` of their estimator (or are not recorded), each with the first
    settings that differ. An estimator whose settings are None (it cannot be made) is left to
    fail when its cells run."""
    out = []
    for cell in cells:
        today = settings.get(cell.estimator)
        report, journal, path = _cell_files(cells_dir, cell)
        if today is None or not (report.exists() or journal.exists()):
            continue
        recorded = json.loads(path.read_text()) if path.exists() else None
        if recorded != today:
            differ = "no settings recorded" if recorded is None else _differences(recorded, today)
            out.append(f"{cell.run_key} ({differ})")
    return sorted(set(out))


def _differences(a: dict, b: dict, most: int = 3) -> str:
    """The first `most` dotted keys whose values differ between `a` and `b`."""
    keys: list[str] = []

    def walk(x: object, y: object, at: str) -> None:
        if isinstance(x, dict) and isinstance(y, dict):
            for k in sorted(set(x) | set(y)):
                walk(x.get(k), y.get(k), f"{at}.{k}" if at else k)
        elif x != y:
            keys.append(at)

    walk(a, b, "")
    return ", ".join(keys[:most]) + (f" and {len(keys) - most} more" if len(keys) > most else "")


def run_cell(cell: Cell, args, cells_dir: Path, settings: dict | None = None) -> dict:
    """Run (or read back, or resume) one cell's `sim.evaluate` report; a run that starts
    records `settings` (`stale_cells` checks them)."""
    from sim.evaluate import evaluate

    report_path, journal, settings_path = _cell_files(cells_dir, cell)
    if settings is not None and not report_path.exists() and not journal.exists():
        atomic_write_json(settings_path, settings)
    if report_path.exists():
        report = json.loads(report_path.read_text())
        if report.get("episodes_per_object") == args.episodes and report.get("objects") == list(
            args.objects
        ):
            return report
    report = evaluate(
        list(args.objects),
        args.episodes,
        cell.estimator,
        EVAL_SEED_BASE,
        workers=args.workers,
        tier=cell.tier,
        backend=args.backend,
        address=args.address,
        journal=journal,
        resume=journal.exists(),
        obs_mode=cell.obs_mode,
        sensor=cell.run_sensor,
    )
    report["episodes_per_object"] = args.episodes
    atomic_write_json(report_path, report)
    return report


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


def cell_summary(report: dict) -> dict:
    """A cell's figures from its report: success with its Wilson interval, pose-correct rate,
    grasped with a wrong pose, the ARs, time per image and the leading failure reasons."""
    g = report["overall"]
    eps = report["episodes"]
    lo, hi = wilson_interval(g["successes"], g["episodes"])
    times = [e["timings_ms"]["estimate"] for e in eps if "estimate" in e.get("timings_ms", {})]
    reasons = Counter(e["failure_reason"] for e in eps if not e["success"])
    rc = risk_coverage([e.get("confidence") for e in eps], [bool(e["success"]) for e in eps])
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
    }


def analyse(cells: list[dict], reports: dict[str, dict]) -> dict:
    """What BOP scores say about grasps over the board: per AR, Spearman's rho of AR against
    success over the cells; per tier, each error's separation AUC over the episodes of every
    estimator but the oracle, and the AR that a logistic fit says gives `TARGET_SUCCESS`."""
    scored = [c for c in cells if c.get("summary") and c["estimator"] != "oracle"]
    out: dict = {"spearman": {}, "auc": {}, "ar_for_success": {}}
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


def _summaries(cells: list[dict]) -> dict[tuple[str, str, str], dict]:
    """The cells' summaries by (estimator, sensor, tier); cells that could not run left out."""
    return {
        (c["estimator"], c["sensor"], c["tier"]): c["summary"] for c in cells if c.get("summary")
    }


def findings(board: dict) -> list[str]:
    """The board's findings in plain words, every figure read from the board: `OURS` against
    the classical depth peers per sensor (success and time per image), how closely the ARs rank
    the cells, which per-episode error separates grasps best and worst, and the AR needed."""
    by = _summaries(board["cells"])
    out = ["## In short", ""]
    for sensor in board["sensors"]:
        groups = [(t, by[OURS, sensor, t]) for t in board["tiers"] if (OURS, sensor, t) in by]
        peers = [p for p in CLASSICAL if any((p, sensor, t) in by for t, _ in groups)]
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
    return [*out, ""]


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.0f} %"


def _num(x: float | None, fmt: str = ".3f") -> str:
    return "-" if x is None else format(x, fmt)


def markdown(board: dict) -> str:
    """The leaderboard page: how it was made, one table per (sensor, tier), the BOP analysis."""
    lines = [
        "# Leaderboard",
        "",
        "Generated by the command below; do not edit by hand. Each cell: grasp success on the",
        "same held-out episodes (Wilson 95 % interval), the share of poses BOP would call right",
        "(MSSD < 10 % of the diameter), grasps held on a wrong pose, BOP's AR of the same poses,",
        "the estimator's time per image on 2 cores and its leading failure reasons.",
        "",
        "```bash",
        board["command"],
        "```",
        "",
        f"{board['episodes_per_cell']} episodes per cell ({board['episodes']} per object x "
        f"{len(board['objects'])} objects), seeds from {board['seed_start']}; "
        f"wall time {board['wall_s'] / 3600:.1f} h with {board.get('workers', 1)} workers (the "
        "episodes' own times, shared over the workers that ran them).",
        "",
        "![success per cell](leaderboard/success.png)",
        "",
        *findings(board),
    ]
    lines += _cell_tables(board)
    lines += _bop_section(board["analysis"])
    lines += [
        "",
        "## Confidence and abstention",
        "",
        "![success against coverage](leaderboard/risk_coverage.png)",
        "",
        "Success among attempted grasps when the robot attempts only the estimates above a",
        "confidence threshold, for the estimators that give a confidence (`RC area` above: the",
        "mean success over attempts ranked by confidence).",
        "",
    ]
    return "\n".join(lines)


def _cell_tables(board: dict) -> list[str]:
    """One Markdown table per (sensor, tier): a row per estimator."""
    lines: list[str] = []
    head = (
        "| estimator | obs | success | 95 % CI | pose right | held, wrong pose | AR_MSSD | "
        "AR_MSPD | AR_VSD | ms/image (med, p90) | RC area | leading failures |"
    )
    for sensor in board["sensors"]:
        for tier in board["tiers"]:
            lines += [f"## {tier}, sensor `{sensor}`", "", head, "|" + "---|" * 12]
            for c in board["cells"]:
                if c["tier"] != tier or c["sensor"] != sensor:
                    continue
                s = c.get("summary")
                if s is None:
                    lines.append(
                        f"| {c['estimator']} | {c['obs_mode']} | {c['error']} |" + " |" * 9
                    )
                    continue
                fails = ", ".join(f"{r} {n}" for r, n in s["failures"]) or "-"
                rc = s["risk_coverage"]
                lines.append(
                    f"| {c['estimator']} | {c['obs_mode']} | {s['successes']}/{s['episodes']} "
                    f"| {_pct(s['wilson'][0])}-{_pct(s['wilson'][1])} "
                    f"| {_pct(s['pose_correct_rate'])} | {s['grasped_wrong_pose']} "
                    f"| {_num(s['ar_mssd'])} | {_num(s['ar_mspd'])} | {_num(s['ar_vsd'])} "
                    f"| {_num(s['time_ms_median'], '.0f')}, {_num(s['time_ms_p90'], '.0f')} "
                    f"| {_num(rc['area'] if rc else None, '.2f')} | {fails} |"
                )
            lines.append("")
    return lines


def _bop_section(a: dict) -> list[str]:
    """What BOP scores say about grasps: Spearman's rho per AR, the separation AUC per tier
    and error, the AR needed for `TARGET_SUCCESS` per tier."""
    lines = [
        "## What BOP scores say about grasps",
        "",
        "![AR against grasp success](leaderboard/ar_vs_success.png)",
        "",
        "Spearman's rank correlation of each AR with grasp success over the cells (oracle left",
        "out; 95 % bootstrap interval over cells):",
        "",
        "| AR | rho | 95 % CI | cells |",
        "|---|---|---|---|",
    ]
    for key, r in a["spearman"].items():
        lines.append(
            f"| {key.upper()} | {_num(r['rho'], '.2f')} | {_num(r['low'], '.2f')} to "
            f"{_num(r['high'], '.2f')} | {r['n']} |"
        )
    errs = list(next(iter(a["auc"].values()), {}).keys())
    lines += [
        "",
        "How well each per-episode error separates held grasps from failed ones (ROC AUC; 0.5",
        "says nothing, 1 separates perfectly), over every estimator's episodes with a pose:",
        "",
        "| tier | " + " | ".join(errs) + " |",
        "|---|" + "---|" * len(errs),
    ]
    for tier, aucs in a["auc"].items():
        lines.append(f"| {tier} | " + " | ".join(_num(aucs[e]["auc"], ".2f") for e in errs) + " |")
    lines += [
        "",
        f"The AR at which a logistic fit of success on AR over a tier's cells reaches "
        f"{TARGET_SUCCESS:.0%} grasps:",
        "",
        "| tier | " + " | ".join(k.upper() for k in AR_KEYS) + " |",
        "|---|" + "---|" * len(AR_KEYS),
    ]
    for tier, fits in a["ar_for_success"].items():
        row = [_num(f["ar"], ".2f") if f["ar"] is not None else f["note"] for f in fits.values()]
        lines.append(f"| {tier} | " + " | ".join(row) + " |")
    return lines


def plots(board: dict, folder: Path) -> None:
    """success.png, ar_vs_success.png and risk_coverage.png in folder."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    cells = [c for c in board["cells"] if c.get("summary")]
    names = list(dict.fromkeys(c["estimator"] for c in cells))
    colour = {n: f"C{i % 10}" for i, n in enumerate(names)}
    by_key = _summaries(cells)
    sensors, tiers = board["sensors"], board["tiers"]
    _success_plot(plt, by_key, names, colour, sensors, tiers, folder / "success.png")
    fig, axes = plt.subplots(1, len(AR_KEYS), figsize=(4 * len(AR_KEYS), 4), sharey=True)
    for ax, key in zip(np.atleast_1d(axes), AR_KEYS, strict=True):
        for name in names:
            pts = [
                c["summary"]
                for c in cells
                if c["estimator"] == name and c["summary"][key] is not None
            ]
            ax.scatter([p[key] for p in pts], [p["success_rate"] for p in pts], label=name, s=18)
        r = board["analysis"]["spearman"][key]
        ax.set_title(f"{key.upper()}: rho {_num(r['rho'], '.2f')}")
        ax.set_xlabel(key.upper())
        ax.set_xlim(-0.02, 1.02)
    np.atleast_1d(axes)[0].set_ylabel("grasp success")
    np.atleast_1d(axes)[-1].legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8)
    fig.tight_layout()
    fig.savefig(folder / "ar_vs_success.png", dpi=110)
    plt.close(fig)

    _risk_coverage_plot(plt, by_key, names, colour, sensors, tiers, folder / "risk_coverage.png")


def _success_plot(plt, by_key, names, colour, sensors, tiers, path: Path) -> None:
    """Grasp success with its Wilson interval: a panel per sensor, the tiers as groups."""
    width = 0.8 / max(1, len(names))
    figsize = (max(8.0, 0.16 * len(tiers) * len(names) + 2.5), 2.6 * len(sensors) + 0.6)
    fig, axes = plt.subplots(len(sensors), 1, figsize=figsize, sharey=True, squeeze=False)
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
            ax.bar(
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
        ax.set_ylim(0, 1.05)
        ax.set_ylabel("grasp success")
        ax.set_title(f"sensor {sensor}", fontsize=10, loc="left")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper left", bbox_to_anchor=(0.86, 0.95), fontsize=8)
    fig.subplots_adjust(left=0.06, right=0.85, hspace=0.35)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _risk_coverage_plot(plt, by_key, names, colour, sensors, tiers, path: Path) -> None:
    """Success among the attempted episodes against the share attempted, the most confident
    first: a panel per (sensor, tier), a curve per estimator that gives a confidence."""
    shown = [n for n in names if n != "oracle"]
    fig, axes = plt.subplots(
        len(sensors),
        len(tiers),
        figsize=(2.6 * len(tiers) + 1.8, 2.4 * len(sensors) + 0.5),
        sharex=True,
        sharey=True,
        squeeze=False,
    )
    drawn: dict[str, object] = {}
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
    if drawn:
        fig.legend(
            list(drawn.values()),
            list(drawn),
            loc="upper left",
            bbox_to_anchor=(0.87, 0.93),
            fontsize=8,
        )
    fig.subplots_adjust(left=0.07, right=0.86, wspace=0.12, hspace=0.35)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _settings_or_none(name: str) -> dict | None:
    """`estimator_settings` of `name`; None where it cannot be made (its cells say why)."""
    from sim.estimators import estimator_settings

    try:
        return estimator_settings(name)
    except PosegraspError:
        return None


def _command(argv: Sequence[str]) -> str:
    return "python -m sim.leaderboard " + " ".join(argv)


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    argv = sys.argv[1:] if argv is None else argv
    p = ArgumentParser(prog="python -m sim.leaderboard", description=__doc__.split("\n")[0])
    for flag, choices, default in (
        ("--estimators", ESTIMATORS, ESTIMATORS),
        ("--tiers", TIERS, TIERS),
        ("--sensors", SENSOR_NAMES, SENSORS),
        ("--objects", OBJECT_NAMES, OBJECT_NAMES),
    ):
        p.add_argument(
            flag,
            default=list(default),
            type=arg(check_names, choices, flag[2:-1], flag),
            help=f"a comma list of {', '.join(choices)}, or 'all' (default {','.join(default)})",
        )
    p.add_argument(
        "--episodes",
        type=arg(check_int, 1, 100_000, "--episodes", base=int),
        default=20,
        help="episodes per object and cell (default 20)",
    )
    add_workers_argument(p)
    add_backend_arguments(p)
    add_out_argument(p, "every cell's report and journal", Path("out/leaderboard"))
    p.add_argument("--markdown", type=Path, default=DOCS_DIR / "LEADERBOARD.md")
    p.add_argument("--plots", type=Path, default=DOCS_DIR / "leaderboard")
    add_json_argument(p, "the whole board", DOCS_DIR / "leaderboard.json")
    args = p.parse_args(argv)
    check_backend(args.backend, args.address)
    cells_dir = Path(args.out) / "cells"
    cells_dir.mkdir(parents=True, exist_ok=True)
    cells = cells_of(args.estimators, args.tiers, args.sensors)
    settings = {name: _settings_or_none(name) for name in args.estimators}
    stale = stale_cells(cells, cells_dir, settings)
    if stale:
        raise InvalidArgumentError(
            f"{len(stale)} cells in {cells_dir} ran with other estimator settings or weights than "
            f"today's: {'; '.join(stale[:4])}{' ...' if len(stale) > 4 else ''}; move their files "
            "away to run them again, or give another --out"
        )
    reports: dict[str, dict] = {}
    board_cells = []
    start = time.perf_counter()
    for i, cell in enumerate(cells, 1):
        print(f"cell {i}/{len(cells)}: {cell.estimator}, {cell.tier}, {cell.sensor}", flush=True)
        row = {**asdict(cell), "run_key": cell.run_key}
        try:
            if cell.run_key not in reports:
                reports[cell.run_key] = run_cell(cell, args, cells_dir, settings[cell.estimator])
            row["summary"] = cell_summary(reports[cell.run_key])
        except PosegraspError as exc:
            row["error"] = str(exc).splitlines()[0]
            print(f"  cannot run: {row['error']}", flush=True)
        board_cells.append(row)
    wall = run_time_s(reports.values()) or time.perf_counter() - start
    board = {
        "command": _command(argv),
        "estimators": list(args.estimators),
        "tiers": list(args.tiers),
        "sensors": [Sensor.parse(s).name for s in args.sensors],
        "objects": list(args.objects),
        "episodes": args.episodes,
        "episodes_per_cell": args.episodes * len(args.objects),
        "seed_start": EVAL_SEED_BASE,
        "wall_s": wall,
        "workers": args.workers,
        "cells": board_cells,
        "analysis": analyse(board_cells, reports),
    }
    write_json(args.json, board)
    atomic_write_bytes(args.markdown, markdown(board).encode())
    plots(board, args.plots)
    print(f"wrote {in_repo(args.markdown)} and the plots in {in_repo(args.plots)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
