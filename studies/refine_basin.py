"""The render-and-compare refiner's basin: from how far off does it land on the truth?

    python studies/refine_basin.py [--split headcam_any-pose] [--subset val] [--images 100]
        [--passes 2] [--json PATH]

For every image's target (the split's requested object) that the shipped detector finds, the
refiner (`perception.refine.PoseRefiner`, `--passes` runs as `hybrid-global` does) starts from
the true pose turned by 5, 10, 15, 20, 30 and 45 deg about a random axis (seeded per image) and
refines against the detector's mask and the image. Prints, per start angle, the share of final
rotation errors below 5 deg and their median: the angle up to which the codebook's hypotheses
must reach.
"""

from __future__ import annotations

import sys

import numpy as np

from perception.hybrid import HybridPoseEstimator, detect_target
from perception.metrics import rotation_error_deg
from perception.refine import PoseRefiner
from perception.training.data.dataset import PoseDataset
from posegrasp.core.cli import ArgumentParser, add_json_argument, command, write_json
from posegrasp.core.contract import Observation
from posegrasp.core.paths import data_root
from posegrasp.core.progress import progress_bar
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.transforms import axis_angle
from posegrasp.core.validate import arg, check_int

ANGLES_DEG = (5.0, 10.0, 15.0, 20.0, 30.0, 45.0)


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(prog="python studies/refine_basin.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--split", default="headcam_any-pose", help="dataset folder under the data root")
    p.add_argument("--subset", default="val", help="the split's subset (default val)")
    p.add_argument(
        "--images",
        type=arg(check_int, 1, 100000, "--images", base=int),
        default=100,
        help="the first N images of the subset, 1..100000 (default 100)",
    )
    p.add_argument(
        "--passes",
        type=arg(check_int, 1, 10, "--passes", base=int),
        default=2,
        help="refiner passes from each start, 1..10 (default 2, as hybrid-global runs)",
    )
    add_json_argument(p, "the final errors per start angle")
    args = p.parse_args(argv)
    setup_rendering(threads=1)
    hybrid = HybridPoseEstimator.from_weights()
    refiner = PoseRefiner()
    ds = PoseDataset(data_root() / args.split, args.subset)
    final: dict[float, list[float]] = {a: [] for a in ANGLES_DEG}
    for i in progress_bar(range(min(args.images, len(ds))), desc="basin", leave=False):
        s = ds[i]
        name = s.extra.get("target", s.objects[0].name)
        gt = next(o for o in s.objects if o.name == name)
        target = detect_target(hybrid, Observation(s.rgb, s.K, np.eye(4), name, s.seed))
        if target.best is None:
            continue
        rng = np.random.default_rng(i)
        occluder = target.occluder()
        for a in ANGLES_DEG:
            axis = rng.normal(size=3)
            T = gt.T_C_O.copy()
            T[:3, :3] = axis_angle(axis / np.linalg.norm(axis), np.deg2rad(a)) @ T[:3, :3]
            for _ in range(args.passes):
                T, _ = refiner.refine(name, T, s.K, target.best.mask, s.rgb, occluder)
            final[a].append(rotation_error_deg(T[:3, :3], gt.T_C_O[:3, :3]))
    print(
        f"{args.split}/{args.subset}: {len(final[ANGLES_DEG[0]])} detected targets, "
        f"{args.passes} refiner pass(es)"
    )
    res = {}
    for a, e in final.items():
        e = np.array(e)
        res[str(a)] = {
            "below_5_deg_pct": float(100 * np.mean(e < 5)),
            "median": float(np.median(e)),
        }
        print(
            f"  start {a:4.0f} deg off: final < 5 deg {res[str(a)]['below_5_deg_pct']:5.1f} %, "
            f"median {res[str(a)]['median']:5.2f} deg"
        )
    if args.json is not None:
        write_json(args.json, {"passes": args.passes, "angles": res})
    return 0


if __name__ == "__main__":
    sys.exit(main())
