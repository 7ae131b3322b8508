"""Evaluate an estimator by grasp success over many seeded episodes.

    python -m sim.evaluate --objects all --episodes 50 --estimator hybrid [--workers N] \
        [--tier T] [--noise SIGMAS] [--margin] --json out.json --plot success_vs_error.png

Scene seeds start at `posegrasp.world.constants.EVAL_SEED_BASE`, far from the seeds the data
generator renders training images from, so a learned estimator is never scored on a scene it was
trained on.
"""

from __future__ import annotations

import functools
import itertools
import re
import sys
import time
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from grasping.candidates import CANDIDATE_SOURCES, generated_candidates
from perception import metrics
from posegrasp.core.backends import add_backend_arguments, check_backend
from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    add_workers_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.contract import PoseEstimator
from posegrasp.core.errors import InvalidArgumentError, PosegraspError
from posegrasp.core.failures import check_failure_reason
from posegrasp.core.files import sha256_file
from posegrasp.core.journal import Journal, journal_path, run_journaled
from posegrasp.core.paths import DOCS_DIR
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import (
    arg,
    check_choice,
    check_input_file,
    check_int,
    check_plot_path,
    check_seed,
    check_tolerance_file,
    effective_workers,
)
from posegrasp.world import constants as C
from posegrasp.world.objects import OBJECT_NAMES, check_objects
from posegrasp.world.tiers import DEFAULT_TIER, TIERS, add_pool_argument, check_tier
from sim.bop_results import BopPosesEstimator, time_summary, truth_match
from sim.episode import execution_settings
from sim.estimators import (
    DEFAULT_ESTIMATOR,
    PrivilegedEstimator,
    add_estimator_arguments,
    add_obs_mode_argument,
    make_estimator,
)
from sim.pose_noise import parse_noise
from sim.report_schema import REPORT_SCHEMA, validate_report
from sim.stats import BOOTSTRAP, bootstrap_means, margin_error_correlation, wilson_interval

#: An estimator as `evaluate` takes it: a spec (`sim.estimators`: a built-in name, an entry point
#: or ``package.module:factory``) or an object implementing the contract.
EstimatorRef = str | PoseEstimator | PrivilegedEstimator


@functools.cache
def _estimator(spec: str, noise: str | None = None):
    """One estimator per worker process and spec (the hybrid one loads its weights once)."""
    return _one_thread(make_estimator(spec, None if noise is None else parse_noise(noise)))


def _one_thread(estimator):
    """A learned estimator computes on one thread, with any number of workers and on any backend:
    the nets' sums run in an order that depends on the thread count, so this keeps every
    episode's pose, to the last bit, independent of how the evaluation was spread."""
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)
    return estimator


def _resolve(ref: EstimatorRef, noise: str | None):
    return _estimator(ref, noise) if isinstance(ref, str) else _one_thread(ref)


def estimator_label(ref: EstimatorRef) -> str:
    """What a report calls the estimator: its spec, or an object's ``name``."""
    return ref if isinstance(ref, str) else str(ref.name)


def _init_worker() -> None:
    """One compute thread per worker process (torch, OpenMP, Mesa's software rasteriser): the
    workers already fill the cores."""
    setup_rendering(threads=1)


class EpisodeJob(NamedTuple):
    """One episode of an evaluation, as a worker receives it."""

    object: str
    seed: int
    estimator: EstimatorRef
    tier: str
    noise: str | None = None
    margin: bool = False
    obs_mode: str = "rgb"
    pool: tuple[str, ...] = ()
    candidates: str = "designed"


