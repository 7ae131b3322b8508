"""Hybrid episode wall time and the speed-up of `sim.evaluate` with 2 worker processes over 1.

    python bench/evaluate_speed.py [--estimator hybrid] [--episodes 10] [--json]

Runs the same held-out episodes (`--episodes` per object) with 1 and with 2 workers through
`sim.evaluate.evaluate`, prints the median episode wall time (one process, estimator loaded) and
the wall time of both runs. Targets: a hybrid episode <= 3 s wall median on 2 cores; 2 workers
at least 1.6x faster than 1; at least 10 episodes/s with 2 workers. Both runs must agree episode
by episode (they are seeded); the script says so.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

import sim  # noqa: F401  (sets MUJOCO_GL before MuJoCo loads)
from sim.estimators import DEFAULT_ESTIMATOR
from sim.evaluate import evaluate
from sim.world.objects import OBJECT_NAMES

SEED_START = 1_200_000_000  # held out (sim.world.constants.EVAL_SEED_BASE and above)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--estimator", default=DEFAULT_ESTIMATOR)
    p.add_argument("--episodes", type=int, default=10, help="episodes per object")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    objs = list(OBJECT_NAMES)
    one = evaluate(objs, args.episodes, args.estimator, SEED_START, workers=1)
    two = evaluate(objs, args.episodes, args.estimator, SEED_START, workers=2)
    walls = [e["wall_ms"] for e in one["episodes"]]
    same = [e["success"] for e in one["episodes"]] == [e["success"] for e in two["episodes"]]
    out = {
        "estimator": args.estimator,
        "episodes": len(walls),
        "episode_wall_ms_median": float(np.median(walls)),
        "episode_wall_ms_p90": float(np.percentile(walls, 90)),
        "wall_s_1_worker": one["wall_s"],
        "wall_s_2_workers": two["wall_s"],
        "speedup_2_workers": one["wall_s"] / two["wall_s"],
        "episodes_per_s_2_workers": len(walls) / two["wall_s"],
        "same_outcomes": same,
        "successes": one["overall"]["successes"],
    }
    if args.json:
        print(json.dumps(out, sort_keys=True))
        return
    ok = lambda good: "PASS" if good else "MISS"  # noqa: E731
    print(f"{args.estimator}: {out['episodes']} episodes, {out['successes']} successes")
    print(
        f"episode wall (1 process), median {out['episode_wall_ms_median']:.0f} ms, "
        f"p90 {out['episode_wall_ms_p90']:.0f} ms  "
        f"[target <= 3000 ms: {ok(out['episode_wall_ms_median'] <= 3000)}]"
    )
    print(
        f"sim.evaluate wall: 1 worker {out['wall_s_1_worker']:.1f} s, 2 workers "
        f"{out['wall_s_2_workers']:.1f} s, speed-up {out['speedup_2_workers']:.2f}x  "
        f"[target >= 1.6x: {ok(out['speedup_2_workers'] >= 1.6)}]"
    )
    print(
        f"throughput with 2 workers: {out['episodes_per_s_2_workers']:.2f} episodes/s  "
        f"[target >= 10: {ok(out['episodes_per_s_2_workers'] >= 10)}]"
    )
    print(f"same outcomes with 1 and 2 workers: {same}")


if __name__ == "__main__":
    main()
