"""Build the pose datasets with MuJoCo: ``python -m perception.training.datagen``.

    python -m perception.training.datagen --dist {paper,headcam} --split {train,val,test} --count N
        [--out DIR] [--objects all|phone,car] [--width W --height H] [--preview sheet.png]
        [--workers K] [--backend {local,ray} [--address ADDR]]

Two distributions (docs/DESIGN.md §8; the generators are in
`perception.training.generators`):

- ``paper``: the paper's protocol (section 2.8), one object alone in a randomised studio
  (`perception.training.studio`): camera uniform on the sphere at a random distance, random roll,
  procedural backgrounds, clutter, lights and colours; 256x256 by default.
- ``headcam``: the deployment distribution: the Fetch head camera's view of a seeded
  `sim.world.scene.build_scene` (target + 0-3 distractors on the table, randomised
  appearance), 640x480 by default; every object with visible pixels is annotated.

Layout and units: see `perception.training.bop` (BOP layout, BOP files in millimetres,
everything else in metres). Default ``--out``: ``$POSEGRASP_DATA/<dist>`` if the variable is
set, else ``data/<dist>`` in the repository (git-ignored).

Seeds: sample ``index`` of a split has seed ``SEED_BASES[split] + index``; the bases are 10^8
apart, so splits never share a seed (``--count`` is at most 10^8). ``paper`` draws everything from
``numpy.random.default_rng(seed)``; ``headcam`` builds ``build_scene(target, seed, ...)`` with the
number of distractors drawn from ``default_rng([seed, 1])``. The class of sample index is
``objects[index % len(objects)]``. Same arguments, same bytes: PNGs are encoded with fixed
parameters, JSON with sorted keys, and nothing depends on the number of workers or on timing.

Resuming: every file is written to a temporary name and renamed; an image is done once its record
(``records/<im_id>.json``) exists, and a re-run skips done images. The BOP scene files are merged
from the records whenever a scene's images are complete and at the end of a run.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import sim  # noqa: F401  # isort: skip  (defaults MUJOCO_GL before mujoco is imported)
from tqdm import tqdm

from perception.training import bop
from perception.training.dataset import DISTS, SPLITS, load_info
from perception.training.generators import HeadcamGenerator, PaperGenerator, make_generator
from perception.training.sheets import write_preview
from perception.training.writer import (
    add_wall_time,
    merge_scene,
    write_camera,
    write_models,
    write_sample,
)
from sim.core.backends import add_backend_arguments, check_backend, default_chunk, run_map
from sim.core.cli import fail
from sim.core.errors import InvalidArgumentError, PosegraspError, UnknownNameError
from sim.core.paths import data_root
from sim.core.validate import check_names, check_output_file, check_workers
from sim.world.camera import check_resolution
from sim.world.objects import OBJECT_NAMES
from sim.world.tiers import TIERS, check_tier

GENERATOR_VERSION = "2"
SEED_BASES: dict[str, int] = {"train": 0, "val": 100_000_000, "test": 200_000_000}
MAX_COUNT = 100_000_000
DEFAULT_SIZE: dict[str, tuple[int, int]] = {"paper": (256, 256), "headcam": (640, 480)}
EXIT_FAILURE = 1
EXIT_USAGE = 2


@dataclass(frozen=True)
class GenConfig:
    """A checked generation request.

    Attributes:
        dist: "paper" or "headcam".
        split: "train", "val" or "test".
        count: number of samples of the split (indices 0..count-1).
        out: dataset folder.
        objects: classes cycled over by sample index.
        width, height: image size [px].
        workers, backend, address: rendering processes and where they run (`sim.core.backends`).
        preview: where to write a contact sheet, or None.
        progress: show a tqdm bar.
        tier: the scene tier of ``headcam`` images (`sim.world.tiers`); None is the mixed
            table scenes of 0-3 distractors the shipped networks were trained on.
    """

    dist: str
    split: str
    count: int
    out: Path
    objects: tuple[str, ...] = OBJECT_NAMES
    width: int = 256
    height: int = 256
    workers: int = 1
    preview: Path | None = None
    progress: bool = True
    tier: str | None = None
    backend: str = "local"
    address: str | None = None

    def seed(self, index: int) -> int:
        """Seed of sample index."""
        return SEED_BASES[self.split] + index

    def object_of(self, index: int) -> str:
        """Class of sample index (the target, for headcam)."""
        return self.objects[index % len(self.objects)]

    def command(self) -> str:
        """The command line that regenerates the split (without --out)."""
        objs = "all" if self.objects == OBJECT_NAMES else ",".join(self.objects)
        tier = "" if self.tier is None else f" --tier {self.tier}"
        return (
            f"python -m perception.training.datagen --dist {self.dist} --split {self.split} "
            f"--count {self.count} --objects {objs} --width {self.width} --height {self.height}"
            + tier
        )


# --- the run ---------------------------------------------------------------------------------


def _check_info(cfg: GenConfig) -> dict[str, Any]:
    """info.json of the dataset folder updated for this run; errors if arguments conflict."""
    path = cfg.out / "info.json"
    if path.exists():
        info = load_info(cfg.out)
        have = (info.get("dist"), info.get("width"), info.get("height"), info.get("version"))
        want = (cfg.dist, cfg.width, cfg.height, GENERATOR_VERSION)
        if have != want or info.get("tier") != cfg.tier:
            raise InvalidArgumentError(
                f"{cfg.out} holds a {have[0]} dataset at {have[1]}x{have[2]} (generator "
                f"version {have[3]}, tier {info.get('tier')}); this run asks for {cfg.dist} at "
                f"{cfg.width}x{cfg.height} (version {GENERATOR_VERSION}, tier {cfg.tier}); "
                "use another --out"
            )
        old = info["splits"].get(cfg.split)
        if old is not None and tuple(old["objects"]) != cfg.objects:
            raise InvalidArgumentError(
                f"split {cfg.split!r} in {cfg.out} was generated with --objects "
                f"{','.join(old['objects'])}; use the same objects or another --out"
            )
    else:
        info = {
            "generator": "perception.training.datagen",
            "version": GENERATOR_VERSION,
            "dist": cfg.dist,
            "width": cfg.width,
            "height": cfg.height,
            "images_per_scene": bop.IMAGES_PER_SCENE,
            "objects": {str(bop.obj_id(n)): n for n in OBJECT_NAMES},
            "units": (
                "BOP files (scene_gt cam_t_m2c, scene_camera cam_t_w2c, models) in millimetres; "
                "scene_posegrasp.json and records in metres; pixels with (0, 0) the centre of "
                "the top-left pixel"
            ),
            "seed_bases": SEED_BASES,
            "splits": {},
        }
        if cfg.tier is not None:
            info["tier"] = cfg.tier
    return info


def _write_info(cfg: GenConfig, info: dict[str, Any], count: int) -> None:
    """Write info.json with the split's entry set to count images."""
    base = SEED_BASES[cfg.split]
    info["splits"][cfg.split] = {
        "count": count,
        "objects": list(cfg.objects),
        "seed_range": [base, base + count],
        "command": dataclasses.replace(cfg, count=count).command(),
    }
    bop.write_json(cfg.out / "info.json", info)


