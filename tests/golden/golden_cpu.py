"""The CPU kind golden files are recorded on, and the sets of them recorded so far.

torch's CPU kernels choose their blocking and vector paths by the processor, so the same
estimator on the same image can differ in the last bits (and, through a close decision, more)
from one processor to another. Golden files are therefore kept per CPU kind: each folder of
golden files (``poses/``, ``reports/``) holds the set first recorded at its top and one set per
further kind under ``cpu/<kind>/``. A result equal to the bit to any set is golden; on a kind
with a set of its own, nothing else is; on a kind with none, the tests fall back to a stated
tolerance and say so.
"""

from __future__ import annotations

import functools
import hashlib
import platform
from pathlib import Path

#: The instruction-set flags of /proc/cpuinfo that decide which kernels run.
ISA_PREFIXES = ("avx", "amx", "fma", "f16c", "sse4", "ssse3")


@functools.cache
def cpu_kind() -> str:
    """This processor's kind: the machine, then a short hash of its model name and its
    instruction-set flags (``x86_64-1a2b3c4d``)."""
    model, flags = "", set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and not model:
                model = value.strip()
            elif key.strip() == "flags" and not flags:
                flags = {f for f in value.split() if f.startswith(ISA_PREFIXES)}
    except OSError:
        model = platform.processor()
    digest = hashlib.sha256(f"{model}|{' '.join(sorted(flags))}".encode()).hexdigest()[:8]
    return f"{platform.machine()}-{digest}"


#: The file in a set's folder that names the CPU kind it was recorded on (none: not noted).
KIND_FILE = "cpu.txt"


def golden_sets(folder: Path) -> list[Path]:
    """The recorded sets in `folder`: the folder itself, then ``cpu/<kind>/`` by name."""
    kinds = sorted(p for p in (folder / "cpu").glob("*") if p.is_dir())
    return [folder, *kinds]


def set_kind(folder: Path) -> str | None:
    """The CPU kind the set in `folder` was recorded on, or None where it was not noted."""
    path = folder / KIND_FILE
    return path.read_text().strip() if path.exists() else None


def own_set(folder: Path) -> Path | None:
    """This CPU kind's set in `folder`, or None where it has none."""
    kind = cpu_kind()
    return next((s for s in golden_sets(folder) if set_kind(s) == kind), None)


def default_out(folder: Path) -> Path:
    """Where a recording on this CPU goes: its own set, else the top of `folder` while that
    holds none, else ``cpu/<kind>/``."""
    own = own_set(folder)
    if own is not None:
        return own
    if not any(folder.glob("*.json")):
        return folder
    return folder / "cpu" / cpu_kind()


def note_kind(out: Path) -> None:
    """Write this CPU's kind into the set in `out`."""
    (out / KIND_FILE).write_text(cpu_kind() + "\n")
