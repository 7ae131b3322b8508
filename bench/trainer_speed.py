"""Training speed of the nets on this machine: samples/s of PoseNet and detector training steps.

    python bench/trainer_speed.py [--nets posenet,detector] [--threads 2] [--seconds 8]
                                  [--rounds 2] [--batches 32,64,128,256]
                                  [--detector-batches 2,4,8] [--data DIR] [--cut-images 300]
                                  [--json PATH]

Model step: for the ours and the paper variant (the shipped width), times the trainer's own training
step (`perception.training.trainers.posenet_trainer.training_loss`: forward, loss in fp32; then
`perception.training.trainers.schedule.optimiser_step`: backward, gradient clip, AdamW) on random
crops shaped as real ones (64x64 RGB, labels in their ranges), at each batch in four arithmetics:
fp32, channels-last, bf16 autocast, and both. Each configuration starts from a fresh seeded net,
takes `WARMUP_STEPS` untimed steps and then as many as fit in its share of ``--seconds``; its
samples/s is the batch over the median step time. The configurations are timed in ``--rounds``
rounds over all of them and the fastest round of each counts, so that bursts of other processes
on a shared machine move the figures least (the mean's figure and the load average are in the
JSON).

End to end: the same step fed by the trainer's data path (`train_posenet.batch_tensors` on the
epoch's random order, then `train_posenet.training_inputs`: normalisation and photometric
jitter), on real crops: the crop caches training leaves under the data root
(``<data>/<dataset>/crops_*.npz``), or, when there are none, crops cut in memory (nothing is
written) from the first ``--cut-images`` rendered images of a dataset there; if there are no
rendered images either, it says so. The data path's share of each step (medians of both parts)
is reported alongside.

Detector: the detector trainer's step
(`perception.training.trainers.detector_trainer.detection_loss`, then the same optimiser step) on
real head-camera images and their targets
(`perception.training.trainers.detection_data.DetectionSet`, the first rendered split found under
the data root, photometric augmentation as in training), starting from the shipped detector
weights, at each of ``--detector-batches`` in the same four arithmetics; images/s.

One process; torch threads 2 unless told otherwise. ``--json PATH`` writes the figures. No
target is set for training speed: the figures compare arithmetics and batches, and the bench
says so; its exit status is 0 once it has measured.
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from perception.detector_net import build_detector
from perception.nets import CROP, PoseNet
from perception.training.data.crop_sets import CropConfig, CropSet, random_boxes
from perception.training.data.dataset import DATASETS, PoseDataset
from perception.training.trainers.ddp import ONE_PROCESS
from perception.training.trainers.detection_data import DetectionSet, augment_shard, start_from
from perception.training.trainers.detector_trainer import DetectorTrainConfig, detection_loss
from perception.training.trainers.options import MAX_BATCH
from perception.training.trainers.posenet_trainer import (
    BATCH_KEYS,
    GRAD_CLIP,
    PoseNetTrainConfig,
    batch_tensors,
    training_inputs,
    training_loss,
)
from perception.training.trainers.schedule import optimiser_step
from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    add_threads_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.paths import WEIGHTS_DIR, data_root
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_int

#: The arithmetics timed: name -> (precision, channels_last).
MODES = {
    "fp32": ("fp32", False),
    "channels_last": ("fp32", True),
    "bf16": ("bf16", False),
    "bf16+channels_last": ("bf16", True),
}
VARIANTS = ("ours", "paper")
BATCHES = (32, 64, 128, 256)
DETECTOR_BATCHES = (2, 4, 8)
#: Images held for the detector's steps (the batches cycle through them).
DETECTOR_IMAGES = 24
NETS = ("posenet", "detector")
#: Untimed steps before each configuration's timing.
WARMUP_STEPS = 3
#: The end-to-end batch: the shipped "ours" stages'.
E2E_BATCH = PoseNetTrainConfig.batch
#: Learning rate of the timed steps (the rate does not change the step's cost).
LR = 1e-4


def random_crops(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    """A crop set of `n` random rows shaped and typed as `perception.training.data.crop_sets`
    cuts."""
    rng = np.random.default_rng(seed)
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return {
        "crops": rng.integers(0, 256, (n, CROP, CROP, 3), dtype=np.uint8),
        "cls": rng.integers(0, 6, n).astype(np.int64),
        "scale": rng.uniform(0.05, 0.4, n).astype(np.float32),
        "uv_unit": rng.uniform(0.2, 0.8, (n, 2)).astype(np.float32),
        "p": (direction * rng.uniform(0.3, 1.5, (n, 1))).astype(np.float32),
        "theta": rng.uniform(-np.pi, np.pi, n).astype(np.float32),
    }


def _setup(cfg: PoseNetTrainConfig) -> tuple[PoseNet, torch.optim.Optimizer, torch.Generator]:
    """A fresh seeded net laid out as `cfg` asks, its optimiser and a jitter generator."""
    torch.manual_seed(0)
    model = PoseNet(cfg.net_config())
    if cfg.channels_last:
        model = model.to(memory_format=torch.channels_last)
    model.train()
    opt = torch.optim.AdamW(model.parameters(), lr=LR, weight_decay=cfg.weight_decay)
    return model, opt, torch.Generator().manual_seed(0)


def _model_step(
    cfg: PoseNetTrainConfig,
    model: PoseNet,
    opt: torch.optim.Optimizer,
    x: torch.Tensor,
    batch: dict[str, torch.Tensor],
) -> None:
    """One training step of the trainer on a prepared input."""
    loss, _ = training_loss(cfg, model, None, x, batch)
    optimiser_step(model, opt, loss, LR, GRAD_CLIP)


def _timed(step, seconds: float) -> list[float]:
    """Wall times [s] of `step()` after `WARMUP_STEPS` untimed calls, for about `seconds`."""
    for _ in range(WARMUP_STEPS):
        step()
    times: list[float] = []
    while sum(times) < seconds:
        t0 = time.perf_counter()
        step()
        times.append(time.perf_counter() - t0)
    return times


def time_model_step(cfg: PoseNetTrainConfig, seconds: float) -> dict[str, float]:
    """Samples/s of the model step of `cfg` on one random batch, prepared once: the batch over
    the median step time (which other processes' bursts on a shared machine move least), and
    over the mean."""
    model, opt, g = _setup(cfg)
    tr = random_crops(cfg.batch)
    batch = batch_tensors(tr, np.arange(cfg.batch), ONE_PROCESS.device)
    x = training_inputs(cfg, batch, g, ONE_PROCESS)
    times = _timed(lambda: _model_step(cfg, model, opt, x, batch), seconds)
    return {
        "samples_per_s": cfg.batch / float(np.median(times)),
        "samples_per_s_mean": cfg.batch / float(np.mean(times)),
        "steps": len(times),
        "load_average_1min": os.getloadavg()[0],
    }


def time_end_to_end(cfg: PoseNetTrainConfig, tr: dict, seconds: float) -> dict[str, float]:
    """Samples/s of the trainer's steps fed by its data path over `tr` in a random epoch order
    (from the median times), and the share of each step the data path takes."""
    model, opt, g = _setup(cfg)
    order = torch.randperm(len(tr["crops"]), generator=torch.Generator().manual_seed(0)).numpy()
    per_epoch = max(1, len(order) // cfg.batch)
    split: list[tuple[float, float]] = []
    done = 0

    def step() -> None:
        nonlocal done
        b = done % per_epoch
        t0 = time.perf_counter()
        batch = batch_tensors(tr, order[b * cfg.batch : (b + 1) * cfg.batch], ONE_PROCESS.device)
        x = training_inputs(cfg, batch, g, ONE_PROCESS)
        t1 = time.perf_counter()
        _model_step(cfg, model, opt, x, batch)
        split.append((t1 - t0, time.perf_counter() - t1))
        done += 1

    times = _timed(step, seconds)
    data, model_s = (float(np.median(t)) for t in zip(*split[WARMUP_STEPS:], strict=True))
    return {
        "samples_per_s": min(cfg.batch, len(order)) / float(np.median(times)),
        "data_share": data / (data + model_s),
        "data_ms_per_step": 1000 * data,
        "model_ms_per_step": 1000 * model_s,
        "steps": len(times),
        "load_average_1min": os.getloadavg()[0],
    }


def real_crops(root: Path, cut_images: int) -> tuple[dict | None, str]:
    """Crops for the end-to-end figure and where they come from (None and why not, if none).

    The crop caches under `root` (``<dataset>/crops_*.npz``) when there are any, else crops cut
    in memory from the first `cut_images` images of the first rendered split found there.
    """
    caches = sorted(root.glob("*/crops_*.npz"))
    if caches:
        parts = []
        for path in caches:
            with np.load(path) as z:
                parts.append({k: z[k] for k in BATCH_KEYS})
        same = [p for p in parts if p["crops"].shape[1:] == (CROP, CROP, 3)]
        if same:
            tr = {k: np.concatenate([p[k] for p in same]) for k in same[0]}
            return tr, f"{len(tr['crops'])} cached crops from {len(caches)} file(s) under {root}"
    for split in ("train", "val", "test"):
        for name in DATASETS:
            folder = root / name
            if not (folder / split).is_dir():
                continue
            ds = PoseDataset(folder, split)
            n = min(cut_images, len(ds))
            if n == 0:
                continue
            crops = CropSet()
            for sample, obj, box in random_boxes(ds, CropConfig(), n):
                crops.add(sample.rgb, sample.K, obj, box)
            tr = crops.arrays()
            if len(tr["crops"]):
                return tr, (
                    f"no crop cache under {root}: {len(tr['crops'])} crops cut in memory from "
                    f"the first {n} images of {name}/{split}"
                )
    return None, f"no crop cache and no rendered images under {root}: end to end not measured"


def detector_images(root: Path, n: int) -> tuple[list | None, str]:
    """The first `n` (image, target) pairs of the first head-camera split rendered under `root`,
    as the detector trainer loads them, and where they come from (None and why not, if none)."""
    cfg = DetectorTrainConfig()
    for split in ("train", "val", "test"):
        for name in DATASETS:
            if name == "paper" or not (root / name / split).is_dir():
                continue
            ds = DetectionSet(root / name, split, cfg.min_visible_px, cfg.detector)
            if len(ds) == 0:
                continue
            items = [ds[i] for i in range(min(n, len(ds)))]
            return items, f"the first {len(items)} images of {name}/{split} under {root}"
    return None, f"no rendered head-camera images under {root}: the detector is not measured"


def time_detector_step(cfg: DetectorTrainConfig, items: list, seconds: float) -> dict:
    """Images/s of the detector trainer's step under `cfg` on `items` (cycled through in
    batches), from the shipped weights: the batch over the median step time, and the mean's."""
    torch.manual_seed(0)
    model = build_detector(cfg.detector)
    start_from(model, WEIGHTS_DIR / "detector.pt", cfg.detector)
    if cfg.channels_last:
        model = model.to(memory_format=torch.channels_last)
    model.train()
    opt = torch.optim.AdamW(model.parameters(), lr=LR, weight_decay=cfg.weight_decay)
    g = torch.Generator().manual_seed(0)
    done = 0

    def step() -> None:
        nonlocal done
        batch = [items[(done * cfg.batch + j) % len(items)] for j in range(cfg.batch)]
        images = augment_shard([image for image, _ in batch], g, ONE_PROCESS)
        loss, _ = detection_loss(cfg, model, images, [t for _, t in batch], ONE_PROCESS.device)
        optimiser_step(model, opt, loss, LR, cfg.grad_clip)
        done += 1

    times = _timed(step, seconds)
    return {
        "samples_per_s": cfg.batch / float(np.median(times)),
        "samples_per_s_mean": cfg.batch / float(np.mean(times)),
        "steps": len(times),
        "load_average_1min": os.getloadavg()[0],
    }


