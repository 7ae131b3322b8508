"""The leaderboard: every (estimator, tier, sensor) cell on the same held-out episodes.

    python -m sim.leaderboard [--estimators LIST] [--poses CSV EXPORT ...] [--tiers LIST] \
        [--sensors LIST] [--objects all] [--episodes N] [--workers N] [--backend local|ray] \
        [--out DIR] [--publish]

A row is any estimator a spec names (`sim.estimators`: a built-in name, an installed entry point,
a plug-in ``package.module:factory``) or the poses of a BOP results CSV of a method run
elsewhere (``--poses CSV EXPORT``: the CSV answers the export of `sim.export_bop` it names, whose
episodes must be the board's), ranked with the others on the same episodes.

Each cell is one evaluation (`sim.evaluation`; its report and journal under ``--out``/cells), so
a stopped leaderboard resumes where it stopped when its command runs again, as the line it
prints says: a finished cell is read back, a started one resumes from its journal. A cell
records the estimator's settings and weights it ran with (`sim.estimators.estimator_settings`;
a CSV's and its export's hashes); where they are not today's, the board refuses to run and names
the cells, rather than mix runs of other settings into it; so it does for a cell that holds an
episode stopped rather than played, or other episodes than the board's. An estimator that cannot
be made here (an extra not installed) is refused before any cell runs, in one line naming the
install. An estimator that needs depth (`sim.estimators.needs_depth`) sees ``rgbd``
observations, every other one ``rgb``; an RGB-only estimator sees only the sensor's colour
model, so its cells under sensors that differ only in depth are one run, shown under each.

The board goes under ``--out``: the whole board as JSON, the Markdown page and three plots
(`sim.leaderboard_plots`), the page linking its plots relative to where it is written;
``--publish`` writes the shipped page instead (`docs/LEADERBOARD.md`, its JSON and plots, never
edited by hand).
"""

from __future__ import annotations

import json
import os
import re
import shlex
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
from posegrasp.core.files import atomic_write_bytes, atomic_write_json, sha256_file
from posegrasp.core.journal import Interrupted, interrupted
from posegrasp.core.paths import DOCS_DIR, in_repo
from posegrasp.core.validate import arg, check_int, check_names
from posegrasp.world.constants import EVAL_SEED_BASE
from posegrasp.world.objects import OBJECT_NAMES
from posegrasp.world.sensors import SENSOR_NAMES, Sensor
from posegrasp.world.tiers import TIERS
from sim import leaderboard_plots
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

#: Where ``--publish`` writes the board: the shipped page, its JSON and its plots.
PUBLISHED = {
    "markdown": DOCS_DIR / "LEADERBOARD.md",
    "json": DOCS_DIR / "leaderboard.json",
    "plots": DOCS_DIR / "leaderboard",
}


@dataclass(frozen=True)
class Cell:
    """One leaderboard cell and the run that fills it."""

    estimator: str
    tier: str
    sensor: str
    obs_mode: str
    #: The sensor the run actually uses: an RGB-only estimator's ignores the depth model.
    run_sensor: str
    #: A row of a BOP results CSV: the CSV and the export it answers (None: a live estimator).
    poses: tuple[str, str] | None = None

    @property
    def run_key(self) -> str:
        """File stem of the run (shared by cells that are the same run)."""
        return _safe(f"{self.tier}__{self.run_sensor}__{self.estimator}")


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", name)


@dataclass(frozen=True)
class PosesRow:
    """A row of the board from a BOP results CSV: the poses of a method run elsewhere, on the
    episodes of the export the CSV answers.

    Attributes:
        name: the row's name, ``bop:<method>`` (the CSV's name up to its first underscore, as
            BOP names results files ``METHOD_DATASET-SPLIT.csv``).
        csv: the results CSV.
        export: the export folder of `sim.export_bop` that the CSV answers.
        tier, sensor: the export's tier and the sensor its images were rendered through.
    """

    name: str
    csv: str
    export: str
    tier: str
    sensor: str


