"""Ablations of the pose nets: each choice trained both ways on the same data, same seed and
same budget, and scored on the held-out test split.

    python studies/posenet_ablation.py --study per-object [--json PATH]
    python studies/posenet_ablation.py --study ours [--epochs 5] [--json PATH]
    python studies/posenet_ablation.py --study forgetting [--epochs 5] [--json PATH]
    python studies/posenet_ablation.py --study rotation [--epochs 5] [--json PATH]
    python studies/posenet_ablation.py --study ensemble [--epochs 5] [--json PATH]
    python studies/posenet_ablation.py --study arithmetic [--epochs 5] [--json PATH]

Studies:
- ``per-object``: the paper trains one 2D-NET and one 4D-NET per object. Here each object gets
  its own net (the `paper` architecture trained on that object's crops alone) on the shipped
  shared `paper` net's schedule (12 epochs, then 6 in batches of 32), so every object's data is
  seen as often and the total compute is the same. Both are scored on the paper protocol's
  test crops.
- ``ours``: the factors of the `ours` recipe, each changed alone from a base run trained from
  scratch on 5000 head-camera images for `--epochs` epochs (a reduced budget: the shipped net
  trains far longer): backbone width 24 instead of 16, rotation weight lambda 3 instead of 1,
  no photometric augmentation, a constant learning rate instead of the cosine decay, crops of
  48 or 96 px instead of 64 (test crops cut alike at that side), and the rotation as the 6D
  representation instead of viewpoint direction and roll (`perception.nets.ROTATIONS`), and
  distillation: the shipped `ours` (trained far longer, on more data) as a teacher whose outputs
  on each batch are a second target beside the labels. The base
  run is repeated with another seed (initialisation and batch order) to show how far two runs
  of the same recipe differ. Scored on the head-camera test split.
- ``forgetting``: the shipped `ours` fine-tuned for `--epochs` epochs on 5000 images of each
  distribution (paper protocol and head camera) at 5e-4, against the shipped `ours` itself, on
  both test splits; the shipped `paper` net on the paper split is the reference to beat.
- ``rotation``: `ours` trained from scratch on 5000 paper-protocol images for `--epochs` epochs
  with each rotation output (viewpoint direction and roll, or 6D), scored on the paper
  protocol's test split, whose views cover the whole sphere.
- ``ensemble``: two nets as one, their outputs averaged (crop centres, viewpoint directions
  renormalised, distances, rolls as unit (cos, sin) vectors), against each alone, on the
  head-camera test split: the two base runs of ``ours`` (same recipe, two seeds), and the
  shipped `ours` with the shipped hard-tier expert (`posenet_ours_hard.pt`), both of which
  `hybrid` already runs on every detection (it keeps one of the two poses).
- ``arithmetic``: the base run of ``ours`` (fp32, batch 128) against the same run in bf16
  autocast, in bf16 with channels-last weights, and in bf16 at batch 64 (same seed, data and
  epochs): what the faster arithmetic costs in accuracy, beside each run's end-to-end training
  speed (samples stepped per second of its recorded wall time, validation included), on the
  head-camera test split.

Runs checkpoint as they go (`<data>/checkpoints/ablation/`) and a rerun resumes them; a finished
run is not retrained. Test crops are `perception.training.tables`' (`TEST_CROPS`): the same
ground-truth boxes perturbed like detections. Prints centre error in crop pixels (Table 1's
unit) and in image pixels, distance [%], rotation [deg] and the share of rotations over 15 deg,
per object and overall; `--json PATH` writes every figure once all runs are done (``-``: to
standard output; default ``docs/ablation_<study>.json``, the study's name with ``_`` for ``-``).
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path
from typing import TextIO

import numpy as np
import torch

from perception.nets import PoseOutput, load_posenet
from perception.training.data.crop_sets import build_crops
from perception.training.data.render_split import GENERATOR_VERSIONS
from perception.training.evals.posenet_eval import evaluate_arrays
from perception.training.tables import TEST_CROPS
from perception.training.trainers.checkpoints import read_checkpoint
from perception.training.trainers.posenet_trainer import PoseNetTrainConfig, checkpoint_path, train
from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.paths import DOCS_DIR, WEIGHTS_DIR, checkpoint_dir, data_root
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_choice, check_int
from posegrasp.world.objects import OBJECT_NAMES

COLUMNS = ("center_crop_px", "center_px", "distance_pct", "rotation_deg")
STUDIES = ("per-object", "ours", "forgetting", "rotation", "ensemble", "arithmetic")


def _scores(model, data: dict, rows: np.ndarray) -> dict[str, float]:
    """`evaluate_arrays` (mean errors, outliers over 15 deg) on the given crops."""
    return evaluate_arrays(model, {k: v[rows] for k, v in data.items()}) | {"crops": len(rows)}


def _per_object(model_for, data: dict) -> dict[str, dict[str, float]]:
    """Scores per object (model_for(name) scores that object) and their crop-weighted mean."""
    res = {}
    for i, name in enumerate(OBJECT_NAMES):
        rows = np.flatnonzero(data["cls"] == i)
        res[name] = _scores(model_for(name), data, rows)
    n = np.array([r["crops"] for r in res.values()], float)
    res["average"] = {
        k: float(np.sum(n * [r[k] for r in res.values()]) / n.sum())
        for k in (*COLUMNS, "outlier_rate")
    } | {"crops": int(n.sum())}
    return res


def _train(cfg: PoseNetTrainConfig):
    result = train(cfg)
    return load_posenet(Path(result["checkpoint"]), verify=False)


def _own_net(o: str, out: Path):
    """The `paper` net of object `o` alone, on the shipped shared net's schedule (12 epochs in
    batches of 128, then 6 in batches of 32 at 5e-4). Runs are named by the paper protocol's
    generator version, so a net trained on older renders is never reused."""
    tag = f"paper_{o}_v{GENERATOR_VERSIONS['paper']}"
    base = PoseNetTrainConfig(
        variant="paper", dists=("paper",), epochs=12, objects=(o,), out=out, name=tag + "_base"
    )
    train(base)
    return _train(replace(base, epochs=6, batch=32, lr=5e-4, init=tag + "_base", name=tag))


def per_object_study(out: Path) -> dict:
    nets = {o: _own_net(o, out) for o in OBJECT_NAMES}
    shared = load_posenet(WEIGHTS_DIR / "posenet_paper.pt")
    data = build_crops(data_root() / "paper", "test", TEST_CROPS)
    return {
        "shared (shipped paper net)": _per_object(lambda o: shared, data),
        "one net per object": _per_object(lambda o: nets[o], data),
    }


def _ours_base(out: Path, epochs: int) -> PoseNetTrainConfig:
    return PoseNetTrainConfig(
        variant="ours",
        dists=("headcam",),
        dist_limits=(("headcam", 5000),),
        epochs=epochs,
        out=out,
        name=f"ours_base_e{epochs}",
    )


def ours_study(out: Path, epochs: int) -> dict:
    base = _ours_base(out, epochs)
    runs = {
        "base (width 16, lambda 1, jitter, cosine)": base,
        "base, another seed": replace(base, seed=1, name=f"ours_base_seed1_e{epochs}"),
        "lambda 3": replace(base, lam=3.0, name=f"ours_lam3_e{epochs}"),
        "no photometric jitter": replace(base, augment=False, name=f"ours_noaug_e{epochs}"),
        "constant learning rate": replace(base, decay=False, name=f"ours_const_e{epochs}"),
        "width 24": replace(base, width=24, name=f"ours_w24_e{epochs}"),
        "6D rotation": replace(base, rotation="6d", name=f"ours_6d_e{epochs}"),
        "distilled from the shipped ours": replace(
            base, teacher=WEIGHTS_DIR / "posenet_ours.pt", name=f"ours_distil_e{epochs}"
        ),
        "crop 48": replace(base, crops=replace(base.crops, size=48), name=f"ours_crop48_e{epochs}"),
        "crop 96": replace(base, crops=replace(base.crops, size=96), name=f"ours_crop96_e{epochs}"),
    }
    data = {}  # test crops by side
    res = {}
    for label, cfg in runs.items():
        model = _train(cfg)
        side = cfg.crops.size
        if side not in data:
            data[side] = build_crops(
                data_root() / "headcam", "test", replace(TEST_CROPS, size=side)
            )
        res[label] = _per_object(lambda o, m=model: m, data[side])
        res[label]["checkpoint"] = str(checkpoint_path(cfg))
    return res


def arithmetic_study(out: Path, epochs: int) -> dict:
    """The base `ours` run in fp32 and with each faster arithmetic, scored alike; each result also
    holds ``samples_per_s``, the run's samples stepped over its recorded wall time."""
    base = _ours_base(out, epochs)
    bf16 = replace(base, precision="bf16", name=f"ours_bf16_e{epochs}")
    runs = {
        "fp32, batch 128 (base)": base,
        "bf16, batch 128": bf16,
        "bf16 + channels_last, batch 128": replace(
            bf16, channels_last=True, name=f"ours_bf16_cl_e{epochs}"
        ),
        "bf16, batch 64": replace(bf16, batch=64, name=f"ours_bf16_b64_e{epochs}"),
    }
    data = build_crops(data_root() / "headcam", "test", TEST_CROPS)
    res = {}
    for label, cfg in runs.items():
        model = _train(cfg)
        path = checkpoint_path(cfg)
        state = read_checkpoint(path)
        res[label] = _per_object(lambda o, m=model: m, data)
        res[label]["checkpoint"] = str(path)
        res[label]["samples_per_s"] = state["step"] * cfg.batch / max(state["wall_s"], 1e-9)
    return res


