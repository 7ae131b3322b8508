"""Grasps from above of a mesh object in one resting pose, for the Fetch parallel gripper.

For the resting pose's up direction `u` (in O), the gripper comes straight down (-u) and closes
along a horizontal direction `y`. Closing directions are tried every `ANGLE_STEP_DEG` over a half
turn, and grasp lines every `SLIDE_STEP` across the object; along each line the fingers take what
lies in their slab (the pads' 27 mm, grown by the clearance), at depths below its top from
`DEPTHS`. A grasp is kept when

- what lies between the pads is `MIN_WIDTH`..`MAX_WIDTH` across (the finger travel, less room for
  the pads: `grasping.top_grasps.MAX_WIDTH`),
- the fingers keep clear of the object where they sweep as they close and pass on the way down, the
  palm keeps clear of it (`grasping.top_grasps.clear`), and the fingertips stay
  `TABLE_CLEARANCE` above the table (`MIN_TABLE_CLEARANCE` for a pose that has no grasp so),
- the surface is antipodal where the pads touch it (the outermost `CONTACT_BAND` of the surface
  facing each pad): the mean outward normal there lies within `CONE_DEG` of the closing
  direction on either side (inside the friction cone, with a margin), over a patch that spans
  at least `MIN_PATCH` along the pads.

The points are sampled on the collision hulls (what the fingers meet in physics), their normals
are the hulls'. The score, lower being better, is the horizontal distance of the centre of mass
from the grasp line (the lever gravity turns the object about the fingers with) plus penalties
for normals far from the closing direction and for a shallow hold.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import cast

import numpy as np
import trimesh

from grasping.top_grasps import (
    CLEARANCE,
    FINGER_X,
    FINGER_Z,
    MAX_WIDTH,
    MIN_WIDTH,
    clear,
)

#: Closing directions are tried every this many degrees over a half turn.
ANGLE_STEP_DEG = 15.0
#: Grasp lines are this far apart across the object [m].
SLIDE_STEP = 0.006
#: How far below the top of what the pads hold the grasp site sits, deepest first [m]; a site
#: never sits lower than keeps the fingertips `TABLE_CLEARANCE` above the table.
DEPTHS = (0.035, 0.025, 0.017, 0.010)
#: The fingertips stay at least this above the table [m]: the planner keeps the fingers 5 mm
#: from it and passes over a candidate whose open fingertips would come within 6 mm of it at the
#: estimated pose (`grasping.candidates.MESH_TABLE_MARGIN`), and an object settles a few degrees
#: off its stored resting pose.
TABLE_CLEARANCE = 0.012
#: The least fingertip clearance, taken for a pose that has no grasp with `TABLE_CLEARANCE` (an
#: object lying less than about 3 cm high) [m].
MIN_TABLE_CLEARANCE = 0.008
#: The mean outward normal where a pad touches must lie within this of the closing direction
#: [deg] (the friction cone of the coefficient 1 is 45 deg).
CONE_DEG = 30.0
#: Its cosine.
COS_CONE = math.cos(math.radians(CONE_DEG))
#: Points within this of the outermost one on a side are where that pad touches [m].
CONTACT_BAND = 0.002
#: The contact patch must span at least this along the pads (vertically or across) [m].
MIN_PATCH = 0.004
#: Surface samples on the hulls.
SAMPLES = 16000
#: A sample deeper than this inside another hull is not on the object's surface [m].
INSIDE = 0.0005


@dataclass(frozen=True)
class Antipodal:
    """A grasp from above.

    Attributes:
        T_O_G: grasp-site pose in O (x approach = -up, y closing), shape (4, 4) [m].
        width: extent of the object between the pads [m].
        score: lower is better (`score_grasp`).
        com_arm: horizontal distance of the centre of mass from the grasp line [m].
        cone_deg: the largest angle between a contact normal and the closing direction [deg].
        depth: how far the fingertips reach below the top of what the pads hold [m].
    """

    T_O_G: np.ndarray
    width: float
    score: float
    com_arm: float
    cone_deg: float
    depth: float


def hull_points(hulls: list[trimesh.Trimesh], samples: int = SAMPLES, seed: int = 0):
    """Points on the outer surface of the union of the hulls with their outward normals, the
    same on every call: area-weighted samples of every hull's faces, less those lying inside
    another hull by more than `INSIDE` (where hulls meet, inside the object).

    Returns:
        (points (N, 3) [m], normals (N, 3)).
    """
    mesh = cast(trimesh.Trimesh, trimesh.util.concatenate(hulls))
    pts, faces = trimesh.sample.sample_surface(mesh, samples, seed=seed)
    pts = np.asarray(pts)
    normals = np.asarray(mesh.face_normals)[faces]
    owner = np.repeat(np.arange(len(hulls)), [len(h.faces) for h in hulls])[faces]
    inside = np.zeros(len(pts), bool)
    for j, hull in enumerate(hulls):
        n = np.asarray(hull.face_normals)
        d = np.einsum("ij,ij->i", n, np.asarray(hull.triangles)[:, 0])
        depth = (pts @ n.T - d).max(axis=1)
        inside |= (depth < -INSIDE) & (owner != j)
    return pts[~inside], normals[~inside]


def _frame(approach: np.ndarray, y: np.ndarray, site: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.column_stack([approach, y, np.cross(approach, y)])
    T[:3, 3] = site
    return T


def horizontal_basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit directions (e1, e2) spanning the plane normal to the unit direction `up`."""
    e1 = np.cross(up, np.eye(3)[int(np.argmin(np.abs(up)))])
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1)


