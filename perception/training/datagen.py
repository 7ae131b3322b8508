"""Build the pose datasets with MuJoCo: ``python -m perception.training.datagen`` (SPEC section 6).

    python -m perception.training.datagen --dist {paper,headcam} --split {train,val,test} --count N
        [--out DIR] [--objects all|phone,car] [--width W --height H] [--preview sheet.png]
        [--workers K]

Two distributions:

- ``paper``: the paper's protocol (section 2.8), one object alone in a randomised studio
  (`perception.training.studio`): camera uniform on the sphere at a random distance, random roll,
  procedural backgrounds, clutter, lights and colours; 256x256 by default.
- ``headcam``: the deployment distribution: the Fetch head camera's view of a seeded
  `sim.world.scene.build_scene` (target + 0-3 distractors on the table, randomised
  appearance), 640x480 by default; every object with visible pixels is annotated.

Layout and units: see `perception.training.dataset` (BOP layout, BOP files in millimetres,
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
import multiprocessing
import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NoReturn

import sim  # noqa: F401  # isort: skip  (defaults MUJOCO_GL before mujoco is imported)
import cv2
import numpy as np
from tqdm import tqdm

from perception.geometry import invert_transform, project
from perception.training import dataset as ds
from perception.training.studio import HIDDEN_GROUP, OffscreenRenderer, Studio, StudioConfig
from sim.core.errors import AssetError, InvalidArgumentError, PosegraspError, UnknownNameError
from sim.core.paths import data_root
from sim.world import constants as C
from sim.world.camera import T_world_cam, body_mask, camera_intrinsics, check_resolution
from sim.world.objects import OBJECT_NAMES, ObjectModel, load_object
from sim.world.scene import SceneConfig, build_scene

GENERATOR_VERSION = "1"
SEED_BASES: dict[str, int] = {"train": 0, "val": 100_000_000, "test": 200_000_000}
MAX_COUNT = 100_000_000
DEFAULT_SIZE: dict[str, tuple[int, int]] = {"paper": (256, 256), "headcam": (640, 480)}
#: At most this many distractors in a headcam scene (drawn uniformly from 0..3).
MAX_DISTRACTORS = 3
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
        workers: rendering processes.
        preview: where to write a contact sheet, or None.
        progress: show a tqdm bar.
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

    def seed(self, index: int) -> int:
        """Seed of sample index."""
        return SEED_BASES[self.split] + index

    def object_of(self, index: int) -> str:
        """Class of sample index (the target, for headcam)."""
        return self.objects[index % len(self.objects)]

    def command(self) -> str:
        """The command line that regenerates the split (without --out)."""
        objs = "all" if self.objects == OBJECT_NAMES else ",".join(self.objects)
        return (
            f"python -m perception.training.datagen --dist {self.dist} --split {self.split} "
            f"--count {self.count} --objects {objs} --width {self.width} --height {self.height}"
        )


# --- rendering ------------------------------------------------------------------------------


@dataclass
class RenderedObject:
    """One annotated instance of a rendered image.

    Attributes:
        name: class.
        T_C_O: pose in the camera (OpenCV convention), shape (4, 4) [m].
        mask: full silhouette inside the image (occluders ignored), shape (H, W), bool.
        mask_visib: visible pixels, shape (H, W), bool.
        extra: fields for scene_posegrasp.json (body name, target flag ...).
    """

    name: str
    T_C_O: np.ndarray
    mask: np.ndarray
    mask_visib: np.ndarray
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass
class RenderedImage:
    """A rendered image with its camera and annotated instances.

    Attributes:
        rgb: image, shape (H, W, 3), uint8.
        K: intrinsics, shape (3, 3) [px].
        T_C_W: world-to-camera transform, shape (4, 4) [m] (paper: the world is the object).
        objects: annotated instances.
        extra: per-image fields for scene_posegrasp.json.
    """

    rgb: np.ndarray
    K: np.ndarray
    T_C_W: np.ndarray
    objects: list[RenderedObject]
    extra: dict[str, Any] = field(default_factory=dict)


class PaperGenerator:
    """Paper-protocol images from one reusable `Studio` (one GL context per process)."""

    def __init__(self, width: int, height: int) -> None:
        self.studio = Studio(StudioConfig(width=width, height=height))

    def render(self, name: str, seed: int) -> RenderedImage:
        view = self.studio.render(name, np.random.default_rng(seed))
        obj = RenderedObject(name, view.T_C_O, view.mask, view.mask)
        extra = {"roll": view.roll, "camera_distance": view.distance}
        return RenderedImage(view.rgb, view.K, view.T_C_O.copy(), [obj], extra)

    def close(self) -> None:
        self.studio.close()


class HeadcamGenerator:
    """Head-camera images of seeded table scenes: a new scene per image, one GL context."""

    def __init__(self, width: int, height: int) -> None:
        self.width, self.height = width, height
        self.renderer = OffscreenRenderer(width, height)

    def render(self, name: str, seed: int) -> RenderedImage:
        wanted = int(np.random.default_rng([seed, 1]).integers(0, MAX_DISTRACTORS + 1))
        for n in range(wanted, -1, -1):
            try:
                scene = build_scene(
                    name, seed, SceneConfig(n_distractors=n, randomize_appearance=True)
                )
                break
            except InvalidArgumentError:  # the objects did not fit on the table
                if n == 0:
                    raise
        model, data, r = scene.model, scene.data, self.renderer
        cam = model.camera(C.HEAD_CAMERA).id
        K = camera_intrinsics(model, C.HEAD_CAMERA, self.width, self.height)
        T_C_W = invert_transform(T_world_cam(model, data, C.HEAD_CAMERA))
        rgb = r.render(model, data, cam)
        seg = r.geom_ids(model, data, cam)
        groups = model.geom_group.copy()
        objects = []
        for placed in scene.objects:
            T_C_O = T_C_W @ scene.object_pose(placed.body)
            visib = body_mask(model, seg, placed.body)
            if T_C_O[2, 3] <= 0 or not visib.any():
                continue
            # The full silhouette: the same view with every other geom hidden.
            bid = model.body(placed.body).id
            model.geom_group[:] = np.where(model.geom_bodyid == bid, groups, HIDDEN_GROUP)
            try:
                full = body_mask(model, r.geom_ids(model, data, cam), placed.body)
            finally:
                model.geom_group[:] = groups
            extra = {"body": placed.body, "target": placed is scene.target}
            objects.append(RenderedObject(placed.name, T_C_O, full | visib, visib, extra))
        extra = {"target": name, "n_distractors": len(scene.objects) - 1}
        return RenderedImage(rgb, K, T_C_W, objects, extra)

    def close(self) -> None:
        self.renderer.close()


def make_generator(dist: str, width: int, height: int) -> PaperGenerator | HeadcamGenerator:
    """The renderer of a distribution."""
    if dist == "paper":
        return PaperGenerator(width, height)
    if dist == "headcam":
        return HeadcamGenerator(width, height)
    raise UnknownNameError("distribution", dist, ds.DISTS)


# --- annotations -----------------------------------------------------------------------------


def _full_silhouette(
    obj: ObjectModel, T_C_O: np.ndarray, K: np.ndarray, mask: np.ndarray
) -> tuple[int, list[int]]:
    """Pixel count and BOP box of the whole silhouette, including any part outside the image.

    Inside the image the rendered mask is used. Only when the projected mesh leaves the image,
    its triangles are rasterised on a larger canvas (4 x 4 samples per pixel, fewer on very large
    canvases; a pixel counts if more than half of them are covered) for the part outside.
    """
    h, w = mask.shape
    verts = np.asarray(obj.mesh.vertices) @ T_C_O[:3, :3].T + T_C_O[:3, 3]
    if np.any(verts[:, 2] <= 1e-3):
        return int(mask.sum()), ds.bbox_xywh(mask)
    uv = verts[:, :2] / verts[:, 2:3] * [K[0, 0], K[1, 1]] + K[:2, 2]
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    if lo[0] >= -0.5 and lo[1] >= -0.5 and hi[0] <= w - 0.5 and hi[1] <= h - 0.5:
        return int(mask.sum()), ds.bbox_xywh(mask)
    # Canvas [ox, ox + cw) x [oy, oy + ch) in image pixels, at most 5x the image.
    ox = int(np.floor(max(min(lo[0], 0.0), -2.0 * w)))
    oy = int(np.floor(max(min(lo[1], 0.0), -2.0 * h)))
    cw = int(np.ceil(min(max(hi[0], w), 3.0 * w))) - ox + 1
    ch = int(np.ceil(min(max(hi[1], h), 3.0 * h))) - oy + 1
    ss = 4 if ch * cw <= 4 * h * w else 2
    fine = np.zeros((ch * ss, cw * ss), np.uint8)
    pts = np.round(((uv - [ox, oy] + 0.5) * ss - 0.5) * 16).astype(np.int32)
    for tri in np.asarray(obj.mesh.faces):
        cv2.fillConvexPoly(fine, pts[tri], 1, cv2.LINE_8, 4)
    canvas = (fine.reshape(ch, ss, cw, ss).mean(axis=(1, 3)) > 0.5).astype(np.uint8)
    canvas[-oy : -oy + h, -ox : -ox + w] = mask
    x, y, bw, bh = ds.bbox_xywh(canvas)
    return int(canvas.sum()), [x + ox, y + oy, bw, bh]


def annotate(image: RenderedImage, seed: int, dist: str) -> dict[str, Any]:
    """The record of an image: its entries of the four scene files."""
    gts, infos, pg_objs = [], [], []
    T_W_C = invert_transform(image.T_C_W)
    for obj in image.objects:
        model = load_object(obj.name)
        px_all, bbox_obj = _full_silhouette(model, obj.T_C_O, image.K, obj.mask)
        px_visib = int(obj.mask_visib.sum())
        gts.append({**ds.pose_to_bop(obj.T_C_O), "obj_id": ds.obj_id(obj.name)})
        infos.append(
            {
                "bbox_obj": bbox_obj,
                "bbox_visib": ds.bbox_xywh(obj.mask_visib),
                "px_count_all": px_all,
                "px_count_valid": int(obj.mask.sum()),
                "px_count_visib": px_visib,
                "visib_fract": px_visib / px_all if px_all else 0.0,
            }
        )
        pg_objs.append(
            {
                **obj.extra,
                "class": obj.name,
                "obj_id": ds.obj_id(obj.name),
                "T_C_O": obj.T_C_O.tolist(),
                "uv": project(image.K, obj.T_C_O[:3, 3]).tolist(),
                "box_xyxy": ds.box_xyxy(obj.mask_visib),
                "visib_fract": infos[-1]["visib_fract"],
            }
        )
    camera = {
        "cam_K": [float(x) for x in image.K.reshape(-1)],
        "depth_scale": 1.0,
        "cam_R_w2c": [float(x) for x in image.T_C_W[:3, :3].reshape(-1)],
        "cam_t_w2c": [float(x) * ds.MM_PER_M for x in image.T_C_W[:3, 3]],
    }
    pg = {
        **image.extra,
        "dist": dist,
        "seed": seed,
        "T_W_C": T_W_C.tolist(),
        "objects": pg_objs,
    }
    return {
        "scene_gt": gts,
        "scene_camera": camera,
        "scene_gt_info": infos,
        "scene_posegrasp": pg,
    }


def write_sample(
    root: Path, split: str, index: int, seed: int, image: RenderedImage, dist: str
) -> None:
    """Write one image's files; the record goes last and marks the image as done."""
    scene_id, im_id = ds.split_index(index)
    sdir = ds.scene_dir(root, split, scene_id)
    record = annotate(image, seed, dist)
    ds.write_png(ds.rgb_path(sdir, im_id), image.rgb)
    for k, obj in enumerate(image.objects):
        full = ds.png_bytes(obj.mask.astype(np.uint8) * 255)
        same = obj.mask_visib is obj.mask or np.array_equal(obj.mask_visib, obj.mask)
        visib = full if same else ds.png_bytes(obj.mask_visib.astype(np.uint8) * 255)
        ds.write_bytes(ds.mask_path(sdir, im_id, k, False), full)
        ds.write_bytes(ds.mask_path(sdir, im_id, k, True), visib)
    ds.write_json(ds.record_path(sdir, im_id), record, indent=None)


