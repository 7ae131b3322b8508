"""Training of the object extractor (`python -m perception.training.train_detector`).

Trains the Mask R-CNN of `perception.detector_net` from scratch on the head-camera distribution's
train split (``$POSEGRASP_DATA/headcam``) with the targets and augmentation of
`perception.training.detection_data`; instances with fewer than
`DetectorTrainConfig.min_visible_px` visible pixels are left out. Training is seeded and
resumable: a self-describing checkpoint (`perception.training.checkpoints`: weights, model and
training config, optimiser, step, RNG states, data seeds, commit) is written to
``<checkpoints>/detector.pt`` every few minutes and after every epoch, each of which ends with
COCO box and mask AP (`perception.training.detection_eval`) on the first val images. ``--export``
ships the weights (`perception.training.export_detector`).

    python -m perception.training.train_detector                  # train (resumes when interrupted)
    python -m perception.training.train_detector --export  # finish training, ship the weights
    python -m perception.training.train_detector --smoke --data DIR --out DIR   # seconds, tiny data
    torchrun --nproc-per-node 2 -m perception.training.train_detector --device cpu   # 2 processes

Under torchrun the run is data-parallel (`perception.training.ddp`): the same global batch, each
rank its shard, every rank drawing the augmentation stream of the whole batch (so an image is
jittered as in one process), rank 0 evaluating and writing the checkpoint.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from perception.detector import Detector
from perception.detector_net import DetectorConfig, build_detector
from perception.training.checkpoints import (
    config_dict,
    read_checkpoint,
    restore,
    rng_state,
    save_checkpoint,
    seed_torch,
)
from perception.training.dataset import DATASETS, PoseDataset, load_info
from perception.training.ddp import DEVICES, Ranks, resolve_device, start
from perception.training.detection_data import (
    augment_shard,
    collate_list,
    start_from,
    training_images,
)
from perception.training.detection_eval import evaluate_detector, pycocotools_api
from perception.training.export_detector import TRAIN_COMMAND, export_detector
from perception.training.schedule import learning_rate, optimiser_step
from posegrasp.core.cli import ArgumentParser, fail
from posegrasp.core.errors import AssetError, InvalidArgumentError, PosegraspError
from posegrasp.core.paths import WEIGHTS_DIR, checkpoint_dir, data_root
from posegrasp.core.runtime import setup_rendering

CHECKPOINT_NAME = "detector.pt"


@dataclass(frozen=True)
class DetectorTrainConfig:
    """A detector training run.

    Attributes:
        data: dataset folder (BOP layout, splits train and val); None means
            ``data_root() / "headcam"``.
        epochs, batch: passes over the train split and images per step.
        lr, weight_decay, warmup: AdamW peak learning rate, weight decay, and the fraction of
            steps of linear warm-up before the cosine decay
            (`perception.training.schedule.learning_rate`).
        grad_clip: gradient norm clip.
        min_visible_px: instances with fewer visible pixels are not training targets (and are
            ignored by the AP evaluation).
        limit: use at most this many train images (None: all).
        val_images: the AP evaluation after each epoch uses the first this many val images.
        seed: seed of initialisation, image order and augmentation.
        workers: data-loading processes (0: load in the training process).
        threads: torch threads per training process (None: the cores shared by the processes).
        device: "auto", "cpu" or "cuda" (`perception.training.ddp.DEVICES`).
        loss_log: append one JSON line per step here (step, epoch, loss averaged over the
            processes, lr), or None.
        out: checkpoint folder; None means `checkpoint_dir()` (next to the data, outside git).
        checkpoint_minutes: save a resumable checkpoint at least this often.
        detector: the architecture.
        also: further dataset folders under the data root (`perception.training.dataset.
            DATASETS`, e.g. ``headcam_hard``, ``paper``) whose train images are added to the
            run's; validation stays on ``data``'s val split.
        init: shipped detector weights or a detector checkpoint whose weights start the run
            (fine-tuning: fresh optimiser and schedule); None starts from random weights.
    """

    data: Path | None = None
    epochs: int = 12
    batch: int = 4
    lr: float = 1e-3
    weight_decay: float = 1e-4
    warmup: float = 0.02
    grad_clip: float = 10.0
    min_visible_px: int = 100
    limit: int | None = None
    val_images: int = 100
    seed: int = 0
    workers: int = 1
    threads: int | None = None
    out: Path | None = None
    checkpoint_minutes: float = 5.0
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    device: str = "auto"
    loss_log: Path | None = None
    also: tuple[str, ...] = ()
    init: Path | None = None

    def __post_init__(self) -> None:
        bad = [d for d in self.also if d not in DATASETS]
        if bad or len(set(self.also)) != len(self.also):
            raise InvalidArgumentError(
                f"invalid --also {','.join(self.also)!r}; a comma list of: {', '.join(DATASETS)}"
            )
        if self.epochs < 1 or self.batch < 1 or self.val_images < 1 or self.workers < 0:
            raise InvalidArgumentError(
                "epochs, batch and val_images must be >= 1 and workers >= 0, got "
                f"{self.epochs}, {self.batch}, {self.val_images}, {self.workers}"
            )
        if self.threads is not None and self.threads < 1:
            raise InvalidArgumentError(f"threads must be >= 1, got {self.threads}")
        if not (self.lr > 0 and self.checkpoint_minutes > 0):
            raise InvalidArgumentError("lr and checkpoint_minutes must be positive")
        if self.limit is not None and self.limit < 1:
            raise InvalidArgumentError(f"limit must be >= 1, got {self.limit}")

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for checkpoints (paths as strings)."""
        return config_dict(self)


