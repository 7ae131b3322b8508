"""Training on several processes and on GPUs, shared by both trainers (docs/DESIGN.md §7).

A trainer run as ``torchrun --nproc-per-node N -m perception.training.train_posenet ...`` (torchrun
sets ``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK`` and the rendezvous address) joins a process group,
gloo on the CPU and nccl on GPUs, and wraps its model in DistributedDataParallel. Every rank
draws the same epoch order; rank r trains on the items ``r, r + N, r + 2N, ...`` of each global
batch (the shard `torch.utils.data.DistributedSampler` without shuffling gives of the epoch's
order), so the N shards of a step together are the single-process batch and the averaged
gradient is the single-process gradient. Batch norm normalises by the statistics of the whole
global batch (`nn.SyncBatchNorm` on GPUs, `GlobalBatchNorm2d` on the CPU), and on the CPU every
rank draws the dropout masks of the whole batch and keeps its rows (`GlobalDropout`), so a step
there is the single-process step up to the order of floating-point sums. Rank 0 alone
validates, logs and writes checkpoints, which hold the unwrapped model and resume with any
number of processes. Run without torchrun, a trainer is one process exactly as before.
"""

from __future__ import annotations

import contextlib
import copy
import json
import os
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import TypeVar

import torch
import torch.distributed as dist
from torch import nn

from posegrasp.core.errors import InvalidArgumentError

#: The values of ``--device``: ``auto`` is ``cuda`` when a GPU is present, else ``cpu``.
DEVICES = ("auto", "cpu", "cuda")
#: Most torch CPU threads a process may be told to use (``--threads``).
MAX_THREADS = 256
#: How long a rank waits for the others (rank 0 validating and saving) [min].
TIMEOUT_MIN = 60
CPU = torch.device("cpu")

_M = TypeVar("_M", bound=nn.Module)


