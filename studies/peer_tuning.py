"""Tune the classical peers' parameters on training scenes (`perception.peers`).

Renders isolated-tier scenes of every built-in object with seeds below
`posegrasp.world.constants.EVAL_SEED_BASE` (never the held-out ones), runs each point of a
small grid of `FpfhConfig` and `PpfConfig` values around the libraries' sample values on them,
and records, per point, how many poses are correct (MSSD below a tenth of the diameter, as
`sim.episodes.episode` judges), the median rotation and translation errors and the median time per
image. The defaults of `perception.peers` are each grid's chosen point, by the one-standard-error
rule: the fastest point whose count of correct poses is within one binomial standard error of
the most correct (`chosen`; on 48 images the counts of one grid differ by that much by chance).
``--reselect`` applies the rule to the points an earlier record holds, without running them
again. It also records how OpenCV's PPF pose clustering treats two copies of a model at one
position turned apart (`clustering_check`).

    python studies/peer_tuning.py --json studies/peer_tuning.json

``--methods fpfh-icp`` sweeps one grid alone; with ``--json`` naming an earlier record of the
same scenes, the other methods' entries are kept from it.
"""

from __future__ import annotations

import itertools
import json
import math
import statistics
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np

from perception.metrics import mssd, rotation_error_sym_deg
from posegrasp.core.cli import ArgumentParser, add_json_argument, command, write_json
from posegrasp.core.contract import Observation
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.progress import progress_bar
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_int, check_names
from posegrasp.world.constants import EVAL_SEED_BASE
from posegrasp.world.objects import OBJECT_NAMES, load_object

#: The training seeds the scenes are drawn from (below `EVAL_SEED_BASE`).
SEED_START = 1000
#: What the scenes' observations hold: the peers need the depth image.
OBS_MODE = "rgbd"
#: The grids: each key a config field, each value the values tried (the first is the sample's).
FPFH_GRID: dict[str, tuple] = {
    "voxel_m": (0.005, 0.004, 0.007),
    "confidence": (0.999, 0.9999),
    "mutual_filter": (False, True),
    "restarts": (1, 3),
}
#: Every scene point as a reference (scene_sample_step 1.0) takes several times as long per
#: image and found no more poses on training scenes once the clouds were in diameters.
PPF_GRID: dict[str, tuple] = {
    "sampling_step": (0.1, 0.07),
    "scene_sample_step": (0.2,),
    "hypotheses": (2, 5, 10),
}
#: Each method's grid.
GRIDS = {"fpfh-icp": FPFH_GRID, "ppf": PPF_GRID}


def scenes(per_object: int) -> list[tuple[Observation, np.ndarray]]:
    """The isolated training scenes: (observation with depth, true T_C_O) per object and seed."""
    from sim.episodes.episode import Episode, EpisodeConfig

    out = []
    for obj, i in itertools.product(OBJECT_NAMES, range(per_object)):
        assert SEED_START + i < EVAL_SEED_BASE
        ep = Episode(obj, SEED_START + i, EpisodeConfig(obs_mode=OBS_MODE))
        out.append((ep.observe(), ep.T_C_O_true.copy()))
        ep.close()
    return out


def score(estimator: Any, views: list[tuple[Observation, np.ndarray]]) -> dict[str, Any]:
    """Correct poses, median errors and time per image of one estimator on the scenes (the
    first image of each object, which trains or samples its model, is timed apart)."""
    from sim.episodes.episode import object_symmetries

    correct, rot, trans, times, first = 0, [], [], [], []
    seen: set[str] = set()
    for obs, T_true in views:
        t0 = time.perf_counter()
        est = estimator.estimate(obs)
        (first if obs.object not in seen else times).append(time.perf_counter() - t0)
        seen.add(obs.object)
        if est.T_C_O is None:
            rot.append(180.0)
            trans.append(1.0)
            continue
        model = load_object(obs.object)
        syms = object_symmetries(model)
        pts = np.asarray(model.mesh.vertices)
        R, t, R_gt, t_gt = est.T_C_O[:3, :3], est.T_C_O[:3, 3], T_true[:3, :3], T_true[:3, 3]
        rot.append(rotation_error_sym_deg(R, R_gt, syms))
        trans.append(float(np.linalg.norm(t - t_gt)))
        correct += mssd(R, t, R_gt, t_gt, pts, syms) < 0.1 * model.diameter
    return {
        "correct": correct,
        "images": len(views),
        "rotation_deg_median": statistics.median(rot),
        "translation_mm_median": 1000 * statistics.median(trans),
        "time_s_median": statistics.median(times),
        "first_image_s_median": statistics.median(first),
    }


