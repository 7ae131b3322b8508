"""Training of the object extractor (`python -m perception.training.train_detector`).

Trains the Mask R-CNN of `perception.detector` from scratch on the head-camera distribution's
train split (``$POSEGRASP_DATA/headcam``): targets come from the *visible* masks, boxes enclose
them, labels are BOP object ids; instances with fewer than `TrainConfig.min_visible_px` visible
pixels are left out. Photometric augmentation only: no flips, since some objects are chiral
(the faucet's spout, the pistol's grip). Training is seeded and resumable: a self-describing
checkpoint (weights, model and training config, optimiser, step, RNG states, data seeds, commit)
is written to ``<checkpoints>/detector.pt`` every few minutes and after every epoch, each of which
ends with COCO box and mask AP (pycocotools) on the first val images.

    python -m perception.training.train_detector                  # train (resumes when interrupted)
    python -m perception.training.train_detector --export  # finish training, ship the weights
    python -m perception.training.train_detector --smoke --data DIR --out DIR   # seconds, tiny data
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from perception.detector import (
    Detection,
    Detector,
    DetectorConfig,
    build_detector,
    count_parameters,
    image_tensor,
    input_transform,
    state_dict_fp16,
    to_model_box,
)
from perception.training.dataset import PoseDataset, load_info
from perception.training.train_posenet import learning_rate
from sim.core.cli import ArgumentParser, fail
from sim.core.errors import AssetError, InvalidArgumentError, PosegraspError
from sim.core.paths import WEIGHTS_DIR, checkpoint_dir, data_root, git_commit
from sim.world.objects import OBJECT_NAMES

CHECKPOINT_NAME = "detector.pt"
WEIGHTS_NAME = "detector.pt"
MANIFEST_NAME = "manifest.json"


@dataclass(frozen=True)
class TrainConfig:
    """A detector training run.

    Attributes:
        data: dataset folder (BOP layout, splits train and val); None means
            ``data_root() / "headcam"``.
        epochs, batch: passes over the train split and images per step.
        lr, weight_decay, warmup: AdamW peak learning rate, weight decay, and the fraction of
            steps of linear warm-up before the cosine decay
            (`perception.training.train_posenet.learning_rate`).
        grad_clip: gradient norm clip.
        min_visible_px: instances with fewer visible pixels are not training targets (and are
            ignored by the AP evaluation).
        limit: use at most this many train images (None: all).
        val_images: the AP evaluation after each epoch uses the first this many val images.
        seed: seed of initialisation, image order and augmentation.
        workers: data-loading processes (0: load in the training process).
        threads: torch threads for the training process (None: one per core).
        out: checkpoint folder; None means `checkpoint_dir()` (next to the data, outside git).
        checkpoint_minutes: save a resumable checkpoint at least this often.
        detector: the architecture.
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

    def __post_init__(self) -> None:
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
        return {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(self).items()}


#: A run of a few seconds on a handful of images (tests, and checking a set-up).
SMOKE = TrainConfig(epochs=1, batch=2, limit=4, val_images=2, workers=0, threads=1)


def dataset_root(cfg: TrainConfig) -> Path:
    """The dataset folder the run trains on."""
    return Path(cfg.data) if cfg.data is not None else data_root() / "headcam"


# --- data --------------------------------------------------------------------------------------


def mask_box(mask: np.ndarray) -> np.ndarray:
    """The SPEC 2 box (x0, y0, x1, y1) [px] that encloses a mask's pixels (it must have some)."""
    ys, xs = np.nonzero(mask)
    return np.array([xs.min() - 0.5, ys.min() - 0.5, xs.max() + 0.5, ys.max() + 0.5])


