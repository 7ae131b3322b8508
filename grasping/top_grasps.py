"""Grasps from above for an object resting in any pose, generated from its parts.

For a resting pose (the direction `up` in O that points away from the table) every part is tried
as the thing the fingers close on: a part axis that lies nearly horizontal is the closing
direction, the grasp site sits a little below the part's top along the vertical line through a
point of the part, and the gripper comes straight down. A grasp is kept when the part fits
between the open fingers, the fingertips stay above the table, and no point of the object lies
where the fingers sweep as they close, where they pass on the way down, or where the palm is.
Only grasps near the centre of mass (horizontally, within `COM_SPREAD` of the nearest) are
kept: a grasp far from it lets the object turn out of the fingers as it is lifted.
"""

from __future__ import annotations

import functools

import numpy as np
import trimesh

from posegrasp.world import constants as C
from posegrasp.world.objects import ObjectModel, Part, load_object

#: The Fetch fingers in the grasp frame G (x approach, y closing, z across), measured on the
#: converted model: each finger spans x in [-0.0635, 0.0135], |z| <= 0.0135 and, open,
#: |y| in [0.051, 0.065]; the palm lies behind x = -0.057.
FINGER_X = (-0.0635, 0.0135)
FINGER_Z = 0.0135
FINGER_OUTER_Y = 0.065
PALM_X = -0.057
PALM_HALF = (0.065, 0.04)
#: Room kept between the fingers and anything they must not touch [m].
CLEARANCE = 0.004
#: Widest part the fingers take (the opening is twice FINGER_TRAVEL, less room for the pads) [m].
MAX_WIDTH = 2 * C.FINGER_TRAVEL - 0.012
MIN_WIDTH = 0.006
#: A part axis is a closing direction when it is within this of horizontal [deg].
MAX_CLOSE_TILT = 20.0
#: How far below the part's top the site sits, deepest first (a shallower grasp is taken only
#: when the fingertips of a deeper one would touch something), and at most half the part's
#: height [m].
DEPTHS = (0.012, 0.008, 0.005, 0.002)
#: Grasp positions tried along a part (the farthest ones keep the pads on the part).
SLIDES = 5
#: Grasps kept are at most this much farther from the centre of mass than the nearest [m].
COM_SPREAD = 0.03


def _frame(part: Part) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R, centre, half extents) of a part, a cylinder as the box around it (axis along z)."""
    T = part.transform()
    size = np.asarray(part.size, float)
    if part.type == "cylinder":
        half = np.array([size[0], size[0], size[1]])
    elif part.type == "sphere":
        half = np.full(3, size[0])
    else:
        half = size
    return T[:3, :3], T[:3, 3], half


def _exit(R: np.ndarray, c: np.ndarray, half: np.ndarray, p: np.ndarray, u: np.ndarray) -> float:
    """Largest t with p + t u inside the box (R, c, half), p inside it."""
    lp, lu = R.T @ (p - c), R.T @ u
    t = np.inf
    for k in range(3):
        if abs(lu[k]) > 1e-9:
            t = min(t, ((half[k] if lu[k] > 0 else -half[k]) - lp[k]) / lu[k])
    return float(t)


@functools.cache
def top_grasp_points(name: str) -> np.ndarray:
    """Points on the surface of object class `name` in O, the same on every call."""
    mesh = load_object(name).mesh
    pts, _ = trimesh.sample.sample_surface(mesh, 6000, seed=0)
    return np.vstack([np.asarray(mesh.vertices), pts])


def centre_of_mass(obj: ObjectModel) -> np.ndarray:
    """Centre of mass of the colliding parts, uniform density, in O [m]."""
    parts = [p for p in obj.parts if p.collision]
    vol = np.array([p.volume for p in parts])
    return (vol[:, None] * np.array([p.pos for p in parts])).sum(axis=0) / vol.sum()


def clear(T_O_G: np.ndarray, width: float, pts: np.ndarray, floor: float) -> bool:
    """Whether fingers and palm at T_O_G (closing to `width`) keep clear of the object's points
    and the fingertips of the table plane at height `floor` along up."""
    p = (pts - T_O_G[:3, 3]) @ T_O_G[:3, :3]
    x, ay, az = p[:, 0], np.abs(p[:, 1]), np.abs(p[:, 2])
    sweep = (x <= FINGER_X[1] + CLEARANCE) & (az <= FINGER_Z + CLEARANCE)
    sweep &= (ay >= width / 2 + CLEARANCE) & (ay <= FINGER_OUTER_Y + CLEARANCE)
    palm = (x <= PALM_X + CLEARANCE) & (ay <= PALM_HALF[0]) & (az <= PALM_HALF[1])
    return not sweep.any() and not palm.any() and floor >= FINGER_X[1] + CLEARANCE


def _part_grasps(
    part: Part, up: np.ndarray, pts: np.ndarray, low: float
) -> list[tuple[np.ndarray, float]]:
    R, c, half = _frame(part)
    out = []
    sin_tilt = np.sin(np.deg2rad(MAX_CLOSE_TILT))
    for k_close in range(3):
        a_close = R[:, k_close]
        if abs(a_close @ up) > sin_tilt:
            continue
        if part.type == "cylinder" and k_close == 2:
            continue  # closing along a cylinder's axis meets its flat ends: left to boxes
        width = float(2 * np.sum(half * np.abs(R.T @ _horizontal(a_close, up))))
        if not MIN_WIDTH <= width <= MAX_WIDTH:
            continue
        k_slide = max((k for k in range(3) if k != k_close), key=lambda k: -abs(R[:, k] @ up))
        reach = half[k_slide] - FINGER_Z - 0.002
        offsets = np.linspace(-reach, reach, SLIDES) if reach > 0 else np.zeros(1)
        for off in offsets:
            p0 = c + off * R[:, k_slide]
            height = _exit(R, c, half, p0, up) + _exit(R, c, half, p0, -up)
            top = p0 + _exit(R, c, half, p0, up) * up
            y = _horizontal(a_close, up)
            for depth in DEPTHS:
                site = top - min(depth, 0.5 * height) * up
                found = []
                for sign in (1.0, -1.0):
                    T = np.eye(4)
                    T[:3, :3] = np.column_stack([-up, sign * y, np.cross(-up, sign * y)])
                    T[:3, 3] = site
                    if clear(T, width, pts, float(site @ up) - low):
                        found.append((T, width))
                if found:
                    out += found
                    break
    return out


def _horizontal(v: np.ndarray, up: np.ndarray) -> np.ndarray:
    h = v - (v @ up) * up
    return h / np.linalg.norm(h)


def top_grasps(
    obj: ObjectModel, up: np.ndarray, keep: int = 16
) -> list[tuple[str, np.ndarray, float]]:
    """Grasps from above of `obj` resting with direction `up` (in O) pointing up.

    Returns:
        Up to `keep` (part, T_O_G, width) triples, nearest the centre of mass first, none more
        than `COM_SPREAD` farther from it than the nearest.
    """
    u = np.asarray(up, float) / np.linalg.norm(up)
    pts = top_grasp_points(obj.name)
    low = float((pts @ u).min())
    com = centre_of_mass(obj)
    found = []
    for part in obj.parts:
        if not part.collision:
            continue
        for T, width in _part_grasps(part, u, pts, low):
            d = T[:3, 3] - com
            found.append((float(np.linalg.norm(d - (d @ u) * u)), part.name, T, width))
    found.sort(key=lambda f: f[0])
    near = [f for f in found if f[0] <= found[0][0] + COM_SPREAD] if found else []
    return [(name, T, width) for _, name, T, width in near[:keep]]