def merge_scene(root: Path, split: str, scene_id: int) -> int:
    """Merge a scene's records into its four BOP scene files; returns the number of images."""
    sdir = ds.scene_dir(root, split, scene_id)
    merged: dict[str, dict[str, Any]] = {k: {} for k in ds.SCENE_FILES}
    records = sorted((sdir / "records").glob("*.json"))
    for path in records:
        rec = ds.read_json(path, root, split)
        for k in ds.SCENE_FILES:
            merged[k][str(int(path.stem))] = rec[k]
    for k in ds.SCENE_FILES:
        ds.write_json(sdir / f"{k}.json", merged[k])
    return len(records)


def write_models(root: Path) -> None:
    """BOP models (PLY in mm with vertex colours) and models_info.json for every object."""
    info = {}
    for name in OBJECT_NAMES:
        obj = load_object(name)
        verts, normals, colours, faces = [], [], [], []
        offset = 0
        for part in obj.parts:
            m = part.mesh()
            verts.append(np.asarray(m.vertices))
            normals.append(np.asarray(m.vertex_normals))
            rgb = np.clip(np.round(np.asarray(part.rgba[:3]) * 255), 0, 255).astype(np.uint8)
            colours.append(np.tile(rgb, (len(m.vertices), 1)))
            faces.append(np.asarray(m.faces) + offset)
            offset += len(m.vertices)
        v = np.vstack(verts) * ds.MM_PER_M
        ds.write_ply(
            root / "models" / f"obj_{ds.obj_id(name):06d}.ply",
            v,
            np.vstack(normals),
            np.vstack(colours),
            np.vstack(faces),
        )
        lo, size = v.min(axis=0), v.max(axis=0) - v.min(axis=0)
        entry: dict[str, Any] = {"diameter": obj.diameter * ds.MM_PER_M}
        for i, axis in enumerate("xyz"):
            entry[f"min_{axis}"] = float(lo[i])
            entry[f"size_{axis}"] = float(size[i])
        syms = []
        for T in obj.symmetries:
            S = np.array(T, float)
            S[:3, 3] *= ds.MM_PER_M
            syms.append([float(x) for x in S.reshape(-1)])
        if syms:
            entry["symmetries_discrete"] = syms
        info[str(ds.obj_id(name))] = entry
    ds.write_json(root / "models" / "models_info.json", info)


