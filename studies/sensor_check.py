"""The head camera's sensor models against their own formulas, their holes, their speed, and a
figure of one scene under every model.

    python studies/sensor_check.py [--repeats 20] [--plot docs/sensors.png] [--json PATH]

Every image the models see here is rendered by `CameraRenderer`, at the head camera's field of
view and resolution (those of the scene below, 640x480), in a scene of its own: a camera, a
headlight and grey boxes.

(a) A fronto-parallel plane at five distances 0.55..1.6 m (the first just inside azure-tof's
0.5 m range limit): the standard deviation of each noisy depth model's output in the interior
against the model's own `sigma_z` at that distance (``ratio``; `TOLERANCE` is the agreement the
models are held to), and the interior's hole fraction.

(b) A step from a plane at 1.2 m to a nearer one at 0.9 m on the right half: the hole fraction
in the projector's shadow band left of the step (kinect-v1), in the two columns at the step and
on the flat far plane.

(c) The colour model ``camera`` on the plane's flat grey image, at the exposure of `SCENE`'s
episode: each channel's standard deviation against the Poissonian-Gaussian formula of
`posegrasp.world.sensors.camera_rgb` (shot and read noise, through the sRGB curve, plus 8-bit
rounding).

(d) One frame of the real scene (``phone``, seed 1000000000, tier ``clutter``, ``rgbd``): each
model's hole fraction there and its time per frame on one thread (median and best of
`--repeats`), each drawing from the stream the episode's sensor draws from. `--plot` draws that
frame under every model: the colour image ideal and under ``camera``, and the depth images (one
colour scale, holes black).
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_int, check_plot_path
from posegrasp.world import sensors as S

#: Plane distances [m].
DISTANCES = tuple(float(z) for z in np.linspace(0.55, 1.6, 5))
#: The step's far (left) and near (right) planes [m].
STEP = (1.2, 0.9)
#: The scene of the figure and the timings.
SCENE = ("phone", 1_000_000_000, "clutter")
NOISY = ("kinect-v1", "azure-tof")
#: Interior of an image: away from the borders, where resampling clamps.
INNER = (slice(8, -8), slice(8, -8))
#: Largest relative difference between a measured and a modelled standard deviation.
TOLERANCE = 0.10
#: Grey of the planes (RGBA): bright enough that azure-tof drops no pixel as dark.
PLANE_RGBA = "0.6 0.6 0.6 1"


def planes_xml(fovy_deg: float, shape: tuple[int, int], z_left: float, z_right: float) -> str:
    """MJCF of a camera ``cam`` at the origin looking along -z (MuJoCo's camera convention) at a
    plane z_left [m] away filling the view and, on the right half (x > 0), a plane z_right."""
    h, w = shape
    near = ""
    if z_right != z_left:
        near = (
            f'<geom type="box" size="2.5 10 0.005" pos="2.5 0 {-z_right - 0.005}" '
            f'rgba="{PLANE_RGBA}"/>'
        )
    return f"""<mujoco model="planes">
  <visual>
    <global offwidth="{w}" offheight="{h}"/>
    <map znear="0.05" zfar="20"/>
    <headlight ambient="0.5 0.5 0.5" diffuse="0.5 0.5 0.5" specular="0 0 0"/>
  </visual>
  <statistic extent="1" center="0 0 -1"/>
  <worldbody>
    <camera name="cam" pos="0 0 0" fovy="{fovy_deg}"/>
    <geom type="box" size="10 10 0.005" pos="0 0 {-z_left - 0.005}" rgba="{PLANE_RGBA}"/>
    {near}
  </worldbody>
</mujoco>"""


def render_planes(
    K: np.ndarray, shape: tuple[int, int], z_left: float, z_right: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Render a plane z_left [m] in front of a camera of intrinsics K, and optionally a nearer or
    farther plane z_right on the right half of the image (columns from ``W // 2`` on).

    Args:
        K: intrinsics (3, 3) [px] of `posegrasp.core.transforms.intrinsics` (square pixels,
            centred principal point).
        shape: (H, W) [px].
        z_left, z_right: distances along the optical axis [m].

    Returns:
        (rgb (H, W, 3) uint8, ideal depth (H, W) float32 [m]).

    Raises:
        InvalidArgumentError: K is not the rendered camera's.
    """
    import mujoco

    from posegrasp.world.camera import CameraRenderer, camera_intrinsics

    h, w = shape
    fovy = float(np.rad2deg(2 * np.arctan((h / 2) / K[1, 1])))
    xml = planes_xml(fovy, shape, z_left, z_left if z_right is None else z_right)
    model = mujoco.MjModel.from_xml_string(xml)
    if not np.allclose(camera_intrinsics(model, "cam", w, h), K, rtol=0, atol=1e-6):
        raise InvalidArgumentError("K is not a pinhole of square pixels centred on the image")
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    with CameraRenderer(model, w, h) as renderer:
        return renderer.rgb(data, "cam"), renderer.depth(data, "cam")


def plane_table(K: np.ndarray, shape: tuple[int, int]) -> list[dict[str, Any]]:
    """Measured against modelled sigma on rendered planes, per noisy model and distance: the
    interior's standard deviation and hole fraction, the ratio to `sigma_z`, and whether it is
    within `TOLERANCE`."""
    rows = []
    for i, z in enumerate(DISTANCES):
        rgb, depth = render_planes(K, shape, z)
        for model in NOISY:
            out = S.apply_depth(model, depth, K, np.random.default_rng(i), rgb)
            inner = out[INNER]
            kept = inner[inner > 0].astype(np.float64)
            model_sigma = float(S.sigma_z(model, z))
            ratio = float(kept.std()) / model_sigma
            rows.append(
                {
                    "model": model,
                    "z_m": round(z, 4),
                    "sigma_model_mm": round(1000 * model_sigma, 4),
                    "sigma_measured_mm": round(1000 * float(kept.std()), 4),
                    "ratio": round(ratio, 4),
                    "within_tolerance": bool(abs(ratio - 1) < TOLERANCE),
                    "hole_fraction": round(float((inner == 0).mean()), 5),
                    "ideal_sigma_mm": round(1000 * float(depth[INNER].std()), 5),
                }
            )
    return sorted(rows, key=lambda r: (NOISY.index(r["model"]), r["z_m"]))


def edge_table(K: np.ndarray, shape: tuple[int, int]) -> dict[str, dict[str, float]]:
    """Hole fractions at a rendered step from `STEP`'s far plane (left) to its near one (right),
    per noisy model."""
    z_far, z_near = STEP
    col = shape[1] // 2
    rgb, depth = render_planes(K, shape, z_far, z_near)
    width = int(S.KINECT_BASELINE * K[0, 0] * (1 / z_near - 1 / z_far))
    out: dict[str, dict[str, float]] = {}
    for model in NOISY:
        d = S.apply_depth(model, depth, K, np.random.default_rng(0), rgb)[INNER[0]]
        out[model] = {
            "shadow_band": round(float((d[:, col - width + 4 : col - 4] == 0).mean()), 4),
            "step_columns": round(float((d[:, col - 1 : col + 1] == 0).mean()), 4),
            "flat": round(float((d[:, 8 : col - width - 8] == 0).mean()), 5),
        }
    out["shadow_width_px"] = {"model": width}
    return out


def camera_sigma_dn(level: int, gain: float, white_balance: float) -> float:
    """The ``camera`` model's standard deviation [8-bit steps] on a flat patch of sRGB `level`
    (0..255) in one channel: linear mean ``m = l g w`` and spread ``w sqrt(l g N + r^2) / N`` (N
    the full well, r the read noise) through the sRGB curve's slope at m, plus 1/12 of a step
    squared for the rounding to 8 bits."""
    lin = float(S.srgb_to_linear(np.array(level / 255.0)))
    n, r = S.CAMERA_FULL_WELL, S.CAMERA_READ_NOISE
    mean = lin * gain * white_balance
    sd = white_balance * np.sqrt(lin * gain * n + r * r) / n
    eps = 1e-6
    slope = float(S.linear_to_srgb(np.array(mean + eps)) - S.linear_to_srgb(np.array(mean - eps)))
    return float(np.sqrt((255 * slope / (2 * eps) * sd) ** 2 + 1 / 12))


def colour_table(K: np.ndarray, shape: tuple[int, int]) -> list[dict[str, Any]]:
    """The ``camera`` model on the rendered flat plane, per channel: measured against modelled
    standard deviation [8-bit steps] at the channel's median level, at the exposure of
    `SCENE`'s episode; ``level_spread_dn`` is the rendered image's own spread (0: flat)."""
    rgb, _ = render_planes(K, shape, DISTANCES[2])
    exposure = S.episode_exposure(SCENE[1])
    out = S.apply_rgb("camera", rgb, np.random.default_rng(0), exposure)[INNER]
    rows = []
    for c, name in enumerate("RGB"):
        ideal = rgb[INNER][..., c].astype(np.float64)
        level = int(np.median(ideal))
        model_sd = camera_sigma_dn(level, exposure.gain, exposure.white_balance[c])
        measured = float(out[..., c].astype(np.float64).std())
        rows.append(
            {
                "channel": name,
                "level_dn": level,
                "level_spread_dn": round(float(ideal.std()), 4),
                "sigma_model_dn": round(model_sd, 4),
                "sigma_measured_dn": round(measured, 4),
                "ratio": round(measured / model_sd, 4),
                "within_tolerance": bool(abs(measured / model_sd - 1) < TOLERANCE),
            }
        )
    return rows


def _timed(fn, repeats: int) -> tuple[float, float]:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(1000 * (time.perf_counter() - t))
    return statistics.median(times), min(times)


def render_scene() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ideal rgbd observation of `SCENE`: (rgb, depth, K)."""
    from sim.episodes.episode import Episode, EpisodeConfig

    obj, seed, tier = SCENE
    ep = Episode(obj, seed, EpisodeConfig(obs_mode="rgbd", tier=tier))
    try:
        obs = ep.observe()
    finally:
        ep.close()
    return obs.rgb, obs.depth, obs.K


def scene_table(
    rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, repeats: int
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Per model: hole fraction on the scene and time per frame; and the images (those the
    episode of `SCENE` observes under each model)."""
    seed = SCENE[1]
    images: dict[str, np.ndarray] = {}
    stats: dict[str, Any] = {}
    for model in S.DEPTH_MODELS:

        def run(m: str = model) -> np.ndarray:
            return S.apply_depth(m, depth, K, S.sensor_rng(seed, 0, "depth"), rgb)

        images[model] = run()
        median, best = _timed(run, repeats)
        stats[model] = {
            "hole_fraction": round(float((images[model] == 0).mean()), 4),
            "ms_median": round(median, 2),
            "ms_best": round(best, 2),
        }
    exposure = S.episode_exposure(seed)

    def colour() -> np.ndarray:
        return S.apply_rgb("camera", rgb, S.sensor_rng(seed, 0, "rgb"), exposure)

    images["camera"] = colour()
    median, best = _timed(colour, repeats)
    diff = np.abs(images["camera"].astype(np.int16) - rgb.astype(np.int16))
    stats["camera"] = {
        "mean_abs_change_dn": round(float(diff.mean()), 2),
        "exposure": {
            "gain": round(exposure.gain, 4),
            "white_balance": [round(w, 4) for w in exposure.white_balance],
            "blur_sigma_px": round(exposure.blur_sigma, 3),
        },
        "ms_median": round(median, 2),
        "ms_best": round(best, 2),
    }
    return stats, images


def plot(rgb: np.ndarray, images: dict[str, np.ndarray], path: Path) -> None:
    """The scene's colour image ideal and under ``camera``, and its depth under every model."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ideal = images["ideal"]
    shown = ideal[(ideal > 0.3) & (ideal < 4.0)]
    lo, hi = np.percentile(shown, [1, 99])
    cmap = matplotlib.colormaps["turbo"].copy()
    cmap.set_bad("black")
    fig, axes = plt.subplots(2, 3, figsize=(16, 8), layout="constrained")
    axes[0, 0].imshow(rgb)
    axes[0, 0].set_title("rgb: ideal")
    axes[0, 1].imshow(images["camera"])
    axes[0, 1].set_title("rgb: camera")
    panels = [(axes[0, 2], "ideal"), (axes[1, 0], "kinect-v1"), (axes[1, 1], "azure-tof")]
    for ax, model in panels:
        d = images[model]
        im = ax.imshow(np.ma.masked_where(d == 0, d), cmap=cmap, vmin=lo, vmax=hi)
        ax.set_title(f"depth: {model} ({100 * (d == 0).mean():.1f} % holes)")
        fig.colorbar(im, ax=ax, shrink=0.8, label="z [m]")
    err = np.where(images["kinect-v1"] > 0, 1000 * (images["kinect-v1"] - ideal), np.nan)
    ax = axes[1, 2]
    emap = matplotlib.colormaps["coolwarm"].copy()
    emap.set_bad("black")
    im = ax.imshow(np.ma.masked_invalid(err), cmap=emap, vmin=-10, vmax=10)
    ax.set_title("kinect-v1 minus ideal [mm]")
    fig.colorbar(im, ax=ax, shrink=0.8, label="[mm]")
    for ax in axes.flat:
        ax.set_axis_off()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def format_report(report: dict[str, Any]) -> str:
    """The tables of a report, as printed."""
    lines = [
        "rendered plane: sigma of the depth in the interior [mm], model against measured "
        f"(within {TOLERANCE:.0%}: ok)"
    ]
    lines.append(
        f"{'model':10s} {'z [m]':>6s} {'model':>8s} {'measured':>9s} {'ratio':>6s} {'':3s} holes"
    )
    for r in report["planes"]:
        ok = "ok" if r["within_tolerance"] else "NO"
        lines.append(
            f"{r['model']:10s} {r['z_m']:6.3f} {r['sigma_model_mm']:8.3f} "
            f"{r['sigma_measured_mm']:9.3f} {r['ratio']:6.3f} {ok:3s} {r['hole_fraction']:.4f}"
        )
    edges = report["edges"]
    z_far, z_near = STEP
    lines.append(
        f"rendered step {z_far} m -> {z_near} m: hole fraction (shadow band "
        f"{edges['shadow_width_px']['model']} px left of the step | the two step columns | flat)"
    )
    for model in NOISY:
        e = edges[model]
        lines.append(
            f"{model:10s} {e['shadow_band']:.3f} | {e['step_columns']:.3f} | {e['flat']:.4f}"
        )
    lines.append("camera on the rendered plane: sigma per channel [8-bit steps], model, measured")
    for r in report["colour"]:
        ok = "ok" if r["within_tolerance"] else "NO"
        lines.append(
            f"{r['channel']:10s} level {r['level_dn']:3d} {r['sigma_model_dn']:8.3f} "
            f"{r['sigma_measured_dn']:9.3f} {r['ratio']:6.3f} {ok}"
        )
    lines.append("scene (phone, seed 1000000000, clutter), 640x480: holes, ms per frame")
    for model, s in report["scene"].items():
        holes = s.get("hole_fraction", "")
        lines.append(
            f"{model:10s} holes {holes!s:>7s}  median {s['ms_median']:6.2f} ms  "
            f"best {s['ms_best']:6.2f} ms"
        )
    return "\n".join(lines)


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status (1 when a model misses its formula by more than
    `TOLERANCE`)."""
    p = ArgumentParser(prog="python studies/sensor_check.py", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--repeats",
        type=arg(check_int, 1, 1000, "--repeats", base=int),
        default=20,
        help="timed frames per model, 1..1000",
    )
    p.add_argument(
        "--plot",
        type=arg(check_plot_path, "--plot"),
        default=None,
        metavar="PATH",
        help="the scene under every model (.png, .pdf or .svg)",
    )
    add_json_argument(p, "the tables")
    args = p.parse_args(argv)
    setup_rendering(threads=1)
    import cv2

    cv2.setNumThreads(1)  # times per frame on one thread
    log = summary_stream(args.json)
    rgb, depth, K = render_scene()
    report: dict[str, Any] = {
        "planes": plane_table(K, depth.shape),
        "edges": edge_table(K, depth.shape),
        "colour": colour_table(K, depth.shape),
    }
    report["scene"], images = scene_table(rgb, depth, K, args.repeats)
    print(format_report(report), file=log)
    if args.plot is not None:
        plot(rgb, images, args.plot)
        print(f"wrote {args.plot}", file=log)
    if args.json is not None:
        write_json(args.json, report)
    rows = [*report["planes"], *report["colour"]]
    return 0 if all(r["within_tolerance"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