class DetectionSet(torch.utils.data.Dataset):
    """Images of one split with Mask R-CNN targets from the visible masks.

    An item is ``(image, target)`` already scaled to the model's input size as the model's own
    transform would (`input_transform`), so that the work happens in the loading process:
    image (3, h, w) float32 in [0, 1], target a dict with ``boxes`` (N, 4) float32 in
    torchvision's pixel convention, ``labels`` (N,) int64 BOP object ids and ``masks``
    (N, h, w) uint8. Instances with fewer than `min_visible_px` visible pixels (at full
    resolution) are left out (N may be 0: a negative image).
    """

    def __init__(
        self,
        root: Path,
        split: str,
        min_visible_px: int,
        cfg: DetectorConfig,
        limit: int | None = None,
    ) -> None:
        self.data = PoseDataset(root, split)
        self.n = len(self.data) if limit is None else min(limit, len(self.data))
        self.min_visible_px = min_visible_px
        self.transform = input_transform(cfg)

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        s = self.data[i]
        keep = [o for o in s.objects if int(o.mask_visib.sum()) >= self.min_visible_px]
        h, w = s.rgb.shape[:2]
        boxes = np.array([to_model_box(mask_box(o.mask_visib)) for o in keep]).reshape(-1, 4)
        masks = np.array([o.mask_visib for o in keep], np.uint8).reshape(-1, h, w)
        target = {
            "boxes": torch.from_numpy(boxes).float(),
            "labels": torch.tensor([o.obj_id for o in keep], dtype=torch.int64),
            "masks": torch.from_numpy(masks),
        }
        return self.transform.resize(image_tensor(s.rgb), target)


def _collate(batch: list) -> list:
    return batch


