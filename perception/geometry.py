"""The 4D pose representation and the exact virtual-to-real camera correction (numpy).

Implements docs/DESIGN.md §4-§6 (Staszak & Belter 2019, eqs. 1-5, with the exact pinhole form of
eq. 5). Frames:

- ``C``: the real camera, OpenCV convention (x right, y down, z forward).
- ``C'``: the virtual camera, same origin as ``C``, whose +z axis passes through the object origin.
- ``O``: the object frame (origin at the centre of the object's 3D bounding box).

``T_a_b`` is a 4x4 float64 homogeneous transform mapping coordinates in frame ``b`` to frame ``a``.
Units: metres, radians, pixels (pixel (0, 0) has its centre at (u, v) = (0, 0)).
"""

from __future__ import annotations

import math

import numpy as np

from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.transforms import (
    as_array,
    as_scalar,
    check_intrinsics,
    check_rigid,
    invert_transform,
    make_transform,
    rot_x,
    rot_y,
    rot_z,
)

# Below this value of z_x^2 + z_y^2 the optical axis is parallel to O's z (docs/DESIGN.md §5).
SINGULAR_EPS = 1e-9


def project(K: np.ndarray, pts_C: np.ndarray) -> np.ndarray:
    """Project points given in the camera frame C onto the image.

    Args:
        K: Intrinsics (3, 3).
        pts_C: Points in C [m], shape (3,) or (N, 3); each must have z > 0.

    Returns:
        Pixel coordinates (u, v) [px], shape (2,) or (N, 2) matching the input.
    """
    K = check_intrinsics(K)
    pts = np.asarray(pts_C, dtype=np.float64)
    single = pts.shape == (3,)
    pts = np.atleast_2d(pts)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InvalidArgumentError(f"pts_C must have shape (3,) or (N, 3), got {np.shape(pts_C)}")
    if not np.all(np.isfinite(pts)):
        raise InvalidArgumentError("pts_C must be finite")
    if np.any(pts[:, 2] <= 0.0):
        raise InvalidArgumentError("pts_C must lie in front of the camera (z > 0)")
    h = pts @ K.T
    uv = h[:, :2] / h[:, 2:3]
    return uv[0] if single else uv