#: A run of a few seconds on a handful of images (tests, and checking a set-up).
SMOKE = DetectorTrainConfig(epochs=1, batch=2, limit=4, val_images=2, workers=0, threads=1)


def dataset_root(cfg: DetectorTrainConfig) -> Path:
    """The dataset folder the run trains on."""
    return Path(cfg.data) if cfg.data is not None else data_root() / "headcam"


def train(cfg: DetectorTrainConfig, resume: bool = True, max_steps: int | None = None) -> dict:
    """Train, resuming from the run's checkpoint when present; under torchrun every process
    calls this and the run is data-parallel (`perception.training.ddp`).

    Args:
        cfg: the run.
        resume: continue from ``<out>/detector.pt`` if it exists (else start over).
        max_steps: stop (with a checkpoint) once this many steps are done in total; the run
            resumes from there next time.

    Returns:
        ``{"checkpoint": path, "history": [per-epoch validation], "step": steps done,
        "finished": all epochs done}``.

    Raises:
        AssetError: no data, or a corrupt checkpoint.
        InvalidArgumentError: a device that is not there, or a batch the processes cannot share.
    """
    ranks = start(cfg.device, cfg.batch)
    try:
        return _train(cfg, ranks, resume, max_steps)
    finally:
        ranks.close()


def _train(cfg: DetectorTrainConfig, ranks: Ranks, resume: bool, max_steps: int | None) -> dict:
    root = dataset_root(cfg)
    for split in ("train", "val"):
        if not (root / split).is_dir():
            raise AssetError(
                f"no {split} split under {root}; build it with "
                "`python -m perception.training.datagen "
                f"--dist headcam --split {split} --count N --out {root}` (or `make data`)"
            )
    train_set, parts = training_images(root, cfg.also, cfg.min_visible_px, cfg.detector, cfg.limit)
    val_data = PoseDataset(root, "val")
    if len(train_set) < cfg.batch:
        raise AssetError(
            f"{len(train_set)} completed train images under {root}, fewer than one batch "
            f"({cfg.batch}); generate more with "
            "`python -m perception.training.datagen --dist headcam`"
        )
    if len(val_data) == 0:
        raise AssetError(f"no completed val images under {root}; generate them first")
    pycocotools_api()  # fail now, not after the first epoch, when pycocotools is missing
    seed_torch(cfg.seed, ranks.threads(cfg.threads))
    model = build_detector(cfg.detector)
    if cfg.init is not None:
        start_from(model, cfg.init, cfg.detector)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    out = cfg.out or checkpoint_dir()
    out.mkdir(parents=True, exist_ok=True)
    ckpt = out / CHECKPOINT_NAME
    g = torch.Generator()
    step, epoch0, history, g_state, wall_s = 0, 0, [], None, 0.0
    if resume and ckpt.is_file():
        try:
            state = read_checkpoint(ckpt)
            saved_cfg = state["model_config"]
            n_saved = int(state["data_seeds"]["train_images"])
        except Exception as exc:
            raise AssetError(
                f"checkpoint {ckpt} is corrupt ({exc}); delete it or pass --no-resume"
            ) from exc
        if DetectorConfig.from_dict(saved_cfg) != cfg.detector:
            raise AssetError(
                f"checkpoint {ckpt} has another architecture; pass --no-resume to start over "
                "or --out to train elsewhere"
            )
        if len(parts) > 1 and n_saved != len(train_set):
            raise AssetError(
                f"checkpoint {ckpt} trained on {n_saved} images, the datasets now hold "
                f"{len(train_set)}; pass --no-resume to start over"
            )
        if n_saved > len(train_set):
            raise AssetError(
                f"checkpoint {ckpt} trained on {n_saved} images, {root} now has "
                f"{len(train_set)}; pass --no-resume to start over"
            )
        # The same images as before the interruption, even if the split has grown since.
        train_set.n = n_saved
        try:
            step, epoch0, history = restore(state, model, opt)
            g_state = state["rng"]["generator"]
            wall_s = float(state.get("wall_s") or 0.0)
        except Exception as exc:
            raise AssetError(
                f"checkpoint {ckpt} is corrupt ({exc}); delete it or pass --no-resume"
            ) from exc
        if ranks.main:
            print(f"resuming {ckpt} at epoch {epoch0}, step {step}")
    net = ranks.wrap(model)  # the model itself with one process
    steps_per_epoch = len(train_set) // cfg.batch
    total_steps = cfg.epochs * steps_per_epoch
    seeds = {
        "dataset": str(root),
        "dataset_seed_bases": load_info(root).get("seed_bases", {}),
        "train_images": len(train_set),
        "also": {name: len(part) for name, part in zip(cfg.also, parts[1:], strict=True)},
        "init": None if cfg.init is None else str(cfg.init),
        "val_images": min(cfg.val_images, len(val_data)),
        "order_seed": "seed * 1000 + epoch",
        "seed": cfg.seed,
    }

    wall0, started = wall_s, time.monotonic()

    def save(epoch: int) -> None:
        # Wall time of the run over all its resumptions.
        header = {"kind": "detector", "wall_s": wall0 + time.monotonic() - started}
        if ranks.main:
            save_checkpoint(
                ckpt, model, opt, model_config=cfg.detector.to_dict(), train_config=cfg.to_dict(),
                step=step, epoch=epoch, history=history, rng=rng_state(g), data_seeds=seeds,
                header=header,
            )  # fmt: skip

    last_save = time.monotonic()
    for epoch in range(epoch0, cfg.epochs):
        g.manual_seed(cfg.seed * 1000 + epoch)
        order = torch.randperm(len(train_set), generator=g).tolist()
        done = step - epoch * steps_per_epoch  # batches of this epoch already done (resume)
        if g_state is not None and done > 0:  # mid-epoch: continue the augmentation stream
            g.set_state(g_state)
        g_state = None
        loader = torch.utils.data.DataLoader(
            train_set,
            batch_size=cfg.batch // ranks.world,
            sampler=ranks.shard(order[done * cfg.batch : steps_per_epoch * cfg.batch]),
            collate_fn=collate_list,
            num_workers=cfg.workers,
            generator=torch.Generator().manual_seed(cfg.seed),  # leaves the global RNG alone
        )
        model.train()
        bar = tqdm(loader, desc=f"detector epoch {epoch + 1}/{cfg.epochs}", initial=done,
                   total=steps_per_epoch, mininterval=2.0, disable=not ranks.main)  # fmt: skip
        losses = []
        for batch in bar:
            if max_steps is not None and step >= max_steps:
                break
            images = augment_shard([image for image, _ in batch], g, ranks)
            targets = [{k: v.to(ranks.device) for k, v in t.items()} for _, t in batch]
            parts = net(images, targets)
            loss = sum(parts.values())
            lr = learning_rate(step, total_steps, cfg.lr, cfg.warmup)
            optimiser_step(model, opt, loss, lr, cfg.grad_clip)
            step += 1
            losses.append(ranks.mean(loss))  # over the processes (every rank takes part)
            if cfg.loss_log is not None:
                ranks.log(cfg.loss_log, step=step, epoch=epoch + 1, loss=losses[-1], lr=lr)
            if step % 10 == 0:
                bar.set_postfix({k.removeprefix("loss_"): f"{float(v.detach()):.3f}"
                                 for k, v in parts.items()})  # fmt: skip
            if time.monotonic() - last_save > 60 * cfg.checkpoint_minutes:
                save(epoch)
                last_save = time.monotonic()
        bar.close()
        if max_steps is not None and step >= max_steps and step < (epoch + 1) * steps_per_epoch:
            save(epoch)
            return {"checkpoint": str(ckpt), "history": history, "step": step, "finished": False}
        if not ranks.main:
            continue  # rank 0 evaluates and saves; the others meet it at the next step
        det = Detector(
            ranks.on_cpu(model), cfg.detector, score_threshold=cfg.detector.box_score_thresh
        )
        val = evaluate_detector(det, val_data, cfg.val_images, cfg.min_visible_px)
        model.train()
        mean_loss = float(np.mean(losses)) if losses else None
        history.append({"epoch": epoch + 1, "step": step, "train_loss": mean_loss, **val})
        print(
            f"epoch {epoch + 1}: val box AP50 {val['box_ap50']:.3f}, mask AP50 "
            f"{val['mask_ap50']:.3f}, box AP {val['box_ap']:.3f}, mask AP {val['mask_ap']:.3f} "
            f"({val['images']} images)"
        )
        save(epoch + 1)
        last_save = time.monotonic()
    return {"checkpoint": str(ckpt), "history": history, "step": step, "finished": True}


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(prog=TRAIN_COMMAND, description=__doc__.split("\n")[0])
    p.add_argument(
        "--data",
        type=Path,
        default=None,
        help="dataset folder with train and val (default: $POSEGRASP_DATA/headcam)",
    )
    p.add_argument(
        "--also",
        default=None,
        help=f"more train data: a comma list of dataset folders, of: {', '.join(DATASETS)}",
    )
    p.add_argument("--init", type=Path, help="start from these detector weights (fine-tune)")
    p.add_argument("--epochs", type=int, default=DetectorTrainConfig.epochs)
    p.add_argument("--batch", type=int, default=DetectorTrainConfig.batch)
    p.add_argument("--lr", type=float, default=DetectorTrainConfig.lr)
    p.add_argument("--limit", type=int, default=None, help="at most this many train images")
    p.add_argument("--val-images", type=int, default=DetectorTrainConfig.val_images)
    p.add_argument("--workers", type=int, default=1, help="data-loading processes (0: none)")
    p.add_argument(
        "--threads", type=int, default=None, help="torch threads per process (default: all cores)"
    )
    p.add_argument("--device", default="auto", help=f"one of: {', '.join(DEVICES)}")
    p.add_argument(
        "--loss-log", type=Path, default=None, help="append one JSON line per step to this file"
    )
    p.add_argument("--seed", type=int, default=DetectorTrainConfig.seed)
    p.add_argument("--out", type=Path, help="checkpoint folder (default: <data>/checkpoints)")
    p.add_argument("--max-steps", type=int, help="stop after this many steps (resumable)")
    p.add_argument("--smoke", action="store_true", help="a tiny run that takes seconds")
    p.add_argument("--no-resume", action="store_true", help="start over")
    p.add_argument(
        "--export",
        action="store_true",
        help="after training, write perception/weights/detector.pt and its manifest "
        "entry (a finished run is not trained further)",
    )
    p.add_argument("--weights-out", type=Path, default=WEIGHTS_DIR, help="export folder")
    args = p.parse_args(argv)
    setup_rendering()
    try:
        resolve_device(args.device)
        if args.smoke:
            cfg = replace(SMOKE, data=args.data, out=args.out, seed=args.seed,
                          threads=args.threads or SMOKE.threads, device=args.device,
                          loss_log=args.loss_log)  # fmt: skip
        else:
            cfg = DetectorTrainConfig(
                data=args.data, epochs=args.epochs, batch=args.batch, lr=args.lr,
                limit=args.limit, val_images=args.val_images, workers=args.workers,
                seed=args.seed, out=args.out, threads=args.threads, device=args.device,
                loss_log=args.loss_log, init=args.init,
                also=tuple(args.also.split(",")) if args.also else (),
            )  # fmt: skip
        if args.max_steps is not None and args.max_steps < 1:
            raise InvalidArgumentError(f"--max-steps must be >= 1, got {args.max_steps}")
        result = train(cfg, resume=not args.no_resume, max_steps=args.max_steps)
        if result["history"]:
            print(json.dumps(result["history"][-1], sort_keys=True))
        if args.export:
            if not result["finished"]:
                print("note: exporting an unfinished run", file=sys.stderr)
            entry = export_detector(Path(result["checkpoint"]), args.weights_out)
            print(f"wrote {args.weights_out / entry['file']} ({entry['bytes'] / 1e6:.1f} MB)")
    except PosegraspError as exc:
        return fail(str(exc))
    return 0


if __name__ == "__main__":
    sys.exit(main())