def antipodal_grasps(
    points: np.ndarray,
    normals: np.ndarray,
    up: np.ndarray,
    com: np.ndarray,
    table_clearance: float = TABLE_CLEARANCE,
) -> list[Antipodal]:
    """Every grasp from above that passes the checks of the module, best first.

    Args:
        points: surface points of the collision geometry in O (N, 3) [m].
        normals: their outward unit normals (N, 3).
        up: the resting pose's up direction in O (3,).
        com: centre of mass in O (3,) [m].
        table_clearance: how far above the table the fingertips stay [m].

    Returns:
        The grasps, lowest score first; one finger order each (the gripper is symmetric under
        a half turn about its approach).
    """
    u = np.asarray(up, float) / np.linalg.norm(up)
    h = points @ u
    e1, e2 = horizontal_basis(u)
    out: list[Antipodal] = []
    for k in range(round(180.0 / ANGLE_STEP_DEG)):
        theta = math.radians(k * ANGLE_STEP_DEG)
        y = math.cos(theta) * e1 + math.sin(theta) * e2
        out += _closing_along(_Closing.make(points, normals, h, u, y, com, table_clearance))
    out.sort(key=lambda g: g.score)
    return out


@dataclass(frozen=True)
class _Closing:
    """The surface seen by a gripper coming down -u and closing along the horizontal y.

    Attributes:
        points, normals: the surface samples and their outward normals in O.
        h, py, pz: each sample's height along u, and its coordinates along y and along z.
        ny: each normal's component along y.
        u, y, z: up, the closing direction and the direction across the pads (-u cross y).
        low: the lowest sample's height (the table's) [m].
        com: the centre of mass in O [m].
        table_clearance: how far above the table the fingertips stay [m].
    """

    points: np.ndarray
    normals: np.ndarray
    h: np.ndarray
    py: np.ndarray
    pz: np.ndarray
    ny: np.ndarray
    u: np.ndarray
    y: np.ndarray
    z: np.ndarray
    low: float
    com: np.ndarray
    table_clearance: float

    @staticmethod
    def make(
        points: np.ndarray,
        normals: np.ndarray,
        h: np.ndarray,
        u: np.ndarray,
        y: np.ndarray,
        com: np.ndarray,
        table_clearance: float,
    ) -> _Closing:
        """The view of samples `points` (heights `h` along `u`) closing along `y`."""
        z = np.cross(-u, y)  # across the pads, horizontal
        py, pz, ny = points @ y, points @ z, normals @ y
        low = float(h.min())
        return _Closing(points, normals, h, py, pz, ny, u, y, z, low, com, table_clearance)


def _closing_along(c: _Closing) -> list[Antipodal]:
    """The grasps closing along c.y: on each grasp line (every `SLIDE_STEP` across), the first
    of `DEPTHS` below the top of what lies in the pads' slab that makes a grasp."""
    out: list[Antipodal] = []
    for s in np.arange(c.pz.min(), c.pz.max() + 1e-9, SLIDE_STEP):
        slab = np.abs(c.pz - s) <= FINGER_Z + CLEARANCE
        if slab.sum() < 10:
            continue
        top = float(c.h[slab].max())
        for depth in DEPTHS:
            grasp = _grasp_at(c, s, slab, top, depth)
            if grasp is not None:
                out.append(grasp)
                break
    return out


