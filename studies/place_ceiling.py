"""How often can the robot place an object it holds when it knows the object's pose?

    python studies/place_ceiling.py [--tiers all] [--episodes 20] [--workers N] [--json PATH]

For each tier, `oracle` plays the place task (`sim.episodes.episode.EpisodeConfig.task`) on the
same held-out scenes (`--episodes` per object, seeds from
`posegrasp.world.constants.EVAL_SEED_BASE`) with each belief of where the object lies in its
hand (`grasping.place.BELIEFS`): ``predicted``, as scored, the true pose at grasp time seen from
the gripper as it closed, moved as a physics check of the grasp moves the object in the hand;
``estimate``, the same not moved; and ``truth``, the true pose in the hand after the lift (what
a perfect look at the object in the hand would give). The gap from ``estimate`` to ``truth`` is
what the grasp itself shifts in the hand while the fingers close and the arm lifts, the gap from
``predicted`` to ``truth`` what the check does not foresee of it; what ``truth`` misses is the
set-down and release. Per tier it prints each belief's successes (Wilson 95 % intervals) and
failures.
"""

from __future__ import annotations

import sys

from grasping.place import BELIEFS
from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    add_workers_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_int, check_names
from posegrasp.world.constants import EVAL_SEED_BASE
from posegrasp.world.objects import OBJECT_NAMES
from posegrasp.world.tiers import TIERS
from sim.evaluation import Protocol, evaluate_protocol


def _parser() -> ArgumentParser:
    """The command line."""
    p = ArgumentParser(prog="python studies/place_ceiling.py", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--tiers",
        default="all",
        type=arg(check_names, list(TIERS), "tier", "--tiers"),
        help=f"comma list of: {', '.join(TIERS)}, or all (default)",
    )
    p.add_argument(
        "--episodes",
        default=20,
        type=arg(check_int, 1, 1000, "--episodes", base=int),
        help="episodes per object and tier, 1..1000 (default 20)",
    )
    add_workers_argument(p)
    add_json_argument(p, "the successes and failures per tier and belief")
    return p


def _play(tier: str, belief: str, episodes: int, workers: int) -> dict:
    """One tier's place episodes of the oracle with one belief: successes and failures."""
    protocol = Protocol(OBJECT_NAMES, episodes, EVAL_SEED_BASE, tier, task="place", belief=belief)
    report = evaluate_protocol(protocol, "oracle", workers=workers)
    o = report["overall"]
    return {
        "episodes": o["episodes"],
        "placed": o["successes"],
        "wilson": [o["wilson_low"], o["wilson_high"]],
        "failures": o["failure_reasons"],
    }


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    args = _parser().parse_args(argv)
    setup_rendering(threads=1)
    log = summary_stream(args.json)
    rows = {}
    print(f"{'tier':<9} {'belief':<9} {'placed':>8} {'wilson 95%':>15}  failures", file=log)
    for tier in args.tiers:
        rows[tier] = {}
        for belief in BELIEFS:
            r = rows[tier][belief] = _play(tier, belief, args.episodes, args.workers)
            lo, hi = r["wilson"]
            print(
                f"{tier:<9} {belief:<9} {r['placed']:>4}/{r['episodes']:<3} [{lo:.3f}, {hi:.3f}]  "
                + ", ".join(f"{k}: {v}" for k, v in r["failures"].items()),
                file=log,
            )
    if args.json is not None:
        write_json(args.json, {"episodes_per_object": args.episodes, "tiers": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
