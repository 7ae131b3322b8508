"""The training of the 2D/4D pose nets on our renders (its command line:
`perception.training.train_posenet`).

Crops are cut once per split with the paper's imprecise boxes and cached next to the data
(`perception.training.data.crop_sets`). Training is seeded, checkpoints every epoch and every
few minutes with everything needed to resume or rebuild the model (weights, model config,
optimiser, step, RNG states, data seeds, commit; `perception.training.trainers.checkpoints`), and
validates each epoch (`perception.training.evals.posenet_eval`). Under torchrun the run is
data-parallel over the processes (`perception.training.trainers.ddp`): same global batch, each
rank its shard of it, rank 0 validating and writing the checkpoint.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar, cast

import numpy as np
import torch
from torch import nn

from perception.nets import CROP, NetConfig, PoseNet, PoseOutput, load_posenet, normalise
from perception.training.data.crop_sets import CropConfig, data_seed_ranges, split_crops
from perception.training.data.dataset import DISTS, format_data
from perception.training.evals.posenet_eval import evaluate_arrays
from perception.training.trainers.augment import photometric_jitter
from perception.training.trainers.checkpoints import (
    config_dict,
    read_checkpoint,
    restore,
    rng_state,
    save_checkpoint,
    seed_torch,
)
from perception.training.trainers.ddp import Ranks, joined
from perception.training.trainers.loop import PRECISIONS, Run, Step, autocast, fit
from perception.training.trainers.losses import posenet_loss
from perception.training.trainers.manifest import shipped_stages
from perception.training.trainers.schedule import learning_rate, optimiser_step
from posegrasp.core.errors import AssetError, InvalidArgumentError
from posegrasp.core.paths import checkpoint_dir
from posegrasp.core.validate import check_choice
from posegrasp.world.objects import OBJECT_NAMES

#: The command line of this module.
TRAIN_COMMAND = "python -m perception.training.train_posenet"
#: What a fine-tuning run keeps of the checkpoint it starts from.
LINEAGE_KEYS = ("command", "init_from", "train_config", "epoch", "wall_s", "data_seeds", "commit")
#: Gradient-norm clip of every step.
GRAD_CLIP = 5.0

_M = TypeVar("_M", bound=nn.Module)


@dataclass(frozen=True)
class PoseNetTrainConfig:
    """A training run of the pose nets.

    Attributes:
        variant: "paper" or "ours".
        dists: which data distributions to train on.
        epochs, batch, lr, weight_decay, lam: optimisation (lam weighs the rotation loss).
        decay: cosine decay of the learning rate after the warm-up (False: constant).
        width: backbone width.
        rotation: rotation output of "ours" (`perception.nets.ROTATIONS`).
        augment: photometric jitter of the training crops.
        objects: train and validate on these objects' crops only (empty: all), as the paper's
            one-net-per-object design does.
        crops: how crops are cut.
        limit: use at most this many images per split (None: all).
        dist_limits: per-distribution image limits, ((dist, images), ...), on top of `limit`.
        init: checkpoint whose weights start this run (fine-tuning: fresh optimiser and
            schedule); its record is kept in this run's checkpoint.
        name: checkpoint file stem (default "posenet_<variant>").
        seed: seed of initialisation and batching.
        out: checkpoint folder; None means `checkpoint_dir()` (next to the data, outside git).
        checkpoint_minutes: save a resumable checkpoint at least this often.
        max_theta_deg: "paper" trains only on rolls within this range, as published.
        threads: torch CPU threads per process (None: the cores shared by the processes).
        device: "auto", "cpu" or "cuda" (`perception.training.trainers.ddp.DEVICES`).
        loss_log: append one JSON line per step here (step, epoch, loss averaged over the
            processes, lr), or None.
        teacher: distillation: pose-net weights whose outputs on each training batch are a
            second target, weighted as the labels are (None: labels only).
        precision: arithmetic of the training forward passes (`PRECISIONS`): "fp32", or
            "bf16", under `torch.autocast` with bfloat16; the loss is computed in fp32 either way,
            and validation runs in fp32.
        channels_last: keep the model's weights and its input crops in channels-last memory
            layout (`torch.channels_last`).
    """

    variant: str = "ours"
    dists: tuple[str, ...] = DISTS
    epochs: int = 7
    batch: int = 128
    lr: float = 2e-3
    weight_decay: float = 1e-4
    lam: float = 1.0
    decay: bool = True
    width: int = 16
    rotation: str = "view-roll"
    augment: bool = True
    objects: tuple[str, ...] = ()
    crops: CropConfig = field(default_factory=CropConfig)
    limit: int | None = None
    dist_limits: tuple[tuple[str, int], ...] = ()
    init: str | None = None
    name: str | None = None
    seed: int = 0
    out: Path | None = None
    checkpoint_minutes: float = 5.0
    max_theta_deg: float = 60.0
    threads: int | None = None
    device: str = "auto"
    loss_log: Path | None = None
    teacher: Path | None = None
    precision: str = "fp32"
    channels_last: bool = False

    def __post_init__(self) -> None:
        check_choice(self.precision, PRECISIONS, "precision")
        if bad := sorted(set(self.objects) - set(OBJECT_NAMES)):
            raise InvalidArgumentError(f"unknown objects {bad}; valid: {', '.join(OBJECT_NAMES)}")
        self.net_config()  # checks variant, width, crop side and rotation output

    def net_config(self) -> NetConfig:
        """The model this run trains."""
        return NetConfig(
            self.variant, len(OBJECT_NAMES), self.width, self.crops.size, self.rotation
        )

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for checkpoints (paths as strings)."""
        return config_dict(self)