def _in_rounds(configs: dict, timing, rounds: int) -> list[tuple[Any, dict[str, float]]]:
    """``timing(cfg)`` of every configuration in each of `rounds` rounds over all of them, and of
    each the round with the most samples/s: a burst of other processes on a shared machine then
    spoils one round of a configuration rather than its figure."""
    best: dict = {}
    for i in range(rounds):
        for key, cfg in configs.items():
            r = timing(cfg)
            if key not in best or r["samples_per_s"] > best[key]["samples_per_s"]:
                best[key] = r
        print(f"  round {i + 1}/{rounds} done", file=sys.stderr)
    return list(best.items())


def _table(
    rows: dict[str, dict[str, dict[str, float]]], batches: list[int], log, digits: int = 0
) -> None:
    """Print samples/s with `digits` decimals: one line per net and arithmetic, one column per
    batch."""
    head = f"{'net':10}{'arithmetic':20}" + "".join(f"{f'batch {b}':>11}" for b in batches)
    print(head, file=log)
    for key, per_batch in rows.items():
        net, mode = key.split("/")
        cells = "".join(f"{per_batch[str(b)]['samples_per_s']:>11.{digits}f}" for b in batches)
        print(f"{net:10}{mode:20}{cells}", file=log)


def _batches(text: str, name: str = "--batches") -> list[int]:
    """`name`: a comma list of batches, each 1..`MAX_BATCH`."""
    try:
        return [check_int(int(b), 1, MAX_BATCH, name) for b in text.split(",")]
    except ValueError:
        raise InvalidArgumentError(
            f"invalid {name} {text!r}; valid: a comma list of integers 1..{MAX_BATCH}"
        ) from None


