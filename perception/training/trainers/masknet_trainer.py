"""The training of the mask net (`perception.mask_net`) on rendered scenes (its command
line: `perception.training.train_masknet`), and its measure on held-out images with the
detector's own masks: the tiers' or the paper protocol's (`PROTOCOLS`).

Each visible object of a training image (at least `MIN_VISIBLE_PX` visible pixels) gives one
window around its true visible mask, its centre and side jittered as a detector's box would be.
The windows are cut once into a cache (``$POSEGRASP_DATA/masknet``). The coarse input is drawn on
the batch from the true mask (`degrade`): averaged onto a coarse grid and drawn back, thresholded
at a random level, its thin parts opened away at random, with whole parts lost and gained, and
shifted by a few pixels. The loss is the binary cross-entropy with the true mask's coverage of
each window pixel. A run's further windows may be cut around a detector's own masks, which are
then their coarse input (`detector_windows`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch

from perception.detector import PAPER_DETECTOR, Detection, Detector
from perception.mask_net import (
    DEFAULT_MASKNET,
    PAPER_MASKNET,
    PAPER_MASKNET_EXPERTS,
    MaskNet,
    MaskNetConfig,
    MaskRefiner,
    cut,
    net_input,
    window_of,
)
from perception.metrics import mask_iou
from perception.training.data.dataset import PoseDataset, format_data
from perception.training.trainers.checkpoints import (
    config_dict,
    read_checkpoint,
    restore,
    rng_state,
    save_checkpoint,
    seed_torch,
)
from perception.training.trainers.loop import (
    Checkpointer,
    autocast,
)
from perception.training.trainers.manifest import shipped_entry, stage_record
from posegrasp.core.errors import AssetError, InvalidArgumentError
from posegrasp.core.files import sha256_file
from posegrasp.core.paths import checkpoint_dir, data_root, in_repo
from posegrasp.core.progress import progress_bar

#: The command line of this module.
TRAIN_COMMAND = "python -m perception.training.train_masknet"
#: Objects with fewer visible pixels give no training window.
MIN_VISIBLE_PX = 100
#: `detector_windows` keeps its windows in blocks of this many images.
DETECTED_BLOCK = 10000

#: A detection counts as an object's (`detector_windows`) from this score and mask IoU with it.
DETECTED_SCORE = 0.3
DETECTED_IOU = 0.3
#: The splits a run trains on by default and how many images of each.
DEFAULT_SOURCES = (("headcam_hard", 9000), ("headcam_any-pose", 3000), ("headcam", 3000))
VAL_SOURCE = ("headcam_hard", 500)


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
    "tiers": MaskNetProtocol(DEFAULT_SOURCES, VAL_SOURCE, None, DEFAULT_MASKNET),
    "paper": MaskNetProtocol(
        (("paper", 30000),), ("paper", 1000), PAPER_DETECTOR, PAPER_MASKNET, PAPER_MASKNET_EXPERTS
    ),
}


@dataclass(frozen=True)
class MaskTrainConfig:
    """One training run.

    Attributes:
        sources: (split folder, images) pairs of training scenes.
        val: (split folder, images) of the validation scenes (their ``val`` split).
        heavy: coarse masks with whole parts lost and gained and windows jittered twice as far
            (`degrade`'s `heavy`, `_jittered_window`'s `spread`), as both protocols' detectors
            need; off, only outlines a pixel or two off.
        epochs, batch, lr: the schedule (one-cycle, AdamW).
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
    """

    sources: tuple[tuple[str, int], ...] = DEFAULT_SOURCES
    val: tuple[str, int] = VAL_SOURCE
    heavy: bool = True
    epochs: int = 3
    batch: int = 32
    lr: float = 2e-3
    seed: int = 0
    precision: str = "bf16"
    channels_last: bool = True
    out: Path = field(default_factory=lambda: checkpoint_dir() / "masknet")
    net: MaskNetConfig = field(default_factory=MaskNetConfig)
    init: Path | None = None
    detected: tuple[str, int, int] | None = None
    detector: Path | None = None


def _jittered_window(
    mask: np.ndarray, margin: float, rng: np.random.Generator, spread: float = 1.0
) -> tuple[int, int, int] | None:
    """`window_of` the mask, its centre moved by about `spread` x 5 % of its side and its side
    scaled by about `spread` x 8 % at random (a detector's box is a little off)."""
    win = window_of(mask, margin)
    if win is None:
        return None
    x0, y0, side = win
    new = max(8, round(side * math.exp(rng.normal(0, 0.08 * spread))))
    dx, dy = rng.normal(0, 0.05 * spread * side, 2)
    return (
        round(x0 + (side - new) / 2 + dx),
        round(y0 + (side - new) / 2 + dy),
        new,
    )


def _kept(name: str) -> dict[str, np.ndarray] | None:
    """The windows kept as ``$POSEGRASP_DATA/masknet/<name>.npz``, None when not kept yet."""
    path = data_root() / "masknet" / f"{name}.npz"
    if not path.is_file():
        return None
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def _keep(name: str, cache: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Write `cache` as `_kept` reads it (whole or not at all) and return it."""
    path = data_root() / "masknet" / f"{name}.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **cast("dict[str, Any]", cache))  # NumPy: a key could be allow_pickle
    tmp.replace(path)
    return cache


def _split(root: Path, split: str) -> PoseDataset:
    """The rendered split under `root`.

    Raises:
        AssetError: it is missing (the message names ``make data``).
    """
    try:
        return PoseDataset(root, split)
    except (OSError, KeyError, ValueError) as exc:
        raise AssetError(
            f"no {split} split in {root} ({exc}); render it with `make data`"
        ) from None


def build_cache(
    folder: str, split: str, images: int, net: MaskNetConfig, seed: int, spread: float = 1.0
) -> dict[str, np.ndarray]:
    """The windows of the first `images` images of a split (jittered by `spread`,
    `_jittered_window`), cut once and kept in ``$POSEGRASP_DATA/masknet``: ``rgb`` (N, S, S, 3)
    uint8, ``target`` (N, S, S) uint8 (the true visible mask's coverage of each pixel, 0-255)
    and ``cls`` (N,) the class names.

    Raises:
        AssetError: the split is missing (the message names ``make data``).
    """
    root = data_root() / folder
    S = net.size
    name = f"{folder}_{split}_{images}_{S}_{net.margin}_{seed}" + (
        f"_{spread}" if spread != 1 else ""
    )
    if (kept := _kept(name)) is not None:
        return kept
    data = _split(root, split)
    n = min(images, len(data))
    rgbs, targets, names = [], [], []
    for i in progress_bar(range(n), desc=f"windows of {folder}/{split}", mininterval=5):
        sample = data[i]
        rng = np.random.default_rng([seed, i])
        for obj in sample.objects:
            if int(obj.mask_visib.sum()) < MIN_VISIBLE_PX:
                continue
            win = _jittered_window(obj.mask_visib, net.margin, rng, spread)
            assert win is not None
            rgbs.append(cut(sample.rgb, win, S))
            cover = cut(obj.mask_visib.astype(np.float32), win, S)
            targets.append(np.round(cover * 255).astype(np.uint8))
            names.append(obj.name)
    cache = {"rgb": np.stack(rgbs), "target": np.stack(targets), "cls": np.array(names)}
    return _keep(name, cache)


def best_detection(
    dets: list[Detection], name: str, truth: np.ndarray, least: float
) -> tuple[Detection | None, float]:
    """Of the detections `dets` of class `name`, the one whose mask overlaps the true visible
    mask `truth` most, with that mask IoU; (None, `least`) when none reaches `least`."""
    best, best_iou = None, least
    for d in dets:
        if d.name == name and (iou := mask_iou(d.mask, truth)) >= best_iou:
            best, best_iou = d, iou
    return best, best_iou


def detector_windows(
    folder: str,
    split: str,
    first: int,
    images: int,
    net: MaskNetConfig,
    detector_path: Path | None,
) -> dict[str, np.ndarray]:
    """Windows of images ``first .. first + images - 1`` of a split as the estimator cuts them:
    around the mask of the detector's detection of each visible object (the same class, score
    >= `DETECTED_SCORE`, the largest mask IoU with the truth, at least `DETECTED_IOU`), with
    that mask as the coarse input. Kept in ``$POSEGRASP_DATA/masknet`` as `build_cache`'s, with
    ``coarse`` (N, S, S) uint8 in {0, 1}, in blocks of `DETECTED_BLOCK` images from `first`: a
    longer run reuses the blocks of a shorter one, and an interrupted one keeps the blocks it
    finished. Objects the detector misses give no window.

    Raises:
        AssetError: the split is missing (the message names ``make data``), the detector's
            weights are, or the detector found no object at all.
    """
    from perception.detector import TIERS_DETECTOR

    path_of_detector = detector_path or TIERS_DETECTOR
    tag = sha256_file(path_of_detector)[:12] if path_of_detector.is_file() else "missing"
    data = _split(data_root() / folder, split)
    last = min(first + images, len(data))
    detector, desc = None, f"detections of {folder}/{split}"
    blocks = []
    for start in range(first, last, DETECTED_BLOCK):
        images_here = range(start, min(start + DETECTED_BLOCK, last))
        name = f"{folder}_{split}_{start}+{len(images_here)}_{net.size}_{net.margin}_detected_{tag}"
        if (kept := _kept(name)) is None:
            detector = detector or Detector.from_weights(path_of_detector)
            kept = _keep(name, _detected_block(data, images_here, net, detector, desc))
        blocks.append(kept)
    out = {k: np.concatenate([b[k] for b in blocks]) for k in blocks[0]} if blocks else {}
    if not out or not len(out["cls"]):
        raise AssetError(f"the detector found no object in {folder}/{split} {first}+{images}")
    return out


def _detected_block(
    data: PoseDataset, images: range, net: MaskNetConfig, detector: Detector, desc: str
) -> dict[str, np.ndarray]:
    """`detector_windows` of the `images` of `data` (empty arrays when the detector finds none
    of their objects)."""
    S = net.size
    rgbs, coarse, targets, names = [], [], [], []
    for i in progress_bar(images, desc=desc, mininterval=5):
        sample = data[i]
        dets = detector.detect(sample.rgb, DETECTED_SCORE)
        for obj in sample.objects:
            truth = obj.mask_visib
            if int(truth.sum()) < MIN_VISIBLE_PX:
                continue
            best, _ = best_detection(dets, obj.name, truth, DETECTED_IOU)
            win = None if best is None else window_of(best.mask, net.margin)
            if win is None:
                continue
            assert best is not None  # win is None when best is
            rgbs.append(cut(sample.rgb, win, S))
            coarse.append((cut(best.mask.astype(np.float32), win, S) >= 0.5).astype(np.uint8))
            cover = cut(truth.astype(np.float32), win, S)
            targets.append(np.round(cover * 255).astype(np.uint8))
            names.append(obj.name)
    return {
        "rgb": np.asarray(rgbs, np.uint8).reshape(-1, S, S, 3),
        "coarse": np.asarray(coarse, np.uint8).reshape(-1, S, S),
        "target": np.asarray(targets, np.uint8).reshape(-1, S, S),
        "cls": np.array(names, dtype=str),
    }


def _lose_and_gain(coarse: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """Coarse masks (B, 1, S, S) with, each with probability one half, a disc cut out of the
    object and a disc of background added beside it: centred 0.5-1.3 of the object's radius
    (that of a disc of its area) from its centre, in a random direction, with a radius of
    0.3-0.8 of it."""
    B, _, S, _ = coarse.shape
    yy, xx = torch.meshgrid(torch.arange(S).float(), torch.arange(S).float(), indexing="ij")
    draws = torch.rand(B, 2, 4, generator=g)
    out = coarse.clone()
    for b in range(B):
        pixels = out[b, 0].nonzero().float()
        if len(pixels) == 0:
            continue
        cy, cx = pixels.mean(0)
        extent = math.sqrt(len(pixels) / math.pi)
        for k, cut_out in enumerate((True, False)):
            on, turn, away, size = (float(v) for v in draws[b, k])
            if on < 0.5:
                continue
            angle, dist = 2 * math.pi * turn, extent * (0.5 + 0.8 * away)
            y, x = cy + dist * math.sin(angle), cx + dist * math.cos(angle)
            disc = (yy - y) ** 2 + (xx - x) ** 2 <= (extent * (0.3 + 0.5 * size)) ** 2
            out[b, 0] = out[b, 0] * ~disc if cut_out else torch.maximum(out[b, 0], disc.float())
    return out


def degrade(target: torch.Tensor, g: torch.Generator, heavy: bool = False) -> torch.Tensor:
    """Coarse masks (B, S, S) in {0, 1} drawn from true coverages (B, S, S) in [0, 1], as the
    detector draws them: averaged onto a grid of 10-32 cells across the window and drawn back
    bilinearly, thresholded at 0.35-0.65, thin parts opened away (kernel 1, 3 or 5 px) in half
    of them, shifted by up to 2 px. With `heavy`, whole parts are also lost and gained
    (`_lose_and_gain`) before the shift, which goes up to 4 px."""
    B, S, _ = target.shape
    x = target[:, None].float()
    out = torch.empty_like(x)
    groups = torch.randint(0, 4, (B,), generator=g)
    for k in range(4):  # a few grid sizes per batch
        idx = (groups == k).nonzero()[:, 0]
        if len(idx) == 0:
            continue
        cells = int(torch.randint(10, 33, (1,), generator=g))
        low = torch.nn.functional.adaptive_avg_pool2d(x[idx], cells)
        out[idx] = torch.nn.functional.interpolate(
            low, size=(S, S), mode="bilinear", align_corners=False
        )
    level = 0.35 + 0.3 * torch.rand(B, 1, 1, 1, generator=g)
    coarse = (out >= level).float()
    opened = torch.rand(B, generator=g) < 0.5
    kernel = int(torch.randint(0, 3, (1,), generator=g)) * 2 + 1
    if kernel > 1 and opened.any():
        pad = kernel // 2
        sub = coarse[opened]
        eroded = -torch.nn.functional.max_pool2d(-sub, kernel, 1, pad)
        coarse[opened] = torch.nn.functional.max_pool2d(eroded, kernel, 1, pad)
    if heavy:
        coarse = _lose_and_gain(coarse, g)
    reach = 4 if heavy else 2
    dx, dy = (int(v) for v in torch.randint(-reach, reach + 1, (2,), generator=g))
    return torch.roll(coarse[:, 0], shifts=(dy, dx), dims=(1, 2))


def _iou(pred: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Per-window IoU of boolean masks (B, S, S)."""
    inter = (pred & truth).flatten(1).sum(1).float()
    union = (pred | truth).flatten(1).sum(1).float()
    return torch.where(union > 0, inter / union.clamp(min=1), torch.ones_like(inter))


@torch.inference_mode()
def validate(
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


@dataclass
class _Run:
    """A run's net, optimiser and schedule, and where it stands (updated as it trains).

    Attributes:
        net: the net (channels-last when the run asks for it).
        opt, sched: its optimiser and one-cycle schedule.
        steps_per_epoch: the plan.
        record: what the run was started with (epochs, batch, lr, seed, init, detected), its
            ``train_config``; a resumed run must match it.
        lineage: the stages that made the net it started from (``stages``).
        step, epoch: optimiser steps and whole epochs done.
        history: per-epoch validation.
        wall0: wall time before this process resumed it [s].
    """

    net: MaskNet
    opt: torch.optim.Optimizer
    sched: torch.optim.lr_scheduler.LRScheduler
    steps_per_epoch: int
    record: dict[str, Any]
    lineage: dict[str, Any]
    step: int = 0
    epoch: int = 0
    history: list[dict] = field(default_factory=list)
    wall0: float = 0.0


def _start_run(cfg: MaskTrainConfig, windows: Windows, resume: bool) -> _Run:
    """The net, fresh, started from `cfg.init`, or resumed from ``cfg.out/last.pt``.

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
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=1e-4)
    steps_per_epoch = len(windows.train["rgb"]) // cfg.batch
    total = steps_per_epoch * cfg.epochs
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, cfg.lr, total_steps=total, pct_start=0.15)
    run = _Run(net, opt, sched, steps_per_epoch, record, lineage)
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
        run.lineage = state.get("lineage", lineage)
        sched.load_state_dict(state["scheduler"])
        run.wall0 = float(state["wall_s"])
    return run


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


def train(cfg: MaskTrainConfig, resume: bool = True, max_steps: int | None = None) -> dict:
    """Train (resuming from ``cfg.out/last.pt`` when asked and present: the same steps as a run
    never stopped); returns the last checkpoint's contents. `max_steps` stops the run, saved,
    after that many steps in all (as an interruption would).

    Raises:
        InvalidArgumentError: the checkpoint to resume belongs to a run of other epochs, batch,
            seed or start (its schedule or data would change under it).
        AssetError: `cfg.init` is missing, corrupt or of another net.
    """
    seed_torch(cfg.seed, None)
    windows = training_windows(cfg)
    run = _start_run(cfg, windows, resume)
    cfg.out.mkdir(parents=True, exist_ok=True)
    last = cfg.out / "last.pt"
    data_seeds = _data_seeds(cfg, windows)
    if cfg.init is not None and not run.history:  # the start, on the same validation windows
        val = validate(run.net, windows.val, 0, cfg.heavy, windows.val_detected)
        run.history.append({"epoch": 0, "step": 0, **val})
        print(f"start ({cfg.init}): {run.history[-1]}", flush=True)

    def save(done: int, wall_s: float) -> None:
        save_checkpoint(
            last,
            run.net,
            run.opt,
            model_config=config_dict(cfg.net),
            train_config=run.record,
            step=run.step,
            epoch=done,
            history=run.history,
            rng=rng_state(),
            data_seeds=data_seeds,
            header={
                "kind": "masknet",
                "command": command_line(cfg),
                "scheduler": run.sched.state_dict(),
                "wall_s": wall_s,
                "lineage": run.lineage,
            },
        )

    _train_epochs(cfg, windows, run, Checkpointer(save, minutes=5, wall_s=run.wall0), max_steps)
    return read_checkpoint(last)


def _train_epochs(
    cfg: MaskTrainConfig, windows: Windows, run: _Run, ckpts: Checkpointer, max_steps: int | None
) -> None:
    """The steps not done yet, validating and saving after each epoch; stops, saved, after
    `max_steps` steps in all."""
    tr, detected = windows.train, windows.detected
    device = torch.device("cpu")
    while run.epoch < cfg.epochs:
        epoch = run.epoch
        g = torch.Generator().manual_seed(cfg.seed * 1000 + epoch)
        order = torch.randperm(len(tr["rgb"]), generator=g).numpy()
        run.net.train()
        desc = f"mask net epoch {epoch + 1}/{cfg.epochs}"
        bar = progress_bar(range(run.steps_per_epoch), desc=desc)
        for b in bar:
            if b < run.step - epoch * run.steps_per_epoch:
                # Done before the resume: only the coarse masks' draws, which the data never
                # changes, so the steps after it draw as an unstopped run's did.
                degrade(torch.zeros(cfg.batch, 1, 1), g, cfg.heavy)
                continue
            if max_steps is not None and run.step >= max_steps:
                ckpts.save(epoch)
                return
            idx = np.sort(order[b * cfg.batch : (b + 1) * cfg.batch])
            t = torch.as_tensor(tr["target"][idx]).float() / 255
            coarse = degrade(t, g, cfg.heavy).numpy()
            if detected is not None and (mine := idx >= windows.first_detected).any():
                coarse[mine] = detected["coarse"][idx[mine] - windows.first_detected]
            x = net_input(tr["rgb"][idx], coarse)
            if cfg.channels_last:
                x = x.contiguous(memory_format=torch.channels_last)
            with autocast(cfg.precision, device):
                logits = run.net(x)
            loss = torch.nn.functional.binary_cross_entropy_with_logits(logits.float()[:, 0], t)
            run.opt.zero_grad(set_to_none=True)
            loss.backward()
            run.opt.step()
            run.sched.step()
            run.step += 1
            if b % 20 == 0:
                bar.set_postfix(loss=f"{loss.item():.4f}")
            ckpts.save_if_due(epoch)
        run.epoch += 1
        val = validate(run.net, windows.val, 0, cfg.heavy, windows.val_detected)
        run.history.append({"epoch": run.epoch, "step": run.step, **val})
        print(f"epoch {run.epoch}: {run.history[-1]}", flush=True)
        ckpts.save(run.epoch)


def evaluate(
    split: str, images: int, protocol: str = "tiers", examples: list | None = None
) -> dict[str, Any]:
    """The protocol's detector's masks of the `images` first images of a split of its
    validation folder (every visible object it finds, mask IoU >= 0.5 with the truth) against
    its shipped mask net's, by IoU with the true visible mask, per class and overall.
    `examples`, when given, receives the first object of each class: (name, image window,
    detector's, mask net's and true mask in it, both IoUs)."""
    from perception.detector import TIERS_DETECTOR

    proto = PROTOCOLS[protocol]
    folder = proto.val[0]
    detector = Detector.from_weights(proto.detector or TIERS_DETECTOR)
    refiner = MaskRefiner.from_weights(proto.weights, experts=proto.experts)
    data = PoseDataset(data_root() / folder, split)
    rows: list[tuple[str, float, float]] = []
    spent = 0.0
    for i in progress_bar(
        range(min(images, len(data))), desc=f"masks of {folder}/{split}", mininterval=5
    ):
        sample = data[i]
        dets = detector.detect(sample.rgb, 0.3)
        for obj in sample.objects:
            truth = obj.mask_visib
            if int(truth.sum()) < MIN_VISIBLE_PX:
                continue
            best, best_iou = best_detection(dets, obj.name, truth, 0.5)
            if best is None:
                continue
            t0 = time.perf_counter()
            sharp = refiner.refine(sample.rgb, best.mask, obj.name)
            spent += time.perf_counter() - t0
            after = mask_iou(sharp, truth)
            rows.append((obj.name, best_iou, after))
            if examples is not None and all(e[0] != obj.name for e in examples):
                win = window_of(truth, refiner.cfg.margin)
                assert win is not None
                S = 4 * refiner.cfg.size
                cuts = [cut(m.astype(np.float32), win, S) >= 0.5 for m in (best.mask, sharp, truth)]
                examples.append((obj.name, cut(sample.rgb, win, S), *cuts, best_iou, after))
    names = sorted({r[0] for r in rows})
    per = {
        n: {
            "objects": sum(r[0] == n for r in rows),
            "detector_iou": float(np.mean([r[1] for r in rows if r[0] == n])),
            "refined_iou": float(np.mean([r[2] for r in rows if r[0] == n])),
        }
        for n in names
    }
    return {
        "split": f"{folder}/{split}",
        "images": min(images, len(data)),
        "objects": len(rows),
        "detector_iou": float(np.mean([r[1] for r in rows])),
        "refined_iou": float(np.mean([r[2] for r in rows])),
        "refined_better": float(np.mean([r[2] > r[1] for r in rows])),
        "ms_per_mask": 1000 * spent / max(1, len(rows)),
        "per_class": per,
    }


def plot_examples(examples: list, path: Path) -> None:
    """One row per class: the window, then the detector's, the mask net's and the true mask's
    outlines drawn on it."""
    import cv2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(examples), 4, figsize=(8, 2.1 * len(examples)), squeeze=False)
    for row, (name, rgb, det, sharp, truth, before, after) in zip(axes, examples, strict=True):
        titles = (name, f"detector: IoU {before:.3f}", f"mask net: IoU {after:.3f}", "truth")
        colours = (None, (255, 60, 60), (60, 255, 60), (255, 255, 255))
        for ax, mask, title, colour in zip(
            row, (None, det, sharp, truth), titles, colours, strict=True
        ):
            img = rgb.copy()
            if mask is not None:
                edges = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3)))
                img[edges.astype(bool)] = colour
            ax.imshow(img)
            ax.set_title(title, fontsize=8)
            ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print(f"wrote {path}")


def command_line(cfg: MaskTrainConfig) -> str:
    """The CLI command that runs `cfg` (as far as the CLI exposes it: the protocol whose
    validation scenes it has, then what it changes), in the trainers' shared spelling."""
    protocol = next((k for k, v in PROTOCOLS.items() if v.val == cfg.val), "tiers")
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
