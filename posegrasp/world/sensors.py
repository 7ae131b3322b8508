"""Seeded sensor models of the head camera: what a real depth camera and colour camera return.

A `Sensor` names one depth model (`DEPTH_MODELS`) and one colour model (`RGB_MODELS`) and turns
one rendered frame (the ideal colour image and the ideal depth of `CameraRenderer`) into what
such a sensor would return:

- depth ``ideal``: the rendered depth, unchanged (the default).
- depth ``kinect-v1``: structured light (Microsoft Kinect v1): axial and lateral noise of
  Nguyen, Izadi and Lovell 2012, 1/8 px disparity quantisation, projector shadows, holes at
  depth edges, range 0.4..4 m (`kinect_v1`).
- depth ``azure-tof``: time of flight (Azure Kinect, narrow field of view): axial noise growing
  with depth, flying pixels at depth edges, dropouts on dark surfaces, range 0.5..3.86 m
  (`azure_tof`).
- colour ``ideal``: the rendered image, unchanged (the default).
- colour ``camera``: defocus, exposure and white balance drawn per episode, shot and read
  noise (`camera_rgb`).

Images: depth (H, W) float32, z along the optical axis of the OpenCV camera frame [m] (as
`CameraRenderer.depth`), 0 where the sensor returns nothing (holes, as real sensors and BOP depth
images have them); colour (H, W, 3) uint8 RGB; pixel (u, v) is column u, row v.

Randomness: every model draws only from the `np.random.Generator` it is given; `sensor_rng`
derives an episode's generators from its seed, on streams apart from the scene's (one per image
of a frame), so an episode's sensor noise is the same on every run and its scene is the same
under every sensor.

An episode observes through the sensor its config names
(`sim.episodes.episode.EpisodeConfig.sensor`, ``--sensor NAME`` on the commands); ``ideal``
observes the rendered images unchanged.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from posegrasp.core.errors import InvalidArgumentError, UnknownNameError
from posegrasp.core.transforms import check_intrinsics
from posegrasp.core.validate import check_choice

#: Depth models by name; ``ideal`` is the rendered depth.
DEPTH_MODELS: tuple[str, ...] = ("ideal", "kinect-v1", "azure-tof")
#: Colour models by name; ``ideal`` is the rendered image.
RGB_MODELS: tuple[str, ...] = ("ideal", "camera")
#: Every sensor name `Sensor.parse` accepts: ``DEPTH`` or ``DEPTH+RGB``.
SENSOR_NAMES: tuple[str, ...] = DEPTH_MODELS + tuple(
    f"{d}+{c}" for d in DEPTH_MODELS for c in RGB_MODELS if c != "ideal"
)
#: First word of every sensor generator's seed: keeps sensor noise apart from the scene's stream.
SENSOR_STREAM = 0x5E7502
#: The images of a frame whose noise draws from a stream of its own (`sensor_rng`).
SENSOR_IMAGES: tuple[str, ...] = ("depth", "rgb")

# Kinect v1 (structured light).
#: Projector-to-IR-camera baseline [m]; the projector sits at +x of the camera (image right).
KINECT_BASELINE = 0.075
#: Disparity steps per pixel (1/8 px subpixel disparity).
KINECT_SUBPIXEL = 8
#: Range with a depth value [m].
KINECT_RANGE = (0.4, 4.0)
#: Side of the window [px] and largest disparity spread in it [px] the matcher still accepts.
KINECT_EDGE_WINDOW = 5
KINECT_EDGE_DISPARITY = 1.0
#: Incidence angle the noise formulas are evaluated at, at most [rad].
KINECT_MAX_ANGLE = float(np.deg2rad(80.0))
#: Rounded-Gaussian table: mean offsets from 0 to 1/2 step, spreads 0..(QUANT_T - 1) QUANT_DT.
QUANT_PHASES = 33
QUANT_T = 401
QUANT_DT = 0.01

# Azure Kinect (time of flight, narrow field of view, unbinned).
#: Range with a depth value [m].
AZURE_RANGE = (0.5, 3.86)
#: Depth spread [m] in a 3x3 window above which a pixel mixes foreground and background.
AZURE_EDGE_STEP = 0.03
#: Share of mixed pixels the depth engine invalidates; the rest return a value in between.
AZURE_EDGE_DROP = 0.5
#: Luminance (0..255) at and below which every pixel drops, and above which none does.
AZURE_DARK = (15.0, 40.0)

# Colour camera.
#: Electrons at full scale (the photon count scale of shot noise) and read noise [electrons].
CAMERA_FULL_WELL = 2000.0
CAMERA_READ_NOISE = 3.0
#: Standard deviation of log exposure and of each channel's log white-balance gain.
CAMERA_EXPOSURE_LOG_SIGMA = 0.15
CAMERA_WB_LOG_SIGMA = 0.04
#: Range of the defocus blur's standard deviation [px].
CAMERA_BLUR = (0.5, 1.0)
#: Mean count below which shot noise is drawn exactly; above, from its Gaussian limit.
POISSON_EXACT_BELOW = 20.0


def sensor_rng(seed: int, frame: int = 0, image: str = "depth") -> np.random.Generator:
    """The generator of the noise of one image of frame `frame` in the episode of `seed`.

    Each frame's depth and colour images draw from streams of their own (depth
    ``[SENSOR_STREAM, seed, 2 + frame]``, colour ``[SENSOR_STREAM, seed, 2 + frame, 1]``),
    apart from the scene's (`np.random.default_rng(seed)`), from the episode's camera settings
    (`episode_exposure`) and from each other, so the colour image is the same whether or not
    the depth image is taken.

    Args:
        seed: the episode's seed.
        frame: index of the frame within the episode.
        image: one of `SENSOR_IMAGES`.

    Raises:
        UnknownNameError: an image not in `SENSOR_IMAGES`.
    """
    check_choice(image, SENSOR_IMAGES, "sensor image")
    entropy = [SENSOR_STREAM, int(seed), 2 + int(frame)]
    return np.random.default_rng(entropy + ([1] if image == "rgb" else []))


# --------------------------------------------------------------------------------------------
# Noise formulas


def _real(x: np.ndarray | float) -> np.ndarray:
    """x as an array: float32 kept, anything else as float64."""
    x = np.asarray(x)
    return x if x.dtype == np.float32 else x.astype(np.float64)


def sigma_z(model: str, z: np.ndarray | float, theta: np.ndarray | float = 0.0) -> np.ndarray:
    """Axial (along the optical axis) noise of a depth model's output.

    - ``ideal``: 0.
    - ``kinect-v1``: Nguyen, Izadi and Lovell, "Modeling Kinect Sensor Noise for Improved 3D
      Reconstruction and Tracking", 3DIMPVT 2012, eq. (4):
      ``0.0012 + 0.0019 (z - 0.4)^2 + 0.0001 / sqrt(z) * theta^2 / (pi/2 - theta)^2``, with
      theta clipped to `KINECT_MAX_ANGLE` (quantisation included, as measured).
    - ``azure-tof``: ``0.0005 + 0.001 max(z - 0.5, 0)``, the noise of BlenderProc's
      ``add_kinect_azure_noise`` (Denninger et al., "BlenderProc2", JOSS 2023), fitted to the
      precision Tölgyessy et al. measured ("Evaluation of the Azure Kinect and Its Comparison
      to Kinect V1 and Kinect V2", Sensors 21(2):413, 2021).

    Args:
        model: one of `DEPTH_MODELS`.
        z: depth [m], any shape.
        theta: angle between the surface normal and the optical axis [rad], broadcast with z.

    Returns:
        Standard deviation [m], the broadcast shape of z and theta (float32 for float32 z,
        float64 otherwise).

    Raises:
        UnknownNameError: a model not in `DEPTH_MODELS`.
    """
    check_choice(model, DEPTH_MODELS, "depth model")
    z, theta = _real(z), _real(theta)
    shape = np.broadcast(z, theta).shape
    if model == "ideal":
        return np.zeros(shape, z.dtype)
    if model == "kinect-v1":
        th = np.clip(theta, 0.0, KINECT_MAX_ANGLE).astype(z.dtype)
        angle = 0.0001 / np.sqrt(np.maximum(z, 1e-6)) * (th / (np.pi / 2 - th)) ** 2
        return 0.0012 + 0.0019 * (z - 0.4) ** 2 + angle
    return np.broadcast_to(0.0005 + 0.001 * np.maximum(z - 0.5, 0.0), shape)


def sigma_lateral(model: str, theta: np.ndarray | float = 0.0) -> np.ndarray:
    """Lateral (in the image plane) noise of a depth model [px], per axis.

    ``kinect-v1``: ``0.8 + 0.035 theta / (pi/2 - theta)`` (Nguyen et al. 2012, eq. 3, in
    pixels), theta clipped to `KINECT_MAX_ANGLE`; 0 for the other models.

    Args:
        model: one of `DEPTH_MODELS`.
        theta: angle between the surface normal and the optical axis [rad], any shape.
    """
    check_choice(model, DEPTH_MODELS, "depth model")
    theta = _real(theta)
    if model != "kinect-v1":
        return np.zeros(theta.shape, theta.dtype)
    th = np.clip(theta, 0.0, KINECT_MAX_ANGLE).astype(theta.dtype)
    return 0.8 + 0.035 * th / (np.pi / 2 - th)


@functools.cache
def _quantised_noise_table() -> np.ndarray:
    """``R[i, j]``: the standard deviation r of Gaussian noise (in quantisation steps) whose
    rounded output has standard deviation ``j * QUANT_DT`` steps, for a mean
    ``i / (QUANT_PHASES - 1) / 2`` steps from the nearest level; shape (QUANT_PHASES, QUANT_T).

    The rounded output's variance is summed over levels k exactly:
    ``P_k = Phi((k + 1/2 - p) / r) - Phi((k - 1/2 - p) / r)``.
    """
    from scipy.special import ndtr

    phase = np.linspace(0.0, 0.5, QUANT_PHASES)[:, None, None]
    r = np.linspace(1e-4, QUANT_T * QUANT_DT + 0.5, 1200)[None, :, None]
    k = np.arange(-48, 49, dtype=np.float64)[None, None, :]
    pk = ndtr((k + 0.5 - phase) / r) - ndtr((k - 0.5 - phase) / r)
    mean = (k * pk).sum(-1)
    std = np.sqrt(np.maximum((k * k * pk).sum(-1) - mean**2, 0.0))
    # Make each row strictly increasing in r (below the lowest reachable spread: no noise).
    std = np.maximum.accumulate(std, axis=1) + 1e-9 * np.arange(std.shape[1])
    t = np.arange(QUANT_T) * QUANT_DT
    return np.stack([np.interp(t, row, r[0, :, 0], left=0.0) for row in std]).astype(np.float32)


def quantised_gaussian_sigma(target: np.ndarray, mean_steps: np.ndarray) -> np.ndarray:
    """The Gaussian standard deviation (in quantisation steps) that, rounded to whole steps,
    leaves a spread of `target` steps around a mean of `mean_steps` (a tabulated inverse of the
    exact variance of a rounded Gaussian; 0 where rounding alone spreads more; Sheppard's
    ``sqrt(target^2 - 1/12)`` beyond the table).

    Args:
        target: wanted standard deviation after rounding [steps], any shape.
        mean_steps: the mean before rounding [steps], same shape.
    """
    table = _quantised_noise_table()
    target = target.astype(np.float32)
    off = np.abs(mean_steps - np.rint(mean_steps)).astype(np.float32)
    row = np.rint(off * np.float32(2 * (QUANT_PHASES - 1))).astype(np.intp)
    x = np.minimum(target / np.float32(QUANT_DT), np.float32(QUANT_T - 1.001))
    col = x.astype(np.intp)
    frac = x - col
    r = table[row, col] * (1 - frac) + table[row, col + 1] * frac
    far = np.sqrt(np.maximum(target * target - np.float32(1 / 12), 0))
    return np.where(target > (QUANT_T - 1) * QUANT_DT, far, r)


def azure_dark_drop(luminance: np.ndarray | float) -> np.ndarray:
    """Probability that the time-of-flight sensor returns nothing on a surface of `luminance`.

    Low IR signal invalidates pixels (Azure Kinect DK documentation, "Depth camera:
    invalidation"); the colour image's luminance stands in for the IR amplitude. Every pixel at
    or below ``AZURE_DARK[0]`` drops (BlenderProc's threshold), none above ``AZURE_DARK[1]``,
    linear in between.

    Args:
        luminance: ITU-R BT.601 luma of the colour image, 0..255, any shape.
    """
    lo, hi = AZURE_DARK
    return np.clip((hi - np.asarray(luminance, np.float64)) / (hi - lo), 0.0, 1.0)


# --------------------------------------------------------------------------------------------
# Geometry of a depth image


def incidence_angle(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Angle between each pixel's surface normal and the optical axis, from the depth alone.

    The normal is the cross product of the back-projected surface's derivatives along u and v
    (central differences): ``n ~ (-fx z_u, -fy z_v, z + (u - cx) z_u + (v - cy) z_v)``.

    Args:
        depth: z [m], shape (H, W).
        K: intrinsics (3, 3) [px].

    Returns:
        theta [rad] in [0, pi/2], shape (H, W), float32 (meaningless at depth edges).
    """
    z = depth.astype(np.float32)
    zu, zv = _central_difference(z, 1), _central_difference(z, 0)
    h, w = z.shape
    u = np.arange(w, dtype=np.float32)[None, :] - np.float32(K[0, 2])
    v = np.arange(h, dtype=np.float32)[:, None] - np.float32(K[1, 2])
    nx = np.float32(K[0, 0]) * zu
    ny = np.float32(K[1, 1]) * zv
    nz = z + u * zu + v * zv
    cos = np.abs(nz) / np.maximum(np.sqrt(nx * nx + ny * ny + nz * nz), np.float32(1e-12))
    return np.arccos(np.clip(cos, 0.0, 1.0))


def _central_difference(z: np.ndarray, axis: int) -> np.ndarray:
    """Derivative of z along an axis per pixel: central inside, one-sided at the borders."""
    out = np.empty_like(z)
    a = np.moveaxis(z, axis, 0)
    o = np.moveaxis(out, axis, 0)
    np.subtract(a[2:], a[:-2], out=o[1:-1])
    o[1:-1] *= np.float32(0.5)
    o[0] = a[1] - a[0]
    o[-1] = a[-1] - a[-2]
    return out


def projector_shadow(disparity: np.ndarray) -> np.ndarray:
    """Pixels the projector cannot light: a nearer surface hides them from it.

    The projector sits one baseline to the right (+x) of the camera, so a point at disparity d
    [px] in column u falls in projector column ``u - d``. Along each row, a pixel is shadowed
    when a pixel to its right reaches the same or a smaller projector column (a nearer surface
    lies on the projector's ray to it): shadows fall to the left of near objects.

    Args:
        disparity: ``b f / z`` [px], shape (H, W), 0 where there is no surface.

    Returns:
        Shadowed pixels, shape (H, W), bool.
    """
    w = disparity.shape[1]
    cols = np.arange(w, dtype=np.float32)[None, :]
    q = np.where(disparity > 0, cols - disparity, np.float32(np.inf))
    seen_right = np.minimum.accumulate(q[:, ::-1], axis=1)[:, ::-1]
    nearest_right = np.full_like(q, np.inf)
    nearest_right[:, :-1] = seen_right[:, 1:]
    return (disparity > 0) & (nearest_right < q - np.float32(1e-3))


def shift_nearest(
    image: np.ndarray, sigma: np.ndarray | float, rng: np.random.Generator
) -> np.ndarray:
    """Resample an image at a random displacement: each pixel takes the value of the pixel
    nearest to its own position plus a Gaussian shift (sigma [px] per axis, per pixel; halves
    round to even), clamped to the image.

    Args:
        image: shape (H, W), float32.
        sigma: per-axis standard deviation of the shift [px], scalar or (H, W).
        rng: draws the shifts (u first, then v).

    Returns:
        The resampled image, shape and dtype of `image`.
    """
    import cv2

    h, w = image.shape
    sigma = np.asarray(sigma, np.float32)
    map_u = rng.standard_normal((h, w), dtype=np.float32)
    map_u *= sigma
    map_u += np.arange(w, dtype=np.float32)[None, :]
    map_v = rng.standard_normal((h, w), dtype=np.float32)
    map_v *= sigma
    map_v += np.arange(h, dtype=np.float32)[:, None]
    return cv2.remap(image, map_u, map_v, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)


def _window_extrema(
    image: np.ndarray, valid: np.ndarray, size: int
) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) of the valid values in each size x size window; (0, 0) where none is valid."""
    import cv2

    kernel = np.ones((size, size), np.uint8)
    border = cv2.BORDER_REPLICATE
    hi = cv2.dilate(np.where(valid, image, np.float32(0)), kernel, borderType=border)
    lo = cv2.erode(np.where(valid, image, np.float32(np.inf)), kernel, borderType=border)
    return np.where(np.isfinite(lo), lo, np.float32(0)), hi


# --------------------------------------------------------------------------------------------
# Depth models


def kinect_v1(depth: np.ndarray, K: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Structured-light depth of a Microsoft Kinect v1 (the recipe of Handa et al., "A
    Benchmark for RGB-D Visual Odometry, 3D Reconstruction and SLAM", ICRA 2014, with the noise
    of Nguyen et al. 2012).

    On the ideal depth: (1) holes where the projector is shadowed (`projector_shadow`,
    baseline `KINECT_BASELINE`) and where the disparity spreads by more than
    `KINECT_EDGE_DISPARITY` px in a `KINECT_EDGE_WINDOW` square window (the correlation window
    straddles a depth edge); (2) lateral noise: every pixel is resampled at a Gaussian shift of
    `sigma_lateral` px (`shift_nearest`); (3) axial Gaussian noise, then (4) disparity
    quantised to 1/`KINECT_SUBPIXEL` px (``d = b fx / z``). Nguyen's `sigma_z` was measured on
    quantised output, so the Gaussian part is the one whose rounded disparity has exactly
    `sigma_z` (`quantised_gaussian_sigma`: none where rounding alone spreads more). (5) Values
    outside `KINECT_RANGE` are holes. The incidence angle theta of
    the noise formulas comes from the depth (`incidence_angle`).

    Args:
        depth: ideal z [m], shape (H, W), 0 where nothing.
        K: intrinsics (3, 3) [px].
        rng: draws the shifts (u, v) and the axial noise, in that order.

    Returns:
        z [m], shape (H, W), float32, 0 at holes.
    """
    z = depth.astype(np.float32)
    valid = z > 0
    bf = np.float32(KINECT_BASELINE * K[0, 0])
    disparity = np.where(valid, bf / np.where(valid, z, np.float32(1)), np.float32(0))
    holes = projector_shadow(disparity)
    lo, hi = _window_extrema(disparity, valid, KINECT_EDGE_WINDOW)
    holes |= hi - lo > KINECT_EDGE_DISPARITY
    theta = incidence_angle(z, K)
    src = np.where(valid & ~holes, z, np.float32(0))
    zs = shift_nearest(src, sigma_lateral("kinect-v1", theta), rng)
    noise = rng.standard_normal(z.shape, dtype=np.float32)
    seen = zs > 0
    zs[~seen] = 1.0
    bf8 = bf * np.float32(KINECT_SUBPIXEL)
    step = zs * zs / bf8  # depth of one disparity step at zs [m]
    total = sigma_z("kinect-v1", zs, theta) / step
    zn = zs + quantised_gaussian_sigma(total, bf8 / zs) * step * noise
    seen &= zn > 0
    d = np.rint(bf8 / np.where(seen, zn, np.float32(1)))
    seen &= d > 0
    zq = bf8 / np.where(seen, d, np.float32(1))
    seen &= (zq >= KINECT_RANGE[0]) & (zq <= KINECT_RANGE[1])
    return np.where(seen, zq, np.float32(0)).astype(np.float32)


def luminance(rgb: np.ndarray) -> np.ndarray:
    """ITU-R BT.601 luma of an RGB image, (H, W) float32 in 0..255."""
    c = rgb.astype(np.float32)
    return 0.299 * c[..., 0] + 0.587 * c[..., 1] + 0.114 * c[..., 2]


def azure_tof(
    depth: np.ndarray, K: np.ndarray, rng: np.random.Generator, rgb: np.ndarray | None = None
) -> np.ndarray:
    """Time-of-flight depth of an Azure Kinect (narrow field of view), after BlenderProc's
    ``add_kinect_azure_noise`` (Denninger et al., JOSS 2023) and Tölgyessy et al. 2021.

    On the ideal depth: (1) mixed pixels: where the depth spreads by more than
    `AZURE_EDGE_STEP` in a 3x3 window, a pixel integrates foreground and background; it is
    invalidated with probability `AZURE_EDGE_DROP` and otherwise returns a flying value
    ``lo + a (hi - lo)``, a ~ U(0, 1), between the window's nearest and farthest depths;
    (2) axial Gaussian noise of `sigma_z`; (3) dark surfaces drop with probability
    `azure_dark_drop` of the colour image's luminance (when `rgb` is given); (4) values outside
    `AZURE_RANGE` are holes. Unlike BlenderProc the output is not rounded to millimetres, and
    the explicit mixed pixels replace its 0.25 px bilinear shifts.

    Args:
        depth: ideal z [m], shape (H, W), 0 where nothing.
        K: intrinsics (3, 3) [px] (unused: the model acts per pixel).
        rng: draws the axial noise, the edge choices, the dark dropouts, in that order.
        rgb: the colour image of the same camera, (H, W, 3) uint8, or None (no dark dropouts).

    Returns:
        z [m], shape (H, W), float32, 0 at holes.
    """
    del K
    z = depth.astype(np.float32)
    valid = z > 0
    noise = rng.standard_normal(z.shape, dtype=np.float32)
    lo, hi = _window_extrema(z, valid, 3)
    edge = np.flatnonzero(valid & (hi - lo > AZURE_EDGE_STEP))
    drop = rng.random(edge.size) < AZURE_EDGE_DROP
    mix = rng.random(edge.size, dtype=np.float32)
    flat = z.reshape(-1).copy()
    lo_e = lo.reshape(-1)[edge]
    flat[edge] = lo_e + mix * (hi.reshape(-1)[edge] - lo_e)
    seen_flat = valid.reshape(-1).copy()
    seen_flat[edge[drop]] = False
    z = flat.reshape(z.shape)
    seen = seen_flat.reshape(z.shape)
    zn = z + sigma_z("azure-tof", z).astype(np.float32) * noise
    if rgb is not None:
        seen &= rng.random(z.shape, dtype=np.float32) >= azure_dark_drop(luminance(rgb))
    seen &= (zn >= AZURE_RANGE[0]) & (zn <= AZURE_RANGE[1])
    return np.where(seen, zn, np.float32(0)).astype(np.float32)


def apply_depth(
    model: str,
    depth: np.ndarray,
    K: np.ndarray,
    rng: np.random.Generator,
    rgb: np.ndarray | None = None,
) -> np.ndarray:
    """A depth model applied to one ideal depth image.

    Args:
        model: one of `DEPTH_MODELS`.
        depth: ideal z [m] along the optical axis, (H, W), finite, >= 0 (0 where nothing).
        K: intrinsics (3, 3) [px] of the camera that rendered it.
        rng: the only source of randomness (`sensor_rng`).
        rgb: the colour image of the same camera, (H, W, 3) uint8; ``azure-tof`` drops dark
            surfaces with it.

    Returns:
        z [m], (H, W) float32, 0 at holes; ``ideal`` returns a float32 copy of `depth`.

    Raises:
        UnknownNameError: a model not in `DEPTH_MODELS`.
        InvalidArgumentError: a depth that is not (H, W), finite and >= 0; a bad K; an rgb of
            another size.
    """
    check_choice(model, DEPTH_MODELS, "depth model")
    depth = np.asarray(depth)
    if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.floating):
        raise InvalidArgumentError(f"depth must be an (H, W) float array, got {depth.shape}")
    if not np.all(np.isfinite(depth)) or np.any(depth < 0):
        raise InvalidArgumentError("depth must be finite and >= 0 (0 where nothing)")
    K = check_intrinsics(K)
    if rgb is not None:
        _check_rgb(rgb, depth.shape)
    if model == "ideal":
        return depth.astype(np.float32, copy=True)
    if model == "kinect-v1":
        return kinect_v1(depth, K, rng)
    return azure_tof(depth, K, rng, rgb)


# --------------------------------------------------------------------------------------------
# Colour models


@dataclass(frozen=True)
class Exposure:
    """A colour camera's settings for one episode.

    Attributes:
        gain: exposure relative to the rendered image (light collected per pixel).
        white_balance: per-channel gains (R, G, B) applied after read-out.
        blur_sigma: standard deviation of the defocus blur [px].
    """

    gain: float = 1.0
    white_balance: tuple[float, float, float] = (1.0, 1.0, 1.0)
    blur_sigma: float = 0.0

    @classmethod
    def draw(cls, rng: np.random.Generator) -> Exposure:
        """Settings drawn from rng: log-normal gain (`CAMERA_EXPOSURE_LOG_SIGMA`) and white
        balance (`CAMERA_WB_LOG_SIGMA` per channel), blur uniform in `CAMERA_BLUR`."""
        gain = float(np.exp(rng.normal(0.0, CAMERA_EXPOSURE_LOG_SIGMA)))
        wb = np.exp(rng.normal(0.0, CAMERA_WB_LOG_SIGMA, 3))
        blur = float(rng.uniform(*CAMERA_BLUR))
        return cls(gain, (float(wb[0]), float(wb[1]), float(wb[2])), blur)


def episode_exposure(seed: int) -> Exposure:
    """The camera settings of the episode of `seed` (stream ``[SENSOR_STREAM, seed, 1]``)."""
    return Exposure.draw(np.random.default_rng([SENSOR_STREAM, int(seed), 1]))


def srgb_to_linear(v: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB decoding, values in [0, 1]."""
    v = np.asarray(v, np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(v: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB encoding, values in [0, 1]."""
    v = np.asarray(v, np.float64)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(np.maximum(v, 0), 1 / 2.4) - 0.055)


#: Decoding of every 8-bit code, and encoding to 8 bits of every 16-bit linear code.
_DECODE = srgb_to_linear(np.arange(256) / 255.0).astype(np.float32)
_ENCODE = np.rint(255.0 * linear_to_srgb(np.arange(65536) / 65535.0)).astype(np.uint8)


def camera_rgb(rgb: np.ndarray, rng: np.random.Generator, exposure: Exposure) -> np.ndarray:
    """A colour camera's image of the rendered scene (the Poissonian-Gaussian sensor of Foi et
    al., "Practical Poissonian-Gaussian Noise Modeling and Fitting for Single-Image Raw-Data",
    IEEE TIP 2008; random gains as in Brooks et al., "Unprocessing Images for Learned Raw
    Denoising", CVPR 2019).

    The rendered image is taken as sRGB and decoded to linear light l; blurred by a Gaussian of
    ``exposure.blur_sigma`` px (defocus); collected as ``lam = l * gain * CAMERA_FULL_WELL``
    electrons with shot noise (Poisson, exact below `POISSON_EXACT_BELOW` electrons and its
    Gaussian limit above) and Gaussian read noise of `CAMERA_READ_NOISE` electrons; scaled back
    by the full well and each channel's white-balance gain, clipped to [0, 1], and encoded to
    8-bit sRGB (through 16-bit linear codes). Per channel, a flat patch of linear value l reads
    linear mean ``m = l g w_c`` with standard deviation
    ``w_c sqrt(l g N + r^2) / N`` (N the full well, r the read noise).

    Args:
        rgb: (H, W, 3) uint8.
        rng: draws the bright pixels' noise, then the dim pixels' shot and read noise.
        exposure: the episode's camera settings.

    Returns:
        (H, W, 3) uint8.
    """
    import cv2

    lin = _DECODE[rgb]
    if exposure.blur_sigma > 0:
        lin = cv2.GaussianBlur(lin, (0, 0), exposure.blur_sigma, borderType=cv2.BORDER_REFLECT)
    lam = lin * np.float32(exposure.gain * CAMERA_FULL_WELL)
    read2 = np.float32(CAMERA_READ_NOISE**2)
    # Shot plus read noise as one Gaussian of variance lam + r^2 where the count is large.
    electrons = rng.standard_normal(lam.shape, dtype=np.float32)
    electrons *= np.sqrt(lam + read2)
    electrons += lam
    dim = np.flatnonzero(lam < POISSON_EXACT_BELOW)
    shot = rng.poisson(lam.reshape(-1)[dim]).astype(np.float32)
    read = rng.standard_normal(dim.size, dtype=np.float32) * np.float32(CAMERA_READ_NOISE)
    electrons.reshape(-1)[dim] = shot + read
    gains = np.asarray(exposure.white_balance, np.float32) / np.float32(CAMERA_FULL_WELL)
    signal = np.clip(electrons * gains, 0.0, 1.0)
    return _ENCODE[np.rint(signal * np.float32(65535)).astype(np.int32)]


def apply_rgb(
    model: str, rgb: np.ndarray, rng: np.random.Generator, exposure: Exposure | None = None
) -> np.ndarray:
    """A colour model applied to one rendered image.

    Args:
        model: one of `RGB_MODELS`.
        rgb: (H, W, 3) uint8.
        rng: the frame's noise (`sensor_rng`).
        exposure: the episode's camera settings (`episode_exposure`); drawn from rng when None.

    Returns:
        (H, W, 3) uint8; ``ideal`` returns a copy of `rgb`.

    Raises:
        UnknownNameError: a model not in `RGB_MODELS`.
        InvalidArgumentError: an image that is not (H, W, 3) uint8.
    """
    check_choice(model, RGB_MODELS, "colour model")
    _check_rgb(rgb, None)
    if model == "ideal":
        return rgb.copy()
    return camera_rgb(rgb, rng, exposure if exposure is not None else Exposure.draw(rng))


def _check_rgb(rgb: np.ndarray, shape: Sequence[int] | None) -> None:
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise InvalidArgumentError(
            f"rgb must be an (H, W, 3) uint8 image, got {rgb.shape} {rgb.dtype}"
        )
    if shape is not None and rgb.shape[:2] != tuple(shape):
        raise InvalidArgumentError(f"rgb is {rgb.shape[:2]} but depth is {tuple(shape)}")


# --------------------------------------------------------------------------------------------
# Sensors by name


@dataclass(frozen=True)
class Sensor:
    """The head camera's sensor: one depth model and one colour model.

    Attributes:
        depth: one of `DEPTH_MODELS`.
        rgb: one of `RGB_MODELS`.

    Raises:
        UnknownNameError: a model not among the valid ones.
    """

    depth: str = "ideal"
    rgb: str = "ideal"

    def __post_init__(self) -> None:
        check_choice(self.depth, DEPTH_MODELS, "depth model")
        check_choice(self.rgb, RGB_MODELS, "colour model")

    @property
    def name(self) -> str:
        """``DEPTH`` with the ideal colour model, ``DEPTH+RGB`` otherwise (`SENSOR_NAMES`)."""
        return self.depth if self.rgb == "ideal" else f"{self.depth}+{self.rgb}"

    @classmethod
    def parse(cls, spec: str) -> Sensor:
        """A sensor from its name, ``DEPTH`` or ``DEPTH+RGB`` (e.g. ``azure-tof+camera``).

        Raises:
            UnknownNameError: a name not in `SENSOR_NAMES` (one line listing them).
        """
        spec = str(spec).strip()
        if spec not in SENSOR_NAMES:
            raise UnknownNameError("sensor", spec, SENSOR_NAMES)
        depth, _, rgb = spec.partition("+")
        return cls(depth, rgb or "ideal")

    def apply(
        self,
        rgb: np.ndarray,
        depth: np.ndarray | None,
        K: np.ndarray,
        seed: int,
        frame: int = 0,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """One frame of the episode of `seed` as this sensor sees it: the same noise on every
        run (`sensor_rng(seed, frame, "depth")` and `sensor_rng(seed, frame, "rgb")`, settings
        from `episode_exposure(seed)`), and the same colour image with depth or without.

        The depth model sees the ideal colour image (dark surfaces are a property of the
        scene, not of the colour camera's noise).

        Args:
            rgb: the rendered colour image, (H, W, 3) uint8.
            depth: the rendered depth, (H, W) float [m], or None (no depth observed).
            K: intrinsics (3, 3) [px].
            seed: the episode's seed.
            frame: index of the frame within the episode.

        Returns:
            (rgb (H, W, 3) uint8, depth (H, W) float32 [m] with holes 0, or None).
        """
        out_depth = None
        if depth is not None:
            out_depth = apply_depth(self.depth, depth, K, sensor_rng(seed, frame, "depth"), rgb)
        exposure = episode_exposure(seed) if self.rgb == "camera" else None
        out_rgb = apply_rgb(self.rgb, rgb, sensor_rng(seed, frame, "rgb"), exposure)
        return out_rgb, out_depth