def augment(x: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """Photometric jitter of one (3, H, W) image in [0, 1]: brightness, contrast, saturation,
    per-channel gain and pixel noise. Geometry is untouched (no flips: some objects are chiral).
    """
    r = torch.rand(6, generator=g)
    grey = x.mean(dim=0, keepdim=True)
    x = grey + (x - grey) * (0.6 + 0.8 * r[0])  # saturation
    x = (x - x.mean()) * (0.7 + 0.6 * r[1]) + x.mean()  # contrast
    x = x * (0.9 + 0.2 * torch.rand(3, 1, 1, generator=g)) + (r[2] - 0.5) * 0.2  # gain, bright
    x = x + torch.randn(x.shape, generator=g) * (0.03 * r[3])  # noise
    return x.clamp(0.0, 1.0)


# --- evaluation --------------------------------------------------------------------------------


def _coco() -> tuple[Any, Any, Any]:
    try:
        from pycocotools import mask as mask_utils
        from pycocotools.coco import COCO
        from pycocotools.cocoeval import COCOeval
    except ImportError as exc:
        raise AssetError(
            "the detector's AP evaluation needs pycocotools: pip install pycocotools "
            "(a dependency in pyproject.toml; reinstall with `make setup`)"
        ) from exc
    return COCO, COCOeval, mask_utils


def coco_ap(
    gts: list[list[tuple[int, np.ndarray]]],
    dets: list[list[Detection]],
    min_visible_px: int,
    per_class: dict[str, dict[str, float]] | None = None,
) -> dict[str, float]:
    """COCO box and mask AP of detections against ground truth, by pycocotools' COCOeval.

    Args:
        gts: per image, (obj_id, visible mask (H, W) bool) of every object; objects with fewer
            than `min_visible_px` pixels are marked crowd, so that they count neither as misses
            nor (when detected) as false positives.
        dets: per image, the detections (scores from low thresholds give the full curve).
        min_visible_px: see gts.
        per_class: when given, filled with class name -> ``box_ap``, ``box_ap50``, ``mask_ap``,
            ``mask_ap50`` of that class alone.

    Returns:
        ``box_ap50``, ``box_ap`` (IoU 0.5:0.95), ``mask_ap50``, ``mask_ap`` in [0, 1]; 0 when
        there is no detection; -1 when there is no ground truth (pycocotools' convention).
    """
    COCO, COCOeval, mask_utils = _coco()

    def rle(mask: np.ndarray) -> dict:
        return mask_utils.encode(np.asfortranarray(mask.astype(np.uint8)))

    images, anns, box_res, seg_res = [], [], [], []
    for i, (gt, dd) in enumerate(zip(gts, dets, strict=True)):
        h, w = gt[0][1].shape if gt else (dd[0].mask.shape if dd else (1, 1))
        images.append({"id": i, "height": int(h), "width": int(w)})
        for oid, m in gt:
            r = rle(m)
            area = int(m.sum())
            anns.append({
                "id": len(anns) + 1, "image_id": i, "category_id": int(oid),
                "segmentation": r, "area": float(area), "bbox": mask_utils.toBbox(r).tolist(),
                "iscrowd": int(area < min_visible_px),
            })  # fmt: skip
        for d in dd:
            x0, y0, x1, y1 = to_model_box(d.box_xyxy)
            common = {"image_id": i, "category_id": d.obj_id, "score": d.score}
            box_res.append({**common, "bbox": [x0, y0, x1 - x0, y1 - y0]})
            seg_res.append({**common, "segmentation": rle(d.mask)})
    cats = [{"id": k + 1, "name": n} for k, n in enumerate(OBJECT_NAMES)]
    out: dict[str, float] = {}
    with contextlib.redirect_stdout(io.StringIO()):  # pycocotools prints progress
        gt_api = COCO()
        gt_api.dataset = {"images": images, "annotations": anns, "categories": cats}
        gt_api.createIndex()
        for kind, res in (("box", box_res), ("mask", seg_res)):
            if not res:
                out[f"{kind}_ap50"] = out[f"{kind}_ap"] = 0.0 if anns else -1.0
                continue
            ev = COCOeval(gt_api, gt_api.loadRes(res), "bbox" if kind == "box" else "segm")
            ev.evaluate()
            ev.accumulate()
            ev.summarize()
            out[f"{kind}_ap"] = float(ev.stats[0])
            out[f"{kind}_ap50"] = float(ev.stats[1])
            if per_class is not None:
                for name, (ap, ap50) in _per_class_ap(ev).items():
                    per_class.setdefault(name, {})[f"{kind}_ap"] = ap
                    per_class[name][f"{kind}_ap50"] = ap50
    return out


def _per_class_ap(ev: Any) -> dict[str, tuple[float, float]]:
    """(AP at IoU 0.5:0.95, AP50) per class from an accumulated COCOeval: the mean of its
    precision table over IoU thresholds and recall points, all areas, at most 100 detections;
    -1 for a class without ground truth (pycocotools' convention)."""
    prec = ev.eval["precision"]  # (IoU thresholds, recall points, classes, areas, max dets)
    out = {}
    for k, cat in enumerate(ev.params.catIds):
        pk = prec[:, :, k, 0, -1]
        valid = pk > -1
        ap = float(pk[valid].mean()) if valid.any() else -1.0
        p50 = pk[0][pk[0] > -1]
        out[OBJECT_NAMES[cat - 1]] = (ap, float(p50.mean()) if p50.size else -1.0)
    return out


def evaluate_detector(
    detector: Detector, data: PoseDataset, n_images: int, min_visible_px: int
) -> dict[str, float]:
    """COCO AP (`coco_ap`) of a detector on the first n_images of a split."""
    gts, dets = [], []
    for i in range(min(n_images, len(data))):
        s = data[i]
        gts.append([(o.obj_id, o.mask_visib) for o in s.objects if o.mask_visib.any()])
        dets.append(detector.detect(s.rgb))
    return coco_ap(gts, dets, min_visible_px) | {"images": len(gts)}


# --- training ----------------------------------------------------------------------------------


def _rng_state(g: torch.Generator) -> dict[str, torch.Tensor]:
    return {"torch": torch.get_rng_state(), "generator": g.get_state()}


def _checkpoint(path: Path, model, opt, cfg: TrainConfig, step, epoch, history, seeds, rng) -> None:
    state = {
        "kind": "detector",
        "model": model.state_dict(),
        "model_config": cfg.detector.to_dict(),
        "optimizer": opt.state_dict(),
        "train_config": cfg.to_dict(),
        "step": step,
        "epoch": epoch,
        "history": history,
        "rng": rng,
        "data_seeds": seeds,
        "commit": git_commit(),
    }
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    tmp.replace(path)


def train(cfg: TrainConfig, resume: bool = True, max_steps: int | None = None) -> dict:
    """Train, resuming from the run's checkpoint when present.

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
    """
    root = dataset_root(cfg)
    for split in ("train", "val"):
        if not (root / split).is_dir():
            raise AssetError(
                f"no {split} split under {root}; build it with "
                "`python -m perception.training.datagen "
                f"--dist headcam --split {split} --count N --out {root}` (or `make data`)"
            )
    train_set = DetectionSet(root, "train", cfg.min_visible_px, cfg.detector, cfg.limit)
    val_data = PoseDataset(root, "val")
    if len(train_set) < cfg.batch:
        raise AssetError(
            f"{len(train_set)} completed train images under {root}, fewer than one batch "
            f"({cfg.batch}); generate more with "
            "`python -m perception.training.datagen --dist headcam`"
        )
    if len(val_data) == 0:
        raise AssetError(f"no completed val images under {root}; generate them first")
    _coco()  # fail now, not after the first epoch, when pycocotools is missing
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads or max(1, os.cpu_count() or 1))
    model = build_detector(cfg.detector)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    out = cfg.out or checkpoint_dir()
    out.mkdir(parents=True, exist_ok=True)
    ckpt = out / CHECKPOINT_NAME
    g = torch.Generator()
    step, epoch0, history, g_state = 0, 0, [], None
    if resume and ckpt.is_file():
        try:
            state = torch.load(ckpt, map_location="cpu", weights_only=False)
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
        if n_saved > len(train_set):
            raise AssetError(
                f"checkpoint {ckpt} trained on {n_saved} images, {root} now has "
                f"{len(train_set)}; pass --no-resume to start over"
            )
        # The same images as before the interruption, even if the split has grown since.
        train_set.n = n_saved
        try:
            model.load_state_dict(state["model"])
            opt.load_state_dict(state["optimizer"])
            torch.set_rng_state(state["rng"]["torch"])
            g_state = state["rng"]["generator"]
            step, epoch0, history = state["step"], state["epoch"], state["history"]
        except Exception as exc:
            raise AssetError(
                f"checkpoint {ckpt} is corrupt ({exc}); delete it or pass --no-resume"
            ) from exc
        print(f"resuming {ckpt} at epoch {epoch0}, step {step}")
    steps_per_epoch = len(train_set) // cfg.batch
    total_steps = cfg.epochs * steps_per_epoch
    seeds = {
        "dataset": str(root),
        "dataset_seed_bases": load_info(root).get("seed_bases", {}),
        "train_images": len(train_set),
        "val_images": min(cfg.val_images, len(val_data)),
        "order_seed": "seed * 1000 + epoch",
        "seed": cfg.seed,
    }

    def save(epoch: int) -> None:
        _checkpoint(ckpt, model, opt, cfg, step, epoch, history, seeds, _rng_state(g))

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
            batch_size=cfg.batch,
            sampler=order[done * cfg.batch : steps_per_epoch * cfg.batch],
            collate_fn=_collate,
            num_workers=cfg.workers,
            generator=torch.Generator().manual_seed(cfg.seed),  # leaves the global RNG alone
        )
        model.train()
        bar = tqdm(loader, desc=f"detector epoch {epoch + 1}/{cfg.epochs}", initial=done,
                   total=steps_per_epoch, mininterval=2.0)  # fmt: skip
        losses = []
        for batch in bar:
            if max_steps is not None and step >= max_steps:
                break
            images = [augment(image, g) for image, _ in batch]
            parts = model(images, [t for _, t in batch])
            loss = sum(parts.values())
            for group in opt.param_groups:
                group["lr"] = learning_rate(step, total_steps, cfg.lr, cfg.warmup)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
            opt.step()
            step += 1
            losses.append(float(loss.detach()))
            if step % 10 == 0:
                bar.set_postfix({k.removeprefix("loss_"): f"{float(v):.3f}"
                                 for k, v in parts.items()})  # fmt: skip
            if time.monotonic() - last_save > 60 * cfg.checkpoint_minutes:
                save(epoch)
                last_save = time.monotonic()
        bar.close()
        if max_steps is not None and step >= max_steps and step < (epoch + 1) * steps_per_epoch:
            save(epoch)
            return {"checkpoint": str(ckpt), "history": history, "step": step, "finished": False}
        det = Detector(model, cfg.detector, score_threshold=cfg.detector.box_score_thresh)
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


