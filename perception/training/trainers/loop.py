"""The training loop the three nets share (`fit`), and what their runs have in common.

`fit` reads as a run goes: start the run (fresh, from another net's weights, or resumed from its
own checkpoint), then every epoch its steps in the run's seeded order, a checkpoint whenever one is
due, then validation and a checkpoint at the epoch's end. A net brings only what is its own, the
five methods of a `NetTrainer`: its data and model (`start`), an epoch's batches (`batches`), one
optimiser step (`step`), its validation (`validate`) and its checkpoint (`save`). Exporting the
weights is the commands' (`perception.training.shipping.ship`).
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import torch
from torch import nn

from perception.training.trainers.ddp import Ranks
from posegrasp.core.progress import progress_bar

#: Arithmetic of the training forward passes (``--precision``): fp32, or bf16 autocast.
PRECISIONS = ("fp32", "bf16")


def autocast(precision: str, device: torch.device) -> contextlib.AbstractContextManager[Any]:
    """bfloat16 autocast on `device` for a bf16 run; nothing for fp32."""
    if precision == "bf16":
        return torch.autocast(device_type=device.type, dtype=torch.bfloat16)
    return contextlib.nullcontext()


@dataclass
class Run:
    """A run's model and optimiser, its plan and where it stands (`fit` updates it as it trains).

    Attributes:
        model: the net itself, unwrapped (what a checkpoint holds).
        opt: its optimiser.
        steps_per_epoch: the optimiser steps of an epoch.
        step: optimiser steps done.
        epoch: whole epochs done.
        history: per-epoch validation.
        wall_s: wall time of the run before this process started it [s].
    """

    model: nn.Module
    opt: torch.optim.Optimizer
    steps_per_epoch: int
    step: int = 0
    epoch: int = 0
    history: list[dict] = field(default_factory=list)
    wall_s: float = 0.0

    def done_in(self, epoch: int) -> int:
        """The steps of epoch `epoch` (0-based) done already (those of a resumed epoch)."""
        return max(0, self.step - epoch * self.steps_per_epoch)


@dataclass(frozen=True)
class Step:
    """What one optimiser step reports.

    Attributes:
        loss: the loss on this process's shard of the batch.
        lr: the learning rate of the step.
        shown: the figures the progress bar shows (tensors are read only when it shows them).
        mean: the loss averaged over the processes when the net has averaged it already (None:
            `fit` averages it when it logs the loss).
    """

    loss: torch.Tensor
    lr: float
    shown: Mapping[str, float | torch.Tensor]
    mean: float | None = None


class NetTrainer(Protocol):
    """What a net brings to `fit`.

    Attributes:
        label: what the progress bar calls the net.
        ranks: this process's place in the run (`perception.training.trainers.ddp`).
    """

    label: str
    ranks: Ranks

    def start(self, resume: bool) -> Run:
        """The run's data, model and optimiser: fresh, started from another net's weights, or
        (with `resume`) resumed from the run's own checkpoint when it has one."""
        ...

    def batches(self, run: Run, epoch: int) -> Iterator[Any]:
        """The batches of epoch `epoch` (0-based) that are not done yet, in the run's order for
        that epoch (this process's shard of each)."""
        ...

    def step(self, run: Run, batch: Any, epoch: int) -> Step:
        """One optimiser step on `batch`, at step `run.step`."""
        ...

    def validate(self, run: Run, epoch: int) -> None:
        """Measure the net after epoch `epoch` (0-based), append the figures to `run.history`
        and print them."""
        ...

    def save(self, run: Run, epoch: int, wall_s: float) -> None:
        """Write the run's checkpoint: `epoch` whole epochs done, `wall_s` the run's wall time
        over all its resumptions [s]."""
        ...


def fit(
    net: NetTrainer,
    epochs: int,
    *,
    resume: bool = True,
    checkpoint_minutes: float = 5.0,
    loss_log: Path | None = None,
    max_steps: int | None = None,
) -> tuple[Run, bool]:
    """Train `net` for `epochs` epochs: the loop every trainer runs.

    Rank 0 validates and saves after each epoch; the other processes meet it at the next step.

    Args:
        net: the net's part of the run.
        epochs: whole epochs to reach.
        resume: continue from the run's checkpoint when it has one.
        checkpoint_minutes: save at least this often during an epoch.
        loss_log: append one JSON line per step here (step, epoch, loss averaged over the
            processes, learning rate), or None.
        max_steps: stop, saved, once this many steps are done in all (as an interruption would;
            the run resumes from there).

    Returns:
        The run, and whether all its epochs are done.
    """
    run = net.start(resume)
    ckpts = Checkpointer(lambda e, wall_s: net.save(run, e, wall_s), checkpoint_minutes, run.wall_s)
    ranks = net.ranks
    for epoch in range(run.epoch, epochs):
        run.model.train()
        bar = progress_bar(
            net.batches(run, epoch),
            desc=f"{net.label} epoch {epoch + 1}/{epochs}",
            initial=run.done_in(epoch),
            total=run.steps_per_epoch,
            mininterval=2.0,
            disable=not ranks.main,
        )
        for batch in bar:
            if max_steps is not None and run.step >= max_steps:
                bar.close()
                ckpts.save(epoch)
                return run, False
            step = net.step(run, batch, epoch)
            run.step += 1
            if loss_log is not None:  # every rank takes part in the mean
                loss = ranks.mean(step.loss) if step.mean is None else step.mean
                ranks.log(loss_log, step=run.step, epoch=epoch + 1, loss=loss, lr=step.lr)
            if run.step % 20 == 0:
                bar.set_postfix({k: f"{float(v):.3f}" for k, v in step.shown.items()})
            ckpts.save_if_due(epoch)
        bar.close()
        run.epoch = epoch + 1
        if ranks.main:
            net.validate(run, epoch)
            ckpts.save(run.epoch)
    return run, True


class Checkpointer:
    """When a run writes its checkpoint, and its wall time over all its resumptions.

    The run saves whenever it is told (`save`: after each epoch, or when it stops) and at least
    every `minutes` in between (`save_if_due`, called after each step).

    Args:
        save: writes the checkpoint of ``(epoch, wall_s)``: whole epochs done and the run's wall
            time so far [s].
        minutes: longest time between two saves during an epoch.
        wall_s: wall time the run had taken before this process resumed it [s].
    """

    def __init__(self, save: Callable[[int, float], None], minutes: float, wall_s: float = 0.0):
        self._save = save
        self._seconds = 60 * minutes
        self._wall0 = wall_s
        self._started = self._last = time.monotonic()

    def wall_s(self) -> float:
        """The run's wall time so far, over all its resumptions [s]."""
        return self._wall0 + time.monotonic() - self._started

    def save(self, epoch: int) -> None:
        """Write the checkpoint now, `epoch` whole epochs done."""
        self._save(epoch, self.wall_s())
        self._last = time.monotonic()

    def save_if_due(self, epoch: int) -> None:
        """Write the checkpoint if the last one is older than the interval."""
        if time.monotonic() - self._last > self._seconds:
            self.save(epoch)
