"""Shared helpers of the command-line tools: one-line errors, never a traceback."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import NoReturn

from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.files import atomic_write_json


class ArgumentParser(argparse.ArgumentParser):
    """argparse that reports a bad argument in one line on stderr and exits with status 2."""

    def error(self, message: str) -> NoReturn:
        print(f"error: {message} (see --help)", file=sys.stderr)
        raise SystemExit(2)


def fail(message: str, status: int = 2) -> int:
    """Print a one-line error and return the exit status."""
    print(f"error: {message}", file=sys.stderr)
    return status


def check_writable_file(path: Path) -> None:
    """Raise InvalidArgumentError unless a file can be written at path."""
    parent = path.resolve().parent
    blocker = next((q for q in (parent, *parent.parents) if q.exists()), None)
    if blocker is not None and not blocker.is_dir():
        raise InvalidArgumentError(f"cannot write {path}: {blocker} is a file, not a folder")
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InvalidArgumentError(f"cannot create folder {parent}: {exc.strerror}") from exc
    if path.is_dir():
        raise InvalidArgumentError(f"output path {path} is a folder; give a file name")
    probe = parent / f".{path.name}.probe"
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise InvalidArgumentError(f"cannot write to {parent}: {exc.strerror}") from exc


def write_json(path: Path, report: dict) -> None:
    """Write a report as indented JSON with sorted keys, atomically (`posegrasp.core.files`),
    and say where."""
    atomic_write_json(path, report)
    print(f"wrote {path}")
