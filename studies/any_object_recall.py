"""How many objects it has never seen does a detector of any object find?

    python studies/any_object_recall.py --detector PATH
        [--splits headcam_bank_rooms:val,headcam_bank_held-out_rooms:val] [--images 200]
        [--score 0.3] [--objects LIST] [--json PATH]

For each dataset split (rendered by ``datagen --bank [BANK] [--rooms]``: scenes whose only
objects are meshes of one bank, each annotated), over its first `--images` images: the share of
the annotated objects with at least `MIN_VISIBLE_PX` visible pixels that a detection scoring
`--score` or more covers (mask IoU with the visible mask >= 0.5: recall), the detections at that
score that cover none (false positives per image), and COCO's box and mask AP50 over every
score. The training bank's validation scenes show meshes the detector was trained on in scenes
it never saw; the held-out bank's show meshes it never saw. A FOLDER may also be a dataset's path,
for example a tier's scenes of the unseen track's objects (``POSEGRASP_OBJECTS=out/unseen/objects
python -m perception.training.datagen --dist headcam --tier clutter --objects can,milk,...
--split val --out out/unseen/data/clutter``); ``--objects`` then counts only those objects in the
recall (the detections that cover any other object are not false ones).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from perception.detector import Detector
from perception.metrics import mask_iou
from perception.training.data.dataset import DATASETS, SPLITS, PoseDataset
from perception.training.evals.detection_eval import coco_ap, visible_objects
from posegrasp.core.cli import ArgumentParser, add_json_argument, command, write_json
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.paths import data_root
from posegrasp.core.progress import progress_bar
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_float, check_input_file, check_int
from posegrasp.world.objects import check_objects

#: Objects with fewer visible pixels are not counted (the detector's training targets' floor).
MIN_VISIBLE_PX = 100
#: A detection covers an object when their masks overlap this much.
COVER_IOU = 0.5


def check_splits(spec: str) -> list[tuple[str, str]]:
    """``--splits``: a comma list of ``FOLDER:SPLIT``, each folder one of `DATASETS` or the path
    of a dataset's folder."""
    out = []
    for item in (x.strip() for x in spec.split(",") if x.strip()):
        folder, _, split = item.rpartition(":")
        known = folder in DATASETS or ("/" in folder and Path(folder, split).is_dir())
        if not known or split not in SPLITS:
            raise InvalidArgumentError(
                f"--splits {item!r}: FOLDER:SPLIT with FOLDER one of {', '.join(DATASETS)} or a "
                f"dataset's path (with a / in it) and SPLIT one of {', '.join(SPLITS)}"
            )
        out.append((folder, split))
    if not out:
        raise InvalidArgumentError("--splits needs at least one FOLDER:SPLIT")
    return out


def measure(
    detector: Detector,
    data: PoseDataset,
    n: int,
    score: float,
    objects: list[str] | None = None,
) -> dict:
    """Recall (of `objects` alone, if given), false positives per image and COCO AP50 over the
    first `n` images of `data`."""
    found = counted = false = 0
    gts, dets_all = [], []
    for i in progress_bar(range(min(n, len(data))), desc="images", leave=False):
        s = data[i]
        dets = detector.detect(s.rgb, 0.05)
        gts.append(visible_objects(s))
        dets_all.append(dets)
        kept = [d for d in dets if d.score >= score]
        covers = np.zeros(len(kept), bool)
        for o in s.objects:
            if int(o.mask_visib.sum()) < MIN_VISIBLE_PX:
                continue
            ious = [mask_iou(d.mask, o.mask_visib) for d in kept]
            hits = np.asarray(ious, float) >= COVER_IOU
            covers |= hits
            if objects is None or o.name in objects:
                counted += 1
                found += int(hits.any())
        # A detection overlapping only objects too small to count is not a false one.
        small = [o.mask_visib for o in s.objects if int(o.mask_visib.sum()) < MIN_VISIBLE_PX]
        for k, d in enumerate(kept):
            if not covers[k] and not any(mask_iou(d.mask, m) > 0 for m in small):
                false += 1
    ap = coco_ap(gts, dets_all, MIN_VISIBLE_PX, classes=detector.cfg.classes)
    images = len(gts)
    return {
        "images": images,
        "objects": counted,
        "recall": found / counted if counted else float("nan"),
        "false_per_image": false / images if images else float("nan"),
        "box_ap50": ap["box_ap50"],
        "mask_ap50": ap["mask_ap50"],
    }


def _parser() -> ArgumentParser:
    p = ArgumentParser(
        prog="python studies/any_object_recall.py", description=__doc__.split("\n\n")[0]
    )
    p.add_argument(
        "--detector",
        required=True,
        type=arg(check_input_file, "--detector"),
        help="the detector's weights (train_detector --any-object --export)",
    )
    p.add_argument(
        "--splits",
        default="headcam_bank_rooms:val,headcam_bank_held-out_rooms:val",
        type=arg(check_splits),
        help="comma list of FOLDER:SPLIT under the data root "
        "(default headcam_bank_rooms:val,headcam_bank_held-out_rooms:val)",
    )
    p.add_argument(
        "--images",
        default=200,
        type=arg(check_int, 1, 100_000, "--images", base=int),
        help="images per split, 1..100000 (default 200)",
    )
    p.add_argument(
        "--score",
        default=0.3,
        type=arg(check_float, 0.01, 1.0, "--score"),
        help="the score a detection needs, 0.01..1 (default 0.3, the target's)",
    )
    p.add_argument(
        "--objects",
        default=None,
        type=arg(check_objects, "--objects"),
        help="count only these objects in the recall (a comma list, built-in or user objects; "
        "default: every annotated object)",
    )
    add_json_argument(p, "the figures per split")
    return p


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    args = _parser().parse_args(argv)
    setup_rendering(threads=2)
    detector = Detector.from_weights(Path(args.detector), verify=False)
    rows = {}
    for folder, split in args.splits:
        root = Path(folder) if "/" in folder else data_root() / folder
        rows[f"{folder}:{split}"] = measure(
            detector, PoseDataset(root, split), args.images, args.score, args.objects
        )
    print(
        f"{'split':<36} {'images':>6} {'objects':>7} {'recall':>7} {'false/img':>9} "
        f"{'box AP50':>8} {'mask AP50':>9}"
    )
    for name, r in rows.items():
        print(
            f"{name:<36} {r['images']:>6} {r['objects']:>7} {r['recall']:>7.3f} "
            f"{r['false_per_image']:>9.2f} {r['box_ap50']:>8.3f} {r['mask_ap50']:>9.3f}"
        )
    if args.json is not None:
        write_json(args.json, {"score": args.score, "objects": args.objects, "splits": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