def chosen(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The one-standard-error rule: of the points whose correct count is within one binomial
    standard error of the most correct, the fastest."""
    top = max(r["correct"] for r in rows)
    n = rows[0]["images"]
    se = math.sqrt(top * (n - top) / n)  # in poses: n * sqrt(p (1 - p) / n)
    near = [r for r in rows if r["correct"] >= top - se]
    return min(near, key=lambda r: (r["time_s_median"], -r["correct"]))


def _config(method: str) -> tuple[type, type]:
    """`method`'s config and registration stage."""
    if method == "ppf":
        from perception.peers.ppf import PpfConfig, PpfRegistration

        return PpfConfig, PpfRegistration
    from perception.peers.fpfh import FpfhConfig, FpfhRegistration

    return FpfhConfig, FpfhRegistration


def chosen_record(method: str, grid: dict[str, Any], rows: list[dict[str, Any]]) -> dict[str, Any]:
    """A grid's record: its points (most correct first) and the chosen point's whole config."""
    Config, _ = _config(method)
    rows = sorted(rows, key=lambda r: (-r["correct"], r["time_s_median"]))
    pick = chosen(rows)
    return {
        "grid": {k: list(v) for k, v in grid.items()},
        "points": rows,
        "rule": "one standard error: the fastest point within one binomial SE of the most correct",
        "chosen": pick["values"],
        "best": asdict(replace(Config(), **pick["values"])),
    }


def sweep(method: str, grid: dict[str, tuple], views: list) -> dict[str, Any]:
    """Every point of `grid` for `method` (``fpfh-icp`` or ``ppf``), and the chosen one."""
    from perception.peers.estimator import PeerEstimator
    from sim.episodes.registry import check_depth

    check_depth(method, OBS_MODE)
    Config, Stage = _config(method)
    points = [dict(zip(grid, values, strict=True)) for values in itertools.product(*grid.values())]
    rows = []
    for values in progress_bar(points, desc=method, unit="config"):
        config = replace(Config(), **values)
        rows.append({"values": values} | score(PeerEstimator(method, Stage(config)), views))
    return chosen_record(method, grid, rows)


def clustering_check() -> dict[str, Any]:
    """Two copies of the pistol's model at one position, the second turned 90 deg about z:
    the poses OpenCV's PPF detector returns for them (rotation errors to each copy [deg])."""
    import cv2

    from perception.metrics import rotation_error_deg
    from perception.peers.points import model_surface
    from posegrasp.core.transforms import rot_z

    model = load_object("pistol")
    pts, normals = model_surface(model, 5000, 0)
    pc = np.hstack([pts, normals]).astype(np.float32)
    detector = cv2.ppf_match_3d.PPF3DDetector(0.1, 0.05, 30)
    detector.trainModel(pc)
    poses = [np.eye(4), np.eye(4)]
    poses[1][:3, :3] = rot_z(np.pi / 2)
    for T in poses:
        T[:3, 3] = (0.1, -0.05, 0.8)
    scene = np.vstack([cv2.ppf_match_3d.transformPCPose(pc, T) for T in poses])
    results = detector.match(scene, 0.2, 0.1)
    return {
        "poses_returned": len(results),
        "rotation_error_to_copies_deg": [
            [round(rotation_error_deg(np.asarray(r.pose)[:3, :3], T[:3, :3]), 2) for T in poses]
            for r in results[:3]
        ],
    }


@command
def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog="python studies/peer_tuning.py", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--per-object",
        type=arg(check_int, 1, 100, "--per-object", base=int),
        default=8,
        help="training scenes per object (default 8)",
    )
    p.add_argument(
        "--methods",
        type=arg(check_names, tuple(GRIDS), "method", "--methods"),
        default=list(GRIDS),
        help=f"a comma list of {', '.join(GRIDS)} (default both)",
    )
    p.add_argument(
        "--reselect",
        action="store_true",
        help="apply the rule to the points the --json record holds, running nothing",
    )
    add_json_argument(p, "the grids' figures and the chosen values")
    args = p.parse_args(argv)
    if args.reselect:
        return _reselect(args.json)
    report: dict[str, Any] = {
        "tier": "isolated",
        "seeds": [SEED_START, SEED_START + args.per_object - 1],
        "objects": list(OBJECT_NAMES),
    }
    if args.json and set(args.methods) != set(GRIDS) and Path(args.json).exists():
        earlier = json.loads(Path(args.json).read_text())
        if {k: earlier.get(k) for k in report} != report:
            raise InvalidArgumentError(
                f"{args.json} records other scenes ({earlier.get('seeds')}); sweep every method "
                "or write another file"
            )
        report = earlier
    setup_rendering(threads=2)
    views = scenes(args.per_object)
    for method in args.methods:
        report[method] = sweep(method, GRIDS[method], views)
    if "ppf" in args.methods:
        report["clustering_check"] = clustering_check()
    for method in args.methods:
        _say_chosen(method, report[method])
    if "ppf" in args.methods:
        print(f"ppf clustering check: {report['clustering_check']}")
    if args.json:
        write_json(args.json, report)
    return 0


def _say_chosen(method: str, record: dict[str, Any]) -> None:
    pick = next(r for r in record["points"] if r["values"] == record["chosen"])
    top = record["points"][0]
    print(
        f"{method}: chosen {pick['values']}: {pick['correct']}/{pick['images']} correct "
        f"(the most: {top['correct']}), median {pick['rotation_deg_median']:.2f} deg, "
        f"{pick['translation_mm_median']:.2f} mm, {pick['time_s_median']:.2f} s per image"
    )


def _reselect(path: str | None) -> int:
    """The rule applied again to the record at `path`, which is rewritten."""
    if not path or path == "-" or not Path(path).exists():
        raise InvalidArgumentError("--reselect needs --json naming an existing record")
    report = json.loads(Path(path).read_text())
    for method in GRIDS:
        if method in report:
            grid, rows = report[method]["grid"], report[method]["points"]
            report[method] = chosen_record(method, grid, rows)
            _say_chosen(method, report[method])
    write_json(path, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