@dataclass(frozen=True)
class Ranks:
    """This process's place in a run.

    Attributes:
        rank: its rank, 0..world-1.
        world: number of processes.
        local_world: processes on this machine.
        device: where its model and batches live.
    """

    rank: int = 0
    world: int = 1
    local_world: int = 1
    device: torch.device = CPU

    @property
    def main(self) -> bool:
        """Whether this process validates, logs and saves (rank 0)."""
        return self.rank == 0

    def shard(self, items):
        """This rank's part of a global batch (every `world`-th item from `rank`)."""
        return items[self.rank :: self.world]

    def threads(self, threads: int | None) -> int:
        """Torch CPU threads: `threads`, else this machine's cores shared by its processes."""
        return threads or max(1, (os.cpu_count() or 1) // self.local_world)

    def barrier(self) -> None:
        """Wait for every rank (nothing with one process)."""
        if self.world > 1:
            dist.barrier()

    def mean(self, value: torch.Tensor) -> float:
        """The mean of a scalar over the ranks (every rank must call it)."""
        value = value.detach().reshape(1).clone()
        if self.world > 1:
            dist.all_reduce(value)
            value /= self.world
        return float(value.item())

    def wrap(self, model: nn.Module) -> nn.Module:
        """The module to train with: DistributedDataParallel over `model` with several processes
        (its batch norms made global first), `model` itself with one. `model` is moved to the
        device; its parameters stay the same objects (an optimiser over them still holds)."""
        model.to(self.device)
        if self.world == 1:
            return model
        if self.device.type == "cuda":
            nn.SyncBatchNorm.convert_sync_batchnorm(model)
            return nn.parallel.DistributedDataParallel(model, device_ids=[self.device.index])
        _globalise(model, self)
        return nn.parallel.DistributedDataParallel(model)

    def on_cpu(self, model: _M) -> _M:
        """`model` if it is on the CPU, else a copy of it there."""
        return model if self.device.type == "cpu" else copy.deepcopy(model).cpu()

    def log(self, path: Path, **record) -> None:
        """Append `record` as one JSON line to `path` (rank 0; the others do nothing)."""
        if self.main:
            with Path(path).open("a") as f:
                f.write(json.dumps(record) + "\n")

    def close(self) -> None:
        """Leave the process group."""
        if self.world > 1 and dist.is_initialized():
            dist.destroy_process_group()


class _AllReduceSum(torch.autograd.Function):
    """The sum over the ranks, differentiable: the gradient of each rank's input is the sum of
    the gradients of every rank's output."""

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:
        x = x.clone()
        dist.all_reduce(x)
        return x

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        grad = grad.clone()
        dist.all_reduce(grad)
        return grad


class GlobalBatchNorm2d(nn.BatchNorm2d):
    """`nn.BatchNorm2d` over the global batch of all ranks, for gloo on the CPU (where
    `nn.SyncBatchNorm` does not run): the per-channel sums are all-reduced differentiably, so
    output, running statistics and gradient are those of one `nn.BatchNorm2d` over the whole
    batch. Same parameters, buffers and state-dict keys; in eval mode it is `nn.BatchNorm2d`."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(N, C, H, W) -> (N, C, H, W), normalised by the mean and variance over all ranks.

        The statistics are summed in float32 whatever the input's precision (bfloat16 under
        autocast); the output has the input's dtype."""
        if not self.training:
            return super().forward(x)
        all_reduce = _AllReduceSum.apply
        dtype, x = x.dtype, x.float()  # x itself when it is float32
        c, dims = x.shape[1], (0, 2, 3)
        count = torch.tensor([x.numel() / c], dtype=x.dtype, device=x.device)
        sums = all_reduce(torch.cat([x.sum(dims), count]))
        n = sums[-1]
        mean = sums[:c] / n
        centred = x - mean.view(1, c, 1, 1)
        var = all_reduce((centred * centred).sum(dims)) / n
        # _globalise swaps in only layers that track running statistics: they have these buffers.
        assert self.num_batches_tracked is not None
        assert self.running_mean is not None and self.running_var is not None
        with torch.no_grad():
            self.num_batches_tracked += 1
            m = self.momentum if self.momentum is not None else 1 / int(self.num_batches_tracked)
            self.running_mean.mul_(1 - m).add_(m * mean)
            self.running_var.mul_(1 - m).add_(m * var * n / (n - 1))
        scale = self.weight / torch.sqrt(var + self.eps)
        return (centred * scale.view(1, c, 1, 1) + self.bias.view(1, c, 1, 1)).to(dtype)


class GlobalDropout(nn.Dropout):
    """`nn.Dropout` whose mask is drawn for the global batch (from the global torch RNG, as
    `nn.Dropout` on the CPU draws it) and cut to this rank's rows: the mask one process would
    draw, and the RNG of every rank stays in step with it."""

    def __init__(self, p: float, ranks: Ranks) -> None:
        super().__init__(p)
        self.rank, self.world = ranks.rank, ranks.world

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """This rank's (B, ...) rows of the global batch, dropped out."""
        if not self.training or self.p == 0:
            return x
        shape = (x.shape[0] * self.world, *x.shape[1:])
        keep = torch.empty(shape, dtype=x.dtype, device=x.device).bernoulli_(1 - self.p)
        return x * keep.div_(1 - self.p)[self.rank :: self.world]


def _globalise(model: nn.Module, ranks: Ranks) -> None:
    """Replace the `nn.BatchNorm2d` and `nn.Dropout` modules inside `model` by their global
    versions, which share their parameters and buffers."""
    for name, child in model.named_children():
        if type(child) is nn.BatchNorm2d and child.affine and child.track_running_stats:
            new = GlobalBatchNorm2d(child.num_features, child.eps, child.momentum)
            new.weight, new.bias = child.weight, child.bias
            new.running_mean, new.running_var = child.running_mean, child.running_var
            new.num_batches_tracked = child.num_batches_tracked
            setattr(model, name, new)
        elif type(child) is nn.Dropout and not child.inplace:
            setattr(model, name, GlobalDropout(child.p, ranks))
        else:
            _globalise(child, ranks)


#: A run of one process on the CPU.
ONE_PROCESS = Ranks()


def resolve_device(name: str) -> torch.device:
    """``auto``, ``cpu`` or ``cuda`` as a device.

    Raises:
        InvalidArgumentError: an unknown name, or ``cuda`` without a GPU.
    """
    if name not in DEVICES:
        raise InvalidArgumentError(f"unknown device {name!r}; valid devices: {', '.join(DEVICES)}")
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda" and not torch.cuda.is_available():
        raise InvalidArgumentError("--device cuda, but torch sees no CUDA device; use cpu or auto")
    return torch.device(name)


def start(device: str = "auto", batch: int = 1) -> Ranks:
    """This process's `Ranks`: joins torchrun's process group when there is one.

    Args:
        device: one of `DEVICES`.
        batch: the global batch, which the processes must divide evenly.

    Raises:
        InvalidArgumentError: a bad device, or a batch the processes cannot share evenly.
    """
    dev = resolve_device(device)
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world == 1:
        return Ranks(device=dev)
    if batch % world:
        raise InvalidArgumentError(
            f"--batch {batch} does not split evenly over {world} processes; use a multiple of "
            f"{world}"
        )
    rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    if dev.type == "cuda":
        torch.cuda.set_device(local)
        dev = torch.device("cuda", local)
    backend = "nccl" if dev.type == "cuda" else "gloo"
    dist.init_process_group(backend, timeout=timedelta(minutes=TIMEOUT_MIN))
    local_world = int(os.environ.get("LOCAL_WORLD_SIZE", str(world)))
    return Ranks(rank=rank, world=world, local_world=local_world, device=dev)


@contextlib.contextmanager
def joined(device: str = "auto", batch: int = 1) -> Iterator[Ranks]:
    """This process's `Ranks` for the length of a run (`start`), leaving the process group at the
    end, however the run ends.

    Args:
        device: one of `DEVICES`.
        batch: the global batch, which the processes must divide evenly.

    Yields:
        This process's place in the run.

    Raises:
        InvalidArgumentError: a bad device, or a batch the processes cannot share evenly.
    """
    ranks = start(device, batch)
    try:
        yield ranks
    finally:
        ranks.close()
