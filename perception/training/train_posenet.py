"""Training of the 2D/4D pose nets on our renders (`python -m perception.training.train_posenet`).

The command line of `perception.training.trainers.posenet_trainer`: a seeded, resumable run on
cached crops, validated every epoch; under torchrun, data-parallel over the processes.

    python -m perception.training.train_posenet --variant ours --epochs 7
    python -m perception.training.train_posenet --data headcam=10000 --init CKPT --lr 1e-3
    python -m perception.training.train_posenet --smoke  # seconds, on whatever small data exists
    python -m perception.training.train_posenet --precision bf16 --channels-last  # bf16 steps
    torchrun --nproc-per-node 2 -m perception.training.train_posenet --variant ours --device cpu
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

from perception.nets import CROP, ROTATIONS, VARIANTS
from perception.training.data.crop_sets import CropConfig
from perception.training.data.dataset import DATASETS, DISTS, parse_limit
from perception.training.trainers.ddp import DEVICES, MAX_THREADS
from perception.training.trainers.options import (
    add_arithmetic_arguments,
    add_compute_arguments,
    add_data_argument,
    add_schedule_arguments,
    add_seed_argument,
)
from perception.training.trainers.posenet_trainer import (
    SMOKE,
    TRAIN_COMMAND,
    PoseNetTrainConfig,
    train,
)
from posegrasp.core.cli import ArgumentParser, add_out_argument, command
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_choice


def parse_config(argv: list[str] | None) -> tuple[PoseNetTrainConfig, argparse.Namespace]:
    """The run a command line asks for, and its parsed arguments (nothing is trained).

    Raises:
        InvalidArgumentError: values that do not make a run (a dataset twice, a width below 1,
            ``--data`` beside the older ``--dists`` or ``--limit``).
    """
    args = _parser().parse_args(argv)
    if args.data is not None and (args.dists is not None or args.limit != (None, ())):
        raise InvalidArgumentError("--data names the data alone; drop --dists and --limit")
    if args.data is not None:
        dists = tuple(name for name, _ in args.data)
        limit, dist_limits = None, tuple((d, n) for d, n in args.data if n is not None)
    else:
        dists = tuple((args.dists or ",".join(DISTS)).split(","))
        if any(d not in DATASETS for d in dists) or len(set(dists)) != len(dists):
            raise InvalidArgumentError(
                f"invalid --dists {args.dists!r}; a comma list of: {', '.join(DATASETS)}"
            )
        limit, dist_limits = args.limit
    if args.width < 1 or args.lam < 0:
        raise InvalidArgumentError("--width must be at least 1 and --lam at least 0")
    if args.name is not None and (not args.name or "/" in args.name or args.name.endswith(".pt")):
        raise InvalidArgumentError(
            f"--name must be a plain name such as posenet_ours, got {args.name!r}"
        )
    cfg = PoseNetTrainConfig(  # NetConfig checks the crop side and rotation output
        variant=args.variant,
        dists=dists,
        epochs=args.epochs,
        batch=args.batch,
        lr=args.lr,
        limit=limit,
        dist_limits=dist_limits,
        init=args.init,
        name=args.name,
        seed=args.seed,
        out=args.out,
        threads=args.threads,
        device=args.device,
        loss_log=args.loss_log,
        width=args.width,
        lam=args.lam,
        objects=tuple(o for o in args.objects.split(",") if o),
        augment=not args.no_augment,
        decay=not args.constant_lr,
        crops=CropConfig(size=args.crop),
        rotation=args.rotation,
        precision=args.precision,
        channels_last=args.channels_last,
    )
    if args.smoke:
        cfg = replace(
            SMOKE,
            variant=args.variant,
            dists=dists,
            out=args.out,
            device=args.device,
            loss_log=args.loss_log,
            threads=args.threads,
            precision=args.precision,
            channels_last=args.channels_last,
        )
    return cfg, args


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    cfg, args = parse_config(argv)
    setup_rendering()
    result = train(cfg, resume=not args.no_resume)
    print(json.dumps(result["history"][-1] if result["history"] else {}, sort_keys=True))
    return 0


def _parser() -> ArgumentParser:
    """The command line of `main`, its counts, rates and choices checked while it is parsed."""
    d = PoseNetTrainConfig
    p = ArgumentParser(prog=TRAIN_COMMAND, description=__doc__.split("\n")[0])
    p.add_argument(
        "--variant",
        type=arg(check_choice, VARIANTS, "variant"),
        default=d.variant,
        help=f"one of: {', '.join(VARIANTS)}",
    )
    add_data_argument(p, "distributions", ",".join(DISTS))
    add_schedule_arguments(p, d.epochs, d.batch, d.lr, "the training crops", "")
    add_seed_argument(p, d.seed, "initialisation and batching")
    # The spelling of the recorded commands of the shipped nets (--data replaces both).
    p.add_argument("--limit", type=arg(parse_limit), default=(None, ()), help=argparse.SUPPRESS)
    p.add_argument("--dists", default=None, help=argparse.SUPPRESS)
    p.add_argument(
        "--init", default=None, help="start from this checkpoint's weights (name or path)"
    )
    p.add_argument("--name", default=None, help="checkpoint name (default: posenet_<variant>)")
    add_out_argument(p, "the checkpoint (default: <data>/checkpoints)")
    add_compute_arguments(p, DEVICES, MAX_THREADS, "CPU")
    p.add_argument(
        "--loss-log", type=Path, default=None, help="append one JSON line per step to this file"
    )
    p.add_argument("--width", type=int, default=d.width, help="backbone width")
    p.add_argument("--lam", type=float, default=d.lam, help="rotation weight")
    p.add_argument("--crop", type=int, default=CROP, help=f"crop side [px] (default {CROP})")
    p.add_argument(
        "--rotation", default=d.rotation, help=f"ours' rotation output: {', '.join(ROTATIONS)}"
    )
    p.add_argument("--objects", default="", help="train one net on these objects (comma list)")
    p.add_argument("--no-augment", action="store_true", help="no photometric jitter")
    p.add_argument("--constant-lr", action="store_true", help="no learning-rate decay")
    add_arithmetic_arguments(p, d.precision, "weights and input crops")
    p.add_argument("--smoke", action="store_true", help="a tiny run that takes seconds")
    p.add_argument("--no-resume", action="store_true", help="start over")
    return p


if __name__ == "__main__":
    sys.exit(main())
