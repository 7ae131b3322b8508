"""Photometric augmentation of training crops (docs/DESIGN.md §7)."""

from __future__ import annotations

import torch

from perception.training.trainers.ddp import ONE_PROCESS, Ranks


def photometric_jitter(
    x: torch.Tensor, g: torch.Generator, ranks: Ranks = ONE_PROCESS
) -> torch.Tensor:
    """Brightness, contrast, per-channel gain and pixel noise on normalised crops.

    The jitter is drawn for the whole global batch (`x` is this rank's shard of it) and this
    rank's rows are taken, so a batch is jittered alike on any number of processes.
    """
    b = x.shape[0] * ranks.world
    bright = (torch.rand(b, 1, 1, 1, generator=g) - 0.5) * 0.3
    contrast = 0.75 + 0.5 * torch.rand(b, 1, 1, 1, generator=g)
    gain = 0.9 + 0.2 * torch.rand(b, 3, 1, 1, generator=g)
    noise = torch.randn((b, *x.shape[1:]), generator=g) * 0.02
    jitter = [ranks.shard(t).to(x.device) for t in (bright, contrast, gain, noise)]
    bright, contrast, gain, noise = jitter
    return (x * contrast * gain + bright + noise).clamp(-0.5, 0.5)
