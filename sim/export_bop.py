"""Export the head-camera views of an evaluation's episodes as a BOP dataset.

    python -m sim.export_bop --tier T --objects car,phone --episodes N [--seed-start S] \
        [--sensor NAME] [--shift SPEC] --out DIR [--no-gt]

Any estimator that reads BOP datasets can then estimate the poses of these images offline and
hand back a BOP results CSV, which `sim.evaluation.bop_results` turns into the estimates of the
very same episodes (``sim.evaluate`` with the same tier, objects, episodes and seed start). Episode
i of object X is scene seed ``S + i``, built by `sim.episodes.episode.Episode` and rendered by its
``observe()``, so each RGB image is byte for byte what a live estimator gets, and each depth
image that of ``--obs-mode rgbd`` to the depth step, both as the sensor model ``--sensor``
returns them (`posegrasp.world.sensors`; default ``ideal``, the rendered images): with a real
sensor's model the depth has its noise and its holes (0, BOP's missing depth), and
``px_count_valid`` counts the pixels with depth under it. The episodes' own VSD
(`sim.episodes.episode.EpisodeResult.vsd`) is measured against the ideal depth whatever the sensor,
so it is that against the exported depth only for ``ideal``. With ``--shift SPEC`` the scenes are
seen under those scene shifts (`posegrasp.world.shifts`: lights, textures, colours, visual-only
distractors, the head camera's pose), as ``sim.evaluate --shift SPEC`` sees them; the map file
records them, and ``sim.evaluate --poses CSV --from DIR`` grasps in the same shifted scenes.

Layout of ``DIR`` (BOP toolkit, docs/bop_datasets_format.md; millimetres in every BOP file)::

    DIR/camera.json                         fx, fy, cx, cy, width, height, depth_scale
    DIR/models/models_info.json             diameter, min_*, size_* [mm], symmetries_discrete
    DIR/models/obj_<obj_id:06d>.ply         the objects' meshes [mm] (vertex colours)
    DIR/models_eval/                        the same files (BOP's evaluation models)
    DIR/test/<scene_id:06d>/rgb/000000.png           the head-camera image, 640x480
    DIR/test/<scene_id:06d>/depth/000000.png         z-depth, uint16, mm = value * depth_scale
    DIR/test/<scene_id:06d>/scene_camera.json        cam_K, depth_scale, cam_R_w2c, cam_t_w2c
    DIR/test/<scene_id:06d>/scene_gt.json            cam_R_m2c, cam_t_m2c, obj_id (not --no-gt)
    DIR/test/<scene_id:06d>/scene_gt_info.json       bbox_*, px_count_*, visib_fract (ditto)
    DIR/test/<scene_id:06d>/mask/000000_<gt:06d>.png       full silhouette, 0/255 (ditto)
    DIR/test/<scene_id:06d>/mask_visib/000000_<gt:06d>.png visible part, 0/255 (ditto)
    DIR/test_targets_bop19.json             per image: the episode's target (inst_count 1)
    DIR/test_targets_bop24.json             per image: scene_id, im_id
    DIR/posegrasp_episodes.json             the episodes: tier, seeds, objects, sensor, scene
                                            shifts, image ids, table_top_z [m] per image

One scene per episode, one image each (im_id 0): a BOP scene is one static arrangement, and
each episode is its own. Its ``scene_id`` is `sim.evaluation.bop_results.scene_ids` of the
episode's tier, target and seed, so that exports of other tiers, objects or seeds do not share ids
and a CSV of one is refused by another. ``scene_gt`` lists every object of the scene, the target
first, then the others in the scene's order; ``scene_gt_info`` and the masks follow BOP's public
test sets: the visible mask is the object's pixels in a segmentation render, the full silhouette the
object rendered alone, ``px_count_all`` its pixels also outside the image, ``px_count_valid``
its pixels with depth. Depth beyond ``65535 * depth_scale`` mm (or no surface) is 0, BOP's
missing depth. The map file also holds each image's table height in the world frame (the
``table_top_z`` a live estimator's observation carries; ``scene_camera``'s ``cam_R_w2c`` and
``cam_t_w2c`` give the world frame).

A folder holds one export: the same arguments again write the same bytes, other arguments or
other files are refused. An export under way keeps each finished image's index entries in a
journal in its folder (`JOURNAL_FILE`; the map file says ``"complete": false`` until the last file
is written), so a stopped one resumes after its last finished image when the same command runs
again, and ends with the bytes an unstopped one writes.
"""

