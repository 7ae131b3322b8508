"""The leaderboard's cells: one (estimator, tier, sensor, task, shifts) cell is one evaluation on
the board's held-out episodes (`sim.evaluation`), or the poses of a BOP results CSV on an export
of them; its report, journal and settings under the board's cells folder, and what keeps a cell
off the board. Every cell plays the same seeds, so cells pair episode by episode.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from grasping.place import UNNAMED_BELIEF, PlaceConfig
from posegrasp.core.errors import InvalidArgumentError, PosegraspError
from posegrasp.core.files import atomic_write_json
from posegrasp.core.journal import interrupted
from posegrasp.world.constants import EVAL_SEED_BASE
from posegrasp.world.objects import OBJECT_NAMES
from posegrasp.world.sensors import Sensor
from posegrasp.world.user_objects import description_revision
from sim.board.poses import PosesRow, poses_settings
from sim.board.tracks import BASE_TASK, NO_SHIFT, shifts_of, track_key


@dataclass(frozen=True)
class Cell:
    """One leaderboard cell and the run that fills it.

    Attributes:
        estimator: the row: an estimator's spec or a CSV row's name (``bop:<method>``).
        tier, sensor: the scene tier and the sensor the board shows the cell under.
        obs_mode: what the estimator sees (``rgb`` or ``rgbd``).
        run_sensor: the sensor the run actually uses: an RGB-only estimator's ignores the depth
            model.
        poses: a row of a BOP results CSV: the CSV and the export it answers (None: a live
            estimator).
        task: what the robot does (`posegrasp.world.goals.TASKS`).
        shifts: the shift setting every episode is seen under (`sim.board.tracks.shift_label`).
    """

    estimator: str
    tier: str
    sensor: str
    obs_mode: str
    run_sensor: str
    poses: tuple[str, str] | None = None
    task: str = BASE_TASK
    shifts: str = NO_SHIFT

    @property
    def run_key(self) -> str:
        """File stem of the run (shared by cells that are the same run); today's track (lift, no
        shift) adds nothing to it, so its cells keep the files they had before tracks."""
        track = track_key(self.task, self.shifts)
        return _safe(f"{self.tier}__{self.run_sensor}{track}__{self.estimator}")


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", name)


def _track_cells(
    estimators: Sequence[str],
    tiers: Sequence[str],
    sensors: Sequence[str],
    rows: Sequence[PosesRow],
    task: str,
    shifts: str,
) -> list[Cell]:
    """The cells of one track: per sensor and tier, each estimator's, then each CSV row's of
    that tier and sensor (only unshifted: its poses answer the export's unshifted images)."""
    from sim.episodes.registry import needs_depth

    out = []
    for sensor in sensors:
        parsed = Sensor.parse(sensor)
        for tier in tiers:
            for est in estimators:
                depth = needs_depth(est)
                run_sensor = parsed.name if depth else Sensor("ideal", parsed.rgb).name
                mode = "rgbd" if depth else "rgb"
                out.append(Cell(est, tier, parsed.name, mode, run_sensor, None, task, shifts))
            for row in rows if shifts == NO_SHIFT else ():
                if (row.tier, row.sensor) == (tier, sensor):
                    poses = (row.csv, row.export)
                    out.append(Cell(row.name, tier, sensor, "rgb", sensor, poses, task, shifts))
    return out


def cells_of(
    estimators: Sequence[str],
    tiers: Sequence[str],
    sensors: Sequence[str],
    rows: Sequence[PosesRow] = (),
    tasks: Sequence[str] = (BASE_TASK,),
    shifts: Sequence[str] = (NO_SHIFT,),
) -> list[Cell]:
    """Every (estimator, tier, sensor, task, shifts) cell, with the observation mode and sensor
    it runs in, track by track (task, then shift setting), each as `_track_cells`: a CSV row's
    cells are those of its export's tier and sensor, unshifted.

    Raises:
        InvalidArgumentError: a CSV row whose tier or sensor the board does not show, or CSV
            rows on a board without the unshifted setting.
    """
    names = [Sensor.parse(s).name for s in sensors]
    for row in rows:
        if row.tier not in tiers or row.sensor not in names:
            raise InvalidArgumentError(
                f"{row.csv} answers tier {row.tier} under sensor {row.sensor}, which the board "
                f"does not show; add them to --tiers and --sensors"
            )
    if rows and NO_SHIFT not in shifts:
        raise InvalidArgumentError(
            f"a --poses row answers the unshifted scenes of its export; add {NO_SHIFT} to --shifts"
        )
    return [
        cell
        for task in tasks
        for setting in shifts
        for cell in _track_cells(estimators, tiers, names, rows, task, setting)
    ]


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


def _track_differs(cell: Cell, record: dict) -> str | None:
    """Why a report or a journal's protocol (`record`) is not of the cell's track, or None: the
    task and the shifts it records (none recorded: ``lift``, no shift), and on the place task
    the belief the robot placed on (none recorded: ``estimate``; the board's is the task's
    default, `grasping.place.PlaceConfig.belief`)."""
    task = record.get("task", BASE_TASK)
    theirs = (task, list(record.get("shifts", [])))
    ours = (cell.task, [str(s) for s in shifts_of(cell.shifts)])
    if theirs != ours:
        return (
            f"task {theirs[0]} with shifts {','.join(theirs[1]) or NO_SHIFT}, not {cell.task} "
            f"with {cell.shifts}"
        )
    belief, scored = record.get("belief", UNNAMED_BELIEF), PlaceConfig.belief
    if task == "place" and belief != scored:
        return f"placed on the belief {belief}, not {scored}"
    return None


def _journal_header(path: Path) -> dict:
    """The protocol a journal's header records (empty if it cannot be read)."""
    try:
        with path.open(encoding="utf-8") as f:
            header = json.loads(f.readline())
    except (OSError, ValueError):
        return {}
    return header.get("protocol", {}) if isinstance(header, dict) else {}


def _why_unfit(cell: Cell, report: dict, objects: Sequence[str], episodes: int) -> str | None:
    """Why a cell's report cannot stand on the board, or None (`unfit_cells`)."""
    stopped = [e for e in report.get("episodes", []) if interrupted(e)]
    if stopped:
        return f"holds {len(stopped)} episodes stopped, not played"
    if (
        report.get("episodes_per_object"),
        sorted(report.get("per_object") or {}),
        report.get("seed_start"),
    ) != (episodes, sorted(objects), EVAL_SEED_BASE):
        return (
            f"holds {report.get('episodes_per_object')} episodes of "
            f"{','.join(report.get('per_object') or {})} from seed {report.get('seed_start')}"
        )
    return _track_differs(cell, report)


def unfit_cells(
    cells: Sequence[Cell], cells_dir: Path, objects: Sequence[str], episodes: int
) -> list[str]:
    """The cells whose report or journal in `cells_dir` cannot stand on this board, each with
    why: a report that holds an episode stopped rather than played
    (`posegrasp.core.journal.interrupted`), or other episodes than the board's; a report or a
    journal of another track (task or shifts) than the cell's."""
    out = []
    for cell in cells:
        report_path, journal, _ = cell_files(cells_dir, cell)
        if journal.exists() and (why := _track_differs(cell, _journal_header(journal))):
            out.append(f"{journal} ({why})")
        if not report_path.exists():
            continue
        try:
            report = json.loads(report_path.read_text())
        except ValueError:
            out.append(f"{report_path} (not JSON)")
            continue
        if why := _why_unfit(cell, report, objects, episodes):
            out.append(f"{report_path} ({why})")
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
            pool=tuple(args.pool),
            sensor=cell.run_sensor,
            task=cell.task,
            shifts=shifts_of(cell.shifts),
        )
        report = evaluate_protocol(
            protocol, cell.estimator, journal=journal, resume=journal.exists(), **run
        )
    else:
        csv, export = cell.poses
        poses = poses_estimator(Path(csv), Path(export))
        poses.name = cell.estimator
        protocol = export_protocol(
            poses, obs_mode=cell.obs_mode, sensor=cell.run_sensor, task=cell.task
        )
        report = evaluate_protocol(protocol, poses, journal=journal, resume=journal.exists(), **run)
        report["poses"] = poses_record(poses, Path(csv), report)
    atomic_write_json(report_path, report)
    journal.unlink(missing_ok=True)  # the report now holds every episode
    return report


