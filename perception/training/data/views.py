"""Camera placement of the paper protocol's studio (`perception.training.data.studio`): where a view
looks from and how it is rolled so that its label's in-plane angle is the one drawn."""

from __future__ import annotations

import numpy as np

from perception.geometry import encode
from posegrasp.core.transforms import rot_z


def roll_to_theta(position: np.ndarray, aim: np.ndarray, theta: float, K: np.ndarray) -> np.ndarray:
    """R_world_cv of a camera at position aimed at aim whose view of the object (at the world
    origin, canonical) has in-plane angle theta [rad].

    theta grows one for one with the camera's roll, offset by a small term that depends on where
    the object lies off the optical axis; a few fixed-point steps remove the offset to 1e-9 rad.
    """
    roll = theta
    for _ in range(6):
        R = look_at(position, aim, roll)
        T_C_O = np.eye(4)
        T_C_O[:3, :3] = R.T
        T_C_O[:3, 3] = -R.T @ position
        err = np.angle(np.exp(1j * (theta - encode(T_C_O, K)[1])))
        if abs(err) < 1e-10:
            break
        roll += err
    return R


def look_at(position: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
    """R_world_cv of a camera at position looking at target, rolled by roll about its axis.

    With roll = 0 the image's x axis is horizontal (perpendicular to world z; world y when the
    camera looks straight up or down).
    """
    z = target - position
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, [0.0, 1.0, 0.0])
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1) @ rot_z(roll)


def unit_vector(rng: np.random.Generator, dim: int = 3) -> np.ndarray:
    """A direction uniform on the unit sphere of R^dim (dim 4: a uniform random quaternion)."""
    v = rng.normal(size=dim)
    return v / np.linalg.norm(v)