from __future__ import annotations

import json
import struct
import sys
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from perception.training.data.annotations import full_silhouette
from perception.training.data.bop import (
    MM_PER_M,
    PNG_LEVEL,
    bbox_xywh,
    obj_id,
    pose_to_bop,
    rgb_path,
    scene_dir,
    write_bytes,
    write_json,
    write_png,
)
from perception.training.data.writer import write_models
from posegrasp.core.cli import ArgumentParser, add_out_argument, command
from posegrasp.core.contract import CONTRACT_VERSION
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.journal import Interrupted, Journal, resume_hint
from posegrasp.core.paths import git_commit
from posegrasp.core.progress import progress_bar
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.transforms import invert_transform
from posegrasp.core.validate import arg, check_int, check_seed
from posegrasp.world import constants as C
from posegrasp.world.camera import body_mask, depth_to_uint16
from posegrasp.world.objects import OBJECT_NAMES, check_objects, load_object
from posegrasp.world.scene import SceneConfig
from posegrasp.world.shifts import Shift, canonical
from posegrasp.world.tiers import DEFAULT_TIER, TIERS, check_tier
from sim.episodes.episode import Episode, EpisodeConfig, execution_settings
from sim.episodes.registry import add_sensor_argument, add_shift_argument
from sim.evaluation.bop_results import EXPORT_FORMAT, EXPORT_VERSION, MAP_FILE, scene_ids

#: BOP split the images go to.
SPLIT = "test"
#: Depth PNG unit [mm per value]: 0.1 mm steps up to 6.5535 m.
DEPTH_SCALE = 0.1
#: Most episodes per object (as ``sim.evaluate``).
MAX_EPISODES = 100_000
#: A geom group MuJoCo's default visualisation options do not draw (groups 0-2 are drawn).
_HIDDEN_GROUP = 5
#: BOP's box of an object with no visible pixel (scripts/calc_gt_info.py).
_NO_BOX = [-1, -1, -1, -1]
#: Protocol entries of maps written before they were recorded, at the value they had then.
_PROTOCOL_BEFORE: dict[str, Any] = {"sensor": "ideal", "shifts": []}


#: The im_id of every image: each scene holds one.
IM_ID = 0
#: The journal of an export under way, in its folder: each finished image's index entries.
JOURNAL_FILE = ".export.journal.jsonl"


def depth_path(sdir: Path, im_id: int) -> Path:
    """Depth image of image im_id of the scene folder sdir."""
    return sdir / "depth" / f"{im_id:06d}.png"


def mask_path(sdir: Path, im_id: int, gt_idx: int, visible: bool) -> Path:
    """BOP mask of instance gt_idx of image im_id (``mask_visib/`` when visible, else
    ``mask/``) of the scene folder sdir."""
    return sdir / ("mask_visib" if visible else "mask") / f"{im_id:06d}_{gt_idx:06d}.png"


def png16_bytes(image: np.ndarray) -> bytes:
    """PNG of a grey 16-bit image (BOP's depth images): every row unfiltered, one zlib stream.

    Args:
        image: shape (H, W), uint16.
    """
    img = np.asarray(image)
    if img.dtype != np.uint16 or img.ndim != 2 or img.size == 0:
        raise InvalidArgumentError(f"expected a non-empty (H, W) uint16 image, got {img.shape}")
    h, w = img.shape

    def chunk(kind: bytes, body: bytes) -> bytes:
        crc = struct.pack(">I", zlib.crc32(kind + body))
        return struct.pack(">I", len(body)) + kind + body + crc

    rows = np.zeros((h, 1 + 2 * w), np.uint8)  # leading 0: filter type None
    rows[:, 1:] = img.astype(">u2").view(np.uint8).reshape(h, 2 * w)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 16, 0, 0, 0, 0))
        + chunk(b"IDAT", zlib.compress(rows.tobytes(), PNG_LEVEL))
        + chunk(b"IEND", b"")
    )


