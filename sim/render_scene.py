"""Render a seeded scene from the head camera (and optionally from the external camera).

    python -m sim.render_scene --object phone --seed 0 --png head.png [--external]
        [--width 640 --height 480] [--distractors N] [--no-shadows]

    python -m sim.render_scene --sheet docs/tiers.png [--object phone --seed 0]
        [--estimator hybrid]

writes the head camera's RGB image to `--png`; with `--sheet` instead one picture of every tier
(`posegrasp.world.tiers`), head camera above the external view, labelled; on each head image the
target's true pose (white) and the pose `--estimator` finds in that image (green), with the
estimate's errors in the label (`--estimator none`: no poses); with `--external` also writes
`<stem>_external.png` next to it, a view from the world camera "external" that shows the robot,
the table and the objects. Every argument is checked before the scene is built; a bad one gives a
single `error: ...` line on stderr that names the valid choices, and exit status 2.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from perception.overlay import draw_estimate
from posegrasp.core.cli import ArgumentParser, command
from posegrasp.core.contract import Observation, PoseEstimator
from posegrasp.core.errors import InvalidArgumentError, PosegraspError
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_choice, check_int, check_output_file, check_seed
from posegrasp.world import constants as C  # importing sim defaults MUJOCO_GL to egl
from posegrasp.world.camera import CameraRenderer, RenderOptions, check_resolution
from posegrasp.world.objects import OBJECT_NAMES, object_names
from posegrasp.world.scene import SceneConfig, build_scene
from posegrasp.world.tiers import DEFAULT_TIER, TIERS, check_tier, tier_scene
from sim.episode import Episode, EpisodeConfig
from sim.estimators import (
    DEFAULT_ESTIMATOR,
    PrivilegedEstimator,
    add_estimator_arguments,
    make_estimator,
)

EXTERNAL_CAMERA = "external"
#: `--estimator` value of a sheet without poses.
NO_ESTIMATOR = "none"
#: RGB of a sheet's label lines.
TEXT_COLOUR, ERRORS_COLOUR, MISSED_COLOUR = (0, 0, 0), (0, 120, 0), (190, 0, 0)


@dataclass(frozen=True)
class RenderRequest:
    """A checked command line.

    Attributes:
        object: target object class, one of `OBJECT_NAMES`.
        seed: scene seed (>= 0).
        out: path of the head-camera PNG (`--png`), or of the sheet (`--sheet`).
        external: also render the external camera to `external_path`.
        width, height: image size [px], both cameras.
        distractors: number of other objects on the table.
        shadows: render shadows (about 3x slower on software rendering).
        tier: the scene tier (`posegrasp.world.tiers`); its presets override `distractors`.
        estimator: the estimator (`sim.estimators.ESTIMATORS`) whose poses a sheet shows, or
            `NO_ESTIMATOR`.
    """

    object: str
    seed: int
    out: Path
    external: bool
    width: int
    height: int
    distractors: int
    shadows: bool
    tier: str = DEFAULT_TIER
    estimator: str = NO_ESTIMATOR

    @property
    def external_path(self) -> Path:
        """`<stem>_external.png` next to `out`."""
        return self.out.with_name(f"{self.out.stem}_external{self.out.suffix}")


def build_parser() -> argparse.ArgumentParser:
    """The command-line parser: every value is checked while parsing, the combinations by
    `check_request`."""
    p = ArgumentParser(
        prog="python -m sim.render_scene",
        description="Render a seeded posegrasp scene from the robot's head camera.",
    )
    p.add_argument(
        "--object",
        default="phone",
        type=arg(check_choice, object_names(), "object"),
        metavar="NAME",
        help=f"target object, one of: {', '.join(object_names())} (default: phone)",
    )
    p.add_argument(
        "--seed",
        type=arg(check_seed, "--seed", base=int),
        default=0,
        help="scene seed in 0..2**32-1 (default: 0)",
    )
    image = p.add_mutually_exclusive_group()
    image.add_argument(
        "--png",
        type=arg(check_output_file, "--png", (".png",)),
        default="head.png",
        metavar="PATH",
        help="the head camera's image (default: head.png)",
    )
    image.add_argument(
        "--sheet",
        type=arg(check_output_file, "--sheet", (".png",)),
        default=None,
        metavar="PATH",
        help="instead, one labelled picture of every tier (PNG)",
    )
    p.add_argument(
        "--external",
        action="store_true",
        help="also write <stem>_external.png from the world camera 'external'",
    )
    p.add_argument("--width", type=int, default=640, help="image width [px] (default: 640)")
    p.add_argument("--height", type=int, default=480, help="image height [px] (default: 480)")
    n_max = len(OBJECT_NAMES) - 1
    p.add_argument(
        "--distractors",
        type=arg(check_int, 0, n_max, "--distractors", base=int),
        default=0,
        metavar="N",
        help=f"other objects on the table, 0..{n_max} (default: 0)",
    )
    p.add_argument(
        "--tier",
        default=DEFAULT_TIER,
        type=arg(check_tier),
        help=f"scene tier, one of: {', '.join(TIERS)}",
    )
    p.add_argument("--no-shadows", action="store_true", help="render without shadows (faster)")
    add_estimator_arguments(
        p,
        default=None,
        noise=False,
        purpose="with --sheet: draw the true pose and this estimator's on each head image "
        f"(default {DEFAULT_ESTIMATOR}; {NO_ESTIMATOR}: no poses)",
        also=(NO_ESTIMATOR,),
    )
    return p


def check_request(args: argparse.Namespace) -> RenderRequest:
    """The request of parsed arguments, its combinations checked before anything is built.

    Raises:
        InvalidArgumentError: bad resolution, or `--estimator` without `--sheet`, or no
            writable `<stem>_external.png` beside the image.
    """
    check_resolution(args.width, args.height)
    estimator = NO_ESTIMATOR
    if args.sheet is not None:
        estimator = args.estimator or DEFAULT_ESTIMATOR
    elif args.estimator is not None:
        raise InvalidArgumentError("--estimator applies to --sheet only")
    req = RenderRequest(
        object=args.object,
        seed=args.seed,
        out=Path(args.sheet if args.sheet is not None else args.png),
        external=args.external,
        width=args.width,
        height=args.height,
        distractors=args.distractors,
        shadows=not args.no_shadows,
        tier=args.tier,
        estimator=estimator,
    )
    if req.external:
        check_output_file(req.external_path, "--external")
    return req


def _write_png(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), rgb[..., ::-1]):
        raise PosegraspError(f"cannot write {str(path)!r}")


def render(req: RenderRequest) -> list[Path]:
    """Build the scene of req and write its images.

    Returns:
        The paths written, head camera first.
    """
    scene = build_scene(
        req.object, req.seed, tier_scene(req.tier, SceneConfig(n_distractors=req.distractors))
    )
    written = [req.out]
    cameras = [(C.HEAD_CAMERA, req.out)]
    if req.external:
        cameras.append((EXTERNAL_CAMERA, req.external_path))
        written.append(req.external_path)
    options = RenderOptions(shadows=req.shadows, reflections=False)
    with CameraRenderer(scene.model, req.width, req.height, options) as renderer:
        for camera, path in cameras:
            _write_png(path, renderer.rgb(scene.data, camera))
    return written


def _estimate_on_head(
    ep: Episode, obs: Observation, estimator: PoseEstimator | PrivilegedEstimator
) -> tuple[np.ndarray, str, tuple[int, int, int]]:
    """The head image with the true pose and the estimator's drawn on it (as `sim.run_episode`
    saves it), and a line with the estimate's errors or "not detected" and its colour."""
    est = ep.estimate(estimator, obs).T_C_O
    target = ep.scene.target.model
    v, f = np.asarray(target.mesh.vertices), np.asarray(target.mesh.faces)
    img = draw_estimate(obs.rgb, obs.K, ep.T_C_O_true, est, v, f)
    if est is None:
        return img, f"{estimator.name}: {ep.object} not detected", MISSED_COLOUR
    e = ep.pose_errors(est)  # up to the object's symmetries
    errors = f"{e['translation_m'] * 1000:.0f} mm, {e['rotation_deg']:.1f} deg off"
    return img, f"{estimator.name} estimate: {errors}", ERRORS_COLOUR