def _run_one(job: EpisodeJob) -> dict:
    """One episode of an evaluation, in whatever process runs it (this one, a pool worker, a Ray
    worker started afresh after another died): it sets up rendering there first. An episode that
    raises (any exception) is recorded as failed with ``error``, the exception in its notes (a
    `PosegraspError` by its message, any other by its type and message), and the run goes on."""
    obj, seed, estimator, tier, noise, margin, obs_mode, pool, candidates = job
    from grasping.execute import ExecutionConfig
    from grasping.planner import PlannerConfig
    from posegrasp.world.scene import SceneConfig
    from sim.episode import EpisodeConfig, play_episode

    setup_rendering()
    t = time.perf_counter()
    try:
        cfg = EpisodeConfig(
            scene=SceneConfig(distractor_pool=pool),
            planner=PlannerConfig(candidates=candidates),
            tier=tier,
            execution=ExecutionConfig(measure_margin=margin),
            obs_mode=obs_mode,
        )
        r = play_episode(obj, seed, _resolve(estimator, noise), cfg)
        d = r.to_json()
    except Exception as exc:  # an episode never takes the evaluation down, whatever it raised
        note = str(exc) if isinstance(exc, PosegraspError) else f"{type(exc).__name__}: {exc}"
        d = {
            "object": obj,
            "seed": seed,
            "estimator": estimator_label(estimator),
            "tier": tier,
            "success": False,
            "failure_reason": check_failure_reason("error"),
            "notes": [note],
            "pose_error": None,
            "timings_ms": {},
        }
    d["wall_ms"] = (time.perf_counter() - t) * 1000
    return d


def _group(episodes: list[dict]) -> dict:
    n = len(episodes)
    k = sum(bool(e["success"]) for e in episodes)
    lo, hi = wilson_interval(k, n)
    reasons = Counter(e["failure_reason"] for e in episodes if not e["success"])
    out = {
        "episodes": n,
        "successes": k,
        "success_rate": k / n if n else 0.0,
        "wilson_low": lo,
        "wilson_high": hi,
        "failure_reasons": dict(sorted(reasons.items())),
    }
    errs = [e["pose_error"] for e in episodes if e.get("pose_error")]
    if errs:
        for key in ("translation_m", "rotation_deg"):
            v = np.array([x[key] for x in errs])
            out[f"{key}_median"] = float(np.median(v))
            out[f"{key}_p90"] = float(np.percentile(v, 90))
    margins = np.array([e["friction_margin"] for e in episodes if e.get("friction_margin")])
    if margins.size:
        boot = bootstrap_means(margins, BOOTSTRAP, np.random.default_rng(0))
        out["friction_margin_mean"] = float(margins.mean())
        out["friction_margin_low"], out["friction_margin_high"] = (
            float(v) for v in np.percentile(boot, [2.5, 97.5])
        )
        out["margin_error_spearman"] = margin_error_correlation(episodes)
    judged = [e for e in episodes if e.get("pose_correct") is not None]
    out["pose_judged"] = len(judged)
    out["pose_correct"] = sum(bool(e["pose_correct"]) for e in judged)
    # The grasp and the pose disagree: held on a wrong pose, or dropped on a right one.
    out["grasped_wrong_pose"] = sum(bool(e["success"]) and not e["pose_correct"] for e in judged)
    out["missed_right_pose"] = sum(not e["success"] and bool(e["pose_correct"]) for e in judged)
    out.update(bop_scores(episodes))
    walls = [e["wall_ms"] for e in episodes]
    plans = [e["timings_ms"]["ik"] for e in episodes if "ik" in e.get("timings_ms", {})]
    out["episode_wall_ms_median"] = float(np.median(walls)) if walls else None
    out["planning_ms_median"] = float(np.median(plans)) if plans else None
    return out