def forgetting_study(out: Path, epochs: int) -> dict:
    """The shipped `ours` saw the paper protocol only before version 3 and last trained on the
    head camera alone. Fine-tuned from it on both distributions (5000 images of each, a fresh
    schedule at 5e-4), does it learn the paper protocol without losing the head camera?"""
    shipped = WEIGHTS_DIR / "posenet_ours.pt"
    cfg = PoseNetTrainConfig(
        variant="ours",
        dists=("paper", "headcam"),
        epochs=epochs,
        dist_limits=(("paper", 5000), ("headcam", 5000)),
        lr=5e-4,
        init=str(shipped),
        out=out,
        name=f"ours_both_v{GENERATOR_VERSIONS['paper']}_e{epochs}",
    )
    nets = {"shipped ours": load_posenet(shipped), "fine-tuned on both": _train(cfg)}
    reference = {"shipped paper (reference)": load_posenet(WEIGHTS_DIR / "posenet_paper.pt")}
    res = {}
    for dist in ("paper", "headcam"):
        data = build_crops(data_root() / dist, "test", TEST_CROPS)
        for label, net in (nets | reference if dist == "paper" else nets).items():
            res[f"{dist}: {label}"] = _per_object(lambda o, m=net: m, data)
    res["paper: fine-tuned on both"]["checkpoint"] = str(checkpoint_path(cfg))
    return res


