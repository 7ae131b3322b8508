"""Build the pose datasets with MuJoCo: ``python -m perception.training.datagen``.

    python -m perception.training.datagen --dist {paper,headcam} --split {train,val,test} --count N
        [--out DIR] [--objects all|phone,car] [--width W --height H] [--preview sheet.png]
        [--workers K] [--backend {local,ray} [--address ADDR]] [--tier T] [--views V]

Two distributions (docs/DESIGN.md §8; the generators are in
`perception.training.generators`):

- ``paper``: the paper's protocol (section 2.8), one object alone in a randomised studio
  (`perception.training.studio`): camera uniform on the sphere at a random distance, random roll,
  procedural backgrounds, clutter, lights and colours; 256x256 by default.
- ``headcam``: the deployment distribution: the Fetch head camera's view of a seeded
  `posegrasp.world.scene.build_scene` (target + 0-3 distractors on the table, randomised
  appearance), 640x480 by default; every object with visible pixels is annotated.

Layout and units: see `perception.training.bop` (BOP layout, BOP files in millimetres,
everything else in metres). Default ``--out``: ``$POSEGRASP_DATA/<dist>`` if the variable is
set, else ``data/<dist>`` in the repository (git-ignored).

Seeds, views per scene and resuming: see `perception.training.generation`.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import NoReturn

from perception.training.dataset import DISTS, SPLITS
from perception.training.generation import (
    DEFAULT_SIZE,
    MAX_COUNT,
    MAX_VIEWS,
    GenConfig,
    generate,
)
from perception.training.sheets import write_preview
from posegrasp.core.backends import add_backend_arguments, check_backend
from posegrasp.core.cli import fail
from posegrasp.core.errors import InvalidArgumentError, PosegraspError, UnknownNameError
from posegrasp.core.paths import data_root
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import check_names, check_output_file, check_workers
from posegrasp.world.camera import check_resolution
from posegrasp.world.objects import OBJECT_NAMES
from posegrasp.world.tiers import TIERS, check_tier

EXIT_FAILURE = 1
EXIT_USAGE = 2

# --- command line ----------------------------------------------------------------------------


class _Parser(argparse.ArgumentParser):
    """argparse that raises a rejected argument as InvalidArgumentError, with the usage line."""

    def error(self, message: str) -> NoReturn:
        raise InvalidArgumentError(f"{message}; {' '.join(self.format_usage().split())}")


def _parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="python -m perception.training.datagen",
        description="Render a seeded, resumable pose dataset in the BOP layout.",
    )
    p.add_argument("--dist", required=True, help="paper (studio views) or headcam (table scenes)")
    p.add_argument("--split", required=True, help="train, val or test")
    p.add_argument("--count", required=True, type=int, help="number of images in the split")
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="dataset folder (default: $POSEGRASP_DATA/<dist>, else data/<dist> in the repo)",
    )
    p.add_argument("--objects", default="all", help="'all' or a comma list, e.g. phone,car")
    p.add_argument("--width", type=int, default=None, help="image width (256 paper, 640 headcam)")
    p.add_argument("--height", type=int, default=None, help="image height (256 / 480)")
    p.add_argument("--preview", default=None, help="write a contact sheet PNG here")
    p.add_argument("--workers", type=int, default=1, help="rendering processes, 1..64 (default 1)")
    p.add_argument(
        "--tier",
        default=None,
        help=f"headcam only: scene tier, one of: {', '.join(TIERS)} (default: the mixed table "
        "scenes; the default folder is then <dist>_<tier>)",
    )
    p.add_argument(
        "--views",
        type=int,
        default=1,
        help=f"headcam only: images per scene, 1..{MAX_VIEWS}, the head aimed at each object in "
        "turn (default 1: one image per scene, as an episode sees it)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_backend_arguments(p)
    return p


def parse_args(argv: Sequence[str] | None) -> GenConfig:
    """Parse and check a command line.

    Raises:
        InvalidArgumentError: an argument argparse rejects, or one out of range.
        UnknownNameError: an unknown distribution, split or object.
    """
    a = _parser().parse_args(argv)
    if a.dist not in DISTS:
        raise UnknownNameError("distribution", a.dist, DISTS)
    if a.split not in SPLITS:
        raise UnknownNameError("split", a.split, SPLITS)
    if not 1 <= a.count <= MAX_COUNT:
        raise InvalidArgumentError(f"invalid --count {a.count}; valid: 1..{MAX_COUNT}")
    check_workers(a.workers)
    check_backend(a.backend, a.address)
    objects = tuple(check_names(a.objects, OBJECT_NAMES, "object", "--objects"))
    if a.tier is not None:
        check_tier(a.tier)
        if a.dist != "headcam":
            raise InvalidArgumentError(f"--tier applies to --dist headcam, not {a.dist}")
    if not 1 <= a.views <= MAX_VIEWS:
        raise InvalidArgumentError(f"invalid --views {a.views}; valid: 1..{MAX_VIEWS}")
    if a.views > 1 and a.dist != "headcam":
        raise InvalidArgumentError(f"--views applies to --dist headcam, not {a.dist}")
    width = a.width if a.width is not None else DEFAULT_SIZE[a.dist][0]
    height = a.height if a.height is not None else DEFAULT_SIZE[a.dist][1]
    check_resolution(width, height)
    out = a.out
    if out is None:
        out = data_root() / (a.dist if a.tier is None else f"{a.dist}_{a.tier}")
    return GenConfig(
        dist=a.dist,
        split=a.split,
        count=a.count,
        out=Path(out),
        objects=objects,
        width=width,
        height=height,
        workers=a.workers,
        preview=None if a.preview is None else check_output_file(a.preview, "--preview", (".png",)),
        progress=not a.quiet,
        tier=a.tier,
        backend=a.backend,
        address=a.address,
        views=a.views,
    )


def _check_writable(out: Path) -> None:
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write_test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise InvalidArgumentError(
            f"cannot write to output folder {out}: {exc.strerror or exc}"
        ) from None


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point; returns the exit status."""
    try:
        cfg = parse_args(argv)
        setup_rendering()
        _check_writable(cfg.out)
    except SystemExit as exc:  # --help
        return int(exc.code or 0)
    except PosegraspError as exc:
        return fail(str(exc), EXIT_USAGE)
    # One software-rendering thread per process is faster than llvmpipe's default on 2 cores.
    os.environ.setdefault("LP_NUM_THREADS", "1")
    try:
        n = generate(cfg)
        if cfg.preview is not None:
            cfg.preview.parent.mkdir(parents=True, exist_ok=True)
            write_preview(cfg.out, cfg.split, cfg.dist, cfg.preview)
    except KeyboardInterrupt:
        return fail("interrupted; run the same command again to resume", 130)
    except (PosegraspError, OSError) as exc:
        return fail(str(exc), EXIT_FAILURE)
    done = f"{cfg.dist}/{cfg.split}: rendered {n}, {cfg.count - n} already done, in {cfg.out}"
    if cfg.preview is not None:
        done += f"; preview {cfg.preview}"
    print(done)
    return 0


if __name__ == "__main__":
    sys.exit(main())
