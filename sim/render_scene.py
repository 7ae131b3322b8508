"""Render a seeded scene from the head camera (and optionally from the external camera).

    python -m sim.render_scene --object phone --seed 0 --png head.png [--external]
        [--width 640 --height 480] [--distractors N] [--no-shadows] [--sensor NAME] [--depth]
        [--shift SPEC]

    python -m sim.render_scene --sheet docs/tiers.png [--object phone --seed 0]
        [--estimator hybrid] [--sensor NAME] [--shift SPEC]

writes the head camera's RGB image to `--png`, as the sensor `--sensor` returns it (the sensor
models of `posegrasp.world.sensors`, with the noise an episode of the same seed observes;
``ideal``, the default: the rendered image); with `--depth` also the head camera's depth as that
sensor returns it, `<stem>_depth.png` (metric, 16-bit, millimetres, 0 where the sensor returns
nothing) and `<stem>_depth_view.png` (coloured, with its scale). With `--sheet` instead one
picture of every tier (`posegrasp.world.tiers`), head camera above the external view, labelled;
on each head image the target's true pose (white) and the pose `--estimator` finds in that image
(green), seen through the sensor as in an episode, with the estimate's errors in the label
(`--estimator none`: no poses); with `--external` also writes `<stem>_external.png` next to it,
a view from the world camera "external" that shows the robot, the table and the objects. With
`--shift SPEC` every image is of the scene under those scene shifts (`posegrasp.world.shifts`:
``NAME[:LEVEL]``, a comma list, ``all[:LEVEL]``), the sheet's head images and estimates too, as
an episode with ``--shift SPEC`` sees it; the sheet's labels name them. Every
argument is checked before the scene is built; a bad one gives a single `error: ...` line on
stderr that names the valid choices, and exit status 2.
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
from posegrasp.world.camera import (
    MM_PER_M,
    CameraRenderer,
    RenderOptions,
    camera_intrinsics,
    check_resolution,
    depth_to_uint16,
    far_plane,
)
from posegrasp.world.objects import OBJECT_NAMES, object_names
from posegrasp.world.scene import SceneConfig, build_scene
from posegrasp.world.sensors import Sensor
from posegrasp.world.shifts import FACTORS, Shift
from posegrasp.world.tiers import DEFAULT_TIER, TIERS, check_tier, tier_scene
from sim.episodes.episode import Episode, EpisodeConfig
from sim.episodes.registry import (
    DEFAULT_ESTIMATOR,
    PrivilegedEstimator,
    add_estimator_arguments,
    add_sensor_argument,
    add_shift_argument,
    depth_unused_note,
    make_estimator,
    needs_depth,
)

EXTERNAL_CAMERA = "external"
#: `--estimator` value of a sheet without poses.
NO_ESTIMATOR = "none"
#: RGB of a sheet's label lines.
TEXT_COLOUR, ERRORS_COLOUR, MISSED_COLOUR = (0, 0, 0), (0, 120, 0), (190, 0, 0)
#: Percentiles of the valid depths that span a depth view's colours (the rest is clipped to the
#: ends of the scale, marked <= and >=).
VIEW_PERCENTILES = (1.0, 99.0)
#: Width of a depth view's scale panel and height of its caption band [px].
SCALE_W, CAPTION_H = 96, 24
#: Tick labels on a depth view's scale.
SCALE_TICKS = 5
#: Colour of a depth view's pixels without a reading (not on the colour scale).
NO_READING_RGB = (255, 255, 255)


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
        estimator: the estimator (`sim.episodes.registry.ESTIMATORS`) whose poses a sheet shows, or
            `NO_ESTIMATOR`.
        sensor: the head camera's sensor model (`posegrasp.world.sensors.SENSOR_NAMES`).
        depth: also write the head camera's depth as the sensor returns it (`depth_paths`).
        shifts: the scene shifts every image is rendered under (`posegrasp.world.shifts`).
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
    sensor: str = "ideal"
    depth: bool = False
    shifts: tuple[Shift, ...] = ()

    @property
    def external_path(self) -> Path:
        """`<stem>_external.png` next to `out`."""
        return self.out.with_name(f"{self.out.stem}_external{self.out.suffix}")

    @property
    def depth_paths(self) -> tuple[Path, Path]:
        """`<stem>_depth.png` (metric) and `<stem>_depth_view.png` (coloured) next to `out`."""
        return (
            self.out.with_name(f"{self.out.stem}_depth{self.out.suffix}"),
            self.out.with_name(f"{self.out.stem}_depth_view{self.out.suffix}"),
        )


def _add_sensing_arguments(p: argparse.ArgumentParser) -> None:
    """Add what the head camera senses: ``--sensor``, ``--depth`` and ``--shift``."""
    add_sensor_argument(p)
    add_shift_argument(p)
    p.add_argument(
        "--depth",
        action="store_true",
        help="also write the head camera's depth as the sensor returns it: <stem>_depth.png "
        "(16-bit, millimetres, 0: no reading) and <stem>_depth_view.png (coloured, with its "
        "scale); not with --sheet",
    )


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
    _add_sensing_arguments(p)
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
    if args.depth and args.sheet is not None:
        raise InvalidArgumentError("--depth applies to --png only, not to --sheet")
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
        sensor=args.sensor,
        depth=args.depth,
        shifts=args.shift,
    )
    if req.external:
        check_output_file(req.external_path, "--external")
    for path in req.depth_paths if req.depth else ():
        check_output_file(path, "--depth")
    return req


def _write_png(path: Path, image: np.ndarray) -> None:
    """Write an RGB image (H, W, 3) uint8, or a grey one (H, W) of uint8 or uint16, as PNG."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), image[..., ::-1] if image.ndim == 3 else image):
        raise PosegraspError(f"cannot write {str(path)!r}")