def rotation_study(out: Path, epochs: int) -> dict:
    """`ours` with either rotation output, from scratch on 5000 paper-protocol images: its views
    cover the whole sphere, poles included, where direction and roll are ill-conditioned."""
    base = PoseNetTrainConfig(
        variant="ours",
        dists=("paper",),
        dist_limits=(("paper", 5000),),
        epochs=epochs,
        out=out,
        name=f"ours_paper_v{GENERATOR_VERSIONS['paper']}_e{epochs}",
    )
    runs = {"direction and roll": base, "6D": replace(base, rotation="6d", name=base.name + "_6d")}
    data = build_crops(data_root() / "paper", "test", TEST_CROPS)
    res = {}
    for label, cfg in runs.items():
        model = _train(cfg)
        res[label] = _per_object(lambda o, m=model: m, data)
        res[label]["checkpoint"] = str(checkpoint_path(cfg))
    return res


class Ensemble(torch.nn.Module):
    """Several pose nets as one: the mean of their crop centres, viewpoint directions
    (renormalised), distances and rolls (as unit (cos, sin) vectors)."""

    def __init__(self, nets: list[torch.nn.Module]) -> None:
        super().__init__()
        self.nets = torch.nn.ModuleList(nets)

    def forward(self, crops: torch.Tensor, cls: torch.Tensor, scale: torch.Tensor) -> PoseOutput:
        outs = [net(crops, cls, scale) for net in self.nets]

        def unit(v: torch.Tensor) -> torch.Tensor:
            return v / torch.linalg.norm(v, dim=1, keepdim=True).clamp_min(1e-9)

        uv = torch.stack([o.uv_unit for o in outs]).mean(0)
        dist = torch.stack([torch.linalg.norm(o.p, dim=1) for o in outs]).mean(0)
        direction = unit(torch.stack([unit(o.p) for o in outs]).mean(0))
        cs = torch.stack([unit(o.cs) for o in outs]).mean(0)
        return PoseOutput(uv, direction * dist.unsqueeze(1), cs)


