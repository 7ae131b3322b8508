"""What the mask costs the pose: refined from the true pose, how far does the fit drift?

    python studies/mask_drift.py [--split headcam_hard] [--subset test] [--images 300]
        [--json PATH]

For every image's target (the split's requested object) that the tiers' detector finds (at
`hybrid-global`'s target score), the render-and-compare refiner (two runs, as `hybrid-global`
runs its best starts) starts from the *true* pose and refines against the image and one of three
masks: the detector's, the mask net's redrawing of it (`perception.mask_net`) and the true
visible mask. A perfect mask leaves the truth where it is; how far each mask moves it along the
viewing ray and in rotation is the error the mask alone causes. Also prints each mask's IoU with
the true visible mask and the mask net's time per mask.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from perception.global_pose import GlobalPoseEstimator
from perception.hybrid import detect_target
from perception.metrics import mask_iou, rotation_error_deg
from perception.stages import Verify
from perception.training.data.dataset import PoseDataset
from posegrasp.core.cli import ArgumentParser, add_json_argument, command, write_json
from posegrasp.core.contract import Observation
from posegrasp.core.paths import data_root
from posegrasp.core.progress import progress_bar
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_int

MASKS = ("detector", "mask net", "truth")


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(prog="python studies/mask_drift.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--split", default="headcam_hard", help="dataset folder under the data root")
    p.add_argument("--subset", default="test", help="the split's subset (default test)")
    p.add_argument(
        "--images",
        type=arg(check_int, 1, 100000, "--images", base=int),
        default=300,
        help="the first N images of the subset, 1..100000 (default 300)",
    )
    add_json_argument(p, "the drift and IoU per mask")
    args = p.parse_args(argv)
    setup_rendering(threads=1)
    est = GlobalPoseEstimator.from_weights()
    verify, cfg = est.stage("verify"), est.config
    assert isinstance(verify, Verify)
    refiner = verify.refiner
    ds = PoseDataset(data_root() / args.split, args.subset)
    ray: dict[str, list[float]] = {m: [] for m in MASKS}
    rot: dict[str, list[float]] = {m: [] for m in MASKS}
    iou: dict[str, list[float]] = {m: [] for m in MASKS[:2]}
    spent = []
    for i in progress_bar(range(min(args.images, len(ds))), desc="drift", mininterval=5):
        s = ds[i]
        name = s.extra.get("target", s.objects[0].name)
        gt = next(o for o in s.objects if o.name == name)
        obs = Observation(s.rgb, s.K, np.eye(4), name, s.seed)
        target = detect_target(est.hybrid, obs, cfg.detection.target_score, False)
        if target.best is None:
            continue
        t0 = time.perf_counter()
        sharp = est.sharpened(target.best, s.rgb).mask
        spent.append(time.perf_counter() - t0)
        occluder = target.occluder()
        truth = gt.mask_visib
        for m, mask in zip(MASKS, (target.best.mask, sharp, truth), strict=True):
            prepared = refiner.prepare(s.K, mask, s.rgb, occluder)
            T = gt.T_C_O.copy()
            for _ in range(2):
                T, _ = refiner.refine_prepared(name, T, prepared)
            ray[m].append(1000 * (np.linalg.norm(T[:3, 3]) - np.linalg.norm(gt.T_C_O[:3, 3])))
            rot[m].append(rotation_error_deg(T[:3, :3], gt.T_C_O[:3, :3]))
            if m in iou:
                iou[m].append(mask_iou(mask, truth))
    n = len(ray[MASKS[0]])
    print(f"{args.split}/{args.subset}: {n} detected targets, refined twice from the true pose")
    res = {}
    for m in MASKS:
        r, a = np.abs(ray[m]), np.array(rot[m])
        res[m] = {
            "ray_mean_mm": float(r.mean()),
            "ray_over_20mm_pct": float(100 * np.mean(r > 20)),
            "ray_over_40mm_pct": float(100 * np.mean(r > 40)),
            "rotation_mean_deg": float(a.mean()),
            "mask_iou": float(np.mean(iou[m])) if m in iou else 1.0,
        }
        print(
            f"  {m:9s} mask IoU {res[m]['mask_iou']:.3f}: along the ray {r.mean():5.1f} mm "
            f"(> 20 mm {res[m]['ray_over_20mm_pct']:4.1f} %, > 40 mm "
            f"{res[m]['ray_over_40mm_pct']:4.1f} %), rotation {a.mean():5.2f} deg"
        )
    ms = 1000 * float(np.median(spent)) if spent else 0.0
    print(f"  mask net: {ms:.1f} ms per mask (median)")
    if args.json is not None:
        write_json(
            args.json,
            {"split": f"{args.split}/{args.subset}", "targets": n, "masks": res, "mask_net_ms": ms},
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
