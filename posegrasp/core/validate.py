"""One validator per concept, shared by every command line and the env.

Each ``check_*`` returns the checked value or raises `InvalidArgumentError` with one line that
names the option and the valid range or choices. `arg` turns a validator into an argparse
``type=``, so a bad value is reported while the command line is parsed, before any work starts.
Nothing here leaves a file behind: a folder is probed with a nameless temporary file.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from posegrasp.core.errors import InvalidArgumentError, PosegraspError, UnknownNameError
from posegrasp.core.transforms import check_intrinsics

T = TypeVar("T")
#: Seeds are what numpy's generators accept from every caller: 0 <= seed < 2**32.
SEED_LIMIT = 2**32
#: Worker processes of any command: at most, and unless told otherwise.
MAX_WORKERS = 64
DEFAULT_WORKERS = 1
#: ``--json`` value that means standard output.
STDOUT = "-"
#: Plot formats matplotlib writes without extra packages.
PLOT_SUFFIXES = (".png", ".pdf", ".svg")
#: Largest focal length and principal-point offset accepted in ``--K`` [px].
MAX_INTRINSIC_PX = 1e5


def check_int(value: Any, lo: int, hi: int, name: str) -> int:
    """`value` as an int in lo..hi (inclusive); bools and non-integral numbers are refused."""
    ok = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
    if not ok or not lo <= int(value) <= hi:
        raise InvalidArgumentError(f"invalid {name} {value!r}; valid: integers {lo}..{hi}")
    return int(value)


def check_float(value: Any, lo: float, hi: float, name: str) -> float:
    """`value` as a finite float in lo..hi (inclusive); bools and non-numbers are refused."""
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
        value, (bool, np.bool_)
    )
    if not ok or not math.isfinite(value) or not lo <= float(value) <= hi:
        raise InvalidArgumentError(f"invalid {name} {value!r}; valid: numbers {lo:g}..{hi:g}")
    return float(value)


def check_float_list(spec: str, lo: float, hi: float, name: str) -> list[float]:
    """A comma list of finite numbers, each in lo..hi (inclusive; `check_float`)."""
    out = []
    for v in str(spec).split(","):
        try:
            number: Any = float(v)
        except ValueError:
            number = v  # refused below with the valid range
        out.append(check_float(number, lo, hi, name))
    return out


def check_seed(value: Any, name: str = "seed", count: int = 1) -> int:
    """A seed (or the first of `count` consecutive seeds) in 0..2**32 - 1."""
    seed = check_int(value, 0, SEED_LIMIT - 1, name)
    if seed + count > SEED_LIMIT:
        raise InvalidArgumentError(
            f"invalid {name} {seed}: {count} seeds from it pass {SEED_LIMIT - 1}; "
            f"valid: 0..{SEED_LIMIT - count}"
        )
    return seed


def check_workers(value: Any, name: str = "--workers") -> int:
    """A worker count in 1..`MAX_WORKERS`."""
    return check_int(value, 1, MAX_WORKERS, name)


def effective_workers(requested: int, jobs: int) -> tuple[int, str | None]:
    """Workers actually started: at most one per job and per core; with a note when capped."""
    n = max(1, min(requested, jobs, os.cpu_count() or 1))
    note = None
    if n < requested:
        note = f"note: using {n} worker(s), not {requested}: {jobs} job(s), {os.cpu_count()} cores"
    return n, note


def check_names(spec: str, choices: Sequence[str], kind: str, option: str) -> list[str]:
    """'all' or a comma list of distinct names of `choices`."""
    if spec == "all":
        return list(choices)
    names = [s.strip() for s in str(spec).split(",")]
    if not spec or "" in names:
        raise InvalidArgumentError(
            f"invalid {option} {spec!r}; valid: all or a comma list of {', '.join(choices)}"
        )
    for n in names:
        if n not in choices:
            raise UnknownNameError(kind, n, choices)
    if dup := sorted({n for n in names if names.count(n) > 1}):
        raise InvalidArgumentError(f"{option} names {', '.join(dup)} twice; give each once")
    return names


def check_choice(value: str, choices: Sequence[str], kind: str) -> str:
    """`value` when it is one of `choices` (UnknownNameError listing them otherwise)."""
    if value not in choices:
        raise UnknownNameError(kind, str(value), choices)
    return value


def _writable_ancestor(folder: Path) -> None:
    existing = next((q for q in (folder, *folder.parents) if q.exists()), None)
    if existing is None or not existing.is_dir():
        raise InvalidArgumentError(f"cannot write in {folder}: {existing} is a file, not a folder")
    try:  # a nameless file, gone when closed: os.access says yes to root on read-only mounts
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError as exc:
        raise InvalidArgumentError(
            f"cannot write in {folder}: {existing} is not writable ({exc.strerror})"
        ) from None


def check_output_file(path: str | Path, option: str, suffixes: Sequence[str] = ()) -> Path:
    """A file that can be written: not a folder (``dir/`` is refused), a known suffix when
    `suffixes` are given, and a writable folder (or writable nearest existing ancestor)."""
    raw = str(path)
    p = Path(raw)
    if raw.endswith(("/", os.sep)) or p.is_dir() or not p.name:
        raise InvalidArgumentError(f"invalid {option} {raw!r}: it is a folder; give a file name")
    if suffixes and p.suffix.lower() not in suffixes:
        raise InvalidArgumentError(
            f"invalid {option} {raw!r}; valid suffixes: {', '.join(suffixes)}"
        )
    if p.exists() and not os.access(p, os.W_OK):
        raise InvalidArgumentError(f"invalid {option} {raw!r}: the file is not writable")
    _writable_ancestor(p.resolve().parent)
    return p


def check_output_dir(path: str | Path, option: str) -> Path:
    """A folder that can be written in (created later, when the work writes)."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise InvalidArgumentError(f"invalid {option} {str(path)!r}: a file, not a folder")
    _writable_ancestor(p.resolve())
    return p