def evaluate(
    objects: list[str],
    episodes: int,
    estimator: EstimatorRef,
    seed_start: int,
    workers: int = 1,
    tier: str = DEFAULT_TIER,
    noise: str | None = None,
    margin: bool = False,
    backend: str = "local",
    address: str | None = None,
    journal: Path | None = None,
    resume: bool = False,
    obs_mode: str = "rgb",
    pool: Sequence[str] = (),
    candidates: str = "designed",
) -> dict:
    """Run episodes (objects x seeds) of one tier and aggregate per object and overall.

    Args:
        objects: the target classes; episode i of object X plays scene seed ``seed_start + i``.
        episodes: episodes per object.
        estimator: a spec (`sim.estimators`) or an object implementing the contract
            (`posegrasp.core.contract.PoseEstimator`); with more than one worker an object is
            pickled to the workers with every episode, so a heavy one is better given by spec.
        seed_start: the first scene seed.
        workers: processes (or Ray CPUs) running episodes.
        tier: the scene tier (`posegrasp.world.tiers.TIERS`).
        noise: the errors of ``noisy-oracle`` (`sim.pose_noise.NOISE_FORMAT`).
        margin: measure each successful grasp's friction margin.
        backend, address: where the episodes run (`posegrasp.core.backends.run_map`); on Ray each
            episode records the ``node`` that ran it.
        journal: keep every finished episode in this JSON-lines file as it returns
            (`posegrasp.core.journal`); removed by the caller once the report is written.
        resume: run only the episodes the journal does not hold yet.
        obs_mode: what the estimator sees (`sim.episode.OBS_MODES`): ``rgbd`` adds depth.
        pool: the classes the tier's distractors are drawn from, built-in or user objects
            (`posegrasp.world.scene.SceneConfig.distractor_pool`); empty for the built-in ones.
        candidates: where the built-in objects' grasp candidates come from
            (`grasping.candidates.CANDIDATE_SOURCES`); generated ones are made here first.

    Raises:
        Interrupted: Ctrl-C or SIGTERM; with a journal, its line says how to resume.
    """
    check_tier(tier)
    label = estimator_label(estimator)
    n_jobs = len(objects) * episodes
    pool = tuple(pool)
    check_choice(candidates, CANDIDATE_SOURCES, "candidate source")
    protocol = run_protocol(
        objects, episodes, label, seed_start, tier, noise, margin, obs_mode, pool, candidates
    )
    if candidates == "generated":  # made once, before the workers read them
        for o in objects:
            if o in OBJECT_NAMES:
                generated_candidates(o, progress=True)
    workers, note = effective_workers(workers, n_jobs)
    if note:
        print(note, file=sys.stderr)
    # Made as the workers take them, never all at once.
    jobs = (
        EpisodeJob(o, seed_start + i, estimator, tier, noise, margin, obs_mode, pool, candidates)
        for o in objects
        for i in range(episodes)
    )
    t = time.perf_counter()
    ordered = run_journaled(
        _run_one,
        jobs,
        n_jobs,
        Journal(journal, "evaluate", protocol) if journal else None,
        resume,
        backend=backend,
        workers=workers,
        address=address,
        desc="episodes",
        initializer=_init_worker,
    )
    return make_report(
        ordered,
        objects,
        label,
        tier,
        seed_start,
        episodes,
        noise=noise,
        workers=workers,
        wall_s=time.perf_counter() - t,
        obs_mode=obs_mode,
        pool=pool,
        candidates=candidates,
    )


def make_report(
    episodes: list[dict],
    objects: list[str],
    estimator: str,
    tier: str,
    seed_start: int,
    episodes_per_object: int,
    noise: str | None = None,
    workers: int = 1,
    wall_s: float = 0.0,
    obs_mode: str = "rgb",
    pool: Sequence[str] = (),
    candidates: str = "designed",
) -> dict:
    """The report (schema `REPORT_SCHEMA`, checked) of finished episodes: the protocol, the
    aggregates per object and overall, and the episodes in run order; ``distractor_pool`` only
    when the distractors came from a pool of the caller's, ``candidates`` only when the built-in
    objects' candidates were generated."""
    extra = _optional(pool, candidates)
    return validate_report(
        {
            "schema": REPORT_SCHEMA,
            "estimator": estimator,
            "tier": tier,
            "noise": noise,
            "obs_mode": obs_mode,
            "execution": execution_settings(),
            "seed_start": seed_start,
            "episodes_per_object": episodes_per_object,
            "workers": workers,
            "wall_s": wall_s,
            "per_object": {o: _group([e for e in episodes if e["object"] == o]) for o in objects},
            "overall": _group(episodes),
            "episodes": episodes,
            **extra,
        },
        "the evaluation's report",
    )


