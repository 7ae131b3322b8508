"""Dataset generation speed: images per second, end to end (render + PNG/JSON writes).

    python bench/datagen_speed.py [--paper N] [--headcam N] [--workers K]

Prints, for the paper protocol at 256x256 in one process and with K worker processes (default 2;
the target is >= 50 images/s on 2 cores), and for the head-camera distribution at 640x480 in one
process:

- the end-to-end rate (including the workers' start-up: spawn, imports, GL contexts);
- the steady rate, timed from the first finished image to the last;
- the CPU time per image (this process and its workers), which does not depend on how busy the
  machine is; cores / CPU time is the rate an otherwise idle machine would reach.

Output goes to a temporary folder that is deleted afterwards.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

from perception.training.datagen import GenConfig, generate


def _cpu_seconds() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def measure(cfg: GenConfig) -> dict[str, float]:
    """Generate cfg.count images; returns end-to-end and steady rates [1/s], CPU per image [s]."""
    stamps: list[float] = []
    cpu0, t0 = _cpu_seconds(), time.perf_counter()
    generate(cfg, on_image=lambda _: stamps.append(time.perf_counter()))
    t1, cpu1 = time.perf_counter(), _cpu_seconds()
    steady = (len(stamps) - 1) / (stamps[-1] - stamps[0]) if len(stamps) > 1 else float("nan")
    return {
        "rate": cfg.count / (t1 - t0),
        "steady": steady,
        "seconds": t1 - t0,
        "cpu": (cpu1 - cpu0) / cfg.count,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--paper", type=int, default=400, help="paper images per run")
    p.add_argument("--headcam", type=int, default=12, help="headcam images")
    p.add_argument("--workers", type=int, default=2, help="worker processes of the pool run")
    a = p.parse_args(argv)
    os.environ.setdefault("LP_NUM_THREADS", "1")
    cores = os.cpu_count() or 1
    print(f"cores: {cores}, load average: {os.getloadavg()[0]:.2f}")
    runs = [
        ("paper 256x256, 1 process", "paper", a.paper, 256, 256, 1),
        (f"paper 256x256, {a.workers} workers", "paper", a.paper, 256, 256, a.workers),
        ("headcam 640x480, 1 process", "headcam", a.headcam, 640, 480, 1),
    ]
    with tempfile.TemporaryDirectory() as tmp:
        for k, (label, dist, n, w, h, workers) in enumerate(runs):
            if n <= 0:
                continue
            cfg = GenConfig(
                dist=dist,
                split="train",
                count=n,
                out=Path(tmp) / f"run{k}",
                width=w,
                height=h,
                workers=workers,
                progress=False,
            )
            r = measure(cfg)
            print(
                f"{label}: {r['rate']:6.1f} images/s end to end ({n} in {r['seconds']:.1f} s), "
                f"{r['steady']:6.1f} images/s steady, {1000 * r['cpu']:.1f} ms CPU per image "
                f"(idle-machine estimate {min(workers, cores) / r['cpu']:.0f} images/s)",
                flush=True,
            )
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