def depth_to_png(depth_m: np.ndarray, depth_scale: float = DEPTH_SCALE) -> np.ndarray:
    """BOP depth values of a z-depth image: ``round(depth [mm] / depth_scale)``.

    Args:
        depth_m: depth along the optical axis, shape (H, W) [m].
        depth_scale: mm per value.

    Returns:
        Shape (H, W), uint16; 0 where the depth is not finite, not positive or out of range.
    """
    return depth_to_uint16(depth_m, depth_scale)


def export_protocol(
    objects: list[str],
    episodes: int,
    seed_start: int,
    tier: str,
    ground_truth: bool,
    sensor: str = "ideal",
    shifts: tuple[Shift, ...] = (),
) -> dict[str, Any]:
    """What defines an export's files: a folder holds one export, rewritten only by the same.
    The scene shifts are ``NAME:LEVEL`` items in `posegrasp.world.shifts.FACTORS` order."""
    return {
        "format": EXPORT_FORMAT,
        "version": EXPORT_VERSION,
        "tier": tier,
        "objects": list(objects),
        "episodes": episodes,
        "seed_start": seed_start,
        "ground_truth": ground_truth,
        "depth_scale": DEPTH_SCALE,
        "camera": C.HEAD_CAMERA,
        "width": EpisodeConfig.width,
        "height": EpisodeConfig.height,
        "sensor": sensor,
        "shifts": [str(s) for s in canonical(shifts)],
    }


def _describe(p: dict[str, Any]) -> str:
    objects = p.get("objects")
    objects = ",".join(objects) if isinstance(objects, list) else objects
    gt = "with" if p.get("ground_truth") else "without"
    return (
        f"tier {p.get('tier')}, objects {objects}, {p.get('episodes')} episodes from seed "
        f"{p.get('seed_start')}, {gt} ground truth, sensor {p.get('sensor', 'ideal')}"
        + (f", shifts {','.join(map(str, shifts))}" if (shifts := p.get("shifts")) else "")
    )


def check_out_folder(out: Path, protocol: dict[str, Any]) -> None:
    """Refuse a folder that holds anything but an export with the same protocol.

    Raises:
        InvalidArgumentError: one line saying what the folder holds.
    """
    out = Path(out)
    if not out.is_dir() or not any(out.iterdir()):
        return
    try:
        old = json.loads((out / MAP_FILE).read_text())
    except (OSError, ValueError, UnicodeDecodeError):
        raise InvalidArgumentError(
            f"--out {out} holds files but no readable {MAP_FILE}, so not a posegrasp BOP "
            "export; give an empty or new folder"
        ) from None
    same = isinstance(old, dict) and all(
        old.get(k, _PROTOCOL_BEFORE.get(k)) == v for k, v in protocol.items()
    )
    if not same:
        what = _describe(old) if isinstance(old, dict) else "an unreadable map"
        raise InvalidArgumentError(
            f"--out {out} holds another export ({what}); give the same arguments to rewrite "
            f"it, or an empty or new folder for {_describe(protocol)}"
        )


def _object_masks(ep: Episode) -> list[tuple[np.ndarray, np.ndarray]]:
    """(visible, full) masks inside the image of each object of an episode's scene, target
    first, shape (H, W) bool: its pixels in a segmentation render of the scene, and in one with
    every other geom hidden."""
    model, data = ep.scene.model, ep.scene.data
    seg = ep.renderer.segmentation(data, C.HEAD_CAMERA)
    groups = model.geom_group.copy()
    masks = []
    try:
        for placed in ep.scene.objects:
            visible = body_mask(model, seg, placed.body)
            own = model.geom_bodyid == model.body(placed.body).id
            model.geom_group[:] = np.where(own, groups, _HIDDEN_GROUP)
            alone = ep.renderer.segmentation(data, C.HEAD_CAMERA)
            masks.append((visible, body_mask(model, alone, placed.body) | visible))
    finally:
        model.geom_group[:] = groups
    return masks


