"""The studio's bank of background textures: MuJoCo builtin and numpy-made, in random colours.

Half of the bank is numpy-made (smooth noise, stripes or blobs between two random colours), half
MuJoCo builtin textures (checker, gradient, flat with noise marks). The bank is drawn from one
fixed seed, so it is part of the generator's definition rather than of any sample.
"""

from __future__ import annotations

import cv2
import mujoco
import numpy as np

#: Name of the white texture of plain (untextured-looking) surfaces.
PLAIN_TEXTURE = "plain"


def bank_texture_name(i: int) -> str:
    """Name of texture i of the bank."""
    return f"bank_{i:03d}"


def random_colour(rng: np.random.Generator) -> np.ndarray:
    """A random RGB colour in [0, 1], shape (3,): saturated, pastel or grey with equal chance."""
    kind = rng.integers(3)
    if kind == 0:
        return rng.uniform(0.0, 1.0, 3)
    if kind == 1:
        return rng.uniform(0.5, 1.0, 3)
    return np.full(3, rng.uniform(0.05, 0.95))


def procedural_texture(rng: np.random.Generator, size: int) -> np.ndarray:
    """A (size, size, 3) uint8 texture: smooth noise, stripes or blobs in random colours."""
    c1, c2 = random_colour(rng), random_colour(rng)
    kind = rng.integers(3)
    if kind == 0:
        cells = int(rng.integers(3, 17))
        low = rng.random((cells, cells)).astype(np.float32)
        w = cv2.resize(low, (size, size), interpolation=cv2.INTER_CUBIC)
        w = np.clip(w, 0.0, 1.0)[..., None]
    elif kind == 1:
        v, u = np.mgrid[0:size, 0:size] / size
        angle = rng.uniform(0.0, np.pi)
        freq = float(rng.integers(1, 9))
        phase = np.cos(angle) * u + np.sin(angle) * v
        w = (0.5 + 0.5 * np.sin(2 * np.pi * freq * phase))[..., None]
        if rng.random() < 0.5:
            w = (w > 0.5).astype(np.float64)
    else:
        img = np.zeros((size, size), np.float32)
        for _ in range(int(rng.integers(5, 40))):
            centre = (int(rng.integers(size)), int(rng.integers(size)))
            radius = int(rng.integers(2, size // 4))
            cv2.circle(img, centre, radius, float(rng.uniform(0.3, 1.0)), -1)
        w = img[..., None]
    tex = (1.0 - w) * c1 + w * c2
    return np.clip(np.round(255.0 * tex), 0, 255).astype(np.uint8)


def add_texture_bank(spec: mujoco.MjSpec, n_textures: int, size: int, seed: int) -> list[str]:
    """Add the bank's 2D textures and the plain white one to spec.

    Args:
        spec: the model being built.
        n_textures: size of the bank.
        size: side of each bank texture [px].
        seed: seed of the bank.

    Returns:
        The names of the bank's textures (`bank_texture_name` order; `PLAIN_TEXTURE` excluded).
    """
    rng = np.random.default_rng(seed)
    names = []
    builtins = (
        mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
        mujoco.mjtBuiltin.mjBUILTIN_GRADIENT,
        mujoco.mjtBuiltin.mjBUILTIN_FLAT,
    )
    marks = (
        mujoco.mjtMark.mjMARK_NONE,
        mujoco.mjtMark.mjMARK_EDGE,
        mujoco.mjtMark.mjMARK_CROSS,
        mujoco.mjtMark.mjMARK_RANDOM,
    )
    for i in range(n_textures):
        tex = spec.add_texture()
        tex.name = bank_texture_name(i)
        tex.type = mujoco.mjtTexture.mjTEXTURE_2D
        tex.width = tex.height = size
        if i % 2 == 0:
            tex.nchannel = 3
            tex.data = procedural_texture(rng, size).tobytes()
        else:
            tex.builtin = builtins[rng.integers(len(builtins))]
            tex.rgb1 = random_colour(rng)
            tex.rgb2 = random_colour(rng)
            mark = marks[rng.integers(len(marks))]
            if tex.builtin == mujoco.mjtBuiltin.mjBUILTIN_FLAT:
                mark = mujoco.mjtMark.mjMARK_RANDOM
            tex.mark = mark
            tex.markrgb = random_colour(rng)
            tex.random = float(rng.uniform(0.01, 0.3))
        names.append(tex.name)
    # Plain surfaces use a white texture rather than none: switching a material's texture off at
    # run time (texid -1) leaves the previous frame's texture bound in MuJoCo's renderer.
    tex = spec.add_texture()
    tex.name = PLAIN_TEXTURE
    tex.type = mujoco.mjtTexture.mjTEXTURE_2D
    tex.builtin = mujoco.mjtBuiltin.mjBUILTIN_FLAT
    tex.width = tex.height = 8
    tex.rgb1 = tex.rgb2 = [1.0, 1.0, 1.0]
    return names