# --- the run ---------------------------------------------------------------------------------


def _check_info(cfg: GenConfig) -> dict[str, Any]:
    """info.json of the dataset folder updated for this run; errors if arguments conflict."""
    path = cfg.out / "info.json"
    if path.exists():
        info = ds.load_info(cfg.out)
        have = (info.get("dist"), info.get("width"), info.get("height"), info.get("version"))
        want = (cfg.dist, cfg.width, cfg.height, GENERATOR_VERSION)
        if have != want:
            raise InvalidArgumentError(
                f"{cfg.out} holds a {have[0]} dataset at {have[1]}x{have[2]} (generator "
                f"version {have[3]}); this run asks for {cfg.dist} at {cfg.width}x{cfg.height} "
                f"(version {GENERATOR_VERSION}); use another --out"
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
            "images_per_scene": ds.IMAGES_PER_SCENE,
            "objects": {str(ds.obj_id(n)): n for n in OBJECT_NAMES},
            "units": (
                "BOP files (scene_gt cam_t_m2c, scene_camera cam_t_w2c, models) in millimetres; "
                "scene_posegrasp.json and records in metres; pixels with (0, 0) the centre of "
                "the top-left pixel"
            ),
            "seed_bases": SEED_BASES,
            "splits": {},
        }
    return info


