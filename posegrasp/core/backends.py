"""Where embarrassingly parallel work runs: a local process pool or a Ray cluster.

`run_map(fn, jobs, backend=...)` applies `fn` to every job and yields the results in job order
(or as they complete, `ordered=False`), with a progress bar that counts items as they return:

- ``local`` (the default): ``fn`` in this process (one worker) or in a pool of `workers` spawned
  processes, one job at a time (`chunk` jobs with ``chunk``).
- ``ray``: Ray tasks over chunks of jobs, sized so the per-task overhead (a few milliseconds)
  stays small against the work (`default_chunk`). With `address` the tasks run on that existing
  cluster (``ray start --head`` prints it; ``auto`` finds one started on this machine), else a
  Ray with `workers` CPUs starts here and stops at the end. A chunk whose worker process or node
  dies is run again (up to `MAX_RETRIES` times), so the results stay complete and identical. An
  address that cannot be reached is a `BackendError` within `CONNECT_TIMEOUT_S`.

Ray is an optional dependency (``pip install 'posegrasp[ray]'``), imported only by the ``ray``
backend. Jobs, results, `fn` and `initializer` must pickle (module-level functions); on a
cluster of several machines every node needs posegrasp installed, and files written by `fn` a
folder all nodes share.
"""

from __future__ import annotations

import argparse
import importlib
import itertools
import logging
import multiprocessing as mp
import os
import signal
import socket
import sys
import threading
import uuid
from collections.abc import Callable, Iterable, Iterator, Sized
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from posegrasp.core.errors import InvalidArgumentError, PosegraspError, UnknownNameError
from posegrasp.core.progress import progress_bar

#: The backends, the first the default.
BACKENDS = ("local", "ray")
#: An unreachable cluster is reported within this many seconds.
CONNECT_TIMEOUT_S = 20.0
#: How often a chunk is run again after its worker process or node died.
MAX_RETRIES = 3
#: Largest chunk `default_chunk` makes (a retried chunk repeats at most this many jobs).
MAX_CHUNK = 16
#: Jobs handed to the local pool at a time, per worker.
LOCAL_WINDOW = 32
#: Object store of a Ray started here [bytes]: the jobs and results are small.
OBJECT_STORE_BYTES = 100 * 2**20


class BackendError(PosegraspError, RuntimeError):
    """The parallel backend cannot run: Ray missing, or its cluster unreachable."""


def check_backend(backend: str, address: str | None = None) -> None:
    """Raise UnknownNameError for an unknown backend, InvalidArgumentError for an address the
    backend does not take or that is not ``auto``, ``ray://host:port`` or ``host:port``."""
    if backend not in BACKENDS:
        raise UnknownNameError("backend", backend, BACKENDS)
    if address is None:
        return
    if backend != "ray":
        raise InvalidArgumentError(f"--address needs --backend ray, not {backend}")
    if address != "auto" and not address.startswith("ray://"):
        _host_port(address)


