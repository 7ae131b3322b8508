"""Train the mask net (`perception.mask_net`) on rendered scenes, and measure it on held-out
images with the detector's own masks: the tiers' (``--protocol tiers``, the default) or the paper
protocol's (``--protocol paper``; `PROTOCOLS`).

    python -m perception.training.train_masknet --epochs 5 --channels-last --export
    python -m perception.training.train_masknet --evaluate --split test --images 300
    python -m perception.training.train_masknet --protocol paper --epochs 6 --channels-last --export

Each visible object of a training image (at least `MIN_VISIBLE_PX` visible pixels) gives one
window around its true visible mask, its centre and side jittered as a detector's box would be.
The windows are cut once into a cache (``$POSEGRASP_DATA/masknet``). The coarse input is drawn on
the batch from the true mask (`degrade`): averaged onto a coarse grid and drawn back, thresholded
at a random level, its thin parts opened away at random, with whole parts lost and gained, and
shifted by a few pixels. The loss is the binary cross-entropy with the true mask's coverage of
each window pixel.

``--detected N`` adds the N training images after the protocol's, their windows cut around the
protocol detector's own mask of each object (as the estimator cuts them) with that mask as the
coarse input (`detector_windows`): the detector's real failures, such as a whole dark part lost,
beside the drawn ones. Validation then also measures the net on the detector's masks of the
validation scenes (``detected_iou``).

A run checkpoints after every epoch and every few minutes (``--out``) and resumes from there;
``--export`` writes the protocol's net (``perception/weights/tiers/masknet.pt``,
``perception/weights/paper_protocol/masknet.pt``) and its manifest entry (``mask_net``: command,
data, validation, wall time). ``--init`` starts a run from a shipped net (a further stage, on
windows cut afresh with another ``--seed``); its entry then lists every stage that made it.
The shipped nets are made by the recipe (`perception.training.recipe`), each stage one call to
`train`; its command line names the training scenes as the other trainers do (``--data
NAME=N,...``, ``--val NAME=N``).

    python -m perception.training.train_masknet --init perception/weights/tiers/masknet.pt \
        --seed 1 --epochs 3 --lr 0.001 --channels-last --export
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import torch

from perception.detector import TIERS_DETECTOR
from perception.training.data.dataset import parse_data
from perception.training.evals.masknet_eval import evaluate, plot_examples
from perception.training.shipping.ship import export_masknet
from perception.training.trainers.masknet_trainer import (
    DEFAULT_PROTOCOL,
    PROTOCOLS,
    TRAIN_COMMAND,
    MaskTrainConfig,
    train,
)
from perception.training.trainers.options import (
    add_arithmetic_arguments,
    add_data_argument,
    add_schedule_arguments,
    add_seed_argument,
)
from posegrasp.core.cli import ArgumentParser, add_out_argument, command, write_json
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.paths import checkpoint_dir
from posegrasp.core.validate import arg, check_choice, check_int, check_plot_path
from posegrasp.world.objects import OBJECT_NAMES


def parse_config(argv: list[str] | None) -> tuple[MaskTrainConfig, argparse.Namespace]:
    """The run a command line asks for, and its parsed arguments (nothing is trained).

    Raises:
        InvalidArgumentError: ``--expert`` without ``--export`` or for an object the protocol
            has no net of its own for.
    """
    args = _parser().parse_args(argv)
    proto = PROTOCOLS[args.protocol]
    if args.expert is not None and (not args.export or args.expert not in proto.experts):
        raise InvalidArgumentError(
            f"--expert {args.expert} needs --export and one of the objects the {args.protocol} "
            f"protocol's estimator has a net of its own for: {', '.join(proto.experts) or 'none'}"
        )
    sources = proto.sources if args.data is None else args.data
    if any(n is None for _, n in sources):
        raise InvalidArgumentError("--data wants a count of every folder: NAME=N,...")
    if args.val is not None and (len(args.val) != 1 or args.val[0][1] is None):
        raise InvalidArgumentError("--val wants one NAME=N")
    folder, first = proto.sources[0]
    name = "masknet" + ("" if args.protocol == DEFAULT_PROTOCOL else f"_{args.protocol}")
    cfg = MaskTrainConfig(
        detected=None if args.detected is None else (folder, first, args.detected),
        detector=None if args.detected is None else args.detector or proto.detector,
        sources=tuple(sources),
        val=proto.val if args.val is None else args.val[0],
        epochs=args.epochs,
        batch=args.batch,
        lr=args.lr,
        precision=args.precision,
        channels_last=args.channels_last,
        out=args.out or checkpoint_dir() / name,
        seed=args.seed,
        init=args.init,
    )
    return cfg, args


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    argv = sys.argv[1:] if argv is None else list(argv)
    cfg, args = parse_config(argv)
    torch.set_num_threads(2)
    if args.evaluate:
        return _report(args)
    train(cfg, resume=not args.no_resume)
    if args.export:
        weights = PROTOCOLS[args.protocol].weights
        if args.weights_out is not None:
            weights = args.weights_out / weights.name
        line = f"{TRAIN_COMMAND} {shlex.join(argv)}".strip()
        entry = export_masknet(cfg.out / "last.pt", line, weights, args.expert)
        print(f"wrote {entry['file']} beside {weights} ({entry['bytes']} bytes)")
    return 0


def _report(args: argparse.Namespace) -> int:
    """``--evaluate``: measure the protocol's shipped net and print (and write) the figures."""
    examples: list | None = [] if args.plot else None
    proto = PROTOCOLS[args.protocol]
    detector = proto.detector or TIERS_DETECTOR
    report = evaluate(
        proto.val[0], args.split, args.images, detector, proto.weights, proto.experts, examples
    )
    print(
        f"{report['split']}: {report['objects']} objects, mask IoU with the truth: detector "
        f"{report['detector_iou']:.3f}, refined {report['refined_iou']:.3f} (better for "
        f"{100 * report['refined_better']:.1f} %), {report['ms_per_mask']:.1f} ms per mask"
    )
    for name, r in report["per_class"].items():
        print(f"  {name:7s} {r['objects']:4d}  {r['detector_iou']:.3f} -> {r['refined_iou']:.3f}")
    if args.json:
        write_json(args.json, report)
    if args.plot and examples:
        plot_examples(examples, args.plot)
    return 0