def today_settings(
    cells: Sequence[Cell], objects: Sequence[str] = (), pool: Sequence[str] = ()
) -> dict[Cell, dict]:
    """What each cell runs with today: its estimator's settings and weights
    (`sim.episodes.registry.estimator_settings`), or a CSV row's hashes (`poses_settings`); made
    once per estimator, before any cell runs. With user objects among `objects` or the
    distractors' `pool`, each one's description revision too (``user_objects``: an object made
    again is another object), and a pool of distractors other than the built-in objects
    (``pool``).

    Raises:
        InvalidArgumentError: an estimator that cannot be made here (an optional extra not
            installed, weights missing, a plug-in's factory failing), in one line that says how
            to install it or to leave it out.
    """
    from sim.episodes.registry import estimator_settings

    mine = {n: description_revision(n) for n in (*objects, *pool) if n not in OBJECT_NAMES}
    extra: dict = {"user_objects": mine} if mine else {}
    if pool:
        extra["pool"] = list(pool)
    made: dict[str, dict] = {}
    out = {}
    for cell in cells:
        if cell.poses is not None:
            out[cell] = poses_settings(*cell.poses) | extra
            continue
        if cell.estimator not in made:
            try:
                made[cell.estimator] = estimator_settings(cell.estimator)
            except PosegraspError as exc:
                first = (str(exc).splitlines() or [type(exc).__name__])[0]
                raise InvalidArgumentError(
                    f"{first}; or leave {cell.estimator} out of --estimators"
                ) from None
        out[cell] = made[cell.estimator] | extra
    return out
