"""Runs that survive interruption: an append-only journal of finished work, and Ctrl-C or SIGTERM
turned into one line that says how to resume.

A journal is a JSON-lines file. Its first line is a header naming the kind of run and the
run's *protocol* (everything that defines its results: estimator, seeds, tier, ...); every further
line is one finished unit of work (an episode, a tolerance level), written and flushed as it
returns. ``--resume`` reads the units back, checks that the protocol is the same, and runs only
the rest; a line cut short by the interruption is dropped (its unit runs again). Once the run's
report is written, the journal is removed: the report then holds everything it held.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shlex
import signal
import sys
import threading
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, TextIO

from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.paths import data_root
from posegrasp.core.validate import STDOUT

#: Version of the journal format.
JOURNAL_VERSION = 1
#: Exit status of an interrupted command (128 + SIGINT, as shells report Ctrl-C).
INTERRUPTED_EXIT = 130


class Interrupted(KeyboardInterrupt):
    """Ctrl-C or SIGTERM arrived, or a worker process was killed; what had finished is in the
    journal.

    A KeyboardInterrupt, as Ctrl-C's is: raised wherever the run is (in an episode, in an
    estimator), it passes every ``except Exception`` that turns a failure into an outcome, so a
    stopped run is never scored; and the libraries that watch for Ctrl-C while they wait (Ray's
    ``get`` and ``wait``) stop for it as they do for Ctrl-C.

    Attributes:
        journal: the journal that holds the finished units (None when the run kept none).
        done: units finished, total: units of the run.
    """

    def __init__(
        self, message: str, journal: Path | None = None, done: int = 0, total: int = 0
    ) -> None:
        super().__init__(message)
        self.journal, self.done, self.total = journal, done, total


class Journal:
    """The journal of one run at `path`.

    Args:
        path: the JSON-lines file.
        kind: what kind of run writes it (``evaluate``, ``tolerance``, ...).
        protocol: JSON-serialisable description of everything that defines the results; a
            resumed run must have the same.
    """

    def __init__(self, path: Path, kind: str, protocol: dict[str, Any]) -> None:
        self.path = Path(path)
        self.kind = kind
        self.protocol = json.loads(json.dumps(protocol))  # as it reads back
        self._file: TextIO | None = None

    def start(self, resume: bool) -> list[dict[str, Any]]:
        """Open the journal for appending and return the units it already holds.

        Args:
            resume: continue the run whose journal is at `path` (it must exist and hold the
                same protocol); else start a new one (no journal may be there).

        Raises:
            InvalidArgumentError: resuming with no journal, or another run's; starting anew
                over an unfinished run's journal that holds finished units (they are never
                overwritten; one that holds none, a run stopped before its first unit, is
                replaced).
        """
        header = {"journal": self.kind, "version": JOURNAL_VERSION, "protocol": self.protocol}
        if not resume:
            if self.path.exists() and self._holds_units():
                raise InvalidArgumentError(
                    f"{self.path} holds an unfinished run; add --resume to finish it, or delete "
                    "the file to start over"
                )
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = self.path.open("w", encoding="utf-8")
            self._write(header)
            return []
        if not self.path.is_file():
            raise InvalidArgumentError(f"nothing to resume: no journal at {self.path}")
        units, good_bytes = self._read(header)
        with self.path.open("r+b") as f:  # drop a last line cut short by the interruption
            f.truncate(good_bytes)
        self._file = self.path.open("a", encoding="utf-8")
        return units

    def _holds_units(self) -> bool:
        """Whether the file holds a unit after its header (one cut short counts too)."""
        with self.path.open("rb") as f:
            f.readline()
            return bool(f.read(1))

    def _read(self, header: dict[str, Any]) -> tuple[list[dict[str, Any]], int]:
        raw = self.path.read_bytes()
        lines = raw.split(b"\n")
        try:
            first = json.loads(lines[0])
        except ValueError:
            first = None
        if not isinstance(first, dict) or first.get("journal") != self.kind:
            raise InvalidArgumentError(f"{self.path} is not a journal of a {self.kind} run")
        theirs = first.get("protocol", {})
        if differ := sorted(
            k for k in {*theirs, *self.protocol} if theirs.get(k) != self.protocol.get(k)
        ):
            raise InvalidArgumentError(
                f"{self.path} is the journal of another run (it differs in {', '.join(differ)}); "
                "resume with the same arguments, or delete it to start over"
            )
        units, good = [], len(lines[0]) + 1
        for line in lines[1:]:
            try:
                unit = json.loads(line)
            except ValueError:
                break  # the cut-short last line, and nothing after it
            if not isinstance(unit, dict):
                break
            units.append(unit)
            good += len(line) + 1
        return units, min(good, len(raw))

    def _write(self, record: dict[str, Any]) -> None:
        assert self._file is not None
        self._file.write(json.dumps(record, sort_keys=True) + "\n")
        self._file.flush()
        os.fsync(self._file.fileno())

    def append(self, unit: dict[str, Any]) -> None:
        """Keep one finished unit (written through to the disk before this returns)."""
        self._write(unit)

    def close(self) -> None:
        """Close the file; the journal stays (an unfinished run)."""
        if self._file is not None:
            self._file.close()
            self._file = None

    def finish(self) -> None:
        """The run's report is written: close and remove the journal."""
        self.close()
        self.path.unlink(missing_ok=True)