def _optional(pool: Sequence[str], candidates: str) -> dict:
    """The protocol's entries that are left out at their defaults (older reports lack them)."""
    out: dict = {"distractor_pool": list(pool)} if pool else {}
    if candidates != "designed":
        out["candidates"] = candidates
    return out


def run_protocol(
    objects: list[str],
    episodes: int,
    estimator: str,
    seed_start: int,
    tier: str,
    noise: str | None,
    margin: bool,
    obs_mode: str = "rgb",
    pool: Sequence[str] = (),
    candidates: str = "designed",
) -> dict:
    """What defines an evaluation's results: a resumed run must have the same."""
    extra = _optional(pool, candidates)
    return {
        "objects": list(objects),
        "episodes_per_object": episodes,
        "estimator": estimator,
        "seed_start": seed_start,
        "tier": tier,
        "noise": noise,
        "margin": margin,
        "obs_mode": obs_mode,
        "execution": execution_settings(),
        **extra,
    }


def _ar(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


#: Most notes the summary shows per failure reason, and most characters of each.
NOTES_SHOWN, NOTE_CHARS = 3, 110


def failure_notes(episodes: list[dict], top: int = NOTES_SHOWN) -> dict[str, list[tuple[str, int]]]:
    """Why the episodes failed: per failure reason, its most frequent notes and how many failed
    episodes carry each (notes alike but for their numbers count as one, shown by the first).

    Args:
        episodes: the report's episodes.
        top: most notes per reason.

    Returns:
        reason -> [(note, episodes), ...], most frequent first; reasons without notes are left
        out.
    """
    counts: dict[str, Counter] = {}
    example: dict[tuple[str, str], str] = {}
    for e in episodes:
        if e["success"]:
            continue
        reason = str(e["failure_reason"])
        seen = set()
        for note in e.get("notes") or []:
            key = re.sub(r"-?\d+(?:\.\d+)?(?:e[-+]?\d+)?", "#", str(note))
            if key in seen:
                continue
            seen.add(key)
            counts.setdefault(reason, Counter())[key] += 1
            example.setdefault((reason, key), str(note))
    return {
        reason: [(example[(reason, key)], n) for key, n in c.most_common(top)]
        for reason, c in sorted(counts.items())
    }


def _one_line(note: str) -> str:
    line = " ".join(note.split())
    return line if len(line) <= NOTE_CHARS else line[: NOTE_CHARS - 3] + "..."


def format_report(report: dict) -> str:
    """The report as a table: per object and overall, success, pose errors, BOP's AR_MSSD,
    AR_MSPD and AR_VSD, times and failures; then the most frequent notes of each failure
    reason (`failure_notes`)."""
    rows = [
        f"estimator {report['estimator']}, tier {report.get('tier', DEFAULT_TIER)}: "
        f"{report['episodes_per_object']} episodes per object, "
        f"seeds from {report['seed_start']}, {report['workers']} worker(s), "
        f"{report['wall_s']:.1f} s wall",
        f"{'object':<8} {'success':>8} {'rate':>6} {'wilson 95%':>15} {'t med mm':>9} "
        f"{'r med deg':>9} {'AR_MSSD':>7} {'AR_MSPD':>7} {'AR_VSD':>7} {'plan ms':>8} "
        f"{'ep ms':>7}  failures",
    ]
    items = [*report["per_object"].items(), ("overall", report["overall"])]
    for name, g in items:
        tm = g.get("translation_m_median")
        rm = g.get("rotation_deg_median")
        rows.append(
            f"{name:<8} {g['successes']:>4}/{g['episodes']:<3} {g['success_rate']:>6.1%} "
            f"[{g['wilson_low']:.3f}, {g['wilson_high']:.3f}] "
            f"{'-' if tm is None else f'{tm * 1000:.1f}':>9} "
            f"{'-' if rm is None else f'{rm:.2f}':>9} "
            f"{_ar(g['ar_mssd']):>7} {_ar(g['ar_mspd']):>7} {_ar(g.get('ar_vsd')):>7} "
            f"{g['planning_ms_median'] or 0:>8.1f} {g['episode_wall_ms_median'] or 0:>7.0f}  "
            + ", ".join(f"{k}: {v}" for k, v in g["failure_reasons"].items())
        )
    o = report["overall"]
    rows.append(
        f"pose right (BOP MSSD < 0.1 diameter) in {o['pose_correct']} of {o['pose_judged']} "
        f"estimates; grasped with a wrong pose: {o['grasped_wrong_pose']}; missed with a right "
        f"pose: {o['missed_right_pose']}"
    )
    notes = failure_notes(report["episodes"])
    if notes:
        rows.append("why episodes failed (most frequent notes, episodes with each):")
        for reason, top in notes.items():
            rows.extend(f"  {reason}: {n}x {_one_line(note)}" for note, n in top)
    margins = [(n, g) for n, g in items if "friction_margin_mean" in g]
    if margins:
        rows.append("friction margin (lowest sliding friction that still holds; lower is firmer):")
        rows.extend(
            f"  {n:<8} {g['friction_margin_mean']:.3f} "
            f"[{g['friction_margin_low']:.3f}, {g['friction_margin_high']:.3f}] (bootstrap 95 %)"
            for n, g in margins
        )
        rho = report["overall"].get("margin_error_spearman") or {}
        if any(rho.get(k) is not None for k in ("translation_m", "rotation_deg", "add_m")):
            rows.append(
                f"margin vs pose error, Spearman over {rho['episodes']} grasped episodes: "
                + ", ".join(
                    f"{k} {rho[k]:+.2f}"
                    for k in ("translation_m", "rotation_deg", "add_m")
                    if rho.get(k) is not None
                )
            )
    return "\n".join(rows)


#: The error components of `perception.metrics.error_components`, as the tolerance study names them
#: (``sim.tolerance``: key, unit scale from the episode's SI value, bin edges).
COMPONENTS: dict[str, tuple[str, float, tuple[float, ...]]] = {
    "ray_mm": ("ray_m", 1000.0, (0, 5, 10, 15, 20, 30, 45, 70)),
    "lateral_mm": ("lateral_m", 1000.0, (0, 5, 10, 15, 20, 30, 45, 70)),
    "inplane_deg": ("inplane_deg", 1.0, (0, 2.5, 5, 7.5, 10, 15, 20, 30, 45)),
    "outplane_deg": ("outplane_deg", 1.0, (0, 2.5, 5, 7.5, 10, 15, 20, 30, 45)),
}
DEFAULT_TOLERANCE = DOCS_DIR / "tolerance.json"
#: Most episodes per object one evaluation runs.
MAX_EPISODES = 100_000


def plot_success_vs_error(report: dict, path: Path, tolerance: dict | None = None) -> None:
    """PNG of grasp success against each component of the estimated pose's error.

    One panel per component (ray, lateral, in-plane, out-of-plane): the episodes binned by that
    component's error, success rate per bin with its Wilson 95 % interval and count, each
    episode as a tick (top: success, bottom: failure), and, when given, the tolerance curves of
    `sim.tolerance` of the report's objects (success with the true pose plus that error alone,
    one line per object, one colour per object in every panel). The episodes carry all
    components at once, so a bin's rate is a marginal, not a single-factor curve. One legend
    below the panels names every line and mark.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    eps = [e for e in report["episodes"] if e.get("pose_error")]
    scored = sorted({str(e["object"]) for e in report["episodes"]})
    curves = {o: (tolerance or {})[o] for o in scored if o in (tolerance or {})}
    colour = {o: f"C{i}" for i, o in enumerate(curves)}
    fig, axes = plt.subplots(1, 4, figsize=(17, 4.2), sharey=True)
    for ax, (kind, (key, scale, edges)) in zip(axes, COMPONENTS.items(), strict=True):
        for obj, kinds in curves.items():
            if kind in kinds:
                c = kinds[kind]
                ax.plot(
                    c["levels"],
                    c["success_rate"],
                    lw=1.5,
                    alpha=0.8,
                    color=colour[obj],
                    label=f"{obj}: true pose + this error alone",
                )
        x = np.array([e["pose_error"][key] * scale for e in eps if key in e["pose_error"]])
        ok = np.array([bool(e["success"]) for e in eps if key in e["pose_error"]])
        if len(x):
            top = max(edges[-1], float(x.max()) * 1.05)
            bins = [*edges, top]
            ax.plot(
                x,
                np.where(ok, 1.04, -0.04),
                "|",
                color="k",
                alpha=0.3,
                ms=8,
                label="one episode (top: grasped, bottom: failed)",
            )
            for lo, hi in itertools.pairwise(bins):
                sel = (x >= lo) & (x < hi) if hi < top else (x >= lo)
                n = int(sel.sum())
                if n == 0:
                    continue
                k = int(ok[sel].sum())
                wlo, whi = wilson_interval(k, n)
                mid = (lo + min(hi, edges[-1] * 1.3)) / 2
                err = [[max(0.0, k / n - wlo)], [max(0.0, whi - k / n)]]
                ax.errorbar(
                    mid,
                    k / n,
                    yerr=err,
                    fmt="o",
                    color="k",
                    ms=4 + 6 * min(1.0, n / 50),
                    capsize=3,
                    label="episodes in a bin: success rate, Wilson 95 %, count beside",
                )
                ax.annotate(
                    str(n), (mid, k / n), textcoords="offset points", xytext=(4, -12), fontsize=7
                )
        name, unit = kind.rsplit("_", 1)
        ax.set_xlabel(f"{name} error [{unit}]")
        ax.set_ylim(-0.1, 1.1)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("grasp success rate")
    named: dict[str, object] = {}  # one entry per label, over all panels
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            named.setdefault(label, handle)
    fig.suptitle(
        f"{report['estimator']}: grasp success against each component of the pose error "
        f"({', '.join(scored)})"
    )
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    if named:
        fig.legend(
            list(named.values()),
            list(named),
            loc="lower center",
            ncol=min(4, len(named)),
            fontsize=8,
            frameon=False,
        )
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _episodes_of(args) -> BopPosesEstimator | None:
    """Fill in the episodes the command line leaves open: the defaults, or, with ``--poses``,
    those of the export ``--from`` names (then the estimator is the CSV's poses).

    Raises:
        InvalidArgumentError: ``--poses`` without ``--from`` or with an option that would choose
            other episodes or another estimator, or ``--from`` alone.
    """
    chosen = {
        "--objects": args.objects,
        "--episodes": args.episodes,
        "--seed-start": args.seed_start,
        "--tier": args.tier,
        "--estimator": args.estimator,
        "--noise": args.noise,
        "--pool": args.pool or None,
    }
    if args.poses is None:
        if args.export is not None:
            raise InvalidArgumentError("--from names the export of --poses; give both")
        args.objects = args.objects or list(OBJECT_NAMES)
        args.episodes = args.episodes or 50
        args.seed_start = C.EVAL_SEED_BASE if args.seed_start is None else args.seed_start
        args.tier = args.tier or DEFAULT_TIER
        args.estimator = args.estimator or DEFAULT_ESTIMATOR
        return None
    if args.export is None:
        raise InvalidArgumentError("--poses needs --from DIR, the export the CSV answers")
    if given := [k for k, v in chosen.items() if v is not None]:
        raise InvalidArgumentError(
            f"--poses grasps on the export's episodes with the CSV's poses; leave out "
            f"{', '.join(given)}"
        )
    estimator = BopPosesEstimator(args.poses, args.export)
    export = estimator.export
    digest = sha256_file(args.poses)[:12]
    estimator.name = f"bop:{Path(args.poses).name}@{digest}"
    args.objects, args.episodes = list(export.objects), export.episodes
    args.seed_start, args.tier = export.seed_start, export.tier
    return estimator


#: The head camera's width the episodes render at [px] (BOP scales MSPD's thresholds by it).
IMAGE_WIDTH = 640


def bop_scores(episodes: list[dict]) -> dict[str, float | None]:
    """BOP 2019's average recalls of the episodes' estimates: AR_MSSD (thresholds 0.05..0.5 of
    the diameter), AR_MSPD (5..50 px at 640 px width) and AR_VSD (the episodes' ``vsd``, taus
    and thresholds 0.05..0.5); an episode without an estimate, whose MSPD is infinite or
    without ``vsd`` counts as a miss. None for no episodes (AR_VSD also when no episode has a
    ``vsd``, as in reports written before episodes recorded it)."""
    if not episodes:
        return {"ar_mssd": None, "ar_mspd": None, "ar_vsd": None}

    def err(e: dict, key: str) -> float | None:
        return (e.get("pose_error") or {}).get(key)

    vsd = [e.get("vsd") for e in episodes]
    return {
        "ar_mssd": metrics.ar_mssd([err(e, "mssd_rel_diameter") for e in episodes], 1.0),
        "ar_mspd": metrics.ar_mspd([err(e, "mspd_px") for e in episodes], IMAGE_WIDTH),
        "ar_vsd": metrics.ar_vsd(vsd) if any(v is not None for v in vsd) else None,
    }


def poses_record(estimator: BopPosesEstimator, csv_path: Path, report: dict) -> dict:
    """Where the poses of a ``--poses`` run came from (the CSV and its hash, the export), how many
    of the export's targets the CSV had a row for, the method's time per image from the CSV's
    ``time`` column (`sim.bop_results.time_summary`), and whether the poses belong to these
    episodes at all (``truth_match``, `sim.bop_results.truth_match`)."""
    eps = report["episodes"]
    times = [(e.get("estimate_info") or {}).get("time") for e in eps]
    return {
        "csv": str(csv_path),
        "csv_sha256": sha256_file(csv_path),
        "export": str(estimator.export.root),
        "targets": len(eps),
        "targets_with_a_row": sum(e.get("T_C_O_est") is not None for e in eps),
        **time_summary([t for t in times if isinstance(t, (int, float))]),
        "truth_match": truth_match(eps),
    }


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(prog="python -m sim.evaluate", description=__doc__.split("\n")[0])
    p.add_argument(
        "--objects",
        default=None,
        type=arg(check_objects, "--objects"),
        help=f"'all' (default: {', '.join(OBJECT_NAMES)}) or a comma list of objects, built-in "
        "or user objects (python -m sim.add_object)",
    )
    add_pool_argument(p)
    p.add_argument(
        "--candidates",
        default="designed",
        type=arg(check_choice, CANDIDATE_SOURCES, "candidate source"),
        help="the built-in objects' grasp candidates: designed (default) or generated (by the "
        "generator of user objects' candidates, made once and kept in the data folder)",
    )
    p.add_argument(
        "--episodes",
        type=arg(check_int, 1, MAX_EPISODES, "--episodes", base=int),
        default=None,
        help=f"episodes per object, 1..{MAX_EPISODES} (default 50)",
    )
    add_estimator_arguments(p, default=None)
    p.add_argument(
        "--poses",
        type=arg(check_input_file, "--poses"),
        default=None,
        metavar="CSV",
        help="grasp on the poses of this BOP results CSV instead of running an estimator; the "
        "episodes are those of the export --from names",
    )
    p.add_argument(
        "--from",
        dest="export",
        type=Path,
        default=None,
        metavar="DIR",
        help="with --poses: the BOP export of python -m sim.export_bop that the CSV answers",
    )
    add_obs_mode_argument(p)
    p.add_argument(
        "--seed-start",
        type=arg(check_seed, "--seed-start", base=int),
        default=None,
        help=f"first scene seed (default {C.EVAL_SEED_BASE}: held-out scenes, never rendered as "
        "training data)",
    )
    add_workers_argument(p, what="at most one per episode and core")
    p.add_argument(
        "--tier",
        default=None,
        type=arg(check_tier),
        help=f"scene tier, one of: {', '.join(TIERS)} (default {DEFAULT_TIER})",
    )
    p.add_argument(
        "--margin", action="store_true", help="measure each grasp's friction margin (slower)"
    )
    add_json_argument(p, "the full report")
    p.add_argument(
        "--plot",
        type=arg(check_plot_path),
        default=None,
        metavar="PATH",
        help="plot of success against pose error (.png, .pdf or .svg)",
    )
    p.add_argument(
        "--tolerance",
        type=arg(check_tolerance_file),
        default=DEFAULT_TOLERANCE,
        metavar="PATH",
        help="tolerance curves to overlay (JSON of python -m sim.tolerance)",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="finish an interrupted run of the same arguments from its journal (beside the --json "
        "file, else under the data folder's runs/)",
    )
    add_backend_arguments(p)
    args = p.parse_args(argv)
    setup_rendering()
    poses = _episodes_of(args)
    check_seed(args.seed_start, "--seed-start", args.episodes)
    check_backend(args.backend, args.address)
    if args.noise is not None:
        make_estimator(args.estimator, parse_noise(args.noise))  # validates the pair
    tolerance = args.tolerance  # the checked curves, or the default file's path
    if isinstance(tolerance, Path):
        tolerance = check_tolerance_file(tolerance) if args.plot and tolerance.is_file() else None
    estimator = poses or args.estimator
    if poses is None:
        _estimator(args.estimator, args.noise)  # fails fast (missing weights)
    protocol = run_protocol(
        args.objects,
        args.episodes,
        estimator_label(estimator),
        args.seed_start,
        args.tier,
        args.noise,
        args.margin,
        args.obs_mode,
        args.pool,
        args.candidates,
    )
    journal = journal_path(args.json, "evaluate", protocol)
    report = evaluate(
        args.objects,
        args.episodes,
        estimator,
        args.seed_start,
        args.workers,
        args.tier,
        args.noise,
        args.margin,
        args.backend,
        args.address,
        journal=journal,
        resume=args.resume,
        obs_mode=args.obs_mode,
        pool=args.pool,
        candidates=args.candidates,
    )
    if poses is not None:
        report["poses"] = poses_record(poses, args.poses, report)
    log = summary_stream(args.json)
    print(format_report(report), file=log)
    if poses is not None:
        rec = report["poses"]
        timed = (
            f"time per image median {rec['time_s_median']:.3g} s, 90th percentile "
            f"{rec['time_s_p90']:.3g} s ({rec['images_timed']} images timed)"
            if rec["images_timed"]
            else "no time given"
        )
        print(
            f"BOP route: {rec['targets_with_a_row']} of {rec['targets']} targets had a row in "
            f"{rec['csv']}; {timed}",
            file=log,
        )
        match = rec["truth_match"]
        if match["unrelated"]:
            print(
                f"warning: only {match['nearest_own']} of {match['estimates']} estimates lie "
                f"nearest their own episode's target ({match['chance']:.1f} expected of poses "
                f"made for other scenes, chance {match['p_value']:.2g}): does {rec['csv']} "
                f"answer another export than {rec['export']}, or are its poses far off?",
                file=log,
            )
    if args.plot is not None:
        plot_success_vs_error(report, args.plot, tolerance)
        print(f"wrote {args.plot}", file=log)
    if args.json is not None:
        write_json(args.json, report)
    Path(journal).unlink(missing_ok=True)  # the report now holds every episode
    return 0


if __name__ == "__main__":
    sys.exit(main())