def _gt_info(
    name: str, T_C_O: np.ndarray, K: np.ndarray, visible: np.ndarray, full: np.ndarray, depth
) -> dict[str, Any]:
    """One object's scene_gt_info entry (BOP scripts/calc_gt_info.py's keys and conventions)."""
    px_all, bbox_obj = full_silhouette(load_object(name).mesh, T_C_O, K, full)
    px_visib = int(visible.sum())
    return {
        "bbox_obj": bbox_obj if px_visib else _NO_BOX,
        "bbox_visib": bbox_xywh(visible) if px_visib else _NO_BOX,
        "px_count_all": int(px_all),
        "px_count_valid": int((full & (depth > 0)).sum()),
        "px_count_visib": px_visib,
        "visib_fract": px_visib / px_all if px_all else 0.0,
    }


def _export_image(
    ep: Episode, ground_truth: bool
) -> tuple[np.ndarray, np.ndarray, dict, list, list, list]:
    """RGB (H, W, 3) uint8, depth values (H, W) uint16, the scene_camera, scene_gt and
    scene_gt_info entries, and the (full, visible) masks (H, W) bool of each object of the
    head-camera view of an episode observing ``rgbd`` (no gt and masks without ground_truth)."""
    obs = ep.observe()
    assert obs.depth is not None, "an export observes rgbd"
    depth = depth_to_png(obs.depth)
    T_C_W = invert_transform(obs.T_world_cam)
    camera = {
        "cam_K": [float(x) for x in obs.K.reshape(-1)],
        "depth_scale": DEPTH_SCALE,
        "cam_R_w2c": [float(x) for x in T_C_W[:3, :3].reshape(-1)],
        "cam_t_w2c": [float(x) * MM_PER_M for x in T_C_W[:3, 3]],
    }
    gts, infos, masks = [], [], []
    if ground_truth:
        poses = [(ep.object, ep.T_C_O_true), *ep.true_neighbours()]
        for (name, T), (visible, full) in zip(poses, _object_masks(ep), strict=True):
            gts.append({**pose_to_bop(T), "obj_id": obj_id(name)})
            infos.append(_gt_info(name, T, obs.K, visible, full, depth))
            masks.append((full, visible))
    return obs.rgb, depth, camera, gts, infos, masks


def _write_index(
    out: Path, scenes: dict[int, dict[str, dict[str, Any]]], images: list[dict], gt: bool
) -> None:
    """The per-scene JSON files (scene_camera, and with gt scene_gt and scene_gt_info),
    test_targets_bop19.json, test_targets_bop24.json and camera.json of an export's images."""
    for scene_id, files in scenes.items():
        for kind, content in files.items():
            if gt or kind == "scene_camera":
                write_json(scene_dir(out, SPLIT, scene_id) / f"{kind}.json", content)
    targets = [
        {
            "im_id": im["im_id"],
            "inst_count": 1,
            "obj_id": obj_id(im["object"]),
            "scene_id": im["scene_id"],
        }
        for im in images
    ]
    targets.sort(key=lambda t: (t["scene_id"], t["im_id"]))
    write_json(out / "test_targets_bop19.json", targets)
    images24 = [{"im_id": t["im_id"], "scene_id": t["scene_id"]} for t in targets]
    write_json(out / "test_targets_bop24.json", images24)
    first = next(iter(scenes.values()))["scene_camera"]
    K = np.reshape(next(iter(first.values()))["cam_K"], (3, 3))
    camera = {
        "cx": float(K[0, 2]),
        "cy": float(K[1, 2]),
        "fx": float(K[0, 0]),
        "fy": float(K[1, 1]),
        "width": EpisodeConfig.width,
        "height": EpisodeConfig.height,
        "depth_scale": DEPTH_SCALE,
    }
    write_json(out / "camera.json", camera)


def _copy_models(out: Path) -> None:
    """``models_eval/``: the files of ``models/`` (BOP evaluates on uniformly resampled
    models; the toolkit reads any mesh there)."""
    for path in sorted((out / "models").iterdir()):
        write_bytes(out / "models_eval" / path.name, path.read_bytes())


