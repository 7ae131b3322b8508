"""Turn training checkpoints into the shipped weights and their manifest.

    python -m perception.training.export [--checkpoints DIR (default: <data>/checkpoints)]
        [--plot training_curves.png]

Writes `perception/weights/posenet_<name>.pt` (float16 weights and the model config, no
optimiser state) and `perception/weights/manifest.json` (command, data seed ranges, sizes,
validation metrics, commit) for every shipped net (`SHIPPED`) that has a checkpoint. The
detector is shipped by `perception.training.export_detector` (``python -m
perception.training.train_detector --export``).
"""

from __future__ import annotations

import pickle
import sys
from collections.abc import Sequence
from pathlib import Path

import torch

from perception.nets import VARIANTS
from perception.training.checkpoints import read_checkpoint, save_atomically
from perception.training.crop_sets import data_seed_ranges
from perception.training.dataset import DISTS
from perception.training.manifest import MANIFEST_NAME, read_manifest, weights_entry, write_manifest
from perception.training.train_posenet import TRAIN_COMMAND
from posegrasp.core.cli import ArgumentParser, command
from posegrasp.core.errors import AssetError, PosegraspError
from posegrasp.core.paths import WEIGHTS_DIR, checkpoint_dir, git_commit
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_plot_path

MANIFEST = WEIGHTS_DIR / MANIFEST_NAME
#: The shipped pose nets: each variant, and `ours` fine-tuned on the hard tier too (the expert
#: of ``hybrid``, `perception.hybrid.HARD_POSENET`).
SHIPPED: tuple[str, ...] = (*VARIANTS, "ours_hard")


def export(checkpoints: Path, out: Path = WEIGHTS_DIR) -> dict:
    """Export every shipped net (`SHIPPED`) found under `checkpoints`; returns the manifest.

    Writes ``<out>/posenet_<name>.pt`` and updates the ``pose_nets`` key of `MANIFEST`; the
    test figures of a net are kept only when its weights are unchanged.

    Raises:
        AssetError: no checkpoint under `checkpoints`, or a manifest that is not valid JSON.
    """
    out.mkdir(parents=True, exist_ok=True)
    manifest = read_manifest(MANIFEST)
    nets = manifest.setdefault("pose_nets", {})
    found = False
    for variant in SHIPPED:
        ckpt = checkpoints / f"posenet_{variant}.pt"
        if not ckpt.is_file():
            continue
        found = True
        state = read_checkpoint(ckpt)
        shipped = {
            "model": {
                k: (v.half() if v.is_floating_point() else v) for k, v in state["model"].items()
            },
            "model_config": state["model_config"],
            "step": state["step"],
            "epoch": state["epoch"],
            "commit": state["commit"],
        }
        path = out / f"posenet_{variant}.pt"
        # Test figures stay valid only for the very same weights, compared by value: two saves
        # of equal tensors need not give equal bytes. Unchanged weights are not rewritten.
        same = _same_weights(path, shipped)
        if not same:
            save_atomically(shipped, path)
        kept = {k: v for k, v in nets.get(variant, {}).items() if same and k.startswith("test")}
        tc = state["train_config"]
        command = state.get("command") or (
            f"{TRAIN_COMMAND} --variant {state['model_config']['variant']} --epochs {tc['epochs']}"
        )
        nets[variant] = {
            **weights_entry(path),
            "command": command,
            "stages": _stages(state, command),
            "train_config": tc,
            "data_seeds": _seeds(state["data_seeds"], tc.get("dists", DISTS)),
            "epochs_done": state["epoch"],
            "validation": state["history"][-1] if state["history"] else None,
            "trained_at_commit": state["commit"],
            **kept,
        }
    if not found:
        raise AssetError(f"no checkpoints under {checkpoints}; run {TRAIN_COMMAND}")
    manifest["rebuild"] = "make weights"
    manifest["exported_at_commit"] = git_commit()
    write_manifest(MANIFEST, manifest)
    return manifest


def _same_weights(path: Path, shipped: dict) -> bool:
    """`path` holds exactly the tensors and model config of `shipped`."""
    if not path.is_file():
        return False
    try:
        old = torch.load(path, map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, pickle.UnpicklingError):
        return False  # unreadable: it is replaced
    a, b = old.get("model", {}), shipped["model"]
    return (
        old.get("model_config") == shipped["model_config"]
        and a.keys() == b.keys()
        and all(a[k].dtype == b[k].dtype and torch.equal(a[k], b[k]) for k in a)
    )


