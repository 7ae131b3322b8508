"""Dataset generation speed: images per second, end to end (render + PNG/JSON writes).

    python bench/datagen_speed.py [--paper N] [--headcam N] [--workers K] [--views V]
        [--json PATH]

Prints, for the paper protocol at 256x256 in one process and with K worker processes (default 2,
the count the targets are for: >= 50 images/s on 2 cores), and for the head-camera distribution
at 640x480 in one process, with K workers, and with K workers rendering V views per scene
(`--views`, default 4; the target is >= 30 images/s on 2 cores):

- the end-to-end rate of a run of 2N images (including the workers' start-up: spawn, imports,
  GL contexts);
- the rate of a long run, start-up cancelled: N more images (a fresh run of 2N against one of
  N) take the difference of the two wall times; this is the rate of a split of thousands;
- the CPU time per image of a long run, the same difference in CPU time (this process and its
  workers); it does not depend on how busy the machine is, and cores / CPU time is the rate an
  otherwise idle machine would reach.

Each target is judged on the long-run rate (a split of thousands runs at it): the paper protocol
with K workers, and the head camera with K workers and V views per scene (with ``--views 1``
that run, and its target, is left out). `--json PATH` writes these figures per run and
``targets_met`` (``-``: to standard output). Exit status 0 when every target is met, 1 when one
is missed.

Output goes to a temporary folder in the data root (`$POSEGRASP_DATA`, else data/), where
generated data normally goes (file creation costs differ between file systems), and is deleted
afterwards.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import TextIO

from perception.training.data.render_split import MAX_VIEWS, GenConfig, generate
from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    add_workers_argument,
    command,
    summary_stream,
    target,
    write_json,
)
from posegrasp.core.paths import data_root
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_int

#: Worker processes of the pool runs unless told otherwise: the targets are for 2 cores.
TARGET_WORKERS = 2
#: Long-run rates [images/s] with the pool: the paper protocol, and the head camera with
#: several views per scene.
TARGET_PAPER = 50.0
TARGET_HEADCAM_VIEWS = 30.0


def _cpu_seconds() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _run(cfg: GenConfig) -> tuple[float, float]:
    """Generate cfg; returns its wall and CPU time [s]."""
    cpu0, t0 = _cpu_seconds(), time.perf_counter()
    generate(cfg)
    return time.perf_counter() - t0, _cpu_seconds() - cpu0


def measure(cfg: GenConfig) -> dict[str, float]:
    """Runs of cfg.count and 2 * cfg.count images (fresh folders); returns the end-to-end rate
    of the longer [1/s], and the rate and CPU time per image [s] of the images it adds."""
    n = cfg.count
    wall1, cpu1 = _run(replace(cfg, out=cfg.out / "n"))
    wall2, cpu2 = _run(replace(cfg, count=2 * n, out=cfg.out / "2n"))
    return {
        "rate": 2 * n / wall2,
        "seconds": wall2,
        "long_rate": n / (wall2 - wall1),
        "cpu": (cpu2 - cpu1) / n,
    }


def _parser() -> ArgumentParser:
    p = ArgumentParser(prog="python bench/datagen_speed.py", description=__doc__.splitlines()[0])
    images = arg(check_int, 0, 100_000, "--paper", base=int)
    p.add_argument(
        "--paper",
        type=images,
        default=400,
        help="paper images N (runs of N and 2N), 0..100000 (0: none)",
    )
    images = arg(check_int, 0, 100_000, "--headcam", base=int)
    p.add_argument(
        "--headcam",
        type=images,
        default=120,
        help="headcam images N (runs of N and 2N), 0..100000 (0: none)",
    )
    add_workers_argument(p, TARGET_WORKERS, "of the pool runs, the targets' count")
    p.add_argument(
        "--views",
        type=arg(check_int, 1, MAX_VIEWS, "--views", base=int),
        default=4,
        help=f"headcam views per scene of the last run, 1..{MAX_VIEWS}",
    )
    add_json_argument(p, "every run's rates")
    return p


#: A run: label, distribution, images, width, height, workers, views, long-run target or None.
Run = tuple[str, str, int, int, int, int, int, float | None]


def _runs(a: argparse.Namespace) -> list[Run]:
    """The runs the arguments ask for, in order (those of no images or views skipped later)."""
    w = a.workers
    return [
        ("paper 256x256, 1 process", "paper", a.paper, 256, 256, 1, 1, None),
        (f"paper 256x256, {w} workers", "paper", a.paper, 256, 256, w, 1, TARGET_PAPER),
        ("headcam 640x480, 1 process", "headcam", a.headcam, 640, 480, 1, 1, None),
        (f"headcam 640x480, {w} workers", "headcam", a.headcam, 640, 480, w, 1, None),
        (
            f"headcam 640x480, {w} workers, {a.views} views per scene",
            "headcam",
            a.headcam,
            640,
            480,
            w,
            a.views,
            TARGET_HEADCAM_VIEWS,
        ),
    ]


def _measure_runs(
    runs: list[Run], max_views: int, cores: int, log: TextIO
) -> tuple[dict[str, dict], dict[str, bool]]:
    """Each run with images (and, for several views, `max_views` > 1) measured in a temporary
    folder of the data root and printed to `log`; returns the figures and the targets met."""
    root = data_root()
    root.mkdir(parents=True, exist_ok=True)
    rows, met = {}, {}
    with tempfile.TemporaryDirectory(dir=root, prefix=".datagen_speed_") as tmp:
        for k, (label, dist, n, w, h, workers, views, goal) in enumerate(runs):
            if n <= 0 or (views > 1 and max_views <= 1):
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
                views=views,
            )
            r = measure(cfg)
            rows[label] = r | {"images": 2 * n, "workers": workers, "views": views}
            print(
                f"{label}: {r['rate']:5.1f} images/s end to end ({2 * n} in "
                f"{r['seconds']:.1f} s); long run {r['long_rate']:5.1f} images/s, "
                f"{1000 * r['cpu']:.1f} ms CPU per image (idle-machine estimate "
                f"{min(workers, cores) / r['cpu']:.0f} images/s)",
                file=log,
                flush=True,
            )
            if goal is not None:
                met[label] = r["long_rate"] >= goal
                print(
                    f"  long run {r['long_rate']:.1f} images/s "
                    + target(f">= {goal:.0f} images/s", met[label]),
                    file=log,
                    flush=True,
                )
    return rows, met


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns 0 when every target is met, 1 when one is missed."""
    a = _parser().parse_args(argv)
    setup_rendering()
    log = summary_stream(a.json)
    os.environ.setdefault("LP_NUM_THREADS", "1")
    cores = os.cpu_count() or 1
    print(f"cores: {cores}, load average: {os.getloadavg()[0]:.2f}", file=log)
    rows, met = _measure_runs(_runs(a), a.views, cores, log)
    print(f"load average after: {os.getloadavg()[0]:.2f}", file=log)
    if a.json is not None:
        write_json(a.json, {"cores": cores, "runs": rows, "targets_met": met})
    return 0 if all(met.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
