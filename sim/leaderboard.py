"""The leaderboard: every (estimator, tier, sensor, task, shifts) cell on the same episodes.

    python -m sim.leaderboard [--estimators LIST] [--poses CSV EXPORT ...] [--tiers LIST] \
        [--sensors LIST] [--tasks lift,place] [--shifts SETTINGS] [--objects all] \
        [--episodes N] [--workers N] [--backend local|ray] [--out DIR] [--publish]

A row is any estimator a spec names (`sim.episodes.registry`: a built-in name, an installed entry
point, a plug-in ``package.module:factory``) or the poses of a BOP results CSV of a method run
elsewhere (``--poses CSV EXPORT``: the CSV answers the export of `sim.export_bop` it names, whose
episodes must be the board's), ranked with the others on the same episodes.

Beside today's cells (task ``lift``, no shift) the board runs tracks (`sim.board.tracks`):
``--tasks lift,place`` adds the place task (the robot carries the object to a goal pose and
succeeds only if it rests within 2 cm and 10 deg), ``--shifts`` purely visual scene shifts, a
comma list of settings: ``none``, ``NAME[:LEVEL]``, several at once joined by ``+``
(``light_colour:3+camera:3``), every factor at once ``all[:LEVEL]``, and ``factors[:LEVEL]`` for
``none`` and each factor alone (``--shifts none,camera:3,all:3``). Every cell plays the same
seeds, so the page pairs them episode by episode: each pair of estimators in a cell (McNemar's
exact test; on the place task also the signed-rank test of placement errors), and each estimator
under each shift against itself unshifted. Today's cells keep their files, so a board of the
default track reads them back.

Each cell is one evaluation (`sim.evaluation`; its report and journal under ``--out``/cells), so
a stopped leaderboard resumes where it stopped when its command runs again, as the line it
prints says: a finished cell is read back, a started one resumes from its journal. A cell
records the estimator's settings and weights it ran with
(`sim.episodes.registry.estimator_settings`; a CSV's and its export's hashes); where they are not
today's, the board refuses to run and names the cells, rather than mix runs of other settings into
it; so it does for a cell that holds an episode stopped rather than played, other episodes than
the board's, or another task or other shifts than its own. An estimator that cannot be made
here (an extra not installed) is refused before any cell runs, in one line naming the install. An
estimator that needs depth (`sim.episodes.registry.needs_depth`) sees ``rgbd`` observations, every
other one ``rgb``; an RGB-only estimator sees only the sensor's colour model, so its cells under
sensors that differ only in depth are one run, shown under each.

Every cell's episodes run through `sim.evaluation.evaluate_protocol` on ``--backend`` (a local
pool of ``--workers``, or Ray: ``--backend ray [--address HOST:PORT]`` for a big board), the
tracks' cells as today's.

The board goes under ``--out``: the whole board as JSON, the Markdown page and its plots
(`sim.board`; with the place task, also success against the estimate's error), the page linking
its plots relative to where it is written; ``--publish`` writes the shipped page instead
(`docs/LEADERBOARD.md`, its JSON and plots, never edited by hand).
"""

from __future__ import annotations

import os
import shlex
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path

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
from posegrasp.core.files import atomic_write_bytes
from posegrasp.core.journal import Interrupted
from posegrasp.core.paths import DOCS_DIR, in_repo
from posegrasp.core.validate import arg, check_int, check_names
from posegrasp.world.constants import EVAL_SEED_BASE
from posegrasp.world.goals import TASKS
from posegrasp.world.objects import OBJECT_NAMES, check_objects
from posegrasp.world.sensors import SENSOR_NAMES, Sensor
from posegrasp.world.tiers import TIERS, add_pool_argument
from sim.board.analysis import analyse
from sim.board.cell_summaries import cell_summary, run_time_s
from sim.board.cells import cells_of, run_cell, stale_cells, today_settings, unfit_cells
from sim.board.figures import plots
from sim.board.page import markdown
from sim.board.poses import poses_rows
from sim.board.tracks import (
    BASE_TASK,
    NO_SHIFT,
    SHIFTS_SYNTAX,
    check_shift_settings,
    check_tasks,
    track_title,
)
from sim.episodes.registry import BOARD_ESTIMATORS

