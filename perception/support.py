"""Support-plane refinement of an estimated pose: the object rests on a known horizontal plane.

A tabletop robot knows where its table is. An object lying on it can only be in one of its
resting poses (`posegrasp.world.objects.ObjectModel.resting_poses`, free yaw about the plane's
normal) with its lowest point on the plane. `refine_on_support` keeps what the image
measures best, the ray through the object's origin (2D-NET) and the yaw about the plane
normal (4D-NET), and replaces what it measures worst, the distance along that ray and the
tilt, by the values the plane allows:

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

from perception.geometry import rot_z
from perception.metrics import mask_iou, rotation_error_deg
from perception.overlay import mask_window, silhouette, window_intrinsics
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.transforms import quat_to_mat
from posegrasp.world.objects import ObjectModel


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

    def description(self) -> dict:
        """What an estimate reports of it (``info["support"]``): a new dict each call."""
        return {
            "resting_pose": self.resting_pose,
            "tilt_deg": self.tilt_deg,
            "shift_m": self.shift_m,
            "applied": list(self.applied),
        }


def snap_to_resting(R_W_O: np.ndarray, model: ObjectModel) -> tuple[np.ndarray, str, float, float]:
    """The resting orientation (any yaw) nearest to a world-frame orientation.

    Returns:
        (R, name, angle_deg, height): the snapped rotation, its resting pose's name, its geodesic
        distance from R_W_O and the origin's height above the plane when so resting [m].
    """
    best: tuple[np.ndarray, str, float, float] | None = None
    for name, quat in model.resting_poses.items():
        R_k = quat_to_mat(np.asarray(quat, float))
        M = R_k @ R_W_O.T
        R = rot_z(float(np.arctan2(M[0, 1] - M[1, 0], M[0, 0] + M[1, 1]))) @ R_k
        ang = rotation_error_deg(R, R_W_O)
        if best is None or ang < best[2]:
            best = (R, name, ang, model.resting_height(quat))
    if best is None:
        raise InvalidArgumentError(f"object {model.name!r} has no resting poses")
    return best


def resting_surface_z(T_C_O: np.ndarray, T_world_cam: np.ndarray, model: ObjectModel) -> float:
    """The world height [m] of the horizontal surface an object so posed would rest on: its
    origin's height minus the resting height of the resting pose nearest its orientation
    (`snap_to_resting`, which also gives how far that is)."""
    T_C_O = np.asarray(T_C_O, np.float64)
    T_world_cam = np.asarray(T_world_cam, np.float64)
    R_wc, c_w = T_world_cam[:3, :3], T_world_cam[:3, 3]
    height = snap_to_resting(R_wc @ T_C_O[:3, :3], model)[3]
    return float((R_wc @ T_C_O[:3, 3] + c_w)[2] - height)


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


@dataclass(frozen=True)
class MaskRefinement:
    """Result of `refine_with_mask`.

    Attributes:
        T_C_O: refined pose in the camera frame, shape (4, 4).
        iou_before: silhouette IoU of the input pose with the mask.
        iou_after: the same for the refined pose (>= iou_before).
        yaw_deg: yaw change about the support normal [deg].
        shift_m: (dx, dy) change of the origin on the support plane [m].
        renders: silhouettes rendered.
    """

    T_C_O: np.ndarray
    iou_before: float
    iou_after: float
    yaw_deg: float
    shift_m: tuple[float, float]
    renders: int


def refine_with_mask(
    T_C_O: np.ndarray,
    T_world_cam: np.ndarray,
    K: np.ndarray,
    model: ObjectModel,
    mask: np.ndarray,
    yaw_range_deg: float = 24.0,
    shift_range_m: float = 0.01,
) -> MaskRefinement:
    """Adjust the yaw and the position on the support of a resting pose so that the model's
    silhouette best overlaps a segmentation mask (intersection over union).

    The pose must already rest on the support (`refine_on_support`): yaw turns it about the
    world's vertical through its origin and the shifts move it in the horizontal plane, so it
    keeps resting. Coarse-to-fine search: yaw in 3 degree steps over +-`yaw_range_deg`, then the
    origin on a 3x3 grid of `shift_range_m` / 2 steps, then yaw in 1 degree steps over +-3
    degrees. Silhouettes are rasterised in a window around the mask.

    Args:
        T_C_O: resting pose estimate in the camera frame, (4, 4).
        T_world_cam: camera pose in the world (z up), (4, 4).
        K: intrinsics, (3, 3).
        model: the object (its mesh).
        mask: the object's segmentation in the image, (H, W) bool (e.g. the detector's).
    """
    mask = np.asarray(mask, bool)
    T_C_O = np.asarray(T_C_O, np.float64)
    box = mask_window(mask)
    if box is None:
        return MaskRefinement(T_C_O.copy(), 0.0, 0.0, 0.0, (0.0, 0.0), 0)
    x0, y0, x1, y1 = box
    mesh = model.mesh
    T_W_O = T_world_cam @ T_C_O
    scorer = _MaskScorer(
        mask[y0:y1, x0:x1],
        window_intrinsics(K, x0, y0),
        np.asarray(mesh.vertices),
        np.asarray(mesh.faces),
        np.linalg.inv(T_world_cam),
        T_W_O[:3, :3],
        T_W_O[:3, 3],
    )
    before = scorer.score(0.0, 0.0, 0.0)
    best = _search_yaw(scorer, (before, 0.0, 0.0, 0.0), yaw_range_deg)
    best = _search_shift(scorer, best, shift_range_m / 2)
    best = _search_fine_yaw(scorer, best)
    s, yaw, dx, dy = best
    return MaskRefinement(
        scorer.pose(yaw, dx, dy), before, s, float(np.degrees(yaw)), (dx, dy), scorer.renders
    )


@dataclass
class _MaskScorer:
    """Silhouette IoU with a mask of a resting pose turned and shifted on its support.

    Attributes:
        window: the mask in its window, (h, w) bool.
        Kw: the window's intrinsics, (3, 3) [px].
        v, f: the object's mesh: vertices in O (V, 3) [m], faces (F, 3).
        T_cam_world: the world in the camera frame, (4, 4).
        R0, p0: the pose's rotation (3, 3) and origin (3,) [m] in the world (z up).
        renders: silhouettes rendered so far.
    """

    window: np.ndarray
    Kw: np.ndarray
    v: np.ndarray
    f: np.ndarray
    T_cam_world: np.ndarray
    R0: np.ndarray
    p0: np.ndarray
    renders: int = 0

    def pose(self, yaw: float, dx: float, dy: float) -> np.ndarray:
        """The pose turned by `yaw` [rad] about the world's vertical through its origin and
        moved by (dx, dy) [m] in the world's horizontal plane, in the camera frame (4, 4)."""
        T = np.eye(4)
        T[:3, :3] = rot_z(yaw) @ self.R0
        T[:3, 3] = self.p0 + np.array([dx, dy, 0.0])
        return self.T_cam_world @ T

    def score(self, yaw: float, dx: float, dy: float) -> float:
        """The silhouette IoU with the mask of `pose` (yaw, dx, dy); counted in `renders`."""
        self.renders += 1
        silh = silhouette(self.pose(yaw, dx, dy), self.Kw, self.v, self.f, self.window.shape)
        return mask_iou(silh, self.window)


