"""Training of the 2D/4D pose nets on our renders (`python -m perception.training.train_posenet`).

Crops are cut once per split with the paper's imprecise boxes (random shift and scale of the
visible box), several per object instance, and cached next to the data (`crops_*.npz`). Training
is seeded, checkpoints every epoch and every few minutes with everything needed to resume or
rebuild the model (weights, model config, optimiser, step, RNG states, data seeds, commit), and
validates each epoch.

    python -m perception.training.train_posenet --variant ours --epochs 7
    python -m perception.training.train_posenet --smoke  # seconds, on whatever small data exists
"""

from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from perception.crops import (
    crop_and_resize,
    crop_to_image,
    from_unit,
    image_to_crop,
    random_square_box,
    to_unit,
)
from perception.geometry import decode, encode
from perception.nets import CROP, VARIANTS, NetConfig, PoseNet, normalise
from perception.training.dataset import DISTS, PoseDataset, load_info
from perception.training.losses import posenet_loss
from sim.core.cli import ArgumentParser, fail
from sim.core.errors import AssetError, InvalidArgumentError, PosegraspError
from sim.core.paths import checkpoint_dir, data_root, git_commit
from sim.world.objects import OBJECT_NAMES

# --- crops -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CropConfig:
    """How crops are cut from a split.

    Attributes:
        per_object: crops per annotated object instance (each with its own random box).
        max_shift: random shift of the box centre, as a fraction of its side.
        scale_range: random scale of the square box side relative to the box's longer side.
        min_visib: instances less visible than this are skipped.
        seed: seed of the random boxes.
    """

    per_object: int = 2
    max_shift: float = 0.1
    scale_range: tuple[float, float] = (0.95, 1.35)
    min_visib: float = 0.5
    seed: int = 0


def data_seed_ranges(
    dists: tuple[str, ...] | list[str], limits: dict[str, int] | None = None
) -> dict[str, dict[str, list[int]]]:
    """Seed range [first, end) of every generated split of each distribution, from its
    info.json: dist -> split -> range. `limits` (dist -> images) shortens the ranges to the first
    images of each split, as training with that limit uses them."""
    out = {}
    for d in dists:
        splits = load_info(data_root() / d).get("splits", {})
        out[d] = {}
        for s, v in splits.items():
            if "seed_range" not in v:
                continue
            first, end = v["seed_range"]
            if limits and d in limits:
                end = min(end, first + limits[d])
            out[d][s] = [first, end]
    return out


class CropSet:
    """Crops of annotated objects and their labels, collected one at a time."""

    KEYS = ("crops", "cls", "uv_unit", "p", "theta", "scale", "box", "K", "T_C_O", "uv")

    def __init__(self) -> None:
        self.rows: dict[str, list] = {k: [] for k in self.KEYS}

    def add(self, rgb: np.ndarray, K: np.ndarray, obj, box: tuple[float, float, float]) -> None:
        """Cut the square `box` (x0, y0, side) of `rgb` around annotated object `obj`."""
        p, theta, uv = encode(obj.T_C_O, K)
        r = self.rows
        r["crops"].append(crop_and_resize(rgb, box, CROP))
        r["cls"].append(obj.obj_id - 1)
        r["uv_unit"].append(to_unit(image_to_crop(uv, box, CROP), CROP))
        r["p"].append(p)
        r["theta"].append(theta)
        r["scale"].append(box[2] / K[0, 0])
        r["box"].append(np.asarray(box, float))
        r["K"].append(K)
        r["T_C_O"].append(obj.T_C_O)
        r["uv"].append(uv)

    def arrays(self) -> dict[str, np.ndarray]:
        """The layout `build_crops` returns (empty arrays of the right shapes when no crop)."""
        r = self.rows
        return {
            "crops": np.asarray(r["crops"], np.uint8).reshape(-1, CROP, CROP, 3),
            "cls": np.asarray(r["cls"], np.int64),
            "uv_unit": np.asarray(r["uv_unit"], np.float32).reshape(-1, 2),
            "p": np.asarray(r["p"], np.float32).reshape(-1, 3),
            "theta": np.asarray(r["theta"], np.float32),
            "scale": np.asarray(r["scale"], np.float32),
            "box": np.asarray(r["box"], np.float64).reshape(-1, 3),
            "K": np.asarray(r["K"], np.float64).reshape(-1, 3, 3),
            "T_C_O": np.asarray(r["T_C_O"], np.float64).reshape(-1, 4, 4),
            "uv": np.asarray(r["uv"], np.float64).reshape(-1, 2),
        }