# Per-process state of pool workers (each worker owns one renderer; set by `_init_worker`).
_WORKER: dict[str, Any] = {}


def _init_worker(cfg: GenConfig) -> None:
    os.environ.setdefault("LP_NUM_THREADS", "1")
    _WORKER["cfg"] = cfg
    _WORKER["gen"] = make_generator(cfg.dist, cfg.width, cfg.height, cfg.tier)


def _work(index: int) -> int:
    cfg: GenConfig = _WORKER["cfg"]
    _generate_one(cfg, _WORKER["gen"], index)
    return index


def _generate_one(cfg: GenConfig, gen: PaperGenerator | HeadcamGenerator, index: int) -> None:
    seed = cfg.seed(index)
    image = gen.render(cfg.object_of(index), seed)
    write_sample(cfg.out, cfg.split, index, seed, image, cfg.dist)


def _done(cfg: GenConfig, index: int) -> bool:
    scene_id, im_id = bop.split_index(index)
    return bop.record_path(bop.scene_dir(cfg.out, cfg.split, scene_id), im_id).exists()


def generate(cfg: GenConfig, on_image: Callable[[int], None] | None = None) -> int:
    """Generate (or complete) a split; returns the number of images rendered by this call.

    Args:
        cfg: what to generate.
        on_image: called with each sample index as soon as its files are written.
    """
    started = time.monotonic()
    cfg.out.mkdir(parents=True, exist_ok=True)
    info = _check_info(cfg)
    write_models(cfg.out)
    _write_info(cfg, info, max(cfg.count, info["splits"].get(cfg.split, {}).get("count", 0)))
    todo = [i for i in range(cfg.count) if not _done(cfg, i)]
    # Images still to render per scene; a scene's files are merged when it reaches zero. Scenes
    # with nothing to render are merged at the end if their files are missing.
    left: dict[int, int] = {}
    for i in todo:
        left[i // bop.IMAGES_PER_SCENE] = left.get(i // bop.IMAGES_PER_SCENE, 0) + 1
    n_scenes = -(-cfg.count // bop.IMAGES_PER_SCENE)
    stale = set(left) | {
        s
        for s in range(n_scenes)
        if not (bop.scene_dir(cfg.out, cfg.split, s) / "scene_gt.json").exists()
    }
    bar = tqdm(total=cfg.count, initial=cfg.count - len(todo), desc=f"{cfg.dist}/{cfg.split}",
               unit="img", disable=not cfg.progress, dynamic_ncols=True)  # fmt: skip

    def finished(index: int) -> None:
        bar.update(1)
        if on_image is not None:
            on_image(index)
        s = index // bop.IMAGES_PER_SCENE
        left[s] -= 1
        if left[s] == 0:
            merge_scene(cfg.out, cfg.split, s)
            stale.discard(s)

    try:
        if len(todo) <= 1 or (cfg.workers <= 1 and cfg.backend == "local"):
            gen = make_generator(cfg.dist, cfg.width, cfg.height, cfg.tier)
            try:
                for i in todo:
                    _generate_one(cfg, gen, i)
                    finished(i)
            finally:
                gen.close()
        else:  # in the order the images come back; the Ray backend sizes its own chunks
            chunk = default_chunk(len(todo), cfg.workers) if cfg.backend == "local" else None
            for i in run_map(_work, todo, backend=cfg.backend, workers=cfg.workers,
                             address=cfg.address, chunk=chunk, initializer=_init_worker,
                             initargs=(cfg,), ordered=False):  # fmt: skip
                finished(i)
    finally:
        bar.close()
    for s in sorted(stale):
        merge_scene(cfg.out, cfg.split, s)
    split_dir = cfg.out / cfg.split
    total = sum(1 for _ in split_dir.glob("*/records/*.json"))
    _write_info(cfg, load_info(cfg.out), total)
    add_wall_time(cfg.out, cfg.split, time.monotonic() - started)
    write_camera(cfg.out, cfg.split, cfg.width, cfg.height)
    return len(todo)


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
