"""Clearance of a grasp from the neighbours the robot knows of.

The open gripper at a grasp, with the stretch of its approach, is modelled as a box in the grasp
site's frame G (x: approach, y: closing direction, z = x cross y). A neighbour is a point cloud
sampled once from its class's mesh and placed at the pose the robot was told. A grasp is clear
when no neighbour point lies in the box grown by a margin.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
import trimesh

from posegrasp.world import constants as C
from posegrasp.world.objects import load_object

#: The open gripper and its approach in G [m]: from the pre-grasp (10 cm back along the
#: approach) to the fingertips (13.5 mm ahead of the site); fingers open to twice the finger
#: travel, pads 27 mm wide along z, a little more for the finger links.
GRIPPER_BOX = (
    (-0.16, 0.02),
    (-(C.FINGER_TRAVEL + 0.015), C.FINGER_TRAVEL + 0.015),
    (-0.02, 0.02),
)
#: Extra room required around the box [m].
MARGIN = 0.01
#: Points sampled on each neighbour's surface.
SAMPLES = 1500


def surface_points(name: str) -> np.ndarray:
    """Points on the surface of object class `name`, in its frame O [m], (SAMPLES + vertices,
    3); the same points on every call while the object is unchanged (sampled with a fixed
    seed)."""
    return _surface_points(name, load_object(name).revision)


@functools.cache
def _surface_points(name: str, revision: str) -> np.ndarray:
    del revision  # the cache key: a user object made again is sampled again
    mesh = load_object(name).mesh
    pts, _ = trimesh.sample.sample_surface(mesh, SAMPLES, seed=0)
    return np.vstack([np.asarray(mesh.vertices), np.asarray(pts)])


def intrusion(T_world_G: np.ndarray, neighbours: Sequence[tuple[str, np.ndarray]]) -> int:
    """How many neighbour points lie inside the gripper box (grown by `MARGIN`) at grasp pose
    T_world_G (4, 4); `neighbours` are (class, T_world_N) pairs. 0 means the grasp is clear."""
    if not neighbours:
        return 0
    R, t = T_world_G[:3, :3], T_world_G[:3, 3]
    lo = np.array([b[0] for b in GRIPPER_BOX]) - MARGIN
    hi = np.array([b[1] for b in GRIPPER_BOX]) + MARGIN
    count = 0
    for name, T in neighbours:
        p_world = surface_points(name) @ T[:3, :3].T + T[:3, 3]
        p_G = (p_world - t) @ R
        count += int(np.count_nonzero(np.all((p_G >= lo) & (p_G <= hi), axis=1)))
    return count
