"""Point clouds of the classical peers: the scene's points from the depth image, the model's
from its mesh.

The scene: every pixel with depth is back-projected with K into the camera frame C (pixel
(u, v) at depth z is ``z K^-1 (u, v, 1)``, docs/DESIGN.md §4), the points are taken to the
world with the camera's pose, and the table is removed as depth pipelines do it with a known
support plane: the points on the table top (within `CropConfig.table_band_m` of its height)
give the table's footprint (their convex hull seen from above), and a point belongs to an
object when it lies over that footprint, at least `CropConfig.min_height_m` above the top and
no higher than the object's diameter. What is left is the objects on the table (with a mask,
only those inside it). A real sensor's table top is noisy: both thresholds grow to
`TABLE_NOISE_SIGMAS` times the spread of the table's measured heights (`table_noise`), so that
its noise does not stay in the scene as points; with ideal depth they stay as configured.

The model: points sampled uniformly over the mesh surface in the object frame O with the
normals of their faces; a built-in object's parts overlap, and a sample inside another part
(a face no camera sees) is dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import ConvexHull, QhullError

from posegrasp.core.errors import InvalidArgumentError
from posegrasp.world.objects import ObjectModel

#: Least number of table-top points that make a footprint (fewer: the footprint is not used).
MIN_TABLE_POINTS = 16
#: The table band and the least object height grow to this many robust standard deviations
#: of the table top's measured heights (a Gaussian's 99.7 %).
TABLE_NOISE_SIGMAS = 3.0
#: The table top's noise is measured on the points within this height of it [m].
TABLE_NOISE_WINDOW_M = 0.02


def table_noise(height: np.ndarray) -> float:
    """A robust standard deviation of the table top's measured heights [m]: 1.4826 times the
    median absolute deviation of the heights (above the top) within `TABLE_NOISE_WINDOW_M` of
    it, where the table's points outnumber the objects' lowest ones; 0 with too few points."""
    near = height[np.abs(height) < TABLE_NOISE_WINDOW_M]
    if len(near) < MIN_TABLE_POINTS:
        return 0.0
    return float(1.4826 * np.median(np.abs(near - np.median(near))))


@dataclass(frozen=True)
class CropConfig:
    """How the objects' points are cut out of the depth image.

    Attributes:
        table_band_m: a point within this height of the table top is on the top [m].
        min_height_m: an object's point is at least this far above the table top [m].
        max_height_factor: ... and at most this many object diameters above it.
        table_stride: every this-many-th table point goes into the footprint's hull.
        mask_grow_px: a detection mask is grown by this many pixels before it cuts the
            points (its outline is a pixel or two inside the object's).
    """

    table_band_m: float = 0.003
    min_height_m: float = 0.003
    max_height_factor: float = 1.0
    table_stride: int = 4
    mask_grow_px: int = 2

    def __post_init__(self) -> None:
        if min(self.table_band_m, self.min_height_m, self.max_height_factor) <= 0:
            raise InvalidArgumentError(
                "CropConfig: table_band_m, min_height_m and max_height_factor must be > 0"
            )
        if self.table_stride < 1 or self.mask_grow_px < 0:
            raise InvalidArgumentError("CropConfig: table_stride >= 1 and mask_grow_px >= 0")


def back_project(depth: np.ndarray, K: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """The camera-frame points of the pixels with depth (0 or non-finite: none).

    Args:
        depth: z along the optical axis, shape (H, W) [m].
        K: intrinsics, shape (3, 3) [px].
        mask: only these pixels, shape (H, W) bool (None: all).

    Returns:
        Points in C, shape (N, 3) [m], float64, in row-major pixel order.

    Raises:
        InvalidArgumentError: depth is not (H, W), K not (3, 3) or mask not depth's shape.
    """
    depth = np.asarray(depth)
    K = np.asarray(K, np.float64)
    if depth.ndim != 2 or K.shape != (3, 3):
        raise InvalidArgumentError(
            f"depth must be (H, W) and K (3, 3), got {depth.shape} and {K.shape}"
        )
    valid = np.isfinite(depth) & (depth > 0)
    if mask is not None:
        if np.shape(mask) != depth.shape:
            raise InvalidArgumentError(f"mask must be {depth.shape}, got {np.shape(mask)}")
        valid &= np.asarray(mask, bool)
    v, u = np.nonzero(valid)
    z = depth[v, u].astype(np.float64)
    return np.linalg.solve(K, np.stack([u * z, v * z, z])).T


def _footprint(table_xy: np.ndarray) -> np.ndarray | None:
    """The half-planes (a, b, c) of the convex hull of the table points seen from above,
    ``a x + b y + c <= 0`` inside, shape (F, 3); None when they span no area."""
    if len(table_xy) < MIN_TABLE_POINTS:
        return None
    try:
        return ConvexHull(table_xy).equations
    except QhullError:
        return None


def object_points(
    depth: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray,
    table_top_z: float,
    diameter: float,
    crop: CropConfig,
    mask: np.ndarray | None = None,
) -> np.ndarray:
    """The points of the objects on the table (module docstring), in the camera frame.

    Args:
        depth: z along the optical axis, shape (H, W) [m].
        K: intrinsics, shape (3, 3) [px].
        T_world_cam: the camera's pose in the world (OpenCV frame), shape (4, 4).
        table_top_z: height of the table top in the world [m].
        diameter: the requested object's diameter [m] (bounds the height kept).
        crop: the thresholds.
        mask: only the points of these pixels (grown by `CropConfig.mask_grow_px`), shape
            (H, W) bool; the table's footprint still comes from the whole image.

    Returns:
        Points in C, shape (N, 3) [m].
    """
    pts_C = back_project(depth, K)
    T = np.asarray(T_world_cam, np.float64)
    pts_W = pts_C @ T[:3, :3].T + T[:3, 3]
    height = pts_W[:, 2] - float(table_top_z)
    spread = TABLE_NOISE_SIGMAS * table_noise(height)
    low = max(crop.min_height_m, spread)
    keep = (height > low) & (height < crop.max_height_factor * diameter)
    on_top = np.abs(height) < max(crop.table_band_m, spread)
    planes = _footprint(pts_W[on_top][:: crop.table_stride, :2])
    if planes is not None:
        xy = pts_W[keep, :2]
        inside = np.all(xy @ planes[:, :2].T + planes[:, 2] <= 0.0, axis=1)
        keep[np.flatnonzero(keep)[~inside]] = False
    if mask is not None:
        grown = np.asarray(mask, bool)
        if crop.mask_grow_px:
            grown = ndimage.binary_dilation(grown, iterations=crop.mask_grow_px)
        valid = np.isfinite(depth) & (np.asarray(depth) > 0)
        keep &= grown[valid]
    return pts_C[keep]


def _inside_other_part(model: ObjectModel, points: np.ndarray, part_of: np.ndarray) -> np.ndarray:
    """Whether each sample of a built-in object lies strictly inside a part other than its own
    (every part is convex: inside all of its face planes), shape (N,) bool."""
    inside = np.zeros(len(points), bool)
    for i, part in enumerate(model.parts):
        mesh = part.mesh()
        normals = np.asarray(mesh.face_normals)
        offsets = np.einsum("ij,ij->i", normals, np.asarray(mesh.triangles)[:, 0])
        depth_in = (points @ normals.T - offsets).max(axis=1)
        inside |= (depth_in < -1e-5) & (part_of != i)
    return inside


def model_surface(model: ObjectModel, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Points sampled uniformly over the object's visible surface, with their face normals.

    Args:
        model: the object.
        count: samples drawn before those inside other parts are dropped.
        seed: the sampling's seed.

    Returns:
        (points (N, 3) [m], outward unit normals (N, 3)), both in O, N <= count.
    """
    mesh = model.mesh
    points, faces = trimesh.sample.sample_surface(mesh, count, seed=seed)
    points = np.asarray(points, np.float64)
    normals = np.asarray(mesh.face_normals)[faces]
    if model.parts:
        sizes = [len(p.mesh().faces) for p in model.parts]
        part_of = np.searchsorted(np.cumsum(sizes), faces, side="right")
        visible = ~_inside_other_part(model, points, part_of)
        points, normals = points[visible], normals[visible]
    return points, normals


def nearest_rigid(T: np.ndarray) -> np.ndarray:
    """The rigid transform nearest to a (4, 4) matrix: its rotation block projected onto SO(3)
    (SVD, Frobenius norm), its translation kept, last row (0, 0, 0, 1); a library's float
    rounding never makes a pose fail `posegrasp.core.contract.pose_problem`."""
    T = np.asarray(T, np.float64)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    out = np.eye(4)
    out[:3, :3] = U @ D @ Vt
    out[:3, 3] = T[:3, 3]
    return out
