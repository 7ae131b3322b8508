"""Make a mesh into a posegrasp object, usable by every command that takes an object.

    python -m sim.add_object MESH --name NAME --units {m,mm} [--scale S]
        [--mass KG | --density KG_M3] [--friction MU] [--symmetry SPEC ...] [--force]

Reads an OBJ, STL, PLY or GLB file (trimesh), and writes the object's folder into the user objects
directory (`posegrasp.world.user_objects`: ``$POSEGRASP_OBJECTS``, else
``~/.local/share/posegrasp/objects``): the visual mesh; convex collision hulls from CoACD, its
parameters recorded; mass (given, or density times the hulls' volume) and inertia from the hulls,
also for a mesh that is not watertight; the stable resting poses, found by dropping it
(`posegrasp.world.resting`); for every resting pose, grasp candidates for the Fetch gripper
(antipodal pairs, checked by closing the gripper in physics, a batch of them on each core;
`grasping.mesh_grasps`); its symmetries, detected or given, in BOP's models_info form; and a
preview sheet. Last it builds the object's silhouette codebook, which every RGB estimator here
matches detections against (`perception.codebook`, cached under the data root), so that the
object is onboarded as a whole: ``timings_s.onboarding`` in object.json is the time of it all.
Then ``python -m sim.run_episode --object NAME`` grasps it.
"""

from __future__ import annotations

import json
import math
import os
import platform
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from grasping.antipodal import horizontal_basis, hull_points
from grasping.grasp_check import CheckConfig
from grasping.mesh_grasps import KEEP, PoseGrasps, checks_per_pose, mesh_grasps
from grasping.top_grasps import FINGER_X, MAX_WIDTH
from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.files import atomic_write_json, sha256_file
from posegrasp.core.paths import git_commit
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_float, check_input_file, check_int, check_seed
from posegrasp.world import meshes as M
from posegrasp.world.object_preview import preview_sheet
from posegrasp.world.objects import OBJECT_NAMES, ObjectModel
from posegrasp.world.resting import (
    CLUSTER_DEG,
    RestingPose,
    axis_name,
    find_resting_poses,
    upright_quat,
)
from posegrasp.world.user_objects import (
    DESCRIPTION_FILE,
    FORMAT_VERSION,
    PREVIEW_FILE,
    MeshGeometry,
    check_object_name,
    object_folder,
    objects_dir,
    write_object_folder,
)

#: Density when neither --mass nor --density is given [kg/m^3] (a solid plastic part).
DEFAULT_DENSITY = 500.0
#: MuJoCo friction of the object (sliding, torsional, rolling), the built-in objects'.
DEFAULT_FRICTION = (1.0, 0.01, 0.0005)
#: Random drops that find the resting poses.
DEFAULT_DROPS = 96
#: Name of the canonical resting pose.
CANONICAL = "canonical"
#: Resting poses whose up directions are closer than this, up to the object's symmetries, are
#: one [deg] (the rarer one's share goes to the other): a candidate made for one would be met
#: tilted in the other.
MERGE_DEG = 15.0
#: Directions of the mesh file's frame `--up` may name.
UP_CHOICES = ("auto", "+x", "-x", "+y", "-y", "+z", "-z")


def check_new_name(name: str) -> str:
    """A name a new user object may take: valid (`check_object_name`) and not a built-in one.

    Raises:
        InvalidArgumentError: otherwise.
    """
    if name in OBJECT_NAMES:
        raise InvalidArgumentError(
            f"--name {name!r} is a built-in object ({', '.join(OBJECT_NAMES)}); choose another"
        )
    return check_object_name(name)


def check_coacd(spec: str) -> tuple[str, Any]:
    """``KEY=VALUE``: one CoACD parameter (`posegrasp.world.meshes.COACD_DEFAULTS`), the value
    of the default's type.

    Raises:
        InvalidArgumentError: an unknown key or a value of the wrong type.
    """
    key, sep, text = str(spec).partition("=")
    if not sep or key not in M.COACD_DEFAULTS:
        raise InvalidArgumentError(
            f"invalid --coacd {spec!r}; valid: KEY=VALUE with KEY one of "
            + ", ".join(M.COACD_DEFAULTS)
        )
    default = M.COACD_DEFAULTS[key]
    value: Any = None
    if isinstance(default, bool):
        if text in ("true", "false"):
            value = text == "true"
    else:
        try:
            value = type(default)(text)
        except ValueError:
            value = None
    if value is None:
        raise InvalidArgumentError(
            f"invalid --coacd {spec!r}: {key} takes a {type(default).__name__} "
            f"(default {str(default).lower() if isinstance(default, bool) else default})"
        )
    return key, value


