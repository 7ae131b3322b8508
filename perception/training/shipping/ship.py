"""The one route from training checkpoints to shipped weights and their manifest entries.

`ship` writes a checkpoint's weights (float16 state dict and model config, no optimiser) and its
entry in the manifest beside them (command, train config, data seeds, epochs, wall time,
validation, commit, size and hash, and the stages behind it); every shipping goes through it:
the recipe's ``ship`` step (`perception.training.recipe`), which makes the shipped weights, and
the trainers' own exports of weights one trains oneself (`export` for the pose nets, the command
`perception.training.export`; `export_detector`, ``train_detector --export``; `export_masknet`,
``train_masknet --export``).
"""

from __future__ import annotations

import pickle
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from perception.detector_net import (
    DetectorConfig,
    build_detector,
    count_parameters,
    state_dict_fp16,
)
from perception.mask_net import expert_path
from perception.nets import VARIANTS
from perception.training.data.crop_sets import data_seed_ranges
from perception.training.data.dataset import DISTS
from perception.training.trainers.checkpoints import read_checkpoint, save_atomically
from perception.training.trainers.manifest import (
    MANIFEST_NAME,
    read_manifest,
    stage_record,
    weights_entry,
    write_manifest,
)
from perception.training.trainers.posenet_trainer import TRAIN_COMMAND
from posegrasp.core.errors import AssetError, PosegraspError
from posegrasp.core.paths import WEIGHTS_DIR, git_commit
from posegrasp.core.validate import check_choice

#: The shipped pose nets: each variant, and `ours` fine-tuned on the hard tier too (the expert
#: of ``hybrid``, `perception.hybrid.HARD_POSENET`).
SHIPPED: tuple[str, ...] = (*VARIANTS, "ours_hard")
#: What a checkpoint can be shipped as.
KINDS = ("posenet", "detector", "masknet")


def shipped_weights(kind: str, state: dict[str, Any]) -> dict[str, Any]:
    """What the shipped file of a checkpoint `state` of `kind` (`KINDS`) holds, as its loader
    reads it: the float16 weights, the model config and, for the nets that carry it, where the
    run ended.

    Raises:
        InvalidArgumentError: an unknown kind.
        AssetError: a detector checkpoint whose weights do not build its model.
    """
    check_choice(kind, KINDS, "kind")
    model: dict[str, torch.Tensor]
    if kind == "detector":
        model = state_dict_fp16(_detector(state))
    else:
        model = {k: v.half() if v.is_floating_point() else v for k, v in state["model"].items()}
    weights = {"model": model, "model_config": state["model_config"]}
    if kind == "masknet":
        return weights
    ended = {"step": state["step"], "epoch": state["epoch"], "commit": state["commit"]}
    if kind == "posenet":
        return weights | ended
    history = state.get("history")
    return {"kind": "detector", **weights, **ended, "validation": history[-1] if history else None}


def _detector(state: dict[str, Any]) -> torch.nn.Module:
    """The detector of a checkpoint, built from its model config and weights.

    Raises:
        AssetError: the weights do not build that model.
    """
    try:
        model = build_detector(DetectorConfig.from_dict(state["model_config"]))
        model.load_state_dict(state["model"])
    except Exception as exc:
        raise AssetError(f"the detector checkpoint is corrupt ({exc})") from exc
    return model