def render_sheet(req: RenderRequest, path: Path) -> Path:
    """One column per tier (seed `req.seed`, target `req.object`): the head camera above the
    external view, each at `req.width` x `req.height`, with the tier's name and summary. Unless
    `req.estimator` is `NO_ESTIMATOR`, the estimator runs on each head image as in an episode
    (`sim.episode.Episode.estimate`); the image shows the true pose and the estimate, the label
    the estimate's translation and rotation errors, or that it found no target."""
    estimator = None if req.estimator == NO_ESTIMATOR else make_estimator(req.estimator)
    columns = []
    for name, tier in TIERS.items():
        cfg = EpisodeConfig(width=req.width, height=req.height, shadows=req.shadows, tier=name)
        ep = Episode(req.object, req.seed, cfg)
        try:
            obs = ep.observe()
            hidden = (
                f" ({ep.scene.occlusion:.0%} of the target hidden)" if ep.scene.occlusion else ""
            )
            head, lines = obs.rgb, [(name + hidden, TEXT_COLOUR), (tier.summary, TEXT_COLOUR)]
            if estimator is not None:
                head, errors, colour = _estimate_on_head(ep, obs, estimator)
                lines.append((errors, colour))
            external = ep.renderer.rgb(ep.scene.data, EXTERNAL_CAMERA)
        finally:
            ep.close()
        label = np.full((4 + 18 * len(lines), req.width, 3), 255, np.uint8)
        for row, (text, colour) in enumerate(lines):
            cv2.putText(
                label,
                text[:70],
                (6, 16 + 18 * row),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.45 if row else 0.55,
                colour,
                1,
                cv2.LINE_AA,
            )
        columns.append(np.vstack([label, head, external]))
    _write_png(path, np.hstack(columns))
    return path


@command
def main(argv: list[str] | None = None) -> int:
    """Command-line entry point; returns the exit status."""
    args = build_parser().parse_args(argv)
    setup_rendering()
    req = check_request(args)
    for path in [render_sheet(req, req.out)] if args.sheet is not None else render(req):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
