"""The optimisation schedule both trainers share: learning rate per step and one optimiser step
(docs/DESIGN.md §7)."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn


def learning_rate(
    step: int, total_steps: int, peak: float, warmup: float = 0.05, decay: bool = True
) -> float:
    """Linear warm-up to `peak` over the first `warmup` fraction of steps, then cosine to 1 %
    (or, with ``decay=False``, `peak` to the end)."""
    w = max(1, int(warmup * total_steps))
    if step < w:
        return peak * (step + 1) / w
    if not decay:
        return peak
    frac = min(1.0, (step - w) / max(1, total_steps - w))
    return peak * (0.01 + 0.99 * 0.5 * (1 + np.cos(np.pi * frac)))


def optimiser_step(
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    loss: torch.Tensor,
    lr: float,
    max_grad_norm: float,
) -> None:
    """Set the learning rate, back-propagate `loss`, clip the gradient norm, take the step."""
    for group in optimizer.param_groups:
        group["lr"] = lr
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), max_grad_norm)
    optimizer.step()