def depth_to_mm(depth_m: np.ndarray, far_m: float | None = None) -> np.ndarray:
    """A depth image [m] in whole millimetres, 16-bit, 0 where there is no reading (also at the
    far plane `far_m` where given): `posegrasp.world.camera.depth_to_uint16`."""
    return depth_to_uint16(depth_m, 1.0, far_m)


def _text(img: np.ndarray, text: str, xy: tuple[int, int], scale: float = 0.4) -> None:
    cv2.putText(img, text, xy, cv2.FONT_HERSHEY_SIMPLEX, scale, TEXT_COLOUR, 1, cv2.LINE_AA)


def depth_view(depth_mm: np.ndarray, caption: str) -> np.ndarray:
    """A metric depth image (`depth_to_mm`) in colour for a person to read: the valid depths
    between the `VIEW_PERCENTILES` coloured near (blue) to far (red), white where there is no
    reading, a scale in metres on the right and `caption` above.

    Args:
        depth_mm: (H, W) uint16 [mm], 0: no reading.
        caption: what the image is (the sensor, whether the estimator saw it).

    Returns:
        RGB (H + `CAPTION_H`, W + `SCALE_W`, 3) uint8.
    """
    h, w = depth_mm.shape
    valid = depth_mm > 0
    lo, hi = np.percentile(depth_mm[valid], VIEW_PERCENTILES) if valid.any() else (0.0, 1.0)
    hi = max(float(hi), float(lo) + 1.0)
    level = np.clip((depth_mm.astype(np.float64) - lo) / (hi - lo), 0.0, 1.0)
    grey = np.rint(255 * level).astype(np.uint8)
    colour = cv2.applyColorMap(grey, cv2.COLORMAP_TURBO)[..., ::-1]
    colour[~valid] = NO_READING_RGB
    out = np.full((h + CAPTION_H, w + SCALE_W, 3), 255, np.uint8)
    out[CAPTION_H:, :w] = colour
    _text(out, caption + "; white: no reading", (4, CAPTION_H - 8), 0.42)
    top, bottom = CAPTION_H + 8, CAPTION_H + h - 8
    ramp = np.linspace(0, 255, max(bottom - top, 2)).astype(np.uint8)[:, None]
    bar = cv2.applyColorMap(ramp, cv2.COLORMAP_TURBO)[..., ::-1]
    out[top : top + len(ramp), w + 6 : w + 22] = bar
    for k in range(SCALE_TICKS):
        share = k / (SCALE_TICKS - 1)
        y = round(top + share * (len(ramp) - 1))
        mark = "<=" if k == 0 else ">=" if k == SCALE_TICKS - 1 else ""
        metres = (lo + share * (hi - lo)) / MM_PER_M
        out[y, w + 22 : w + 27] = 0
        _text(out, f"{mark}{metres:.2f} m", (w + 29, y + 4), 0.36)
    return out


def write_depth(paths: tuple[Path, Path], depth_m: np.ndarray, caption: str, far_m: float) -> None:
    """Write a depth image as `depth_to_mm`'s metric 16-bit PNG and `depth_view`'s coloured one.

    Args:
        paths: the metric PNG and the coloured one.
        depth_m: depth along the optical axis (H, W) [m], 0 where the sensor returns nothing.
        caption: what the coloured view says it shows.
        far_m: the far clipping plane [m] (beyond it the renderer drew nothing).
    """
    mm = depth_to_mm(depth_m, far_m)
    _write_png(paths[0], mm)
    _write_png(paths[1], depth_view(mm, caption))


