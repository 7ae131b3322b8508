"""Support-plane refinement of an estimated pose: the object rests on a known horizontal plane.

A tabletop robot knows where its table is. An object lying on it can only be in one of its
resting poses (`sim.objects.ObjectModel.resting_poses`, free yaw about the plane's normal) with
its lowest point on the plane. `refine_on_support` keeps what the image measures best, the ray
through the object's origin (2D-NET) and the yaw about the plane normal (4D-NET), and replaces
what it measures worst, the distance along that ray and the tilt, by the values the plane
allows:

1. Rotation: the resting pose R_k and yaw psi that bring ``Rz(psi) R_k`` nearest to the
   estimated world orientation. With ``M = R_k R_W^T`` the best yaw is
   ``psi = atan2(M01 - M10, M00 + M11)`` (it maximises ``trace(Rz(psi) M)``); the resting pose
   with the smallest geodesic distance wins.
2. Translation: the origin slides along its camera ray to the height at which the object,
   so oriented, touches the plane: ``z_origin = support_z + resting_height(R_k)``.

Each step is skipped (and says so in `SupportRefinement.applied`) when the estimate is too far
from any resting pose, or the ray is too close to parallel to the plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.objects import ObjectModel, _quat_to_mat


@dataclass(frozen=True)
class SupportRefinement:
    """Result of `refine_on_support`.

    Attributes:
        T_C_O: refined pose in the camera frame, shape (4, 4).
        resting_pose: name of the chosen resting pose, or None when the rotation was kept.
        tilt_deg: geodesic angle between the estimated and the snapped rotation [deg].
        shift_m: distance the origin moved along its ray [m] (0 when the translation was kept).
        applied: ("rotation", "translation") or the subset that was applied.
    """

    T_C_O: np.ndarray
    resting_pose: str | None
    tilt_deg: float
    shift_m: float
    applied: tuple[str, ...]


def _geodesic_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def snap_to_resting(R_W_O: np.ndarray, model: ObjectModel) -> tuple[np.ndarray, str, float, float]:
    """The resting orientation (any yaw) nearest to a world-frame orientation.

    Returns:
        (R, name, angle_deg, height): the snapped rotation, its resting pose's name, its geodesic
        distance from R_W_O and the origin's height above the plane when so resting [m].
    """
    best: tuple[np.ndarray, str, float, float] | None = None
    for name, quat in model.resting_poses.items():
        R_k = _quat_to_mat(np.asarray(quat, float))
        M = R_k @ R_W_O.T
        psi = np.arctan2(M[0, 1] - M[1, 0], M[0, 0] + M[1, 1])
        c, s = np.cos(psi), np.sin(psi)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ R_k
        ang = _geodesic_deg(R, R_W_O)
        if best is None or ang < best[2]:
            best = (R, name, ang, model.resting_height(quat))
    if best is None:
        raise ValueError(f"object {model.name!r} has no resting poses")
    return best


def refine_on_support(
    T_C_O: np.ndarray,
    T_world_cam: np.ndarray,
    model: ObjectModel,
    support_z: float,
    max_tilt_deg: float = 45.0,
    min_ray_dz: float = 0.1,
) -> SupportRefinement:
    """Move an estimated pose onto a horizontal support plane (see the module docstring).

    Args:
        T_C_O: estimated pose of the object in the camera frame, (4, 4).
        T_world_cam: camera pose in the world (z up), (4, 4).
        model: the object (its resting poses and mesh).
        support_z: height of the support plane in the world [m].
        max_tilt_deg: estimates further than this from every resting pose keep their rotation
            and translation (the object may not be resting).
        min_ray_dz: the ray must descend at least this much per unit length (|r_z|), otherwise
            the distance along it is kept.

    Returns:
        The refined pose and what was done.
    """
    T_C_O = np.asarray(T_C_O, np.float64)
    T_world_cam = np.asarray(T_world_cam, np.float64)
    R_wc, c_w = T_world_cam[:3, :3], T_world_cam[:3, 3]
    R_W_O = R_wc @ T_C_O[:3, :3]
    R_snap, name, tilt, height = snap_to_resting(R_W_O, model)
    if tilt > max_tilt_deg:
        return SupportRefinement(T_C_O.copy(), None, tilt, 0.0, ())
    out = T_C_O.copy()
    out[:3, :3] = R_wc.T @ R_snap
    applied: tuple[str, ...] = ("rotation",)
    t = T_C_O[:3, 3]
    dist = float(np.linalg.norm(t))
    shift = 0.0
    r_w = R_wc @ (t / dist)
    if r_w[2] < -min_ray_dz:
        lam = (support_z + height - c_w[2]) / r_w[2]
        if lam > 0:
            out[:3, 3] = t / dist * lam
            shift = lam - dist
            applied = ("rotation", "translation")
    return SupportRefinement(out, name, tilt, shift, applied)