def add_backend_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--backend`` and ``--address`` to a command line."""
    parser.add_argument(
        "--backend",
        default=BACKENDS[0],
        help=f"where the work runs, one of: {', '.join(BACKENDS)} (default {BACKENDS[0]})",
    )
    parser.add_argument(
        "--address",
        default=None,
        help="ray only: an existing cluster, host:port or auto (default: start Ray here with "
        "--workers CPUs)",
    )


def default_chunk(n_jobs: int, slots: int) -> int:
    """Jobs per Ray task: about four tasks per CPU slot, at most `MAX_CHUNK` jobs."""
    return max(1, min(MAX_CHUNK, n_jobs // (4 * max(1, slots))))


def run_map(
    fn: Callable[[Any], Any],
    jobs: Iterable[Any],
    *,
    backend: str = "local",
    workers: int = 1,
    address: str | None = None,
    chunk: int | None = None,
    desc: str | None = None,
    unit: str = "it",
    initializer: Callable[..., None] | None = None,
    initargs: tuple = (),
    ordered: bool = True,
    with_node: bool = False,
    total: int | None = None,
) -> Iterator[Any]:
    """Yield ``fn(job)`` for every job.

    Args:
        fn: a module-level function of one job.
        jobs: the jobs; an iterator is consumed lazily on the local backend (the pool takes
            jobs as workers free up), so a long run never holds them all.
        backend: one of `BACKENDS`.
        workers: local processes, or the CPUs of a Ray started here (ignored with `address`).
        address: an existing Ray cluster (``host:port``, ``ray://host:port`` or ``auto``).
        chunk: jobs per pool hand-out or Ray task (default: 1 locally, `default_chunk` on Ray).
        desc: label of the progress bar; None shows none.
        unit: what the bar counts.
        initializer: run with `initargs` once in each worker process before its first job
            (pool processes and Ray workers; not when one local worker runs the jobs here).
        ordered: yield in job order (else as the results come back).
        with_node: yield ``(result, node)`` pairs, node the Ray node id that ran the job (None
            on the local backend).
        total: the number of jobs, for the bar (default: ``len(jobs)`` when it has one).

    Raises:
        UnknownNameError, InvalidArgumentError: a bad backend or address.
        BackendError: Ray is not installed or its cluster cannot be reached.
    """
    check_backend(backend, address)
    if backend == "ray":  # cut into chunks up front
        jobs = list(jobs)
    if total is None:
        total = len(jobs) if isinstance(jobs, Sized) else None
    ray, owned = None, False
    if backend == "ray":  # connect before the bar shows, so a failure is one line
        ray = _import_ray()
        owned = not ray.is_initialized()  # a caller's own Ray session is used and left running
        if owned:
            _connect_keeping_sigterm(ray, address, workers)
    bar = progress_bar(total=total, desc=desc, unit=unit, disable=desc is None)
    try:
        if ray is not None:
            results = _ray_map(ray, fn, jobs, workers, chunk, initializer, initargs, ordered, bar)
        else:
            local = _local_map(fn, jobs, workers, chunk, initializer, initargs, ordered)
            results = ((r, None) for r in local)
        for result, node in results:
            if ray is None:
                bar.update(1)
            yield (result, node) if with_node else result
    finally:
        bar.close()
        if owned and ray is not None:
            ray.shutdown()


def _pool_init(initializer: Callable[..., None] | None, initargs: tuple) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if initializer is not None:
        initializer(*initargs)


class WorkerDied(BackendError):
    """A local pool's worker process ended before returning its job (killed by a signal, by the
    kernel for memory, or crashed): the job it held has no result, so the run stops rather than
    wait for it forever or record it as an outcome.

    Attributes:
        exitcode: the dead worker's exit status (negative: the signal that ended it), None when
            it is not known.
    """

    def __init__(self, exitcode: int | None) -> None:
        how = (
            "ended for an unknown reason"
            if exitcode is None
            else f"was killed by {signal.Signals(-exitcode).name}"
            if exitcode < 0 and -exitcode in signal.valid_signals()
            else f"exited with status {exitcode}"
        )
        super().__init__(f"a worker process {how} before finishing its job")
        self.exitcode = exitcode


def _local_map(fn, jobs, workers, chunk, initializer, initargs, ordered) -> Iterator[Any]:
    if workers <= 1:
        yield from map(fn, jobs)
        return
    # The workers leave Ctrl-C to this process, which stops the run in one line (its pool is
    # terminated on the way out) instead of a traceback from every worker: they start with
    # SIGINT ignored (inherited), and keep it so.
    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if in_main else None
    try:
        pool = ProcessPoolExecutor(
            workers, mp.get_context("spawn"), _pool_init, (initializer, initargs)
        )
        # Every worker starts now, with SIGINT still ignored (else each would start at its
        # first job, after this process listens to Ctrl-C again).
        launch = getattr(pool, "_launch_processes", None)
        if launch is not None:
            launch()
    finally:
        if in_main:
            signal.signal(signal.SIGINT, previous)
    procs = list((getattr(pool, "_processes", None) or {}).values())
    try:
        yield from _pool_results(pool, fn, jobs, workers * LOCAL_WINDOW, chunk or 1, ordered)
    except BrokenProcessPool:
        raise WorkerDied(_dead_exitcode(procs)) from None
    finally:
        _stop_pool(pool, procs)


def _run_items(fn: Callable[[Any], Any], items: list) -> list:
    return [fn(item) for item in items]


def _pool_results(pool, fn, jobs, window: int, chunk: int, ordered: bool) -> Iterator[Any]:
    """`fn` over `jobs` in `pool`, `chunk` jobs a task, at most `window` jobs in flight: the
    input is read as the workers free up, so a long stream of jobs is never held in memory."""
    it = iter(jobs)
    pending: dict[Future, int] = {}
    done: dict[int, list] = {}
    submitted = emitted = 0
    while True:
        while len(pending) * chunk < window and (items := list(itertools.islice(it, chunk))):
            pending[pool.submit(_run_items, fn, items)] = submitted
            submitted += 1
        if not pending:
            return
        finished, _ = wait(pending, return_when=FIRST_COMPLETED)
        for future in finished:
            done[pending.pop(future)] = future.result()
        keys = (
            list(itertools.takewhile(done.__contains__, itertools.count(emitted)))
            if ordered
            else sorted(done)
        )
        for key in keys:
            emitted += 1
            yield from done.pop(key)


def _dead_exitcode(procs: list) -> int | None:
    """The exit status of the worker that broke the pool, of its worker processes `procs`: the
    pool terminates the others (SIGTERM) once one died, so a status of another kind, where there
    is one, is the first death's."""
    for p in procs:
        p.join(timeout=2.0)  # each is dead or being terminated; this reaps it
    codes = [p.exitcode for p in procs if p.exitcode not in (None, 0)]
    other = [c for c in codes if c != -signal.SIGTERM]
    return (other or codes or [None])[0]


