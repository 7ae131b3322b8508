"""Evaluate an estimator by grasp success over many seeded episodes.

    python -m sim.evaluate --objects all --episodes 50 --estimator hybrid [--workers N] \
        [--tier T] [--noise SIGMAS] [--margin] [--task lift|place] [--shift SPEC] \
        --json out.json --plot success_vs_error.png

Scene seeds start at `posegrasp.world.constants.EVAL_SEED_BASE`, far from the seeds the data
generator renders training images from, so a learned estimator is never scored on a scene it was
trained on.

The command line over `sim.evaluation` (the `Protocol`, the harness, the report, its text and
plot, the BOP route); code evaluates through that library, never through this module.
"""

from __future__ import annotations

import sys
from pathlib import Path

from grasping.candidates import CANDIDATE_SOURCES
from posegrasp.core.backends import add_backend_arguments, check_backend
from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    add_workers_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.journal import journal_path, resumable
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
)
from posegrasp.world import constants as C
from posegrasp.world.objects import OBJECT_NAMES, check_objects
from posegrasp.world.tiers import DEFAULT_TIER, TIERS, add_pool_argument, check_tier
from sim.episodes.pose_noise import parse_noise
from sim.episodes.registry import (
    DEFAULT_ESTIMATOR,
    add_estimator_arguments,
    add_obs_mode_argument,
    add_sensor_argument,
    add_shift_argument,
    add_task_argument,
    check_depth,
    depth_unused_note,
    make_estimator,
)
from sim.evaluation import (
    Protocol,
    cached_estimator,
    estimator_label,
    evaluate_protocol,
    export_protocol,
    format_poses_record,
    format_report,
    plot_success_vs_error,
    poses_estimator,
    poses_record,
    run_protocol,
)
from sim.evaluation.bop_results import BopPosesEstimator

DEFAULT_TOLERANCE = DOCS_DIR / "tolerance.json"
#: Most episodes per object one evaluation runs.
MAX_EPISODES = 100_000


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
    return poses_estimator(args.poses, args.export)


def _protocol(args, poses: BopPosesEstimator | None) -> Protocol:
    """The protocol the command line asks for: its episodes (or, with ``--poses``, the
    export's, `sim.evaluation.export_protocol`, seen through the sensor and under the scene
    shifts its images were rendered with) and their settings.

    Raises:
        InvalidArgumentError: with ``--poses``, a ``--sensor`` or ``--shift`` other than the
            export's.
    """
    settings = {
        "noise": args.noise,
        "margin": args.margin,
        "obs_mode": args.obs_mode,
        "pool": tuple(args.pool),
        "candidates": args.candidates,
        "sensor": args.sensor,
        "task": args.task,
        "shifts": args.shift,
    }
    if poses is not None:
        rendered = poses.export.sensor
        if args.sensor not in ("ideal", rendered):
            raise InvalidArgumentError(
                f"the export {poses.export.root} was rendered through sensor {rendered}, not "
                f"{args.sensor}; leave out --sensor (the export's is recorded)"
            )
        shifts = poses.export.shifts
        if args.shift and args.shift != shifts:
            under = ",".join(map(str, shifts)) or "no scene shift"
            raise InvalidArgumentError(
                f"the export {poses.export.root} was rendered under {under}, not "
                f"{','.join(map(str, args.shift))}; leave out --shift (the export's are recorded)"
            )
        return export_protocol(poses, **{**settings, "sensor": rendered, "shifts": shifts})
    return Protocol(
        objects=tuple(args.objects),
        episodes=args.episodes,
        seed_start=args.seed_start,
        tier=args.tier,
        **settings,
    )


def _add_episode_arguments(p: ArgumentParser) -> None:
    """Add which episodes run: ``--objects``, ``--pool``, ``--candidates`` and ``--episodes``."""
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


def _add_pose_source_arguments(p: ArgumentParser) -> None:
    """Add where the grasped poses come from: the estimator's options, or ``--poses`` with
    ``--from`` (a BOP results CSV and the export it answers)."""
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


def _add_output_arguments(p: ArgumentParser) -> None:
    """Add what the run writes and resumes from: ``--json``, ``--plot`` (with the
    ``--tolerance`` curves it overlays) and ``--resume``."""
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


def _parser() -> ArgumentParser:
    """The command-line parser: the episodes, where their poses come from, what is observed,
    the seeds, workers, tier and friction margin, the outputs and the backend (the order of
    ``--help``); every value is checked while parsing, the combinations by `_episodes_of`."""
    p = ArgumentParser(prog="python -m sim.evaluate", description=__doc__.split("\n")[0])
    _add_episode_arguments(p)
    _add_pose_source_arguments(p)
    add_obs_mode_argument(p)
    add_sensor_argument(p)
    add_task_argument(p)
    add_shift_argument(p)
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
    _add_output_arguments(p)
    add_backend_arguments(p)
    return p


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    args = _parser().parse_args(argv)
    setup_rendering()
    poses = _episodes_of(args)
    if poses is None:
        check_depth(args.estimator, args.obs_mode)
    protocol = _protocol(args, poses)
    if poses is None and (note := depth_unused_note(protocol.obs_mode, protocol.sensor)):
        print(note, file=sys.stderr)
    check_seed(protocol.seed_start, "--seed-start", protocol.episodes)
    check_backend(args.backend, args.address)
    if args.noise is not None:
        make_estimator(args.estimator, parse_noise(args.noise))  # validates the pair
    tolerance = args.tolerance  # the checked curves, or the default file's path
    if isinstance(tolerance, Path):
        tolerance = check_tolerance_file(tolerance) if args.plot and tolerance.is_file() else None
    estimator = poses or args.estimator
    if poses is None:
        cached_estimator(args.estimator, args.noise)  # fails fast (missing weights)
    journal = journal_path(
        args.json, "evaluate", run_protocol(protocol, estimator_label(estimator))
    )
    with resumable(journal, protocol.total):
        report = evaluate_protocol(
            protocol,
            estimator,
            workers=args.workers,
            backend=args.backend,
            address=args.address,
            journal=journal,
            resume=args.resume,
        )
        if poses is not None:
            report["poses"] = poses_record(poses, args.poses, report)
        log = summary_stream(args.json)
        print(format_report(report), file=log)
        if poses is not None:
            print(format_poses_record(report["poses"]), file=log)
        if args.plot is not None:
            plot_success_vs_error(report, args.plot, tolerance)
            print(f"wrote {args.plot}", file=log)
        if args.json is not None:
            write_json(args.json, report)
    Path(journal).unlink(missing_ok=True)  # the report now holds every episode
    return 0


if __name__ == "__main__":
    sys.exit(main())
