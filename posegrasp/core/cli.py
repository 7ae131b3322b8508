"""Shared helpers of the command-line tools: one convention, one-line errors, never a traceback.

Every command follows the same convention:

- ``--json PATH`` writes the machine-readable output to PATH; ``-`` writes it to standard output,
  and the human summary then goes to standard error, so that standard output is valid JSON;
- ``--out DIR`` is always a folder of outputs;
- ``--workers N`` is the number of worker processes, `DEFAULT_WORKERS` unless told otherwise;
- every value is checked while the command line is parsed (``type=arg(...)``), and a bad one is a
  single ``error: ...`` line on standard error with exit status 2;
- ``main(argv) -> int`` is wrapped by `command`, so a `PosegraspError` raised later is the same
  one-line error with status 2.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NoReturn, TextIO

from posegrasp.core.errors import PosegraspError
from posegrasp.core.files import atomic_write_json
from posegrasp.core.journal import INTERRUPTED_EXIT, Interrupted, command_line, interruptible
from posegrasp.core.validate import (
    DEFAULT_WORKERS,
    MAX_WORKERS,
    STDOUT,
    arg,
    check_int,
    check_json_output,
    check_output_dir,
    check_workers,
)


class ArgumentParser(argparse.ArgumentParser):
    """argparse that reports a bad argument in one line on stderr and exits with status 2."""

    def error(self, message: str) -> NoReturn:
        print(f"error: {message} (see --help)", file=sys.stderr)
        raise SystemExit(2)


def fail(message: str, status: int = 2) -> int:
    """Print a one-line error and return the exit status."""
    print(f"error: {message}", file=sys.stderr)
    return status


def command(main: Callable[..., int]) -> Callable[..., int]:
    """Decorate a command's ``main(argv) -> int`` so that it always returns its exit status.

    A `PosegraspError` becomes one ``error:`` line on stderr and status 2 (`fail`); Ctrl-C or
    SIGTERM, wherever the command is (`posegrasp.core.journal.interruptible` holds while it
    runs), one line (for a journaled run, the command that resumes it) and status 130; argparse's
    exit (``--help``: 0, a bad argument, already reported in one line: 2) becomes its status. The
    decorated function is a console-script entry point as it is (``sys.exit(main())``).

    Args:
        main: the command; takes the argument list (None: ``sys.argv[1:]``), returns its status.

    Returns:
        The wrapped command.
    """

    @functools.wraps(main)
    def run(*args: Any, **kwargs: Any) -> int:
        try:
            with interruptible():
                return main(*args, **kwargs)
        except PosegraspError as exc:
            return fail(str(exc))
        except Interrupted as exc:  # a journaled run: the line says how to resume
            line = str(exc)
            if exc.journal is None and not line.startswith("interrupted"):
                line = (
                    f"interrupted by {line or 'a signal'}: the work under way is not recorded; "
                    f"run again with: {command_line()}"
                )
            print(line, file=sys.stderr)
            return INTERRUPTED_EXIT
        except KeyboardInterrupt:
            print("interrupted", file=sys.stderr)
            return INTERRUPTED_EXIT
        except SystemExit as exc:
            if exc.code is None or isinstance(exc.code, int):
                return exc.code or 0
            return fail(str(exc.code), 1)

    return run


def summary_stream(json_path: Path | str | None) -> TextIO:
    """Where a command prints its human summary: stderr when its JSON goes to standard output
    (``--json -``), else stdout."""
    return sys.stderr if json_path is not None and str(json_path) == STDOUT else sys.stdout


def write_json(path: Path | str, report: Any) -> None:
    """Write a report as indented JSON with sorted keys and say where: to standard output when
    `path` is ``-`` (`STDOUT`; nothing else is printed), else atomically to the file
    (`posegrasp.core.files`)."""
    if str(path) == STDOUT:
        sys.stdout.write(json.dumps(report, indent=1, sort_keys=True) + "\n")
        sys.stdout.flush()
        return
    atomic_write_json(path, report)
    print(f"wrote {path}")


def add_json_argument(
    parser: argparse.ArgumentParser, what: str, default: Path | str | None = None
) -> None:
    """Add ``--json PATH``: write `what` as JSON to PATH, ``-`` for standard output.

    Args:
        parser: the command line.
        what: what the JSON holds, e.g. "the full report".
        default: written unless told otherwise (None: no JSON unless asked for).
    """
    tail = "" if default is None else f"; default {default}"
    parser.add_argument(
        "--json",
        type=arg(check_json_output, "--json"),
        default=default,
        metavar="PATH",
        help=f"write {what} as JSON to PATH ('-': standard output, the printed summary then "
        f"goes to standard error{tail})",
    )


def add_workers_argument(
    parser: argparse.ArgumentParser, default: int = DEFAULT_WORKERS, what: str = ""
) -> None:
    """Add ``--workers N``: worker processes, 1..`MAX_WORKERS`, checked while parsing.

    Args:
        parser: the command line.
        default: the count unless told otherwise (`DEFAULT_WORKERS` for every command).
        what: more on what the workers do, appended to the help.
    """
    more = f"; {what}" if what else ""
    parser.add_argument(
        "--workers",
        type=arg(check_workers, base=int),
        default=default,
        metavar="N",
        help=f"worker processes, 1..{MAX_WORKERS} (default {default}){more}",
    )


def add_out_argument(
    parser: argparse.ArgumentParser,
    what: str,
    default: Path | str | None = None,
    required: bool = False,
    aliases: Sequence[str] = (),
) -> None:
    """Add ``--out DIR``: the folder of a command's outputs, checked while parsing
    (`check_output_dir`; created when the work writes).

    Args:
        parser: the command line.
        what: what the folder receives, e.g. "the head image and the grasp GIF".
        default: the folder unless told otherwise (None: none); a string is checked like a
            given value.
        required: the command needs one (also when given by an alias).
        aliases: former names of the option, accepted but not shown in ``--help``.
    """
    tail = f" (default {default})" if default is not None else ""
    # A required option with aliases: exactly one of them, named --out in the error.
    group = parser.add_mutually_exclusive_group(required=True) if required and aliases else parser
    group.add_argument(
        "--out",
        type=arg(check_output_dir, "--out", base=Path),
        default=default,
        required=required and not aliases,
        metavar="DIR",
        help=f"folder of the outputs: {what}{tail}",
    )
    for alias in aliases:
        group.add_argument(
            alias, dest="out", type=arg(check_output_dir, alias, base=Path), help=argparse.SUPPRESS
        )


def add_threads_argument(parser: argparse.ArgumentParser, default: int = 2) -> None:
    """Add ``--threads N``: torch's compute threads, checked while parsing (the benchmarks time
    on the machine's 2 cores by default)."""
    parser.add_argument(
        "--threads",
        type=arg(check_int, 1, 64, "--threads", base=int),
        default=default,
        help=f"torch threads, 1..64 (default {default})",
    )


def verdict(met: bool) -> str:
    """A target's verdict as the benchmarks print it: PASS, or MISS."""
    return "PASS" if met else "MISS"


def target(goal: str, met: bool) -> str:
    """A measured figure's target and verdict as the benchmarks print them after the figure,
    e.g. ``[target <= 100 ms: PASS]``."""
    return f"[target {goal}: {verdict(met)}]"