def ensemble_study(out: Path, epochs: int) -> dict:
    """Each pair of nets alone and averaged, on the head-camera test split."""
    base = _ours_base(out, epochs)
    other = replace(base, seed=1, name=f"ours_base_seed1_e{epochs}")
    pairs = {
        "base runs": (("base", _train(base)), ("base, another seed", _train(other))),
        "shipped": (
            ("shipped ours", load_posenet(WEIGHTS_DIR / "posenet_ours.pt")),
            ("shipped expert", load_posenet(WEIGHTS_DIR / "posenet_ours_hard.pt")),
        ),
    }
    data = build_crops(data_root() / "headcam", "test", TEST_CROPS)
    res = {}
    for group, ((a, net_a), (b, net_b)) in pairs.items():
        mean = (f"mean of the {group}", Ensemble([net_a, net_b]))
        for label, net in ((a, net_a), (b, net_b), mean):
            res[label] = _per_object(lambda o, m=net: m, data)
    return res


def _print(results: dict, log: TextIO | None = None) -> None:
    print(
        "| run | object | centre [crop px] | centre [px] | distance [%] | rotation [deg] "
        "| > 15 deg |",
        file=log,
    )
    print("|---" * 7 + "|", file=log)
    for label, per in results.items():
        for obj in (*OBJECT_NAMES, "average"):
            r = per[obj]
            print(
                f"| {label} | {obj} | {r['center_crop_px']:.2f} | {r['center_px']:.2f} | "
                f"{r['distance_pct']:.2f} | {r['rotation_deg']:.2f} | {r['outlier_rate']:.1%} |",
                file=log,
            )
        if "samples_per_s" in per:
            print(f"| {label} | training speed | {per['samples_per_s']:.0f} samples/s |", file=log)


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(
        prog="python studies/posenet_ablation.py", description=__doc__.split("\n\n")[0]
    )
    p.add_argument(
        "--study",
        required=True,
        type=arg(check_choice, STUDIES, "study"),
        help=f"one of: {', '.join(STUDIES)}",
    )
    p.add_argument(
        "--epochs",
        type=arg(check_int, 1, 100, "--epochs", base=int),
        default=5,
        help="epochs of the `ours` runs, 1..100 (default 5)",
    )
    add_json_argument(
        p,
        "every figure of the finished study (default docs/ablation_<study>.json, e.g. "
        "docs/ablation_per_object.json)",
    )
    args = p.parse_args(argv)
    if args.json is None:
        args.json = DOCS_DIR / f"ablation_{args.study.replace('-', '_')}.json"
    setup_rendering()
    out = checkpoint_dir() / "ablation"
    if args.study == "per-object":
        results = per_object_study(out)
    elif args.study == "forgetting":
        results = forgetting_study(out, args.epochs)
    elif args.study == "rotation":
        results = rotation_study(out, args.epochs)
    elif args.study == "ensemble":
        results = ensemble_study(out, args.epochs)
    elif args.study == "arithmetic":
        results = arithmetic_study(out, args.epochs)
    else:
        results = ours_study(out, args.epochs)
    _print(results, summary_stream(args.json))
    if args.json is not None:
        write_json(args.json, {"study": args.study, "results": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