def _parser() -> ArgumentParser:
    """The command line of `main`, its values checked while it is parsed."""
    d = MaskTrainConfig
    p = ArgumentParser(prog=TRAIN_COMMAND, description=__doc__)
    p.add_argument(
        "--protocol",
        type=arg(check_choice, tuple(PROTOCOLS), "protocol"),
        default=DEFAULT_PROTOCOL,
        help="the images and detector: tiers (the head camera's scenes, hybrid-global) or paper "
        f"(the paper's studio images, hybrid-global-paper) (default {DEFAULT_PROTOCOL})",
    )
    add_data_argument(p, "split folders of training scenes", "the protocol's")
    p.add_argument(
        "--val",
        type=arg(parse_data),
        default=None,
        metavar="NAME=N",
        help="the folder of the validation scenes and how many (default: the protocol's)",
    )
    add_schedule_arguments(p, d.epochs, d.batch, d.lr, "the training windows", " of windows")
    add_seed_argument(
        p,
        d.seed,
        "the training windows' jitter, the batches' order and the coarse masks (the validation "
        "windows are seed 0's whatever it is)",
    )
    add_arithmetic_arguments(p, d.precision, "the net and its inputs")
    add_out_argument(p, "the checkpoint (default: <data>/checkpoints/masknet[_<protocol>])")
    p.add_argument(
        "--init", type=Path, default=None, help="start from this mask net (a further stage)"
    )
    p.add_argument(
        "--detected",
        type=arg(check_int, 1, 1_000_000, "--detected", base=int),
        default=None,
        help="also train on this many images after the protocol's training images, cut around "
        "its detector's own masks, which are their coarse input (default none)",
    )
    p.add_argument(
        "--detector",
        type=Path,
        default=None,
        help="with --detected: the detector weights or checkpoint whose masks those are "
        "(default: the protocol's shipped detector)",
    )
    p.add_argument("--no-resume", action="store_true", help="start over")
    p.add_argument(
        "--export",
        action="store_true",
        help="write the protocol's net and its manifest entry when done (the shipped ones are "
        "written by `python -m perception.training.recipe --ship`)",
    )
    p.add_argument(
        "--weights-out",
        type=Path,
        default=None,
        help="with --export: the folder to write the net and its manifest into (default: the "
        "protocol's, perception/weights/tiers or perception/weights/paper_protocol)",
    )
    p.add_argument(
        "--expert",
        type=arg(check_choice, OBJECT_NAMES, "object"),
        default=None,
        help="with --export: ship the net as the one that redraws this object's masks alone "
        "(masknet_<object>.pt beside the protocol's net), one of: " + ", ".join(OBJECT_NAMES),
    )
    _add_evaluate_arguments(p)
    return p


def _add_evaluate_arguments(p: ArgumentParser) -> None:
    """Add ``--evaluate`` and its options: the split, the images, the figures and the picture."""
    p.add_argument(
        "--evaluate",
        action="store_true",
        help="measure the shipped net against the detector's masks instead of training",
    )
    p.add_argument(
        "--split",
        type=arg(check_choice, ("val", "test"), "split"),
        default="test",
        help="with --evaluate: val or test (default test)",
    )
    p.add_argument(
        "--images",
        type=arg(check_int, 1, 100_000, "--images", base=int),
        default=300,
        help="with --evaluate: images of the protocol's split (the hard tier's, the paper's), "
        "1..100000 (default 300)",
    )
    p.add_argument("--json", default=None, help="with --evaluate: write the figures here")
    p.add_argument(
        "--plot",
        type=arg(check_plot_path),
        default=None,
        help="with --evaluate: draw each class's first object's masks into this PNG",
    )


if __name__ == "__main__":
    sys.exit(main())
