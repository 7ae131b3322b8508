"""Does a pose net read the object's distance from its crop, or does it guess?

    python studies/distance_baseline.py [--weights perception/weights/posenet_paper.pt]
        [--data paper] [--json PATH]

On the test crops `perception.training.tables` scores (`TEST_CROPS`: ground-truth boxes
perturbed like detections) of a dataset folder (a name under the data root or a path), per
object and over all:

- the net's distance error ``|T - T^| / |T|`` [%], as `tables` reports it;
- the error of the best constant: the one distance per object that minimises the mean relative
  error ``|d - c| / d`` on these very crops (a weighted median, fitted on the test set itself, so
  it favours the baseline). A net that does not beat it has learned nothing about distance;
- the correlation of log predicted with log true distance (0: no information);
- the true distances in object diameters (min..max), the protocol's range;
- over all objects, the median ratio ``|p^| / |p|`` of the predicted to the true position vector
  by how far the predicted viewpoint (the direction of p) is off: a net trained with eq. 7 shortens
  p where it is unsure of the viewpoint.

The `paper` variant sees only the 64x64 crop, resized from a box of any size, so its distance can
only come from perspective: this study shows whether the protocol's distances leave enough of it.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from perception.nets import load_posenet
from perception.training.data.crop_sets import build_crops
from perception.training.evals.posenet_eval import decode_predictions, pose_metrics, predict
from perception.training.tables import TEST_CROPS
from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.errors import AssetError
from posegrasp.core.paths import WEIGHTS_DIR, data_root
from posegrasp.core.runtime import setup_rendering
from posegrasp.world.objects import OBJECT_NAMES, load_object

#: Bins of the viewpoint error [deg] for `norm_ratios`.
VIEW_BINS = ((0, 10), (10, 20), (20, 40), (40, 80), (80, 181))


def best_constant(d: np.ndarray) -> float:
    """The c minimising mean(|d - c| / d): the median of d weighted by 1 / d."""
    order = np.argsort(d)
    w = 1.0 / d[order]
    k = int(np.searchsorted(np.cumsum(w), w.sum() / 2))
    return float(d[order][k])


def constant_errors(d: np.ndarray) -> np.ndarray:
    """Relative errors |d - c| / d of the best constant c (`best_constant`) of distances d."""
    return np.abs(d - best_constant(d)) / d


def rows(
    pred_d: np.ndarray,
    true_d: np.ndarray,
    net_err: np.ndarray,
    diam: np.ndarray,
    const_err: np.ndarray,
) -> dict:
    """The figures of one group of crops (see the module docstring); `const_err` are the
    relative errors of the constant baseline (`constant_errors`, per object)."""
    return {
        "crops": len(true_d),
        "net_distance_pct": float(net_err.mean()),
        "constant_distance_pct": float(100 * const_err.mean()),
        "log_correlation": float(np.corrcoef(np.log(true_d), np.log(pred_d))[0, 1]),
        "diameters": [float((true_d / diam).min()), float((true_d / diam).max())],
    }


def run(weights: Path, root: Path) -> dict[str, dict]:
    """Per object name and "all": `rows` of the test crops of the dataset at root."""
    data = build_crops(root, "test", TEST_CROPS)
    pred = predict(load_posenet(weights), data["crops"], data["cls"], data["scale"])
    dec = decode_predictions(pred, data)
    err = pose_metrics(dec, data)["distance_pct"]
    true_d = np.linalg.norm(data["T_C_O"][:, :3, 3], axis=1)
    pred_d = np.linalg.norm(dec["T_C_O"][:, :3, 3], axis=1)
    diam = np.array([load_object(OBJECT_NAMES[c]).diameter for c in data["cls"]])
    out, const = {}, np.zeros(len(true_d))
    for c in sorted(set(data["cls"].tolist())):  # class index c is OBJECT_NAMES[c]
        s = data["cls"] == c
        const[s] = constant_errors(true_d[s])
        out[OBJECT_NAMES[c]] = rows(pred_d[s], true_d[s], err[s], diam[s], const[s])
    # Over all objects, each object keeps its own constant.
    out["all"] = rows(pred_d, true_d, err, diam, const)
    out["all"]["norm_ratio_by_viewpoint_error"] = norm_ratios(data["p"], pred["p"])
    return out


def norm_ratios(p: np.ndarray, p_hat: np.ndarray) -> dict[str, dict]:
    """Median |p^| / |p| and count per bin of the angle between p^ and p [deg] (`VIEW_BINS`)."""
    n, n_hat = np.linalg.norm(p, axis=1), np.linalg.norm(p_hat, axis=1)
    ang = np.degrees(np.arccos(np.clip(np.sum(p * p_hat, axis=1) / (n * n_hat), -1.0, 1.0)))
    out = {}
    for lo, hi in VIEW_BINS:
        s = (ang >= lo) & (ang < hi)
        if s.any():
            out[f"{lo}-{hi}"] = {"crops": int(s.sum()), "median": float(np.median(n_hat[s] / n[s]))}
    return out


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(
        prog="python studies/distance_baseline.py", description=__doc__.split("\n\n")[0]
    )
    p.add_argument(
        "--weights",
        type=Path,
        default=WEIGHTS_DIR / "posenet_paper.pt",
        metavar="PATH",
        help="pose net weights (default: the shipped paper net)",
    )
    p.add_argument(
        "--data",
        default="paper",
        help="dataset folder: a name under the data root or a path (default: paper)",
    )
    add_json_argument(p, "the figures")
    a = p.parse_args(argv)
    setup_rendering()
    root = Path(a.data) if Path(a.data).is_dir() else data_root() / a.data
    if not (root / "test").is_dir():
        raise AssetError(f"no test split in {root}: give --data a dataset folder with a test split")
    res = run(a.weights, root)
    log = summary_stream(a.json)
    print(
        f"{a.weights.name} on {root}/test (crops as perception.training.tables cuts them)", file=log
    )
    print(
        f"{'object':<8} {'crops':>5} {'net %':>7} {'constant %':>10} {'log corr':>8} "
        f"{'diameters':>11}",
        file=log,
    )
    for name, r in res.items():
        lo, hi = r["diameters"]
        print(
            f"{name:<8} {r['crops']:5d} {r['net_distance_pct']:7.2f} "
            f"{r['constant_distance_pct']:10.2f} {r['log_correlation']:8.2f} "
            f"{lo:5.2f}-{hi:4.2f}",
            file=log,
        )
    ratios = res["all"]["norm_ratio_by_viewpoint_error"]
    by_error = ", ".join(f"{k} deg {v['median']:.2f} ({v['crops']})" for k, v in ratios.items())
    print(f"|p^| / |p| (median) by viewpoint error: {by_error}", file=log)
    if a.json is not None:
        write_json(a.json, {"weights": a.weights.name, "data": str(root), "rows": res})
    return 0


if __name__ == "__main__":
    sys.exit(main())
