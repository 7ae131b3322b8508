"""Grasp success against pose noise on every tier: the paired noise curve, one line per tier.

    python studies/noise_curves.py [--tiers all] [--objects all] [--episodes 50] [--workers N] \
        [--out out/noise] [--plot docs/noise_curves_tiers.png] [--json PATH]

For each tier, `oracle` and then `noisy-oracle` at sigma = (2.5 mm, 1 deg), (5 mm, 2 deg),
(10 mm, 4 deg) and (20 mm, 8 deg) on all four error components run on the same held-out scenes
(`--episodes` per object, seeds from `posegrasp.world.constants.EVAL_SEED_BASE`, friction margins
measured), exactly as `python -m sim.evaluate --tier T --estimator noisy-oracle --noise
S,S,D,D --margin` does; a seed draws the same standard normals at every level, so each level
pairs with the one before (`sim.compare.curve`: lost and gained grasps, exact McNemar p). Each
run's report is kept in `--out` as ``<tier>_<level>.json`` and a rerun reuses it; the run being
made keeps its finished episodes in ``<tier>_<level>.journal.jsonl`` (`posegrasp.core.journal`),
so a rerun after Ctrl-C or SIGTERM resumes within the level too (a kept report of other
`--objects` is refused: give another `--out`). `--objects` takes built-in and user objects
(`python -m sim.add_object`). Prints each tier's chain;
`--plot` draws success (Wilson 95 % bars) against sigma for every tier in one figure.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from pathlib import Path

from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    add_out_argument,
    add_workers_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.files import atomic_write_json
from posegrasp.core.journal import Interrupted, command_line, journal_path
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_int, check_names, check_plot_path
from posegrasp.world.constants import EVAL_SEED_BASE
from posegrasp.world.objects import OBJECT_NAMES, check_objects
from posegrasp.world.tiers import TIERS
from sim.compare import check_same_execution, curve, format_curve
from sim.evaluation import Protocol, evaluate_protocol
from sim.evaluation.stats import wilson_interval

#: (label, noise) along the curve; None is the true pose.
LEVELS: tuple[tuple[str, str | None], ...] = (
    ("oracle", None),
    ("n2.5", "2.5,2.5,1,1"),
    ("n5", "5,5,2,2"),
    ("n10", "10,10,4,4"),
    ("n20", "20,20,8,8"),
)


def _tick(noise: str | None) -> str:
    """A level's axis label: "0", or the sigmas as "<mm> mm, <deg> deg"."""
    if noise is None:
        return "0"
    mm, _, deg, _ = noise.split(",")
    return f"{mm} mm, {deg} deg"


def run_tier(
    tier: str, episodes: int, out: Path, workers: int = 1, objects: Sequence[str] = OBJECT_NAMES
) -> list[dict]:
    """The tier's chain of reports on `objects` (run on `workers` processes, or read back when
    already in `out`)."""
    paths = []
    for label, noise in LEVELS:
        path = out / f"{tier}_{label}.json"
        if path.is_file():
            kept = list(json.loads(path.read_text())["per_object"])
            if kept != list(objects):
                raise InvalidArgumentError(
                    f"{path} holds a run on {', '.join(kept)}, not {', '.join(objects)}; give "
                    "another --out"
                )
        else:
            estimator = "oracle" if noise is None else "noisy-oracle"
            print(f"{tier}: {estimator} {noise or ''}", file=sys.stderr)
            journal = journal_path(path, "evaluate", {})
            try:
                report = evaluate_protocol(
                    Protocol(tuple(objects), episodes, EVAL_SEED_BASE, tier, noise, margin=True),
                    estimator,
                    workers=workers,
                    journal=journal,
                    resume=journal.is_file(),
                )
            except Interrupted as exc:
                raise Interrupted(
                    f"interrupted: {exc.done} of {exc.total} episodes of {tier} {label} kept in "
                    f"{exc.journal}; resume with: {command_line()}"
                ) from None
            atomic_write_json(path, report)
            journal.unlink()
            print(f"wrote {path}", file=sys.stderr)
        paths.append(path)
    check_same_execution(paths)
    return curve(paths)


def plot(chains: dict[str, list[dict]], path: Path) -> None:
    """Success against the noise level, one line per tier."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    for i, (tier, rows) in enumerate(chains.items()):
        x = np.arange(len(rows)) + (i - (len(chains) - 1) / 2) * 0.04
        rate = np.array([r["successes"] / r["episodes"] for r in rows])
        ci = np.array([wilson_interval(r["successes"], r["episodes"]) for r in rows])
        ax.errorbar(
            x,
            100 * rate,
            yerr=100 * np.abs(ci.T - rate),
            fmt="o-",
            capsize=3,
            label=tier,
            markersize=4,
        )
    ax.set_xticks(np.arange(len(LEVELS)), [_tick(noise) for _, noise in LEVELS], fontsize=8)
    ax.set_xlabel("sigma of each error component (along and across the ray, in and out of plane)")
    ax.set_ylabel("grasp success [%]")
    n = next(iter(chains.values()))[0]["episodes"] if chains else 0
    ax.set_title(f"noisy-oracle on {n} paired scenes per tier", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(prog="python studies/noise_curves.py", description=__doc__.split("\n\n")[0])
    tiers = arg(check_names, list(TIERS), "tier", "--tiers")
    p.add_argument(
        "--tiers",
        type=tiers,
        default=list(TIERS),
        help="'all' or a comma list of " + ", ".join(TIERS),
    )
    p.add_argument(
        "--objects",
        type=arg(check_objects, "--objects"),
        default=list(OBJECT_NAMES),
        help="'all' (default: the built-in objects) or a comma list of objects, built-in or user",
    )
    p.add_argument(
        "--episodes",
        type=arg(check_int, 3, 10_000, "--episodes", base=int),
        default=50,
        help="episodes per object and level, 3..10000",
    )
    add_workers_argument(p)
    add_out_argument(p, "the runs' reports, <tier>_<level>.json, reused by a rerun", "out/noise")
    p.add_argument(
        "--plot",
        type=arg(check_plot_path, "--plot"),
        default=None,
        metavar="PATH",
        help="success against sigma for every tier (.png, .pdf or .svg)",
    )
    add_json_argument(p, "every tier's chain")
    args = p.parse_args(argv)
    setup_rendering()
    log = summary_stream(args.json)
    args.out.mkdir(parents=True, exist_ok=True)
    chains = {}
    for tier in args.tiers:
        chains[tier] = run_tier(tier, args.episodes, args.out, args.workers, args.objects)
        print(f"tier {tier}:\n{format_curve(chains[tier])}\n", file=log)
    if args.plot is not None:
        plot(chains, args.plot)
        print(f"wrote {args.plot}", file=log)
    if args.json is not None:
        write_json(args.json, chains)
    return 0


if __name__ == "__main__":
    sys.exit(main())