def _merged(
    found: list[RestingPose], syms: M.Symmetries, prefer: np.ndarray | None = None
) -> list[RestingPose]:
    """Resting poses with those within `MERGE_DEG` of a more frequent one, up to the object's
    symmetries, folded into it (a symmetric object lies the same way in both); a pose whose up
    direction is within `CLUSTER_DEG` of `prefer` (3,) is kept before any other."""
    cos = math.cos(math.radians(CLUSTER_DEG))

    def first(p: RestingPose) -> tuple[bool, float]:
        return (prefer is None or not p.up @ prefer > cos, -p.share)

    kept: list[RestingPose] = []
    for p in sorted(found, key=first):
        near = next((k for k, q in enumerate(kept) if syms.angle_deg(p.up, q.up) < MERGE_DEG), None)
        if near is None:
            kept.append(p)
        else:
            q = kept[near]
            kept[near] = RestingPose(q.name, q.quat, q.up, q.share + p.share)
    return kept


def _load() -> list[float] | None:
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return None


def _narrowest(points: np.ndarray, up: np.ndarray) -> float:
    """The object's smallest horizontal width over closing directions, resting with `up` (in
    its frame) up, above the fingertips' lowest reach [m]."""
    u = up / np.linalg.norm(up)
    h = points @ u
    keep = points[h >= h.min() + FINGER_X[1] + 0.008]
    if len(keep) < 3:
        keep = points
    e1, e2 = horizontal_basis(u)
    widths = []
    for k in range(36):
        t = math.pi * k / 36
        widths.append(float(np.ptp(keep @ (math.cos(t) * e1 + math.sin(t) * e2))))
    return min(widths)


def make_object(
    mesh_path: Path,
    name: str,
    units: str,
    scale: float = 1.0,
    mass: float | None = None,
    density: float | None = None,
    friction: float | None = None,
    symmetry: list[str] | None = None,
    drops: int = DEFAULT_DROPS,
    seed: int = 0,
    keep: int = KEEP,
    force: bool = False,
    up: str = "auto",
    coacd: dict[str, Any] | None = None,
    log=sys.stdout,
) -> dict[str, Any]:
    """Make the object and write its folder; what `main` does.

    Args:
        mesh_path: the mesh file.
        name: the new object's name (`check_new_name`).
        units: the file's length unit, one of `posegrasp.world.meshes.UNITS`.
        scale: factor applied after the units.
        mass: total mass [kg]; or
        density: density [kg/m^3] (`DEFAULT_DENSITY` when neither is given).
        friction: sliding friction coefficient (`DEFAULT_FRICTION`'s when None).
        symmetry: ``--symmetry`` specifications (`posegrasp.world.meshes.given_symmetries`);
            None detects them.
        drops: random drops that find the resting poses.
        seed: seed of the drops and of every sampling.
        keep: grasps kept per resting pose.
        force: replace an existing user object of that name.
        up: the direction of the mesh file's frame that points up in the canonical resting
            pose (one of `UP_CHOICES`); "auto" takes +z when the mesh rests graspably so, else
            the graspable pose most drops end in.
        coacd: CoACD parameters that replace `posegrasp.world.meshes.COACD_DEFAULTS`' (the
            seed is `seed` unless given).
        log: where progress lines go.

    Returns:
        The object's description (its object.json) with ``folder``.

    Raises:
        InvalidArgumentError: the mesh cannot become an object (one line saying why).
    """
    t_start = time.perf_counter()
    load_start = _load()
    timings: dict[str, float] = {}
    _check_request(name, mass, density, force)
    say = _printer(log)
    src = _source(
        mesh_path, name, units, scale, mass, density, friction, symmetry, seed, coacd, say, timings
    )
    found, axis = _resting(src, mesh_path, drops, seed, up, say, timings)
    grasps_s = _grasps(src, found, keep, timings)
    graspable = _graspable(mesh_path, found, grasps_s, src.dec, seed)
    canon, why = _canonical(mesh_path, found, graspable, axis, up)
    made = _in_canonical_frame(src, found, canon, why, grasps_s)
    obj, png = _preview(name, mesh_path, src, made, timings)
    timings["total"] = time.perf_counter() - t_start

    request = _Request(mesh_path, name, units, scale, mass, symmetry, drops, seed, keep)
    description = _description(request, src, made, obj.diameter, timings, load_start)
    folder = write_object_folder(
        name, description, made.visual, made.hulls, png, replace=force, texture=made.texture
    )
    timings["codebook"] = _codebook(name, say)
    timings["onboarding"] = time.perf_counter() - t_start
    written = json.loads((folder / DESCRIPTION_FILE).read_text())
    atomic_write_json(folder / DESCRIPTION_FILE, {**written, "timings_s": dict(timings)})
    description = {**written, "timings_s": dict(timings), "folder": str(folder)}
    _report(description, log)
    return description


