"""The BOP round trip: export episodes as a BOP dataset, answer them with a BOP results CSV, grasp
on the CSV's poses, and check that the route changes nothing.

    python studies/bop_round_trip.py [--tier isolated] [--objects all] [--episodes 20] \
        [--workers N] [--out out/bop_round_trip] [--json PATH]

Writes `python -m sim.export_bop` of the episodes to ``--out``/<tier>/export and two CSVs from
the export's own ground truth: ``truth.csv`` (the true poses) and ``turned.csv`` (each target turned
by exactly `TURN_DEG` out of the image plane, about a seeded random direction: the draw of
`noisy-oracle` with fixed errors, `sim.episodes.pose_noise.PoseNoise(mode="fixed")`). Then it grasps
four times on the same scenes: on ``truth.csv`` and with ``oracle``, on ``turned.csv`` and with
that ``noisy-oracle``, and pairs each CSV run with its estimator episode by episode
(`sim.compare`). The CSVs print R with 9 decimals and t in mm with 6, as BOP results do. Every
report is kept in ``--out``/<tier> (each tier its own folder); the table gives success, Wilson
95 % intervals, AR_MSSD and AR_MSPD, the paired comparison and how many episodes had the same
outcome.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TextIO

import numpy as np

from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    add_out_argument,
    add_workers_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.files import atomic_write_json
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_int, check_names
from posegrasp.world.constants import EVAL_SEED_BASE
from posegrasp.world.objects import OBJECT_NAMES
from posegrasp.world.tiers import DEFAULT_TIER, TIERS, check_tier
from sim.compare import compare, load_report
from sim.episodes.pose_noise import PoseNoise, perturb_pose
from sim.episodes.registry import NoisyOracleEstimator
from sim.evaluation import Protocol, evaluate_protocol, poses_record
from sim.evaluation.bop_results import CSV_COLUMNS, read_export
from sim.evaluation.stats import wilson_interval
from sim.export_bop import export_bop

#: The out-of-plane turn of ``turned.csv`` [deg].
TURN_DEG = 10.0


def turn_noise() -> PoseNoise:
    """The fixed error of ``turned.csv`` and of the noisy-oracle it is paired with."""
    return PoseNoise(outplane=np.deg2rad(TURN_DEG), mode="fixed")


def write_csv(root: Path, path: Path, noise: PoseNoise | None) -> int:
    """A BOP results CSV of every object in every image of the export at root, from its
    scene_gt.json; with `noise`, each image's target (its first object) perturbed as the
    noisy-oracle perturbs it in that episode. Returns the rows written."""
    export = read_export(root)
    seed_of = {ids: seed for (_, seed), ids in export.images.items()}
    rows = [",".join(CSV_COLUMNS)]
    for sdir in sorted((root / "test").iterdir()):
        scene_gt = json.loads((sdir / "scene_gt.json").read_text())
        for im_id, objs in sorted(scene_gt.items(), key=lambda kv: int(kv[0])):
            for k, o in enumerate(objs):
                T = np.eye(4)
                T[:3, :3] = np.array(o["cam_R_m2c"], float).reshape(3, 3)
                T[:3, 3] = np.array(o["cam_t_m2c"], float) / 1000.0
                if noise is not None and k == 0:
                    seed = seed_of[(int(sdir.name), int(im_id))]
                    T = perturb_pose(T, noise, noise.rng(seed))
                R = " ".join(f"{v:.9f}" for v in T[:3, :3].ravel())
                t = " ".join(f"{v * 1000.0:.6f}" for v in T[:3, 3])
                rows.append(f"{int(sdir.name)},{int(im_id)},{o['obj_id']},1.0,{R},{t},-1")
    path.write_text("\n".join(rows) + "\n")
    return len(rows) - 1


def _ar(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


def _same(a: dict, b: dict) -> int:
    """Episodes (by object and seed) whose success and failure reason agree."""
    key = {(e["object"], e["seed"]): (e["success"], e["failure_reason"]) for e in a["episodes"]}
    return sum(
        key.get((e["object"], e["seed"])) == (e["success"], e["failure_reason"])
        for e in b["episodes"]
    )


def _parser() -> ArgumentParser:
    p = ArgumentParser(
        prog="python studies/bop_round_trip.py", description=__doc__.split("\n\n")[0]
    )
    p.add_argument(
        "--tier",
        default=DEFAULT_TIER,
        type=arg(check_tier),
        help=f"scene tier, one of: {', '.join(TIERS)}",
    )
    p.add_argument(
        "--objects",
        default=list(OBJECT_NAMES),
        type=arg(check_names, OBJECT_NAMES, "object", "--objects"),
        help="'all' or a comma list",
    )
    p.add_argument(
        "--episodes",
        default=20,
        type=arg(check_int, 1, 10_000, "--episodes", base=int),
        help="episodes per object, 1..10000",
    )
    add_workers_argument(p)
    add_out_argument(p, "the export, the CSVs and every report", "out/bop_round_trip")
    add_json_argument(p, "the table")
    return p


def _export(
    out: Path, objects: list[str], episodes: int, tier: str
) -> tuple[Path, dict[str, Path]]:
    """The episodes exported under `out`/export, and its ``truth.csv`` and ``turned.csv``."""
    root = out / "export"
    export_bop(root, objects, episodes, EVAL_SEED_BASE, tier)
    csvs = {"truth": out / "truth.csv", "turned": out / "turned.csv"}
    write_csv(root, csvs["truth"], None)
    write_csv(root, csvs["turned"], turn_noise())
    return root, csvs


def _grasp(
    out: Path, root: Path, csvs: dict[str, Path], args: argparse.Namespace
) -> dict[str, tuple[Path, dict]]:
    """The four runs on the same scenes, each report kept in `out`: label -> (path, report)."""
    from sim.evaluation.bop_results import BopPosesEstimator

    runs = {
        "oracle": "oracle",
        "truth.csv": BopPosesEstimator(csvs["truth"], root),
        "noisy-oracle": NoisyOracleEstimator(turn_noise()),
        "turned.csv": BopPosesEstimator(csvs["turned"], root),
    }
    reports = {}
    for label, est in runs.items():
        path = out / f"{label}.report.json"
        print(f"{label}: {args.episodes} episodes of {', '.join(args.objects)}", file=sys.stderr)
        protocol = Protocol(args.objects, args.episodes, EVAL_SEED_BASE, args.tier)
        r = evaluate_protocol(protocol, est, workers=args.workers)
        if label.endswith(".csv"):
            r["poses"] = poses_record(est, csvs[label.removesuffix(".csv")], r)
        atomic_write_json(path, r)
        reports[label] = (path, r)
    return reports


def _table(reports: dict[str, tuple[Path, dict]], log: TextIO) -> dict[str, dict]:
    """Per run: its success, Wilson interval and ARs; a CSV run's comparison with its
    estimator's. Printed to `log`."""
    runs = {}
    print(
        f"{'run':<14} {'success':>9} {'wilson 95%':>15} {'AR_MSSD':>8} {'AR_MSPD':>8} "
        f"{'AR_VSD':>7}  paired",
        file=log,
    )
    for label, (path, r) in reports.items():
        g = r["overall"]
        lo, hi = wilson_interval(g["successes"], g["episodes"])
        row = {
            "successes": g["successes"],
            "episodes": g["episodes"],
            "wilson": [lo, hi],
            "ar_mssd": g["ar_mssd"],
            "ar_mspd": g["ar_mspd"],
            "ar_vsd": g["ar_vsd"],
        }
        paired = ""
        if label.endswith(".csv"):
            ref = "oracle" if label == "truth.csv" else "noisy-oracle"
            ref_path, ref_report = reports[ref]
            c = compare(load_report(ref_path), load_report(path))
            row["against"] = ref
            row["same_outcome"] = _same(ref_report, r)
            row["difference"] = c["overall"]["difference"]
            row["mcnemar_p"] = c["overall"]["mcnemar_p"]
            paired = (
                f"against {ref}: same outcome {row['same_outcome']}/{g['episodes']}, "
                f"difference {row['difference']:+.1%}, McNemar p {row['mcnemar_p']:.3f}"
            )
        runs[label] = row
        print(
            f"{label:<14} {g['successes']:>4}/{g['episodes']:<4} [{lo:.3f}, {hi:.3f}] "
            f"{row['ar_mssd']:8.3f} {row['ar_mspd']:8.3f} {_ar(row['ar_vsd']):>7}  {paired}",
            file=log,
        )
    return runs


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    args = _parser().parse_args(argv)
    setup_rendering()
    out, log = args.out / args.tier, summary_stream(args.json)
    root, csvs = _export(out, args.objects, args.episodes, args.tier)
    reports = _grasp(out, root, csvs, args)
    table = {"tier": args.tier, "episodes_per_object": args.episodes, "runs": _table(reports, log)}
    if args.json is not None:
        write_json(args.json, table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
