"""Sensor models of the head camera, each against its own formula on synthetic depth images."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import ndtr

from posegrasp.core.errors import InvalidArgumentError, UnknownNameError
from posegrasp.core.transforms import intrinsics
from posegrasp.world import sensors as S

H, W = 480, 640
#: The head camera's intrinsics at 640x480 (fovy 50 deg).
K = intrinsics(np.deg2rad(50.0), W, H)
#: Plane distances [m]: 0.5..1.6, starting just inside azure-tof's 0.5 m range limit.
DISTANCES = np.linspace(0.55, 1.6, 5)
#: Interior of an image: away from the borders, where resampling clamps.
INNER = (slice(8, -8), slice(8, -8))
NOISY = ("kinect-v1", "azure-tof")


def plane(z: float) -> np.ndarray:
    return np.full((H, W), z, np.float32)


def step(z_left: float, z_right: float, col: int = W // 2) -> np.ndarray:
    d = plane(z_left)
    d[:, col:] = z_right
    return d


def paper_sigma(model: str, z: float) -> float:
    """Axial noise at normal incidence, written out from the sources."""
    if model == "kinect-v1":  # Nguyen, Izadi and Lovell 2012
        return 0.0012 + 0.0019 * (z - 0.4) ** 2
    return 0.0005 + 0.001 * max(z - 0.5, 0.0)  # BlenderProc add_kinect_azure_noise


@pytest.mark.parametrize("model", NOISY)
def test_plane_noise_matches_sigma_z(model: str) -> None:
    for i, z in enumerate(DISTANCES):
        out = S.apply_depth(model, plane(z), K, np.random.default_rng(i))[INNER]
        assert np.count_nonzero(out == 0) == 0, f"holes on a flat plane at {z} m"
        measured = out.astype(np.float64).std()
        expected = paper_sigma(model, z)
        assert abs(measured / expected - 1) < 0.05, (z, measured, expected)
        assert abs(out.astype(np.float64).mean() - z) < 0.5 * expected


def test_sigma_formulas() -> None:
    z = np.array([0.5, 1.0, 2.0])
    assert np.allclose(S.sigma_z("kinect-v1", z), 0.0012 + 0.0019 * (z - 0.4) ** 2)
    # At 45 deg the angle term is 0.0001 / sqrt(z) exactly.
    extra = S.sigma_z("kinect-v1", z, np.pi / 4) - S.sigma_z("kinect-v1", z)
    assert np.allclose(extra, 0.0001 / np.sqrt(z))
    assert np.allclose(S.sigma_z("azure-tof", z), [0.0005, 0.001, 0.002])
    assert np.all(S.sigma_z("ideal", z) == 0)
    assert np.allclose(S.sigma_lateral("kinect-v1", [0.0, np.pi / 4]), [0.8, 0.835])
    assert np.all(S.sigma_lateral("azure-tof", [0.0, 1.0]) == 0)


def test_incidence_angle_of_a_tilted_plane() -> None:
    tilt = np.deg2rad(40.0)
    n = np.array([np.sin(tilt), 0.0, -np.cos(tilt)])  # normal 40 deg off the optical axis
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((H, W))], -1)
    depth = (-1.0 / (rays @ n)).astype(np.float32)  # plane n . P = -1, so z = -1 / (n . ray)
    theta = S.incidence_angle(depth, K)[INNER]
    assert np.abs(np.rad2deg(theta) - 40.0).max() < 0.2


def test_shift_nearest_spreads_like_a_rounded_gaussian() -> None:
    sigma = 0.8
    ramp = np.tile(np.arange(W, dtype=np.float32), (H, 1))
    shift = (S.shift_nearest(ramp, sigma, np.random.default_rng(0)) - ramp)[INNER]
    k = np.arange(-10, 11)
    p = ndtr((k + 0.5) / sigma) - ndtr((k - 0.5) / sigma)
    assert abs(shift.std() / np.sqrt((k * k * p).sum()) - 1) < 0.02
    assert set(np.unique(shift)) <= set(k.astype(np.float32))


def test_quantised_gaussian_sigma_gives_the_target_after_rounding() -> None:
    rng = np.random.default_rng(0)
    for mean, target in [(10.0, 0.45), (10.25, 0.55), (7.5, 0.6), (3.1, 1.2), (2.0, 5.0)]:
        r = float(S.quantised_gaussian_sigma(np.array([target]), np.array([mean]))[0])
        rounded = np.rint(mean + r * rng.standard_normal(400_000))
        assert abs(rounded.std() / target - 1) < 0.02, (mean, target, r)


def test_kinect_projector_shadow_left_of_near_objects() -> None:
    z_far, z_near, col = 1.2, 0.9, W // 2
    width = S.KINECT_BASELINE * K[0, 0] * (1 / z_near - 1 / z_far)  # disparity jump [px]
    shadow = S.projector_shadow(np.float32(S.KINECT_BASELINE * K[0, 0]) / step(z_far, z_near))
    runs = shadow.sum(axis=1)
    assert np.all(np.abs(runs - width) <= 1), (runs.min(), runs.max(), width)
    assert not shadow[:, col:].any() and shadow[:, col - int(width) + 1 : col].all()

    out = S.apply_depth("kinect-v1", step(z_far, z_near, col), K, np.random.default_rng(0))
    band = out[INNER[0], col - int(width) + 4 : col - 4]  # shadow, away from the jitter
    assert (band == 0).mean() > 0.98
    assert (out[INNER[0], col + 5 : col + 40] == 0).mean() < 0.01  # the lit near surface
    assert (out[INNER[0], 8 : col - 40] == 0).mean() < 0.01  # the far surface, lit
    # The mirrored step: the near object on the left casts no shadow to its right.
    out = S.apply_depth("kinect-v1", step(z_near, z_far, col), K, np.random.default_rng(0))
    assert (out[INNER[0], col + 5 : col + 40] == 0).mean() < 0.01
    assert (out[INNER[0], col - 1 : col + 1] == 0).mean() > 0.75  # the edge itself (jittered)


def test_azure_edges_fly_or_drop() -> None:
    z_near, z_far, col = 0.9, 1.2, W // 2
    out = S.apply_depth("azure-tof", step(z_near, z_far, col), K, np.random.default_rng(0))
    band = out[INNER[0], col - 1 : col + 1]  # the two columns whose 3x3 window straddles it
    holes = (band == 0).mean()
    n = band.size
    assert abs(holes - S.AZURE_EDGE_DROP) < 5 * np.sqrt(0.25 / n)
    kept = band[band > 0]
    assert np.all((kept > z_near - 0.01) & (kept < z_far + 0.01))
    assert ((kept > z_near + 0.01) & (kept < z_far - 0.01)).mean() > 0.9  # flying pixels
    assert (out[INNER[0], col + 2 : col + 60] == 0).mean() == 0
    assert (out[INNER[0], 8 : col - 2] == 0).mean() == 0


def test_azure_dark_surfaces_drop() -> None:
    levels = np.array([0, 10, 15, 20, 27.5, 35, 40, 80], np.float64)
    band = W // len(levels)
    rgb = np.zeros((H, W, 3), np.uint8)
    for i, y in enumerate(levels):
        rgb[:, i * band : (i + 1) * band] = np.round(y)
    out = S.apply_depth("azure-tof", plane(1.0), K, np.random.default_rng(0), rgb=rgb)
    for i, y in enumerate(levels):
        y = float(np.round(y))
        p = min(max((40.0 - y) / 25.0, 0.0), 1.0)  # 1 at and below 15, 0 from 40 on
        measured = (out[:, i * band : (i + 1) * band] == 0).mean()
        n = H * band
        assert abs(measured - p) <= 5 * np.sqrt(p * (1 - p) / n) + 1e-9, (y, measured, p)
    assert (S.apply_depth("azure-tof", plane(1.0), K, np.random.default_rng(0)) > 0).all()


@pytest.mark.parametrize("model", NOISY)
def test_holes_are_exactly_zero_and_range_holds(model: str) -> None:
    lo, hi = S.KINECT_RANGE if model == "kinect-v1" else S.AZURE_RANGE
    depth = step(0.3, 0.8)
    depth[: H // 2, : W // 4] = 0.0  # nothing there
    depth[H // 2 :, : W // 4] = 6.0  # beyond range
    out = S.apply_depth(model, depth, K, np.random.default_rng(0))
    assert out.dtype == np.float32 and out.shape == (H, W)
    holes = out == 0
    assert np.all(np.isfinite(out)) and not np.signbit(out).any()
    assert np.all((out[~holes] >= lo) & (out[~holes] <= hi))
    # Nothing, too far, too near (azure-tof's pixels on the far/near edge may fly into range).
    assert holes[:, : W // 4 - 1].all() and holes[:, W // 4 + 1 : W // 2 - 4].all()
    assert not holes[INNER[0], W // 2 + 4 : -8].any()


@pytest.mark.parametrize("model", NOISY)
def test_depth_seeded(model: str) -> None:
    depth, rgb = step(0.9, 1.2), np.full((H, W, 3), 25, np.uint8)
    a = S.apply_depth(model, depth, K, np.random.default_rng(7), rgb)
    b = S.apply_depth(model, depth, K, np.random.default_rng(7), rgb)
    c = S.apply_depth(model, depth, K, np.random.default_rng(8), rgb)
    assert a.tobytes() == b.tobytes()
    assert a.tobytes() != c.tobytes()


def test_ideal_is_the_identity() -> None:
    rng = np.random.default_rng(3)
    depth = (rng.random((H, W)) * 60).astype(np.float32)
    rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    before = rng.bit_generator.state
    out = S.apply_depth("ideal", depth, K, rng, rgb)
    assert out.tobytes() == depth.tobytes() and out is not depth
    assert S.apply_rgb("ideal", rgb, rng).tobytes() == rgb.tobytes()
    assert rng.bit_generator.state == before  # draws nothing
    out_rgb, out_depth = S.Sensor().apply(rgb, depth, K, seed=5)
    assert out_rgb.tobytes() == rgb.tobytes() and out_depth.tobytes() == depth.tobytes()


def srgb(lin: float) -> float:
    return 12.92 * lin if lin <= 0.0031308 else 1.055 * lin ** (1 / 2.4) - 0.055


def srgb_inverse(v: float) -> float:
    return v / 12.92 if v <= 0.04045 else ((v + 0.055) / 1.055) ** 2.4


def test_camera_noise_matches_poisson_gaussian_formula() -> None:
    exposure = S.Exposure(gain=1.1, white_balance=(1.05, 1.0, 0.93), blur_sigma=0.7)
    n_full, read = S.CAMERA_FULL_WELL, S.CAMERA_READ_NOISE
    for level in (60, 128, 200):
        img = np.full((200, 200, 3), level, np.uint8)
        out = S.apply_rgb("camera", img, np.random.default_rng(level), exposure)[10:-10, 10:-10]
        lin = srgb_inverse(level / 255)
        for c, w in enumerate(exposure.white_balance):
            mean_lin = lin * exposure.gain * w
            sd_lin = w * np.sqrt(lin * exposure.gain * n_full + read**2) / n_full
            slope = (srgb(mean_lin + 1e-6) - srgb(mean_lin - 1e-6)) / 2e-6
            sd = np.sqrt((255 * slope * sd_lin) ** 2 + 1 / 12)  # delta method + 8-bit rounding
            got = out[..., c].astype(np.float64)
            assert abs(got.mean() - 255 * srgb(mean_lin)) < 0.5, (level, c)
            assert abs(got.std() / sd - 1) < 0.1, (level, c, got.std(), sd)


def test_camera_changes_the_image_within_bounds_and_is_seeded() -> None:
    v, u = np.mgrid[0:H, 0:W]
    rgb = np.stack([u * 255 // W, v * 255 // H, (u + v) * 255 // (W + H)], -1).astype(np.uint8)
    a = S.apply_rgb("camera", rgb, np.random.default_rng(1))
    b = S.apply_rgb("camera", rgb, np.random.default_rng(1))
    c = S.apply_rgb("camera", rgb, np.random.default_rng(2))
    assert a.dtype == np.uint8 and a.shape == rgb.shape
    assert a.tobytes() == b.tobytes() and a.tobytes() != c.tobytes()
    diff = np.abs(a.astype(np.int16) - rgb.astype(np.int16))
    assert 0.5 < diff.mean() < 30
    assert abs(a.astype(np.float64).mean() - rgb.astype(np.float64).mean()) < 40
    for seed in range(20):
        e = S.episode_exposure(seed)
        assert S.CAMERA_BLUR[0] <= e.blur_sigma <= S.CAMERA_BLUR[1]
        assert abs(np.log(e.gain)) < 5 * S.CAMERA_EXPOSURE_LOG_SIGMA
        assert np.all(np.abs(np.log(e.white_balance)) < 5 * S.CAMERA_WB_LOG_SIGMA)


def test_sensor_names_round_trip() -> None:
    for name in S.SENSOR_NAMES:
        assert S.Sensor.parse(name).name == name
    assert S.Sensor.parse("azure-tof+camera") == S.Sensor("azure-tof", "camera")
    assert S.Sensor.parse("kinect-v1") == S.Sensor("kinect-v1", "ideal")
    assert S.Sensor().name == "ideal"
    assert S.Sensor("ideal", "camera").name == "ideal+camera"


@pytest.mark.parametrize(
    "call",
    [
        lambda: S.Sensor.parse("kinect-v2"),
        lambda: S.Sensor.parse("camera"),
        lambda: S.Sensor.parse("azure-tof+hdr"),
        lambda: S.Sensor(depth="lidar"),
        lambda: S.Sensor(rgb="hdr"),
        lambda: S.apply_depth("lidar", plane(1.0), K, np.random.default_rng(0)),
        lambda: S.apply_rgb("hdr", np.zeros((4, 4, 3), np.uint8), np.random.default_rng(0)),
        lambda: S.sigma_z("lidar", 1.0),
    ],
)
def test_bad_names_are_one_line_errors(call) -> None:
    with pytest.raises(UnknownNameError) as info:
        call()
    message = str(info.value)
    assert "\n" not in message and "valid" in message
    assert any(name in message for name in ("kinect-v1", "camera"))


def test_bad_images_are_refused() -> None:
    rng = np.random.default_rng(0)
    with pytest.raises(InvalidArgumentError):
        S.apply_depth("kinect-v1", np.zeros((4, 4, 1), np.float32), K, rng)
    with pytest.raises(InvalidArgumentError):
        S.apply_depth("kinect-v1", np.full((4, 4), np.nan, np.float32), K, rng)
    with pytest.raises(InvalidArgumentError):
        S.apply_depth("azure-tof", plane(1.0), K, rng, rgb=np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(InvalidArgumentError):
        S.apply_rgb("camera", np.zeros((4, 4, 3), np.float32), rng)


def test_sensor_apply_is_seeded_per_episode() -> None:
    sensor = S.Sensor.parse("kinect-v1+camera")
    depth, rgb = step(0.9, 1.2), np.full((H, W, 3), 90, np.uint8)
    rgb_a, depth_a = sensor.apply(rgb, depth, K, seed=11)
    rgb_b, depth_b = sensor.apply(rgb, depth, K, seed=11)
    rgb_c, depth_c = sensor.apply(rgb, depth, K, seed=12)
    assert rgb_a.tobytes() == rgb_b.tobytes() and depth_a.tobytes() == depth_b.tobytes()
    assert rgb_a.tobytes() != rgb_c.tobytes() and depth_a.tobytes() != depth_c.tobytes()
    rgb_only, no_depth = sensor.apply(rgb, None, K, seed=11)
    assert no_depth is None
    assert rgb_only.tobytes() == rgb_a.tobytes()  # the same colour image with depth or without
    # Apart from the scene's stream of the same seed, from each other and from other frames.
    streams = [
        S.sensor_rng(11, 0, "depth"),
        S.sensor_rng(11, 0, "rgb"),
        S.sensor_rng(11, 1, "depth"),
        S.sensor_rng(11, 1, "rgb"),
        np.random.default_rng(11),
    ]
    assert len({g.random(4).tobytes() for g in streams}) == len(streams)
    with pytest.raises(UnknownNameError, match="valid sensor images: depth, rgb"):
        S.sensor_rng(11, 0, "ir")


def _study(name: str):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "studies" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_rendered_planes_match_each_model_sigma_within_10_percent() -> None:
    """studies/sensor_check.py's check: planes rendered at five distances 0.55..1.6 m, each
    noisy depth model's spread against its own sigma_z, and the colour camera's against its
    Poissonian-Gaussian formula on the rendered grey."""
    study = _study("sensor_check")
    rows = study.plane_table(K, (H, W))
    assert [(r["model"], r["z_m"]) for r in rows] == [
        (m, round(float(z), 4)) for m in NOISY for z in DISTANCES
    ]
    for r in rows:
        assert abs(r["ratio"] - 1) < 0.10, r
        assert r["hole_fraction"] == 0 and r["ideal_sigma_mm"] < 0.01, r
        expected = 1000 * paper_sigma(r["model"], r["z_m"])
        assert r["sigma_model_mm"] == pytest.approx(expected, abs=1e-3)
    for r in study.colour_table(K, (H, W)):
        assert abs(r["ratio"] - 1) < 0.10 and 40 < r["level_dn"] < 250, r
        assert r["level_spread_dn"] == 0, r  # a flat grey: the spread is the camera's alone