def _nets(text: str) -> list[str]:
    """``--nets``: a comma list of `NETS`."""
    nets = [n for n in text.split(",") if n]
    if not nets or any(n not in NETS for n in nets):
        raise InvalidArgumentError(f"invalid --nets {text!r}; a comma list of: {', '.join(NETS)}")
    return nets


def _posenet(args, log) -> dict:
    """The PoseNet figures: every variant, arithmetic and batch, then end to end."""
    print(
        f"PoseNet training steps, {args.threads} threads, {args.seconds} s per configuration, "
        f"load average {os.getloadavg()[0]:.1f}; samples/s of the model step",
        file=log,
    )
    configs = {
        (f"{variant}/{mode}", str(b)): PoseNetTrainConfig(
            variant=variant, batch=b, precision=precision, channels_last=channels_last
        )
        for variant in VARIANTS
        for mode, (precision, channels_last) in MODES.items()
        for b in args.batches
    }
    per_round = args.seconds / args.rounds
    rows: dict[str, dict[str, dict[str, float]]] = {}
    for key, r in _in_rounds(configs, lambda cfg: time_model_step(cfg, per_round), args.rounds):
        rows.setdefault(key[0], {})[key[1]] = r
    _table(rows, args.batches, log)
    tr, source = real_crops(args.data or data_root(), args.cut_images)
    print(f"end to end (ours, batch {E2E_BATCH}): {source}", file=log)
    e2e: dict[str, dict[str, float]] = {}
    if tr is not None:
        base = PoseNetTrainConfig(variant="ours", batch=E2E_BATCH)
        modes = {
            mode: replace(base, precision=precision, channels_last=channels_last)
            for mode, (precision, channels_last) in MODES.items()
        }
        e2e = dict(_in_rounds(modes, lambda cfg: time_end_to_end(cfg, tr, per_round), args.rounds))
        for mode, r in e2e.items():
            total_ms = r["data_ms_per_step"] + r["model_ms_per_step"]
            print(
                f"  {mode:20}{r['samples_per_s']:>7.0f} samples/s; data path "
                f"{r['data_ms_per_step']:.1f} ms of {total_ms:.1f} ms per step "
                f"({r['data_share']:.0%})",
                file=log,
            )
    return {
        "model_step": rows,
        "end_to_end": {"source": source, "batch": E2E_BATCH, "modes": e2e},
    }


