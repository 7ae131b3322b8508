"""The training of the object extractor (its command line:
`perception.training.train_detector`).

Trains the Mask R-CNN of `perception.detector_net` from scratch on the head-camera distribution's
train split (``$POSEGRASP_DATA/headcam``) with the targets and augmentation of
`perception.training.trainers.detection_data`; instances with fewer than
`DetectorTrainConfig.min_visible_px` visible pixels are left out. Training is seeded and
resumable: a self-describing checkpoint (`perception.training.trainers.checkpoints`: weights,
model and training config, optimiser, step, RNG states, data seeds, commit) is written to
``<checkpoints>/detector.pt`` every few minutes and after every epoch, each of which ends with
COCO box and mask AP (`perception.training.evals.detection_eval`) on the first val images.

Under torchrun the run is data-parallel (`perception.training.trainers.ddp`): the same global
batch, each rank its shard, every rank drawing the augmentation stream of the whole batch (so an
image is jittered as in one process), rank 0 evaluating and writing the checkpoint.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from perception.detector import Detector
from perception.detector_net import DetectorConfig, build_detector
from perception.training.data.dataset import DATASETS, PoseDataset, format_data, load_info
from perception.training.evals.detection_eval import evaluate_detector, pycocotools_api
from perception.training.trainers.checkpoints import (
    config_dict,
    read_checkpoint,
    restore,
    rng_state,
    save_checkpoint,
    seed_torch,
)
from perception.training.trainers.ddp import Ranks, joined
from perception.training.trainers.detection_data import (
    augment_shard,
    collate_list,
    start_from,
    training_images,
)
from perception.training.trainers.loop import PRECISIONS, Run, Step, autocast, fit
from perception.training.trainers.schedule import learning_rate, optimiser_step
from posegrasp.core.errors import AssetError, InvalidArgumentError
from posegrasp.core.paths import checkpoint_dir, data_root
from posegrasp.core.validate import DEFAULT_WORKERS, check_choice

#: The command line of this module.
TRAIN_COMMAND = "python -m perception.training.train_detector"
CHECKPOINT_NAME = "detector.pt"


@dataclass(frozen=True)
class DetectorTrainConfig:
    """A detector training run.

    Attributes:
        data: dataset folder (BOP layout, splits train and val), or the name of one under the data
            root (`perception.training.data.dataset.DATASETS`); None means
            ``data_root() / "headcam"``.
        epochs, batch: passes over the train split and images per step.
        lr, weight_decay, warmup: AdamW peak learning rate, weight decay, and the fraction of
            steps of linear warm-up before the cosine decay
            (`perception.training.trainers.schedule.learning_rate`).
        grad_clip: gradient norm clip.
        min_visible_px: instances with fewer visible pixels are not training targets (and are
            ignored by the AP evaluation).
        limit: use at most this many train images of each folder (None: all).
        limits: per-folder caps on top of `limit`, ((folder name, images), ...); the first
            folder goes by its own name (``headcam_hard`` for ``data/headcam_hard``).
        val_images: the AP evaluation after each epoch uses the first this many val images.
        seed: seed of initialisation, image order and augmentation.
        workers: data-loading processes (0: load in the training process).
        threads: torch threads per training process (None: the cores shared by the processes).
        device: "auto", "cpu" or "cuda" (`perception.training.trainers.ddp.DEVICES`).
        loss_log: append one JSON line per step here (step, epoch, loss averaged over the
            processes, lr), or None.
        out: checkpoint folder; None means `checkpoint_dir()` (next to the data, outside git).
        checkpoint_minutes: save a resumable checkpoint at least this often.
        detector: the architecture.
        also: further dataset folders under the data root (`perception.training.data.
            dataset.DATASETS`, e.g. ``headcam_hard``, ``paper``) whose train images are added to the
            run's; validation stays on ``data``'s val split.
        init: shipped detector weights or a detector checkpoint whose weights start the run
            (fine-tuning: fresh optimiser and schedule); None starts from random weights.
        precision: arithmetic of the training forward passes (`perception.training.trainers.loop.
            PRECISIONS`): "fp32", or "bf16" under `torch.autocast` with bfloat16 (the losses
            summed in fp32).
        channels_last: keep the model's weights in channels-last memory layout (and so the
            feature maps the convolutions make).
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
    limits: tuple[tuple[str, int], ...] = ()
    val_images: int = 100
    seed: int = 0
    workers: int = DEFAULT_WORKERS
    threads: int | None = None
    out: Path | None = None
    checkpoint_minutes: float = 5.0
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    device: str = "auto"
    loss_log: Path | None = None
    also: tuple[str, ...] = ()
    init: Path | None = None
    precision: str = "fp32"
    channels_last: bool = False

    def __post_init__(self) -> None:
        check_choice(self.precision, PRECISIONS, "precision")
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
        if any(n < 1 for _, n in self.limits):
            raise InvalidArgumentError(f"limits must be >= 1, got {self.limits}")

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for checkpoints (paths as strings)."""
        return config_dict(self)


#: A run of a few seconds on a handful of images (tests, and checking a set-up).
SMOKE = DetectorTrainConfig(epochs=1, batch=2, limit=4, val_images=2, workers=0, threads=1)


def dataset_root(cfg: DetectorTrainConfig) -> Path:
    """The dataset folder the run trains on."""
    if cfg.data is None or str(cfg.data) in DATASETS:
        return data_root() / str(cfg.data or "headcam")
    return Path(cfg.data)


def part_limits(cfg: DetectorTrainConfig) -> tuple[int | None, ...]:
    """The most train images the run takes of each of its folders (None: all), the data
    folder's first, then those of `also`."""
    names = (dataset_root(cfg).name, *cfg.also)
    caps = dict(cfg.limits)
    out = []
    for name in names:
        lims = [n for n in (cfg.limit, caps.get(name)) if n is not None]
        out.append(min(lims) if lims else None)
    return tuple(out)


