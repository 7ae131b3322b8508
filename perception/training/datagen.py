"""Build the pose datasets with MuJoCo: ``python -m perception.training.datagen``.

    python -m perception.training.datagen --dist {paper,headcam} --split {train,val,test} --count N
        [--out DIR] [--objects all|phone,car] [--width W --height H] [--preview sheet.png]
        [--workers N] [--backend {local,ray} [--address ADDR]] [--tier T] [--views V]

Two distributions (docs/DESIGN.md §8; the generators are in
`perception.training.data.distributions`):

- ``paper``: the paper's protocol (section 2.8), one object alone in a randomised studio
  (`perception.training.data.studio`): camera uniform on the sphere at a random distance, random
  roll, procedural backgrounds, clutter, lights and colours; 256x256 by default.
- ``headcam``: the deployment distribution: the Fetch head camera's view of a seeded
  `posegrasp.world.scene.build_scene` (target + 0-3 distractors on the table, randomised
  appearance), 640x480 by default; every object with visible pixels is annotated.

Layout and units: see `perception.training.data.bop` (BOP layout, BOP files in millimetres,
everything else in metres). Default ``--out``: ``$POSEGRASP_DATA/<dist>`` if the variable is
set, else ``data/<dist>`` in the repository (git-ignored).

Seeds, views per scene and resuming: see `perception.training.data.render_split`.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from perception.training.data.dataset import DISTS, SPLITS
from perception.training.data.render_split import (
    DEFAULT_SIZE,
    MAX_COUNT,
    MAX_VIEWS,
    GenConfig,
    generate,
)
from perception.training.data.rooms import FAMILIES, folder_suffix
from perception.training.data.sheets import write_preview
from posegrasp.core.backends import add_backend_arguments, check_backend
from posegrasp.core.cli import ArgumentParser, add_out_argument, add_workers_argument, command, fail
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.paths import data_root
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import (
    arg,
    check_choice,
    check_int,
    check_output_dir,
    check_output_file,
)
from posegrasp.world.camera import check_resolution
from posegrasp.world.distractor_bank import BANKS
from posegrasp.world.objects import check_objects
from posegrasp.world.tiers import TIERS, check_tier

#: Exit status of a generation that failed on the way (a full disk ...).
EXIT_FAILURE = 1

# --- command line ----------------------------------------------------------------------------


def _parser() -> argparse.ArgumentParser:
    p = ArgumentParser(
        prog="python -m perception.training.datagen",
        description="Render a seeded, resumable pose dataset in the BOP layout.",
    )
    p.add_argument(
        "--dist",
        required=True,
        type=arg(check_choice, DISTS, "distribution"),
        help="paper (studio views) or headcam (table scenes)",
    )
    p.add_argument(
        "--split",
        required=True,
        type=arg(check_choice, SPLITS, "split"),
        help=", ".join(SPLITS),
    )
    p.add_argument(
        "--count",
        required=True,
        type=arg(check_int, 1, MAX_COUNT, "--count", base=int),
        metavar="N",
        help=f"number of images in the split, 1..{MAX_COUNT}",
    )
    add_out_argument(
        p, "the dataset (default: $POSEGRASP_DATA/<dist>, else data/<dist> in the repo)"
    )
    p.add_argument(
        "--objects",
        default="all",
        type=arg(check_objects, "--objects"),
        help="'all' (the six built-in objects) or a comma list of targets, e.g. phone,car; "
        "--dist headcam takes user objects too (python -m sim.add_object)",
    )
    p.add_argument("--width", type=int, default=None, help="image width (256 paper, 640 headcam)")
    p.add_argument("--height", type=int, default=None, help="image height (256 / 480)")
    p.add_argument(
        "--preview",
        type=arg(check_output_file, "--preview", (".png",)),
        default=None,
        metavar="PATH",
        help="write a contact sheet PNG here",
    )
    add_workers_argument(p, what="they render")
    p.add_argument(
        "--tier",
        default=None,
        type=arg(check_tier),
        help=f"headcam only: scene tier, one of: {', '.join(TIERS)} (default: the mixed table "
        "scenes; the default folder is then <dist>_<tier>)",
    )
    p.add_argument(
        "--views",
        type=arg(check_int, 1, MAX_VIEWS, "--views", base=int),
        default=1,
        help=f"headcam only: images per scene, 1..{MAX_VIEWS}, the head aimed at each object in "
        "turn (default 1: one image per scene, as an episode sees it)",
    )
    p.add_argument(
        "--rooms",
        nargs="?",
        const="wide",
        default=None,
        metavar="FAMILY",
        type=arg(check_choice, list(FAMILIES), "room family"),
        help="headcam only: each scene in a room drawn for training (lights, surfaces, object "
        "colours, camera, unseen distractors; perception.training.data.rooms), of the family "
        f"{' or '.join(FAMILIES)} (default wide: each factor in about half the images; joint: "
        "most factors at once); the default folder then ends in _rooms, or _rooms_<family>",
    )
    p.add_argument(
        "--bank",
        nargs="?",
        const="training",
        default=None,
        metavar="BANK",
        type=arg(check_choice, list(BANKS), "bank"),
        help="headcam only, without --tier: scenes whose only objects in sight are meshes of the "
        "bank BANK (training: pybullet's random meshes 0-899, the default; shapes: generated "
        "boxes, cylinders, capsules, ellipsoids, cones and bottles 1000-1999, for training too; "
        "held-out: 900-999, for scoring), each annotated as an object of its own (bank-NNN), for "
        "a detector of objects it has never seen; the default folder is then "
        "headcam_bank[_held-out|_shapes][_rooms...]",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_backend_arguments(p)
    return p


def parse_args(argv: Sequence[str] | None) -> GenConfig:
    """Parse and check a command line (a bad value exits with status 2, in one line).

    Raises:
        InvalidArgumentError: an option that does not apply to the distribution, or a bad
            resolution or output folder.
        UnknownNameError: an unknown backend.
    """
    a = _parser().parse_args(argv)
    check_backend(a.backend, a.address)
    if a.tier is not None and a.dist != "headcam":
        raise InvalidArgumentError(f"--tier applies to --dist headcam, not {a.dist}")
    if a.rooms is not None and a.dist != "headcam":
        raise InvalidArgumentError(f"--rooms applies to --dist headcam, not {a.dist}")
    if a.bank is not None and (a.dist != "headcam" or a.tier is not None or a.views > 1):
        raise InvalidArgumentError("--bank applies to --dist headcam, without --tier or --views")
    if a.views > 1 and a.dist != "headcam":
        raise InvalidArgumentError(f"--views applies to --dist headcam, not {a.dist}")
    width = a.width if a.width is not None else DEFAULT_SIZE[a.dist][0]
    height = a.height if a.height is not None else DEFAULT_SIZE[a.dist][1]
    check_resolution(width, height)
    out = a.out
    if out is None:
        name = a.dist if a.tier is None else f"{a.dist}_{a.tier}"
        if a.bank is not None:
            name += "_bank" if a.bank == "training" else f"_bank_{a.bank}"
        out = data_root() / (name if a.rooms is None else name + folder_suffix(a.rooms))
        check_output_dir(out, "--out")
    return GenConfig(
        dist=a.dist,
        split=a.split,
        count=a.count,
        out=Path(out),
        objects=tuple(a.objects),
        width=width,
        height=height,
        workers=a.workers,
        preview=a.preview,
        progress=not a.quiet,
        tier=a.tier,
        backend=a.backend,
        address=a.address,
        views=a.views,
        rooms=a.rooms,
        bank=a.bank,
    )


@command
def main(argv: list[str] | None = None) -> int:
    """Command-line entry point; returns the exit status."""
    cfg = parse_args(argv)
    setup_rendering()
    # One software-rendering thread per process is faster than llvmpipe's default on 2 cores.
    os.environ.setdefault("LP_NUM_THREADS", "1")
    try:
        n = generate(cfg)
        if cfg.preview is not None:
            cfg.preview.parent.mkdir(parents=True, exist_ok=True)
            write_preview(cfg.out, cfg.split, cfg.dist, cfg.preview)
    except KeyboardInterrupt:
        return fail("interrupted; run the same command again to resume", 130)
    except OSError as exc:
        return fail(str(exc), EXIT_FAILURE)
    done = f"{cfg.dist}/{cfg.split}: rendered {n}, {cfg.count - n} already done, in {cfg.out}"
    if cfg.preview is not None:
        done += f"; preview {cfg.preview}"
    print(done)
    return 0


if __name__ == "__main__":
    sys.exit(main())
