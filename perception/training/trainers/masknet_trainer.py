"""The training of the mask net (`perception.mask_net`) on rendered scenes (its command line:
`perception.training.train_masknet`), for the tiers' or the paper protocol's images
(`PROTOCOLS`).

A run trains on windows cut once around each visible object (`perception.training.trainers.
mask_windows`): their coarse input is drawn for each batch from the true mask (`degrade`), or is a
detector's own mask for the windows cut around it. The loss is the binary cross-entropy with the
true mask's coverage of each window pixel; validation measures the IoU of the net's masks with
the truth, also on the detector's masks of the validation scenes when the run has them.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch

from perception.detector import PAPER_DETECTOR
from perception.mask_net import (
    DEFAULT_MASKNET,
    PAPER_MASKNET,
    PAPER_MASKNET_EXPERTS,
    MaskNet,
    MaskNetConfig,
    MaskRefiner,
    net_input,
)
from perception.training.data.dataset import format_data
from perception.training.trainers.checkpoints import (
    config_dict,
    read_checkpoint,
    restore,
    rng_state,
    save_checkpoint,
    seed_torch,
)
from perception.training.trainers.ddp import ONE_PROCESS
from perception.training.trainers.loop import Run, Step, autocast, fit
from perception.training.trainers.manifest import shipped_entry, stage_record
from perception.training.trainers.mask_windows import build_cache, degrade, detector_windows
from posegrasp.core.errors import AssetError, InvalidArgumentError
from posegrasp.core.files import sha256_file
from posegrasp.core.paths import checkpoint_dir, in_repo

#: The command line of this module.
TRAIN_COMMAND = "python -m perception.training.train_masknet"


@dataclass(frozen=True)
class MaskNetProtocol:
    """Which images a mask net is trained on, which detector's masks it redraws and where it
    ships.

    Attributes:
        sources: (split folder, images) pairs of training scenes.
        val: (split folder, images) of the validation scenes (their ``val`` split).
        detector: the detector whose masks ``--evaluate`` measures it on (None: the tiers').
        weights: where ``--export`` writes it.
        experts: the objects whose masks the net beside it serves instead
            (`perception.mask_net.expert_path`, ``--export --expert NAME``).
    """

    sources: tuple[tuple[str, int], ...]
    val: tuple[str, int]
    detector: Path | None
    weights: Path
    experts: tuple[str, ...] = ()


#: The mask nets by image protocol: the tiers' head-camera scenes (``hybrid-global``), whose
#: detector takes in part of an occluder and drops thin parts, and the paper's 256x256 studio
#: images on random backgrounds (``hybrid-global-paper``), whose detector misses whole parts of
#: an object and takes in background beside it (docs/DESIGN.md §7, "Mask refinement").
PROTOCOLS = {
    "tiers": MaskNetProtocol(
        (("headcam_hard", 9000), ("headcam_any-pose", 3000), ("headcam", 3000)),
        ("headcam_hard", 500),
        None,
        DEFAULT_MASKNET,
    ),
    "paper": MaskNetProtocol(
        (("paper", 30000),), ("paper", 1000), PAPER_DETECTOR, PAPER_MASKNET, PAPER_MASKNET_EXPERTS
    ),
}
#: The protocol of a run unless told (``--protocol``): its splits are a run's by default.
DEFAULT_PROTOCOL = "tiers"


@dataclass(frozen=True)
class MaskTrainConfig:
    """One training run.

    Attributes:
        sources: (split folder, images) pairs of training scenes.
        val: (split folder, images) of the validation scenes (their ``val`` split).
        heavy: coarse masks with whole parts lost and gained and windows jittered twice as far
            (`degrade`'s `heavy`, `_jittered_window`'s `spread`), as both protocols' detectors
            need; off, only outlines a pixel or two off.
        epochs, batch, lr, weight_decay: the schedule (one-cycle, AdamW).
        seed: of the windows' jitter, the batches' order and the coarse masks.
        precision, channels_last: the arithmetic (`perception.training.trainers.loop`).
        out: checkpoint folder (default ``<data>/checkpoints/masknet``).
        net: the net.
        init: a shipped mask net the run starts from (None: from scratch); its net must be
            `net`.
        detected: (split folder, first image, images) of further training scenes whose
            windows are cut around `detector`'s own masks, which are their coarse input as they
            are (`detector_windows`), instead of drawn from the truth (None: none). Validation
            then also measures the net on the detector's masks of the validation scenes.
        detector: the detector of `detected` (None: the tiers').
        checkpoint_minutes: save a resumable checkpoint at least this often.
    """

    sources: tuple[tuple[str, int], ...] = PROTOCOLS[DEFAULT_PROTOCOL].sources
    val: tuple[str, int] = PROTOCOLS[DEFAULT_PROTOCOL].val
    heavy: bool = True
    epochs: int = 3
    batch: int = 32
    lr: float = 2e-3
    weight_decay: float = 1e-4
    seed: int = 0
    precision: str = "bf16"
    channels_last: bool = True
    out: Path = field(default_factory=lambda: checkpoint_dir() / "masknet")
    net: MaskNetConfig = field(default_factory=MaskNetConfig)
    init: Path | None = None
    detected: tuple[str, int, int] | None = None
    detector: Path | None = None
    checkpoint_minutes: float = 5.0


def train(cfg: MaskTrainConfig, resume: bool = True, max_steps: int | None = None) -> dict:
    """Train (resuming from ``cfg.out/last.pt`` when asked and present: the same steps as a run
    never stopped); returns the last checkpoint's contents. `max_steps` stops the run, saved,
    after that many steps in all (as an interruption would).

    Raises:
        InvalidArgumentError: the checkpoint to resume belongs to a run of other epochs, batch,
            seed or start (its schedule or data would change under it).
        AssetError: `cfg.init` is missing, corrupt or of another net.
    """
    trainer = MaskNetTrainer(cfg)
    fit(
        trainer,
        cfg.epochs,
        resume=resume,
        checkpoint_minutes=cfg.checkpoint_minutes,
        max_steps=max_steps,
    )
    return read_checkpoint(trainer.ckpt)


class MaskNetTrainer:
    """The mask net's part of the training loop (`perception.training.trainers.loop.fit`): its
    windows, the coarse masks drawn for each batch, its step and its validation IoUs. One
    process, on the CPU.

    Args:
        cfg: the run.
    """

    def __init__(self, cfg: MaskTrainConfig) -> None:
        self.cfg, self.ranks = cfg, ONE_PROCESS
        self.label = "mask net"
        self.ckpt = cfg.out / "last.pt"
        self.g = torch.Generator()  # an epoch's order and coarse masks

    def start(self, resume: bool) -> Run:
        """The windows (`training_windows`), the net, its optimiser and schedule (`_start_run`);
        a run from a shipped net is first validated as it starts (epoch 0)."""
        cfg = self.cfg
        seed_torch(cfg.seed, None)
        self.windows = training_windows(cfg)
        run, self.sched, self.record, self.lineage = _start_run(cfg, self.windows, resume)
        cfg.out.mkdir(parents=True, exist_ok=True)
        self.data_seeds = _data_seeds(cfg, self.windows)
        if cfg.init is not None and not run.history:  # the start, on the same validation windows
            run.history.append({"epoch": 0, "step": 0, **self._ious(run)})
            print(f"start ({cfg.init}): {run.history[-1]}", flush=True)
        return run

    def batches(self, run: Run, epoch: int) -> Iterator[np.ndarray]:
        """The window indices of the epoch's batches not done yet, in the epoch's seeded order.

        The batches done before a resume draw their coarse masks all the same (`degrade`, whose
        draws the data never changes), so the steps after it draw as an unstopped run's did.
        """
        cfg = self.cfg
        self.g = torch.Generator().manual_seed(cfg.seed * 1000 + epoch)
        order = torch.randperm(len(self.windows.train["rgb"]), generator=self.g).numpy()
        done = run.done_in(epoch)
        for b in range(run.steps_per_epoch):
            if b < done:
                degrade(torch.zeros(cfg.batch, 1, 1), self.g, cfg.heavy)
                continue
            yield np.sort(order[b * cfg.batch : (b + 1) * cfg.batch])

    def step(self, run: Run, batch: np.ndarray, epoch: int) -> Step:
        """One optimiser step on the windows `batch`: their coarse masks drawn from the truth
        (the detector's own for its windows), the binary cross-entropy with the true coverage."""
        cfg, tr = self.cfg, self.windows.train
        t = torch.as_tensor(tr["target"][batch]).float() / 255
        coarse = degrade(t, self.g, cfg.heavy).numpy()
        first, detected = self.windows.first_detected, self.windows.detected
        if detected is not None and (mine := batch >= first).any():
            coarse[mine] = detected["coarse"][batch[mine] - first]
        x = net_input(tr["rgb"][batch], coarse)
        if cfg.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        with autocast(cfg.precision, self.ranks.device):
            logits = run.model(x)
        loss = torch.nn.functional.binary_cross_entropy_with_logits(logits.float()[:, 0], t)
        lr = run.opt.param_groups[0]["lr"]
        run.opt.zero_grad(set_to_none=True)
        loss.backward()
        run.opt.step()
        self.sched.step()
        return Step(loss, lr, {"loss": loss.detach()})

    def validate(self, run: Run, epoch: int) -> None:
        """The IoUs on the validation windows (`window_ious`), into the history and printed."""
        run.history.append({"epoch": epoch + 1, "step": run.step, **self._ious(run)})
        print(f"epoch {epoch + 1}: {run.history[-1]}", flush=True)

    def _ious(self, run: Run) -> dict[str, float]:
        """`window_ious` of the net on the run's validation windows."""
        w = self.windows
        return window_ious(cast("MaskNet", run.model), w.val, 0, self.cfg.heavy, w.val_detected)

    def save(self, run: Run, epoch: int, wall_s: float) -> None:
        """Write the run's checkpoint, with its schedule and the stages behind its start."""
        save_checkpoint(
            self.ckpt,
            run.model,
            run.opt,
            model_config=config_dict(self.cfg.net),
            train_config=self.record,
            step=run.step,
            epoch=epoch,
            history=run.history,
            rng=rng_state(),
            data_seeds=self.data_seeds,
            header={
                "kind": "masknet",
                "command": command_line(self.cfg),
                "scheduler": self.sched.state_dict(),
                "wall_s": wall_s,
                "lineage": self.lineage,
            },
        )


@dataclass
class Windows:
    """A run's windows (`build_cache`, `detector_windows`): what it trains and validates on.

    Attributes:
        train: ``rgb`` (N, S, S, 3) uint8 and ``target`` (N, S, S) uint8 of every training
            window, the drawn ones first, then the detector's.
        first_detected: where the detector's windows begin in `train` (N when there are none).
        detected: the detector's training windows with their ``coarse`` masks, or None.
        val: the validation windows (their coarse masks drawn, seed 0).
        val_detected: the detector's windows of the validation scenes, or None.
    """

    train: dict[str, np.ndarray]
    first_detected: int
    detected: dict[str, np.ndarray] | None
    val: dict[str, np.ndarray]
    val_detected: dict[str, np.ndarray] | None


def training_windows(cfg: MaskTrainConfig) -> Windows:
    """Cut (or read back from the cache) the windows of a run.

    Raises:
        AssetError: a split or the detector's weights are missing, or the detector found no
            object.
    """
    spread = 2.0 if cfg.heavy else 1.0
    parts = [build_cache(f, "train", n, cfg.net, cfg.seed, spread) for f, n in cfg.sources]
    first_detected = sum(len(p["rgb"]) for p in parts)
    detected = val_detected = None
    if cfg.detected is not None:
        folder, first, images = cfg.detected
        detected = detector_windows(folder, "train", first, images, cfg.net, cfg.detector)
        parts.append(detected)
        val_detected = detector_windows(cfg.val[0], "val", 0, cfg.val[1], cfg.net, cfg.detector)
    train = {k: np.concatenate([p[k] for p in parts]) for k in ("rgb", "target")}
    val = build_cache(cfg.val[0], "val", cfg.val[1], cfg.net, 0, spread)
    return Windows(train, first_detected, detected, val, val_detected)


def _start_run(
    cfg: MaskTrainConfig, windows: Windows, resume: bool
) -> tuple[Run, torch.optim.lr_scheduler.LRScheduler, dict[str, Any], dict[str, Any]]:
    """The net, fresh, started from `cfg.init`, or resumed from ``cfg.out/last.pt``; its
    one-cycle schedule; what the run was started with (epochs, batch, lr, seed, init, detected:
    its ``train_config``, which a resumed run must match); the stages that made the net it
    started from (``stages``).

    Raises:
        InvalidArgumentError: the checkpoint to resume belongs to a run of other epochs, batch,
            seed, start or detector windows.
        AssetError: `cfg.init` is missing, corrupt or of another net.
    """
    net = MaskNet(cfg.net)
    lineage = {"stages": []} if cfg.init is None else _start_from(net, cfg.init)
    record = {
        "epochs": cfg.epochs,
        "batch": cfg.batch,
        "lr": cfg.lr,
        "seed": cfg.seed,
        "init": None if cfg.init is None else str(cfg.init),
        "detected": None if cfg.detected is None else list(cfg.detected),
    }
    if cfg.channels_last:
        net = net.to(memory_format=torch.channels_last)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    run = Run(net, opt, steps_per_epoch=len(windows.train["rgb"]) // cfg.batch)
    total = run.steps_per_epoch * cfg.epochs
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, cfg.lr, total_steps=total, pct_start=0.15)
    last = cfg.out / "last.pt"
    if resume and last.is_file():
        state = read_checkpoint(last)
        was = state["train_config"]
        keys = ("epochs", "batch", "seed", "init", "detected")
        if any(was.get(k, 0 if k == "seed" else None) != record[k] for k in keys):
            started = " ".join(f"--{k} {was.get(k)}" for k in keys if was.get(k) is not None)
            raise InvalidArgumentError(
                f"the run in {cfg.out} was started with {started}; resume it with those, or "
                "start over with --no-resume"
            )
        run.step, run.epoch, run.history = restore(state, net, opt)
        lineage = state.get("lineage", lineage)
        sched.load_state_dict(state["scheduler"])
        run.wall_s = float(state["wall_s"])
    return run, sched, record, lineage


def _start_from(net: MaskNet, init: Path) -> dict[str, Any]:
    """Load the shipped mask net at `init` (hash checked) into `net`; returns the stages that
    made it, from its manifest (one unnamed stage when the manifest does not record it).

    Raises:
        AssetError: the file is missing or corrupt, or its net is not `net`'s.
    """
    shipped = MaskRefiner.from_weights(init).net
    if shipped.cfg != net.cfg:
        raise AssetError(f"{init} holds a mask net of {shipped.cfg}, this run trains {net.cfg}")
    net.load_state_dict(shipped.state_dict())
    entry = shipped_entry(init)
    if entry is None:
        return {"stages": [{"command": None, "init": str(init)}]}
    return {"stages": entry.get("stages") or [stage_record(entry)]}


def _data_seeds(cfg: MaskTrainConfig, windows: Windows) -> dict[str, Any]:
    """Which windows the run trains and validates on, as its checkpoint records it."""
    seeds = {
        "sources": dict(cfg.sources),
        "val": dict([cfg.val]),
        "windows": len(windows.train["rgb"]),
        "seed": cfg.seed,
        "val_seed": 0,
        "init": None if cfg.init is None else str(cfg.init),
        "init_sha256": None if cfg.init is None else sha256_file(cfg.init),
    }
    if cfg.detected is not None:
        seeds |= {
            "detected": list(cfg.detected),
            "detected_windows": len(windows.train["rgb"]) - windows.first_detected,
            "detector": None if cfg.detector is None else str(in_repo(cfg.detector)),
            "detector_sha256": sha256_file(cfg.detector) if cfg.detector else None,
        }
    return seeds


@torch.inference_mode()
def window_ious(
    net: MaskNet,
    val: dict[str, np.ndarray],
    seed: int,
    heavy: bool = False,
    detected: dict[str, np.ndarray] | None = None,
) -> dict[str, float]:
    """Mean IoU with the true mask (coverage >= 0.5) of the degraded input and of the net's
    mask, on the validation windows (their coarse masks seeded, the same every epoch); with
    `detected` (`detector_windows`), also of the detector's masks (``detector_iou``) and of the
    net's redrawing of them (``detected_iou``)."""
    net.eval()
    extra: dict[str, float] = {}
    if detected is not None:
        given, redrawn = [], []
        for i in range(0, len(detected["rgb"]), 256):
            c = detected["coarse"][i : i + 256]
            truth = torch.as_tensor(detected["target"][i : i + 256]) >= 128
            logits = net(net_input(detected["rgb"][i : i + 256], c.astype(np.float32)))[:, 0]
            given.append(_iou(torch.as_tensor(c) > 0, truth))
            redrawn.append(_iou(logits >= 0, truth))
        extra = {
            "detector_iou": float(torch.cat(given).mean()),
            "detected_iou": float(torch.cat(redrawn).mean()),
        }
    g = torch.Generator().manual_seed(seed)
    before, after = [], []
    for i in range(0, len(val["rgb"]), 256):
        t = torch.as_tensor(val["target"][i : i + 256]).float() / 255
        coarse = degrade(t, g, heavy)
        logits = net(net_input(val["rgb"][i : i + 256], coarse.numpy()))[:, 0]
        truth = t >= 0.5
        before.append(_iou(coarse >= 0.5, truth))
        after.append(_iou(logits >= 0, truth))
    return {
        "coarse_iou": float(torch.cat(before).mean()),
        "iou": float(torch.cat(after).mean()),
        **extra,
    }


def _iou(pred: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Per-window IoU of boolean masks (B, S, S)."""
    inter = (pred & truth).flatten(1).sum(1).float()
    union = (pred | truth).flatten(1).sum(1).float()
    return torch.where(union > 0, inter / union.clamp(min=1), torch.ones_like(inter))


def command_line(cfg: MaskTrainConfig) -> str:
    """The CLI command that runs `cfg` (as far as the CLI exposes it: the protocol whose
    validation scenes it has, then what it changes), in the trainers' shared spelling."""
    protocol = next((k for k, v in PROTOCOLS.items() if v.val == cfg.val), DEFAULT_PROTOCOL)
    proto, d = PROTOCOLS[protocol], MaskTrainConfig
    options = (
        (cfg.lr != d.lr, f"--lr {cfg.lr:g}"),
        (cfg.batch != d.batch, f"--batch {cfg.batch}"),
        (cfg.seed != d.seed, f"--seed {cfg.seed}"),
        (cfg.precision != d.precision, f"--precision {cfg.precision}"),
        (cfg.channels_last, "--channels-last"),
        (cfg.init is not None, f"--init {cfg.init}"),
        (cfg.detected is not None, f"--detected {cfg.detected and cfg.detected[2]}"),
        (cfg.detector not in (None, proto.detector), f"--detector {cfg.detector}"),
        (cfg.val != proto.val, f"--val {format_data((cfg.val,))}"),
        (True, f"--out {cfg.out}"),
    )
    head = [TRAIN_COMMAND, f"--protocol {protocol}", f"--data {format_data(cfg.sources)}"]
    head.append(f"--epochs {cfg.epochs}")
    return " ".join(head + [text for wanted, text in options if wanted])