def command_line(cfg: DetectorTrainConfig) -> str:
    """The CLI command that runs `cfg` (the options it changed), in the trainers' shared
    spelling (``--data NAME=COUNT,...``)."""
    d = DetectorTrainConfig
    root = str(cfg.data) if cfg.data is not None else "headcam"
    data = format_data(tuple(zip((root, *cfg.also), part_limits(cfg), strict=True)))
    added = [c for c in cfg.detector.classes if c not in DetectorConfig().classes]
    options = (
        (cfg.batch != d.batch, f"--batch {cfg.batch}"),
        (cfg.lr != d.lr, f"--lr {cfg.lr:g}"),
        (cfg.seed != d.seed, f"--seed {cfg.seed}"),
        (cfg.precision != d.precision, f"--precision {cfg.precision}"),
        (cfg.channels_last, "--channels-last"),
        (cfg.detector.any_object, "--any-object"),
        (bool(added) and not cfg.detector.any_object, f"--objects {','.join(added)}"),
        (cfg.init is not None, f"--init {cfg.init}"),
        (cfg.out is not None, f"--out {cfg.out}"),
    )
    head = [TRAIN_COMMAND, f"--data {data}", f"--epochs {cfg.epochs}"]
    return " ".join(head + [text for wanted, text in options if wanted])