# --- export ------------------------------------------------------------------------------------


def export(checkpoint: Path, out_dir: Path = WEIGHTS_DIR) -> dict:
    """Write the shipped weights (float16 state dict, model config) and their manifest entry.

    Writes ``<out_dir>/detector.pt`` and updates the ``detector`` key of
    ``<out_dir>/manifest.json``, keeping every other key.

    Returns:
        The manifest entry.

    Raises:
        AssetError: missing or corrupt checkpoint.
    """
    if not checkpoint.is_file():
        raise AssetError(f"no detector checkpoint {checkpoint}; run python -m "
                         "perception.training.train_detector first")  # fmt: skip
    try:
        state = torch.load(checkpoint, map_location="cpu", weights_only=False)
        cfg = DetectorConfig.from_dict(state["model_config"])
        model = build_detector(cfg)
        model.load_state_dict(state["model"])
    except Exception as exc:
        raise AssetError(f"detector checkpoint {checkpoint} is corrupt ({exc})") from exc
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / WEIGHTS_NAME
    validation = state["history"][-1] if state["history"] else None
    shipped = {
        "kind": "detector",
        "model": state_dict_fp16(model),
        "model_config": cfg.to_dict(),
        "step": state["step"],
        "epoch": state["epoch"],
        "validation": validation,
        "commit": state["commit"],
    }
    tmp = path.with_suffix(".tmp")
    torch.save(shipped, tmp)
    tmp.replace(path)
    tc = state["train_config"]
    entry = {
        "file": path.name,
        "bytes": path.stat().st_size,
        "parameters": count_parameters(model),
        "command": f"python -m perception.training.train_detector --epochs {tc['epochs']} --export",
        "train_config": tc,
        "data_seeds": state["data_seeds"],
        "epochs_done": state["epoch"],
        "validation": validation,
        "trained_at_commit": state["commit"],
    }
    manifest_path = out_dir / MANIFEST_NAME
    try:
        manifest = json.loads(manifest_path.read_text()) if manifest_path.is_file() else {}
    except ValueError as exc:
        raise AssetError(f"{manifest_path} is not valid JSON ({exc}); fix or delete it") from exc
    manifest["detector"] = entry
    tmp_manifest = manifest_path.with_suffix(".tmp")
    tmp_manifest.write_text(json.dumps(manifest, indent=1, sort_keys=True) + "\n")
    tmp_manifest.replace(manifest_path)
    return entry


