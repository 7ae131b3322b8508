"""Run an evaluation's episodes on a backend and aggregate them: `evaluate_protocol`.

Each episode is one `EpisodeJob` (object, seed, estimator, `Protocol`), run by `run_job` in
whatever process takes it (this one, a pool worker, a Ray worker); with a journal, every finished
episode is kept as it returns and an interrupted run resumes (`posegrasp.core.journal`). The
report is `sim.evaluation.aggregate.make_report`'s.
"""

from __future__ import annotations

import functools
import sys
import time
from pathlib import Path
from typing import Any, NamedTuple

from grasping.candidates import generated_candidates
from posegrasp.core.contract import PoseEstimator
from posegrasp.core.errors import PosegraspError
from posegrasp.core.failures import check_failure_reason
from posegrasp.core.journal import Journal, run_journaled
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import effective_workers
from posegrasp.world.objects import OBJECT_NAMES
from sim.episodes.pose_noise import parse_noise
from sim.episodes.registry import PrivilegedEstimator, make_estimator
from sim.evaluation.aggregate import make_report
from sim.evaluation.protocol import Protocol, run_protocol

#: An estimator as an evaluation takes it: a spec (`sim.episodes.registry`: a built-in name, an
#: entry point or ``package.module:factory``) or an object implementing the contract.
EstimatorRef = str | PoseEstimator | PrivilegedEstimator


@functools.cache
def cached_estimator(spec: str, noise: str | None = None) -> Any:
    """One estimator per process, spec and noise (a learned one loads its weights once), on one
    compute thread (`_one_thread`).

    Raises:
        PosegraspError: a spec that cannot be made (`sim.episodes.registry.make_estimator`).
    """
    return _one_thread(make_estimator(spec, None if noise is None else parse_noise(noise)))


def _one_thread(estimator: Any) -> Any:
    """A learned estimator computes on one thread, with any number of workers and on any backend:
    the nets' sums run in an order that depends on the thread count, so this keeps every
    episode's pose, to the last bit, independent of how the evaluation was spread."""
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)
    return estimator


def _resolve(ref: EstimatorRef, noise: str | None) -> Any:
    return cached_estimator(ref, noise) if isinstance(ref, str) else _one_thread(ref)


def estimator_label(ref: EstimatorRef) -> str:
    """What a report calls the estimator: its spec, or an object's ``name``."""
    return ref if isinstance(ref, str) else str(ref.name)


def _init_worker() -> None:
    """One compute thread per worker process (torch, OpenMP, Mesa's software rasteriser): the
    workers already fill the cores."""
    setup_rendering(threads=1)


class EpisodeJob(NamedTuple):
    """One episode of an evaluation, as a worker receives it: the target `object`, the scene
    `seed`, the `estimator` and the `protocol` whose settings the episode plays with."""

    object: str
    seed: int
    estimator: EstimatorRef
    protocol: Protocol


def run_job(job: EpisodeJob) -> dict[str, Any]:
    """One episode of an evaluation, in whatever process runs it (this one, a pool worker, a Ray
    worker started afresh after another died): it sets up rendering there first.

    Returns:
        The episode's record (`sim.episodes.episode.EpisodeResult.to_json`) with its wall time
        ``wall_ms`` [ms]. An episode that raises (any exception) is recorded as failed with
        ``error``, the exception in its notes (a `PosegraspError` by its message, any other by
        its type and message), and the run goes on.
    """
    from sim.episodes.episode import play_episode

    setup_rendering()
    t = time.perf_counter()
    protocol = job.protocol
    try:
        r = play_episode(
            job.object,
            job.seed,
            _resolve(job.estimator, protocol.noise),
            protocol.episode_config(),
        )
        d = r.to_json()
    except Exception as exc:  # an episode never takes the evaluation down, whatever it raised
        note = str(exc) if isinstance(exc, PosegraspError) else f"{type(exc).__name__}: {exc}"
        d = {
            "object": job.object,
            "seed": job.seed,
            "estimator": estimator_label(job.estimator),
            "tier": protocol.tier,
            "success": False,
            "failure_reason": check_failure_reason("error"),
            "notes": [note],
            "pose_error": None,
            "timings_ms": {},
        }
    d["wall_ms"] = (time.perf_counter() - t) * 1000
    return d


def evaluate_protocol(
    protocol: Protocol,
    estimator: EstimatorRef,
    workers: int = 1,
    backend: str = "local",
    address: str | None = None,
    journal: Path | None = None,
    resume: bool = False,
) -> dict[str, Any]:
    """Run the protocol's episodes and aggregate them per object and overall.

    Args:
        protocol: the episodes and their settings.
        estimator: a spec (`sim.episodes.registry`) or an object implementing the contract
            (`posegrasp.core.contract.PoseEstimator`); with more than one worker an object is
            pickled to the workers with every episode, so a heavy one is better given by spec.
        workers: processes (or Ray CPUs) running episodes.
        backend, address: where the episodes run (`posegrasp.core.backends.run_map`); on Ray each
            episode records the ``node`` that ran it.
        journal: keep every finished episode in this JSON-lines file as it returns
            (`posegrasp.core.journal`); removed by the caller once the report is written.
        resume: run only the episodes the journal does not hold yet.

    Returns:
        The report (`sim.evaluation.aggregate.make_report`).

    Raises:
        Interrupted: Ctrl-C or SIGTERM; with a journal, its line says how to resume.
    """
    label = estimator_label(estimator)
    header = run_protocol(protocol, label)
    if protocol.candidates == "generated":  # made once, before the workers read them
        for o in protocol.objects:
            if o in OBJECT_NAMES:
                generated_candidates(o, progress=True)
    workers, note = effective_workers(workers, protocol.total)
    if note:
        print(note, file=sys.stderr)
    # Made as the workers take them, never all at once.
    jobs = (EpisodeJob(o, seed, estimator, protocol) for o, seed in protocol.seeds())
    t = time.perf_counter()
    ordered = run_journaled(
        run_job,
        jobs,
        protocol.total,
        Journal(journal, "evaluate", header) if journal else None,
        resume,
        backend=backend,
        workers=workers,
        address=address,
        desc="episodes",
        initializer=_init_worker,
    )
    return make_report(ordered, protocol, label, workers, time.perf_counter() - t)
