"""The ablation that chose `hybrid-global`'s verification: hypotheses per detection and the weights
of the score, measured on a validation split (never on a test split).

    python studies/global_ablation.py [--split headcam_any-pose] [--subset val] [--images 150]
        [--json PATH]
    python studies/global_ablation.py --keeps 0,1,2,3,4 [--images 150]

For every image's target detection (the shipped detector; the target is the split's requested
object, ``target`` in the image record, else its first object), every start of
`perception.global_pose.GlobalPoseEstimator.verify` (the nets' pose and the codebook's 12
hypotheses) is refined and scored once, and each refined pose's rotation error is recorded. The
ablation then replays the choice offline:

- the verification score's weights (colour correlation x edge agreement): mean and median
  rotation error of the chosen pose and its share over 15 deg;
- K, the codebook hypotheses kept (the first K by codebook score, plus the nets' pose): the
  chosen pose's errors and those of the best of the K (what a perfect score would pick);
- a resting prior (the camera pose's gravity and the object's resting poses): starts further
  than a tilt from every resting pose are passed over.

With `--keeps`, it measures instead the verification that refines every start once, scores them and
gives the second refiner run only to the best few (`GlobalConfig.refinement.keep_after_first`; 0 is
every start twice); with `--screens`, a first run of fewer refiner steps for every start
(`GlobalConfig.refinement.screen_iterations`); with `--tilts`, the resting prior
(`GlobalConfig.gravity.tilt_deg`, with the image's camera pose); with `--snaps`, how many of the
best starts are snapped onto their resting poses (`GlobalConfig.gravity.snap_candidates`), with
`--snap-steps`, the refiner steps of a snapped start's run
(`GlobalConfig.gravity.snap_iterations`); with `--appearances` and `--edge-weights`, the
verification score's weights (`GlobalConfig.scoring.appearance_weight`,
`GlobalConfig.scoring.edge_weight`) with the rest as shipped; with `--ks`, the codebook hypotheses
per detection (`GlobalConfig.codebook.hypotheses`); with `--rests`, the extra codebook hypotheses
among the templates that could be resting (`GlobalConfig.codebook.resting_hypotheses`); with
`--passes`, the full refiner runs of the best few (`GlobalConfig.refinement.passes`); with
`--grows`, the codebook's extra framings of a mask another detection touches
(`GlobalConfig.codebook.occluded_grow`); with `--looks`, the second look
(`GlobalConfig.second_look.hypotheses` more hypotheses when the best score is below
`GlobalConfig.second_look.below`): for each setting, the chosen pose's rotation errors, those of
the best verified start, the chosen translation's error and the verification's time per detection
(median, one thread), each setting on the same images with the same detections.

    python studies/global_ablation.py --split headcam_hard --grows "none;1.4;1.5;1.3,1.6"
    python studies/global_ablation.py --split headcam_hard --tilts none,5,10,20
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from perception.global_pose import GlobalConfig, GlobalPoseEstimator
from perception.hybrid import detect_target
from perception.metrics import rotation_error_deg
from perception.support import snap_to_resting
from perception.training.data.dataset import PoseDataset
from posegrasp.core.cli import ArgumentParser, add_json_argument, command, write_json
from posegrasp.core.contract import Observation
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.paths import data_root
from posegrasp.core.progress import progress_bar
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_float_list, check_int
from posegrasp.world.objects import load_object

APPEARANCE = (0.0, 0.05, 0.1, 0.2)
EDGES = (0.0, 0.1, 0.2, 0.3, 0.5, 1.0)
KS = (0, 1, 2, 4, 6, 8, 12)
TILTS = (5.0, 10.0, 20.0, 30.0)


def check_grow_lists(spec: str) -> list[tuple[float, ...]]:
    """';'-separated comma lists of growth factors in (1, 4], or 'none' (the mask's own box)."""
    out = []
    for group in str(spec).split(";"):
        if group.strip() == "none":
            out.append(())
            continue
        try:
            g = tuple(float(v) for v in group.split(","))
        except ValueError:
            g = ()
        if not g or not all(1 < v <= 4 for v in g):
            raise InvalidArgumentError(
                f"--grows takes ';'-separated comma lists of factors in (1, 4] or 'none', "
                f"got {group!r}"
            )
        out.append(g)
    return out


def check_tilt_list(spec: str) -> list[float | None]:
    """A comma list of angles in (0, 180) [deg] or ``none``."""
    out: list[float | None] = []
    for v in str(spec).split(","):
        if v.strip() == "none":
            out.append(None)
            continue
        try:
            t = float(v)
        except ValueError:
            t = float("nan")
        if not 0 < t < 180:
            raise InvalidArgumentError(
                f"--tilts takes a comma list of angles in (0, 180) or 'none', got {v!r}"
            )
        out.append(t)
    return out


def check_int_list(spec: str, hi: int = 13, flag: str = "--keeps", lo: int = 0) -> list[int]:
    """A comma list of whole numbers lo..hi."""
    out = []
    for v in str(spec).split(","):
        try:
            out.append(int(v))
        except ValueError:
            out.append(v)  # refused below with the valid range
    return [check_int(v, lo, hi, flag) for v in out]


def configured(settings: dict[str, Any]) -> GlobalConfig:
    """The shipped `GlobalConfig` with the given settings changed, each named by its path in the
    nested config (``"codebook.hypotheses"``, ``"second_look.below"``); a ``gravity.tilt_deg``
    of None leaves gravity (and the support it needs) out, a ``second_look.hypotheses`` of 0 the
    second look."""
    cfg = GlobalConfig()
    groups: dict[str, dict] = {}
    for path, value in settings.items():
        group, key = path.split(".")
        groups.setdefault(group, {})[key] = value
    changes = {}
    for group, values in groups.items():
        if (group, values.get("tilt_deg", 0)) == ("gravity", None) or (
            group == "second_look" and values.get("hypotheses") == 0
        ):
            changes[group] = None
        else:
            changes[group] = dataclasses.replace(getattr(cfg, group), **values)
    if changes.get("gravity", cfg.gravity) is None:
        changes["support"] = None  # the neighbours' support is found from resting poses
    return dataclasses.replace(cfg, **changes)


def check_snap_list(spec: str) -> list[int]:
    """A comma list of snapped starts 0..13."""
    return check_int_list(spec, 13, "--snaps")


def check_screen_list(spec: str) -> list[int]:
    """A comma list of refiner steps 0..6."""
    return check_int_list(spec, 6, "--screens")


def check_snap_steps(spec: str) -> list[int]:
    """A comma list of refiner steps 1..6."""
    return check_int_list(spec, 6, "--snap-steps", lo=1)


def check_k_list(spec: str) -> list[int]:
    """A comma list of codebook hypotheses 1..48."""
    return check_int_list(spec, 48, "--ks", lo=1)


def check_rest_list(spec: str) -> list[int]:
    """A comma list of resting hypotheses 0..24."""
    return check_int_list(spec, 24, "--rests")


def check_passes(spec: str) -> list[int]:
    """A comma list of refiner runs 1..3."""
    return check_int_list(spec, 3, "--passes", lo=1)


def check_looks(spec: str) -> list[tuple[int, float, int]]:
    """A comma list of ``N@S`` or ``N+R@S``: N (0..36) more hypotheses, and R (0..36) resting
    ones, when the best score is below S."""
    out = []
    for v in str(spec).split(","):
        n, _, below = v.partition("@")
        n, _, rest = n.partition("+")
        try:
            look = (int(n), float(below), int(rest or 0))
        except ValueError:
            look = (-1, float("nan"), -1)
        if not (0 <= look[0] <= 36 and 0 <= look[2] <= 36 and np.isfinite(look[1])):
            raise InvalidArgumentError(
                "--looks takes a comma list of N@S or N+R@S (N, R in 0..36, S a score, e.g. "
                f"8@1.1), got {v!r}"
            )
        out.append(look)
    return out


def record(split: str, subset: str, images: int) -> list[dict]:
    """Per target: each start's rank, IoU, colour and edge scores and rotation error [deg]."""
    est = GlobalPoseEstimator.from_weights()
    ds = PoseDataset(data_root() / split, subset)
    out = []
    for i in progress_bar(range(min(images, len(ds))), desc=f"{split}/{subset}", leave=False):
        s = ds[i]
        name = s.extra.get("target", s.objects[0].name)
        gt = next(o for o in s.objects if o.name == name)
        T_W_C, model = np.asarray(s.extra["T_W_C"], float), load_object(name)
        target = detect_target(
            est.hybrid,
            Observation(s.rgb, s.K, np.eye(4), name, s.seed),
            est.config.detection.target_score,
        )
        if target.best is None:
            out.append({"image": i, "object": name, "detected": False})
            continue
        t0 = time.perf_counter()
        ranked, _ = est.verify(est.sharpened(target.best, s.rgb), s.K, s.rgb, target.occluder())
        starts = sorted(ranked, key=lambda v: v.rank)
        out.append(
            {
                "image": i,
                "object": name,
                "detected": True,
                "ms": (time.perf_counter() - t0) * 1000,
                "starts": [
                    [
                        v.iou,
                        v.appearance,
                        v.edges,
                        rotation_error_deg(v.T_C_O[:3, :3], gt.T_C_O[:3, :3]),
                        snap_to_resting(T_W_C[:3, :3] @ v.T_C_O[:3, :3], model)[2],
                    ]
                    for v in starts
                ],
            }
        )
    return out


def config_sweep(
    split: str, subset: str, images: int, configs: dict[str, GlobalConfig]
) -> list[dict]:
    """Per verification setting: the chosen pose's rotation errors, those of the best of its
    verified starts, its translation error and the verification's time, on the split's first
    `images` target detections (each setting on the same detections)."""
    est = GlobalPoseEstimator.from_weights()
    ds = PoseDataset(data_root() / split, subset)
    cases = []
    for i in progress_bar(range(min(images, len(ds))), desc="detections", leave=False):
        s = ds[i]
        name = s.extra.get("target", s.objects[0].name)
        gt = next(o for o in s.objects if o.name == name)
        target = detect_target(
            est.hybrid,
            Observation(s.rgb, s.K, np.eye(4), name, s.seed),
            est.config.detection.target_score,
        )
        if target.best is not None:
            R_W_C = np.asarray(s.extra["T_W_C"], float)[:3, :3] if "T_W_C" in s.extra else None
            det = est.sharpened(target.best, s.rgb)
            cases.append((det, s.K, s.rgb, target.occluder(), gt.T_C_O, R_W_C))
    out = []
    for label, cfg in configs.items():
        est = est.with_config(cfg)
        errors, best, shift, ms, looks = [], [], [], [], 0
        for det, K, rgb, occluder, T_true, R_W_C in progress_bar(cases, desc=label, leave=False):
            t0 = time.perf_counter()
            ranked, times = est.verify(det, K, rgb, occluder, R_W_C)
            ms.append((time.perf_counter() - t0) * 1000)
            looks += "second_look" in times
            errors.append(rotation_error_deg(ranked[0].T_C_O[:3, :3], T_true[:3, :3]))
            best.append(min(rotation_error_deg(v.T_C_O[:3, :3], T_true[:3, :3]) for v in ranked))
            t, t_true = ranked[0].T_C_O[:3, 3], T_true[:3, 3]
            shift.append(100 * np.linalg.norm(t - t_true) / np.linalg.norm(t_true))
        e, b = np.array(errors), np.array(best)
        out.append(
            {
                "setting": label,
                "config": dataclasses.asdict(cfg),
                "second_look_pct": 100 * looks / max(1, len(cases)),
                "detections": len(cases),
                "mean": float(e.mean()),
                "median": float(np.median(e)),
                "over_15_pct": float(100 * (e > 15).mean()),
                "best_mean": float(b.mean()),
                "best_over_15_pct": float(100 * (b > 15).mean()),
                "translation_pct": float(np.mean(shift)),
                "verify_ms_median": float(np.median(ms)),
                "verify_ms_p90": float(np.percentile(ms, 90)),
            }
        )
    return out


def _choose(
    rows: list[dict], wa: float, we: float, k: int, max_tilt: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Rotation errors of the chosen start and of the best of the first k + 1 starts; with
    `max_tilt`, starts further than that from every resting pose [deg] are passed over while
    any start is within it."""
    chosen, best = [], []
    for r in rows:
        c = np.array(r["starts"])[: k + 1]
        score = c[:, 0] + wa * c[:, 1] + we * c[:, 2]
        if max_tilt is not None and (c[:, 4] <= max_tilt).any():
            score = np.where(c[:, 4] <= max_tilt, score, -np.inf)
        chosen.append(c[np.argmax(score), 3])
        best.append(c[:, 3].min())
    return np.array(chosen), np.array(best)


def ablate(rows: list[dict]) -> dict:
    """The weight grid at K = 12 and the K sweep at the chosen weights."""
    found = [r for r in rows if r["detected"]]
    weights = []
    for wa, we in itertools.product(APPEARANCE, EDGES):
        e, _ = _choose(found, wa, we, 12)
        weights.append(
            {
                "appearance": wa,
                "edges": we,
                "mean": float(e.mean()),
                "median": float(np.median(e)),
                "over_15_pct": float(100 * (e > 15).mean()),
            }
        )
    ks = []
    for k in KS:
        e, b = _choose(found, 0.05, 0.3, k)
        ks.append(
            {
                "k": k,
                "chosen_mean": float(e.mean()),
                "chosen_over_15_pct": float(100 * (e > 15).mean()),
                "best_mean": float(b.mean()),
                "best_over_15_pct": float(100 * (b > 15).mean()),
            }
        )
    tilts = []
    for t in TILTS:
        e, _ = _choose(found, 0.05, 0.3, 12, t)
        tilts.append(
            {
                "max_tilt_deg": t,
                "mean": float(e.mean()),
                "median": float(np.median(e)),
                "over_15_pct": float(100 * (e > 15).mean()),
            }
        )
    return {
        "targets": len(rows),
        "detected": len(found),
        "weights": weights,
        "k": ks,
        "resting_prior": tilts,
        "median_verify_ms": float(np.median([r["ms"] for r in found])),
    }


def _named(name: str, fmt=str) -> Callable[[Any], str]:
    """Labels a setting: ``name value`` (``none`` for None or an empty list)."""
    return lambda v: f"{name} {fmt(v) if v not in (None, ()) else 'none'}"


#: The settings --FLAG sweeps: the path of its setting in `GlobalConfig` (or paths, each value
#: then a tuple), parser, metavar, help, label of a value.
SWEEPS: dict[str, tuple[str | tuple[str, ...], Callable, str, str, Callable[[Any], str]]] = {
    "keeps": (
        "refinement.keep_after_first",
        check_int_list,
        "LIST",
        "comma list of 0..13",
        _named("keep"),
    ),
    "grows": (
        "codebook.occluded_grow",
        check_grow_lists,
        "LISTS",
        "';'-separated comma lists of factors 1..4, 'none' for the mask's own box alone",
        _named("grow", lambda g: ",".join(map(str, g))),
    ),
    "screens": (
        "refinement.screen_iterations",
        check_screen_list,
        "LIST",
        "comma list of 0..6, 0 for the refiner's full run",
        _named("screen"),
    ),
    "snaps": (
        "gravity.snap_candidates",
        check_snap_list,
        "LIST",
        "comma list of 0..13, 0: no snap",
        _named("snap"),
    ),
    "snap_steps": (
        "gravity.snap_iterations",
        check_snap_steps,
        "LIST",
        "comma list of 1..6",
        _named("snap steps"),
    ),
    "appearances": (
        "scoring.appearance_weight",
        lambda spec: check_float_list(spec, 0.0, 10.0, "--appearances"),
        "LIST",
        "comma list of weights in [0, 10]",
        _named("appearance"),
    ),
    "edge_weights": (
        "scoring.edge_weight",
        lambda spec: check_float_list(spec, 0.0, 10.0, "--edge-weights"),
        "LIST",
        "comma list of weights in [0, 10]",
        _named("edges"),
    ),
    "ks": (
        "codebook.hypotheses",
        check_k_list,
        "LIST",
        "comma list of 1..48",
        _named("K"),
    ),
    "rests": (
        "codebook.resting_hypotheses",
        check_rest_list,
        "LIST",
        "comma list of 0..24",
        _named("rests"),
    ),
    "passes": (
        "refinement.passes",
        check_passes,
        "LIST",
        "comma list of 1..3",
        _named("passes"),
    ),
    "looks": (
        ("second_look.hypotheses", "second_look.below", "second_look.resting"),
        check_looks,
        "LIST",
        "comma list of N@S or N+R@S: N more hypotheses, R resting ones, when the best score is "
        "below S",
        lambda v: f"look {v[0]}+{v[2]}@{v[1]:g}",
    ),
    "tilts": (
        "gravity.tilt_deg",
        check_tilt_list,
        "LIST",
        "comma list of degrees in (0, 180), 'none' for no resting prior",
        _named("tilt"),
    ),
}


def _parser() -> ArgumentParser:
    p = ArgumentParser(
        prog="python studies/global_ablation.py", description=__doc__.split("\n\n")[0]
    )
    p.add_argument("--split", default="headcam_any-pose", help="dataset folder under the data root")
    p.add_argument("--subset", default="val", help="the split's subset (default val)")
    p.add_argument(
        "--images",
        type=arg(check_int, 1, 100000, "--images", base=int),
        default=150,
        help="the first N images of the subset, 1..100000 (default 150)",
    )
    add_json_argument(p, "every start's scores and the ablation")
    for flag, (path, check, metavar, text, _) in SWEEPS.items():
        paths = ", ".join(path) if isinstance(path, tuple) else path
        p.add_argument(
            f"--{flag.replace('_', '-')}",
            type=arg(check),
            default=None,
            metavar=metavar,
            help=f"instead, measure these {paths} settings ({text})",
        )
    p.add_argument(
        "--replay",
        type=Path,
        default=None,
        metavar="PATH",
        help="replay the starts recorded in an earlier --json instead of measuring",
    )
    return p


def _sweep(args: argparse.Namespace, flag: str) -> None:
    """Measure, print and (with ``--json``) write the settings ``--FLAG`` asks for."""
    setup_rendering(threads=1)
    path, _, _, _, label = SWEEPS[flag]
    configs = {}
    for v in getattr(args, flag):
        pairs = zip(path, v, strict=True) if isinstance(path, tuple) else [(path, v)]
        configs[label(v)] = configured(dict(pairs))
    sweep = config_sweep(args.split, args.subset, args.images, configs)
    print(f"{args.split}/{args.subset}, {sweep[0]['detections']} detections:")
    for k in sweep:
        print(
            f"  {k['setting']:16s}: mean {k['mean']:6.2f}  median {k['median']:5.2f}  "
            f"> 15 deg {k['over_15_pct']:5.1f} %  (best start {k['best_mean']:6.2f}, "
            f"{k['best_over_15_pct']:5.1f} %)  translation {k['translation_pct']:5.2f} %  "
            f"verify {k['verify_ms_median']:.0f} ms (p90 {k['verify_ms_p90']:.0f}), "
            f"second look {k['second_look_pct']:.0f} %"
        )
    if args.json is not None:
        write_json(args.json, {"sweep": sweep})


def _print_ablation(res: dict, where: str) -> None:
    """The offline ablation of `ablate`: the weight grid, the K sweep and the resting prior."""
    print(
        f"{where}: {res['detected']} of {res['targets']} targets detected; "
        f"verification {res['median_verify_ms']:.0f} ms per detection (median)"
    )
    print("score = IoU + a x colour + e x edges, K = 12:")
    for w in sorted(res["weights"], key=lambda w: (w["mean"], w["over_15_pct"])):
        print(
            f"  a {w['appearance']:.2f}  e {w['edges']:.2f}: mean {w['mean']:6.2f}  "
            f"median {w['median']:5.2f}  > 15 deg {w['over_15_pct']:5.1f} %"
        )
    print("K codebook hypotheses (+ the nets' pose), a 0.05, e 0.3: chosen | best of K")
    for k in res["k"]:
        print(
            f"  K {k['k']:2d}: {k['chosen_mean']:6.2f} deg, {k['chosen_over_15_pct']:5.1f} % | "
            f"{k['best_mean']:6.2f} deg, {k['best_over_15_pct']:5.1f} %"
        )
    print("resting prior (camera pose + resting poses), a 0.05, e 0.3, K 12:")
    for t in res["resting_prior"]:
        print(
            f"  tilt <= {t['max_tilt_deg']:4.0f} deg: mean {t['mean']:6.2f}  "
            f"median {t['median']:5.2f}  > 15 deg {t['over_15_pct']:5.1f} %"
        )


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    args = _parser().parse_args(argv)
    chosen = [flag for flag in SWEEPS if getattr(args, flag) is not None]
    if chosen:
        _sweep(args, chosen[0])
        return 0
    if args.replay is not None:
        rows = json.loads(args.replay.read_text())["rows"]
    else:
        setup_rendering(threads=1)
        rows = record(args.split, args.subset, args.images)
        if args.json is not None:
            write_json(args.json, {"rows": rows})
    res = ablate(rows)
    _print_ablation(res, f"{args.split}/{args.subset}")
    if args.json is not None:
        write_json(args.json, {"ablation": res, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
