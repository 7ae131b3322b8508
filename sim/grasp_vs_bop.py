"""What BOP scores say about grasps, as a command: the study (`sim.evaluation.bop_agreement`)
of `sim.evaluate` reports, each report one cell::

    python -m sim.grasp_vs_bop REPORT [REPORT ...] [--target 0.95] [--boot N] [--json PATH]

per report and pooled over them, each per-episode error's separation AUC; given several
reports, Spearman's rho of each AR against grasp success over them and the AR each needs for
the target success.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.validate import arg, check_float, check_input_file, check_int
from sim.evaluation.bop_agreement import DEFAULT_BOOT, DEFAULT_TARGET, format_study, study
from sim.evaluation.report_schema import read_report


def read_reports(paths: Sequence[Path]) -> list[tuple[str, dict[str, Any]]]:
    """The reports in `paths`, each labelled by its file name (its path where two share a name).

    Raises:
        InvalidArgumentError: a file that is unreadable, not JSON, not a conforming report or
            one that holds a stopped episode (`sim.evaluation.report_schema.read_report`), naming
            it.
    """
    names = [Path(p).name for p in paths]
    return [
        (name if names.count(name) == 1 else str(path), read_report(path))
        for path, name in zip(paths, names, strict=True)
    ]


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(
        prog="python -m sim.grasp_vs_bop",
        description="What BOP scores say about grasps: per sim.evaluate report and pooled, how "
        "well each pose error separates held grasps from failed ones; over several reports "
        "(cells), how AR ranks them by grasp success and the AR a target success needs.",
    )
    p.add_argument(
        "reports",
        nargs="+",
        type=arg(check_input_file, "report", base=Path),
        metavar="REPORT",
        help="a report of python -m sim.evaluate --json; several are the cells of the study",
    )
    p.add_argument(
        "--target",
        type=arg(check_float, 0.5, 0.999, "--target", base=float),
        default=DEFAULT_TARGET,
        help=f"the grasp success whose AR is found, 0.5..0.999 (default {DEFAULT_TARGET})",
    )
    p.add_argument(
        "--boot",
        type=arg(check_int, 100, 100_000, "--boot", base=int),
        default=DEFAULT_BOOT,
        help=f"bootstrap resamples of Spearman's interval, 100..100000 (default {DEFAULT_BOOT})",
    )
    add_json_argument(p, "the study")
    args = p.parse_args(argv)
    result = study(read_reports(args.reports), args.target, args.boot)
    print(format_study(result), file=summary_stream(args.json))
    if args.json is not None:
        write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
