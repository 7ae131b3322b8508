"""Does the global estimator's worker process pay for itself? One process against two, same images.

    python studies/global_processes.py [--estimator hybrid-global] [--tier hard] [--images 24]
        [--repeat 3] [--threads 2] [--json PATH]

Renders the head-camera images of the first `--images` held-out episodes of the tier (objects in
turn), warms the estimator up on them twice (its codebooks, and the worker process
`GlobalConfig.processes` = 2 starts), then times each image's estimate with
`GlobalConfig.processes` 1 and 2 in turn, each the fastest of `--repeat` runs in a row: the
median and 90th percentile of each [ms], and the median of the paired gains (one process's time
less two processes') [ms and %]. The two settings run interleaved, image by image, so the
machine's drift falls on both alike; the estimates are the same to the bit either way
(`tests/test_golden_poses.py`).
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    add_threads_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.contract import Observation
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_choice, check_int
from posegrasp.world import constants as C
from posegrasp.world.objects import OBJECT_NAMES
from posegrasp.world.tiers import TIERS

#: The estimators with a worker process.
if TYPE_CHECKING:
    from perception.global_pose import GlobalPoseEstimator

ESTIMATORS = ("hybrid-global", "hybrid-global-table", "hybrid-global-paper")


def _parser() -> ArgumentParser:
    p = ArgumentParser(
        prog="python studies/global_processes.py", description=__doc__.split("\n\n")[0]
    )
    p.add_argument(
        "--estimator",
        default="hybrid-global",
        type=arg(check_choice, ESTIMATORS, "estimator"),
        help=f"one of: {', '.join(ESTIMATORS)} (default hybrid-global)",
    )
    p.add_argument(
        "--tier",
        default="hard",
        type=arg(check_choice, list(TIERS), "tier"),
        help=f"the episodes' tier, one of: {', '.join(TIERS)} (default hard)",
    )
    p.add_argument(
        "--images",
        default=24,
        type=arg(check_int, 2, 10000, "--images", base=int),
        help="the first N held-out episodes' head images, 2..10000 (default 24)",
    )
    p.add_argument(
        "--repeat",
        default=3,
        type=arg(check_int, 1, 20, "--repeat", base=int),
        help="timed runs per image and setting, the fastest kept, 1..20 (default 3)",
    )
    add_threads_argument(p)
    add_json_argument(p, "the figures")
    return p


def _observations(tier: str, images: int) -> list[Observation]:
    """The head-camera observations of the tier's first `images` held-out episodes, objects
    in turn."""
    from sim.episodes.episode import Episode, EpisodeConfig

    observations = []
    for i in range(images):
        obj = OBJECT_NAMES[i % len(OBJECT_NAMES)]
        ep = Episode(obj, C.EVAL_SEED_BASE + i // len(OBJECT_NAMES), EpisodeConfig(tier=tier))
        try:
            observations.append(ep.observe())
        finally:
            ep.close()
    return observations


def _timings(
    est: GlobalPoseEstimator, observations: list[Observation], repeat: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per observation, the fastest of `repeat` estimates [ms] with one process and with two,
    the settings interleaved image by image (each composition hands the worker on)."""
    config = est.config
    ms: dict[int, list[float]] = {1: [], 2: []}
    for obs in observations:
        for processes in (1, 2):
            est = est.with_config(replace(config, processes=processes))
            runs = []
            for _ in range(repeat):
                t0 = time.perf_counter()
                est.estimate(obs)
                runs.append((time.perf_counter() - t0) * 1000)
            ms[processes].append(min(runs))
    return np.array(ms[1]), np.array(ms[2])


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    args = _parser().parse_args(argv)
    setup_rendering(threads=args.threads)
    from perception.estimators import LEARNED_ESTIMATORS
    from perception.global_pose import GlobalPoseEstimator

    est = LEARNED_ESTIMATORS[args.estimator]()
    assert isinstance(est, GlobalPoseEstimator)  # ESTIMATORS are its variants
    observations = _observations(args.tier, args.images)
    for obs in observations * 2:  # the codebooks, and the worker starts in the second estimate
        est.estimate(obs)
    one, two = _timings(est, observations, args.repeat)
    res = {
        "estimator": args.estimator,
        "tier": args.tier,
        "images": len(observations),
        "threads": args.threads,
        "repeat": args.repeat,
        "one_process": {
            "median_ms": float(np.median(one)),
            "p90_ms": float(np.percentile(one, 90)),
        },
        "two_processes": {
            "median_ms": float(np.median(two)),
            "p90_ms": float(np.percentile(two, 90)),
        },
        "paired_gain_ms": float(np.median(one - two)),
        "paired_gain_pct": float(np.median((one - two) / one) * 100),
    }
    print(
        f"{args.estimator} on {args.tier}, {len(observations)} images, {args.threads} threads: "
        f"one process median {res['one_process']['median_ms']:.1f} ms "
        f"(90th percentile {res['one_process']['p90_ms']:.1f}), two "
        f"{res['two_processes']['median_ms']:.1f} ms ({res['two_processes']['p90_ms']:.1f}); "
        f"paired gain {res['paired_gain_ms']:.1f} ms ({res['paired_gain_pct']:.0f} %)",
        file=summary_stream(args.json),
    )
    if args.json is not None:
        write_json(args.json, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
