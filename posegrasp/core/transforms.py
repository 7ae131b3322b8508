"""Rigid transforms, rotations, quaternions and the pinhole intrinsics, written once.

Conventions (docs/DESIGN.md §4): SI units; ``T_a_b`` is the 4x4 transform
that maps coordinates in frame b to frame a; quaternions are ``wxyz`` (MuJoCo's order, through
whose routines every quaternion here is converted); camera frames are OpenCV's (x right, y down,
z forward) and pixel (0, 0) has its centre at (u, v) = (0, 0).
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from posegrasp.core.errors import InvalidArgumentError

#: Largest deviation of R^T R from the identity accepted as a rotation.
ORTHONORMAL_TOL = 1e-6


def as_array(x: object, shape: tuple[int, ...], name: str) -> np.ndarray:
    """``x`` as a finite float64 array of the given shape.

    Raises:
        InvalidArgumentError: not numeric, another shape, or a NaN or infinite entry.
    """
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidArgumentError(
            f"{name} must be a numeric array of shape {shape}, got {x!r}"
        ) from None
    if arr.shape != shape:
        raise InvalidArgumentError(f"{name} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InvalidArgumentError(f"{name} must be finite, got {arr!r}")
    return arr


def as_scalar(x: object, name: str) -> float:
    """``x`` as a finite Python float.

    Raises:
        InvalidArgumentError: not a single finite number.
    """
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidArgumentError(f"{name} must be a number, got {x!r}") from None
    if arr.size != 1:
        raise InvalidArgumentError(f"{name} must be a scalar, got shape {arr.shape}")
    value = float(arr.reshape(()))
    if not math.isfinite(value):
        raise InvalidArgumentError(f"{name} must be finite, got {value}")
    return value


# --- rotations ---------------------------------------------------------------------------------


def rot_x(angle: float) -> np.ndarray:
    """Rotation about x by ``angle`` [rad]; returns (3, 3)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle: float) -> np.ndarray:
    """Rotation about y by ``angle`` [rad]; returns (3, 3)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle: float) -> np.ndarray:
    """Rotation about z by ``angle`` [rad]; returns (3, 3)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix of ``angle`` [rad] about ``axis`` (normalised here; Rodrigues)."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    Kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * Kx + (1 - np.cos(angle)) * Kx @ Kx


# --- quaternions (w, x, y, z) ------------------------------------------------------------------


def quat_to_mat(q: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of a quaternion (w, x, y, z), normalised first."""
    q = np.asarray(q, dtype=float)
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, q / np.linalg.norm(q))
    return mat.reshape(3, 3)


def mat_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix, with w >= 0."""
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=float).reshape(9))
    return q if q[0] >= 0 else -q


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of two quaternions (w, x, y, z)."""
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, np.asarray(a, float), np.asarray(b, float))
    return out


def yaw_quat(yaw: float) -> np.ndarray:
    """Quaternion (w, x, y, z) of a rotation by ``yaw`` [rad] about z."""
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


# --- rigid transforms --------------------------------------------------------------------------


def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Build a 4x4 transform from a rotation (3, 3) and a translation (3,) or (3, 1) [m]."""
    R = as_array(R, (3, 3), "R")
    t = as_array(np.asarray(t, dtype=np.float64).reshape(-1), (3,), "t")
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def invert_transform(T_a_b: np.ndarray) -> np.ndarray:
    """Invert a rigid transform: returns ``T_b_a`` (4, 4) from ``T_a_b`` (4, 4)."""
    T_a_b = as_array(T_a_b, (4, 4), "T_a_b")
    R = T_a_b[:3, :3]
    T_b_a = np.eye(4)
    T_b_a[:3, :3] = R.T
    T_b_a[:3, 3] = -R.T @ T_a_b[:3, 3]
    return T_b_a


def rigid_problem(T: object, tol: float = ORTHONORMAL_TOL) -> str | None:
    """What keeps ``T`` from being a finite 4x4 rigid transform, or None when it is one.

    Args:
        T: the candidate transform.
        tol: accepted deviation of R^T R from the identity.
    """
    T = np.asarray(T)
    if T.shape != (4, 4):
        return f"must have shape (4, 4), got {T.shape}"
    if not np.issubdtype(T.dtype, np.number) or np.iscomplexobj(T):
        return f"must be a real-valued 4x4 transform, got dtype {T.dtype}"
    T = T.astype(np.float64)
    if not np.all(np.isfinite(T)):
        return "contains NaN or infinite values"
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > tol or np.linalg.det(R) <= 0.0:
        return "must have a proper rotation block (orthonormal, det +1)"
    if np.abs(T[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-9:
        return "last row must be [0, 0, 0, 1]"
    return None


def check_rigid(T: object, name: str = "pose", tol: float = ORTHONORMAL_TOL) -> np.ndarray:
    """``T`` as a float64 (4, 4) array when it is a finite rigid transform.

    Raises:
        InvalidArgumentError: otherwise, naming ``name`` and what is wrong.
    """
    problem = rigid_problem(T, tol)
    if problem is not None:
        raise InvalidArgumentError(f"{name} {problem}")
    return np.asarray(T, dtype=np.float64)


# --- pinhole camera ----------------------------------------------------------------------------


def intrinsics(fovy: float, width: int, height: int) -> np.ndarray:
    """Pinhole intrinsics of a MuJoCo camera (docs/DESIGN.md §4).

    Args:
        fovy: Vertical field of view [rad], in (0, pi).
        width: Image width W [px].
        height: Image height H [px].

    Returns:
        K (3, 3) with ``fy = (H/2) / tan(fovy/2)``, ``fx = fy``, ``cx = (W-1)/2``,
        ``cy = (H-1)/2``.

    Raises:
        InvalidArgumentError: fovy outside (0, pi), or a size that is not a positive integer.
    """
    fovy = as_scalar(fovy, "fovy")
    if not 0.0 < fovy < math.pi:
        raise InvalidArgumentError(f"fovy must be in (0, pi) radians, got {fovy}")
    if int(width) != width or int(height) != height or width <= 0 or height <= 0:
        raise InvalidArgumentError(
            f"width and height must be positive integers, got {width}x{height}"
        )
    fy = (height / 2.0) / math.tan(fovy / 2.0)
    return np.array([[fy, 0.0, (width - 1) / 2.0], [0.0, fy, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def check_intrinsics(K: object) -> np.ndarray:
    """``K`` as a float64 (3, 3) pinhole matrix: finite, positive focal lengths, upper
    triangular with last row (0, 0, 1).

    Raises:
        InvalidArgumentError: otherwise.
    """
    K = as_array(K, (3, 3), "K")
    if K[0, 0] <= 0.0 or K[1, 1] <= 0.0:
        raise InvalidArgumentError(
            f"K must have positive focal lengths, got fx={K[0, 0]}, fy={K[1, 1]}"
        )
    if K[2, 0] != 0.0 or K[2, 1] != 0.0 or K[2, 2] != 1.0 or K[1, 0] != 0.0:
        raise InvalidArgumentError(f"K must be upper triangular with last row (0, 0, 1), got\n{K}")
    return K
