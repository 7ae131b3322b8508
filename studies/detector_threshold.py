"""The detector score a target's detection needs (`GlobalConfig.detection.target_score`),
chosen on a validation split (never on a test split).

    python studies/detector_threshold.py [--split headcam_hard] [--subset val] [--images 200]
        [--scores 0.5,0.4,0.3,0.2,0.1] [--detector PATH] [--json PATH]

For every image's episode target at least half visible (``target`` in the image record; the
paper protocol's images hold one object, which is), and
each score: whether a detection of its class at that score or more overlaps it (box IoU >= 0.5:
found), and whether a wrong detection of its class (IoU < 0.5 with it) outscores the best right
one (the estimator would then pose the wrong thing). The detector runs once per image, at the
lowest score asked.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from perception.detector import TIERS_DETECTOR, Detector
from perception.metrics import box_iou
from perception.training.data.dataset import PoseDataset
from posegrasp.core.cli import ArgumentParser, add_json_argument, command, write_json
from posegrasp.core.paths import data_root
from posegrasp.core.progress import progress_bar
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_float_list, check_int

MIN_VISIB = 0.5


def check_scores(spec: str) -> list[float]:
    """A comma list of scores in 0.01..1, highest first."""
    return sorted(set(check_float_list(spec, 0.01, 1.0, "--scores")), reverse=True)


def measure(detector: Detector, data: PoseDataset, n: int, scores: list[float]) -> dict:
    """Targets found and wrong picks per score over the first n images of `data`."""
    best_right, best_wrong = [], []
    for i in progress_bar(range(min(n, len(data))), desc="images", leave=False):
        s = data[i]
        dets = detector.detect(s.rgb, min(scores))
        for o in s.objects:
            # The paper protocol's studio images hold one object and name no target: it is.
            if not o.extra.get("target", True) or o.visib_fract < MIN_VISIB or o.T_C_O[2, 3] <= 0:
                continue
            mine = [d for d in dets if d.name == o.name]
            right = [d.score for d in mine if box_iou(d.box_xyxy, o.box_xyxy) >= 0.5]
            wrong = [d.score for d in mine if box_iou(d.box_xyxy, o.box_xyxy) < 0.5]
            best_right.append(max(right, default=0.0))
            best_wrong.append(max(wrong, default=0.0))
    right, wrong = np.array(best_right), np.array(best_wrong)
    rows = [
        {
            "score": t,
            "found": int((right >= t).sum()),
            "found_pct": 100.0 * float((right >= t).mean()) if len(right) else 0.0,
            "wrong_picks": int(((wrong >= t) & (wrong > right)).sum()),
        }
        for t in scores
    ]
    return {"targets": len(right), "rows": rows}


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(
        prog="python studies/detector_threshold.py", description=__doc__.split("\n\n")[0]
    )
    p.add_argument("--split", default="headcam_hard", help="dataset folder under the data root")
    p.add_argument("--subset", default="val", help="the split's subset (default val)")
    p.add_argument(
        "--images",
        type=arg(check_int, 1, 100000, "--images", base=int),
        default=200,
        help="the first N images of the subset, 1..100000 (default 200)",
    )
    p.add_argument(
        "--scores",
        type=arg(check_scores),
        default=[0.5, 0.4, 0.3, 0.2, 0.1],
        help="comma list of detector scores to measure, each in 0.01..1 "
        "(default 0.5,0.4,0.3,0.2,0.1)",
    )
    p.add_argument("--detector", type=Path, default=TIERS_DETECTOR, help="detector weights")
    add_json_argument(p, "the figures")
    args = p.parse_args(argv)
    setup_rendering()
    detector = Detector.from_weights(args.detector)
    data = PoseDataset(data_root() / args.split, args.subset)
    res = measure(detector, data, args.images, args.scores)
    print(f"{args.split}/{args.subset}: {res['targets']} targets at least half visible")
    for r in res["rows"]:
        print(
            f"  score >= {r['score']:.2f}: found {r['found']} ({r['found_pct']:.1f} %), "
            f"a wrong detection of the class outranks it in {r['wrong_picks']}"
        )
    if args.json is not None:
        write_json(args.json, res | {"split": args.split, "subset": args.subset})
    return 0


if __name__ == "__main__":
    sys.exit(main())
