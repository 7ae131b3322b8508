"""The trainers' one command-line vocabulary (``--data NAME=COUNT,...``, ``--init``, ``--epochs``,
``--batch``, ``--lr``, ``--seed``, ``--precision``, ``--channels-last``, ``--out``), checked while
parsing, and the bounds it checks against."""

from __future__ import annotations

import math
from typing import Any

from perception.training.data.dataset import DATASETS, parse_data
from perception.training.trainers.loop import PRECISIONS
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.validate import arg, check_choice, check_int, check_seed

#: Most epochs and largest global batch a command line accepts.
MAX_EPOCHS = 10_000
MAX_BATCH = 65_536
#: Most images a run may be limited to (``--limit``).
MAX_LIMIT = 100_000_000
#: Largest peak learning rate a command line accepts.
MAX_LR = 1.0


def check_learning_rate(value: Any, name: str = "--lr") -> float:
    """`value` as a peak learning rate: a finite number in (0, `MAX_LR`].

    Raises:
        InvalidArgumentError: anything else, in one line naming the option and the range.
    """
    ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not ok or not math.isfinite(value) or not 0 < value <= MAX_LR:
        raise InvalidArgumentError(f"invalid {name} {value!r}; valid: numbers in (0, {MAX_LR:g}]")
    return float(value)


def add_schedule_arguments(
    parser, epochs: int, batch: int, lr: float, epoch_of: str, batch_of: str
) -> None:
    """Add ``--epochs``, ``--batch`` and ``--lr``, checked while parsing, with their defaults;
    `epoch_of` and `batch_of` say what an epoch passes over and what a batch holds."""
    parser.add_argument(
        "--epochs",
        type=arg(check_int, 1, MAX_EPOCHS, "--epochs", base=int),
        default=epochs,
        help=f"passes over {epoch_of}, 1..{MAX_EPOCHS} (default {epochs})",
    )
    parser.add_argument(
        "--batch",
        type=arg(check_int, 1, MAX_BATCH, "--batch", base=int),
        default=batch,
        help=f"global batch{batch_of}, 1..{MAX_BATCH} (default {batch})",
    )
    parser.add_argument(
        "--lr",
        type=arg(check_learning_rate, "--lr", base=float),
        default=lr,
        help=f"peak learning rate, in (0, {MAX_LR:g}] (default {lr:g})",
    )


def add_data_argument(parser, what: str, default: str, folder_first: bool = False) -> None:
    """Add ``--data NAME[=COUNT],...``: the dataset folders under the data root a run trains on
    and how many training images of each (all when no COUNT), checked while parsing
    (`perception.training.data.dataset.parse_data`; None when not given).

    Args:
        parser: the command line.
        what: what the names are, for the help.
        default: what the run trains on without the option, for the help.
        folder_first: the first NAME may also be a folder path.
    """
    first = " (the first may be a folder path)" if folder_first else ""
    parser.add_argument(
        "--data",
        type=arg(parse_data, folder_first),
        default=None,
        metavar="NAME[=N],...",
        help=f"{what}{first} and the training images of each, of: {', '.join(DATASETS)} "
        f"(default {default})",
    )


def add_seed_argument(parser, default: int, what: str) -> None:
    """Add ``--seed``, checked while parsing; `what` says what it seeds."""
    parser.add_argument(
        "--seed",
        type=arg(check_seed, "--seed", base=int),
        default=default,
        help=f"seed of {what} (default {default})",
    )


def add_compute_arguments(parser, devices: tuple[str, ...], max_threads: int, what: str) -> None:
    """Add ``--threads`` (`what` threads per process) and ``--device``, checked while parsing."""
    parser.add_argument(
        "--threads",
        type=arg(check_int, 1, max_threads, "--threads", base=int),
        default=None,
        help=f"{what} threads per process, 1..{max_threads} (default: the cores shared by the "
        "processes)",
    )
    parser.add_argument(
        "--device",
        type=arg(check_choice, devices, "device"),
        default="auto",
        help=f"one of: {', '.join(devices)}",
    )


def add_arithmetic_arguments(parser, precision: str, laid_out: str) -> None:
    """Add ``--precision`` (default `precision`) and ``--channels-last`` (`laid_out` in
    channels-last memory layout), checked while parsing."""
    parser.add_argument(
        "--precision",
        type=arg(check_choice, PRECISIONS, "precision"),
        default=precision,
        help=f"arithmetic of the forward passes, one of: {', '.join(PRECISIONS)} (bf16: "
        f"bfloat16 autocast, the loss in fp32; default {precision})",
    )
    parser.add_argument(
        "--channels-last",
        action="store_true",
        help=f"{laid_out} in channels-last memory layout",
    )
