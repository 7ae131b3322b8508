"""How often can the robot place an object it holds when it knows the object's pose?

    python studies/place_ceiling.py [--tiers all] [--episodes 20] [--json PATH]

For each tier, `oracle` plays the place task (`sim.episodes.episode.EpisodeConfig.task`) on the
same held-out scenes (`--episodes` per object, seeds from
`posegrasp.world.constants.EVAL_SEED_BASE`) twice: once as scored, the robot believing the
object lies in its hand as the true pose at grasp time seen from the gripper as it closed
(`grasping.place.PlaceConfig.belief` ``estimate``), and once knowing the true pose in its hand
after the lift (``truth``: what a perfect look at the object in the hand would give). The first
is the oracle's place success; the gap to the second is what the grasp itself shifts in the hand
while the fingers close and the arm lifts; what the second misses is the set-down and release.
Per tier it prints both successes (Wilson 95 % intervals) and the failures of each.
"""

from __future__ import annotations

import sys
from collections import Counter
from dataclasses import replace

from grasping.place import PlaceConfig
from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.progress import progress_bar
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_int, check_names
from posegrasp.world.constants import EVAL_SEED_BASE
from posegrasp.world.objects import OBJECT_NAMES
from posegrasp.world.tiers import TIERS
from sim.episodes.episode import Episode, EpisodeConfig
from sim.episodes.registry import make_estimator
from sim.evaluation.stats import wilson_interval

#: The robot's beliefs compared (`grasping.place.BELIEFS`).
BELIEFS = ("estimate", "truth")


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
    add_json_argument(p, "the successes and failures per tier and belief")
    return p


def _play(tier: str, belief: str, episodes: int) -> dict:
    """One tier's place episodes of the oracle with one belief: successes and failures."""
    oracle = make_estimator("oracle")
    config = replace(EpisodeConfig(task="place", tier=tier), place=PlaceConfig(belief=belief))
    reasons: Counter[str] = Counter()
    placed = 0
    seeds = [(o, EVAL_SEED_BASE + i) for o in OBJECT_NAMES for i in range(episodes)]
    for obj, seed in progress_bar(seeds, desc=f"{tier} {belief}", leave=False):
        ep = Episode(obj, seed, config)
        try:
            res = ep.run(oracle)[1]
        finally:
            ep.close()
        placed += res.success
        if not res.success:
            reasons[str(res.failure_reason)] += 1
    lo, hi = wilson_interval(placed, len(seeds))
    return {
        "episodes": len(seeds),
        "placed": placed,
        "wilson": [lo, hi],
        "failures": dict(sorted(reasons.items())),
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
            r = rows[tier][belief] = _play(tier, belief, args.episodes)
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
