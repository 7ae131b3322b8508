"""Run one grasp episode and print what happened.

python -m sim.run_episode --object phone [--seed N] [--estimator hybrid] [--tier T]
    [--noise SIGMAS] [--json PATH] [--out DIR]
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TextIO

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
from posegrasp.world.camera import external_renderer
from posegrasp.world.objects import object_names
from posegrasp.world.tiers import DEFAULT_TIER, TIERS, add_pool_argument, check_tier
from sim.estimators import add_estimator_arguments, add_obs_mode_argument, make_estimator
from sim.pose_noise import parse_noise


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
        f"tier={result.tier}",
        f"  true pose (camera frame)      {_fmt_pose(result.T_C_O_true)}",
        f"  estimated pose (camera frame) {_fmt_pose(result.T_C_O_est)}",
    ]
    info = result.estimate_info
    if info:
        if info.get("detected"):
            lines.append(
                f"  detection   {info['class']}  score {info['score']:.3f}  box ("
                + ", ".join(f"{v:.0f}" for v in info["box_xyxy"])
                + f") px  {info['detections']} detection(s) of the class"
            )
        elif "detected" in info:
            lines.append(f"  detection   no {result.object} detected")
        sup = info.get("support")
        if sup:
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
    for note in result.notes:
        lines.append(f"  note        {note}")
    t = result.timings_ms
    lines.append("  timings     " + "  ".join(f"{k} {v:.0f} ms" for k, v in t.items()))
    st = info.get("timings_ms") if info else None
    if st:
        lines.append("  estimator   " + "  ".join(f"{k} {v:.1f} ms" for k, v in st.items()))
    return "\n".join(lines)


def _run(
    obj: str,
    seed: int,
    estimator,
    save: Path | None,
    tier: str = DEFAULT_TIER,
    log: TextIO | None = None,
    obs_mode: str = "rgb",
    pool: tuple[str, ...] = (),
):
    from posegrasp.world.scene import SceneConfig
    from sim.episode import Episode, EpisodeConfig

    cfg = EpisodeConfig(scene=SceneConfig(distractor_pool=pool), tier=tier, obs_mode=obs_mode)
    ep = Episode(obj, seed, cfg)
    external = None
    try:
        recorder = None
        if save is not None:
            external = external_renderer(ep.scene.model)
            recorder = lambda scene: external.rgb(scene.data, C.EXTERNAL_CAMERA)  # noqa: E731
        obs, result = ep.run(estimator, recorder)
        if save is not None:
            _save(save, obs, result.T_C_O_est, ep, result, log or sys.stdout)
        return result
    finally:
        ep.close()
        if external is not None:
            external.close()


def _save(folder: Path, obs, est, ep, result, log: TextIO) -> None:
    import cv2
    from PIL import Image

    from perception.overlay import draw_estimate

    folder.mkdir(parents=True, exist_ok=True)
    mesh = ep.scene.target.model.mesh
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    img = draw_estimate(obs.rgb, obs.K, result.T_C_O_true, est, v, f)
    cv2.imwrite(str(folder / "head.png"), img[..., ::-1])
    frames = [Image.fromarray(fr) for fr in ep.frames]
    if frames:
        frames[0].save(
            folder / "grasp.gif", save_all=True, append_images=frames[1:], duration=100, loop=0
        )
        # Five frames from approach to hold, side by side.
        pick = np.linspace(0, len(ep.frames) - 1, 5).round().astype(int)
        cv2.imwrite(
            str(folder / "grasp_strip.png"),
            np.concatenate([ep.frames[i] for i in pick], axis=1)[..., ::-1],
        )
    print(
        f"wrote {folder / 'head.png'}, {folder / 'grasp.gif'} ({len(frames)} frames) and "
        f"{folder / 'grasp_strip.png'}",
        file=log,
    )


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
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
        "head.png (the head image with the true and estimated poses drawn on it), grasp.gif and "
        "grasp_strip.png (the grasp from the external camera)",
        aliases=("--save",),
    )
    args = p.parse_args(argv)
    setup_rendering()
    log = summary_stream(args.json)
    noise = None if args.noise is None else parse_noise(args.noise)
    estimator = make_estimator(args.estimator, noise)
    result = _run(
        args.object, args.seed, estimator, args.out, args.tier, log, args.obs_mode, args.pool
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
