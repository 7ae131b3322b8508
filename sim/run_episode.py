"""Run one grasp episode and print what happened.

python -m sim.run_episode --object phone [--seed N] [--estimator hybrid] [--tier T]
    [--noise SIGMAS] [--obs-mode rgbd] [--sensor NAME] [--json PATH] [--out DIR]

The summary names the sensor the head camera observed through. ``--out DIR`` writes what the
estimator was shown and what the grasp did: the head image with the true and estimated poses
drawn on it, the head camera's depth image as the episode's sensor produced it (what the
estimator saw with ``--obs-mode rgbd``; with ``rgb`` it was not given it), the grasp as a GIF and
a strip of its stages. A depth sensor with an RGB-only observation prints one note: its depth
goes unused.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

import mujoco
import numpy as np

from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    add_out_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_choice, check_seed
from posegrasp.world import constants as C
from posegrasp.world.camera import CameraRenderer, RenderOptions, far_plane
from posegrasp.world.objects import object_names
from posegrasp.world.tiers import DEFAULT_TIER, TIERS, add_pool_argument, check_tier
from sim.episodes.pose_noise import parse_noise
from sim.episodes.registry import (
    add_estimator_arguments,
    add_obs_mode_argument,
    add_sensor_argument,
    add_shift_argument,
    add_task_argument,
    check_depth,
    depth_unused_note,
    make_estimator,
)

if TYPE_CHECKING:
    from posegrasp.world.scene import Scene


def _rpy_deg(R: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw (XYZ extrinsic) in degrees, for printing only."""
    pitch = np.arcsin(-np.clip(R[2, 0], -1, 1))
    roll = np.arctan2(R[2, 1], R[2, 2])
    yaw = np.arctan2(R[1, 0], R[0, 0])
    return np.rad2deg([roll, pitch, yaw])


def _fmt_pose(T: np.ndarray | None) -> str:
    if T is None:
        return "none"
    t = T[:3, 3] * 1000
    r = _rpy_deg(T[:3, :3])
    return (
        f"t = ({t[0]:7.1f}, {t[1]:7.1f}, {t[2]:7.1f}) mm   "
        f"rpy = ({r[0]:6.1f}, {r[1]:6.1f}, {r[2]:6.1f}) deg"
    )


