"""The leaderboard's cells: one (estimator, tier, sensor) cell is one evaluation on the board's
held-out episodes (`sim.evaluation`), or the poses of a BOP results CSV on an export of them; its
report, journal and settings under the board's cells folder, what keeps a cell off the board, and
a cell's figures (`cell_summary`).
"""

from __future__ import annotations

import json
import re
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from posegrasp.core.errors import InvalidArgumentError, PosegraspError
from posegrasp.core.files import atomic_write_json, sha256_file
from posegrasp.core.journal import interrupted
from posegrasp.world.constants import EVAL_SEED_BASE
from posegrasp.world.sensors import Sensor
from sim.evaluation.stats import risk_coverage, wilson_interval

#: The ARs reported per cell, and against success.
AR_KEYS: tuple[str, ...] = ("ar_mssd", "ar_mspd", "ar_vsd")
#: Failure reasons shown per cell.
TOP_REASONS = 2


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
    from sim.evaluation.bop_results import BopPosesEstimator

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
    from sim.episodes.registry import needs_depth

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


def cell_files(cells_dir: Path, cell: Cell) -> tuple[Path, Path, Path]:
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
        report, journal, path = cell_files(cells_dir, cell)
        if today is None or not (report.exists() or journal.exists()):
            continue
        recorded = json.loads(path.read_text()) if path.exists() else None
        if recorded != today:
            differ = "no settings recorded" if recorded is None else differences(recorded, today)
            out.append(f"{cell.run_key} ({differ})")
    return sorted(set(out))


def differences(a: dict, b: dict, most: int = 3) -> str:
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
    from sim.evaluation.bop_results import MAP_FILE

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
        report_path = cell_files(cells_dir, cell)[0]
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

    report_path, journal, settings_path = cell_files(cells_dir, cell)
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
    }


def today_settings(cells: Sequence[Cell]) -> dict[Cell, dict]:
    """What each cell runs with today: its estimator's settings and weights
    (`sim.episodes.registry.estimator_settings`), or a CSV row's hashes (`poses_settings`); made
    once per estimator, before any cell runs.

    Raises:
        InvalidArgumentError: an estimator that cannot be made here (an optional extra not
            installed, weights missing, a plug-in's factory failing), in one line that says how
            to install it or to leave it out.
    """
    from sim.episodes.registry import estimator_settings

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


def summaries(cells: list[dict]) -> dict[tuple[str, str, str], dict]:
    """The cells' summaries by (estimator, sensor, tier); cells that could not run left out."""
    return {
        (c["estimator"], c["sensor"], c["tier"]): c["summary"] for c in cells if c.get("summary")
    }
