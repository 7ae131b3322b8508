"""Grasp candidates per object, in the object's own frame O.

A candidate is the pose T_O_G of the gripper's grasp site G (x: approach direction, out of the
gripper; y: closing direction of the fingers; z = x cross y) when the fingers close on the part,
plus the opening the part needs. Candidates come from graspable segments of each object: the grasp
centre slides along a part, the fingers close across it, the gripper approaches from above; each
position is taken with both finger orders (the gripper is symmetric under a half turn about its
approach axis), and every object symmetry maps the set onto itself.

Those hand-designed segments serve the canonical resting pose. Every other resting pose of the
object (`posegrasp.world.resting`) gets the grasps from above that `grasping.top_grasps` generates
from the parts, so that every pose an object can lie in has candidates.

A user object made from a mesh (``python -m sim.add_object``) carries its candidates, generated
for every resting pose and checked in physics when it was made (`grasping.mesh_grasps`); they are
read from it as they are (their set already covers the object all round, both finger orders
included), and reach the planner through the same `grasp_candidates`.

A built-in object's candidates can come from that generator too (source ``generated``: its convex
parts stand for hulls, every graspable resting pose gets its checked grasps), so the two sources
can be paired on the same episodes; they are made once and kept under the data folder
(``$POSEGRASP_DATA/candidates``), keyed by the object's definition and the generator's code.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from grasping import antipodal, grasp_check, mesh_grasps
from grasping.top_grasps import top_grasps
from posegrasp.core.errors import UnknownNameError
from posegrasp.core.files import atomic_write_json
from posegrasp.core.paths import data_root
from posegrasp.core.transforms import quat_to_mat
from posegrasp.world.objects import (
    OBJECT_NAMES,
    OBJECTS_DIR,
    ObjectModel,
    check_object,
    load_object,
)


@dataclass(frozen=True)
class GraspCandidate:
    """One grasp in the object frame O.

    Attributes:
        T_O_G: pose of the grasp site in O, shape (4, 4), translations in [m].
        width: extent of the part between the finger pads [m].
        part: name of the grasped part ("mesh" for a user object).
        pose: the resting pose it was made for (`ObjectModel.resting_poses`).
        table_margin: when set, the planner passes over the candidate if at the estimated pose
            the open fingertips would come closer than this to the table [m] (a user object's
            candidates, made for one resting pose, met tilted when the object lies in a pose
            near it); None: no such check (the built-in objects' designed candidates).
    """

    T_O_G: np.ndarray
    width: float
    part: str
    pose: str = ""
    table_margin: float | None = None


@dataclass(frozen=True)
class GraspSegment:
    """Where an object can be grasped from above.

    Attributes:
        part: the part the fingers close on.
        slide: offsets of the grasp centre along `slide_axis` from the part's centre [m].
        slide_axis: axis of the part's own frame along which the grasp centre slides (0, 1, 2).
        close_axis: axis of the part's own frame the fingers close along.
        depth: how far below the part's top the grasp site sits [m].
    """

    part: str
    slide: tuple[float, ...]
    slide_axis: int
    close_axis: int
    depth: float


#: Graspable segments, designed against the geometry in scenes/objects/*.json: the finger pads
#: (27 mm wide along the slide, reaching 13.5 mm below the grasp site) clear every other part and
#: the table.
SEGMENTS: dict[str, tuple[GraspSegment, ...]] = {
    "phone": (GraspSegment("handset", (-0.024, -0.008, 0.008, 0.024), 1, 0, 0.012),),
    "car": (GraspSegment("cabin", (-0.03, -0.01, 0.01, 0.03), 0, 1, 0.018),),
    "faucet": (GraspSegment("spout", (-0.03, -0.01, 0.01, 0.03), 2, 1, 0.011),),
    "chair": (GraspSegment("backrest", (-0.018, -0.006, 0.006, 0.018), 1, 0, 0.012),),
    "screen": (GraspSegment("panel", (-0.075, -0.025, 0.025, 0.075), 0, 1, 0.015),),
    "pistol": (
        GraspSegment("slide", (0.038, 0.052), 0, 1, 0.010),
        GraspSegment("grip", (-0.022, -0.008, 0.006), 1, 0, 0.009),
    ),
}


def _part_frame(obj: ObjectModel, part: str) -> tuple[np.ndarray, np.ndarray]:
    p = next((q for q in obj.parts if q.name == part), None)
    if p is None:
        raise UnknownNameError("part", part, [q.name for q in obj.parts])
    T = p.transform()
    return T, p.size


def _candidates_for(obj: ObjectModel) -> list[GraspCandidate]:
    poses = list(obj.resting_poses.items())
    out: list[GraspCandidate] = _segment_candidates(obj, poses[0][0])
    for pose, quat in poses[1:]:
        up = quat_to_mat(quat)[2]
        out += [GraspCandidate(T, w, part, pose) for part, T, w in top_grasps(obj, up)]
    # Close the set under the object's symmetries.
    extra = [
        GraspCandidate(S @ c.T_O_G, c.width, c.part, c.pose) for S in obj.symmetries for c in out
    ]
    return out + extra


def _segment_candidates(obj: ObjectModel, pose: str) -> list[GraspCandidate]:
    out: list[GraspCandidate] = []
    for seg in SEGMENTS[obj.name]:
        T_part, size = _part_frame(obj, seg.part)
        R = T_part[:3, :3]
        if len(size) == 2:  # cylinder: local z is its axis, half-length size[1], radius size[0]
            half = np.array([size[0], size[0], size[1]])
        else:
            half = np.asarray(size, float)
        slide_dir = R[:, seg.slide_axis]
        close_dir = R[:, seg.close_axis]
        # Projected onto the horizontal plane of O: the approach is straight down (-z of O).
        close_dir = close_dir - close_dir[2] * np.array([0, 0, 1.0])
        close_dir /= np.linalg.norm(close_dir)
        approach = np.array([0.0, 0.0, -1.0])
        # Top of the part at its centre line.
        top = T_part[:3, 3].copy()
        top[2] = max(
            (T_part[:3, :3] @ (np.array(s) * half) + T_part[:3, 3])[2]
            for s in np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).T.reshape(-1, 3)
        )
        width = float(2 * half[seg.close_axis])
        for off in seg.slide:
            centre = top + off * slide_dir
            centre[2] -= seg.depth
            for sign in (1.0, -1.0):
                y = sign * close_dir
                z = np.cross(approach, y)
                T = np.eye(4)
                T[:3, :3] = np.column_stack([approach, y, z])
                T[:3, 3] = centre
                out.append(GraspCandidate(T, width, seg.part, pose))
    return out


#: The part a user object's candidates name (it is one mesh).
MESH_PART = "mesh"
#: The closest a user object's candidate may bring the open fingertips to the table at the
#: estimated pose [m] (`GraspCandidate.table_margin`; the planner keeps the fingers 5 mm off it).
MESH_TABLE_MARGIN = 0.006


#: Where a built-in object's candidates come from: its designed segments (the default), or the
#: generator of a user object's (`grasping.mesh_grasps`). A user object's are generated either way.
CANDIDATE_SOURCES = ("designed", "generated")
#: The part generated candidates name.
GENERATED_PART = "generated"


def grasp_candidates(name: str, source: str = "designed") -> tuple[GraspCandidate, ...]:
    """The grasp candidates of an object class, built-in or user object, in its frame O; the
    same tuple while the object is unchanged.

    Args:
        name: the object.
        source: for a built-in object, one of `CANDIDATE_SOURCES`.

    Raises:
        UnknownNameError: name is not a known object, or an unknown source.
    """
    if source not in CANDIDATE_SOURCES:
        raise UnknownNameError("candidate source", source, CANDIDATE_SOURCES)
    if name in OBJECT_NAMES:
        if source == "generated":
            return generated_candidates(name)
        return _builtin_candidates(name)
    check_object(name)
    return _stored_candidates(load_object(name))


@functools.cache
def _builtin_candidates(name: str) -> tuple[GraspCandidate, ...]:
    return tuple(_candidates_for(load_object(name)))


def _generator_key(name: str) -> str:
    """What a built-in object's generated candidates depend on: its definition and the
    generator's code (a change to either makes them anew)."""
    h = hashlib.sha256((OBJECTS_DIR / f"{name}.json").read_bytes())
    for module in (antipodal, grasp_check, mesh_grasps):
        h.update(Path(inspect.getfile(module)).read_bytes())
    return h.hexdigest()[:16]


_GENERATED: dict[str, tuple[GraspCandidate, ...]] = {}


def generated_candidates(name: str, progress: bool = False) -> tuple[GraspCandidate, ...]:
    """A built-in object's candidates made by the generator of user objects, for every graspable
    resting pose (about half a minute per object the first time, with a progress bar when
    `progress`; then read from the data folder), kept in memory by name."""
    if name not in _GENERATED:
        _GENERATED[name] = _read_or_make(name, progress)
    return _GENERATED[name]


def _read_or_make(name: str, progress: bool) -> tuple[GraspCandidate, ...]:
    path = data_root() / "candidates" / f"{name}_{_generator_key(name)}.json"
    try:
        rows = json.loads(path.read_text())
    except (OSError, ValueError):
        obj = load_object(name)
        resting = {k: q for k, q in obj.resting_poses.items() if k not in obj.ungraspable}
        made = mesh_grasps.mesh_grasps(obj, resting, progress=progress)
        rows = [
            {"pose": pose, "T_O_G": g.T_O_G.tolist(), "width": g.width}
            for pose, res in made.items()
            for g in res.grasps
        ]
        try:
            atomic_write_json(path, rows)
        except OSError:
            pass  # a read-only data folder: made again by the next process
    return tuple(
        GraspCandidate(
            np.asarray(r["T_O_G"], float),
            float(r["width"]),
            GENERATED_PART,
            r["pose"],
            MESH_TABLE_MARGIN,
        )
        for r in rows
    )


_STORED: dict[tuple[str, str], tuple[GraspCandidate, ...]] = {}


def _stored_candidates(obj: ObjectModel) -> tuple[GraspCandidate, ...]:
    """A user object's stored candidates, cached by name and revision."""
    key = (obj.name, obj.revision)
    if key not in _STORED:
        _STORED[key] = tuple(
            GraspCandidate(g.T_O_G, g.width, MESH_PART, g.pose, MESH_TABLE_MARGIN)
            for g in obj.grasps
        )
    return _STORED[key]
