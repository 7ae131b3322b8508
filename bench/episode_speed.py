"""Grasp planning and whole-episode wall time, in one process (2 cores).

    python bench/episode_speed.py [--episodes 5] [--tier hard] [--estimator hybrid] [--json]

Targets: planning (all IK for one grasp) <= 100 ms median; a whole oracle episode <= 3 s wall
median; a `hard` episode <= 1.5 s wall median. Scenes are held out (seeds from 1.4e9); the
estimator is loaded before the clock starts.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from posegrasp.core.runtime import setup_rendering
from posegrasp.world.objects import OBJECT_NAMES
from posegrasp.world.tiers import TIERS
from sim.episode import EpisodeConfig, play_episode
from sim.estimators import ESTIMATORS, make_estimator

SEED_START = 1_400_000_000


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--episodes", type=int, default=5, help="episodes per object")
    p.add_argument("--tier", choices=list(TIERS), default="isolated")
    p.add_argument("--estimator", choices=[e for e in ESTIMATORS if e != "noisy-oracle"],
                   default="oracle")  # fmt: skip
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    setup_rendering()
    if not 1 <= args.episodes <= 1000:
        p.error("--episodes must be in 1..1000")
    walls, stages = [], {}
    successes = 0
    estimator = make_estimator(args.estimator)
    cfg = EpisodeConfig(tier=args.tier)
    for obj in OBJECT_NAMES:
        for seed in range(SEED_START, SEED_START + args.episodes):
            t = time.perf_counter()
            r = play_episode(obj, seed, estimator, cfg)
            walls.append((time.perf_counter() - t) * 1000)
            successes += r.success
            for k, v in r.timings_ms.items():
                stages.setdefault(k, []).append(v)
    med = {k: float(np.median(v)) for k, v in stages.items()}
    out = {
        "episodes": len(walls),
        "successes": successes,
        "planning_ms_median": med.get("ik"),
        "episode_wall_ms_median": float(np.median(walls)),
        "episode_wall_ms_p90": float(np.percentile(walls, 90)),
        "stage_ms_median": med,
    }
    if args.json:
        print(json.dumps(out, sort_keys=True))
        return
    ok = lambda good: "PASS" if good else "MISS"  # noqa: E731
    print(f"{args.estimator} episodes, tier {args.tier}: {out['episodes']} ({successes} successes)")
    print(
        f"planning (IK for one grasp), median: {out['planning_ms_median']:.1f} ms  "
        f"[target <= 100 ms: {ok(out['planning_ms_median'] <= 100)}]"
    )
    print(
        f"episode wall, median: {out['episode_wall_ms_median']:.0f} ms, "
        f"p90 {out['episode_wall_ms_p90']:.0f} ms  "
        f"[target <= 3000 ms: {ok(out['episode_wall_ms_median'] <= 3000)}"
        + (f"; hard <= 1500 ms: {ok(out['episode_wall_ms_median'] <= 1500)}]"
           if args.tier == "hard" else "]")
    )  # fmt: skip
    print("stages, median ms: " + "  ".join(f"{k} {v:.0f}" for k, v in med.items()))


if __name__ == "__main__":
    main()