def pixel_ray(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Unit direction (3,) in C of the ray through pixel ``uv`` (2,) [px]."""
    uv = as_array(uv, (2,), "uv")
    K = check_intrinsics(K)
    d = np.linalg.solve(K, np.array([uv[0], uv[1], 1.0]))
    return d / np.linalg.norm(d)


def r_corr(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Rotation ``R_C_C'`` that turns the virtual camera's axis onto the ray through ``uv``.

    docs/DESIGN.md §6 (exact form of paper eq. 5): with ``(x_n, y_n, 1) = K^-1 (u, v, 1)``,
    ``alpha = atan(x_n)``, ``beta = -asin(y_n / sqrt(x_n^2 + y_n^2 + 1))`` and
    ``R_corr = Ry(alpha) @ Rx(beta)``, so ``R_corr @ (0, 0, 1)`` is the unit ray through (u, v).

    Args:
        uv: Pixel (u, v) [px] where the object origin projects, shape (2,).
        K: Intrinsics (3, 3).

    Returns:
        R_C_C' (3, 3), mapping C' coordinates to C.
    """
    uv = as_array(uv, (2,), "uv")
    K = check_intrinsics(K)
    x_n, y_n, _ = np.linalg.solve(K, np.array([uv[0], uv[1], 1.0]))
    return ray_correction(x_n, y_n)


def ray_correction(x_n: float, y_n: float) -> np.ndarray:
    """`r_corr` of the ray through the normalised image point (x_n, y_n, 1): a point (x, y, z)
    of C with z > 0 gives it as (x / z, y / z), whatever K."""
    alpha = math.atan(x_n)
    beta = -math.asin(y_n / math.sqrt(x_n * x_n + y_n * y_n + 1.0))
    return rot_y(alpha) @ rot_x(beta)


def axes_from_p(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The theta = 0 axes (x, y, z) of C' in O for a camera at ``p`` (docs/DESIGN.md §5, eqs. 1-3).

    ``z = -p/|p|``; ``x = (z_y, -z_x, 0)/sqrt(z_x^2 + z_y^2)``; ``y = z x x``. At the singularity
    (``z_x^2 + z_y^2 < 1e-9``) x is (1, 0, 0) made orthogonal to z (Gram-Schmidt), which equals
    (1, 0, 0) exactly when z = (0, 0, +-1) and keeps the rotation orthonormal inside the band.

    Args:
        p: Position of C' in O [m], shape (3,), non-zero.

    Returns:
        Unit vectors x, y, z (each (3,)) expressed in O; ``[x y z]`` is a proper rotation.
    """
    p = as_array(p, (3,), "p")
    norm = float(np.linalg.norm(p))
    if norm == 0.0:
        raise InvalidArgumentError("p must be non-zero (camera at the object origin)")
    z = -p / norm
    s2 = z[0] * z[0] + z[1] * z[1]
    if s2 < SINGULAR_EPS:
        x = np.array([1.0, 0.0, 0.0]) - z[0] * z
        x /= np.linalg.norm(x)
    else:
        x = np.array([z[1], -z[0], 0.0]) / math.sqrt(s2)
    y = np.cross(z, x)
    return x, y, z


def rotation_from_p_theta(p: np.ndarray, theta: float) -> np.ndarray:
    """Rotation ``R_O_C'`` of the virtual camera from the 4D representation (docs/DESIGN.md §5).

    Args:
        p: Position of C' in O [m], shape (3,).
        theta: Roll of C' about its optical axis [rad].

    Returns:
        R_O_C' (3, 3) = ``[x y z] @ Rz(theta)``.
    """
    theta = as_scalar(theta, "theta")
    x, y, z = axes_from_p(p)
    return np.column_stack((x, y, z)) @ rot_z(theta)


def encode(T_C_O: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Encode a ground-truth pose as the network targets (docs/DESIGN.md §5, §6).

    Args:
        T_C_O: Object pose in the real camera (4, 4); the object origin must be in front of
            the camera (z > 0).
        K: Intrinsics (3, 3).

    Returns:
        ``(p, theta, uv)``: p (3,) is the position of C' in O [m]; theta the roll [rad] in
        (-pi, pi]; uv (2,) the pixel [px] where the object origin projects.
    """
    T_C_O = check_rigid(T_C_O, "T_C_O")
    K = check_intrinsics(K)
    uv = project(K, T_C_O[:3, 3])
    R_C_Cv = r_corr(uv, K)
    T_Cv_O = T_C_O.copy()
    T_Cv_O[:3, :] = R_C_Cv.T @ T_C_O[:3, :]
    T_O_Cv = invert_transform(T_Cv_O)
    p = T_O_Cv[:3, 3]
    x, y, _ = axes_from_p(p)
    x_prime = T_O_Cv[:3, 0]
    theta = math.atan2(float(x_prime @ y), float(x_prime @ x))
    return p, theta, uv


def decode(p: np.ndarray, theta: float, uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Decode the 4D representation and the origin pixel into the pose in the real camera.

    Args:
        p: Position of C' in O [m], shape (3,).
        theta: Roll of C' about its optical axis [rad].
        uv: Pixel (u, v) [px] where the object origin projects, shape (2,).
        K: Intrinsics (3, 3).

    Returns:
        T_C_O (4, 4) = ``[[R_corr, 0], [0, 1]] @ inverse(T_O_C')``.
    """
    p = as_array(p, (3,), "p")
    T_O_Cv = make_transform(rotation_from_p_theta(p, theta), p)
    T_Cv_O = invert_transform(T_O_Cv)
    T_C_O = T_Cv_O.copy()
    T_C_O[:3, :] = r_corr(uv, K) @ T_Cv_O[:3, :]
    return T_C_O