def _write_info(cfg: GenConfig, info: dict[str, Any], count: int) -> None:
    base = SEED_BASES[cfg.split]
    run = GenConfig(cfg.dist, cfg.split, count, cfg.out, cfg.objects, cfg.width, cfg.height)
    info["splits"][cfg.split] = {
        "count": count,
        "objects": list(cfg.objects),
        "seed_range": [base, base + count],
        "command": run.command(),
    }
    ds.write_json(cfg.out / "info.json", info)


def _write_camera(cfg: GenConfig) -> None:
    """BOP camera.json, from the K of the split's first image (all images share it)."""
    first = next(iter(sorted((cfg.out / cfg.split).glob("*/records/*.json"))), None)
    if first is None:
        return
    K = np.asarray(ds.read_json(first, cfg.out, cfg.split)["scene_camera"]["cam_K"]).reshape(3, 3)
    camera = {
        "cx": float(K[0, 2]),
        "cy": float(K[1, 2]),
        "fx": float(K[0, 0]),
        "fy": float(K[1, 1]),
        "width": cfg.width,
        "height": cfg.height,
        "depth_scale": 1.0,
    }
    ds.write_json(cfg.out / "camera.json", camera)


# Per-process state of pool workers (each worker owns one renderer; set by `_init_worker`).
_WORKER: dict[str, Any] = {}