def ship(
    state: dict[str, Any],
    kind: str,
    dest: Path,
    key: tuple[str, ...],
    command: str,
    earlier: list[dict[str, Any]] | None = None,
    stage: str | None = None,
) -> dict[str, Any]:
    """Ship the checkpoint `state` as `dest` and record it under `key` of the manifest beside it.

    The weights are written only when they differ by value from the file already there (two saves
    of equal tensors need not give equal bytes); the entry's test figures (keys ``test...``,
    written by ``tables --record``) are kept only then, since they hold for those weights alone.
    Every other key of the manifest is kept.

    Args:
        state: a training checkpoint (`perception.training.trainers.checkpoints`).
        kind: what it holds (`KINDS`).
        dest: the shipped file.
        key: the entry's place in the manifest, e.g. ``("pose_nets", "ours")``, ``("detector",)``.
        command: the command that trained it.
        earlier: the records (`stage_record`) of the stages before it, first to last; the
            entry's ``stages`` are those and its own (None: no ``stages``, the entry is its one
            stage).
        stage: the name of its stage in a recipe (`perception.training.recipe`), recorded when
            given.

    Returns:
        The entry.

    Raises:
        AssetError: a manifest that is not valid JSON.
    """
    shipped = shipped_weights(kind, state)
    dest.parent.mkdir(parents=True, exist_ok=True)
    same = _same_weights(dest, shipped)
    if not same:
        save_atomically(shipped, dest)
    manifest_path = dest.parent / MANIFEST_NAME
    manifest = read_manifest(manifest_path)
    parent = manifest
    for part in key[:-1]:
        parent = parent.setdefault(part, {})
    kept = {k: v for k, v in parent.get(key[-1], {}).items() if same and k.startswith("test")}
    history = state.get("history") or []
    wall_s = state.get("wall_s")
    entry = {
        **weights_entry(dest),
        **({"stage": stage} if stage else {}),
        "command": command,
        "train_config": state.get("train_config"),
        "data_seeds": state.get("data_seeds"),
        "epochs_done": state["epoch"],
        "wall_s": None if wall_s is None else round(float(wall_s), 1),
        "validation": history[-1] if history else None,
        "trained_at_commit": state.get("commit"),
        "parameters": _parameters(kind, state),
        **kept,
    }
    if earlier is not None:
        entry["stages"] = [*earlier, stage_record(entry)]
    parent[key[-1]] = entry
    write_manifest(manifest_path, manifest)
    return entry


def _parameters(kind: str, state: dict[str, Any]) -> int:
    """The number of parameters of a checkpoint's net (the detector's trainable ones; the
    others' every tensor)."""
    if kind == "detector":
        return count_parameters(_detector(state))
    return sum(int(v.numel()) for v in state["model"].values())


def export(checkpoints: Path, out: Path = WEIGHTS_DIR) -> dict:
    """Ship every pose net (`SHIPPED`) found under `checkpoints` as ``<out>/posenet_<name>.pt``
    (`ship`, entry ``pose_nets.<name>``, with the stages its checkpoints started from); returns
    the manifest.

    Raises:
        AssetError: no checkpoint under `checkpoints`, or a manifest that is not valid JSON.
    """
    found = False
    for variant in SHIPPED:
        ckpt = checkpoints / f"posenet_{variant}.pt"
        if not ckpt.is_file():
            continue
        found = True
        state = read_checkpoint(ckpt)
        tc = state["train_config"]
        command = state.get("command") or (
            f"{TRAIN_COMMAND} --variant {state['model_config']['variant']} --epochs {tc['epochs']}"
        )
        state = {**state, "data_seeds": _seeds(state["data_seeds"], tc.get("dists", DISTS))}
        path = out / f"posenet_{variant}.pt"
        ship(state, "posenet", path, ("pose_nets", variant), command, _stages(state)[:-1])
    if not found:
        raise AssetError(f"no checkpoints under {checkpoints}; run {TRAIN_COMMAND}")
    return stamp_manifest(out)


def stamp_manifest(weights: Path) -> dict[str, Any]:
    """Record in the manifest in `weights` how its files are rebuilt and the commit that shipped
    them; returns the manifest.

    Raises:
        AssetError: a manifest that is not valid JSON.
    """
    manifest_path = weights / MANIFEST_NAME
    manifest = read_manifest(manifest_path)
    manifest["rebuild"] = "make weights"
    manifest["exported_at_commit"] = git_commit()
    write_manifest(manifest_path, manifest)
    return manifest


