"""Rendering a dataset split: the checked request (`GenConfig`), its seeds, and `generate`.

Seeds: sample ``index`` of a split shows scene ``index // views`` (``views`` = 1 unless
``--views``), whose seed is ``SEED_BASES[split] + index // views``; the bases are 10^8 apart, so
splits never share a seed. Within a split, each kind of scene starts at its own multiple of
`KIND_SPAN` and holds at most that many (``--count`` is at most `MAX_COUNT`), so no two kinds share
a seed: rooms (``--rooms [FAMILY]``, `perception.training.data.rooms`) start their family's
`ROOM_SEED_OFFSETS` further on, the bank's scenes (``--bank [BANK]``,
`perception.training.data.distributions.BankGenerator`) their bank's `BANK_SEED_OFFSETS` further
again.
``paper`` draws everything from ``numpy.random.default_rng(seed)``; ``headcam`` builds
``build_scene(target, seed, ...)`` with the number of distractors drawn from
``default_rng([seed, 1])`` and renders view ``index % views`` of it
(`HeadcamGenerator.render_views`: view 0 aimed at the target, the others at each object in turn).
The class of sample index (its scene's target) is ``objects[(index // views) % len(objects)]``. With
several views per scene, building and settling a scene (a third of an image's cost) is paid once per
scene. Same arguments, same bytes: PNGs are encoded with fixed parameters, JSON with sorted keys,
and nothing depends on the number of workers or on timing.

Resuming: every file is written to a temporary name and renamed; an image is done once its record
(``records/<im_id>.json``) exists, and a re-run skips done images. The BOP scene files are merged
from the records whenever a scene's images are complete and at the end of a run.
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from perception.training.data import bop
from perception.training.data.dataset import load_info
from perception.training.data.distributions import HeadcamGenerator, PaperGenerator, make_generator
from perception.training.data.rooms import FAMILIES
from perception.training.data.writer import (
    add_wall_time,
    merge_scene,
    write_camera,
    write_models,
    write_sample,
)
from posegrasp.core.backends import default_chunk, run_map
from posegrasp.core.errors import InvalidArgumentError, UnknownNameError
from posegrasp.core.progress import progress_bar
from posegrasp.core.runtime import setup_rendering
from posegrasp.world.distractor_bank import BANKS, bank_name
from posegrasp.world.objects import OBJECT_NAMES

#: Generator version per distribution; a dataset folder only resumes at its own version. Paper
#: protocol 3: the camera 1.2-1.8 object diameters from the object (2: 1.6-4.5).
GENERATOR_VERSIONS: dict[str, str] = {"paper": "3", "headcam": "2"}
SEED_BASES: dict[str, int] = {"train": 0, "val": 100_000_000, "test": 200_000_000}
#: The seeds a kind of scene of a split may take, and so the most images of a split.
KIND_SPAN = 6_250_000
MAX_COUNT = KIND_SPAN
#: Where the seeds of a split's rooms start after its plain seeds, per family of rooms, and where
#: the scenes of each bank's meshes start after those of the same room (or the plain ones).
ROOM_SEED_OFFSETS: dict[str, int] = {"wide": 8 * KIND_SPAN, "joint": 12 * KIND_SPAN}
BANK_SEED_OFFSETS: dict[str, int] = {
    "training": KIND_SPAN,
    "held-out": 2 * KIND_SPAN,
    "shapes": 3 * KIND_SPAN,
}
#: Most head-camera views rendered of one scene (`--views`).
MAX_VIEWS = 16
DEFAULT_SIZE: dict[str, tuple[int, int]] = {"paper": (256, 256), "headcam": (640, 480)}


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
        workers, backend, address: rendering processes and where they run
            (`posegrasp.core.backends`).
        preview: where to write a contact sheet, or None.
        progress: show a tqdm bar.
        tier: the scene tier of ``headcam`` images (`posegrasp.world.tiers`); None is the mixed
            table scenes of 0-3 distractors the shipped networks were trained on.
        views: ``headcam`` images per scene (`HeadcamGenerator.render_views`); 1 for
            ``paper``.
        rooms: ``headcam`` scenes in rooms drawn for training, of this family of
            `perception.training.data.rooms.FAMILIES`; None for the plain room.
        bank: ``headcam`` scenes of this bank's meshes alone
            (`posegrasp.world.distractor_bank.BANKS`), each annotated as an object of its own
            (`perception.training.data.distributions.BankGenerator`); None for the objects'.
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
    views: int = 1
    rooms: str | None = None
    bank: str | None = None

    def __post_init__(self) -> None:
        if self.rooms is not None and self.rooms not in ROOM_SEED_OFFSETS:
            raise UnknownNameError("room family", self.rooms, FAMILIES)
        if not 1 <= self.count <= MAX_COUNT:
            raise InvalidArgumentError(f"a split holds 1..{MAX_COUNT} images, not {self.count}")
        if self.bank is not None and self.bank not in BANK_SEED_OFFSETS:
            raise UnknownNameError("bank", self.bank, BANK_SEED_OFFSETS)
        if (self.rooms is not None or self.bank is not None) and self.dist != "headcam":
            raise InvalidArgumentError("rooms and bank scenes are of --dist headcam")
        if self.bank is not None and (self.tier is not None or self.views != 1):
            raise InvalidArgumentError("bank scenes have no tier and one view")

    def seed(self, index: int) -> int:
        """Seed of sample index (of its scene)."""
        offset = 0 if self.rooms is None else ROOM_SEED_OFFSETS[self.rooms]
        offset += 0 if self.bank is None else BANK_SEED_OFFSETS[self.bank]
        return SEED_BASES[self.split] + offset + index // self.views

    def view(self, index: int) -> int:
        """View of its scene that sample index shows."""
        return index % self.views

    def object_of(self, index: int) -> str:
        """Class of sample index (its scene's target, for headcam)."""
        return self.objects[(index // self.views) % len(self.objects)]

    def command(self) -> str:
        """The command line that regenerates the split (without --out)."""
        objs = "all" if self.objects == OBJECT_NAMES else ",".join(self.objects)
        tier = "" if self.tier is None else f" --tier {self.tier}"
        tier += "" if self.views == 1 else f" --views {self.views}"
        if self.rooms is not None:
            tier += " --rooms" if self.rooms == "wide" else f" --rooms {self.rooms}"
        if self.bank is not None:
            tier += " --bank" if self.bank == "training" else f" --bank {self.bank}"
        return (
            f"python -m perception.training.datagen --dist {self.dist} --split {self.split} "
            f"--count {self.count} --objects {objs} --width {self.width} --height {self.height}"
            + tier
        )


# --- the run ---------------------------------------------------------------------------------


def _classes(cfg: GenConfig) -> list[str]:
    """The objects a split's images may show: the six built-in ones (the distractors) and the
    user objects it takes as targets; for bank scenes, their bank's meshes."""
    if cfg.bank is not None:
        return [bank_name(i) for i in BANKS[cfg.bank]]
    return [*OBJECT_NAMES, *(o for o in cfg.objects if o not in OBJECT_NAMES)]


def _check_info(cfg: GenConfig) -> dict[str, Any]:
    """info.json of the dataset folder updated for this run; errors if arguments conflict."""
    path = cfg.out / "info.json"
    if path.exists():
        info = load_info(cfg.out)
        have = (info.get("dist"), info.get("width"), info.get("height"), info.get("version"))
        want = (cfg.dist, cfg.width, cfg.height, GENERATOR_VERSIONS[cfg.dist])
        rooms, bank = info.get("rooms"), info.get("bank")
        rooms = "wide" if rooms is True else rooms  # folders of the first family said true
        if have != want or info.get("tier") != cfg.tier or (rooms, bank) != (cfg.rooms, cfg.bank):
            raise InvalidArgumentError(
                f"{cfg.out} holds a {have[0]} dataset at {have[1]}x{have[2]} (generator "
                f"version {have[3]}, tier {info.get('tier')}, rooms {rooms}, bank {bank}); "
                f"this run asks for {cfg.dist} at {cfg.width}x{cfg.height} (version {want[3]}, "
                f"tier {cfg.tier}, rooms {cfg.rooms}, bank {cfg.bank}); "
                "use another --out"
            )
        old = info["splits"].get(cfg.split)
        if old is not None and tuple(old["objects"]) != cfg.objects:
            raise InvalidArgumentError(
                f"split {cfg.split!r} in {cfg.out} was generated with --objects "
                f"{','.join(old['objects'])}; use the same objects or another --out"
            )
        if old is not None and old.get("views", 1) != cfg.views:
            raise InvalidArgumentError(
                f"split {cfg.split!r} in {cfg.out} was generated with --views "
                f"{old.get('views', 1)}; use the same views or another --out"
            )
    else:
        info = {
            "generator": "perception.training.datagen",
            "version": GENERATOR_VERSIONS[cfg.dist],
            "dist": cfg.dist,
            "width": cfg.width,
            "height": cfg.height,
            "images_per_scene": bop.IMAGES_PER_SCENE,
            "objects": {str(bop.obj_id(n)): n for n in _classes(cfg)},
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
        if cfg.rooms is not None:
            info["rooms"] = cfg.rooms
        if cfg.bank is not None:
            info["bank"] = cfg.bank
    return info


def _write_info(cfg: GenConfig, info: dict[str, Any], count: int) -> None:
    """Write info.json with the split's entry set to count images."""
    base = cfg.seed(0)
    info["splits"][cfg.split] = {
        "count": count,
        "objects": list(cfg.objects),
        "seed_range": [base, base + -(-count // cfg.views)],
        "command": dataclasses.replace(cfg, count=count).command(),
    }
    if cfg.views > 1:
        info["splits"][cfg.split]["views"] = cfg.views
    bop.write_json(cfg.out / "info.json", info)


# Per-process state of pool workers (each worker owns one renderer; set by `_init_worker`).
_WORKER: dict[str, Any] = {}


def _init_worker(cfg: GenConfig) -> None:
    os.environ.setdefault("LP_NUM_THREADS", "1")
    setup_rendering()
    _WORKER["cfg"] = cfg
    _WORKER["gen"] = make_generator(cfg.dist, cfg.width, cfg.height, cfg.tier, cfg.rooms, cfg.bank)


def _work(indices: tuple[int, ...]) -> tuple[int, ...]:
    return _generate(_WORKER["cfg"], _WORKER["gen"], indices)


def _generate(
    cfg: GenConfig, gen: PaperGenerator | HeadcamGenerator, indices: tuple[int, ...]
) -> tuple[int, ...]:
    """Render and write samples of one scene (the same ``index // views``); returns indices."""
    seed = cfg.seed(indices[0])
    if cfg.views == 1:
        images = [gen.render(cfg.object_of(indices[0]), seed)]
    else:
        assert isinstance(gen, HeadcamGenerator)  # datagen allows views > 1 for headcam only
        views = [cfg.view(i) for i in indices]
        images = gen.render_views(cfg.object_of(indices[0]), seed, views)
    for index, image in zip(indices, images, strict=True):
        write_sample(cfg.out, cfg.split, index, seed, image, cfg.dist)
    return indices


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
    write_models(cfg.out, _classes(cfg))
    _write_info(cfg, info, max(cfg.count, info["splits"].get(cfg.split, {}).get("count", 0)))
    todo = [i for i in range(cfg.count) if not _done(cfg, i)]
    tasks, left, stale = _plan(cfg, todo)
    bar = progress_bar(
        total=cfg.count,
        initial=cfg.count - len(todo),
        desc=f"{cfg.dist}/{cfg.split}",
        unit="img",
        disable=not cfg.progress,
    )

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
        _render_tasks(cfg, tasks, finished)
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


def _plan(
    cfg: GenConfig, todo: list[int]
) -> tuple[list[tuple[int, ...]], dict[int, int], set[int]]:
    """The work of the images `todo` of a split: its tasks (the images of one generator scene
    each), the images still to render per BOP scene (a scene's files are merged when it reaches
    zero), and the BOP scenes whose files are to be merged (those with images to render, and
    those whose files are missing, merged at the end)."""
    groups: dict[int, list[int]] = {}  # the samples still to render per generator scene
    for i in todo:
        groups.setdefault(i // cfg.views, []).append(i)
    left: dict[int, int] = {}
    for i in todo:
        left[i // bop.IMAGES_PER_SCENE] = left.get(i // bop.IMAGES_PER_SCENE, 0) + 1
    n_scenes = -(-cfg.count // bop.IMAGES_PER_SCENE)
    stale = set(left) | {
        s
        for s in range(n_scenes)
        if not (bop.scene_dir(cfg.out, cfg.split, s) / "scene_gt.json").exists()
    }
    return [tuple(g) for g in groups.values()], left, stale


def _render_tasks(
    cfg: GenConfig, tasks: list[tuple[int, ...]], finished: Callable[[int], None]
) -> None:
    """Render `tasks` in this process, or on the workers of `cfg`'s backend in the order the
    images come back, calling `finished` with each image's index once its files are written."""
    if len(tasks) <= 1 or (cfg.workers <= 1 and cfg.backend == "local"):
        gen = make_generator(cfg.dist, cfg.width, cfg.height, cfg.tier, cfg.rooms, cfg.bank)
        try:
            for task in tasks:
                for i in _generate(cfg, gen, task):
                    finished(i)
        finally:
            gen.close()
        return
    chunk = default_chunk(len(tasks), cfg.workers) if cfg.backend == "local" else None
    for done in run_map(  # the Ray backend sizes its own chunks
        _work,
        tasks,
        backend=cfg.backend,
        workers=cfg.workers,
        address=cfg.address,
        chunk=chunk,
        initializer=_init_worker,
        initargs=(cfg,),
        ordered=False,
    ):
        for i in done:
            finished(i)
