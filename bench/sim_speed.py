"""Simulation and rendering speed of posegrasp scenes, against the project's targets.

    python bench/sim_speed.py [--seeds 10] [--sim-seconds 5] [--frames 30] [--json PATH]

Measures, on this machine (software EGL rendering unless MUJOCO_GL says otherwise):
- scene build time: `build_scene` (compile, place, aim the head, 0.5 s settle), median over seeds;
- physics real-time factor (simulated s per wall-clock s) with the robot holding its posture,
  with the target alone and with five distractors;
- head-camera frames per second at 640x480 and 256x256, RGB and segmentation, shadows on and off
  (each frame includes `update_scene`, the render and the read-back).

Targets: scene build <= 0.5 s; RTF >= 10; RGB >= 30 fps at 640x480 without shadows.
Other processes on the machine lower every figure: the report includes the load average.
`--json PATH` writes every figure and ``targets_met``. Exit status 0 when every target is met,
1 when one is missed.
"""

from __future__ import annotations

# Before MuJoCo is imported: it picks its GL backend at import time (sim does the same, but
# mujoco is imported first here).
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

import mujoco

from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    command,
    summary_stream,
    verdict,
    write_json,
)
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_float, check_int
from posegrasp.world import constants as C
from posegrasp.world.camera import CameraRenderer, RenderOptions
from posegrasp.world.objects import OBJECT_NAMES
from posegrasp.world.scene import SceneConfig, build_scene

TARGET_BUILD_S = 0.5
TARGET_RTF = 10.0
TARGET_RGB_FPS = 30.0  # 640x480, no shadows


@dataclass(frozen=True)
class RenderSpeed:
    """Frames per second of one render configuration of the head camera."""

    kind: str  # "rgb" or "segmentation"
    width: int
    height: int
    shadows: bool
    msaa_samples: int  # multisample anti-aliasing samples of the offscreen buffer (0: off)
    fps: float


@dataclass(frozen=True)
class SpeedReport:
    """Every figure the benchmark measures (times in [s])."""

    build_s_median: float
    build_s_min: float
    build_s_max: float
    build_seeds: int
    rtf_one_object: float
    rtf_six_objects: float
    render: list[RenderSpeed]
    msaa_samples: int  # the scene's own multisampling, used by every target
    machine: dict[str, str]

    def rgb_fps(self, width: int, height: int, shadows: bool) -> float:
        """RGB frames/s of the head camera with the scene's own multisampling."""
        key = ("rgb", width, height, shadows, self.msaa_samples)
        return next(
            r.fps
            for r in self.render
            if (r.kind, r.width, r.height, r.shadows, r.msaa_samples) == key
        )

    def checks(self) -> dict[str, bool]:
        """Each target: met or not."""
        return {
            "build": self.build_s_median <= TARGET_BUILD_S,
            "rtf": self.rtf_one_object >= TARGET_RTF,
            "rgb_640x480_no_shadows": self.rgb_fps(640, 480, False) >= TARGET_RGB_FPS,
        }


def time_builds(seeds: int) -> list[float]:
    """Wall-clock time of `build_scene` for seeds 0..seeds-1, cycling through the objects [s]."""
    build_scene(OBJECT_NAMES[0], 0)  # warm-up: object meshes, the Fetch XML, imports
    times = []
    for seed in range(seeds):
        t0 = time.perf_counter()
        build_scene(OBJECT_NAMES[seed % len(OBJECT_NAMES)], seed)
        times.append(time.perf_counter() - t0)
    return times


def real_time_factor(n_distractors: int, sim_seconds: float) -> float:
    """Simulated seconds per wall-clock second, robot holding its home posture."""
    scene = build_scene("phone", 0, SceneConfig(n_distractors=n_distractors))
    n = round(sim_seconds / scene.model.opt.timestep)
    t0 = time.perf_counter()
    mujoco.mj_step(scene.model, scene.data, nstep=n)
    return n * scene.model.opt.timestep / (time.perf_counter() - t0)


def _fps(render: Callable[[mujoco.MjData, str], object], data: mujoco.MjData, frames: int) -> float:
    for _ in range(3):  # warm-up: context, textures, shadow maps
        render(data, C.HEAD_CAMERA)
    t0 = time.perf_counter()
    for _ in range(frames):
        render(data, C.HEAD_CAMERA)
    return frames / (time.perf_counter() - t0)