def _init_worker(cfg: GenConfig) -> None:
    os.environ.setdefault("LP_NUM_THREADS", "1")
    _WORKER["cfg"] = cfg
    _WORKER["gen"] = make_generator(cfg.dist, cfg.width, cfg.height)


def _work(index: int) -> int:
    cfg: GenConfig = _WORKER["cfg"]
    _generate_one(cfg, _WORKER["gen"], index)
    return index


def _generate_one(cfg: GenConfig, gen: PaperGenerator | HeadcamGenerator, index: int) -> None:
    seed = cfg.seed(index)
    image = gen.render(cfg.object_of(index), seed)
    write_sample(cfg.out, cfg.split, index, seed, image, cfg.dist)


def _done(cfg: GenConfig, index: int) -> bool:
    scene_id, im_id = ds.split_index(index)
    return ds.record_path(ds.scene_dir(cfg.out, cfg.split, scene_id), im_id).exists()


def generate(cfg: GenConfig, on_image: Callable[[int], None] | None = None) -> int:
    """Generate (or complete) a split; returns the number of images rendered by this call.

    Args:
        cfg: what to generate.
        on_image: called with each sample index as soon as its files are written.
    """
    cfg.out.mkdir(parents=True, exist_ok=True)
    info = _check_info(cfg)
    write_models(cfg.out)
    _write_info(cfg, info, max(cfg.count, info["splits"].get(cfg.split, {}).get("count", 0)))
    todo = [i for i in range(cfg.count) if not _done(cfg, i)]
    # Images still to render per scene; a scene's files are merged when it reaches zero. Scenes
    # with nothing to render are merged at the end if their files are missing.
    left: dict[int, int] = {}
    for i in todo:
        left[i // ds.IMAGES_PER_SCENE] = left.get(i // ds.IMAGES_PER_SCENE, 0) + 1
    n_scenes = -(-cfg.count // ds.IMAGES_PER_SCENE)
    stale = set(left) | {
        s
        for s in range(n_scenes)
        if not (ds.scene_dir(cfg.out, cfg.split, s) / "scene_gt.json").exists()
    }
    bar = tqdm(
        total=cfg.count,
        initial=cfg.count - len(todo),
        desc=f"{cfg.dist}/{cfg.split}",
        unit="img",
        disable=not cfg.progress,
        dynamic_ncols=True,
    )

    def finished(index: int) -> None:
        bar.update(1)
        if on_image is not None:
            on_image(index)
        s = index // ds.IMAGES_PER_SCENE
        left[s] -= 1
        if left[s] == 0:
            merge_scene(cfg.out, cfg.split, s)
            stale.discard(s)

    try:
        if cfg.workers <= 1 or len(todo) <= 1:
            gen = make_generator(cfg.dist, cfg.width, cfg.height)
            try:
                for i in todo:
                    _generate_one(cfg, gen, i)
                    finished(i)
            finally:
                gen.close()
        else:
            ctx = multiprocessing.get_context("spawn")
            with ctx.Pool(cfg.workers, initializer=_init_worker, initargs=(cfg,)) as pool:
                chunk = max(1, min(16, len(todo) // (4 * cfg.workers)))
                for i in pool.imap_unordered(_work, todo, chunksize=chunk):
                    finished(i)
    finally:
        bar.close()
    for s in sorted(stale):
        merge_scene(cfg.out, cfg.split, s)
    split_dir = cfg.out / cfg.split
    total = sum(1 for _ in split_dir.glob("*/records/*.json"))
    _write_info(cfg, ds.load_info(cfg.out), total)
    _write_camera(cfg)
    return len(todo)


def write_preview(cfg: GenConfig, path: Path, n: int = 24) -> None:
    """Contact sheet of the split's first n images with axes, boxes and origins drawn."""
    data = ds.PoseDataset(cfg.out, cfg.split)
    images = [ds.draw_annotations(data[i]) for i in range(min(n, len(data)))]
    cols = 6 if cfg.dist == "paper" else 4
    sheet = ds.contact_sheet(images, cols=cols, tile=256 if cfg.dist == "paper" else 320)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), sheet[..., ::-1]):
        raise AssetError(f"cannot write preview {path}")


# --- command line ----------------------------------------------------------------------------


class _UsageError(Exception):
    """An argument argparse rejected."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        raise _UsageError(f"{message}; {' '.join(self.format_usage().split())}")


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
    p.add_argument("--preview", type=Path, default=None, help="write a contact sheet PNG here")
    p.add_argument("--workers", type=int, default=1, help="rendering processes (default 1)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def parse_args(argv: Sequence[str] | None) -> GenConfig:
    """Parse and check a command line (raises _UsageError or PosegraspError)."""
    a = _parser().parse_args(argv)
    if a.dist not in ds.DISTS:
        raise UnknownNameError("distribution", a.dist, ds.DISTS)
    if a.split not in ds.SPLITS:
        raise UnknownNameError("split", a.split, ds.SPLITS)
    if not 1 <= a.count <= MAX_COUNT:
        raise InvalidArgumentError(f"invalid --count {a.count}; valid: 1..{MAX_COUNT}")
    if a.workers < 1:
        raise InvalidArgumentError(f"invalid --workers {a.workers}; valid: 1 or more")
    if a.objects == "all":
        objects = OBJECT_NAMES
    else:
        objects = tuple(s.strip() for s in a.objects.split(",") if s.strip())
        if not objects:
            raise InvalidArgumentError(
                f"empty --objects; valid: all or a comma list of {', '.join(OBJECT_NAMES)}"
            )
        for n in objects:
            if n not in OBJECT_NAMES:
                raise UnknownNameError("object", n, OBJECT_NAMES)
    width = a.width if a.width is not None else DEFAULT_SIZE[a.dist][0]
    height = a.height if a.height is not None else DEFAULT_SIZE[a.dist][1]
    check_resolution(width, height)
    out = a.out
    if out is None:
        out = data_root() / a.dist
    return GenConfig(
        dist=a.dist,
        split=a.split,
        count=a.count,
        out=Path(out),
        objects=objects,
        width=width,
        height=height,
        workers=a.workers,
        preview=a.preview,
        progress=not a.quiet,
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
    except _UsageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except PosegraspError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    # One software-rendering thread per process is faster than llvmpipe's default on 2 cores.
    os.environ.setdefault("LP_NUM_THREADS", "1")
    try:
        n = generate(cfg)
        if cfg.preview is not None:
            write_preview(cfg, cfg.preview)
    except KeyboardInterrupt:
        print("error: interrupted; run the same command again to resume", file=sys.stderr)
        return 130
    except (PosegraspError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    done = f"{cfg.dist}/{cfg.split}: rendered {n}, {cfg.count - n} already done, in {cfg.out}"
    if cfg.preview is not None:
        done += f"; preview {cfg.preview}"
    print(done)
    return 0


if __name__ == "__main__":
    sys.exit(main())