def render(req: RenderRequest) -> list[Path]:
    """Build the scene of req and write its images: the head camera's through the sensor
    (with the noise an episode of the same seed observes), with `req.depth` its depth too.

    Returns:
        The paths written, head camera first, then its depth images, then the external view.
    """
    base = SceneConfig(n_distractors=req.distractors, shifts=req.shifts)
    scene = build_scene(req.object, req.seed, tier_scene(req.tier, base))
    sensor = Sensor.parse(req.sensor)
    written = [req.out]
    options = RenderOptions(shadows=req.shadows, reflections=False)
    with CameraRenderer(scene.model, req.width, req.height, options) as renderer:
        rgb = renderer.rgb(scene.data, C.HEAD_CAMERA)
        depth = renderer.depth(scene.data, C.HEAD_CAMERA) if req.depth else None
        if sensor.name != "ideal":
            K = camera_intrinsics(scene.model, C.HEAD_CAMERA, req.width, req.height)
            rgb, depth = sensor.apply(rgb, depth, K, req.seed)
        _write_png(req.out, rgb)
        if depth is not None:
            caption = f"head camera depth, sensor {sensor.name}"
            write_depth(req.depth_paths, depth, caption, far_plane(scene.model))
            written.extend(req.depth_paths)
        if req.external:
            _write_png(req.external_path, renderer.rgb(scene.data, EXTERNAL_CAMERA))
            written.append(req.external_path)
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


def shifts_text(shifts: tuple[Shift, ...]) -> str:
    """Scene shifts in a few words: ``all:L`` for every factor at level L, else the
    ``NAME:LEVEL`` items."""
    levels = {s.level for s in shifts}
    if len(shifts) == len(FACTORS) and len(levels) == 1:
        return f"all:{levels.pop()}"
    return ",".join(map(str, shifts))


def render_sheet(req: RenderRequest, path: Path) -> Path:
    """One column per tier (seed `req.seed`, target `req.object`): the head camera above the
    external view, each at `req.width` x `req.height`, with the tier's name and summary. Unless
    `req.estimator` is `NO_ESTIMATOR`, the estimator runs on each head image as in an episode
    (`sim.episodes.episode.Episode.estimate`); the image shows the true pose and the estimate, the
    label the estimate's translation and rotation errors, or that it found no target. The head
    images are seen through `req.sensor`, with the depth image for an estimator that needs it
    (`sim.episodes.registry.needs_depth`), under the scene shifts `req.shifts`, which the
    first label line names."""
    estimator = None if req.estimator == NO_ESTIMATOR else make_estimator(req.estimator)
    obs_mode = "rgbd" if needs_depth(req.estimator) else "rgb"
    columns = []
    for name, tier in TIERS.items():
        cfg = EpisodeConfig(
            width=req.width,
            height=req.height,
            shadows=req.shadows,
            tier=name,
            obs_mode=obs_mode,
            sensor=req.sensor,
            scene=SceneConfig(shifts=req.shifts),
        )
        ep = Episode(req.object, req.seed, cfg)
        try:
            obs = ep.observe()
            hidden = (
                f" ({ep.scene.occlusion:.0%} of the target hidden)" if ep.scene.occlusion else ""
            ) + (f", shifts {shifts_text(req.shifts)}" if req.shifts else "")
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


def depth_note(req: RenderRequest, sheet: bool) -> str | None:
    """The one ``note:`` line when the sensor's depth model changes a depth image that nothing
    written shows: a sheet whose estimator sees colour only
    (`sim.episodes.registry.depth_unused_note`) or shows no estimate, or a head image without
    ``--depth``; None otherwise."""
    if sheet and req.estimator != NO_ESTIMATOR:
        return None if needs_depth(req.estimator) else depth_unused_note("rgb", req.sensor)
    if Sensor.parse(req.sensor).depth == "ideal" or req.depth:
        return None
    where = "a sheet does not show" if sheet else "only --depth writes"
    return f"note: sensor {req.sensor} changes the depth image, which {where}"


@command
def main(argv: list[str] | None = None) -> int:
    """Command-line entry point; returns the exit status."""
    args = build_parser().parse_args(argv)
    setup_rendering()
    req = check_request(args)
    note = depth_note(req, args.sheet is not None)
    if note is not None:
        print(note, file=sys.stderr)
    for path in [render_sheet(req, req.out)] if args.sheet is not None else render(req):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