#: The best (IoU, yaw [rad], dx [m], dy [m]) a search has found.
_Best = tuple[float, float, float, float]


def _search_yaw(scorer: _MaskScorer, best: _Best, yaw_range_deg: float) -> _Best:
    """`best` after trying yaws in 3 degree steps over +-`yaw_range_deg`, unshifted."""
    for yaw in np.radians(np.arange(-yaw_range_deg, yaw_range_deg + 1e-9, 3.0)):
        s = scorer.score(yaw, 0.0, 0.0)
        if s > best[0]:
            best = (s, yaw, 0.0, 0.0)
    return best


def _search_shift(scorer: _MaskScorer, best: _Best, step: float) -> _Best:
    """`best` after trying, at its yaw, the 8 shifts of a 3x3 grid of `step` [m] around it."""
    yaw_b = best[1]
    for dx in (-step, 0.0, step):
        for dy in (-step, 0.0, step):
            if dx == 0.0 and dy == 0.0:
                continue
            s = scorer.score(yaw_b, dx, dy)
            if s > best[0]:
                best = (s, yaw_b, dx, dy)
    return best


def _search_fine_yaw(scorer: _MaskScorer, best: _Best) -> _Best:
    """`best` after trying, at its shift, yaws 1 to 3 degrees either side of its own."""
    _, yaw_b, dx_b, dy_b = best
    for d in np.radians((-3.0, -2.0, -1.0, 1.0, 2.0, 3.0)):
        s = scorer.score(yaw_b + d, dx_b, dy_b)
        if s > best[0]:
            best = (s, yaw_b + d, dx_b, dy_b)
    return best
