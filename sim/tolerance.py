"""How much pose error a grasp tolerates: success rate against injected error.

For each error kind (translation along the camera ray, lateral translation, in-plane rotation
about the camera ray, out-of-plane rotation) and each magnitude, episodes grasp on the true pose
perturbed by exactly that magnitude (random sign or direction, seeded). The tolerance of a kind
is the largest magnitude up to which the success rate stays at or above 90 %; where it never
falls below, the study bounds it from below by its largest level (``tolerance`` null and
``at_least`` that level in the JSON, ``>= level`` in the table). Scenes are held out from the
networks' training data (seeds from `posegrasp.world.constants.EVAL_SEED_BASE` by default).
With ``--task place`` success is the place task's (`sim.episodes.episode.EpisodeConfig.task`:
lifted, carried to a goal and resting within 2 cm and 10 deg of it), so the curves say how much
pose error a place tolerates; the JSON has the same form, its task in the journal and the plot.

    python -m sim.tolerance --object phone   (or --objects all) [--episodes 10] [--workers N]
        [--tier T] [--task lift|place] [--json out/tolerance.json] [--plot out/tolerance.png]

writes the curves and tolerances as JSON (`--json`, read by ``sim.evaluate --tolerance``) and
their plot (`--plot`).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from posegrasp.core.backends import add_backend_arguments, check_backend
from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    add_workers_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.journal import Journal, journal_path, run_journaled
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import (
    arg,
    check_choice,
    check_int,
    check_plot_path,
    check_seed,
    effective_workers,
)
from posegrasp.world import constants as C
from posegrasp.world.objects import check_objects, object_names
from posegrasp.world.tiers import DEFAULT_TIER, TIERS, check_tier
from sim.episodes.registry import add_task_argument

#: Error kinds and the magnitudes tried, in report units (mm or deg).
LEVELS: dict[str, tuple[float, ...]] = {
    "ray_mm": (0, 10, 20, 30, 40, 60),
    "lateral_mm": (0, 10, 20, 30, 40, 60),
    "inplane_deg": (0, 5, 10, 20, 30, 45),
    "outplane_deg": (0, 5, 10, 15, 20, 30),
}
THRESHOLD = 0.9
#: Where the curves and their plot go unless told otherwise (checked like a given path).
DEFAULT_JSON = "out/tolerance.json"
DEFAULT_PLOT = "out/tolerance.png"
#: The first scene seed unless told otherwise: held-out scenes, never a training image.
DEFAULT_SEED_START = C.EVAL_SEED_BASE


def _noise(kind: str, value: float):
    from sim.episodes.pose_noise import PoseNoise

    si = value / 1000 if kind.endswith("_mm") else float(np.deg2rad(value))
    size = dict.fromkeys(("ray", "lateral", "inplane", "outplane"), 0.0)
    size[kind.split("_")[0]] = si
    return PoseNoise(size["ray"], size["lateral"], size["inplane"], size["outplane"], mode="fixed")


def _job(
    args: tuple[str, str, float, int, str, str],
) -> tuple[str, str, float, int, bool, str | None]:
    obj, kind, value, seed, tier, task = args
    from sim.episodes.episode import Episode, EpisodeConfig
    from sim.episodes.pose_noise import perturb_pose

    ep = Episode(obj, seed, EpisodeConfig(tier=tier, task=task))
    try:
        rng = np.random.default_rng([seed, 104729, int(value * 1000)])
        T_est = perturb_pose(ep.T_C_O_true, _noise(kind, value), rng)
        r = ep.act(T_est, "noisy-oracle", neighbours=ep.true_neighbours())
    finally:
        ep.close()
    return obj, kind, value, seed, r.success, r.failure_reason


def tolerance_of(
    levels: list[float], rates: list[float], threshold: float = THRESHOLD
) -> float | None:
    """Largest level up to which every rate is >= threshold, linearly interpolated to the first
    crossing; None when no rate drops below it (the tolerance is then at least the last level,
    not measured)."""
    for i, r in enumerate(rates):
        if r < threshold:
            if i == 0:
                return 0.0
            r0, l0, l1 = rates[i - 1], levels[i - 1], levels[i]
            return float(l0 + (r0 - threshold) / (r0 - r) * (l1 - l0))
    return None


def curve_record(levels: list[float], rates: list[float]) -> dict:
    """One kind's curve as the JSON records it: ``levels``, ``success_rate``, the measured
    ``tolerance`` (`tolerance_of`) or, when success never fell below `THRESHOLD`, ``tolerance``
    None and ``at_least`` the largest level tested."""
    tol = tolerance_of(levels, rates)
    out: dict = {"levels": list(levels), "success_rate": list(rates), "tolerance": tol}
    if tol is None:
        out["at_least"] = float(levels[-1])
    return out


def format_tolerances(result: dict, task: str = "lift") -> str:
    """The tolerances as a table, one row per object; a bound is printed ``>= level`` and
    explained below the table; `task` names what succeeded (``lift``: the grasp)."""
    rows = [f"{'object':<8}" + "".join(f"{k:>14}" for k in LEVELS)]
    bounded = False
    for o, kinds in result.items():
        cells = []
        for k in LEVELS:
            c = kinds[k]
            if c["tolerance"] is None:
                bounded = True
                cells.append(f"{'>= ' + format(c['at_least'], '.1f'):>14}")
            else:
                cells.append(f"{c['tolerance']:>14.1f}")
        rows.append(f"{o:<8}" + "".join(cells))
    what = "success" if task == "lift" else f"{task} success"
    rows.append(f"tolerance = error where {what} drops below {THRESHOLD:.0%}")
    if bounded:
        rows.append(
            f">= L: success never fell below {THRESHOLD:.0%} up to the largest level tested, L; "
            "the tolerance is at least L, not measured"
        )
    return "\n".join(rows)


def study(
    objects: list[str],
    episodes: int,
    seed_start: int,
    workers: int,
    tier: str = DEFAULT_TIER,
    backend: str = "local",
    address: str | None = None,
    journal: Path | None = None,
    resume: bool = False,
    task: str = "lift",
) -> dict:
    """Run the study on one tier and return {object: {kind: {levels, rates, tolerance}}};
    `backend` and `address` say where the episodes run (`posegrasp.core.backends.run_map`);
    `journal` keeps every finished episode, and `resume` runs only those it lacks
    (`posegrasp.core.journal`); `task` is what succeeds (`posegrasp.world.goals.TASKS`)."""
    check_tier(tier)
    n_jobs = len(objects) * sum(map(len, LEVELS.values())) * episodes
    workers, note = effective_workers(workers, n_jobs)
    if note:
        print(note, file=sys.stderr)
    jobs = (  # made as the workers take them
        (o, k, float(v), seed_start + i, tier, task)
        for o in objects
        for k, vals in LEVELS.items()
        for v in vals
        for i in range(episodes)
    )
    protocol = study_protocol(objects, episodes, seed_start, tier, task)
    results = run_journaled(
        _job,
        jobs,
        n_jobs,
        Journal(journal, "tolerance", protocol) if journal else None,
        resume,
        backend=backend,
        workers=workers,
        address=address,
        desc="episodes",
    )
    out: dict = {}
    for o in objects:
        out[o] = {}
        for k, vals in LEVELS.items():
            rates = []
            for v in vals:
                hits = [r[4] for r in results if r[0] == o and r[1] == k and r[2] == v]
                rates.append(float(np.mean(hits)))
            out[o][k] = curve_record(list(vals), rates)
    return out


def study_protocol(
    objects: list[str], episodes: int, seed_start: int, tier: str, task: str = "lift"
) -> dict:
    """What defines a study's results: a resumed one must have the same (the task only when it
    is not ``lift``, so journals of lift studies read as before)."""
    return {
        "objects": list(objects),
        "episodes": episodes,
        "seed_start": seed_start,
        "tier": tier,
        "levels": LEVELS,
        **({} if task == "lift" else {"task": task}),
    }


def plot(result: dict, path: Path, task: str = "lift") -> None:
    """Success rate against each error kind, one line per object (`task`'s success)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(16, 3.8), sharey=True)
    for ax, kind in zip(axes, LEVELS, strict=True):
        for obj, kinds in result.items():
            ax.plot(kinds[kind]["levels"], kinds[kind]["success_rate"], marker="o", label=obj)
        ax.axhline(THRESHOLD, color="grey", ls="--", lw=1)
        name, unit = kind.rsplit("_", 1)
        ax.set_xlabel(f"{name} error [{unit}]")
        ax.grid(alpha=0.3)
    what = "grasp" if task == "lift" else task
    axes[0].set_ylabel(f"{what} success rate")
    axes[-1].legend(fontsize=8)
    fig.suptitle(f"{what.capitalize()} success against injected pose error")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def parser() -> ArgumentParser:
    """The command line of `main`."""
    p = ArgumentParser(prog="python -m sim.tolerance", description=__doc__.split("\n")[0])
    which = p.add_mutually_exclusive_group()
    which.add_argument(
        "--object",
        type=arg(check_choice, object_names(), "object"),
        help=f"one of: {', '.join(object_names())} (default: phone)",
    )
    which.add_argument(
        "--objects",
        type=arg(check_objects, "--objects"),
        help="'all' (the built-in objects) or a comma list of objects, built-in or user objects",
    )
    p.add_argument(
        "--episodes",
        type=arg(check_int, 1, 10_000, "--episodes", base=int),
        default=10,
        help="episodes per level, 1..10000",
    )
    p.add_argument(
        "--seed-start",
        type=arg(check_seed, "--seed-start", base=int),
        default=DEFAULT_SEED_START,
        help=f"first scene seed (default {DEFAULT_SEED_START}: held-out scenes, never rendered as "
        f"training data, which come from seeds below {C.DATA_SEED_LIMIT})",
    )
    add_workers_argument(p)
    p.add_argument(
        "--tier",
        default=DEFAULT_TIER,
        type=arg(check_tier),
        help=f"scene tier, one of: {', '.join(TIERS)}",
    )
    add_task_argument(p)
    add_json_argument(p, "the curves and tolerances", DEFAULT_JSON)
    p.add_argument(
        "--plot",
        type=arg(check_plot_path),
        default=DEFAULT_PLOT,
        metavar="PATH",
        help=f"plot of the curves (.png, .pdf or .svg; default {DEFAULT_PLOT})",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="finish an interrupted study of the same arguments from its journal (beside --json)",
    )
    add_backend_arguments(p)
    return p


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    args = parser().parse_args(argv)
    setup_rendering()
    objects = args.objects or [args.object or "phone"]
    check_seed(args.seed_start, "--seed-start", args.episodes)
    check_backend(args.backend, args.address)
    protocol = study_protocol(objects, args.episodes, args.seed_start, args.tier, args.task)
    journal = journal_path(args.json, "tolerance", protocol)
    result = study(
        objects,
        args.episodes,
        args.seed_start,
        args.workers,
        args.tier,
        args.backend,
        args.address,
        journal=journal,
        resume=args.resume,
        task=args.task,
    )
    log = summary_stream(args.json)
    plot(result, args.plot, args.task)
    print(format_tolerances(result, args.task), file=log)
    print(f"wrote {args.plot}", file=log)
    write_json(args.json, result)
    journal.unlink(missing_ok=True)  # the curves now hold every episode
    return 0


if __name__ == "__main__":
    sys.exit(main())
