"""Latency of the hybrid pose estimator per stage on 640x480 head-camera images (2 threads).

    python bench/estimator_latency.py [--images 50] [--threads 2] [--json PATH] [--random-weights]

Renders head-camera images of seeded table scenes with 1 object and with 3 objects (the target
and 2 distractors), then times `HybridPoseEstimator.estimate_timed` on each (after a warm-up):
median and 90th percentile of every stage (detect, crop, nets, decode) and of the total.
Targets: total <= 66 ms median for 3 objects; both pose nets <= 7 ms per object (the batched
nets stage of the 3-object images divided by their detections). `--json PATH` writes one JSON
object whose ``total_ms_median`` is the 3-object median (``-``: to standard output).

Without shipped weights (`make weights`), `--random-weights` times the architecture with random
weights: the detector then keeps its top-scoring boxes, as many as the scene has objects, so
every stage sees the work a trained model would do; the poses are meaningless.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

# torch, torchvision and torch._dynamo (which loads triton) must be imported before any MuJoCo
# GL context exists: importing them afterwards crashes the process (docs/DESIGN.md §11).
import torch
import torch._dynamo
import torchvision  # noqa: F401

from perception.detector import DEFAULT_WEIGHTS
from perception.hybrid import DEFAULT_POSENET, STAGES, HybridPoseEstimator
from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    add_threads_argument,
    command,
    fail,
    summary_stream,
    target,
    write_json,
)
from posegrasp.core.errors import PosegraspError
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_int, check_seed
from posegrasp.world import constants as C
from posegrasp.world.camera import CameraRenderer, camera_intrinsics
from posegrasp.world.objects import OBJECT_NAMES
from posegrasp.world.scene import SceneConfig, build_scene

WIDTH, HEIGHT = 640, 480
TARGET_MS = 66.0
NETS_TARGET_MS = 7.0
WARMUP = 3


def render_images(n_objects: int, count: int, seed0: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """`count` head-camera images (rgb, K) of scenes with `n_objects` objects, seeds seed0...."""
    out = []
    for i in range(count):
        obj = OBJECT_NAMES[i % len(OBJECT_NAMES)]
        scene = build_scene(obj, seed0 + i, SceneConfig(n_distractors=n_objects - 1))
        with CameraRenderer(scene.model, WIDTH, HEIGHT) as r:
            rgb = r.rgb(scene.data, C.HEAD_CAMERA)
        out.append((rgb, camera_intrinsics(scene.model, C.HEAD_CAMERA, WIDTH, HEIGHT)))
    return out


def time_estimator(
    est: HybridPoseEstimator, images: list[tuple[np.ndarray, np.ndarray]]
) -> dict[str, Any]:
    """Median and p90 [ms] of every stage and the total, and the mean detections per image."""
    for rgb, K in images[:WARMUP]:
        est.estimate_timed(rgb, K)
    rows, counts = [], []
    for rgb, K in images:
        dets, t = est.estimate_timed(rgb, K)
        rows.append(t)
        counts.append(len(dets))
    stats = {
        k: {
            "median": float(np.median([r[k] for r in rows])),
            "p90": float(np.percentile([r[k] for r in rows], 90)),
        }
        for k in (*STAGES, "total")
    }
    return {"stages_ms": stats, "detections_per_image": float(np.mean(counts))}


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(prog="python bench/estimator_latency.py", description=__doc__.split("\n")[0])
    p.add_argument(
        "--images",
        type=arg(check_int, 1, 10_000, "--images", base=int),
        default=50,
        help="images per scene type, 1..10000 (default 50)",
    )
    add_threads_argument(p)
    p.add_argument(
        "--seed",
        type=arg(check_seed, "--seed", base=int),
        default=5000,
        help="seed of the first scene (default 5000)",
    )
    p.add_argument("--detector", type=Path, default=DEFAULT_WEIGHTS, metavar="PATH")
    p.add_argument("--posenet", type=Path, default=DEFAULT_POSENET, metavar="PATH")
    p.add_argument(
        "--random-weights",
        action="store_true",
        help="time the architecture with random weights (no training needed)",
    )
    add_json_argument(p, "the figures")
    args = p.parse_args(argv)
    setup_rendering()
    check_seed(args.seed, "--seed", 3000 + args.images)
    torch.set_num_threads(args.threads)
    results = {}
    try:
        for n in (1, 3):
            if args.random_weights:
                est = HybridPoseEstimator.with_random_weights(max_detections=n)
            else:
                est = HybridPoseEstimator.from_weights(args.detector, args.posenet)
            images = render_images(n, args.images, args.seed + 1000 * n)
            results[n] = time_estimator(est, images)
    except PosegraspError as exc:
        hint = "" if args.random_weights else " (or pass --random-weights to time the architecture)"
        return fail(f"{exc}{hint}")
    three = results[3]["stages_ms"]["total"]
    dets3 = max(results[3]["detections_per_image"], 1e-9)
    nets_per_object = results[3]["stages_ms"]["nets"]["median"] / dets3
    out = {
        "weights": "random" if args.random_weights else "shipped",
        "threads": args.threads,
        "images": args.images,
        "image_size": [WIDTH, HEIGHT],
        "one_object": results[1],
        "three_objects": results[3],
        "total_ms_median": three["median"],
        "total_ms_p90": three["p90"],
        "target_ms": TARGET_MS,
        "nets_ms_per_object": nets_per_object,
        "load_average_1min": os.getloadavg()[0],
    }
    log = summary_stream(args.json)
    label = "RANDOM WEIGHTS (architecture only)" if args.random_weights else "shipped weights"
    print(
        f"hybrid estimator, {label}, {WIDTH}x{HEIGHT}, {args.threads} threads, "
        f"{args.images} images per row, load average {out['load_average_1min']:.1f}",
        file=log,
    )
    print(f"{'objects':<9}{'dets':>6}" + "".join(f"{s:>18}" for s in (*STAGES, "total")), file=log)
    for n in (1, 3):
        r = results[n]
        cells = "".join(
            f"{r['stages_ms'][s]['median']:>9.1f} /{r['stages_ms'][s]['p90']:>6.1f}"
            for s in (*STAGES, "total")
        )
        print(f"{n:<9}{r['detections_per_image']:>6.1f}{cells}", file=log)
    print("(median / p90 ms)", file=log)
    print(
        f"3-object total median {three['median']:.1f} ms "
        + target(f"<= {TARGET_MS:.0f} ms", three["median"] <= TARGET_MS),
        file=log,
    )
    print(
        f"2D-NET + 4D-NET, batched over the 3-object images: {nets_per_object:.2f} ms per object "
        + target(f"<= {NETS_TARGET_MS:.0f} ms", nets_per_object <= NETS_TARGET_MS),
        file=log,
    )
    if args.json is not None:
        write_json(args.json, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