def journal_path(report: Path | str | None, kind: str, protocol: dict[str, Any]) -> Path:
    """Where a run keeps its journal: beside its report file (``out.json`` ->
    ``out.journal.jsonl``), else, for a report on standard output or none,
    ``<data root>/runs/<kind>-<hash of the protocol>.jsonl``."""
    if report is not None and str(report) != STDOUT:
        report = Path(report)
        return report.with_name(f"{report.stem}.journal.jsonl")
    digest = hashlib.sha256(json.dumps(protocol, sort_keys=True).encode()).hexdigest()[:16]
    return data_root() / "runs" / f"{kind}-{digest}.jsonl"


@contextlib.contextmanager
def interruptible() -> Iterator[None]:
    """Turn SIGTERM into `Interrupted` as Ctrl-C (KeyboardInterrupt) already is, so that both
    stop a run between two Python steps and leave its journal intact."""

    received: list[str] = []

    def on_term(signum: int, frame: Any) -> None:
        received.append(signal.Signals(signum).name)
        raise Interrupted(received[-1])

    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, on_term) if in_main else None
    try:
        yield
    except Interrupted:
        raise
    except KeyboardInterrupt:  # Ctrl-C, or a SIGTERM that a library turned into one
        raise Interrupted(received[-1] if received else "SIGINT") from None
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, previous)


def command_line(argv: list[str] | None = None, flag: str | None = None) -> str:
    """The command that is running, as a shell runs it again: ``python -m <module>`` (or the
    script's name) and its arguments (None: ``sys.argv[1:]``), `flag` appended when missing."""
    args = list(sys.argv[1:] if argv is None else argv)
    if flag is not None and flag not in args:
        args.append(flag)
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    cmd = f"python -m {spec.name}" if spec is not None else f"python {sys.argv[0]}"
    return f"{cmd} {shlex.join(args)}".rstrip()


def resume_hint(
    journal: Path,
    done: int,
    total: int,
    argv: list[str] | None = None,
    why: str = "interrupted",
    flag: str | None = "--resume",
) -> str:
    """The one line an interrupted command prints: what is kept, and the command that resumes.

    Args:
        journal: the journal that keeps the finished units.
        done, total: units finished, and units of the run.
        argv: the command's arguments (None: ``sys.argv[1:]``).
        why: what stopped the run, the line's first words.
        flag: what the command needs to resume (None: it resumes by itself when run again).
    """
    return (
        f"{why}: {done} of {total} finished and kept in {journal}; resume with: "
        f"{command_line(argv, flag)}"
    )


#: The note an episode carries when an interruption was recorded as its outcome (as runs did
#: before `Interrupted` passed the episode's error handling).
INTERRUPTED_NOTE = re.compile(r"^Interrupted: SIG[A-Z]+$")


def interrupted(unit: Any) -> bool:
    """Whether a finished unit (an episode's record) holds an interruption instead of an
    outcome: failed as ``error`` with an `INTERRUPTED_NOTE`. Such a unit is run again on resume
    and refused in a report."""
    if not isinstance(unit, dict) or unit.get("failure_reason") != "error":
        return False
    return any(INTERRUPTED_NOTE.match(str(n)) for n in unit.get("notes") or [])