def summary(result) -> str:
    """A readable multi-line summary of an EpisodeResult."""
    lines = [
        f"episode  object={result.object}  seed={result.seed}  estimator={result.estimator}  "
        f"tier={result.tier}  sensor={result.sensor}",
        f"  true pose (camera frame)      {_fmt_pose(result.T_C_O_true)}",
        f"  estimated pose (camera frame) {_fmt_pose(result.T_C_O_est)}",
    ]
    info = result.estimate_info
    if info:
        if info.get("detected"):
            box, named = info.get("box_xyxy"), info.get("class", result.object)
            lines.append(
                f"  detection   {named}  score {info['score']:.3f}"
                + ("" if box is None else "  box (" + ", ".join(f"{v:.0f}" for v in box) + ") px")
                + f"  {info['detections']} detection(s)"
                + (" of the class" if named == result.object else "")
            )
        elif "detected" in info:
            lines.append(f"  detection   no {result.object} detected")
        sup = info.get("support")
        if sup and sup.get("source") == "neighbours" and "resting_pose" not in sup:
            z = sup.get("surface_z")
            lines.append(
                f"  support     {len(sup['neighbours'])} neighbour(s) verified; their surface "
                + ("none found" if z is None else f"at z = {z:.3f} m")
                + f", the target's own at z = {sup['own_z']:.3f} m: pose kept"
            )
        elif sup:
            lines.append(
                f"  table prior resting pose {sup['resting_pose']}  tilt removed "
                f"{sup['tilt_deg']:.1f} deg  moved {sup['shift_m'] * 1000:+.1f} mm along the ray  "
                f"(applied: {', '.join(sup['applied']) or 'nothing'})"
            )
            if "mask_iou_after" in sup:
                lines.append(
                    f"  mask fit    yaw {sup['mask_yaw_deg']:+.1f} deg, shift "
                    + ", ".join(f"{v * 1000:+.0f}" for v in sup["mask_shift_m"])
                    + f" mm  silhouette IoU {sup['mask_iou_before']:.3f} -> "
                    f"{sup['mask_iou_after']:.3f}"
                )
    e = result.pose_error
    if e is not None:
        lines.append(
            f"  pose error  translation {e['translation_m'] * 1000:.1f} mm "
            f"({e['translation_pct']:.2f} %)  rotation {e['rotation_deg']:.2f} deg  "
            f"ADD {e['add_m'] * 1000:.1f} mm ({e['add_rel_diameter']:.3f} d)  "
            f"ADD-S {e['adi_m'] * 1000:.1f} mm"
        )
        if "ray_m" in e:
            lines.append(
                f"  components  along ray {e['ray_m'] * 1000:.1f} mm  across "
                f"{e['lateral_m'] * 1000:.1f} mm  in-plane {e['inplane_deg']:.2f} deg  "
                f"out-of-plane {e['outplane_deg']:.2f} deg"
            )
    outcome = "SUCCESS" if result.success else f"FAILURE ({result.failure_reason})"
    lines.append(
        f"  outcome     {outcome}   object lifted {result.lift_height * 1000:.0f} mm"
        + (f"   grasped part: {result.grasp_part}" if result.grasp_part else "")
    )
    if result.place is not None:
        goal, pe = result.place["goal"], result.place["errors"]
        lines.append(
            f"  place       goal {goal['moved_m'] * 1000:.0f} mm away, turned "
            f"{goal['turned_deg']:+.0f} deg; rests {pe['translation_m'] * 1000:.1f} mm and "
            f"{pe['rotation_deg']:.1f} deg from it (tilted {pe['tilt_deg']:.1f} deg)"
        )
    for note in result.notes:
        lines.append(f"  note        {note}")
    lines.extend(_timing_lines(result.timings_ms, info.get("timings_ms") if info else None))
    return "\n".join(lines)


def _timing_lines(timings: dict[str, float], estimator: dict[str, float] | None) -> list[str]:
    """The episode's wall times [ms], then the estimator's own stages as parts of its estimate.

    The episode's ``total`` is the sum of its stages (``ik`` is part of ``plan`` and printed as
    such); the estimator's ``total`` (its networks' subtotal) is left out, so that no line holds
    two totals of different things.
    """
    ik = f" (ik {timings['ik']:.0f} ms)" if "ik" in timings else ""
    shown = [
        f"{k} {v:.0f} ms" + (ik if k == "plan" else "") for k, v in timings.items() if k != "ik"
    ]
    lines = ["  timings     " + "  ".join(shown)]
    parts = {k: v for k, v in (estimator or {}).items() if k != "total"}
    if parts:
        whole = f" of the estimate's {timings['estimate']:.0f} ms" if "estimate" in timings else ""
        each = "  ".join(f"{k} {v:.1f} ms" for k, v in parts.items())
        lines.append(f"  estimator   {each}  (parts{whole})")
    return lines


#: The stages of a grasp as the pictures name them, in order: the transit to the pre-grasp, the
#: approach to the grasp, the fingers closing, the lift and the hold.
STAGES = ("transit", "approach", "close", "lift", "hold")
#: The framed points fill at most this share of a close-up's height.
CLOSE_UP_FILL = 0.5
#: Smallest region a close-up shows [m] (a small object is not blown up past it).
CLOSE_UP_MIN_M = 0.3
#: Colours of the outcome band (RGB): held, failed.
HELD_RGB = (40, 150, 60)
FAILED_RGB = (190, 40, 40)


@dataclass(frozen=True)
class Snapshot:
    """The state of one film frame: enough to draw it again afterwards.

    Attributes:
        qpos: joint positions, (nq,).
        ctrl: actuator commands, (nu,).
    """

    qpos: np.ndarray
    ctrl: np.ndarray