SMOKE = PoseNetTrainConfig(epochs=1, batch=16, limit=12, out=Path("out/smoke"), width=4)


def _limit(cfg: PoseNetTrainConfig, dist: str) -> int | None:
    """Images per split of `dist` that a run uses (None: all)."""
    lims = [n for d, n in cfg.dist_limits if d == dist] + ([cfg.limit] if cfg.limit else [])
    return min(lims) if lims else None


def checkpoint_path(cfg: PoseNetTrainConfig) -> Path:
    """Where a run keeps its checkpoint."""
    return (cfg.out or checkpoint_dir()) / f"{cfg.name or 'posenet_' + cfg.variant}.pt"


def _resolve_init(init: str, out: Path) -> Path:
    """`init` as a path, or as a checkpoint name in the checkpoint folder."""
    for cand in (Path(init), out / init, out / f"{init}.pt"):
        if cand.is_file():
            return cand
    raise AssetError(
        f"no checkpoint {init!r} (looked for it as a path and in {out}); train it first"
    )


def command_line(cfg: PoseNetTrainConfig) -> str:
    """The CLI command that runs `cfg` (as far as the CLI exposes it), in the trainers' shared
    spelling (``--data NAME=COUNT,...``)."""
    d = PoseNetTrainConfig
    data = format_data(tuple((dist, _limit(cfg, dist)) for dist in cfg.dists))
    options = (
        (cfg.lr != d.lr, f"--lr {cfg.lr:g}"),
        (cfg.batch != d.batch, f"--batch {cfg.batch}"),
        (cfg.seed != d.seed, f"--seed {cfg.seed}"),
        (cfg.width != d.width or cfg.lam != d.lam, f"--width {cfg.width} --lam {cfg.lam:g}"),
        (bool(cfg.objects), f"--objects {','.join(cfg.objects)}"),
        (cfg.crops.size != CROP, f"--crop {cfg.crops.size}"),
        (cfg.rotation != d.rotation, f"--rotation {cfg.rotation}"),
        (not cfg.augment, "--no-augment"),
        (not cfg.decay, "--constant-lr"),
        (cfg.precision != d.precision, f"--precision {cfg.precision}"),
        (cfg.channels_last, "--channels-last"),
        (bool(cfg.init), f"--init {cfg.init}"),
        (bool(cfg.name), f"--name {cfg.name}"),
        (cfg.out is not None, f"--out {cfg.out}"),
    )
    head = [TRAIN_COMMAND, f"--variant {cfg.variant}", f"--data {data}", f"--epochs {cfg.epochs}"]
    return " ".join(head + [text for wanted, text in options if wanted])