def _detector(args, log) -> dict:
    """The detector figures: every arithmetic and batch on real images."""
    items, source = detector_images(args.data or data_root(), DETECTOR_IMAGES)
    print(f"detector training steps, images/s: {source}", file=log)
    rows: dict[str, dict[str, dict[str, float]]] = {}
    if items is not None:
        configs = {
            (f"detector/{mode}", str(b)): DetectorTrainConfig(
                batch=b, precision=precision, channels_last=channels_last
            )
            for mode, (precision, channels_last) in MODES.items()
            for b in args.detector_batches
        }
        per_round = args.seconds / args.rounds
        timed = _in_rounds(
            configs, lambda cfg: time_detector_step(cfg, items, per_round), args.rounds
        )
        for key, r in timed:
            rows.setdefault(key[0], {})[key[1]] = r
        _table(rows, args.detector_batches, log, digits=1)
    return {"source": source, "step": rows}


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(prog="python bench/trainer_speed.py", description=__doc__.split("\n")[0])
    p.add_argument(
        "--nets",
        type=arg(_nets),
        default=list(NETS),
        help=f"comma list of the nets to time, of: {', '.join(NETS)} (default both)",
    )
    add_threads_argument(p)
    p.add_argument(
        "--seconds",
        type=arg(check_int, 1, 600, "--seconds", base=int),
        default=8,
        help="timed seconds per configuration over all rounds, 1..600 (default 8)",
    )
    p.add_argument(
        "--batches",
        type=arg(_batches),
        default=list(BATCHES),
        help=f"PoseNet: comma list of batches (default {','.join(map(str, BATCHES))})",
    )
    p.add_argument(
        "--detector-batches",
        type=arg(_batches, "--detector-batches"),
        default=list(DETECTOR_BATCHES),
        help="detector: comma list of batches of images "
        f"(default {','.join(map(str, DETECTOR_BATCHES))})",
    )
    p.add_argument(
        "--data",
        type=Path,
        default=None,
        help="data root of the real crops and images (default: the data root)",
    )
    p.add_argument(
        "--cut-images",
        type=arg(check_int, 1, 100_000, "--cut-images", base=int),
        default=300,
        help="without a crop cache: images to cut the end-to-end crops from (default 300)",
    )
    p.add_argument(
        "--rounds",
        type=arg(check_int, 1, 10, "--rounds", base=int),
        default=2,
        help="rounds over all configurations, each timing them for --seconds / --rounds; the "
        "fastest round counts (default 2)",
    )
    add_json_argument(p, "the figures")
    args = p.parse_args(argv)
    setup_rendering()
    torch.set_num_threads(args.threads)
    log = summary_stream(args.json)
    out: dict[str, Any] = {"threads": args.threads, "seconds": args.seconds, "rounds": args.rounds}
    if "posenet" in args.nets:
        out |= _posenet(args, log)
    if "detector" in args.nets:
        out["detector"] = _detector(args, log)
    print("no target: training speed is measured to compare arithmetics and batches", file=log)
    if args.json is not None:
        write_json(args.json, out | {"load_average_1min": os.getloadavg()[0]})
    return 0


if __name__ == "__main__":
    sys.exit(main())
