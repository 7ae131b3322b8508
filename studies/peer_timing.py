"""Time per image and pose errors of the classical peers on held-out isolated episodes.

Renders the head camera's colour and depth images of the first `--images` held-out episodes of
the isolated tier (seeds from `posegrasp.world.constants.EVAL_SEED_BASE`, objects in turn), warms
each estimator up on a training scene of every object it will see (its models are trained or
sampled, its weights loaded, then), and times ``estimate(obs)`` on each image on `--threads`
threads. Prints one line per estimator: the median and largest time per image, the median
rotation and translation errors and how many poses are correct (MSSD below a tenth of the
diameter, as `sim.episodes.episode` judges).

    python studies/peer_timing.py [--images 5] [--threads 2] [--json PATH]
"""

from __future__ import annotations

import statistics
import sys
import time
from typing import Any

import numpy as np

from perception.metrics import mssd, rotation_error_sym_deg
from perception.peers import PEER_ESTIMATORS
from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    add_threads_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_int
from posegrasp.world.constants import EVAL_SEED_BASE
from posegrasp.world.objects import OBJECT_NAMES, load_object

#: The learned estimator the peers are compared with (it sees the same images, depth unused).
REFERENCE = "hybrid-global"
#: The training seed of the warm-up scenes (below `EVAL_SEED_BASE`).
WARM_UP_SEED = 1000


def _view(obj: str, seed: int) -> tuple[Any, np.ndarray]:
    from sim.episodes.episode import Episode, EpisodeConfig

    ep = Episode(obj, seed, EpisodeConfig(obs_mode="rgbd"))
    try:
        return ep.observe(), ep.T_C_O_true.copy()
    finally:
        ep.close()


def measure(name: str, views: list, warm_up: list) -> dict[str, Any]:
    """One estimator's times and errors on the views, after its warm-up."""
    from sim.episodes.episode import object_symmetries
    from sim.episodes.registry import make_estimator

    estimator = make_estimator(name)
    for obs, _ in warm_up:
        estimator.estimate(obs)
    times, rot, trans, correct = [], [], [], 0
    for obs, T_true in views:
        t0 = time.perf_counter()
        est = estimator.estimate(obs)
        times.append(time.perf_counter() - t0)
        if est.T_C_O is None:
            continue
        model = load_object(obs.object)
        syms = object_symmetries(model)
        R, t, R_gt, t_gt = est.T_C_O[:3, :3], est.T_C_O[:3, 3], T_true[:3, :3], T_true[:3, 3]
        rot.append(rotation_error_sym_deg(R, R_gt, syms))
        trans.append(1000 * float(np.linalg.norm(t - t_gt)))
        correct += mssd(R, t, R_gt, t_gt, np.asarray(model.mesh.vertices), syms) < (
            0.1 * model.diameter
        )
    return {
        "time_s_median": statistics.median(times),
        "time_s_max": max(times),
        "estimates": len(rot),
        "correct": correct,
        "rotation_deg": rot,
        "translation_mm": trans,
    }


@command
def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog="python studies/peer_timing.py", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--images",
        type=arg(check_int, 1, 60, "--images", base=int),
        default=5,
        help="held-out isolated episodes (default 5)",
    )
    add_threads_argument(p)
    add_json_argument(p, "the figures")
    args = p.parse_args(argv)
    setup_rendering(threads=args.threads)
    objects = [OBJECT_NAMES[i % len(OBJECT_NAMES)] for i in range(args.images)]
    views = [_view(obj, EVAL_SEED_BASE + i) for i, obj in enumerate(objects)]
    warm_up = [_view(obj, WARM_UP_SEED) for obj in sorted(set(objects))]
    report: dict[str, Any] = {"images": args.images, "threads": args.threads, "estimators": {}}
    log = summary_stream(args.json)
    for name in [*PEER_ESTIMATORS, REFERENCE]:
        r = measure(name, views, warm_up)
        report["estimators"][name] = r
        errors = (
            f"rotation median {statistics.median(r['rotation_deg']):.2f} deg, translation "
            f"median {statistics.median(r['translation_mm']):.2f} mm"
            if r["estimates"]
            else "no estimate"
        )
        print(
            f"{name}: {r['time_s_median']:.3f} s per image (max {r['time_s_max']:.3f}); "
            f"{r['correct']}/{args.images} correct; {errors}",
            file=log,
        )
    if args.json:
        write_json(args.json, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
