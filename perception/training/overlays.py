"""Overlays of the hybrid estimator's poses on held-out test images or on any image file.

python -m perception.training.overlays --dist headcam --split test --images 12 --out DIR
python -m perception.training.overlays --image head.png --K 554.3,554.3,320,240 --out DIR
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import cast

import cv2
import numpy as np

from perception.hybrid import HybridPoseEstimator
from perception.overlay import draw_detections
from perception.training.data.dataset import DISTS, SPLITS, PoseDataset
from perception.training.data.sheets import contact_sheet
from posegrasp.core.cli import ArgumentParser, add_out_argument, command
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.paths import data_root
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_choice, check_int, parse_intrinsics

#: Most images one command overlays.
MAX_IMAGES = 1000


@command
def main(argv: list[str] | None = None) -> int:
    """CLI: estimate poses on rendered test images or on an image file and save overlays.

    python -m perception.training.overlays --dist headcam --split test --images 12 --out out/o
    python -m perception.training.overlays --image head.png --K 554.3,554.3,320,240 --out out/one
    """
    args = _parser().parse_args(argv)
    setup_rendering()
    items = _images(args)
    args.out.mkdir(parents=True, exist_ok=True)
    est = HybridPoseEstimator.from_weights()
    tiles = []
    for name, rgb, K in items:
        found, timings = est.estimate_timed(rgb, K)
        img = draw_detections(rgb, K, found)
        cv2.imwrite(str(args.out / f"{name}.png"), img[..., ::-1])
        tiles.append(img)
        print(
            f"{name}: "
            + (", ".join(f"{d.name} {d.score:.2f}" for d in found) or "no detection")
            + f"  ({timings['total']:.0f} ms)"
        )
    if len(tiles) > 1:
        sheet = contact_sheet(tiles, cols=4, tile=320)
        cv2.imwrite(str(args.out / "overlays.png"), sheet[..., ::-1])
        print(f"wrote {len(tiles)} overlays and {args.out / 'overlays.png'}")
    return 0


def _images(args: argparse.Namespace) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, RGB image, intrinsics) of each image the command line names: the image file, or
    the first images of a rendered split.

    Raises:
        InvalidArgumentError: an image file without intrinsics, unreadable, or whose principal
            point lies outside it.
    """
    if args.image is not None and args.K is None:
        raise InvalidArgumentError("--image needs --K fx,fy,cx,cy")
    if args.image is not None:
        bgr = cv2.imread(str(args.image), cv2.IMREAD_COLOR)
        if bgr is None:
            raise InvalidArgumentError(f"cannot read an image from {args.image}")
        h, w = bgr.shape[:2]
        cx, cy = args.K[0, 2], args.K[1, 2]
        if not (0 <= cx <= w - 1 and 0 <= cy <= h - 1):
            raise InvalidArgumentError(
                f"invalid --K: principal point ({cx:g}, {cy:g}) outside the {w}x{h} image; "
                f"valid: cx in 0..{w - 1}, cy in 0..{h - 1}"
            )
        return [(args.image.stem, bgr[..., ::-1].copy(), args.K)]
    ds = PoseDataset(data_root() / args.dist, args.split)
    items = []
    for i in range(min(args.images, len(ds))):
        s = ds[i]
        items.append((f"{args.split}_{s.scene_id:06d}_{s.im_id:06d}", s.rgb, s.K))
    return items


def _parser() -> ArgumentParser:
    """The command line of `main`, its values checked while it is parsed."""
    p = ArgumentParser(
        prog="python -m perception.training.overlays",
        description=cast(str, main.__doc__).split("\n")[0],
    )
    p.add_argument(
        "--dist",
        default="headcam",
        type=arg(check_choice, DISTS, "distribution"),
        help=f"dataset under $POSEGRASP_DATA, one of: {', '.join(DISTS)}",
    )
    p.add_argument(
        "--split",
        default="test",
        type=arg(check_choice, SPLITS, "split"),
        help=f"one of: {', '.join(SPLITS)}",
    )
    p.add_argument(
        "--images",
        type=arg(check_int, 1, MAX_IMAGES, "--images", base=int),
        default=12,
        help=f"how many images of the split, 1..{MAX_IMAGES}",
    )
    p.add_argument(
        "--image", type=Path, default=None, metavar="PATH", help="an RGB image file instead"
    )
    p.add_argument(
        "--K", type=arg(parse_intrinsics, "--K"), default=None, help="fx,fy,cx,cy of --image [px]"
    )
    add_out_argument(
        p,
        "<name>.png per image, and overlays.png, a contact sheet of them all",
        required=True,
        aliases=("--save",),
    )
    return p


if __name__ == "__main__":
    sys.exit(main())