def build_crops(root: Path, split: str, cfg: CropConfig, limit: int | None = None) -> dict:
    """Cut (or load cached) training crops and labels of one split of one dataset.

    Returns:
        dict of arrays: crops (N, 64, 64, 3) uint8, cls (N,), uv_unit (N, 2), p (N, 3),
        theta (N,), scale (N,) = side / f, box (N, 3) square boxes (x0, y0, side), K (N, 3, 3),
        T_C_O (N, 4, 4), uv (N, 2) true origin pixel.
    """
    ds = PoseDataset(root, split)
    n = len(ds) if limit is None else min(limit, len(ds))
    cache = root / f"crops_{split}_{cfg.per_object}_{cfg.seed}_{n}.npz"  # n: images used
    if cache.is_file():
        try:
            with np.load(cache) as z:
                return {k: z[k] for k in z.files}
        except (OSError, ValueError) as exc:
            raise AssetError(f"corrupt crop cache {cache}: {exc}; delete it to rebuild") from exc
    rng = np.random.default_rng([cfg.seed, ("train", "val", "test").index(split)])
    out = CropSet()
    for i in tqdm(range(n), desc=f"crops {root.name}/{split}", leave=False):
        s = ds[i]
        for obj in s.objects:
            if obj.visib_fract < cfg.min_visib or obj.T_C_O[2, 3] <= 0:
                continue
            for _ in range(cfg.per_object):
                box = random_square_box(obj.box_xyxy, rng, cfg.max_shift, cfg.scale_range)
                out.add(s.rgb, s.K, obj, box)
    arrays = out.arrays()
    tmp = cache.with_suffix(".tmp.npz")
    np.savez(tmp, **arrays)
    tmp.replace(cache)
    return arrays


def concat(parts: list[dict]) -> dict:
    """Concatenate crop dicts."""
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


# --- prediction and metrics -------------------------------------------------------------------


@torch.no_grad()
def predict(model: PoseNet, crops: np.ndarray, cls: np.ndarray, scale: np.ndarray,
            batch: int = 512) -> dict[str, np.ndarray]:  # fmt: skip
    """Network outputs for arrays of crops: uv_unit (N, 2), p (N, 3), theta (N,)."""
    model.eval()
    uv, p, th = [], [], []
    for i in range(0, len(crops), batch):
        out = model(
            normalise(torch.from_numpy(crops[i : i + batch])),
            torch.from_numpy(cls[i : i + batch]),
            torch.from_numpy(scale[i : i + batch]).float(),
        )
        uv.append(out.uv_unit.numpy())
        p.append(out.p.numpy())
        th.append(out.theta.numpy())
    if not uv:
        return {"uv_unit": np.zeros((0, 2)), "p": np.zeros((0, 3)), "theta": np.zeros(0)}
    return {"uv_unit": np.concatenate(uv), "p": np.concatenate(p), "theta": np.concatenate(th)}


def decode_predictions(pred: dict, data: dict) -> dict[str, np.ndarray]:
    """Full-image origin pixels (N, 2) and poses T_C_O (N, 4, 4) from network outputs."""
    n = len(pred["p"])
    uv_img = np.zeros((n, 2))
    T = np.zeros((n, 4, 4))
    for i in range(n):
        box = tuple(data["box"][i])
        uv_img[i] = crop_to_image(from_unit(pred["uv_unit"][i].astype(float), CROP), box, CROP)
        T[i] = decode(pred["p"][i].astype(float), float(pred["theta"][i]), uv_img[i], data["K"][i])
    return {"uv": uv_img, "T_C_O": T}


def pose_metrics(dec: dict, data: dict) -> dict[str, np.ndarray]:
    """Per-crop errors: centre [px] in the full image and in the 64x64 crop, distance [%],
    rotation [deg]."""
    T, Tg = dec["T_C_O"], data["T_C_O"]
    centre = np.linalg.norm(dec["uv"] - data["uv"], axis=1)
    dist = np.linalg.norm(T[:, :3, 3] - Tg[:, :3, 3], axis=1) / np.linalg.norm(Tg[:, :3, 3], axis=1)
    Rrel = np.einsum("nji,njk->nik", T[:, :3, :3], Tg[:, :3, :3])
    cosang = np.clip((np.trace(Rrel, axis1=1, axis2=2) - 1) / 2, -1, 1)
    return {
        "center_px": centre,
        "center_crop_px": centre * CROP / data["box"][:, 2],
        "distance_pct": 100 * dist,
        "rotation_deg": np.rad2deg(np.arccos(cosang)),
    }