def poses_rows(
    pairs: Sequence[Sequence[str]], objects: Sequence[str], episodes: int
) -> list[PosesRow]:
    """The CSV rows ``--poses CSV EXPORT`` gives, each checked against the board's episodes.

    Raises:
        InvalidArgumentError: an export that cannot be read, holds other episodes than the
            board's (objects, episodes per object, first seed), or two CSVs of one method for the
            same tier and sensor.
    """
    from sim.bop_results import BopPosesEstimator

    rows: list[PosesRow] = []
    for csv, folder in pairs:
        export = BopPosesEstimator(csv, folder).export  # reads and checks both
        theirs = (list(export.objects), export.episodes, export.seed_start)
        ours = (list(objects), episodes, EVAL_SEED_BASE)
        if theirs != ours:
            raise InvalidArgumentError(
                f"the export {folder} holds {theirs[1]} episodes of {','.join(theirs[0])} from "
                f"seed {theirs[2]}, the board {ours[1]} of {','.join(ours[0])} from {ours[2]}; "
                f"export the board's: python -m sim.export_bop --tier {export.tier} --sensor "
                f"{export.sensor} --objects {','.join(ours[0])} --episodes {ours[1]} --out DIR"
            )
        name = "bop:" + Path(csv).stem.split("_")[0]
        row = PosesRow(name, str(csv), str(folder), export.tier, export.sensor)
        if any((r.name, r.tier, r.sensor) == (name, row.tier, row.sensor) for r in rows):
            raise InvalidArgumentError(
                f"two CSVs of {name} answer tier {row.tier} under sensor {row.sensor}; give one"
            )
        rows.append(row)
    return rows


def cells_of(
    estimators: Sequence[str],
    tiers: Sequence[str],
    sensors: Sequence[str],
    rows: Sequence[PosesRow] = (),
) -> list[Cell]:
    """Every (estimator, tier, sensor) cell, with the observation mode and sensor it runs in;
    then each CSV row's cell, of its export's tier and sensor (it must be on the board).

    Raises:
        InvalidArgumentError: a CSV row whose tier or sensor the board does not show.
    """
    from sim.estimators import needs_depth

    out = []
    names = [Sensor.parse(s).name for s in sensors]
    for sensor in names:
        parsed = Sensor.parse(sensor)
        for tier in tiers:
            for est in estimators:
                depth = needs_depth(est)
                run_sensor = parsed.name if depth else Sensor("ideal", parsed.rgb).name
                out.append(Cell(est, tier, parsed.name, "rgbd" if depth else "rgb", run_sensor))
            for row in rows:
                if (row.tier, row.sensor) == (tier, sensor):
                    out.append(Cell(row.name, tier, sensor, "rgb", sensor, (row.csv, row.export)))
    for row in rows:
        if row.tier not in tiers or row.sensor not in names:
            raise InvalidArgumentError(
                f"{row.csv} answers tier {row.tier} under sensor {row.sensor}, which the board "
                f"does not show; add them to --tiers and --sensors"
            )
    return out


def _cell_files(cells_dir: Path, cell: Cell) -> tuple[Path, Path, Path]:
    """A cell's report, its journal and the settings it ran with."""
    key = cell.run_key
    return (
        cells_dir / f"{key}.json",
        cells_dir / f"{key}.journal.jsonl",
        cells_dir / f"{key}.settings.json",
    )


def stale_cells(cells: Sequence[Cell], cells_dir: Path, settings: dict[Cell, dict]) -> list[str]:
    """The cells with files in `cells_dir` (a report or a journal) whose recorded settings are
    not their `settings` today (`today_settings`; or are not recorded), each with the first
    settings that differ."""
    out = []
    for cell in cells:
        today = settings.get(cell)
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


def poses_settings(csv: str, export: str) -> dict:
    """What shapes a CSV row's results, as a cell records it: the CSV's and the export's map
    file's hashes."""
    from sim.bop_results import MAP_FILE

    return {
        "weights": None,
        "settings": {
            "csv_sha256": sha256_file(Path(csv)),
            "export_map_sha256": sha256_file(Path(export) / MAP_FILE),
        },
    }


def unfit_cells(
    cells: Sequence[Cell], cells_dir: Path, objects: Sequence[str], episodes: int
) -> list[str]:
    """The cells whose report in `cells_dir` cannot stand on this board, each with why: one that
    holds an episode stopped rather than played (`posegrasp.core.journal.interrupted`), or other
    episodes than the board's."""
    out = []
    for cell in cells:
        report_path = _cell_files(cells_dir, cell)[0]
        if not report_path.exists():
            continue
        try:
            report = json.loads(report_path.read_text())
        except ValueError:
            out.append(f"{report_path} (not JSON)")
            continue
        stopped = [e for e in report.get("episodes", []) if interrupted(e)]
        if stopped:
            out.append(f"{report_path} (holds {len(stopped)} episodes stopped, not played)")
        elif (
            report.get("episodes_per_object"),
            sorted(report.get("per_object") or {}),
            report.get("seed_start"),
        ) != (episodes, sorted(objects), EVAL_SEED_BASE):
            out.append(
                f"{report_path} (holds {report.get('episodes_per_object')} episodes of "
                f"{','.join(report.get('per_object') or {})} from seed {report.get('seed_start')})"
            )
    return sorted(set(out))


