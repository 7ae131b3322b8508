"""Table layouts with neighbours: objects placed by their footprints, edge to edge.

A footprint is the convex hull of an object's mesh seen from above, in its resting pose turned by
its yaw. Gaps between footprints are exact distances between convex polygons [m], so "a
neighbour 3 cm from the target" means 3 cm between their nearest edges.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull

from posegrasp.core.transforms import quat_to_mat, rot_z
from posegrasp.world.objects import ObjectModel

#: Where footprints may lie: the table top (x 0.45..1.05, y -0.5..0.5) less a 2 cm margin [m].
TABLE_XY = ((0.47, 1.03), (-0.48, 0.48))
#: Smallest gap between any two footprints that are not deliberate neighbours [m].
MIN_GAP = 0.02


def footprint(obj: ObjectModel, rest: np.ndarray, yaw: float) -> np.ndarray:
    """Convex footprint of an object resting with orientation `rest` (wxyz) turned by `yaw`
    [rad] about z, centred on its origin: (N, 2) vertices, counter-clockwise [m]."""
    R = rot_z(yaw) @ quat_to_mat(rest)
    xy = (np.asarray(obj.mesh.vertices) @ R.T)[:, :2]
    return xy[ConvexHull(xy).vertices]


def _point_segments(P: np.ndarray, Q: np.ndarray) -> float:
    """Smallest distance from the points P (N, 2) to the edges of polygon Q (M, 2)."""
    a = Q
    ab = np.roll(Q, -1, axis=0) - Q  # (M, 2)
    ap = P[:, None, :] - a[None, :, :]  # (N, M, 2)
    t = np.clip(np.einsum("nmk,mk->nm", ap, ab) / np.maximum((ab * ab).sum(axis=1), 1e-18), 0, 1)
    d = ap - t[..., None] * ab[None, :, :]
    return float(np.sqrt((d * d).sum(axis=2).min()))


def _separated(A: np.ndarray, B: np.ndarray) -> bool:
    """Separating-axis test of two convex polygons."""
    for P in (A, B):
        edges = np.roll(P, -1, axis=0) - P
        normals = np.stack([edges[:, 1], -edges[:, 0]], axis=1)  # (E, 2)
        a, b = A @ normals.T, B @ normals.T  # (N, E), (M, E)
        if np.any((a.max(axis=0) < b.min(axis=0)) | (b.max(axis=0) < a.min(axis=0))):
            return True
    return False


def gap(A: np.ndarray, B: np.ndarray) -> float:
    """Edge-to-edge distance of two convex polygons (N, 2) and (M, 2) [m]; 0 when they overlap."""
    if not _separated(A, B):
        return 0.0
    return min(_point_segments(A, B), _point_segments(B, A))


#: Half-range of the direction, about -x, from the target to a neighbour that occludes it [rad].
OCCLUDER_SPREAD = 0.4


def on_table(F: np.ndarray) -> bool:
    """The footprint (placed, world xy) lies on the table top with its margin."""
    (x0, x1), (y0, y1) = TABLE_XY
    lo, hi = F.min(axis=0), F.max(axis=0)
    return bool(lo[0] >= x0 and hi[0] <= x1 and lo[1] >= y0 and hi[1] <= y1)


def place_beside(
    anchor: np.ndarray, shape: np.ndarray, direction: float, distance: float
) -> np.ndarray:
    """Offset (2,) that puts footprint `shape` (centred on its origin) `distance` from the placed
    footprint `anchor`, edge to edge, along the horizontal `direction` [rad] from the anchor's
    centroid (bisection on the centre distance, to 1/2**17 m)."""
    u = np.array([np.cos(direction), np.sin(direction)])
    c = anchor.mean(axis=0)
    lo, hi = 0.0, 1.0
    for _ in range(17):
        mid = (lo + hi) / 2
        if gap(anchor, shape + c + mid * u) < distance:
            lo = mid
        else:
            hi = mid
    return c + hi * u


def sample_layout(
    objects: list[ObjectModel],
    rests: list[np.ndarray],
    near: int,
    near_gap: tuple[float, float],
    target_xy: tuple[tuple[float, float], tuple[float, float]],
    rng: np.random.Generator,
    attempts: int = 50,
    occluders: int = 0,
) -> list[tuple[np.ndarray, float]] | None:
    """Positions and yaws of objects on the table: the target (first) in its region, the next
    `near` objects beside it with gaps drawn from `near_gap`, the rest anywhere on the table at
    least `near_gap[0]` from the target; no two footprints closer than `MIN_GAP`. The first
    `occluders` of the neighbours stand on the robot's side of the target (-x, within
    `OCCLUDER_SPREAD`), between it and the head camera.

    Returns:
        [(xy (2,), yaw)] per object, or None when no layout was found in `attempts` tries.
    """
    for _ in range(attempts):
        placed: list[np.ndarray] = []
        out: list[tuple[np.ndarray, float]] = []
        for i, (obj, rest) in enumerate(zip(objects, rests, strict=True)):
            for _try in range(100):
                yaw = float(rng.uniform(-np.pi, np.pi))
                shape = footprint(obj, rest, yaw)
                if i == 0:
                    xy = np.array([rng.uniform(*target_xy[0]), rng.uniform(*target_xy[1])])
                elif i <= near:
                    side = (
                        np.pi + rng.uniform(-OCCLUDER_SPREAD, OCCLUDER_SPREAD)
                        if i <= occluders
                        else rng.uniform(-np.pi, np.pi)
                    )
                    xy = place_beside(placed[0], shape, side, rng.uniform(*near_gap))
                else:
                    (x0, x1), (y0, y1) = TABLE_XY
                    xy = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
                F = shape + xy
                # Deliberate neighbours are `near_gap` from the target; everything else keeps at
                # least the smallest of those gaps from it and `MIN_GAP` from the others.
                clear = all(gap(F, G) >= MIN_GAP for G in placed[1:])
                if i > near and placed:
                    clear = clear and gap(F, placed[0]) >= near_gap[0]
                if on_table(F) and clear:
                    placed.append(F)
                    out.append((xy, yaw))
                    break
            else:
                break
        else:
            return out
    return None