# --- training ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class TrainConfig:
    """A training run.

    Attributes:
        variant: "paper" or "ours".
        dists: which data distributions to train on.
        epochs, batch, lr, weight_decay, lam: optimisation (lam weighs the rotation loss).
        width: backbone width.
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
        threads: torch CPU threads (None: all cores).
    """

    variant: str = "ours"
    dists: tuple[str, ...] = DISTS
    epochs: int = 7
    batch: int = 128
    lr: float = 2e-3
    weight_decay: float = 1e-4
    lam: float = 1.0
    width: int = 16
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


SMOKE = TrainConfig(epochs=1, batch=16, limit=12, out=Path("out/smoke"), width=4)


def _load_split(cfg: TrainConfig, split: str) -> dict:
    parts = []
    for d in cfg.dists:
        root = data_root() / d
        if not (root / split).is_dir():
            raise AssetError(
                f"no {d} {split} data under {root}; build it with "
                f"`python -m perception.training.datagen --dist {d} --split {split} --count N` "
                "(or `make data`)"
            )
        parts.append(build_crops(root, split, cfg.crops, _limit(cfg, d)))
    return concat(parts)


def _limit(cfg: TrainConfig, dist: str) -> int | None:
    """Images per split of `dist` that a run uses (None: all)."""
    lims = [n for d, n in cfg.dist_limits if d == dist] + ([cfg.limit] if cfg.limit else [])
    return min(lims) if lims else None


def checkpoint_path(cfg: TrainConfig) -> Path:
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


def _augment(x: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """Photometric jitter: brightness, contrast, per-channel gain and pixel noise."""
    b = x.shape[0]
    bright = (torch.rand(b, 1, 1, 1, generator=g) - 0.5) * 0.3
    contrast = 0.75 + 0.5 * torch.rand(b, 1, 1, 1, generator=g)
    gain = 0.9 + 0.2 * torch.rand(b, 3, 1, 1, generator=g)
    noise = torch.randn(x.shape, generator=g) * 0.02
    return (x * contrast * gain + bright + noise).clamp(-0.5, 0.5)


def evaluate_arrays(model: PoseNet, data: dict) -> dict[str, float]:
    """Mean errors over a crop set."""
    pred = predict(model, data["crops"], data["cls"], data["scale"])
    m = pose_metrics(decode_predictions(pred, data), data)
    return {k: float(np.mean(v)) for k, v in m.items()} | {
        "outlier_rate": float(np.mean(m["rotation_deg"] > 15))
    }


def learning_rate(step: int, total_steps: int, peak: float, warmup: float = 0.05) -> float:
    """Linear warm-up to `peak` over the first `warmup` fraction of steps, then cosine to 1 %."""
    w = max(1, int(warmup * total_steps))
    if step < w:
        return peak * (step + 1) / w
    frac = min(1.0, (step - w) / max(1, total_steps - w))
    return peak * (0.01 + 0.99 * 0.5 * (1 + np.cos(np.pi * frac)))


def _checkpoint(path: Path, model, opt, cfg, step, epoch, history, data_seeds, lineage) -> None:
    state = {
        **lineage,
        "model": model.state_dict(),
        "model_config": model.cfg.to_dict(),
        "optimizer": opt.state_dict(),
        "train_config": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items()},
        "step": step,
        "epoch": epoch,
        "history": history,
        "rng": {"torch": torch.get_rng_state()},
        "data_seeds": data_seeds,
        "commit": git_commit(),
    }
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    tmp.replace(path)