def _init_entry(init: str | None) -> dict[str, Any] | None:
    """The manifest entry of the shipped detector a run started from (`init`: a
    ``detector.pt`` whose folder's manifest records it), or None."""
    if not init or Path(init).name != "detector.pt":
        return None
    manifest_path = Path(init).parent / MANIFEST_NAME
    if not manifest_path.is_file():
        return None
    entry = read_manifest(manifest_path).get("detector")
    return entry if isinstance(entry, dict) and entry.get("file") == "detector.pt" else None


def export_detector(checkpoint: Path, out_dir: Path = WEIGHTS_DIR) -> dict[str, Any]:
    """Ship a detector checkpoint as ``<out_dir>/detector.pt`` (`ship`, entry ``detector``); a
    run started from shipped weights lists the stages that made them before its own.

    Raises:
        AssetError: missing or corrupt checkpoint, or a manifest that is not valid JSON.
    """
    if not checkpoint.is_file():
        raise AssetError(
            f"no detector checkpoint {checkpoint}; run python -m "
            "perception.training.train_detector first"
        )
    try:
        state = read_checkpoint(checkpoint)
    except Exception as exc:
        raise AssetError(f"detector checkpoint {checkpoint} is corrupt ({exc})") from exc
    command = state.get("command") or "python -m perception.training.train_detector"
    previous = _init_entry(state["train_config"].get("init"))
    # Fine-tuned from shipped weights: the stages that made them come first.
    earlier = None if previous is None else previous.get("stages") or [stage_record(previous)]
    return ship(state, "detector", out_dir / "detector.pt", ("detector",), command, earlier)


def export_masknet(
    checkpoint: Path, command: str, out: Path, expert: str | None = None
) -> dict[str, Any]:
    """Ship a mask-net checkpoint as `out` (`ship`, entry ``mask_net``), or with `expert` as the
    net that serves that object alone (`perception.mask_net.expert_path` of `out`, entry
    ``mask_net_experts.<expert>``); a run started from a shipped net lists the stages that made
    it before its own.

    Raises:
        AssetError: the run has not finished its epochs.
    """
    state = read_checkpoint(checkpoint)
    epochs = state["train_config"]["epochs"]
    if state["epoch"] < epochs:
        raise AssetError(
            f"the run in {checkpoint.parent} has done {state['epoch']}/{epochs} epochs; "
            "finish it first"
        )
    dest = out if expert is None else expert_path(out, expert)
    key = ("mask_net",) if expert is None else ("mask_net_experts", expert)
    earlier = (state.get("lineage") or {}).get("stages") or None
    return ship(state, "masknet", dest, key, command, earlier)


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


def checkpoint_record(state: dict[str, Any]) -> dict[str, Any]:
    """What a manifest's ``stages`` keep of the run of a checkpoint (`stage_record`'s keys)."""
    history = state.get("history") or []
    wall_s = state.get("wall_s")
    return {
        "command": state.get("command"),
        "data_seeds": state.get("data_seeds"),
        "epochs_done": state.get("epoch"),
        "wall_s": None if wall_s is None else round(float(wall_s), 1),
        "validation": state.get("validation") or (history[-1] if history else None),
        "trained_at_commit": state.get("commit"),
    }


def _stages(state: dict) -> list[dict]:
    """The training runs that led to a pose-net checkpoint, first to last (`checkpoint_record`
    of each, following the checkpoints each started from; a run started from shipped weights
    continues with the stages their manifest records)."""
    node: dict | None
    chain, node = [], state
    while node:
        if node.get("stages"):  # shipped weights: the stages their manifest recorded
            chain.extend(node["stages"][::-1])
            break
        chain.append(checkpoint_record(node))
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
        path: Path | None = checkpoints / f"posenet_{variant}.pt"
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
        ys: dict[str, list[float]]
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
