"""Self-describing training checkpoints and the random state they carry, for both trainers.

A checkpoint holds everything needed to resume a run or rebuild its model: weights, model and
training config, optimiser, step, epoch, validation history, RNG states, data seeds and the
commit (docs/DESIGN.md §7). Files are written atomically (a temporary file,
then a rename), so an interrupted save leaves the previous file intact.
"""

from __future__ import annotations

import os
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from torch import nn

from posegrasp.core.files import atomic_write
from posegrasp.core.paths import git_commit


def seed_torch(seed: int, threads: int | None) -> None:
    """Seed torch's global RNG and set its CPU threads (None: one per core)."""
    torch.manual_seed(seed)
    torch.set_num_threads(threads or max(1, os.cpu_count() or 1))


def config_dict(cfg: Any) -> dict[str, Any]:
    """A dataclass config as the plain dict a checkpoint stores (paths as strings)."""
    return {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items()}


def rng_state(generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
    """The RNG states to store: torch's global one (``torch``) and, when given, a run's own
    generator (``generator``)."""
    state = {"torch": torch.get_rng_state()}
    if generator is not None:
        state["generator"] = generator.get_state()
    return state


def save_atomically(obj: Any, path: Path) -> None:
    """`torch.save` through a temporary file in `path`'s folder, fsynced, then renamed over it
    (`posegrasp.core.files.atomic_write`): a failed save leaves the previous file intact."""
    atomic_write(path, lambda f: torch.save(obj, f))


def save_checkpoint(
    path: Path,
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    *,
    model_config: dict[str, Any],
    train_config: dict[str, Any],
    step: int,
    epoch: int,
    history: list[dict],
    rng: dict[str, torch.Tensor],
    data_seeds: dict[str, Any],
    header: dict[str, Any] | None = None,
) -> None:
    """Write a resumable checkpoint.

    Args:
        path: the checkpoint file.
        model, optimizer: their state dicts are stored.
        model_config, train_config: plain dicts that rebuild the model and describe the run.
        step, epoch: optimiser steps and whole epochs done.
        history: per-epoch validation results.
        rng: `rng_state()`.
        data_seeds: which data the run trains on.
        header: keys stored first, e.g. the trainer's kind or the run's lineage.
    """
    state = {
        **(header or {}),
        "model": model.state_dict(),
        "model_config": model_config,
        "optimizer": optimizer.state_dict(),
        "train_config": train_config,
        "step": step,
        "epoch": epoch,
        "history": history,
        "rng": rng,
        "data_seeds": data_seeds,
        "commit": git_commit(),
    }
    save_atomically(state, path)


def read_checkpoint(path: Path) -> dict[str, Any]:
    """A checkpoint's contents, tensors on the CPU (raises what `torch.load` raises)."""
    return torch.load(path, map_location="cpu", weights_only=False)


def restore(
    state: dict[str, Any], model: nn.Module, optimizer: torch.optim.Optimizer
) -> tuple[int, int, list[dict]]:
    """Load a checkpoint's weights, optimiser and global torch RNG state.

    Returns:
        (step, epoch, history) to continue from.
    """
    model.load_state_dict(state["model"])
    optimizer.load_state_dict(state["optimizer"])
    torch.set_rng_state(state["rng"]["torch"])
    return state["step"], state["epoch"], state["history"]