def export_bop(
    out: Path,
    objects: list[str],
    episodes: int,
    seed_start: int = C.EVAL_SEED_BASE,
    tier: str = DEFAULT_TIER,
    ground_truth: bool = True,
    progress: bool = True,
    sensor: str = "ideal",
    shifts: tuple[Shift, ...] = (),
) -> dict[str, Any]:
    """Write the head-camera views of the episodes objects x range(episodes) as a BOP dataset.

    Args:
        out: the dataset folder (created; an existing one must hold the same export).
        objects: the target classes; episode i of object X is scene seed ``seed_start + i``.
        episodes: episodes per object.
        seed_start: the first scene seed.
        tier: the scene tier (`posegrasp.world.tiers.TIERS`).
        ground_truth: write scene_gt.json, scene_gt_info.json and the masks.
        progress: show a progress bar.
        sensor: the head camera's sensor model (`posegrasp.world.sensors.SENSOR_NAMES`) whose
            colour and depth images are written.
        shifts: the scene shifts the scenes are seen under (`posegrasp.world.shifts`).

    Returns:
        The map file's content (`sim.evaluation.bop_results.MAP_FILE`).

    Raises:
        InvalidArgumentError: out holds other files or another export; a bad argument.
        UnknownNameError: a sensor not in `posegrasp.world.sensors.SENSOR_NAMES`.
    """
    scene = SceneConfig(shifts=canonical(shifts))
    cfg = EpisodeConfig(scene=scene, tier=check_tier(tier), obs_mode="rgbd", sensor=sensor)
    _check_episodes(objects, episodes, seed_start)
    out = Path(out)
    protocol = export_protocol(objects, episodes, seed_start, tier, ground_truth, sensor, shifts)
    check_out_folder(out, protocol)
    info = _map_info(protocol, objects, episodes, seed_start, tier)
    # The images' index entries, kept as each image's files are written: a stopped export
    # resumes after the last image it finished.
    journal = Journal(out / JOURNAL_FILE, "export_bop", protocol)
    held = {int(u["key"]): u["result"] for u in journal.start(resume=journal.path.is_file())}
    try:
        write_json(out / MAP_FILE, info)  # first: an interrupted export is known by it
        write_models(out, [*OBJECT_NAMES, *(o for o in objects if o not in OBJECT_NAMES)])
        _copy_models(out)
        scenes: dict[int, dict[str, dict[str, Any]]] = {}
        bar = progress_bar(info["images"], desc="images", unit="image", disable=not progress)
        for key, image in enumerate(bar):
            if key not in held:
                held[key] = _write_image(out, image, cfg, ground_truth)
                journal.append({"key": key, "result": held[key]})
            image["table_top_z"] = held[key]["table_top_z"]
            files = scenes.setdefault(image["scene_id"], {})
            for name in ("scene_camera", "scene_gt", "scene_gt_info"):
                files.setdefault(name, {})[str(IM_ID)] = held[key][name]
        _write_index(out, scenes, info["images"], ground_truth)
        info["complete"] = True
        write_json(out / MAP_FILE, info)
    except Interrupted:
        total = len(info["images"])
        hint = resume_hint(journal.path, len(held), total, flag=None)
        raise Interrupted(hint, journal.path, len(held), total) from None
    finally:
        journal.close()
    journal.finish()
    return info


def _check_episodes(objects: list[str], episodes: int, seed_start: int) -> None:
    """Refuse objects that are not distinct built-in or user objects (at least one), an episode
    count out of range and seeds that would run past the last one.

    Raises:
        InvalidArgumentError, UnknownNameError: in one line.
    """
    if not objects or len(set(objects)) != len(objects):
        raise InvalidArgumentError(f"objects must be distinct and at least one, got {objects}")
    for o in objects:
        obj_id(o)
    check_int(episodes, 1, MAX_EPISODES, "episodes")
    check_seed(seed_start, "seed start", episodes)