def _command(cfg: TrainConfig) -> str:
    """The CLI command that runs `cfg` (as far as the CLI exposes it)."""
    parts = [
        "python -m perception.training.train_posenet",
        f"--variant {cfg.variant}",
        f"--epochs {cfg.epochs}",
    ]
    if tuple(cfg.dists) != DISTS:
        parts.append(f"--dists {','.join(cfg.dists)}")
    if cfg.lr != TrainConfig.lr:
        parts.append(f"--lr {cfg.lr:g}")
    if cfg.batch != TrainConfig.batch:
        parts.append(f"--batch {cfg.batch}")
    lims = [f"{d}={n}" for d, n in cfg.dist_limits] + ([str(cfg.limit)] if cfg.limit else [])
    if lims:
        parts.append(f"--limit {','.join(lims)}")
    if cfg.init:
        parts.append(f"--init {cfg.init}")
    if cfg.name:
        parts.append(f"--name {cfg.name}")
    return " ".join(parts)


def train(cfg: TrainConfig, resume: bool = True, command: str | None = None) -> dict:
    """Train (resuming from the run's checkpoint when present) and return the history.

    With `cfg.init`, the model starts from that checkpoint's weights; a resumed run ignores it
    and continues from its own checkpoint."""
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads or max(1, os.cpu_count() or 1))
    tr = _load_split(cfg, "train")
    va = _load_split(cfg, "val")
    if cfg.variant == "paper":
        keep = np.abs(np.rad2deg(tr["theta"])) <= cfg.max_theta_deg
        tr = {k: v[keep] for k, v in tr.items()}
    if len(tr["crops"]) == 0:
        raise AssetError("no training crops; generate data first (`make data`)")
    data_seeds = data_seed_ranges(cfg.dists, {d: n for d in cfg.dists if (n := _limit(cfg, d))})
    model = PoseNet(NetConfig(variant=cfg.variant, n_classes=len(OBJECT_NAMES), width=cfg.width))
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    steps_per_epoch = max(1, len(tr["crops"]) // cfg.batch)
    total_steps = cfg.epochs * steps_per_epoch
    ckpt = checkpoint_path(cfg)
    ckpt.parent.mkdir(parents=True, exist_ok=True)
    lineage = {"command": command or _command(cfg), "init_from": None}
    resuming = resume and ckpt.is_file()
    if cfg.init and not resuming:
        src = _resolve_init(cfg.init, ckpt.parent)
        parent = torch.load(src, map_location="cpu", weights_only=False)
        if parent["model_config"] != model.cfg.to_dict():
            raise AssetError(
                f"{src} holds a {parent['model_config']} model, not {model.cfg.to_dict()}"
            )
        model.load_state_dict(parent["model"])
        lineage["init_from"] = {
            "checkpoint": src.name,
            **{k: parent.get(k) for k in ("command", "init_from", "train_config", "epoch")},
            **{k: parent.get(k) for k in ("data_seeds", "commit")},
            "validation": parent["history"][-1] if parent.get("history") else None,
        }
    step, epoch0, history = 0, 0, []
    if resuming:
        state = torch.load(ckpt, map_location="cpu", weights_only=False)
        lineage = {k: state.get(k, v) for k, v in lineage.items()}
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        torch.set_rng_state(state["rng"]["torch"])
        step, epoch0, history = state["step"], state["epoch"], state["history"]
        print(f"resuming {ckpt} at epoch {epoch0}, step {step}")
    g = torch.Generator().manual_seed(cfg.seed)
    last_save = time.monotonic()
    for epoch in range(epoch0, cfg.epochs):
        g.manual_seed(cfg.seed * 1000 + epoch)
        order = torch.randperm(len(tr["crops"]), generator=g).numpy()
        skip = step - epoch * steps_per_epoch  # batches of this epoch already done (resume)
        model.train()
        bar = tqdm(range(steps_per_epoch), desc=f"{cfg.variant} epoch {epoch + 1}/{cfg.epochs}")
        for b in bar:
            if b < skip:
                continue
            idx = order[b * cfg.batch : (b + 1) * cfg.batch]
            x = _augment(normalise(torch.from_numpy(tr["crops"][idx])), g)
            out = model(x, torch.from_numpy(tr["cls"][idx]), torch.from_numpy(tr["scale"][idx]))
            loss, parts = posenet_loss(
                out,
                torch.from_numpy(tr["uv_unit"][idx]),
                torch.from_numpy(tr["p"][idx]),
                torch.from_numpy(tr["theta"][idx]),
                cfg.variant,
                cfg.lam,
            )
            for group in opt.param_groups:
                group["lr"] = learning_rate(step, total_steps, cfg.lr)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
            opt.step()
            step += 1
            if b % 20 == 0:
                bar.set_postfix({k: f"{v:.3f}" for k, v in parts.items()})
            if time.monotonic() - last_save > 60 * cfg.checkpoint_minutes:
                _checkpoint(ckpt, model, opt, cfg, step, epoch, history, data_seeds, lineage)
                last_save = time.monotonic()
        val = evaluate_arrays(model, va)
        history.append({"epoch": epoch + 1, "step": step, **val})
        print(
            f"epoch {epoch + 1}: val centre {val['center_px']:.2f} px, distance "
            f"{val['distance_pct']:.2f} %, rotation {val['rotation_deg']:.2f} deg, "
            f"outliers {val['outlier_rate']:.1%}"
        )
        _checkpoint(ckpt, model, opt, cfg, step, epoch + 1, history, data_seeds, lineage)
        last_save = time.monotonic()
    return {"checkpoint": str(ckpt), "history": history}


def parse_limit(text: str | None) -> tuple[int | None, tuple[tuple[str, int], ...]]:
    """`--limit`: "N" (every distribution) or "dist=N,..." -> (limit, dist_limits)."""
    if text is None:
        return None, ()
    limit, per = None, []
    for item in text.split(","):
        name, _, num = item.rpartition("=")
        if name and name not in DISTS:
            raise InvalidArgumentError(
                f"unknown distribution {name!r} in --limit; valid: {', '.join(DISTS)}"
            )
        if not num.isdigit() or int(num) < 1:
            raise InvalidArgumentError(f"--limit wants N or dist=N with N >= 1, got {item!r}")
        if name:
            per.append((name, int(num)))
        else:
            limit = int(num)
    return limit, tuple(per)


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(
        prog="python -m perception.training.train_posenet", description=__doc__.split("\n")[0]
    )
    p.add_argument("--variant", default="ours", help=f"one of: {', '.join(VARIANTS)}")
    p.add_argument("--epochs", type=int, default=TrainConfig.epochs)
    p.add_argument("--batch", type=int, default=TrainConfig.batch)
    p.add_argument("--lr", type=float, default=TrainConfig.lr)
    p.add_argument(
        "--limit",
        default=None,
        help="at most this many images per split: N for every distribution, or dist=N,...",
    )
    p.add_argument("--dists", default=",".join(DISTS), help="comma list of: paper, headcam")
    p.add_argument(
        "--init", default=None, help="start from this checkpoint's weights (name or path)"
    )
    p.add_argument("--name", default=None, help="checkpoint name (default: posenet_<variant>)")
    p.add_argument(
        "--out", type=Path, default=None, help="checkpoint folder (default: <data>/checkpoints)"
    )
    p.add_argument("--threads", type=int, default=None, help="CPU threads (default: all)")
    p.add_argument("--smoke", action="store_true", help="a tiny run that takes seconds")
    p.add_argument("--no-resume", action="store_true", help="start over")
    args = p.parse_args(argv)
    if args.variant not in VARIANTS:
        return fail(f"unknown variant {args.variant!r}; valid variants: {', '.join(VARIANTS)}")
    dists = tuple(args.dists.split(","))
    if any(d not in DISTS for d in dists):
        return fail(f"unknown distribution in {args.dists!r}; valid: {', '.join(DISTS)}")
    if args.epochs < 1 or args.batch < 1:
        return fail("--epochs and --batch must be at least 1")
    try:
        limit, dist_limits = parse_limit(args.limit)
    except ValueError as exc:
        return fail(str(exc))
    if args.name is not None and (not args.name or "/" in args.name or args.name.endswith(".pt")):
        return fail(f"--name must be a plain name such as posenet_ours, got {args.name!r}")
    cfg = TrainConfig(
        variant=args.variant, dists=dists, epochs=args.epochs, batch=args.batch, lr=args.lr,
        limit=limit, dist_limits=dist_limits, init=args.init, name=args.name, out=args.out,
        threads=args.threads,
    )  # fmt: skip
    if args.smoke:
        cfg = replace(SMOKE, variant=args.variant, dists=dists, out=args.out)
    try:
        result = train(cfg, resume=not args.no_resume)
    except PosegraspError as exc:
        return fail(str(exc))
    print(json.dumps(result["history"][-1] if result["history"] else {}, sort_keys=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())
