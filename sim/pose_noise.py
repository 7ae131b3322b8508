"""Controlled pose errors and their measure, one decomposition both ways.

`PoseNoise` and `perturb_pose` apply errors along the camera ray, across it, in-plane (about the
ray) and out-of-plane; `error_components` splits any pose error into the same four components.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.core.errors import InvalidArgumentError, UnknownNameError
from sim.core.transforms import axis_angle


@dataclass(frozen=True)
class PoseNoise:
    """Controlled pose errors in the camera frame, magnitudes in [m] and [rad].

    Attributes:
        ray: translation along the camera ray through the object origin.
        lateral: translation perpendicular to that ray, in a random direction.
        inplane: rotation about the camera ray (in-plane).
        outplane: rotation about a random axis perpendicular to the ray (out-of-plane).
        mode: "gaussian" draws each error from N(0, magnitude^2); "fixed" applies exactly the
            magnitude with a random sign (ray, in-plane) or direction (lateral, out-of-plane).
    """

    ray: float = 0.0
    lateral: float = 0.0
    inplane: float = 0.0
    outplane: float = 0.0
    mode: str = "gaussian"

    def __post_init__(self) -> None:
        if self.mode not in ("gaussian", "fixed"):
            raise UnknownNameError("noise mode", self.mode, ("gaussian", "fixed"))
        vals = (self.ray, self.lateral, self.inplane, self.outplane)
        if not all(np.isfinite(v) and v >= 0 for v in vals):
            raise InvalidArgumentError("noise magnitudes must be finite and non-negative")


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


def error_components(T_est: np.ndarray, T_true: np.ndarray) -> dict[str, float]:
    """A pose error split the way `PoseNoise` applies it, relative to the true camera ray u.

    Returns:
        ``ray_m``: |translation error along u| [m]; ``lateral_m``: its norm across u [m];
        ``inplane_deg``: the rotation error's twist about u; ``outplane_deg``: its swing about an
        axis perpendicular to u (swing-twist decomposition of R_est R_true^T) [deg].
    """
    T_est, T_true = np.asarray(T_est, float), np.asarray(T_true, float)
    u = T_true[:3, 3] / np.linalg.norm(T_true[:3, 3])
    dt = T_est[:3, 3] - T_true[:3, 3]
    along = float(dt @ u)
    R = T_est[:3, :3] @ T_true[:3, :3].T
    # Unit quaternion (w, v) of R, w >= 0.
    w = np.sqrt(max(0.0, 1.0 + np.trace(R))) / 2.0
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if w > 1e-6:
        v = v / (4.0 * w)
    else:  # a half turn: v is the axis
        _vals, vecs = np.linalg.eigh((R + np.eye(3)) / 2.0)
        v = vecs[:, -1]
    twist = float(v @ u)
    # Swing q_s = q_t^-1 q with the twist q_t = (w, twist u) / |.|; its angle by atan2 (stable).
    n = np.hypot(w, twist)
    tw, tv = (w / n, twist / n * u) if n > 1e-12 else (1.0, np.zeros(3))
    sw = tw * w + tv @ v
    sv = tw * v - w * tv - np.cross(tv, v)
    return {
        "ray_m": abs(along),
        "lateral_m": float(np.linalg.norm(dt - along * u)),
        "inplane_deg": float(np.degrees(2.0 * np.arctan2(abs(twist), w))),
        "outplane_deg": float(np.degrees(2.0 * np.arctan2(np.linalg.norm(sv), abs(sw)))),
    }


#: What `--noise` takes: sigma along the ray and across it [mm], in-plane and out-of-plane [deg].
NOISE_FORMAT = "RAY_MM,LATERAL_MM,INPLANE_DEG,OUTPLANE_DEG"


def parse_noise(text: str) -> PoseNoise:
    """Gaussian `PoseNoise` from ``"RAY_MM,LATERAL_MM,INPLANE_DEG,OUTPLANE_DEG"`` (each a finite
    number >= 0, at most 1000 mm or 180 deg).

    Raises:
        InvalidArgumentError: anything else, with the expected format.
    """
    parts = str(text).split(",")
    try:
        values = [float(v) for v in parts]
    except ValueError:
        values = []
    ok = len(values) == 4 and all(np.isfinite(v) and v >= 0 for v in values)
    if not ok or max(values[:2]) > 1000 or max(values[2:]) > 180:
        raise InvalidArgumentError(
            f"--noise must be {NOISE_FORMAT}: four numbers >= 0 (mm up to 1000, deg up to 180), "
            f"got {text!r}"
        )
    ray, lat, inp, outp = values
    return PoseNoise(ray / 1000, lat / 1000, np.deg2rad(inp), np.deg2rad(outp))