# --- command line ------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(
        prog="python -m perception.training.train_detector", description=__doc__.split("\n")[0]
    )
    p.add_argument(
        "--data",
        type=Path,
        default=None,
        help="dataset folder with train and val (default: $POSEGRASP_DATA/headcam)",
    )
    p.add_argument("--epochs", type=int, default=TrainConfig.epochs)
    p.add_argument("--batch", type=int, default=TrainConfig.batch)
    p.add_argument("--lr", type=float, default=TrainConfig.lr)
    p.add_argument("--limit", type=int, default=None, help="at most this many train images")
    p.add_argument("--val-images", type=int, default=TrainConfig.val_images)
    p.add_argument(
        "--workers", type=int, default=TrainConfig.workers, help="data-loading processes (0: none)"
    )
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: all cores)")
    p.add_argument("--seed", type=int, default=TrainConfig.seed)
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="checkpoint folder (default: <data root>/checkpoints)",
    )
    p.add_argument(
        "--max-steps",
        type=int,
        default=None,
        help="stop after this many steps in total (resumable)",
    )
    p.add_argument("--smoke", action="store_true", help="a tiny run that takes seconds")
    p.add_argument("--no-resume", action="store_true", help="start over")
    p.add_argument(
        "--export",
        action="store_true",
        help="after training, write perception/weights/detector.pt and its manifest "
        "entry (a finished run is not trained further)",
    )
    p.add_argument(
        "--weights-out",
        type=Path,
        default=WEIGHTS_DIR,
        help="folder of the exported weights and manifest.json",
    )
    args = p.parse_args(argv)  # fmt: skip
    try:
        if args.smoke:
            cfg = replace(SMOKE, data=args.data, out=args.out, seed=args.seed,
                          threads=args.threads or SMOKE.threads)  # fmt: skip
        else:
            cfg = TrainConfig(
                data=args.data, epochs=args.epochs, batch=args.batch, lr=args.lr,
                limit=args.limit, val_images=args.val_images, workers=args.workers,
                seed=args.seed, out=args.out, threads=args.threads,
            )  # fmt: skip
        if args.max_steps is not None and args.max_steps < 1:
            raise InvalidArgumentError(f"--max-steps must be >= 1, got {args.max_steps}")
        result = train(cfg, resume=not args.no_resume, max_steps=args.max_steps)
        if result["history"]:
            print(json.dumps(result["history"][-1], sort_keys=True))
        if args.export:
            if not result["finished"]:
                print("note: exporting an unfinished run", file=sys.stderr)
            entry = export(Path(result["checkpoint"]), args.weights_out)
            print(f"wrote {args.weights_out / entry['file']} ({entry['bytes'] / 1e6:.1f} MB)")
    except PosegraspError as exc:
        return fail(str(exc))
    return 0


if __name__ == "__main__":
    sys.exit(main())
