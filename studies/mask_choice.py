"""What the mask costs the choice of pose: the whole search, with the redrawn mask and with the true
one.

    python studies/mask_choice.py [--estimator hybrid-global] [--split headcam_hard] [--subset test]
        [--images 100] [--targets] [--json PATH]

For every visible object of the first images (at least half visible; with ``--targets`` only each
image's episode target) that the estimator's detector finds, its hypotheses are drawn, refined and
verified (`GlobalPoseEstimator.verify`, the camera's pose giving gravity where the estimator uses
it) twice: against the mask net's redrawing of the detector's mask, as the estimator runs, and
against the true visible mask. The difference between the two rotation errors is what the mask
costs the choice; what is left with the true mask is what the hypotheses and the verification
cost. The support from the neighbours is not run; a detection no start of which gives a pose
counts as 180 deg.
"""

from __future__ import annotations

import sys
from dataclasses import replace

import numpy as np

from perception.estimators import LEARNED_ESTIMATORS
from perception.global_pose import GlobalPoseEstimator
from perception.hybrid import detect_target
from perception.metrics import mask_iou, rotation_error_deg
from perception.training.data.dataset import PoseDataset
from perception.training.evals.estimator_tables import MIN_VISIB, rotation_summary
from posegrasp.core.cli import ArgumentParser, add_json_argument, command, write_json
from posegrasp.core.contract import Observation
from posegrasp.core.paths import data_root
from posegrasp.core.progress import progress_bar
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_choice, check_int

#: The estimators that search hypotheses and verify them.
ESTIMATORS = ("hybrid-global", "hybrid-global-paper")
MASKS = ("mask net", "truth")


def _parser() -> ArgumentParser:
    p = ArgumentParser(prog="python studies/mask_choice.py", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--estimator",
        type=arg(check_choice, ESTIMATORS, "estimator"),
        default="hybrid-global",
        help=f"one of: {', '.join(ESTIMATORS)} (default hybrid-global)",
    )
    p.add_argument("--split", default="headcam_hard", help="dataset folder under the data root")
    p.add_argument("--subset", default="test", help="the split's subset (default test)")
    p.add_argument(
        "--images",
        type=arg(check_int, 1, 100000, "--images", base=int),
        default=100,
        help="the first N images of the subset, 1..100000 (default 100)",
    )
    p.add_argument("--targets", action="store_true", help="only each image's episode target")
    add_json_argument(p, "the errors per object and mask")
    return p


def _measure(
    est: GlobalPoseEstimator, ds: PoseDataset, images: int, targets: bool
) -> list[tuple[str, float, float, float]]:
    """Per detected object of the first `images` images (with `targets`, only each image's
    target): its name, the redrawn mask's IoU and the rotation error [deg] with each mask."""
    gravity = est.config.gravity is not None
    rows: list[tuple[str, float, float, float]] = []  # object, IoU, error with each mask
    for i in progress_bar(range(min(images, len(ds))), desc="masks and choice", mininterval=5):
        s = ds[i]
        T_W_C = np.asarray(s.extra.get("T_W_C", np.eye(4)), float)
        for obj in s.objects:
            if obj.visib_fract < MIN_VISIB or obj.T_C_O[2, 3] <= 0:
                continue
            if targets and obj.name != s.extra.get("target", obj.name):
                continue
            obs = Observation(s.rgb, s.K, T_W_C, obj.name, int(s.seed))
            found = detect_target(est.hybrid, obs, est.config.detection.target_score, False)
            if found.best is None:
                continue
            occluder = found.occluder()
            sharp = est.sharpened(found.best, s.rgb)
            errors = []
            for mask in (sharp.mask, obj.mask_visib):
                ranked, _ = est.verify(
                    replace(found.best, mask=mask),
                    s.K,
                    s.rgb,
                    occluder,
                    T_W_C[:3, :3] if gravity else None,
                )
                T = ranked[0].T_C_O if ranked else None
                errors.append(
                    rotation_error_deg(T[:3, :3], obj.T_C_O[:3, :3]) if T is not None else 180.0
                )
            rows.append((obj.name, mask_iou(sharp.mask, obj.mask_visib), *errors))
    return rows


def _tabulate(rows: list[tuple[str, float, float, float]], report: dict) -> None:
    """Per object and over all: the mask's IoU and each mask's rotation errors, added to
    `report` and printed."""
    names = sorted({r[0] for r in rows})
    print(
        f"{'object':8s} {'n':>4s} {'mask IoU':>8s}   "
        + "   ".join(f"{m + ': mean / median / > 15 %':>34s}" for m in MASKS)
    )
    for name in (*names, "all"):
        sel = [r for r in rows if name in ("all", r[0])]
        entry = {"objects": len(sel), "mask_iou": float(np.mean([r[1] for r in sel]))}
        cells = []
        for k, m in enumerate(MASKS):
            entry[m] = rotation_summary(np.array([r[2 + k] for r in sel]))
            e = entry[m]
            cells.append(
                f"{e['rotation_mean_deg']:14.2f} / {e['rotation_median_deg']:6.2f} / "
                f"{e['over_15_deg_pct']:5.1f}"
            )
        report[name] = entry
        print(f"{name:8s} {len(sel):4d} {entry['mask_iou']:8.3f}   " + "   ".join(cells))


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    args = _parser().parse_args(argv)
    setup_rendering(threads=1)
    est = LEARNED_ESTIMATORS[args.estimator]()
    assert isinstance(est, GlobalPoseEstimator)
    ds = PoseDataset(data_root() / args.split, args.subset)
    rows = _measure(est, ds, args.images, args.targets)
    if not rows:
        print(f"{args.split}/{args.subset}: no object detected")
        return 0
    report: dict = {"split": f"{args.split}/{args.subset}", "estimator": args.estimator}
    print(f"{args.estimator} on {args.split}/{args.subset}: {len(rows)} detected objects")
    _tabulate(rows, report)
    if args.json is not None:
        write_json(args.json, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
