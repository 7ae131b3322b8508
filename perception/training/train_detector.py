"""Training of the object extractor (`python -m perception.training.train_detector`).

The command line of `perception.training.trainers.detector_trainer`: a seeded, resumable run of
the Mask R-CNN, COCO AP after every epoch. ``--export`` writes the weights one trains oneself
(`perception.training.shipping.ship.export_detector`); the shipped ones are made by the recipe
(`perception.training.recipe`).

    python -m perception.training.train_detector                  # train (resumes when interrupted)
    python -m perception.training.train_detector --data headcam=5000 --epochs 8   # NAME=N,...
    python -m perception.training.train_detector --export --weights-out DIR  # and the weights
    python -m perception.training.train_detector --smoke --data DIR --out DIR   # seconds
    python -m perception.training.train_detector --precision bf16   # CPU bf16 forward passes
    torchrun --nproc-per-node 2 -m perception.training.train_detector --device cpu   # 2 processes
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

from perception.detector_net import ANY_OBJECT
from perception.training.shipping.ship import export_detector
from perception.training.trainers.ddp import DEVICES, MAX_THREADS
from perception.training.trainers.detector_trainer import (
    SMOKE,
    TRAIN_COMMAND,
    DetectorTrainConfig,
    train,
)
from perception.training.trainers.options import (
    MAX_LIMIT,
    add_arithmetic_arguments,
    add_compute_arguments,
    add_data_argument,
    add_schedule_arguments,
    add_seed_argument,
)
from posegrasp.core.cli import ArgumentParser, add_out_argument, command
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.paths import WEIGHTS_DIR
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import MAX_WORKERS, arg, check_int, check_output_dir
from posegrasp.world.objects import check_objects


def parse_config(argv: list[str] | None) -> tuple[DetectorTrainConfig, argparse.Namespace]:
    """The run a command line asks for, and its parsed arguments (nothing is trained).

    Raises:
        InvalidArgumentError: ``--data`` of several folders beside the older ``--also``.
    """
    args = _parser().parse_args(argv)
    data = args.data or (("headcam", None),)
    if len(data) > 1 and args.also:
        raise InvalidArgumentError("--data names every folder; drop --also")
    folder, first_images = data[0]
    also = tuple(args.also.split(",")) if args.also else tuple(name for name, _ in data[1:])
    limits = ((Path(folder).name, first_images), *data[1:])
    if args.smoke:
        cfg = replace(
            SMOKE,
            data=None if args.data is None else Path(folder),
            out=args.out,
            seed=args.seed,
            threads=args.threads or SMOKE.threads,
            device=args.device,
            loss_log=args.loss_log,
            init=args.init,
            precision=args.precision,
            channels_last=args.channels_last,
        )
    else:
        cfg = DetectorTrainConfig(
            data=None if args.data is None else Path(folder),
            epochs=args.epochs,
            batch=args.batch,
            lr=args.lr,
            limit=args.limit,
            limits=tuple((name, n) for name, n in limits if n is not None),
            val_images=args.val_images,
            workers=args.workers,
            seed=args.seed,
            out=args.out,
            threads=args.threads,
            device=args.device,
            loss_log=args.loss_log,
            init=args.init,
            also=also,
            precision=args.precision,
            channels_last=args.channels_last,
        )
    if args.objects and args.any_object:
        raise InvalidArgumentError("--any-object detects every object; drop --objects")
    if args.objects:
        cfg = replace(cfg, detector=cfg.detector.widened(args.objects))
    if args.any_object:
        cfg = replace(cfg, detector=replace(cfg.detector, classes=(ANY_OBJECT,), n_classes=2))
    return cfg, args


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    cfg, args = parse_config(argv)
    setup_rendering()
    result = train(cfg, resume=not args.no_resume, max_steps=args.max_steps)
    if result["history"]:
        print(json.dumps(result["history"][-1], sort_keys=True))
    if args.export:
        if not result["finished"]:
            print("note: exporting an unfinished run", file=sys.stderr)
        entry = export_detector(Path(result["checkpoint"]), args.weights_out)
        print(f"wrote {args.weights_out / entry['file']} ({entry['bytes'] / 1e6:.1f} MB)")
    return 0


def _parser() -> ArgumentParser:
    """The command line of `main`, its counts and rates checked while it is parsed."""
    d = DetectorTrainConfig
    p = ArgumentParser(prog=TRAIN_COMMAND, description=__doc__.split("\n")[0])
    add_data_argument(p, "dataset folders", "headcam", folder_first=True)
    # The spelling of the recorded commands of the shipped detectors (--data replaces both).
    p.add_argument("--also", default=None, help=argparse.SUPPRESS)
    p.add_argument(
        "--limit",
        type=arg(check_int, 1, MAX_LIMIT, "--limit", base=int),
        default=None,
        help=argparse.SUPPRESS,
    )
    p.add_argument("--init", type=Path, help="start from these detector weights (fine-tune)")
    p.add_argument(
        "--objects",
        type=arg(check_objects, "--objects"),
        default=None,
        metavar="LIST",
        help="user objects to detect besides the six built-in ones (comma list; with --init, "
        "the class heads of those weights are widened for them)",
    )
    p.add_argument(
        "--any-object",
        action="store_true",
        help=f"one class, {ANY_OBJECT!r}, that every annotated object is, whatever it is: a "
        "detector of objects it has never seen (trained on bank scenes, datagen --bank)",
    )
    add_schedule_arguments(p, d.epochs, d.batch, d.lr, "the train split", " of images")
    p.add_argument(
        "--val-images",
        type=arg(check_int, 1, MAX_LIMIT, "--val-images", base=int),
        default=d.val_images,
        help=f"the AP evaluation uses this many val images (default {d.val_images})",
    )
    p.add_argument(
        "--workers",
        type=arg(check_int, 0, MAX_WORKERS, "--workers", base=int),
        default=d.workers,
        metavar="N",
        help=f"data-loading processes, 0..{MAX_WORKERS} (0: load in the training process; "
        f"default {d.workers})",
    )
    add_compute_arguments(p, DEVICES, MAX_THREADS, "torch")
    add_arithmetic_arguments(p, d.precision, "weights (and so the feature maps)")
    p.add_argument(
        "--loss-log", type=Path, default=None, help="append one JSON line per step to this file"
    )
    add_seed_argument(p, d.seed, "initialisation, image order and augmentation")
    add_out_argument(p, "the checkpoint (default: <data>/checkpoints)")
    p.add_argument(
        "--max-steps",
        type=arg(check_int, 1, 2**62, "--max-steps", base=int),
        help="stop after this many steps (resumable)",
    )
    p.add_argument("--smoke", action="store_true", help="a tiny run that takes seconds")
    p.add_argument("--no-resume", action="store_true", help="start over")
    p.add_argument(
        "--export",
        action="store_true",
        help="after training, write the weights and their manifest entry into --weights-out "
        "(the shipped ones are written by `python -m perception.training.recipe --ship`)",
    )
    p.add_argument(
        "--weights-out",
        type=arg(check_output_dir, "--weights-out", base=Path),
        default=WEIGHTS_DIR,
        help=f"export folder (default {WEIGHTS_DIR})",
    )
    return p


if __name__ == "__main__":
    sys.exit(main())