def _grasp_at(
    c: _Closing, s: float, slab: np.ndarray, top: float, depth: float
) -> Antipodal | None:
    """The grasp on line s (along c.z) with the site `depth` below `top`, when it passes the
    module's checks; None otherwise."""
    site_h = max(top - depth, c.low + FINGER_X[1] + c.table_clearance)
    tip_h = site_h - FINGER_X[1]
    # What the pads take: the slab from the fingertips up (the palm check covers what lies
    # above the fingers).
    held = slab & (c.h >= tip_h - CLEARANCE)
    if held.sum() < 10:
        return None
    ymin, ymax = float(c.py[held].min()), float(c.py[held].max())
    width = ymax - ymin
    if not MIN_WIDTH <= width <= MAX_WIDTH:
        return None
    pad = held & (c.h <= site_h - FINGER_X[0])
    cosines = _contact_cosines(c, pad, ymin, ymax)
    if cosines is None:
        return None
    centre_y = (ymin + ymax) / 2
    site = centre_y * c.y + s * c.z + site_h * c.u
    T = _frame(-c.u, c.y, site)
    if not clear(T, width, c.points, site_h - c.low):
        return None
    arm = abs(float((c.com - site) @ c.z))
    cone = math.degrees(math.acos(min(*cosines, 1.0)))
    reach = top - tip_h
    return Antipodal(T, width, score_grasp(arm, cone, reach), arm, cone, reach)


def _contact_cosines(
    c: _Closing, pad: np.ndarray, ymin: float, ymax: float
) -> tuple[float, float] | None:
    """Where the pads touch, the outermost surface facing each pad (a surface facing away, such
    as the inside of a thin wall, lies behind it): the cosines of its mean normal with the
    closing direction on either side, None when either side is not antipodal (too few points,
    outside `CONE_DEG`, or a patch under `MIN_PATCH`)."""
    plus = pad & (c.py >= ymax - CONTACT_BAND) & (c.ny > 0)
    minus = pad & (c.py <= ymin + CONTACT_BAND) & (c.ny < 0)
    if plus.sum() < 3 or minus.sum() < 3:
        return None
    c_plus = float(_mean_dir(c.normals[plus]) @ c.y)
    c_minus = float(-_mean_dir(c.normals[minus]) @ c.y)
    if min(c_plus, c_minus) < COS_CONE:
        return None
    if min(_span(c.points[plus], c.u, c.z), _span(c.points[minus], c.u, c.z)) < MIN_PATCH:
        return None
    return c_plus, c_minus


def score_grasp(com_arm: float, cone_deg: float, reach: float) -> float:
    """A grasp's score (lower is better): the centre of mass's lever [m], plus 1 mm for every
    3 degrees the contact normals lean off the closing direction, plus 1 mm for every 2 mm the
    pads hold less than 25 mm of the object's height."""
    return com_arm + 0.001 * cone_deg / 3.0 + 0.5 * max(0.0, 0.025 - reach)


def _mean_dir(normals: np.ndarray) -> np.ndarray:
    """The mean of unit normals, normalised (3,)."""
    m = normals.mean(axis=0)
    return m / max(float(np.linalg.norm(m)), 1e-12)


def _span(pts: np.ndarray, up: np.ndarray, across: np.ndarray) -> float:
    """The larger of the extents of points along `up` and along `across` [m]."""
    return max(float(np.ptp(pts @ up)), float(np.ptp(pts @ across)))


def distinct(grasps: list[Antipodal], keep: int, min_dist: float = 0.008) -> list[Antipodal]:
    """At most `keep` grasps, best first, each at least `min_dist` from the kept ones' sites or
    closing along a direction at least 20 degrees off theirs."""
    out: list[Antipodal] = []
    cos20 = math.cos(math.radians(20.0))
    for g in grasps:
        if len(out) >= keep:
            break
        near = any(
            np.linalg.norm(g.T_O_G[:3, 3] - o.T_O_G[:3, 3]) < min_dist
            and abs(float(g.T_O_G[:3, 1] @ o.T_O_G[:3, 1])) > cos20
            for o in out
        )
        if not near:
            out.append(g)
    return out


def flipped(T_O_G: np.ndarray) -> np.ndarray:
    """The same grasp with the fingers swapped: a half turn about the approach (4, 4)."""
    F = T_O_G.copy()
    F[:3, 1] *= -1.0
    F[:3, 2] *= -1.0
    return F