def train(cfg: PoseNetTrainConfig, resume: bool = True, command: str | None = None) -> dict:
    """Train (resuming from the run's checkpoint when present) and return the history.

    With `cfg.init`, the model starts from that checkpoint's weights; a resumed run ignores it
    and continues from its own checkpoint. Under torchrun every process calls this and the run
    is data-parallel (`perception.training.trainers.ddp`).

    Args:
        cfg: the run.
        resume: continue from the run's checkpoint (`checkpoint_path`) if it exists.
        command: the command recorded in the checkpoint (default: the CLI command of `cfg`).

    Returns:
        ``{"checkpoint": path, "history": [per-epoch validation (`evaluate_arrays`)]}``.

    Raises:
        AssetError: no data or no training crops, or an `init` checkpoint that is missing or
            holds another architecture.
        InvalidArgumentError: a device that is not there, or a batch the processes cannot share.
    """
    with joined(cfg.device, cfg.batch) as ranks:
        trainer = PoseNetTrainer(cfg, ranks, command)
        run, _ = fit(
            trainer,
            cfg.epochs,
            resume=resume,
            checkpoint_minutes=cfg.checkpoint_minutes,
            loss_log=cfg.loss_log,
        )
    return {"checkpoint": str(trainer.ckpt), "history": run.history}


class PoseNetTrainer:
    """The pose nets' part of the training loop (`perception.training.trainers.loop.fit`): the
    run's crops, its net (and a teacher when distilling), its step and its validation.

    Args:
        cfg: the run.
        ranks: this process's place in it.
        command: the command its checkpoint records (None: the CLI command of `cfg`).
    """

    def __init__(self, cfg: PoseNetTrainConfig, ranks: Ranks, command: str | None) -> None:
        self.cfg, self.ranks, self.command = cfg, ranks, command
        self.label = cfg.variant
        self.ckpt = checkpoint_path(cfg)
        self.g = torch.Generator().manual_seed(cfg.seed)  # the order and jitter of the batches

    def start(self, resume: bool) -> Run:
        """The crops, the model and its optimiser (`_start_run`), wrapped for the processes."""
        cfg, ranks = self.cfg, self.ranks
        seed_torch(cfg.seed, ranks.threads(cfg.threads))
        self.tr, self.va, self.data_seeds = _training_crops(cfg, ranks)
        run, self.lineage = _start_run(cfg, ranks, resume, self.command, len(self.tr["crops"]))
        self.net = ranks.wrap(_laid_out(cfg, run.model))  # the model itself with one process
        with torch.random.fork_rng():  # building the teacher leaves the run's random stream alone
            teacher = load_posenet(cfg.teacher, verify=False) if cfg.teacher else None
        self.teacher = None if teacher is None else _laid_out(cfg, teacher).to(ranks.device)
        return run

    def batches(self, run: Run, epoch: int) -> Iterator[dict[str, torch.Tensor]]:
        """This rank's shards of the epoch's batches not done yet (`BATCH_KEYS`).

        The epoch's order is drawn from the run's generator seeded by the epoch, so a run resumed
        mid-epoch skips the batches it has done and continues with the same ones.
        """
        cfg = self.cfg
        self.g.manual_seed(cfg.seed * 1000 + epoch)
        order = torch.randperm(len(self.tr["crops"]), generator=self.g).numpy()
        for b in range(run.done_in(epoch), run.steps_per_epoch):
            idx = self.ranks.shard(order[b * cfg.batch : (b + 1) * cfg.batch])
            yield batch_tensors(self.tr, idx, self.ranks.device)

    def step(self, run: Run, batch: dict[str, torch.Tensor], epoch: int) -> Step:
        """One optimiser step on this rank's shard `batch`; shows the parts of its loss."""
        cfg = self.cfg
        x = training_inputs(cfg, batch, self.g, self.ranks)
        loss, parts = training_loss(cfg, self.net, self.teacher, x, batch)
        lr = learning_rate(run.step, cfg.epochs * run.steps_per_epoch, cfg.lr, decay=cfg.decay)
        optimiser_step(run.model, run.opt, loss, lr, GRAD_CLIP)
        return Step(loss, lr, parts)

    def validate(self, run: Run, epoch: int) -> None:
        """The pose errors on the val crops (`evaluate_arrays`), into the history and printed."""
        model = cast("PoseNet", self.ranks.on_cpu(run.model))
        val = evaluate_arrays(model, self.va)  # it works on the CPU
        run.history.append({"epoch": epoch + 1, "step": run.step, **val})
        print(
            f"epoch {epoch + 1}: val centre {val['center_px']:.2f} px, distance "
            f"{val['distance_pct']:.2f} %, rotation {val['rotation_deg']:.2f} deg, "
            f"outliers {val['outlier_rate']:.1%}"
        )

    def save(self, run: Run, epoch: int, wall_s: float) -> None:
        """Write the run's checkpoint (rank 0; the others only keep the wall time)."""
        self.lineage["wall_s"] = wall_s
        if self.ranks.main:
            save_checkpoint(
                self.ckpt,
                run.model,
                run.opt,
                model_config=self.cfg.net_config().to_dict(),
                train_config=self.cfg.to_dict(),
                step=run.step,
                epoch=epoch,
                history=run.history,
                rng=rng_state(),
                data_seeds=self.data_seeds,
                header=self.lineage,
            )