def train(cfg: DetectorTrainConfig, resume: bool = True, max_steps: int | None = None) -> dict:
    """Train, resuming from the run's checkpoint when present; under torchrun every process
    calls this and the run is data-parallel (`perception.training.trainers.ddp`).

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
    with joined(cfg.device, cfg.batch) as ranks:
        trainer = DetectorTrainer(cfg, ranks)
        run, finished = fit(
            trainer,
            cfg.epochs,
            resume=resume,
            checkpoint_minutes=cfg.checkpoint_minutes,
            loss_log=cfg.loss_log,
            max_steps=max_steps,
        )
    return {
        "checkpoint": str(trainer.ckpt),
        "history": run.history,
        "step": run.step,
        "finished": finished,
    }


class DetectorTrainer:
    """The detector's part of the training loop (`perception.training.trainers.loop.fit`): its
    training images and their augmentation, its step and its COCO AP.

    Args:
        cfg: the run.
        ranks: this process's place in it.
    """

    def __init__(self, cfg: DetectorTrainConfig, ranks: Ranks) -> None:
        self.cfg, self.ranks = cfg, ranks
        self.label = "detector"
        self.ckpt = (cfg.out or checkpoint_dir()) / CHECKPOINT_NAME
        self.generator = torch.Generator()  # the image orders and the augmentation
        self.g_state: torch.Tensor | None = None  # the generator's state at the checkpoint
        self.losses: list[float] = []  # the steps' losses of the epoch, over the processes

    def start(self, resume: bool) -> Run:
        """The images (`_datasets`), the model and its optimiser (`_start_run`), wrapped for the
        processes.

        Raises:
            AssetError: missing data or pycocotools, or a checkpoint that does not fit.
        """
        cfg = self.cfg
        root = dataset_root(cfg)
        self.train_set, parts, self.val_data = _datasets(cfg, root)
        pycocotools_api()  # fail now, not after the first epoch, when pycocotools is missing
        run, self.g_state = _start_run(cfg, self.ranks, resume, root, self.train_set, parts)
        self.net = self.ranks.wrap(run.model)  # the model itself with one process
        self.seeds = _data_seeds(cfg, root, self.train_set, parts, self.val_data)
        return run

    def batches(self, run: Run, epoch: int) -> Iterator[list]:
        """This rank's shards of the epoch's batches not done yet, (image, target) pairs.

        The epoch's image order is drawn from the run's generator seeded by the epoch; a run
        resumed mid-epoch skips the batches it has done and continues the augmentation stream
        where it stopped.
        """
        cfg, g = self.cfg, self.generator
        g.manual_seed(cfg.seed * 1000 + epoch)
        order = torch.randperm(len(self.train_set), generator=g).tolist()
        done = run.done_in(epoch)
        if self.g_state is not None and done > 0:  # mid-epoch: continue the augmentation stream
            g.set_state(self.g_state)
        self.g_state, self.losses = None, []
        yield from torch.utils.data.DataLoader(
            self.train_set,
            batch_size=cfg.batch // self.ranks.world,
            sampler=self.ranks.shard(order[done * cfg.batch : run.steps_per_epoch * cfg.batch]),
            collate_fn=collate_list,
            num_workers=cfg.workers,
            generator=torch.Generator().manual_seed(cfg.seed),  # leaves the global RNG alone
        )

    def step(self, run: Run, batch: list, epoch: int) -> Step:
        """One optimiser step on this rank's shard `batch`; shows the parts of its loss."""
        cfg, device = self.cfg, self.ranks.device
        images = augment_shard([image for image, _ in batch], self.generator, self.ranks)
        targets = [{k: v.to(device) for k, v in t.items()} for _, t in batch]
        loss, parts = detection_loss(cfg, self.net, images, targets, device)
        lr = learning_rate(run.step, cfg.epochs * run.steps_per_epoch, cfg.lr, cfg.warmup)
        optimiser_step(run.model, run.opt, loss, lr, cfg.grad_clip)
        mean = self.ranks.mean(loss)  # every rank takes part
        self.losses.append(mean)
        shown = {k.removeprefix("loss_"): v.detach() for k, v in parts.items()}
        return Step(loss, lr, shown, mean)

    def validate(self, run: Run, epoch: int) -> None:
        """COCO AP on the first val images, into the history with the epoch's mean training
        loss, and printed."""
        cfg = self.cfg
        det = Detector(
            self.ranks.on_cpu(run.model),
            cfg.detector,
            score_threshold=cfg.detector.box_score_thresh,
        )
        val = evaluate_detector(det, self.val_data, cfg.val_images, cfg.min_visible_px)
        run.model.train()
        mean_loss = float(np.mean(self.losses)) if self.losses else None
        run.history.append({"epoch": epoch + 1, "step": run.step, "train_loss": mean_loss, **val})
        print(
            f"epoch {epoch + 1}: val box AP50 {val['box_ap50']:.3f}, mask AP50 "
            f"{val['mask_ap50']:.3f}, box AP {val['box_ap']:.3f}, mask AP {val['mask_ap']:.3f} "
            f"({val['images']} images)"
        )

    def save(self, run: Run, epoch: int, wall_s: float) -> None:
        """Write the run's checkpoint (rank 0; the others do nothing)."""
        if self.ranks.main:
            save_checkpoint(
                self.ckpt,
                run.model,
                run.opt,
                model_config=self.cfg.detector.to_dict(),
                train_config=self.cfg.to_dict(),
                step=run.step,
                epoch=epoch,
                history=run.history,
                rng=rng_state(self.generator),
                data_seeds=self.seeds,
                header={"kind": "detector", "command": command_line(self.cfg), "wall_s": wall_s},
            )