def check_plot_path(path: str | Path, option: str = "--plot") -> Path:
    """A plot file whose suffix matplotlib writes (`PLOT_SUFFIXES`)."""
    return check_output_file(path, option, PLOT_SUFFIXES)


def check_json_output(path: str | Path, option: str = "--json") -> Path | str:
    """Where JSON goes: `STDOUT` (``-``) for standard output, else a file `check_output_file`
    accepts."""
    if str(path) == STDOUT:
        return STDOUT
    return check_output_file(path, option)


def check_input_file(path: str | Path, option: str) -> Path:
    """An existing, readable file."""
    path = Path(path)
    if not path.is_file():
        what = "a folder" if path.is_dir() else "no such file"
        raise InvalidArgumentError(f"invalid {option} {str(path)!r}: {what}")
    return path


def check_json_file(path: str | Path, option: str) -> Any:
    """The content of an existing JSON file."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise InvalidArgumentError(
            f"invalid {option} {str(path)!r}: not a JSON file ({exc})"
        ) from None


def parse_intrinsics(spec: str, option: str = "--K") -> np.ndarray:
    """``fx,fy,cx,cy`` [px] as a checked K: positive focal lengths and principal point within
    `MAX_INTRINSIC_PX` (`posegrasp.core.transforms.check_intrinsics`)."""
    try:
        fx, fy, cx, cy = (float(v) for v in str(spec).split(","))
    except ValueError:
        raise InvalidArgumentError(
            f"invalid {option} {spec!r}; valid: four numbers fx,fy,cx,cy [px]"
        ) from None
    for v in (fx, fy, cx, cy):
        if not math.isfinite(v) or abs(v) > MAX_INTRINSIC_PX:
            raise InvalidArgumentError(
                f"invalid {option} {spec!r}; valid: finite values within +-{MAX_INTRINSIC_PX:g}"
            )
    try:
        return check_intrinsics(np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]))
    except InvalidArgumentError as exc:
        raise InvalidArgumentError(f"invalid {option} {spec!r}: {exc}") from None


def arg(check: Callable[..., T], *args: Any, base: Callable[[str], Any] = str) -> Callable:
    """An argparse ``type=`` that converts with `base` and validates with
    ``check(value, *args)``; its error is the validator's one line."""

    def convert(text: str) -> T:
        try:
            value = base(text)
        except ValueError:
            value = text  # the validator refuses it with its own message
        try:
            return check(value, *args)
        except PosegraspError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    return convert


def check_tolerance_curves(data: Any, option: str = "--tolerance") -> dict:
    """Curves of ``python -m sim.tolerance``: {object: {kind: {"levels": [...], "success_rate":
    [...]}}}, levels and rates finite and of one length, rates in [0, 1]."""
    bad = f"invalid {option}: not the JSON of python -m sim.tolerance"
    if not isinstance(data, dict) or not data:
        raise InvalidArgumentError(f"{bad} (no object)")
    for obj, kinds in data.items():
        if not isinstance(kinds, dict):
            raise InvalidArgumentError(f"{bad} ({obj!r} holds no curves)")
        for kind, c in kinds.items():
            try:
                levels = np.asarray(c["levels"], float)
                rates = np.asarray(c["success_rate"], float)
            except (TypeError, KeyError, ValueError):
                raise InvalidArgumentError(f"{bad} ({obj}/{kind})") from None
            if (
                levels.ndim != 1
                or levels.shape != rates.shape
                or not np.all(np.isfinite(levels))
                or not np.all((rates >= 0) & (rates <= 1))
            ):
                raise InvalidArgumentError(f"{bad} ({obj}/{kind}: levels and rates in [0, 1])")
    return data


def check_tolerance_file(path: str | Path, option: str = "--tolerance") -> dict:
    """The validated curves of a ``sim.tolerance`` JSON file."""
    return check_tolerance_curves(check_json_file(path, option), option)
