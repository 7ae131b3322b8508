"""Controlled pose errors: `PoseNoise` and `perturb_pose` apply errors along the camera ray,
across it, in-plane (about the ray) and out-of-plane, the four components that
`perception.metrics.error_components` measures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from posegrasp.core.errors import InvalidArgumentError, UnknownNameError
from posegrasp.core.transforms import axis_angle

#: How `PoseNoise` draws its errors.
MODES: tuple[str, ...] = ("gaussian", "fixed", "spread")


@dataclass(frozen=True)
class PoseNoise:
    """Controlled pose errors in the camera frame, magnitudes in [m] and [rad].

    Attributes:
        ray: translation along the camera ray through the object origin.
        lateral: translation perpendicular to that ray, in a random direction.
        inplane: rotation about the camera ray (in-plane).
        outplane: rotation about a random axis perpendicular to the ray (out-of-plane).
        mode: "gaussian" draws each error from N(0, magnitude^2); "fixed" applies exactly the
            magnitude with a random sign (ray, in-plane) or direction (lateral, out-of-plane);
            "spread" first draws each component's sigma uniformly in [0, magnitude], on its own,
            then the error from N(0, sigma^2), so that a sample of episodes covers every mix of
            the four components.
        draw: which stream of errors: 0 (the default) draws each episode's errors from its
            scene seed alone, so every sigma scales the same standard-normal draws (common
            random numbers); another number gives an independent set of errors for the same
            scenes.
    """

    ray: float = 0.0
    lateral: float = 0.0
    inplane: float = 0.0
    outplane: float = 0.0
    mode: str = "gaussian"
    draw: int = 0

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise UnknownNameError("noise mode", self.mode, MODES)
        vals = (self.ray, self.lateral, self.inplane, self.outplane)
        if not all(np.isfinite(v) and v >= 0 for v in vals):
            raise InvalidArgumentError("noise magnitudes must be finite and non-negative")
        if not 0 <= int(self.draw) < 2**32 or int(self.draw) != self.draw:
            raise InvalidArgumentError(f"noise draw must be an integer in 0..{2**32 - 1}")

    def rng(self, seed: int) -> np.random.Generator:
        """The generator of the errors of the episode with scene seed `seed`."""
        key = [int(seed), 7919] if self.draw == 0 else [int(seed), 7919, int(self.draw)]
        return np.random.default_rng(key)


def perturb_pose(T_C_O: np.ndarray, noise: PoseNoise, rng: np.random.Generator) -> np.ndarray:
    """T_C_O with the errors of `noise` applied (rotations about the object's origin)."""
    T = np.array(T_C_O, dtype=float)
    t = T[:3, 3]
    u = t / np.linalg.norm(t)
    # A random unit vector perpendicular to the ray.
    w = np.cross(u, rng.normal(size=3))
    w /= np.linalg.norm(w)
    if noise.mode == "gaussian":
        e_ray, e_lat = rng.normal(0, noise.ray), rng.normal(0, noise.lateral)
        e_in, e_out = rng.normal(0, noise.inplane), rng.normal(0, noise.outplane)
    elif noise.mode == "spread":
        sigma = rng.uniform(0.0, 1.0, 4) * (noise.ray, noise.lateral, noise.inplane, noise.outplane)
        e_ray, e_lat, e_in, e_out = rng.normal(0.0, 1.0, 4) * sigma
    else:
        sign = rng.choice([-1.0, 1.0], size=2)
        e_ray, e_lat = sign[0] * noise.ray, noise.lateral
        e_in, e_out = sign[1] * noise.inplane, noise.outplane
    w2 = np.cross(u, w)  # a second perpendicular direction for the out-of-plane axis
    out = T.copy()
    out[:3, 3] = t + e_ray * u + e_lat * w
    R = axis_angle(u, e_in) @ axis_angle(w2, e_out) @ T[:3, :3]
    out[:3, :3] = R
    return out


#: What `--noise` takes: sigma along the ray and across it [mm], in-plane and out-of-plane [deg];
#: with the prefix ``spread:``, the largest sigmas of the "spread" mode; with the suffix ``@N``,
#: the N-th independent draw of the errors (`PoseNoise.draw`).
NOISE_FORMAT = "[spread:]RAY_MM,LATERAL_MM,INPLANE_DEG,OUTPLANE_DEG[@DRAW]"


def parse_noise(text: str) -> PoseNoise:
    """`PoseNoise` from ``"RAY_MM,LATERAL_MM,INPLANE_DEG,OUTPLANE_DEG"`` (each a finite number
    >= 0, at most 1000 mm or 180 deg): Gaussian, or "spread" with the prefix ``spread:``.

    Raises:
        InvalidArgumentError: anything else, with the expected format.
    """
    raw = str(text)
    mode = "spread" if raw.startswith("spread:") else "gaussian"
    body, at, draw_text = raw.removeprefix("spread:").partition("@")
    draw = int(draw_text) if draw_text.isdigit() and len(draw_text) <= 10 else -1
    if not at:
        draw = 0
    parts = body.split(",")
    try:
        values = [float(v) for v in parts]
    except ValueError:
        values = []
    ok = len(values) == 4 and all(np.isfinite(v) and v >= 0 for v in values)
    ok = ok and 0 <= draw < 2**32
    if not ok or max(values[:2]) > 1000 or max(values[2:]) > 180:
        raise InvalidArgumentError(
            f"--noise must be {NOISE_FORMAT}: four numbers >= 0 (mm up to 1000, deg up to 180) "
            f"and a draw in 0..{2**32 - 1}, got {raw!r}"
        )
    ray, lat, inp, outp = values
    return PoseNoise(ray / 1000, lat / 1000, np.deg2rad(inp), np.deg2rad(outp), mode, draw)
