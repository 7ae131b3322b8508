"""Texture patterns of the `table_texture` and `walls` scene shifts, drawn from a random stream.

Every pattern is an RGB image, shape (H, W, 3), uint8, that tiles seamlessly (the materials
repeat their textures), and overwrites a texture of the compiled model in place: the texture
keeps its name, size and material, so nothing but the image changes. Colours are RGB in [0, 1].
"""

from __future__ import annotations

import colorsys

import mujoco
import numpy as np

#: Wood tones of the table's mild level: light oak, maple, cherry, walnut, grey-washed ash.
WOOD_TONES = (
    (0.68, 0.55, 0.38),
    (0.74, 0.62, 0.45),
    (0.6, 0.38, 0.25),
    (0.45, 0.33, 0.22),
    (0.58, 0.54, 0.48),
)
#: The patterns of the medium and strong levels.
PATTERNS = ("checker", "stripes", "noise")


def hsv(h: float, s: float, v: float) -> np.ndarray:
    """RGB (3,) of a hue, saturation and value, each in [0, 1]."""
    return np.array(colorsys.hsv_to_rgb(h % 1.0, s, v))


def smooth_noise(h: int, w: int, cells: int, rng: np.random.Generator) -> np.ndarray:
    """Periodic smooth noise in [0, 1], shape (h, w): white noise low-passed to about `cells`
    blobs across the image (in the Fourier domain, so it tiles)."""
    spec = np.fft.fft2(rng.standard_normal((h, w)))
    fy, fx = np.fft.fftfreq(h)[:, None] * h, np.fft.fftfreq(w)[None, :] * w
    noise = np.real(np.fft.ifft2(spec * np.exp(-(fx**2 + fy**2) / (2.0 * cells**2))))
    return (noise - noise.min()) / max(float(np.ptp(noise)), 1e-12)


def wood(h: int, w: int, tone: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Wood grain along x in a tone: rings bent by smooth noise, +-8 % of the tone, (h, w, 3)."""
    y = np.arange(h)[:, None] / h
    grain = np.sin(2 * np.pi * (8 * y + 0.6 * smooth_noise(h, w, 2, rng)))
    shade = 1.0 + 0.08 * grain + 0.04 * (smooth_noise(h, w, 24, rng) - 0.5)
    return _rgb(shade[..., None] * tone)


def two_tone(
    kind: str,
    h: int,
    w: int,
    a: np.ndarray,
    b: np.ndarray,
    rng: np.random.Generator,
    squares: int | None = None,
) -> np.ndarray:
    """A pattern of two colours a and b, (h, w, 3): ``checker`` squares (`squares` a side, else
    4, 6 or 8), ``stripes`` (4 to 10 across x or y), ``noise`` (smooth blobs)."""
    y, x = np.mgrid[0:h, 0:w]
    if kind == "checker":
        drawn = 2 * int(rng.integers(2, 5))  # even, so that the squares tile
        n = squares or drawn
        t = ((x * n // w + y * n // h) % 2).astype(float)
    elif kind == "stripes":
        n = int(rng.integers(2, 6))
        c, size = (x, w) if rng.random() < 0.5 else (y, h)
        t = ((c * 2 * n // size) % 2).astype(float)
    else:
        t = np.clip((smooth_noise(h, w, 4, rng) - 0.5) * 3 + 0.5, 0.0, 1.0)
    return _rgb(a + t[..., None] * (b - a))


def _rgb(image: np.ndarray) -> np.ndarray:
    return np.round(np.clip(image, 0.0, 1.0) * 255).astype(np.uint8)


def texture_colours(model: mujoco.MjModel, name: str) -> np.ndarray:
    """The two colours of texture `name`: the mean of its darker and of its lighter half of
    pixels, (2, 3) RGB in [0, 1]."""
    pixels = texture_pixels(model, name)[:, :3] / 255.0
    order = np.argsort(pixels.sum(axis=1), kind="stable")
    half = len(order) // 2
    return np.stack([pixels[order[:half]].mean(axis=0), pixels[order[half:]].mean(axis=0)])


def set_texture(model: mujoco.MjModel, name: str, image: np.ndarray) -> None:
    """Overwrite the 2D RGB texture `name` of a compiled model with `image`, shape (H, W, 3),
    uint8, of the texture's own size."""
    pixels = texture_pixels(model, name)
    pixels[:] = image[..., : pixels.shape[1]].reshape(pixels.shape)


def texture_size(model: mujoco.MjModel, name: str) -> tuple[int, int]:
    """(height, width) of texture `name` [px]."""
    t = model.texture(name).id
    return int(model.tex_height[t]), int(model.tex_width[t])


def texture_pixels(model: mujoco.MjModel, name: str) -> np.ndarray:
    """The pixels of texture `name`, (H * W, channels) uint8: a view of the model's `tex_data`."""
    t = model.texture(name).id
    h, w = texture_size(model, name)
    adr, c = int(model.tex_adr[t]), int(model.tex_nchannel[t])
    return model.tex_data[adr : adr + h * w * c].reshape(-1, c)