def _stages(state: dict, command: str) -> list[dict]:
    """The training runs that led to a checkpoint, first to last: each stage's command, epochs,
    wall time [s] (None when not recorded), data seed ranges and final validation metrics."""
    chain, node = [], {**state, "command": command}
    while node:
        if node.get("stages"):  # shipped weights: the stages their manifest recorded
            chain.extend(node["stages"][::-1])
            break
        hist = node.get("history")
        chain.append(
            {
                "command": node.get("command"),
                "epochs": node.get("epoch"),
                "wall_s": node.get("wall_s"),
                "data_seeds": node.get("data_seeds"),
                "validation": node.get("validation") or (hist[-1] if hist else None),
            }
        )
        node = node.get("init_from")
    return chain[::-1]


def _stage_history(checkpoints: Path, stage: dict) -> list[dict]:
    """Validation history of a recorded stage: that of the checkpoint its command names
    (``--name``) under `checkpoints` when that run ended on the recorded figures, else its final
    validation alone (empty when none was recorded)."""
    words = (stage.get("command") or "").split()
    final = stage.get("validation")
    if "--name" in words[:-1]:
        path = checkpoints / f"{words[words.index('--name') + 1]}.pt"
        if path.is_file():
            hist = read_checkpoint(path).get("history") or []
            if hist and hist[-1] == final:
                return hist
    return [final] if final else []


def training_curves(checkpoints: Path) -> dict[str, list[list[dict]]]:
    """Validation history of every stage of every exported net: name -> stages (first to
    last) -> epochs. The chain follows the checkpoints each run started from; a run started from
    shipped weights continues with the stages they record (`_stage_history`)."""
    curves = {}
    for variant in SHIPPED:
        path = checkpoints / f"posenet_{variant}.pt"
        stages, seen = [], set()
        while path is not None and path.is_file() and path not in seen:
            seen.add(path)
            state = read_checkpoint(path)
            stages.append(state.get("history") or [])
            parent = state.get("init_from") or {}
            if parent.get("stages"):  # shipped weights: their recorded stages, last first
                stages += [_stage_history(checkpoints, st) for st in parent["stages"][::-1]]
                break
            name = parent.get("checkpoint")  # None: started from scratch
            path = checkpoints / name if name else None
        if stages:
            curves[variant] = stages[::-1]
    return curves


def plot_curves(curves: dict[str, list[list[dict]]], path: Path) -> None:
    """Validation centre, distance, rotation and outlier rate against epoch, one line per
    variant; a dashed line marks where a fine-tuning stage starts."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = (
        ("center_px", "centre [px]"),
        ("distance_pct", "distance [%]"),
        ("rotation_deg", "rotation [deg]"),
        ("outlier_rate", "outliers > 15 deg"),
    )
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.6))
    for variant, stages in curves.items():
        offset, xs, ys = 0, [], {k: [] for k, _ in keys}
        for i, hist in enumerate(stages):
            if i > 0:
                for ax in axes:
                    ax.axvline(offset + 0.5, ls="--", c="grey", lw=0.8)
            for h in hist:
                xs.append(offset + h["epoch"])
                for k, _ in keys:
                    ys[k].append(h[k])
            offset += hist[-1]["epoch"] if hist else 0
        for ax, (k, label) in zip(axes, keys, strict=True):
            ax.plot(xs, ys[k], marker=".", label=variant)
            ax.set_title(label)
            ax.set_xlabel("epoch")
            ax.grid(alpha=0.3)
    axes[0].legend()
    fig.suptitle("validation (each stage on its own validation split; dashed: fine-tuning starts)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _seeds(recorded: dict, dists: Sequence[str]) -> dict:
    """The checkpoint's data seed ranges; read from the datasets when it has none."""
    if any(recorded.get(d) for d in recorded):
        return recorded
    try:
        return data_seed_ranges(dists)
    except (OSError, PosegraspError):  # the data may be gone; the manifest then says so
        return {d: "unknown (dataset not found at export time)" for d in dists}


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(
        prog="python -m perception.training.export", description=__doc__.split("\n")[0]
    )
    p.add_argument(
        "--checkpoints",
        type=Path,
        default=None,
        metavar="DIR",
        help="folder of the training checkpoints (default: <data>/checkpoints)",
    )
    p.add_argument(
        "--plot",
        type=arg(check_plot_path),
        default=None,
        metavar="PATH",
        help="write the training curves here (.png, .pdf or .svg)",
    )
    args = p.parse_args(argv)
    setup_rendering()
    ckpts = args.checkpoints or checkpoint_dir()
    m = export(ckpts)
    if args.plot:
        plot_curves(training_curves(ckpts), args.plot)
        print(f"wrote {args.plot}")
    for v, e in m["pose_nets"].items():
        print(f"{v}: {e['file']} ({e['bytes'] / 1e6:.1f} MB), epochs {e['epochs_done']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