def run_cell(cell: Cell, args, cells_dir: Path, settings: dict | None = None) -> dict:
    """Run (or read back, or resume) one cell's evaluation report; a run that starts records
    `settings` (`stale_cells` checks them)."""
    from sim.evaluation import (
        Protocol,
        evaluate_protocol,
        export_protocol,
        poses_estimator,
        poses_record,
    )

    report_path, journal, settings_path = _cell_files(cells_dir, cell)
    if report_path.exists():
        return json.loads(report_path.read_text())
    if settings is not None and not journal.exists():
        atomic_write_json(settings_path, settings)
    run = {"workers": args.workers, "backend": args.backend, "address": args.address}
    if cell.poses is None:
        protocol = Protocol(
            objects=tuple(args.objects),
            episodes=args.episodes,
            seed_start=EVAL_SEED_BASE,
            tier=cell.tier,
            obs_mode=cell.obs_mode,
            sensor=cell.run_sensor,
        )
        report = evaluate_protocol(
            protocol, cell.estimator, journal=journal, resume=journal.exists(), **run
        )
    else:
        csv, export = cell.poses
        poses = poses_estimator(Path(csv), Path(export))
        poses.name = cell.estimator
        protocol = export_protocol(poses, obs_mode=cell.obs_mode, sensor=cell.run_sensor)
        report = evaluate_protocol(protocol, poses, journal=journal, resume=journal.exists(), **run)
        report["poses"] = poses_record(poses, Path(csv), report)
    atomic_write_json(report_path, report)
    journal.unlink(missing_ok=True)  # the report now holds every episode
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


def _times_ms(report: dict) -> list[float]:
    """The estimator's time per image [ms]: a live estimator's as the episodes timed it; a CSV
    row's as the method's results file states it (BOP's ``time`` column, seconds)."""
    eps = report["episodes"]
    if "poses" in report:
        times = [(e.get("estimate_info") or {}).get("time") for e in eps]
        return [1000.0 * t for t in times if isinstance(t, int | float) and t >= 0]
    return [e["timings_ms"]["estimate"] for e in eps if "estimate" in e.get("timings_ms", {})]


def cell_summary(report: dict) -> dict:
    """A cell's figures from its report: success with its Wilson interval, pose-correct rate,
    grasped with a wrong pose, the ARs, time per image and the leading failure reasons."""
    g = report["overall"]
    eps = report["episodes"]
    lo, hi = wilson_interval(g["successes"], g["episodes"])
    times = _times_ms(report)
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
    return [*out, ""]


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.0f} %"


def _num(x: float | None, fmt: str = ".3f") -> str:
    return "-" if x is None else format(x, fmt)