def _check_request(name: str, mass: float | None, density: float | None, force: bool) -> None:
    """Raise `InvalidArgumentError` when the object cannot be made as asked: a name a new object
    may not take (`check_new_name`), a user object of that name and no `force`, or both a mass
    and a density."""
    check_new_name(name)
    if object_folder(name).exists() and not force:
        raise InvalidArgumentError(
            f"a user object {name!r} exists in {objects_dir()}; give --force to replace it"
        )
    if mass is not None and density is not None:
        raise InvalidArgumentError("give --mass or --density, not both")


def _printer(log) -> Callable[[str], None]:
    """A function printing one progress line to `log` at once."""

    def say(text: str) -> None:
        print(text, file=log, flush=True)

    return say


def _grasps(
    src: _Source, found: list[RestingPose], keep: int, timings: dict[str, float]
) -> dict[str, PoseGrasps]:
    """The checked grasps of every resting pose found (named p0, p1, ... in their order), in
    frame S; the time taken goes into `timings`."""
    t = time.perf_counter()
    by_pose = {f"p{i}": p.quat for i, p in enumerate(found)}
    config = CheckConfig(threads=_cores())
    checked = checks_per_pose(len(by_pose))
    grasps_s = mesh_grasps(
        src.obj_s, by_pose, checked=checked, keep=keep, config=config, progress=True
    )
    timings["grasps"] = time.perf_counter() - t
    return grasps_s


