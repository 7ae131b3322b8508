"""Grasp planning and whole-episode wall time, in one process (2 cores).

    python bench/episode_speed.py [--episodes 5] [--tier hard] [--estimator hybrid] [--json PATH]

Targets: planning (all IK for one grasp) <= 100 ms median; a whole oracle episode <= 3 s wall
median; a `hard` episode <= 1.5 s wall median. Scenes are held out (seeds from 1.4e9); the
estimator is loaded before the clock starts. `--json PATH` writes the figures and
``targets_met``. Exit status 0 when every target is met, 1 when one is missed.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    command,
    summary_stream,
    target,
    write_json,
)
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_choice, check_int
from posegrasp.world.objects import OBJECT_NAMES
from posegrasp.world.tiers import TIERS, check_tier
from sim.episodes.episode import EpisodeConfig, play_episode
from sim.episodes.registry import ESTIMATORS, make_estimator

SEED_START = 1_400_000_000


def _parser() -> ArgumentParser:
    p = ArgumentParser(prog="python bench/episode_speed.py", description=__doc__.split("\n")[0])
    p.add_argument(
        "--episodes",
        type=arg(check_int, 1, 1000, "--episodes", base=int),
        default=5,
        help="episodes per object, 1..1000 (default 5)",
    )
    p.add_argument(
        "--tier",
        type=arg(check_tier),
        default="isolated",
        help=f"scene tier, one of: {', '.join(TIERS)} (default isolated)",
    )
    names = [e for e in ESTIMATORS if e != "noisy-oracle"]
    p.add_argument(
        "--estimator",
        type=arg(check_choice, names, "estimator"),
        default="oracle",
        metavar="NAME",
        help=f"one of: {', '.join(names)} (default oracle)",
    )
    add_json_argument(p, "the figures")
    return p


def measure(estimator_name: str, tier: str, episodes: int) -> dict:
    """`episodes` episodes per object of the tier, the estimator loaded before the clock
    starts: successes, episode wall times and each stage's median [ms]."""
    walls, stages = [], {}
    successes = 0
    estimator = make_estimator(estimator_name)
    cfg = EpisodeConfig(tier=tier)
    for obj in OBJECT_NAMES:
        for seed in range(SEED_START, SEED_START + episodes):
            t = time.perf_counter()
            r = play_episode(obj, seed, estimator, cfg)
            walls.append((time.perf_counter() - t) * 1000)
            successes += r.success
            for k, v in r.timings_ms.items():
                stages.setdefault(k, []).append(v)
    med = {k: float(np.median(v)) for k, v in stages.items()}
    return {
        "episodes": len(walls),
        "successes": successes,
        "planning_ms_median": med.get("ik"),
        "episode_wall_ms_median": float(np.median(walls)),
        "episode_wall_ms_p90": float(np.percentile(walls, 90)),
        "stage_ms_median": med,
    }


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns 0 when every target is met, 1 when one is missed."""
    args = _parser().parse_args(argv)
    setup_rendering()
    out = measure(args.estimator, args.tier, args.episodes)
    successes, med = out["successes"], out["stage_ms_median"]
    log = summary_stream(args.json)
    wall = out["episode_wall_ms_median"]
    met = {"planning": out["planning_ms_median"] <= 100, "episode": wall <= 3000}
    if args.tier == "hard":
        met["hard_episode"] = wall <= 1500
    print(
        f"{args.estimator} episodes, tier {args.tier}: {out['episodes']} ({successes} successes)",
        file=log,
    )
    print(
        f"planning (IK for one grasp), median: {out['planning_ms_median']:.1f} ms  "
        + target("<= 100 ms", met["planning"]),
        file=log,
    )
    print(
        f"episode wall, median: {wall:.0f} ms, p90 {out['episode_wall_ms_p90']:.0f} ms  "
        + target("<= 3000 ms", met["episode"])
        + (
            f" {target('of hard <= 1500 ms', met['hard_episode'])}" if "hard_episode" in met else ""
        ),
        file=log,
    )
    print("stages, median ms: " + "  ".join(f"{k} {v:.0f}" for k, v in med.items()), file=log)
    if args.json is not None:
        write_json(args.json, out | {"targets_met": met})
    return 0 if all(met.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
