"""Training of the 2D/4D pose nets on our renders (`python -m perception.training.train_posenet`).

Crops are cut once per split with the paper's imprecise boxes and cached next to the data
(`perception.training.crop_sets`). Training is seeded, checkpoints every epoch and every few
minutes with everything needed to resume or rebuild the model (weights, model config, optimiser,
step, RNG states, data seeds, commit; `perception.training.checkpoints`), and validates each
epoch (`perception.training.posenet_eval`).

    python -m perception.training.train_posenet --variant ours --epochs 7
    python -m perception.training.train_posenet --smoke  # seconds, on whatever small data exists
    torchrun --nproc-per-node 2 -m perception.training.train_posenet --variant ours --device cpu

Under torchrun the run is data-parallel over the processes (`perception.training.ddp`): same
global batch, each rank its shard of it, rank 0 validating and writing the checkpoint.
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

from perception.nets import CROP, ROTATIONS, VARIANTS, NetConfig, PoseNet, load_posenet, normalise
from perception.training.augment import photometric_jitter
from perception.training.checkpoints import (
    config_dict,
    read_checkpoint,
    restore,
    rng_state,
    save_checkpoint,
    seed_torch,
)
from perception.training.crop_sets import CropConfig, data_seed_ranges, split_crops
from perception.training.dataset import DATASETS, DISTS, parse_limit
from perception.training.ddp import DEVICES, Ranks, resolve_device, start
from perception.training.losses import posenet_loss
from perception.training.manifest import shipped_stages
from perception.training.posenet_eval import evaluate_arrays
from perception.training.schedule import learning_rate, optimiser_step
from posegrasp.core.cli import ArgumentParser, fail
from posegrasp.core.errors import AssetError, InvalidArgumentError, PosegraspError
from posegrasp.core.paths import checkpoint_dir
from posegrasp.core.runtime import setup_rendering
from posegrasp.world.objects import OBJECT_NAMES

#: The command line of this module.
TRAIN_COMMAND = "python -m perception.training.train_posenet"
#: What a fine-tuning run keeps of the checkpoint it starts from.
LINEAGE_KEYS = ("command", "init_from", "train_config", "epoch", "wall_s", "data_seeds", "commit")
#: Gradient-norm clip of every step.
GRAD_CLIP = 5.0


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
        device: "auto", "cpu" or "cuda" (`perception.training.ddp.DEVICES`).
        loss_log: append one JSON line per step here (step, epoch, loss averaged over the
            processes, lr), or None.
        teacher: distillation: pose-net weights whose outputs on each training batch are a
            second target, weighted as the labels are (None: labels only).
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

    def __post_init__(self) -> None:
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


def _command(cfg: PoseNetTrainConfig) -> str:
    """The CLI command that runs `cfg` (as far as the CLI exposes it)."""
    d = PoseNetTrainConfig
    lims = [f"{k}={n}" for k, n in cfg.dist_limits] + ([str(cfg.limit)] if cfg.limit else [])
    options = (
        (tuple(cfg.dists) != DISTS, f"--dists {','.join(cfg.dists)}"),
        (cfg.lr != d.lr, f"--lr {cfg.lr:g}"),
        (cfg.batch != d.batch, f"--batch {cfg.batch}"),
        (bool(lims), f"--limit {','.join(lims)}"),
        (cfg.width != d.width or cfg.lam != d.lam, f"--width {cfg.width} --lam {cfg.lam:g}"),
        (bool(cfg.objects), f"--objects {','.join(cfg.objects)}"),
        (cfg.crops.size != CROP, f"--crop {cfg.crops.size}"),
        (cfg.rotation != d.rotation, f"--rotation {cfg.rotation}"),
        (not cfg.augment, "--no-augment"),
        (not cfg.decay, "--constant-lr"),
        (bool(cfg.init), f"--init {cfg.init}"),
        (bool(cfg.name), f"--name {cfg.name}"),
    )
    head = [TRAIN_COMMAND, f"--variant {cfg.variant}", f"--epochs {cfg.epochs}"]
    return " ".join(head + [text for wanted, text in options if wanted])


def train(cfg: PoseNetTrainConfig, resume: bool = True, command: str | None = None) -> dict:
    """Train (resuming from the run's checkpoint when present) and return the history.

    With `cfg.init`, the model starts from that checkpoint's weights; a resumed run ignores it
    and continues from its own checkpoint. Under torchrun every process calls this and the run
    is data-parallel (`perception.training.ddp`).

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
    ranks = start(cfg.device, cfg.batch)
    try:
        return _train(cfg, ranks, resume, command)
    finally:
        ranks.close()


def _train(cfg: PoseNetTrainConfig, ranks: Ranks, resume: bool, command: str | None) -> dict:
    seed_torch(cfg.seed, ranks.threads(cfg.threads))
    if not ranks.main:
        ranks.barrier()  # rank 0 cuts and caches the crops first
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
    data_seeds = data_seed_ranges(cfg.dists, {d: n for d, n in limits.items() if n})
    model = PoseNet(cfg.net_config())
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    steps_per_epoch = max(1, len(tr["crops"]) // cfg.batch)
    total_steps = cfg.epochs * steps_per_epoch
    ckpt = checkpoint_path(cfg)
    ckpt.parent.mkdir(parents=True, exist_ok=True)
    lineage = {"command": command or _command(cfg), "init_from": None, "wall_s": 0.0}
    resuming = resume and ckpt.is_file()
    if cfg.init and not resuming:
        src = _resolve_init(cfg.init, ckpt.parent)
        parent = read_checkpoint(src)
        if NetConfig(**parent["model_config"]) != model.cfg:  # older files: fields defaulted
            raise AssetError(
                f"{src} holds a {parent['model_config']} model, not {model.cfg.to_dict()}"
            )
        model.load_state_dict(parent["model"])
        lineage["init_from"] = {
            "checkpoint": src.name,
            **{k: parent.get(k) for k in LINEAGE_KEYS},
            "validation": parent["history"][-1] if parent.get("history") else None,
            # Shipped weights carry no lineage of their own: their manifest's stages stand in.
            "stages": shipped_stages(src),
        }
    step, epoch0, history = 0, 0, []
    if resuming:
        state = read_checkpoint(ckpt)
        lineage = {k: state.get(k, v) for k, v in lineage.items()}
        step, epoch0, history = restore(state, model, opt)
        if ranks.main:
            print(f"resuming {ckpt} at epoch {epoch0}, step {step}")
    net = ranks.wrap(model)  # the model itself with one process
    with torch.random.fork_rng():  # building the teacher leaves the run's random stream alone
        teacher = load_posenet(cfg.teacher, verify=False).to(ranks.device) if cfg.teacher else None
    wall0, started = float(lineage.get("wall_s") or 0.0), time.monotonic()  # over resumptions

    def save(epoch: int) -> None:
        lineage["wall_s"] = wall0 + time.monotonic() - started
        if ranks.main:
            save_checkpoint(
                ckpt, model, opt, model_config=model.cfg.to_dict(), train_config=cfg.to_dict(),
                step=step, epoch=epoch, history=history, rng=rng_state(), data_seeds=data_seeds,
                header=lineage,
            )  # fmt: skip

    g = torch.Generator().manual_seed(cfg.seed)
    last_save = time.monotonic()
    for epoch in range(epoch0, cfg.epochs):
        g.manual_seed(cfg.seed * 1000 + epoch)
        order = torch.randperm(len(tr["crops"]), generator=g).numpy()
        skip = step - epoch * steps_per_epoch  # batches of this epoch already done (resume)
        model.train()
        bar = tqdm(range(steps_per_epoch), desc=f"{cfg.variant} epoch {epoch + 1}/{cfg.epochs}",
                   disable=not ranks.main)  # fmt: skip
        for b in bar:
            if b < skip:
                continue
            idx = ranks.shard(order[b * cfg.batch : (b + 1) * cfg.batch])  # this rank's shard

            def batch(key: str, idx=idx) -> torch.Tensor:
                return torch.from_numpy(tr[key][idx]).to(ranks.device)

            x = normalise(batch("crops"))
            if cfg.augment:
                x = photometric_jitter(x, g, ranks)
            out = net(x, batch("cls"), batch("scale"))
            loss, parts = posenet_loss(
                out, batch("uv_unit"), batch("p"), batch("theta"), cfg.variant, cfg.lam
            )
            if teacher is not None:
                with torch.no_grad():
                    t = teacher(x, batch("cls"), batch("scale"))
                loss = loss + posenet_loss(out, t.uv_unit, t.p, t.cs, cfg.variant, cfg.lam)[0]
            lr = learning_rate(step, total_steps, cfg.lr, decay=cfg.decay)
            optimiser_step(model, opt, loss, lr, GRAD_CLIP)
            step += 1
            if cfg.loss_log is not None:
                loss_all = ranks.mean(loss)  # every rank takes part
                ranks.log(cfg.loss_log, step=step, epoch=epoch + 1, loss=loss_all, lr=lr)
            if b % 20 == 0:
                bar.set_postfix({k: f"{v:.3f}" for k, v in parts.items()})
            if time.monotonic() - last_save > 60 * cfg.checkpoint_minutes:
                save(epoch)
                last_save = time.monotonic()
        if not ranks.main:
            continue  # rank 0 validates and saves; the others meet it at the next step
        val = evaluate_arrays(ranks.on_cpu(model), va)  # posenet_eval works on the CPU
        history.append({"epoch": epoch + 1, "step": step, **val})
        print(
            f"epoch {epoch + 1}: val centre {val['center_px']:.2f} px, distance "
            f"{val['distance_pct']:.2f} %, rotation {val['rotation_deg']:.2f} deg, "
            f"outliers {val['outlier_rate']:.1%}"
        )
        save(epoch + 1)
        last_save = time.monotonic()
    return {"checkpoint": str(ckpt), "history": history}


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(prog=TRAIN_COMMAND, description=__doc__.split("\n")[0])
    p.add_argument("--variant", default="ours", help=f"one of: {', '.join(VARIANTS)}")
    p.add_argument("--epochs", type=int, default=PoseNetTrainConfig.epochs)
    p.add_argument("--batch", type=int, default=PoseNetTrainConfig.batch)
    p.add_argument("--lr", type=float, default=PoseNetTrainConfig.lr)
    p.add_argument(
        "--limit",
        default=None,
        help="at most this many images per split: N for every distribution, or dist=N,...",
    )
    p.add_argument(
        "--dists",
        default=",".join(DISTS),
        help=f"comma list of datasets under the data root, of: {', '.join(DATASETS)}",
    )
    p.add_argument(
        "--init", default=None, help="start from this checkpoint's weights (name or path)"
    )
    p.add_argument("--name", default=None, help="checkpoint name (default: posenet_<variant>)")
    p.add_argument(
        "--out", type=Path, default=None, help="checkpoint folder (default: <data>/checkpoints)"
    )
    p.add_argument(
        "--threads", type=int, default=None, help="CPU threads per process (default: all cores)"
    )
    p.add_argument("--device", default="auto", help=f"one of: {', '.join(DEVICES)}")
    p.add_argument(
        "--loss-log", type=Path, default=None, help="append one JSON line per step to this file"
    )
    p.add_argument("--width", type=int, default=PoseNetTrainConfig.width, help="backbone width")
    p.add_argument("--lam", type=float, default=PoseNetTrainConfig.lam, help="rotation weight")
    p.add_argument("--crop", type=int, default=CROP, help=f"crop side [px] (default {CROP})")
    p.add_argument(
        "--rotation", default="view-roll", help=f"ours' rotation output: {', '.join(ROTATIONS)}"
    )
    p.add_argument("--objects", default="", help="train one net on these objects (comma list)")
    p.add_argument("--no-augment", action="store_true", help="no photometric jitter")
    p.add_argument("--constant-lr", action="store_true", help="no learning-rate decay")
    p.add_argument("--smoke", action="store_true", help="a tiny run that takes seconds")
    p.add_argument("--no-resume", action="store_true", help="start over")
    args = p.parse_args(argv)
    setup_rendering()
    if args.variant not in VARIANTS:
        return fail(f"unknown variant {args.variant!r}; valid variants: {', '.join(VARIANTS)}")
    dists = tuple(args.dists.split(","))
    if any(d not in DATASETS for d in dists) or len(set(dists)) != len(dists):
        return fail(f"invalid --dists {args.dists!r}; a comma list of: {', '.join(DATASETS)}")
    if args.epochs < 1 or args.batch < 1 or args.width < 1 or args.lam < 0:
        return fail("--epochs, --batch and --width must be at least 1 and --lam at least 0")
    if args.name is not None and (not args.name or "/" in args.name or args.name.endswith(".pt")):
        return fail(f"--name must be a plain name such as posenet_ours, got {args.name!r}")
    try:
        limit, dist_limits = parse_limit(args.limit)
        resolve_device(args.device)
        cfg = PoseNetTrainConfig(
            variant=args.variant, dists=dists, epochs=args.epochs, batch=args.batch, lr=args.lr,
            limit=limit, dist_limits=dist_limits, init=args.init, name=args.name, out=args.out,
            threads=args.threads, device=args.device, loss_log=args.loss_log, width=args.width,
            lam=args.lam, objects=tuple(o for o in args.objects.split(",") if o),
            augment=not args.no_augment, decay=not args.constant_lr,
            crops=CropConfig(size=args.crop), rotation=args.rotation,
        )  # fmt: skip
    except PosegraspError as exc:  # NetConfig checks the crop side and rotation output
        return fail(str(exc))
    if args.smoke:
        cfg = replace(SMOKE, variant=args.variant, dists=dists, out=args.out, device=args.device,
                      loss_log=args.loss_log, threads=args.threads)  # fmt: skip
    try:
        result = train(cfg, resume=not args.no_resume)
    except PosegraspError as exc:
        return fail(str(exc))
    print(json.dumps(result["history"][-1] if result["history"] else {}, sort_keys=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())