def render_speeds(frames: int) -> tuple[list[RenderSpeed], int]:
    """Head-camera frames per second in every configuration.

    Every configuration renders with the scene's own multisampling (`offsamples` of
    world.xml, MuJoCo's default 4 when unset); RGB without shadows is also measured with
    multisampling off, for comparison.

    Returns:
        The measurements, and the scene's own number of multisamples.
    """
    scene = build_scene("phone", 0)
    quality = scene.model.vis.quality
    default_samples = int(quality.offsamples)
    configs = [
        (w, h, shadows, default_samples) for w, h in ((640, 480), (256, 256)) for shadows in (0, 1)
    ]
    configs += [(640, 480, False, 0), (256, 256, False, 0)]
    out = []
    for width, height, shadows, samples in configs:
        quality.offsamples = samples
        options = RenderOptions(shadows=bool(shadows), reflections=False)
        with CameraRenderer(scene.model, width, height, options) as renderer:
            kinds = [("rgb", renderer.rgb)]
            if samples == default_samples:
                kinds.append(("segmentation", renderer.segmentation))
            for kind, render in kinds:
                fps = _fps(render, scene.data, frames)
                out.append(RenderSpeed(kind, width, height, bool(shadows), samples, fps))
    quality.offsamples = default_samples
    return out, default_samples


def machine_info() -> dict[str, str]:
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    return {
        "cpus": str(os.cpu_count()),
        "load_average_1min": f"{load[0]:.2f}",
        "python": platform.python_version(),
        "mujoco": mujoco.__version__,
        "MUJOCO_GL": os.environ.get("MUJOCO_GL", ""),
    }


def measure(seeds: int, sim_seconds: float, frames: int) -> SpeedReport:
    """Run every measurement."""
    builds = time_builds(seeds)
    render, msaa_samples = render_speeds(frames)
    return SpeedReport(
        build_s_median=statistics.median(builds),
        build_s_min=min(builds),
        build_s_max=max(builds),
        build_seeds=seeds,
        rtf_one_object=real_time_factor(0, sim_seconds),
        rtf_six_objects=real_time_factor(len(OBJECT_NAMES) - 1, sim_seconds),
        render=render,
        msaa_samples=msaa_samples,
        machine=machine_info(),
    )


def format_report(r: SpeedReport) -> str:
    """The human-readable table."""
    ok = r.checks()
    lines = [
        "posegrasp simulation speed  (" + ", ".join(f"{k} {v}" for k, v in r.machine.items()) + ")",
        "",
        f"{'measure':<54}{'value':>10}  {'target':<10}result",
        f"{'scene build, median of ' + str(r.build_seeds) + ' seeds [s]':<54}"
        f"{r.build_s_median:>10.3f}  {'<= 0.5':<10}{verdict(ok['build'])}",
        f"{'  (min / max) [s]':<54}{r.build_s_min:>10.3f}  {r.build_s_max:.3f}",
        f"{'physics real-time factor, 1 object':<54}{r.rtf_one_object:>10.1f}  "
        f"{'>= 10':<10}{verdict(ok['rtf'])}",
        f"{'physics real-time factor, 6 objects':<54}{r.rtf_six_objects:>10.1f}",
        f"(renders use the scene's multisampling, {r.msaa_samples} samples, unless marked)",
    ]
    for s in r.render:
        label = f"head camera {s.kind} {s.width}x{s.height}, shadows {'on' if s.shadows else 'off'}"
        if s.msaa_samples != r.msaa_samples:
            label += ", no MSAA" if s.msaa_samples == 0 else f", MSAA {s.msaa_samples}"
        line = f"{label + ' [fps]':<54}{s.fps:>10.1f}"
        key = (s.kind, s.width, s.height, s.shadows, s.msaa_samples)
        if key == ("rgb", 640, 480, False, r.msaa_samples):
            line += f"  {'>= 30':<10}{verdict(ok['rgb_640x480_no_shadows'])}"
        lines.append(line)
    return "\n".join(lines)


@command
def main(argv: list[str] | None = None) -> int:
    """Command-line entry point; returns 0 when every target is met, 1 when one is missed."""
    parser = ArgumentParser(
        prog="python bench/sim_speed.py",
        description="Scene build time, physics real-time factor and render speed vs targets.",
    )
    parser.add_argument(
        "--seeds",
        type=arg(check_int, 1, 10_000, "--seeds", base=int),
        default=10,
        help="scenes to build, 1..10000 (default: 10)",
    )
    parser.add_argument(
        "--sim-seconds",
        type=arg(check_float, 0.01, 3600.0, "--sim-seconds", base=float),
        default=5.0,
        help="simulated time per RTF run [s], 0.01..3600 (default: 5)",
    )
    parser.add_argument(
        "--frames",
        type=arg(check_int, 1, 100_000, "--frames", base=int),
        default=30,
        help="frames per render figure, 1..100000 (default: 30)",
    )
    add_json_argument(parser, "every figure and the targets met")
    args = parser.parse_args(argv)
    setup_rendering()
    report = measure(args.seeds, args.sim_seconds, args.frames)
    print(format_report(report), file=summary_stream(args.json))
    if args.json is not None:
        write_json(args.json, {**asdict(report), "targets_met": report.checks()})
    return 0 if all(report.checks().values()) else 1


if __name__ == "__main__":
    sys.exit(main())