@contextlib.contextmanager
def resumable(journal: Path, total: int, flag: str | None = "--resume") -> Iterator[None]:
    """Around a journaled command's work: an interruption outside its journaled map (while the
    report is made or written, say) still says what the journal keeps and how to resume."""
    try:
        yield
    except Interrupted as exc:
        if exc.journal is not None or not Path(journal).is_file():
            raise
        with Path(journal).open("rb") as f:
            done = max(0, sum(1 for _ in f) - 1)
        hint = resume_hint(Path(journal), done, total, flag=flag)
        raise Interrupted(hint, Path(journal), done, total) from None


def _results(pending: Iterator, count: int, map_options: dict[str, Any]) -> Iterator[tuple]:
    """(key, result) of each pending (fn, key, job), as `run_map` returns them; a dict result
    gets the Ray ``node`` that ran it."""
    from posegrasp.core.backends import run_map

    for (key, result), node in run_map(
        _keyed, pending, total=count, ordered=False, with_node=True, **map_options
    ):
        if node is not None and isinstance(result, dict):
            result["node"] = node
        yield key, result


def _keyed(item: tuple[Callable[[Any], Any], int, Any]) -> tuple[int, Any]:
    fn, key, job = item
    return key, fn(job)


def run_journaled(
    fn: Callable[[Any], Any],
    jobs: Iterable[Any],
    total: int,
    journal: Journal | None = None,
    resume: bool = False,
    **map_options: Any,
) -> list[Any]:
    """``[fn(job) for job in jobs]`` through `posegrasp.core.backends.run_map`, each result kept
    in `journal` as it returns, so that an interrupted run resumes where it stopped.

    Args:
        fn: a module-level function of one job; its results must be JSON-serialisable (a dict
            result gets the Ray ``node`` that ran it).
        jobs: the `total` jobs, in order; with `resume`, those the journal holds are not run.
        total: the number of jobs.
        journal: where finished results are kept (None: nowhere).
        resume: continue the run the journal holds (`Journal.start`); a unit it holds that
            records an interruption (`interrupted`) runs again.
        map_options: passed to `run_map` (backend, workers, desc, initializer, ...).

    Returns:
        The results in job order, the resumed ones as the journal holds them.

    Raises:
        Interrupted: Ctrl-C or SIGTERM, or a local worker process killed
            (`posegrasp.core.backends.WorkerDied`); with a journal, its message is the line that
            resumes.
        Any error of the run itself (an unreachable cluster, a worker that died ...): a journal
        that holds no finished result then is removed, so the same command can simply be run
        again; one that holds some is kept, and the line that resumes goes to stderr first.
    """
    from posegrasp.core.backends import WorkerDied, by_import_name

    target = by_import_name(fn)  # a Ray worker cannot import a function of ``python -m``'s __main__
    # A later line of a key wins; a unit that holds an interruption runs again.
    kept = {int(u["key"]): u["result"] for u in (journal.start(resume) if journal else [])}
    done = {k: r for k, r in kept.items() if not interrupted(r)}
    results = dict(done)
    pending = ((target, k, job) for k, job in enumerate(jobs) if k not in done)
    try:
        with interruptible():
            for key, result in _results(pending, total - len(done), map_options):
                results[key] = result
                if journal:
                    journal.append({"key": key, "result": result})
    except (Interrupted, WorkerDied) as exc:
        if journal is None:
            raise
        why = "interrupted" if isinstance(exc, Interrupted) else f"stopped: {exc}"
        hint = resume_hint(journal.path, len(results), total, why=why)
        raise Interrupted(hint, journal.path, len(results), total) from None
    except BaseException as exc:
        if journal and not results:  # failed before anything finished: nothing to resume
            journal.finish()
        elif journal:  # a crash keeps what finished, as an interruption does
            why = f"stopped by {type(exc).__name__}"
            hint = resume_hint(journal.path, len(results), total, why=why)
            print(hint, file=sys.stderr)
        raise
    finally:
        if journal:
            journal.close()
    return [results[k] for k in range(total)]