def _training_crops(cfg: PoseNetTrainConfig, ranks: Ranks) -> tuple[dict, dict, dict[str, Any]]:
    """The run's train and val crops and the seeds of the images they come from.

    Rank 0 cuts and caches the crops first; the other ranks then read its cache.

    Raises:
        AssetError: no data, or no training crops left.
    """
    if not ranks.main:
        ranks.barrier()
    limits = {d: _limit(cfg, d) for d in cfg.dists}
    tr, va = (split_crops(cfg.dists, part, cfg.crops, limits) for part in ("train", "val"))
    if ranks.main:
        ranks.barrier()
    if cfg.variant == "paper":
        keep = np.abs(np.rad2deg(tr["theta"])) <= cfg.max_theta_deg
        tr = {k: v[keep] for k, v in tr.items()}
    if cfg.objects:  # one net per object: only its crops
        ids = [OBJECT_NAMES.index(o) for o in cfg.objects]
        tr, va = ({k: v[np.isin(d["cls"], ids)] for k, v in d.items()} for d in (tr, va))
    if len(tr["crops"]) == 0:
        raise AssetError("no training crops; generate data first (`make data`)")
    return tr, va, data_seed_ranges(cfg.dists, {d: n for d, n in limits.items() if n})


def _start_run(
    cfg: PoseNetTrainConfig, ranks: Ranks, resume: bool, command: str | None, n_train: int
) -> tuple[Run, dict[str, Any]]:
    """The model and optimiser, fresh, started from `cfg.init`, or resumed from the run's own
    checkpoint, and the checkpoint's header: command, the run it started from, wall time.

    Args:
        cfg: the run.
        ranks: this process's place in it.
        resume: continue from the run's checkpoint if it exists.
        command: the command to record (None: the CLI command of `cfg`).
        n_train: training crops.

    Raises:
        AssetError: an `init` checkpoint that is missing or holds another architecture.
    """
    model = PoseNet(cfg.net_config())
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    ckpt = checkpoint_path(cfg)
    ckpt.parent.mkdir(parents=True, exist_ok=True)
    lineage: dict[str, Any] = {
        "command": command or command_line(cfg),
        "init_from": None,
        "wall_s": 0.0,
    }
    resuming = resume and ckpt.is_file()
    if cfg.init and not resuming:
        lineage["init_from"] = _start_from(model, _resolve_init(cfg.init, ckpt.parent))
    run = Run(model, opt, steps_per_epoch=max(1, n_train // cfg.batch))
    if resuming:
        state = read_checkpoint(ckpt)
        lineage = {k: state.get(k, v) for k, v in lineage.items()}
        run.step, run.epoch, run.history = restore(state, model, opt)
        if ranks.main:
            print(f"resuming {ckpt} at epoch {run.epoch}, step {run.step}")
    run.wall_s = float(lineage.get("wall_s") or 0.0)  # over resumptions
    return run, lineage


def _start_from(model: PoseNet, src: Path) -> dict[str, Any]:
    """Load the weights of the checkpoint or shipped file `src` into `model`; its record, which
    the run keeps as its ``init_from``.

    Raises:
        AssetError: `src` holds another architecture.
    """
    parent = read_checkpoint(src)
    if NetConfig(**parent["model_config"]) != model.cfg:  # older files: fields defaulted
        raise AssetError(f"{src} holds a {parent['model_config']} model, not {model.cfg.to_dict()}")
    model.load_state_dict(parent["model"])
    return {
        "checkpoint": src.name,
        **{k: parent.get(k) for k in LINEAGE_KEYS},
        "validation": parent["history"][-1] if parent.get("history") else None,
        # Shipped weights carry no lineage of their own: their manifest's stages stand in.
        "stages": shipped_stages(src),
    }


#: The crop-set arrays a training step takes.
BATCH_KEYS = ("crops", "cls", "scale", "uv_unit", "p", "theta")


def _laid_out(cfg: PoseNetTrainConfig, model: _M) -> _M:
    """`model`, its weights moved to channels-last layout when the run asks for it (the same
    parameter objects, so an optimiser over them still holds)."""
    return model.to(memory_format=torch.channels_last) if cfg.channels_last else model


def batch_tensors(tr: dict, idx: np.ndarray, device: torch.device) -> dict[str, torch.Tensor]:
    """The rows `idx` of the crop set `tr` as the tensors a training step takes (`BATCH_KEYS`)."""
    return {k: torch.from_numpy(tr[k][idx]).to(device) for k in BATCH_KEYS}


def training_inputs(
    cfg: PoseNetTrainConfig, batch: dict[str, torch.Tensor], g: torch.Generator, ranks: Ranks
) -> torch.Tensor:
    """The net's input for a shard of a batch: normalised, jittered from `g` when the run
    augments, in channels-last layout when it asks for it."""
    x = normalise(batch["crops"])
    if cfg.augment:
        x = photometric_jitter(x, g, ranks)
    if cfg.channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    return x


def training_loss(
    cfg: PoseNetTrainConfig,
    net: nn.Module,
    teacher: nn.Module | None,
    x: torch.Tensor,
    batch: dict[str, torch.Tensor],
) -> tuple[torch.Tensor, dict[str, float]]:
    """The training loss of a shard: the forward passes in the run's precision, the loss on
    their outputs in fp32 (`posenet_loss`; plus the teacher's term when distilling).

    Args:
        cfg: the run.
        net: the model to train (or its data-parallel wrapper).
        teacher: distillation's teacher, or None.
        x: the input (`training_inputs`).
        batch: the shard's labels and classes (`BATCH_KEYS`).

    Returns:
        The loss, and its parts as numbers.
    """
    with autocast(cfg.precision, x.device):
        out = net(x, batch["cls"], batch["scale"])
    out = _fp32(out)
    loss, parts = posenet_loss(
        out, batch["uv_unit"], batch["p"], batch["theta"], cfg.variant, cfg.lam
    )
    if teacher is not None:
        with torch.no_grad(), autocast(cfg.precision, x.device):
            t = teacher(x, batch["cls"], batch["scale"])
        t = _fp32(t)
        loss = loss + posenet_loss(out, t.uv_unit, t.p, t.cs, cfg.variant, cfg.lam)[0]
    return loss, parts


def _fp32(out: PoseOutput) -> PoseOutput:
    """`out` in float32 (itself when it already is)."""
    if all(t.dtype == torch.float32 for t in (out.uv_unit, out.p, out.cs)):
        return out
    return PoseOutput(out.uv_unit.float(), out.p.float(), out.cs.float())