def _cores() -> int:
    """The cores this process may run on: the grasps' physics checks run a batch on each (as
    CoACD's threads use them all)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity on this platform
        return os.cpu_count() or 1


@dataclass(frozen=True)
class _Request:
    """What the description records of the call."""

    mesh_path: Path
    name: str
    units: str
    scale: float
    mass: float | None
    symmetry: list[str] | None
    drops: int
    seed: int
    keep: int


@dataclass(frozen=True)
class _Made:
    """The object in its canonical frame O: the resting pose chosen as canonical stands upright."""

    T_O_S: np.ndarray
    visual: trimesh.Trimesh
    texture: M.Texture | None
    hulls: list[trimesh.Trimesh]
    props: Any
    syms: Any
    poses: list[dict[str, Any]]
    stored: dict[str, list[dict[str, Any]]]
    drawn: dict[str, list[tuple[np.ndarray, float]]]
    why: str


def _resting(
    src: _Source,
    mesh_path: Path,
    drops: int,
    seed: int,
    up: str,
    say: Callable[[str], None],
    timings: dict[str, float],
) -> tuple[list[RestingPose], np.ndarray]:
    """The resting poses found by dropping the object, merged up to its symmetries, and the
    axis --up names (+z for "auto"); raises `InvalidArgumentError` when it never settles."""
    t = time.perf_counter()
    found = find_resting_poses(src.obj_s, drops=drops, seed=seed, progress=True, settled=True)
    timings["resting_poses"] = time.perf_counter() - t
    if not found:
        raise InvalidArgumentError(
            f"cannot use {mesh_path.name}: it comes to rest in no stable pose on a plane "
            "(it rolls, or rocks without settling)"
        )
    axis = np.eye(3)["xyz".index((up if up != "auto" else "+z")[1])]
    axis = axis * (-1.0 if up.startswith("-") else 1.0)
    found = _merged(found, src.syms_s, axis)
    say(f"  {len(found)} resting poses ({sum(p.share for p in found) * 100:.0f} % of the drops)")
    return found, axis


def _in_canonical_frame(
    src: _Source, found: list[Any], canon: int, why: str, grasps_s: dict[str, PoseGrasps]
) -> _Made:
    """The mesh, hulls, inertia, symmetries, resting poses and grasps moved from frame S into
    the canonical frame O."""
    T_O_S = M.canonical_frame(src.visual_s, found[canon].up)
    visual = src.visual_s.copy()
    visual.apply_transform(T_O_S)
    hulls = [h.copy() for h in src.dec.hulls]
    for h in hulls:
        h.apply_transform(T_O_S)
    poses, stored, drawn = _pose_records(found, canon, grasps_s, T_O_S)
    texture = src.obj_s.geometry.texture if src.obj_s.geometry is not None else None
    return _Made(
        T_O_S=T_O_S,
        visual=visual,
        texture=None if texture is None else texture.moved(T_O_S),
        hulls=hulls,
        props=M.transform_inertia(src.props_s, T_O_S),
        syms=src.syms_s.transformed(T_O_S),
        poses=poses,
        stored=stored,
        drawn=drawn,
        why=why,
    )


def _preview(
    name: str, mesh_path: Path, src: _Source, made: _Made, timings: dict[str, float]
) -> tuple[ObjectModel, Any]:
    """The object as a model and its preview sheet (every resting pose with its grasps); the
    time taken goes into `timings`."""
    t = time.perf_counter()
    obj = ObjectModel(
        name=name,
        description="",
        parts=(),
        mass=made.props.mass,
        friction=src.friction,
        resting_poses={p["name"]: np.asarray(p["quat"]) for p in made.poses},
        geometry=MeshGeometry(
            "preview",
            made.visual,
            tuple(made.hulls),
            src.rgba,
            made.props.com,
            made.props.inertia,
            made.texture,
        ),
    )
    title = (
        f"{name}: {mesh_path.name}, {len(made.hulls)} hulls, {made.props.mass * 1000:.0f} g, "
        f"symmetries {made.syms.describe()}"
    )
    sheet = preview_sheet(obj, made.poses, made.drawn, title)
    timings["preview"] = time.perf_counter() - t
    return obj, sheet


def _description(
    req: _Request,
    src: _Source,
    made: _Made,
    diameter: float,
    timings: dict[str, float],
    load_start: list[float] | None,
) -> dict[str, Any]:
    """The object's description, its object.json: where it came from, its physics, symmetries,
    resting poses and grasps, and how they were found (parameters, times, machine, versions)."""
    props, syms = made.props, made.syms
    return {
        "format": FORMAT_VERSION,
        "name": req.name,
        "description": f"made from {req.mesh_path.name}",
        "units": req.units,
        "scale": req.scale,
        "source": {
            "file": str(req.mesh_path.resolve()),
            "sha256": sha256_file(req.mesh_path),
            "triangles": len(src.raw.faces),
            "watertight": bool(src.raw.is_watertight),
        },
        "T_O_source": [
            [round(float(v), 9) for v in row]
            for row in made.T_O_S @ _centring(src.raw, req.units, req.scale)
        ],
        "mass": props.mass,
        "mass_from": "given" if req.mass is not None else "density x hull volume",
        "density": props.density,
        "hull_volume": props.volume,
        "centre_of_mass": [float(v) for v in props.com],
        "inertia": [[float(v) for v in row] for row in props.inertia],
        "friction": list(src.friction),
        "rgba": [round(float(v), 4) for v in src.rgba],
        "decomposition": {
            "tool": src.dec.tool,
            "parameters": src.dec.parameters,
            "hulls": len(made.hulls),
            "seconds": round(src.dec.seconds, 2),
            "triangles": src.dec.faces,
            "simplified_from": src.dec.simplified_from,
            "convex": src.dec.convex,
        },
        "symmetries": {
            "source": "given" if req.symmetry else "detected",
            "given": req.symmetry or [],
            "summary": syms.describe(),
            "errors_rel_diameter": [round(e, 5) for e in syms.errors],
        },
        "models_info": {**_bop_size(diameter, made.visual), **syms.models_info()},
        "resting_poses": made.poses,
        "canonical_pose": made.why,
        "resting_search": {"drops": req.drops, "seed": req.seed},
        "grasps": made.stored,
        "grasp_search": {"kept_per_pose": req.keep, "both_finger_orders": True},
        "timings_s": {k: round(v, 2) for k, v in timings.items()},
        "machine": {
            "cpus": os.cpu_count(),
            "load_at_start": load_start,
            "load_at_end": _load(),
            "platform": platform.platform(),
        },
        "tools": {
            "posegrasp": git_commit(),
            "trimesh": version("trimesh"),
            "mujoco": version("mujoco"),
            "coacd": version("coacd"),
        },
    }


@dataclass(frozen=True)
class _Source:
    """The mesh made into an object in frame S (the file's axes, centred, in metres)."""

    raw: trimesh.Trimesh
    visual_s: trimesh.Trimesh
    rgba: np.ndarray
    syms_s: Any
    dec: Any
    props_s: Any
    friction: tuple[float, float, float]
    obj_s: ObjectModel


def _source(
    mesh_path: Path,
    name: str,
    units: str,
    scale: float,
    mass: float | None,
    density: float | None,
    friction: float | None,
    symmetry: list[str] | None,
    seed: int,
    coacd: dict[str, Any] | None,
    say: Callable[[str], None],
    timings: dict[str, float],
) -> _Source:
    """Read the mesh, find its symmetries, decompose it into convex hulls and give it mass (see
    `make_object` for the arguments); each step's time goes into `timings`."""
    t = time.perf_counter()
    raw = M.read_mesh(mesh_path)
    visual_s, T_centre = M.centred(M.scaled_mesh(raw, units, scale, mesh_path.name))
    rgba = M.mesh_colour(raw)
    texture = M.mesh_texture(raw, M.UNITS[units] * scale)
    texture_s = None if texture is None else texture.moved(T_centre)
    ext = visual_s.extents
    say(
        f"read {mesh_path.name}: {len(visual_s.faces)} triangles, "
        f"{'watertight' if raw.is_watertight else 'not watertight'}, "
        f"{ext[0] * 1000:.0f} x {ext[1] * 1000:.0f} x {ext[2] * 1000:.0f} mm"
    )
    timings["read"] = time.perf_counter() - t

    t = time.perf_counter()
    syms_s = (
        M.given_symmetries(symmetry, visual_s) if symmetry else M.detect_symmetries(visual_s, seed)
    )
    timings["symmetries"] = time.perf_counter() - t
    say(f"  symmetries: {syms_s.describe()}")

    t = time.perf_counter()
    say("convex decomposition ...")
    dec = M.decompose(visual_s, **{"seed": seed, **(coacd or {})})
    timings["decomposition"] = time.perf_counter() - t
    cut = f", cut from its {dec.faces}-triangle simplification" if dec.simplified_from else ""
    if dec.convex:
        say(f"  convex: its own hull, in {dec.seconds:.1f} s")
    else:
        say(f"  {len(dec.hulls)} hulls in {dec.seconds:.1f} s{cut}")
    props_s = M.mass_properties(
        dec.hulls, mass=mass, density=None if mass is not None else (density or DEFAULT_DENSITY)
    )
    say(
        f"  mass {props_s.mass * 1000:.0f} g"
        + (" (given)" if mass is not None else f" ({props_s.density:g} kg/m^3 x hull volume)")
        + f", hull volume {props_s.volume * 1e6:.0f} cm^3"
    )
    fr = DEFAULT_FRICTION if friction is None else (friction, *DEFAULT_FRICTION[1:])
    obj_s = ObjectModel(
        name=name,
        description="",
        parts=(),
        mass=props_s.mass,
        friction=fr,
        geometry=MeshGeometry(
            "s", visual_s, tuple(dec.hulls), rgba, props_s.com, props_s.inertia, texture_s
        ),
    )
    return _Source(raw, visual_s, rgba, syms_s, dec, props_s, fr, obj_s)


def _graspable(
    mesh_path: Path, found: list[Any], grasps_s: dict[str, PoseGrasps], dec: Any, seed: int
) -> list[int]:
    """The indices of the resting poses with a grasp; raises `InvalidArgumentError` saying why
    when there is none (too wide everywhere, or no grasp held in physics)."""
    graspable = [i for i in range(len(found)) if grasps_s[f"p{i}"].grasps]
    if graspable:
        return graspable
    points, _ = hull_points(list(dec.hulls), 4000, seed)
    narrow = min(_narrowest(points, p.up) for p in found)
    generated = sum(g.generated for g in grasps_s.values())
    if generated == 0 and narrow > MAX_WIDTH:
        raise InvalidArgumentError(
            f"cannot grasp {mesh_path.name}: too wide for the gripper in every resting pose "
            f"(narrowest {narrow * 1000:.0f} mm across; the fingers take at most "
            f"{MAX_WIDTH * 1000:.0f} mm)"
        )
    outcomes = sum((g.outcomes for g in grasps_s.values()), Counter())
    tried = ", ".join(f"{k} {v}" for k, v in sorted(outcomes.items())) or "none checked"
    raise InvalidArgumentError(
        f"cannot grasp {mesh_path.name}: no grasp from above holds in any resting pose "
        f"({generated} antipodal grasps found in {len(found)} poses; in physics: {tried})"
    )


def _canonical(
    mesh_path: Path, found: list[Any], graspable: list[int], axis: np.ndarray, up: str
) -> tuple[int, str]:
    """The canonical pose's index and why it was chosen: the one --up names, or the mesh as it
    stands in its file when that is a graspable resting pose, else the graspable pose most
    drops end in."""
    cos = math.cos(math.radians(CLUSTER_DEG))
    as_given = [i for i in graspable if found[i].up @ axis > cos]
    if up != "auto" and not as_given:
        rests = ", ".join(f"({', '.join(f'{v:+.2f}' for v in found[i].up)})" for i in graspable)
        raise InvalidArgumentError(
            f"--up {up}: {mesh_path.name} does not rest graspably with {up} up; the graspable "
            f"resting poses have up (file frame) {rests}"
        )
    if as_given:
        return as_given[0], f"{up if up != 'auto' else '+z'} of the mesh file up"
    return max(graspable, key=lambda i: found[i].share), "the graspable pose most drops end in"


def _pose_records(
    found: list[Any], canon: int, grasps_s: dict[str, PoseGrasps], T_O_S: np.ndarray
) -> tuple[
    list[dict[str, Any]], dict[str, list[dict[str, Any]]], dict[str, list[tuple[np.ndarray, float]]]
]:
    """The resting poses in frame O, canonical first then by share: their records, their
    grasps' records by pose name, and every other grasp by pose name for the preview."""
    R = T_O_S[:3, :3]
    rest = sorted((i for i in range(len(found)) if i != canon), key=lambda i: -found[i].share)
    poses: list[dict[str, Any]] = []
    taken: set[str] = {CANONICAL}
    stored: dict[str, list[dict[str, Any]]] = {}
    drawn: dict[str, list[tuple[np.ndarray, float]]] = {}
    for i in [canon, *rest]:
        up_dir = R @ found[i].up
        pname = CANONICAL if i == canon else axis_name(up_dir, taken)
        taken.add(pname)
        quat = np.array([1.0, 0.0, 0.0, 0.0]) if i == canon else upright_quat(up_dir)
        pg: PoseGrasps = grasps_s[f"p{i}"]
        poses.append(
            {
                "name": pname,
                "quat": [round(float(v), 6) for v in quat],
                "share": round(found[i].share, 3),
                "up": [round(float(v), 6) for v in up_dir],
                "graspable": bool(pg.grasps),
                "grasp_search": {
                    "generated": pg.generated,
                    "checked": pg.checked,
                    "outcomes": dict(pg.outcomes),
                },
            }
        )
        stored[pname], drawn[pname] = [], []
        for k, g in enumerate(pg.grasps):
            T = T_O_S @ g.T_O_G
            stored[pname].append(
                {
                    "T_O_G": [[round(float(v), 7) for v in row] for row in T],
                    "width": round(g.width, 5),
                    "score": round(g.score, 5),
                    "robust": g.robust,
                }
            )
            if k % 2 == 0:
                drawn[pname].append((T, g.width))
    return poses, stored, drawn


def _bop_size(diameter: float, visual: trimesh.Trimesh) -> dict[str, float]:
    """BOP's models_info size entries [mm]: the diameter, the box's lower corner and size."""
    bounds = visual.bounds
    return {
        "diameter": round(diameter * 1000, 4),
        "min_x": round(float(bounds[0, 0]) * 1000, 4),
        "min_y": round(float(bounds[0, 1]) * 1000, 4),
        "min_z": round(float(bounds[0, 2]) * 1000, 4),
        "size_x": round(float(visual.extents[0]) * 1000, 4),
        "size_y": round(float(visual.extents[1]) * 1000, 4),
        "size_z": round(float(visual.extents[2]) * 1000, 4),
    }


def _centring(raw: trimesh.Trimesh, units: str, scale: float) -> np.ndarray:
    """T_S_file (4, 4): the file's coordinates to the centred frame S, in metres."""
    v = np.asarray(raw.vertices, float) * M.UNITS[units] * scale
    T = np.eye(4) * M.UNITS[units] * scale
    T[3, 3] = 1.0
    T[:3, 3] = -(v.min(axis=0) + v.max(axis=0)) / 2
    return T


def _codebook(name: str, say: Callable[[str], None]) -> float:
    """Build object `name`'s silhouette codebook on the estimators' grid (`CodebookConfig`),
    into the cache they read (`perception.codebook.CodebookCache`); its time [s]."""
    from perception.codebook import CodebookCache
    from perception.stages.config import CodebookConfig

    say("silhouette codebook")
    t = time.perf_counter()
    grid = CodebookConfig()
    CodebookCache(grid.views, grid.inplane).get(name)
    return time.perf_counter() - t


def _report(d: dict[str, Any], log) -> None:
    """What was found, one line per item."""
    poses = d["resting_poses"]
    lines = [
        f"object {d['name']} written to {d['folder']}",
        f"  hulls        {d['decomposition']['hulls']} "
        + (
            "(the mesh is convex: its own hull)"
            if d["decomposition"].get("convex")
            else f"(CoACD {d['decomposition']['tool']['version']})"
        ),
        f"  mass         {d['mass'] * 1000:.0f} g ({d['mass_from']})",
        f"  symmetries   {d['symmetries']['summary']}",
        f"  resting poses {len(poses)} ({sum(not p['graspable'] for p in poses)} not graspable); "
        f"canonical: {poses[0]['name']} ({d['canonical_pose']})",
    ]
    for p in poses:
        s = p["grasp_search"]
        lines.append(
            f"    {p['name']:12s} share {p['share'] * 100:4.0f} %  "
            f"{len(d['grasps'][p['name']]):3d} candidates  "
            f"({s['generated']} generated, {s['checked']} checked: "
            + ", ".join(f"{k} {v}" for k, v in sorted(s["outcomes"].items()))
            + ")"
        )
    t = d["timings_s"]
    lines.append(
        "  time         "
        + ", ".join(f"{k} {v:.1f} s" for k, v in t.items())
        + f"; load {d['machine']['load_at_start']} -> {d['machine']['load_at_end']}"
    )
    lines.append(f"  preview      {Path(d['folder']) / PREVIEW_FILE}")
    lines.append(
        f"  try it       python -m sim.run_episode --object {d['name']} --estimator oracle"
    )
    print("\n".join(lines), file=log)


def _parser() -> ArgumentParser:
    p = ArgumentParser(
        prog="python -m sim.add_object", description=__doc__.split("\n\n")[0].strip()
    )
    p.add_argument(
        "mesh",
        type=arg(check_input_file, "MESH", base=Path),
        metavar="MESH",
        help="an OBJ, STL, PLY or GLB file",
    )
    p.add_argument(
        "--name",
        required=True,
        type=arg(check_new_name),
        help="the object's name: lower-case letters, digits, '_' or '-'",
    )
    p.add_argument("--units", required=True, choices=sorted(M.UNITS), help="the file's length unit")
    p.add_argument(
        "--scale",
        type=arg(check_float, 1e-6, 1e6, "--scale", base=float),
        default=1.0,
        help="factor applied after the units (default 1)",
    )
    _add_physics_arguments(p)
    _add_search_arguments(p)
    p.add_argument("--force", action="store_true", help="replace a user object of that name")
    add_json_argument(p, "the object's description")
    return p


def _add_physics_arguments(p: ArgumentParser) -> None:
    """``--mass`` or ``--density``, ``--friction`` and ``--symmetry``: the object's physics."""
    group = p.add_mutually_exclusive_group()
    group.add_argument(
        "--mass",
        type=arg(check_float, 1e-3, 20.0, "--mass", base=float),
        help="total mass [kg], 0.001..20",
    )
    group.add_argument(
        "--density",
        type=arg(check_float, 1.0, 25000.0, "--density", base=float),
        help=f"density [kg/m^3], 1..25000 (default {DEFAULT_DENSITY:g}): mass = "
        "density x the volume of the collision hulls",
    )
    p.add_argument(
        "--friction",
        type=arg(check_float, 0.1, 2.0, "--friction", base=float),
        help=f"sliding friction coefficient, 0.1..2 (default {DEFAULT_FRICTION[0]})",
    )
    p.add_argument(
        "--symmetry",
        action="append",
        metavar="SPEC",
        help="a symmetry about an axis of the mesh file through its centre, instead of "
        "detecting them: AXIS:N (AXIS x, y or z; N 2..60, or inf for any angle); "
        "repeat for several; 'none' for none",
    )


def _add_search_arguments(p: ArgumentParser) -> None:
    """``--drops``, ``--keep``, ``--seed``, ``--up`` and ``--coacd``: how the hulls, resting
    poses and grasps are found."""
    p.add_argument(
        "--drops",
        type=arg(check_int, 16, 1024, "--drops", base=int),
        default=DEFAULT_DROPS,
        help=f"random drops that find the resting poses, 16..1024 (default {DEFAULT_DROPS})",
    )
    p.add_argument(
        "--keep",
        type=arg(check_int, 1, 32, "--keep", base=int),
        default=KEEP,
        help=f"grasps kept per resting pose, 1..32 (default {KEEP}; each with both finger orders)",
    )
    p.add_argument(
        "--seed",
        type=arg(check_seed, "--seed", base=int),
        default=0,
        help="seed of the drops and samplings (default 0)",
    )
    p.add_argument(
        "--up",
        choices=UP_CHOICES,
        default="auto",
        help="the direction of the mesh file's frame that points up in the canonical resting "
        "pose (the isolated tier's); auto (default): +z when the mesh rests graspably so, else "
        "the graspable pose most drops end in",
    )
    p.add_argument(
        "--coacd",
        action="append",
        type=arg(check_coacd),
        metavar="KEY=VALUE",
        help="a parameter of the convex decomposition (repeat for several; recorded in the "
        "object): " + ", ".join(f"{k} (default {v})" for k, v in M.COACD_DEFAULTS.items()),
    )


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    args = _parser().parse_args(argv)
    if args.symmetry and "none" in args.symmetry and len(args.symmetry) > 1:
        raise InvalidArgumentError("--symmetry none cannot be combined with other symmetries")
    setup_rendering()
    log = summary_stream(args.json)
    d = make_object(
        args.mesh,
        args.name,
        args.units,
        args.scale,
        args.mass,
        args.density,
        args.friction,
        args.symmetry,
        args.drops,
        args.seed,
        args.keep,
        args.force,
        args.up,
        dict(args.coacd or []),
        log,
    )
    if args.json is not None:
        write_json(args.json, json.loads(json.dumps(d)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
