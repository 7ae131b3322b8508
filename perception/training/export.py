"""Ship the pose nets' checkpoints one trained oneself, and draw their training curves.

The shipping itself is `perception.training.shipping.ship`.

    python -m perception.training.export [--checkpoints DIR (default: <data>/checkpoints)]
        [--out DIR] [--plot training_curves.png]
"""

from __future__ import annotations

import sys
from pathlib import Path

from perception.training.shipping.ship import export, plot_curves, training_curves
from posegrasp.core.cli import ArgumentParser, add_out_argument, command
from posegrasp.core.paths import WEIGHTS_DIR, checkpoint_dir
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_plot_path


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(
        prog="python -m perception.training.export", description=__doc__.split("\n")[0]
    )
    p.add_argument(
        "--checkpoints",
        type=Path,
        default=None,
        metavar="DIR",
        help="folder of the pose nets' checkpoints, posenet_<name>.pt (default: "
        "<data>/checkpoints)",
    )
    add_out_argument(
        p,
        "the weights and their manifest (the shipped ones are written by `python -m "
        "perception.training.recipe --ship`)",
        default=WEIGHTS_DIR,
    )
    p.add_argument(
        "--plot",
        type=arg(check_plot_path),
        default=None,
        metavar="PATH",
        help="write the training curves here (.png, .pdf or .svg)",
    )
    args = p.parse_args(argv)
    setup_rendering()
    ckpts = args.checkpoints or checkpoint_dir()
    m = export(ckpts, args.out)
    if args.plot:
        plot_curves(training_curves(ckpts), args.plot)
        print(f"wrote {args.plot}")
    for v, e in m["pose_nets"].items():
        print(f"{v}: {e['file']} ({e['bytes'] / 1e6:.1f} MB), epochs {e['epochs_done']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
