"""Grasp candidates of a mesh object for each of its resting poses: generated, checked, ranked.

For every resting pose, the antipodal grasps from above (`grasping.antipodal`; with the fingertips
nearer the table when there are none) are thinned to
`CHECKED` distinct ones, best score first, and each is closed and lifted in physics
(`grasping.grasp_check`) as generated and with the hand put off it by `PERTURBATIONS` (errors of
the size a noisy pose estimate makes). A grasp is kept when it holds as generated; the kept ones
are ranked by how many of the perturbed grasps held, then by score, and the best `KEEP` are
returned, each with both finger orders. A pose none of whose grasps holds is not graspable.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
import trimesh

from grasping.antipodal import (
    MIN_TABLE_CLEARANCE,
    antipodal_grasps,
    distinct,
    flipped,
    hull_points,
)
from grasping.grasp_check import CheckConfig, check_grasps_in_poses
from posegrasp.core.transforms import quat_to_mat
from posegrasp.world.objects import ObjectModel

#: Distinct grasps checked in physics per resting pose.
CHECKED = 16
#: Grasps kept per resting pose (each stored with both finger orders).
KEEP = 8
#: Distinct grasps checked in physics over all resting poses, where an object has more than
#: this over `CHECKED` poses (`checks_per_pose`): a near-symmetric object (a can with its tab)
#: comes to rest in many poses that differ by a roll, and checking each as fully as an object
#: of few poses is most of its onboarding time.
CHECK_BUDGET = 96
#: Errors of the hand's placement a kept grasp is tried with, in the grasp frame G: (along the
#: approach, along the closing direction, across the pads) [m] and a turn about the approach
#: [deg].
PERTURBATIONS: tuple[tuple[float, float, float, float], ...] = (
    (0.0, 0.005, 0.0, 0.0),
    (0.0, -0.005, 0.0, 0.0),
    (0.0, 0.0, 0.005, 4.0),
    (0.0, 0.0, -0.005, -4.0),
    (0.004, 0.0, 0.0, 0.0),
)


@dataclass(frozen=True)
class RankedGrasp:
    """A grasp kept for a resting pose.

    Attributes:
        T_O_G: grasp-site pose in O (4, 4) [m].
        width: extent of the object between the pads [m].
        score: the generator's score, lower is better (`grasping.antipodal.score_grasp`).
        robust: how many of the perturbed grasps held, of `len(PERTURBATIONS)`.
    """

    T_O_G: np.ndarray
    width: float
    score: float
    robust: int


@dataclass
class PoseGrasps:
    """The grasps of one resting pose and how they were found.

    Attributes:
        pose: the resting pose's name.
        grasps: the kept grasps, best first, both finger orders of each (the flipped one right
            after it).
        generated: antipodal grasps found.
        checked: distinct grasps checked in physics.
        outcomes: the physics outcomes of the checked grasps as generated.
    """

    pose: str
    grasps: list[RankedGrasp] = field(default_factory=list)
    generated: int = 0
    checked: int = 0
    outcomes: Counter = field(default_factory=Counter)


def _perturbed(T_O_G: np.ndarray, p: tuple[float, float, float, float]) -> np.ndarray:
    D = np.eye(4)
    a = math.radians(p[3])
    D[1:3, 1:3] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    D[:3, 3] = p[:3]
    return T_O_G @ D


def convex_pieces(obj: ObjectModel) -> tuple[list[trimesh.Trimesh], np.ndarray]:
    """What the fingers meet and where the mass is: a user object's collision hulls and centre
    of mass, or a built-in object's colliding primitive parts (each convex) and the centre of
    their volume (its density is uniform over them), in O [m]."""
    if obj.geometry is not None:
        return list(obj.geometry.hulls), np.asarray(obj.geometry.com, float)
    parts = [p for p in obj.parts if p.collision]
    volumes = np.array([p.volume for p in parts])
    centres = np.array([p.pos for p in parts], float)
    return [p.mesh() for p in parts], volumes @ centres / volumes.sum()


def checks_per_pose(poses: int) -> int:
    """Distinct grasps to check per resting pose for an object of `poses` resting poses:
    `CHECKED`, or fewer where that would exceed `CHECK_BUDGET` in all, but never fewer than
    `KEEP`."""
    return min(CHECKED, max(KEEP, -(-CHECK_BUDGET // max(poses, 1))))


def mesh_grasps(
    obj: ObjectModel,
    resting: dict[str, np.ndarray],
    checked: int = CHECKED,
    keep: int = KEEP,
    config: CheckConfig | None = None,
    progress: bool = False,
) -> dict[str, PoseGrasps]:
    """The grasp candidates of a mesh object for each resting pose.

    Args:
        obj: the object, in any frame: a mesh object's hulls, or a built-in object's convex
            parts (`convex_pieces`).
        resting: resting pose name -> orientation of O on a plane, wxyz.
        checked: distinct grasps checked in physics per pose.
        keep: grasps kept per pose (each returned with both finger orders).
        config: the physics check's stages.
        progress: show a progress bar over the physics checks' batches.

    Returns:
        pose name -> its grasps (empty when none holds).

    """
    hulls, com = convex_pieces(obj)
    points, normals = hull_points(hulls)
    out: dict[str, PoseGrasps] = {}
    checks: list[tuple[PoseGrasps, list]] = []  # each checked pose and its distinct grasps
    jobs: list[tuple[np.ndarray, list[np.ndarray]]] = []  # its orientation and physics trials
    for name, quat in resting.items():
        up = quat_to_mat(np.asarray(quat, float))[2]
        found = antipodal_grasps(points, normals, up, com)
        if not found:  # lying low: let the fingertips come nearer the table
            found = antipodal_grasps(points, normals, up, com, MIN_TABLE_CLEARANCE)
        tried = distinct(found, checked)
        res = PoseGrasps(name, generated=len(found), checked=len(tried))
        out[name] = res
        if not tried:
            continue
        trials = []
        for a in tried:
            trials.append(a.T_O_G)
            trials += [_perturbed(a.T_O_G, p) for p in PERTURBATIONS]
        checks.append((res, tried))
        jobs.append((np.asarray(quat, float), trials))
    # Every pose's physics in one pool: an object of many poses keeps every thread busy.
    per = len(PERTURBATIONS) + 1
    done = check_grasps_in_poses(obj, jobs, config, progress)
    for (res, tried), outcomes in zip(checks, done, strict=True):
        ranked = []
        for i, a in enumerate(tried):
            own = outcomes[i * per : (i + 1) * per]
            res.outcomes[own[0]] += 1
            if own[0] == "success":
                robust = sum(o == "success" for o in own[1:])
                ranked.append(RankedGrasp(a.T_O_G, a.width, a.score, robust))
        ranked.sort(key=lambda r: (-r.robust, r.score))
        for r in ranked[:keep]:
            res.grasps += [r, RankedGrasp(flipped(r.T_O_G), r.width, r.score, r.robust)]
    return out
