"""Overlays of the hybrid estimator's poses on held-out test images or on any image file.

python -m perception.training.overlays --dist headcam --split test --images 12 --save DIR
python -m perception.training.overlays --image head.png --K 554.3,554.3,320,240 --save DIR
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from perception.hybrid import HybridPoseEstimator
from perception.overlay import draw_detections
from perception.training.dataset import PoseDataset
from perception.training.sheets import contact_sheet
from sim.core.cli import ArgumentParser, check_writable_file, fail
from sim.core.errors import PosegraspError
from sim.core.paths import data_root


def main(argv: list[str] | None = None) -> int:
    """CLI: estimate poses on rendered test images or on an image file and save overlays.

    python -m perception.training.overlays --dist headcam --split test --images 12 --save out/o
    python -m perception.training.overlays --image head.png --K 554.3,554.3,320,240 --save out/one
    """

    p = ArgumentParser(
        prog="python -m perception.training.overlays", description=main.__doc__.split("\n")[0]
    )
    p.add_argument("--dist", default="headcam", help="dataset under $POSEGRASP_DATA: headcam")
    p.add_argument("--split", default="test", help="one of: train, val, test")
    p.add_argument("--images", type=int, default=12, help="how many images of the split")
    p.add_argument("--image", type=Path, default=None, help="an RGB image file instead")
    p.add_argument("--K", default=None, help="fx,fy,cx,cy of --image [px]")
    p.add_argument("--save", type=Path, required=True, metavar="DIR", help="output folder")
    args = p.parse_args(argv)
    if args.split not in ("train", "val", "test"):
        return fail(f"unknown split {args.split!r}; valid splits: train, val, test")
    try:
        check_writable_file(args.save / "overlays.png")
        if args.image is not None:
            if args.K is None:
                return fail("--image needs --K fx,fy,cx,cy")
            try:
                fx, fy, cx, cy = (float(v) for v in args.K.split(","))
            except ValueError:
                return fail(f"--K must be four numbers fx,fy,cx,cy, got {args.K!r}")
            bgr = cv2.imread(str(args.image), cv2.IMREAD_COLOR)
            if bgr is None:
                return fail(f"cannot read an image from {args.image}")
            items = [
                (
                    args.image.stem,
                    bgr[..., ::-1].copy(),
                    np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]),
                )
            ]
        else:
            ds = PoseDataset(data_root() / args.dist, args.split)
            items = []
            for i in range(min(args.images, len(ds))):
                s = ds[i]
                items.append((f"{args.split}_{s.scene_id:06d}_{s.im_id:06d}", s.rgb, s.K))
        est = HybridPoseEstimator.from_weights()
        tiles = []
        for name, rgb, K in items:
            found, timings = est.estimate_timed(rgb, K)
            img = draw_detections(rgb, K, found)
            cv2.imwrite(str(args.save / f"{name}.png"), img[..., ::-1])
            tiles.append(img)
            print(
                f"{name}: "
                + (", ".join(f"{d.name} {d.score:.2f}" for d in found) or "no detection")
                + f"  ({timings['total']:.0f} ms)"
            )
        if len(tiles) > 1:
            sheet = contact_sheet(tiles, cols=4, tile=320)
            cv2.imwrite(str(args.save / "overlays.png"), sheet[..., ::-1])
            print(f"wrote {len(tiles)} overlays and {args.save / 'overlays.png'}")
    except PosegraspError as exc:
        return fail(str(exc))
    return 0


if __name__ == "__main__":
    sys.exit(main())