def markdown(board: dict, plots: str = "leaderboard") -> str:
    """The leaderboard page: how it was made, one table per (sensor, tier), the BOP analysis;
    its images are in the folder `plots`, as a link from the page's folder reads it."""
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
        f"![success per cell]({plots}/success.png)",
        "",
        *findings(board),
    ]
    lines += _cell_tables(board)
    lines += _bop_section(board["analysis"], plots)
    lines += [
        "",
        "## Confidence and abstention",
        "",
        f"![success against coverage]({plots}/risk_coverage.png)",
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


def _bop_section(a: dict, plots: str) -> list[str]:
    """What BOP scores say about grasps: Spearman's rho per AR, the separation AUC per tier
    and error, the AR needed for `TARGET_SUCCESS` per tier."""
    lines = [
        "## What BOP scores say about grasps",
        "",
        f"![AR against grasp success]({plots}/ar_vs_success.png)",
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
    """success.png, ar_vs_success.png and risk_coverage.png in folder (`sim.leaderboard_plots`)."""
    folder.mkdir(parents=True, exist_ok=True)
    cells = [c for c in board["cells"] if c.get("summary")]
    names = list(dict.fromkeys(c["estimator"] for c in cells))
    colour = {n: f"C{i % 10}" for i, n in enumerate(names)}
    by_key = _summaries(cells)
    sensors, tiers = board["sensors"], board["tiers"]
    leaderboard_plots.success_plot(by_key, names, colour, sensors, tiers, folder / "success.png")
    leaderboard_plots.ar_plot(
        cells,
        names,
        colour,
        AR_KEYS,
        board["analysis"]["spearman"],
        folder / "ar_vs_success.png",
    )
    leaderboard_plots.risk_coverage_plot(
        by_key, names, colour, sensors, tiers, folder / "risk_coverage.png"
    )


def check_estimators(value: str) -> list[str]:
    """``--estimators``: a comma list of specs (`sim.estimators`: built-in names, installed entry
    points, plug-ins ``package.module:factory``), or ``all`` (`ESTIMATORS`).

    Raises:
        UnknownNameError: a name that is neither built in nor installed, listing the valid ones.
        InvalidArgumentError: an empty list, a name given twice, a plug-in that does not import.
    """
    from sim.estimators import check_estimator_spec

    if value.strip() == "all":
        return list(ESTIMATORS)
    names = [v.strip() for v in value.split(",") if v.strip()]
    if not names:
        raise InvalidArgumentError("--estimators needs at least one estimator")
    if twice := sorted({n for n in names if names.count(n) > 1}):
        raise InvalidArgumentError(f"--estimators names {', '.join(twice)} more than once")
    return [check_estimator_spec(n) for n in names]


def today_settings(cells: Sequence[Cell]) -> dict[Cell, dict]:
    """What each cell runs with today: its estimator's settings and weights
    (`sim.estimators.estimator_settings`), or a CSV row's hashes (`poses_settings`); made once
    per estimator, before any cell runs.

    Raises:
        InvalidArgumentError: an estimator that cannot be made here (an optional extra not
            installed, weights missing, a plug-in's factory failing), in one line that says how
            to install it or to leave it out.
    """
    from sim.estimators import estimator_settings

    made: dict[str, dict] = {}
    out = {}
    for cell in cells:
        if cell.poses is not None:
            out[cell] = poses_settings(*cell.poses)
            continue
        if cell.estimator not in made:
            try:
                made[cell.estimator] = estimator_settings(cell.estimator)
            except PosegraspError as exc:
                first = (str(exc).splitlines() or [type(exc).__name__])[0]
                raise InvalidArgumentError(
                    f"{first}; or leave {cell.estimator} out of --estimators"
                ) from None
        out[cell] = made[cell.estimator]
    return out


def _command(argv: Sequence[str]) -> str:
    return f"python -m sim.leaderboard {shlex.join(argv)}".rstrip()


def _parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m sim.leaderboard", description=__doc__.split("\n")[0])
    p.add_argument(
        "--estimators",
        default=list(ESTIMATORS),
        type=arg(check_estimators),
        metavar="LIST",
        help="a comma list of estimators: built-in names, installed entry points or plug-ins "
        f"package.module:factory; 'all' is the board's rows (default {','.join(ESTIMATORS)})",
    )
    p.add_argument(
        "--poses",
        nargs=2,
        action="append",
        default=[],
        type=Path,
        metavar=("CSV", "EXPORT"),
        help="a row of a method run elsewhere: its BOP results CSV and the export of python -m "
        "sim.export_bop it answers (the board's objects and episodes, one tier and sensor); "
        "repeat for more tiers or methods",
    )
    for flag, choices, default in (
        ("--tiers", TIERS, TIERS),
        ("--sensors", SENSOR_NAMES, SENSORS),
        ("--objects", OBJECT_NAMES, OBJECT_NAMES),
    ):
        p.add_argument(
            flag,
            default=list(default),
            type=arg(check_names, choices, flag[2:-1], flag),
            metavar="LIST",
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
    add_out_argument(
        p,
        "every cell's report and journal (cells/) and, unless --publish, the board: "
        "leaderboard.json, LEADERBOARD.md and its plots (leaderboard/)",
        Path("out/leaderboard"),
    )
    p.add_argument(
        "--publish",
        action="store_true",
        help=f"write the board as the shipped page: {in_repo(PUBLISHED['markdown'])}, "
        f"{in_repo(PUBLISHED['json'])} and the plots in {in_repo(PUBLISHED['plots'])}/ (the "
        "cells stay under --out)",
    )
    p.add_argument(
        "--markdown",
        type=Path,
        default=None,
        metavar="PATH",
        help="the page (default: LEADERBOARD.md under --out, or the shipped one with --publish)",
    )
    p.add_argument(
        "--plots",
        type=Path,
        default=None,
        metavar="DIR",
        help="the folder of the page's plots (default: leaderboard/ beside the page); the page "
        "links them relative to where it is written",
    )
    add_json_argument(
        p, "the whole board (default: leaderboard.json under --out, or the shipped one)"
    )
    return p


def _outputs(args) -> tuple[Path, Path, Path | str]:
    """The page, its plots' folder and the JSON (a path or ``-``) the command line asks for."""
    out = Path(args.out)
    if args.publish:
        page, board = PUBLISHED["markdown"], PUBLISHED["json"]
    else:
        page, board = out / "LEADERBOARD.md", out / "leaderboard.json"
    page = args.markdown or page
    return page, args.plots or page.parent / "leaderboard", args.json or board


def _refuse(cells_dir: Path, what: str, found: list[str], how: str) -> InvalidArgumentError:
    return InvalidArgumentError(
        f"{len(found)} cells in {cells_dir} {what}: {'; '.join(found[:4])}"
        f"{' ...' if len(found) > 4 else ''}; {how}"
    )


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    argv = sys.argv[1:] if argv is None else argv
    args = _parser().parse_args(argv)
    check_backend(args.backend, args.address)
    cells_dir = Path(args.out) / "cells"
    page, plot_dir, board_json = _outputs(args)
    rows = poses_rows(args.poses, args.objects, args.episodes)
    cells = cells_of(args.estimators, args.tiers, args.sensors, rows)
    settings = today_settings(cells)
    again = _command(argv)
    if stale := stale_cells(cells, cells_dir, settings):
        raise _refuse(
            cells_dir,
            "ran with other estimator settings or weights than today's",
            stale,
            "move their files away to run them again, or give another --out",
        )
    if unfit := unfit_cells(cells, cells_dir, args.objects, args.episodes):
        raise _refuse(
            cells_dir,
            "cannot stand on this board",
            unfit,
            f"remove them and run the board again ({again}), or give another --out",
        )
    cells_dir.mkdir(parents=True, exist_ok=True)
    reports: dict[str, dict] = {}
    board_cells = []
    start = time.perf_counter()
    at = "before its first cell"
    try:
        for i, cell in enumerate(cells, 1):
            at = f"at cell {i} of {len(cells)} ({cell.run_key})"
            print(
                f"cell {i}/{len(cells)}: {cell.estimator}, {cell.tier}, {cell.sensor}", flush=True
            )
            row = {**asdict(cell), "run_key": cell.run_key}
            try:
                if cell.run_key not in reports:
                    reports[cell.run_key] = run_cell(cell, args, cells_dir, settings[cell])
                row["summary"] = cell_summary(reports[cell.run_key])
            except PosegraspError as exc:
                row["error"] = str(exc).splitlines()[0]
                print(f"  cannot run: {row['error']}", flush=True)
            board_cells.append(row)
        at = "while writing the board"
        board = _board(argv, args, board_cells, reports, start)
        write_json(board_json, board)
        links = Path(os.path.relpath(plot_dir, page.parent)).as_posix()
        atomic_write_bytes(page, markdown(board, links).encode())
        plots(board, plot_dir)
    except Interrupted as exc:
        kept = f"; {exc.done} of {exc.total} of its episodes are kept" if exc.journal else ""
        raise Interrupted(
            f"interrupted {at}{kept}; every finished cell is kept in {cells_dir}; resume with: "
            f"{again}"
        ) from None
    print(f"wrote {in_repo(page)} and the plots in {in_repo(plot_dir)}")
    return 0


def _board(argv, args, board_cells: list[dict], reports: dict[str, dict], start: float) -> dict:
    """The whole board as JSON: how it was made, every cell and the analysis."""
    return {
        "command": _command(argv),
        "estimators": list(dict.fromkeys(c["estimator"] for c in board_cells)),
        "tiers": list(args.tiers),
        "sensors": [Sensor.parse(s).name for s in args.sensors],
        "objects": list(args.objects),
        "episodes": args.episodes,
        "episodes_per_cell": args.episodes * len(args.objects),
        "seed_start": EVAL_SEED_BASE,
        "wall_s": run_time_s(reports.values()) or time.perf_counter() - start,
        "workers": args.workers,
        "cells": board_cells,
        "analysis": analyse(board_cells, reports),
    }


if __name__ == "__main__":
    sys.exit(main())