class Film:
    """The recorder of a grasp (`Episode.run`'s ``recorder``): a snapshot of the state per
    recorded step; the frames are drawn afterwards (`render`), from any camera."""

    def __init__(self) -> None:
        self.snapshots: list[Snapshot] = []

    def __call__(self, scene: Scene) -> Snapshot:
        snap = Snapshot(scene.data.qpos.copy(), scene.data.ctrl.copy())
        self.snapshots.append(snap)
        return snap


def finger_actuators(model: mujoco.MjModel) -> np.ndarray:
    """The ids of the finger actuators (those of `C.FINGER_JOINTS`)."""
    return np.array([model.actuator("act_" + j.removeprefix(C.PREFIX)).id for j in C.FINGER_JOINTS])


def _runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) of each run of True in a 1-D bool array."""
    edges = np.diff(np.r_[0, flags.astype(np.int8), 0])
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True))


def label_stages(ctrl: np.ndarray, fingers: np.ndarray) -> list[str]:
    """The stage (`STAGES`) of each recorded frame, from the commands alone.

    The executor opens the fingers and moves the arm through the transit, pauses at the
    pre-grasp, moves in along the approach and pauses again; then it commands the fingers shut
    (close) with the arm still, moves the arm up (lift) and keeps still (hold). So: the frames
    after the first with the fingers commanded shut are close, lift and hold, split where the arm's
    commands start and stop changing; before it, the approach starts after the last pause but one
    (the pre-grasp's), or is the last pause when the approach had no move of its own.

    Args:
        ctrl: the actuator commands of each frame, (N, nu).
        fingers: the finger actuators' ids (`finger_actuators`).

    Returns:
        N stage names.
    """
    n = len(ctrl)
    if n == 0:
        return []
    shut = ctrl[:, fingers].mean(1) < C.FINGER_TRAVEL / 2
    arm = np.delete(ctrl, fingers, axis=1)
    still = np.r_[False, np.all(np.diff(arm, axis=0) == 0, axis=1)]
    c = int(np.argmax(shut)) if shut.any() else n
    labels = ["transit"] * n
    pauses = _runs(still[:c])
    if pauses:
        start = pauses[-2][1] if len(pauses) > 1 else pauses[-1][0]
        labels[start:c] = ["approach"] * (c - start)
    moving = np.flatnonzero(~still[c:]) + c
    lift = int(moving[0]) if len(moving) else n
    after = np.flatnonzero(still[lift:]) + lift
    hold = int(after[0]) if len(after) else n
    labels[c:lift] = ["close"] * (lift - c)
    labels[lift:hold] = ["lift"] * (hold - lift)
    labels[hold:] = ["hold"] * (n - hold)
    return labels


def strip_frames(stages: list[str]) -> list[int]:
    """One frame per stage that happened, in order: the last of each stage (what the stage
    reached), the middle one of the lift."""
    picks = []
    for stage in STAGES:
        idx = [i for i, s in enumerate(stages) if s == stage]
        if idx:
            picks.append(idx[len(idx) // 2] if stage == "lift" else idx[-1])
    return picks


def close_up_pose(
    points: np.ndarray, forward: np.ndarray, fovy_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """A camera looking along `forward` at the centre of `points`, near enough that they fill
    about `CLOSE_UP_FILL` of its height.

    Args:
        points: the world points to frame, (k, 3) [m].
        forward: the viewing direction in the world frame, (3,); its horizontal part is kept
            and it keeps its elevation.
        fovy_deg: the camera's vertical field of view [deg].

    Returns:
        The camera's position (3,) [m] and orientation R_world_cam (3, 3), MuJoCo's camera frame
        (x right, y up, looking along -z).
    """
    lo, hi = points.min(0), points.max(0)
    centre = (lo + hi) / 2
    radius = max(CLOSE_UP_MIN_M / 2, float(np.linalg.norm(points - centre, axis=1).max()))
    f = forward / np.linalg.norm(forward)
    dist = radius / (CLOSE_UP_FILL * math.tan(math.radians(fovy_deg) / 2)) + radius
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, f)
    return centre - dist * f, np.stack([right, up, -f], axis=1)


def render_frames(
    model: mujoco.MjModel,
    snapshots: list[Snapshot],
    camera: str,
    pose: tuple[np.ndarray, np.ndarray] | None = None,
    shadows: bool = False,
) -> list[np.ndarray]:
    """Draw snapshots from a camera of the model, or from that camera moved to `pose`
    (position, R_world_cam as `close_up_pose` gives), at `C.EXTERNAL_SIZE`.

    Returns:
        One RGB image (H, W, 3) uint8 per snapshot.
    """
    data = mujoco.MjData(model)
    cid = model.camera(camera).id
    frames = []
    with CameraRenderer(model, *C.EXTERNAL_SIZE, RenderOptions(shadows=shadows)) as renderer:
        for snap in snapshots:
            data.qpos[:] = snap.qpos
            mujoco.mj_kinematics(model, data)
            mujoco.mj_camlight(model, data)
            if pose is not None:
                data.cam_xpos[cid] = pose[0]
                data.cam_xmat[cid] = pose[1].reshape(-1)
            frames.append(renderer.rgb(data, cid))
    return frames


def _band(img: np.ndarray, text: str, top: bool, rgb: tuple[int, int, int]) -> None:
    """Write `text` in white on a band of colour `rgb` along the top or bottom of `img`."""
    import cv2

    h = 30
    rows = slice(0, h) if top else slice(img.shape[0] - h, img.shape[0])
    img[rows] = (0.35 * img[rows] + 0.65 * np.array(rgb)).astype(np.uint8)
    y = 21 if top else img.shape[0] - 9
    cv2.putText(img, text, (10, y), cv2.FONT_HERSHEY_SIMPLEX, 0.65, (255, 255, 255), 2, cv2.LINE_AA)


def outcome_text(result) -> str:
    """The outcome as the pictures write it: ``held, lifted N mm`` or ``failed: reason``."""
    if result.success:
        return f"held, lifted {result.lift_height * 1000:.0f} mm"
    return f"failed: {result.failure_reason}"


def label_frame(img: np.ndarray, stage: str, outcome: str | None = None, ok: bool = True):
    """A copy of `img` with its stage written on top and, when given, the outcome below."""
    out = img.copy()
    number = STAGES.index(stage) + 1 if stage in STAGES else 0
    _band(out, f"{number}. {stage}" if number else stage, True, (30, 30, 30))
    if outcome is not None:
        _band(out, outcome, False, HELD_RGB if ok else FAILED_RGB)
    return out


def grasp_strip(model: mujoco.MjModel, film: Film, target: str, result) -> np.ndarray | None:
    """The grasp in one picture: a close-up of the last frame of each stage, side by side, each
    labelled with its stage, the last with the outcome; None when nothing was executed.

    The close-up is the external camera moved in along its own viewing direction to frame the
    target where it lay and where it ended, and the gripper at the pre-grasp and at the end.
    """
    if not film.snapshots:
        return None
    stages = label_stages(np.array([s.ctrl for s in film.snapshots]), finger_actuators(model))
    picks = strip_frames(stages)
    data = mujoco.MjData(model)
    body, gripper = model.body(target).id, model.body(C.GRIPPER_BODY).id
    points = []
    pregrasp = [i for i, s in enumerate(stages) if s == "transit"][-1:] or [0]
    for i, with_gripper in ((0, False), (pregrasp[0], True), (len(stages) - 1, True)):
        data.qpos[:] = film.snapshots[i].qpos
        mujoco.mj_kinematics(model, data)
        points.append(data.xpos[body].copy())
        if with_gripper:
            points.append(data.xpos[gripper].copy())
    cid = model.camera(C.EXTERNAL_CAMERA).id
    mujoco.mj_camlight(model, data)
    forward = -data.cam_xmat[cid].reshape(3, 3)[:, 2]
    pose = close_up_pose(np.array(points), forward, float(model.cam_fovy[cid]))
    frames = render_frames(
        model, [film.snapshots[i] for i in picks], C.EXTERNAL_CAMERA, pose, shadows=True
    )
    last = len(picks) - 1
    labelled = [
        label_frame(fr, stages[i], outcome_text(result) if k == last else None, result.success)
        for k, (fr, i) in enumerate(zip(frames, picks, strict=True))
    ]
    return np.concatenate(labelled, axis=1)


def _run(
    obj: str,
    seed: int,
    estimator,
    save: Path | None,
    tier: str = DEFAULT_TIER,
    log: TextIO | None = None,
    obs_mode: str = "rgb",
    pool: tuple[str, ...] = (),
    sensor: str = "ideal",
    task: str = "lift",
    shifts: tuple = (),
):
    from posegrasp.world.scene import SceneConfig
    from sim.episodes.episode import Episode, EpisodeConfig

    cfg = EpisodeConfig(
        scene=SceneConfig(distractor_pool=pool, shifts=shifts),
        tier=tier,
        obs_mode=obs_mode,
        sensor=sensor,
        task=task,
    )
    ep = Episode(obj, seed, cfg)
    try:
        film = Film() if save is not None else None
        # The depth the sensor produces, rendered before the episode moves anything; with rgbd
        # the observation carries the same image.
        depth = sensor_depth(ep) if save is not None and obs_mode != "rgbd" else None
        obs, result = ep.run(estimator, film)
        if save is not None and film is not None:
            seen = obs.depth if depth is None else depth
            assert seen is not None, "rgbd observes depth; rgb renders it above"
            _save(save, obs, seen, ep, result, film, log or sys.stdout)
        return result
    finally:
        ep.close()


def sensor_depth(ep) -> np.ndarray:
    """The head camera's depth image as the episode's sensor produces it in the current state
    (called before `Episode.run`, the state `Episode.observe` sees): the same image, noise
    included, that ``obs_mode="rgbd"`` hands the estimator.

    Returns:
        Depth (H, W) float32 [m] along the optical axis; 0 where the sensor returns nothing.
    """
    depth = ep.renderer.depth(ep.scene.data, C.HEAD_CAMERA)
    if ep.sensor.name == "ideal":
        return depth
    rgb = ep.renderer.rgb(ep.scene.data, C.HEAD_CAMERA)
    return ep.sensor.apply(rgb, depth, ep.K, ep.seed)[1]


def depth_names(sensor: str) -> tuple[str, str]:
    """File names of the depth images `--out` writes: the metric PNG and its coloured view,
    both named after the sensor that produced them."""
    return f"depth_{sensor}.png", f"depth_{sensor}_view.png"


def depth_caption(sensor: str, seen: bool) -> str:
    """What a depth image shows: whose depth, and whether the estimator was given it."""
    given = "seen by the estimator" if seen else "not given to the estimator (--obs-mode rgb)"
    return f"depth of sensor {sensor}, {given}"


def _save(folder: Path, obs, depth: np.ndarray, ep, result, film: Film, log: TextIO) -> None:
    """Write the head image, the sensor's depth image (`depth_names`) and, when a grasp was
    executed, the grasp's GIF and strip into `folder`; say on `log` what was written."""
    import cv2
    from PIL import Image

    from perception.overlay import draw_estimate
    from sim.render_scene import write_depth

    folder.mkdir(parents=True, exist_ok=True)
    model = ep.scene.model
    mesh = ep.scene.target.model.mesh
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    img = draw_estimate(obs.rgb, obs.K, result.T_C_O_true, result.T_C_O_est, v, f)
    cv2.imwrite(str(folder / "head.png"), img[..., ::-1])
    sensor = ep.sensor.name
    names = depth_names(sensor)
    caption = depth_caption(sensor, obs.depth is not None)
    write_depth((folder / names[0], folder / names[1]), depth, caption, far_plane(model))
    depth_line = (
        f"wrote {folder / names[0]} (16-bit, millimetres, 0: no reading) and "
        f"{folder / names[1]}: the {caption}"
    )
    strip = grasp_strip(model, film, ep.scene.target.body, result)
    if strip is None:
        print(
            f"wrote {folder / 'head.png'}; no grasp was executed ({outcome_text(result)}), so no "
            "grasp.gif or grasp_strip.png",
            file=log,
        )
        print(depth_line, file=log)
        return
    cv2.imwrite(str(folder / "grasp_strip.png"), strip[..., ::-1])
    stages = label_stages(np.array([s.ctrl for s in film.snapshots]), finger_actuators(model))
    wide = render_frames(model, film.snapshots, C.EXTERNAL_CAMERA)
    n = len(wide)
    frames = [
        Image.fromarray(
            label_frame(fr, st, outcome_text(result) if i == n - 1 else None, result.success)
        )
        for i, (fr, st) in enumerate(zip(wide, stages, strict=True))
    ]
    frames[0].save(
        folder / "grasp.gif",
        save_all=True,
        append_images=frames[1:],
        duration=[100] * (n - 1) + [2000],
        loop=0,
    )
    print(
        f"wrote {folder / 'head.png'}, {folder / 'grasp.gif'} ({n} frames) and "
        f"{folder / 'grasp_strip.png'}",
        file=log,
    )
    print(depth_line, file=log)


def _parser() -> ArgumentParser:
    """The command line: the episode, the estimator, what it observes and the outputs."""
    p = ArgumentParser(prog="python -m sim.run_episode", description=__doc__.split("\n")[0])
    p.add_argument(
        "--object",
        default="phone",
        type=arg(check_choice, object_names(), "object"),
        help=f"one of: {', '.join(object_names())} (user objects: python -m sim.add_object)",
    )
    p.add_argument(
        "--seed",
        type=arg(check_seed, "--seed", base=int),
        default=C.EVAL_SEED_BASE,
        help=f"scene seed in 0..2**32-1 (default {C.EVAL_SEED_BASE}: seeds below "
        f"{C.DATA_SEED_LIMIT} are the data generator's, i.e. scenes the networks may have been "
        "trained on)",
    )
    add_estimator_arguments(p)
    add_obs_mode_argument(p)
    add_sensor_argument(p)
    add_task_argument(p)
    add_shift_argument(p)
    p.add_argument(
        "--tier",
        default=DEFAULT_TIER,
        type=arg(check_tier),
        help=f"scene tier, one of: {', '.join(TIERS)}",
    )
    add_pool_argument(p)
    add_json_argument(p, "the episode")
    add_out_argument(
        p,
        "head.png (the head image with the true and estimated poses drawn on it), "
        "depth_SENSOR.png (the head camera's depth as the sensor produced it, what the estimator "
        "saw with --obs-mode rgbd: 16-bit, millimetres, 0 where there is no reading) with "
        "depth_SENSOR_view.png (the same in colour, with its scale), grasp.gif (the grasp from "
        "the external camera) and grasp_strip.png (a close-up of each stage, the outcome on the "
        "last)",
        aliases=("--save",),
    )
    return p


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    args = _parser().parse_args(argv)
    check_depth(args.estimator, args.obs_mode)
    setup_rendering()
    log = summary_stream(args.json)
    note = depth_unused_note(args.obs_mode, args.sensor)
    if note is not None:
        print(note, file=sys.stderr)
    noise = None if args.noise is None else parse_noise(args.noise)
    estimator = make_estimator(args.estimator, noise)
    result = _run(
        args.object,
        args.seed,
        estimator,
        args.out,
        args.tier,
        log,
        args.obs_mode,
        args.pool,
        args.sensor,
        args.task,
        args.shift,
    )
    if args.seed < C.DATA_SEED_LIMIT and args.estimator.startswith("hybrid"):
        print(
            f"note: seed {args.seed} is in the data generator's range (< {C.DATA_SEED_LIMIT}); "
            "the networks may have seen this scene in training",
            file=sys.stderr,
        )
    print(summary(result), file=log)
    if args.json is not None:
        write_json(args.json, result.to_json())
    return 0


if __name__ == "__main__":
    sys.exit(main())