def _stop_pool(pool: ProcessPoolExecutor, procs: list) -> None:
    """Shut the pool down; on the way out of an interrupted run its workers (`procs`) are
    terminated rather than left to finish the jobs they hold, and then the pool's own thread is
    joined, so that nothing of it is left for the interpreter's exit to trip over."""
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        if p.is_alive():
            p.terminate()
    for p in procs:
        p.join(timeout=10)
    pool.shutdown(wait=True)


# --- Ray -------------------------------------------------------------------------------------

# Tokens of the `run_map` calls whose initializer already ran in this (Ray worker) process.
_INITIALISED: set[str] = set()


def _run_chunk(payload: tuple, items: list) -> tuple[list, str]:
    """One Ray task: the initializer once per process and call, then `fn` over the chunk."""
    import ray

    token, fn, initializer, initargs = payload
    if initializer is not None and token not in _INITIALISED:
        initializer(*initargs)
        _INITIALISED.add(token)
    return [fn(item) for item in items], ray.get_runtime_context().get_node_id()


def _import_ray():
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # no network calls home
    try:
        import ray
    except ImportError:
        raise BackendError(
            "the ray backend needs Ray: pip install 'posegrasp[ray]' (or: pip install ray)"
        ) from None
    return ray


def _host_port(address: str) -> tuple[str, int]:
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise InvalidArgumentError(
            f"invalid --address {address!r}; valid: host:port (as `ray start --head` prints), "
            "ray://host:port or auto"
        )
    return host, int(port)


def _connect_keeping_sigterm(ray, address: str | None, workers: int) -> None:
    """`connect`, the caller's SIGTERM handler kept and a SIGTERM during the start-up held back
    until Ray has started.

    Ray's start-up installs handlers that exit at once on SIGTERM (Python's `sys.exit` through
    ``ray._private.utils.set_sigterm_handler``, and its core worker's own); a run's handler
    instead stops it keeping what finished (`posegrasp.core.journal.interruptible`), and a Ray
    stopped half-started can abort the process on its way out. So while Ray starts, a SIGTERM is
    only noted; once it has started, the run's handler is put back and a noted SIGTERM is handed
    to it, after Ray is shut down again."""
    in_main = threading.current_thread() is threading.main_thread()
    on_term = signal.getsignal(signal.SIGTERM) if in_main else None
    if not callable(on_term):
        connect(ray, address, workers)
        return
    noted: list[int] = []
    utils = sys.modules.get("ray._private.utils")
    ray_sets = getattr(utils, "set_sigterm_handler", None)
    signal.signal(signal.SIGTERM, lambda signum, frame: noted.append(signum))
    if ray_sets is not None:
        utils.set_sigterm_handler = lambda _handler: None  # type: ignore[union-attr]
    try:
        connect(ray, address, workers)
    finally:
        if ray_sets is not None:
            utils.set_sigterm_handler = ray_sets  # type: ignore[union-attr]
        signal.signal(signal.SIGTERM, on_term)
    if noted:
        ray.shutdown()
        on_term(signal.SIGTERM, None)  # the run's own stop