#: The default sensors: the ideal camera and a structured-light depth camera.
SENSORS: tuple[str, ...] = ("ideal", "kinect-v1")
#: Where ``--publish`` writes the board: the shipped page, its JSON and its plots.
PUBLISHED = {
    "markdown": DOCS_DIR / "LEADERBOARD.md",
    "json": DOCS_DIR / "leaderboard.json",
    "plots": DOCS_DIR / "leaderboard",
}


def check_estimators(value: str) -> list[str]:
    """``--estimators``: a comma list of specs (`sim.episodes.registry`: built-in names, installed
    entry points, plug-ins ``package.module:factory``), or ``all`` (`BOARD_ESTIMATORS`).

    Raises:
        UnknownNameError: a name that is neither built in nor installed, listing the valid ones.
        InvalidArgumentError: an empty list, a name given twice, a plug-in that does not import.
    """
    from sim.episodes.registry import check_estimator_spec

    if value.strip() == "all":
        return list(BOARD_ESTIMATORS)
    names = [v.strip() for v in value.split(",") if v.strip()]
    if not names:
        raise InvalidArgumentError("--estimators needs at least one estimator")
    if twice := sorted({n for n in names if names.count(n) > 1}):
        raise InvalidArgumentError(f"--estimators names {', '.join(twice)} more than once")
    return [check_estimator_spec(n) for n in names]


def _command(argv: Sequence[str]) -> str:
    return f"python -m sim.leaderboard {shlex.join(argv)}".rstrip()


def _add_output_arguments(p: ArgumentParser) -> None:
    """Add where the board goes: ``--publish``, ``--markdown``, ``--plots`` and ``--json``."""
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


def _add_track_arguments(p: ArgumentParser) -> None:
    """Add the board's tracks: ``--tasks`` and ``--shifts`` (`sim.board.tracks`)."""
    p.add_argument(
        "--tasks",
        default=[BASE_TASK],
        type=arg(check_tasks),
        metavar="LIST",
        help=f"a comma list of {', '.join(TASKS)}: lift grasps and holds; place then carries "
        f"the object to a goal pose and scores where it rests (2 cm, 10 deg) (default {BASE_TASK})",
    )
    p.add_argument(
        "--shifts",
        default=[NO_SHIFT],
        type=arg(check_shift_settings),
        metavar="SETTINGS",
        help=f"purely visual scene shifts, each setting a track: {SHIFTS_SYNTAX} (default "
        f"{NO_SHIFT}; e.g. none,camera:3,all:3)",
    )


def _parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m sim.leaderboard", description=__doc__.split("\n")[0])
    p.add_argument(
        "--estimators",
        default=list(BOARD_ESTIMATORS),
        type=arg(check_estimators),
        metavar="LIST",
        help="a comma list of estimators: built-in names, installed entry points or plug-ins "
        f"package.module:factory; 'all' is the board's rows (default {','.join(BOARD_ESTIMATORS)})",
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
    ):
        p.add_argument(
            flag,
            default=list(default),
            type=arg(check_names, choices, flag[2:-1], flag),
            metavar="LIST",
            help=f"a comma list of {', '.join(choices)}, or 'all' (default {','.join(default)})",
        )
    p.add_argument(
        "--objects",
        default=list(OBJECT_NAMES),
        type=arg(check_objects, "--objects"),
        metavar="LIST",
        help=f"'all' (default: {', '.join(OBJECT_NAMES)}) or a comma list of objects, built-in or "
        "user objects (python -m sim.add_object): the unseen-objects track is the board on the "
        "held-out meshes made user objects (studies/public_meshes.py --set unseen)",
    )
    add_pool_argument(p)
    _add_track_arguments(p)
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
    _add_output_arguments(p)
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
    cells = cells_of(args.estimators, args.tiers, args.sensors, rows, args.tasks, args.shifts)
    settings = today_settings(cells, args.objects, args.pool)
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
            track = track_title(cell.task, cell.shifts)
            print(
                f"cell {i}/{len(cells)}: {cell.estimator}, {cell.tier}, {cell.sensor}, {track}",
                flush=True,
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
    """The whole board as JSON: how it was made (its tracks too), every cell and the analysis;
    its wall time [s] is its episodes' (`sim.board.cell_summaries.run_time_s`)."""
    return {
        "command": _command(argv),
        "estimators": list(dict.fromkeys(c["estimator"] for c in board_cells)),
        "tiers": list(args.tiers),
        "sensors": [Sensor.parse(s).name for s in args.sensors],
        "tasks": list(args.tasks),
        "shifts": list(args.shifts),
        "objects": list(args.objects),
        "pool": list(args.pool),
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