def _datasets(cfg: DetectorTrainConfig, root: Path) -> tuple[Any, list, PoseDataset]:
    """The run's training images (`training_images`: the whole mix and its parts) and its
    validation dataset.

    Raises:
        AssetError: a split missing, fewer training images than a batch, or no val image.
    """
    for split in ("train", "val"):
        if not (root / split).is_dir():
            raise AssetError(
                f"no {split} split under {root}; build it with "
                "`python -m perception.training.datagen "
                f"--dist headcam --split {split} --count N --out {root}` (or `make data`)"
            )
    train_set, parts = training_images(
        root, cfg.also, cfg.min_visible_px, cfg.detector, part_limits(cfg)
    )
    val_data = PoseDataset(root, "val")
    if len(train_set) < cfg.batch:
        raise AssetError(
            f"{len(train_set)} completed train images under {root}, fewer than one batch "
            f"({cfg.batch}); generate more with "
            "`python -m perception.training.datagen --dist headcam`"
        )
    if len(val_data) == 0:
        raise AssetError(f"no completed val images under {root}; generate them first")
    return train_set, parts, val_data


def _start_run(
    cfg: DetectorTrainConfig, ranks: Ranks, resume: bool, root: Path, train_set: Any, parts: list
) -> tuple[Run, torch.Tensor | None]:
    """The seeded model and optimiser, fresh, started from `cfg.init`, or resumed from the run's
    checkpoint (which also fixes how many of the training images the run uses), and the state of
    the run's generator at that checkpoint (None: none).

    Raises:
        AssetError: a corrupt checkpoint, or one of another architecture or other data.
    """
    seed_torch(cfg.seed, ranks.threads(cfg.threads))
    model = build_detector(cfg.detector)
    if cfg.init is not None:
        start_from(model, cfg.init, cfg.detector)
    if cfg.channels_last:  # the same parameter objects, so the optimiser below holds them
        model = model.to(memory_format=torch.channels_last)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    out = cfg.out or checkpoint_dir()
    out.mkdir(parents=True, exist_ok=True)
    ckpt = out / CHECKPOINT_NAME
    run, g_state = Run(model, opt, steps_per_epoch=0), None
    if resume and ckpt.is_file():
        run.step, run.epoch, run.history, g_state, run.wall_s = _resume(
            cfg, ckpt, model, opt, root, train_set, parts
        )
        if ranks.main:
            print(f"resuming {ckpt} at epoch {run.epoch}, step {run.step}")
    run.steps_per_epoch = len(train_set) // cfg.batch  # (`_resume` may cut the set)
    return run, g_state


def _resume(
    cfg: DetectorTrainConfig,
    ckpt: Path,
    model: nn.Module,
    opt: torch.optim.Optimizer,
    root: Path,
    train_set: Any,
    parts: list,
) -> tuple[int, int, list[dict], torch.Tensor, float]:
    """Load the run's checkpoint into `model` and `opt` and limit `train_set` to the images it
    trained on.

    Returns:
        (step, epoch, history, generator state, wall time [s]) to continue from.

    Raises:
        AssetError: a corrupt checkpoint, or one of another architecture or other data.
    """
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
        step, epoch, history = restore(state, model, opt)
        return step, epoch, history, state["rng"]["generator"], float(state.get("wall_s") or 0.0)
    except Exception as exc:
        raise AssetError(
            f"checkpoint {ckpt} is corrupt ({exc}); delete it or pass --no-resume"
        ) from exc


def _data_seeds(
    cfg: DetectorTrainConfig, root: Path, train_set: Any, parts: list, val_data: PoseDataset
) -> dict[str, Any]:
    """Which data the run trains and validates on, as its checkpoint records it."""
    return {
        "dataset": str(root),
        "dataset_seed_bases": load_info(root).get("seed_bases", {}),
        "train_images": len(train_set),
        "also": {name: len(part) for name, part in zip(cfg.also, parts[1:], strict=True)},
        "init": None if cfg.init is None else str(cfg.init),
        "val_images": min(cfg.val_images, len(val_data)),
        "order_seed": "seed * 1000 + epoch",
        "seed": cfg.seed,
    }


def detection_loss(
    cfg: DetectorTrainConfig,
    net: nn.Module,
    images: list[torch.Tensor],
    targets: list[dict[str, torch.Tensor]],
    device: torch.device,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The training loss of a shard of augmented images: the forward pass in the run's precision
    (with channels-last weights the convolutions lay out their feature maps so too), its parts and
    their sum in fp32.

    Returns:
        The loss, and its parts (Mask R-CNN's: objectness, RPN boxes, classes, boxes, masks).
    """
    with autocast(cfg.precision, device):
        parts = net(images, targets)
    parts = {k: v.float() for k, v in parts.items()}
    return sum(parts.values()), parts