def connect(ray, address: str | None, workers: int) -> None:
    """Connect to the cluster at `address`, or start a Ray with `workers` CPUs here.

    Raises:
        BackendError: nothing answers at `address` within `CONNECT_TIMEOUT_S`.
    """
    quiet = {"logging_level": logging.ERROR}
    if address is None:
        ray.init(
            num_cpus=workers,
            include_dashboard=False,
            object_store_memory=OBJECT_STORE_BYTES,
            **quiet,
        )
        return
    hint = "start one with `ray start --head` and pass the address it prints"
    if address != "auto" and not address.startswith("ray://"):
        try:  # a refused or silent port fails here, before Ray retries for minutes
            socket.create_connection(_host_port(address), timeout=CONNECT_TIMEOUT_S / 4).close()
        except OSError as exc:
            reason = exc.strerror or type(exc).__name__
            raise BackendError(
                f"cannot reach a Ray cluster at {address} ({reason}); {hint}"
            ) from None
    outcome: list[BaseException | None] = []

    def init() -> None:
        try:
            ray.init(address=address, **quiet)
            outcome.append(None)
        except Exception as exc:
            outcome.append(exc)

    thread = threading.Thread(target=init, daemon=True)
    thread.start()
    thread.join(CONNECT_TIMEOUT_S)
    if not outcome:
        raise BackendError(
            f"no Ray cluster answered at {address} within {CONNECT_TIMEOUT_S:.0f} s; if its "
            "`ray start` enabled token authentication, set RAY_AUTH_MODE=token here (the token "
            "is ~/.ray/auth_token or $RAY_AUTH_TOKEN; `ray get-auth-token`); else " + hint
        )
    if outcome[0] is not None:
        first = (str(outcome[0]).strip().splitlines() or [type(outcome[0]).__name__])[0]
        raise BackendError(f"cannot connect to a Ray cluster at {address}: {first}; {hint}")


def by_import_name(fn: Callable | None) -> Callable | None:
    """`fn` from its module's import name when it was defined in a module run as a script
    (``python -m sim.evaluate`` runs as ``__main__``, which a Ray worker cannot import)."""
    main = sys.modules["__main__"]
    spec = getattr(main, "__spec__", None)
    if fn is None or getattr(fn, "__module__", None) != "__main__" or spec is None:
        return fn
    return getattr(importlib.import_module(spec.name), fn.__qualname__)


def _get(ray, ref) -> Any:
    """A task's result; a task that raised re-raises its error, one Ray gave up on is a
    BackendError."""
    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError:
        raise
    except ray.exceptions.RayError as exc:
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise BackendError(f"Ray gave up on a task after {MAX_RETRIES} retries: {first}") from None


def _ray_map(ray, fn, jobs, workers, chunk, initializer, initargs, ordered, bar):
    """(result, node) pairs from Ray tasks over chunks; at most 4 tasks per CPU in flight."""
    slots = max(1, int(ray.cluster_resources().get("CPU", workers)))
    size = chunk or default_chunk(len(jobs), slots)
    chunks = [jobs[i : i + size] for i in range(0, len(jobs), size)]
    task = ray.remote(_run_chunk).options(
        num_cpus=1, max_retries=MAX_RETRIES, scheduling_strategy="SPREAD"
    )
    payload = ray.put((uuid.uuid4().hex, by_import_name(fn), by_import_name(initializer), initargs))
    pending: dict[Any, int] = {}
    done: dict[int, tuple[list, str]] = {}
    submit, emit = 0, 0
    while emit < len(chunks):
        while submit < len(chunks) and len(pending) < 4 * slots:
            pending[task.remote(payload, chunks[submit])] = submit
            submit += 1
        ready, _ = ray.wait(list(pending), num_returns=1)
        k = pending.pop(ready[0])
        done[k] = _get(ray, ready[0])
        bar.update(len(done[k][0]))
        # In job order: every finished chunk from the next one due; else this one.
        keys = (
            list(itertools.takewhile(done.__contains__, itertools.count(emit))) if ordered else [k]
        )
        for key in keys:
            results, node = done.pop(key)
            emit += 1
            yield from ((r, node) for r in results)
