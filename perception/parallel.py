"""Where a batch of independent work items runs: on this process, or shared with a second one.

A job is an object with ``run(item)`` that pickles; its items are independent of one another,
so running some of them on another process gives each the result this process gives it. An
`Executor` maps a job over a batch of items and returns the results in order:

- `OneProcess` runs every item here;
- `TwoProcesses` runs every other item on a worker process (a `concurrent.futures` process pool
  of one, started from a fresh interpreter) while this process runs the rest. The worker holds
  the `HELD` jobs of each kind it was sent last, so a job travels once for all its batches, also
  when jobs take turns (the codebooks of the objects an evaluation's episodes take in turn,
  between which each detection's verification job passes). Until the worker is up, after it has
  failed, or in a process forked from the one that started it, every item runs here. An error a
  job raises on the worker is raised here.

The worker is started as `multiprocessing` starts a fresh interpreter (``spawn``): it imports
the main module of the program, so a script that makes estimates keeps its work under
``if __name__ == "__main__":``, as every program using `multiprocessing` does. Where the worker
cannot start (an unguarded script), every item runs here, with the same results.
"""

from __future__ import annotations

import concurrent.futures
import multiprocessing
import os
import weakref
from collections import OrderedDict
from collections.abc import Sequence
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Protocol


class Job(Protocol):
    """Work whose items are independent of one another; it pickles."""

    def run(self, item: Any) -> Any:
        """The result of one item."""
        ...


class Executor(Protocol):
    """Maps a job over a batch of items."""

    def map(self, job: Job, items: Sequence[Any]) -> list[Any]:
        """`job.run(item)` of each item, in order."""
        ...


class OneProcess:
    """Every item on this process."""

    @staticmethod
    def map(job: Job, items: Sequence[Any]) -> list[Any]:
        """`job.run(item)` of each item, in order."""
        return [job.run(item) for item in items]


#: Jobs of each kind the worker holds at once: the most recently used are kept.
HELD = 8

#: The worker's jobs by the token its parent gave them (the worker is a process of its own;
#: this is its state).
_HELD: dict[int, Job] = {}


def _worker_start() -> None:
    """Set up the worker: one compute thread each for OpenCV and the BLAS (this process and the
    worker share two cores), Ctrl-C left to the parent."""
    import signal

    import cv2
    import threadpoolctl

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    cv2.setNumThreads(1)
    threadpoolctl.threadpool_limits(limits=1)


def _run_held(
    token: int, job: Job | None, items: Sequence[Any], dropped: Sequence[int]
) -> list[Any]:
    """On the worker: `job` (None: the one held as `token`) run over `items`, after the jobs
    held as `dropped` are let go."""
    for gone in dropped:
        _HELD.pop(gone, None)
    if job is not None:
        _HELD[token] = job
    return [_HELD[token].run(item) for item in items]


def _ready() -> bool:
    return True


class TwoProcesses:
    """This process and a worker process share each batch (see the module docstring); every
    result is the one `OneProcess` gives.

    Raises:
        OSError: the worker cannot be started.
    """

    def __init__(self) -> None:
        context = multiprocessing.get_context("spawn")  # no copy of this process's threads
        self._pool = concurrent.futures.ProcessPoolExecutor(
            1, mp_context=context, initializer=_worker_start
        )
        self._up = self._pool.submit(_ready)
        self._pid = os.getpid()
        # the jobs the worker holds by kind, least recently used first; a job's token is its
        # id(), which stays its own while it is held here
        self._sent: dict[str, OrderedDict[int, Job]] = {}
        self._dropped: list[int] = []  # tokens the worker is to let go with the next batch
        self._broken = False
        self._finalizer = weakref.finalize(self, self._pool.shutdown, False, cancel_futures=True)

    def available(self) -> bool:
        """Whether the worker takes work now: up, alive and started by this process."""
        if os.getpid() != self._pid:
            return False  # a forked child: the pool is its parent's
        if not self._broken and self._up.done():
            self._broken = self._up.exception() is not None
        return self._up.done() and not self._broken

    def map(self, job: Job, items: Sequence[Any]) -> list[Any]:
        """`job.run(item)` of each item, in order: every other one on the worker."""
        if len(items) < 2 or not self.available():
            return OneProcess.map(job, items)
        held = self._sent.setdefault(type(job).__name__, OrderedDict())
        token = id(job)
        theirs = list(items[1::2])
        fresh = held.get(token) is not job
        held[token] = job
        held.move_to_end(token)
        dropped, self._dropped = self._dropped, []
        while len(held) > HELD:
            dropped.append(held.popitem(last=False)[0])
        try:
            future = self._pool.submit(_run_held, token, job if fresh else None, theirs, dropped)
        except (BrokenProcessPool, RuntimeError):  # gone, or shut down
            self._broken = True
            return OneProcess.map(job, items)
        mine = OneProcess.map(job, items[0::2])
        try:
            done = future.result()
        except BrokenProcessPool:  # the worker died: its share done here
            self._broken = True
            done = OneProcess.map(job, theirs)
        except BaseException:  # raised by the job there, or it never arrived: send it again
            held.pop(token, None)
            self._dropped.append(token)
            raise
        return [mine[i // 2] if i % 2 == 0 else done[i // 2] for i in range(len(items))]

    def close(self) -> None:
        """Stop the worker."""
        self._finalizer()