def _map_info(
    protocol: dict[str, Any], objects: list[str], episodes: int, seed_start: int, tier: str
) -> dict[str, Any]:
    """The map file of an export under way: its protocol, how it was made and every image's
    scene, object and seed (``complete`` False until the last file is written)."""
    jobs = [(o, seed_start + i) for o in objects for i in range(episodes)]
    ids = scene_ids(tier, jobs)
    return {
        **protocol,
        "complete": False,
        "commit": git_commit(),
        "contract_version": CONTRACT_VERSION,
        "execution": execution_settings(),
        "layout": "one scene per episode, its one image im_id 0; scene_id = "
        "sim.evaluation.bop_results.scene_ids(tier, object, seed); scene_gt: the target first, "
        "then the other objects; table_top_z: the table top's height in the world frame [m]",
        "images": [
            {"scene_id": ids[(o, seed)], "im_id": IM_ID, "object": o, "seed": seed}
            for o, seed in jobs
        ],
    }


def _write_image(
    out: Path, image: dict[str, Any], cfg: EpisodeConfig, ground_truth: bool
) -> dict[str, Any]:
    """Render one episode's image and write its files (colour, depth, masks); returns its
    entries of the scene files and its table height, as JSON reads them back."""
    scene_id, im_id = image["scene_id"], IM_ID
    ep = Episode(image["object"], image["seed"], cfg)
    try:
        rgb, depth, camera, gts, infos, masks = _export_image(ep, ground_truth)
        table_top_z = float(ep.scene.table_top_z)
    finally:
        ep.close()
    sdir = scene_dir(out, SPLIT, scene_id)
    write_png(rgb_path(sdir, im_id), rgb)
    write_bytes(depth_path(sdir, im_id), png16_bytes(depth))
    for gt_idx, (full, visible) in enumerate(masks):
        write_png(mask_path(sdir, im_id, gt_idx, False), full.astype(np.uint8) * 255)
        write_png(mask_path(sdir, im_id, gt_idx, True), visible.astype(np.uint8) * 255)
    entry = {
        "scene_camera": camera,
        "scene_gt": gts,
        "scene_gt_info": infos,
        "table_top_z": table_top_z,
    }
    return json.loads(json.dumps(entry))  # as a resumed export reads it back


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(prog="python -m sim.export_bop", description=__doc__.split("\n")[0])
    p.add_argument(
        "--tier",
        default=DEFAULT_TIER,
        type=arg(check_tier),
        help=f"scene tier, one of: {', '.join(TIERS)} (default {DEFAULT_TIER})",
    )
    p.add_argument(
        "--objects",
        default=list(OBJECT_NAMES),
        type=arg(check_objects, "--objects"),
        help=f"'all' (default: {', '.join(OBJECT_NAMES)}) or a comma list of objects, built-in or "
        "user objects",
    )
    p.add_argument(
        "--episodes",
        type=arg(check_int, 1, MAX_EPISODES, "--episodes", base=int),
        default=50,
        help=f"episodes per object, 1..{MAX_EPISODES} (default 50)",
    )
    p.add_argument(
        "--seed-start",
        type=arg(check_seed, "--seed-start", base=int),
        default=C.EVAL_SEED_BASE,
        help="first scene seed, as sim.evaluate's (default: its held-out scenes)",
    )
    add_sensor_argument(p)
    add_shift_argument(p)
    add_out_argument(p, "the BOP dataset and its map file", required=True)
    p.add_argument(
        "--no-gt",
        action="store_true",
        help="leave out scene_gt.json, scene_gt_info.json, mask/ and mask_visib/, as BOP's "
        "public test sets do",
    )
    args = p.parse_args(argv)
    check_seed(args.seed_start, "--seed-start", args.episodes)
    protocol = export_protocol(
        args.objects,
        args.episodes,
        args.seed_start,
        args.tier,
        not args.no_gt,
        args.sensor,
        args.shift,
    )
    check_out_folder(args.out, protocol)  # before any rendering
    setup_rendering()
    info = export_bop(
        args.out,
        args.objects,
        args.episodes,
        args.seed_start,
        args.tier,
        not args.no_gt,
        sensor=args.sensor,
        shifts=args.shift,
    )
    n = len(info["images"])
    print(
        f"wrote {n} image(s) to {args.out}: {_describe(protocol)} "
        f"(seeds {args.seed_start}..{args.seed_start + args.episodes - 1})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
