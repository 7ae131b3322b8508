"""Meshes posegrasp did not make, from packages on PyPI, made into objects, grasped by the oracle.

    python studies/public_meshes.py [--set public|unseen] [--episodes 100] \
        [--tiers isolated,any-pose,clutter] [--dense FACES] [--workers 2] [--out out/public] \
        [--json PATH]

Each mesh comes out of a pinned wheel of the package that ships it (``pip download --no-deps``
into ``<out>/wheels``, the member read from the zip). The ``public`` set: robosuite's can, milk
carton and bottle (STL in metres), and pybullet's duck (OBJ, scaled by 0.05 as its URDF does) and
mug (OBJ in metres). The ``unseen`` set, the held-out meshes of the unseen-objects track, never
trained or tuned on: robosuite's can, milk carton, bottle, bread, cereal box and lemon as their
OBJ files, with the MTL and texture image each names (read out in the wheel's own layout, so
that the MTL's relative paths hold). Each becomes a user object in ``<out>/objects`` by
``python -m sim.add_object`` with its defaults (timed, one object at a time, the silhouette
codebook included: its onboarding), then the oracle grasps it on `--episodes` held-out episodes
per tier (seeds from `posegrasp.world.constants.EVAL_SEED_BASE`; 0: none), exactly as
``POSEGRASP_OBJECTS=<out>/objects python -m sim.evaluate --objects NAME --tier T --estimator
oracle`` does. Made objects and reports already in `--out` are reused, so a rerun after an
interruption goes on where it stopped. Prints one row per mesh: source, size, faces, watertight
or not, hulls, resting poses (graspable), candidates, add_object time, codebook time, the
onboarding's whole time and oracle success per tier. With `--dense FACES`, each mesh is also
subdivided and simplified to FACES triangles (``<out>/meshes/<name>_dense.stl``, no texture) and
made the object ``<name>_dense`` the same way: onboarding's time on a dense mesh.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from dataclasses import dataclass, replace
from pathlib import Path

import trimesh

from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    add_out_argument,
    add_workers_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.files import atomic_write_json
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_choice, check_int, check_names
from posegrasp.world.constants import EVAL_SEED_BASE
from posegrasp.world.meshes import read_mesh, simplified
from posegrasp.world.user_objects import OBJECTS_ENV


@dataclass(frozen=True)
class PublicMesh:
    """A mesh inside a package's wheel.

    Attributes:
        name: the object's name.
        package, version: the wheel (``pip download package==version``).
        member: the mesh's path inside the wheel.
        units, scale: `python -m sim.add_object`'s --units and --scale for it.
        extras: further members the mesh file names (its MTL, texture images), read out with it
            in the wheel's layout.
    """

    name: str
    package: str
    version: str
    member: str
    units: str = "m"
    scale: float = 1.0
    extras: tuple[str, ...] = ()


MESHES: tuple[PublicMesh, ...] = (
    PublicMesh("can", "robosuite", "1.5.2", "robosuite/models/assets/objects/meshes/can.stl"),
    PublicMesh("milk", "robosuite", "1.5.2", "robosuite/models/assets/objects/meshes/milk.stl"),
    PublicMesh("bottle", "robosuite", "1.5.2", "robosuite/models/assets/objects/meshes/bottle.stl"),
    PublicMesh("duck", "pybullet", "3.2.7", "pybullet_data/duck.obj", scale=0.05),
    PublicMesh("mug", "pybullet", "3.2.7", "pybullet_data/objects/mug.obj"),
)
_ROBOSUITE = "robosuite/models/assets/"


def _robosuite_obj(name: str, texture: str | None) -> PublicMesh:
    """Robosuite's OBJ of `name`, with its MTL and the texture image that names."""
    mesh = f"{_ROBOSUITE}objects/meshes/{name}"
    extras = (f"{mesh}.mtl",) + (() if texture is None else (f"{_ROBOSUITE}textures/{texture}",))
    return PublicMesh(name, "robosuite", "1.5.2", f"{mesh}.obj", extras=extras)


#: The held-out meshes of the unseen-objects track: the detector of any object never saw them.
UNSEEN: tuple[PublicMesh, ...] = (
    _robosuite_obj("can", "soda.png"),
    _robosuite_obj("milk", "ceramic.png"),
    _robosuite_obj("bottle", None),
    _robosuite_obj("bread", "bread.png"),
    _robosuite_obj("cereal", "cereal.png"),
    _robosuite_obj("lemon", "lemon.png"),
)
SETS: dict[str, tuple[PublicMesh, ...]] = {"public": MESHES, "unseen": UNSEEN}
TIER_CHOICES = ("isolated", "any-pose", "clutter")


def fetch_mesh(mesh: PublicMesh, out: Path) -> Path:
    """The mesh file, read out of its wheel (downloaded once into ``out/wheels``); with
    `PublicMesh.extras`, read out with them under ``out/meshes/<name>/`` in the wheel's
    layout."""
    target = out / "meshes" / f"{mesh.name}{Path(mesh.member).suffix}"
    if mesh.extras:
        target = out / "meshes" / mesh.name / mesh.member
    if target.is_file():
        return target
    wheels = out / "wheels"
    wheels.mkdir(parents=True, exist_ok=True)
    pattern = f"{mesh.package}-{mesh.version}-*.whl"
    if not list(wheels.glob(pattern)):
        cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary", ":all:"]
        cmd += ["-q", "-d", str(wheels), f"{mesh.package}=={mesh.version}"]
        done = subprocess.run(cmd, capture_output=True, text=True)
        if done.returncode != 0 or not list(wheels.glob(pattern)):
            last = (done.stderr.strip().splitlines() or ["no wheel"])[-1]
            raise InvalidArgumentError(f"cannot download {mesh.package}=={mesh.version}: {last}")
    with zipfile.ZipFile(next(wheels.glob(pattern))) as z:
        for member in mesh.extras:
            extra = out / "meshes" / mesh.name / member
            extra.parent.mkdir(parents=True, exist_ok=True)
            extra.write_bytes(z.read(member))
        data = z.read(mesh.member)
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_bytes(data)  # last: its presence says every member is there
    return target


def dense_mesh(mesh: PublicMesh, path: Path, faces: int, out: Path) -> tuple[PublicMesh, Path]:
    """The mesh subdivided until it has at least `faces` triangles, then quadric-simplified to
    `faces` (``out/meshes/<name>_dense.stl``, in the mesh's own units), and its `PublicMesh`."""
    target = out / "meshes" / f"{mesh.name}_dense.stl"
    if not target.is_file():
        m = read_mesh(path)
        m = trimesh.Trimesh(m.vertices, m.faces)  # the geometry alone
        while len(m.faces) < faces:
            m = m.subdivide()
        m = simplified(m, faces)
        target.parent.mkdir(parents=True, exist_ok=True)
        part = target.with_name(target.name + ".part.stl")
        m.export(part)
        part.replace(target)
    member = f"{mesh.member}, subdivided and simplified to {faces} triangles"
    return replace(mesh, name=f"{mesh.name}_dense", member=member, extras=()), target


def make(mesh: PublicMesh, path: Path, objects: Path) -> dict:
    """The object's description, made by ``python -m sim.add_object`` in a process of its own
    (read back when the object exists)."""
    desc = objects / mesh.name / "object.json"
    if not desc.is_file():
        cmd = [sys.executable, "-m", "sim.add_object", str(path), "--name", mesh.name]
        cmd += ["--units", mesh.units, "--scale", str(mesh.scale)]
        env = {**os.environ, OBJECTS_ENV: str(objects)}
        print(f"add_object {mesh.name} ({mesh.package} {mesh.member})", file=sys.stderr)
        done = subprocess.run(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        if done.returncode != 0:
            raise InvalidArgumentError(
                f"add_object refused {mesh.name}: {done.stderr.decode().strip()[-300:]}"
            )
    return json.loads(desc.read_text())


def grasp(name: str, tier: str, episodes: int, out: Path, workers: int) -> dict:
    """The oracle's report on the object in the tier (reused when in ``out``)."""
    from sim.evaluation import Protocol, evaluate_protocol

    path = out / "reports" / f"{name}_{tier}.json"
    if path.is_file():
        return json.loads(path.read_text())
    print(f"oracle {name} {tier}", file=sys.stderr)
    protocol = Protocol([name], episodes, EVAL_SEED_BASE, tier)
    report = evaluate_protocol(protocol, "oracle", workers=workers)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(path, report)
    return report


def row(mesh: PublicMesh, desc: dict, reports: dict[str, dict]) -> dict:
    """One table row: the mesh, what add_object found, and the oracle's success per tier."""
    poses = desc["resting_poses"]
    ext = [desc["models_info"][f"size_{a}"] for a in "xyz"]
    return {
        "object": mesh.name,
        "source": f"{mesh.package} {mesh.version}: {mesh.member}",
        "size_mm": [round(e) for e in ext],
        "watertight": desc["source"]["watertight"],
        "triangles": desc["source"]["triangles"],
        "textured": "texture" in desc,
        "symmetries": desc["symmetries"]["summary"],
        "hulls": desc["decomposition"]["hulls"],
        "resting_poses": len(poses),
        "graspable_poses": sum(p["graspable"] for p in poses),
        "candidates": sum(len(g) for g in desc["grasps"].values()),
        "add_object_s": desc["timings_s"]["total"],
        "codebook_s": desc["timings_s"].get("codebook"),
        "onboarding_s": desc["timings_s"].get("onboarding"),
        "oracle": {
            t: [r["overall"]["successes"], r["overall"]["episodes"]] for t, r in reports.items()
        },
    }


def _seconds(x: float | None) -> str:
    return "-" if x is None else f"{x:.0f} s"


def table(rows: list[dict]) -> str:
    """The rows as a Markdown table."""
    tiers = list(rows[0]["oracle"]) if rows else []
    head = "| object | source | size [mm] | faces | textured | watertight | symmetry | hulls "
    head += "| resting poses (graspable) | candidates | add_object | codebook | onboarding | "
    head += " | ".join(tiers) + " |"
    lines = [head, "|" + "---|" * (13 + len(tiers))]
    for r in rows:
        succ = " | ".join(f"{s}/{n}" for s, n in r["oracle"].values())
        lines.append(
            f"| {r['object']} | {r['source']} | {' x '.join(map(str, r['size_mm']))} | "
            f"{r['triangles']} | {'yes' if r['textured'] else 'no'} | "
            f"{'yes' if r['watertight'] else 'no'} | {r['symmetries']} | {r['hulls']} | "
            f"{r['resting_poses']} ({r['graspable_poses']}) | {r['candidates']} | "
            f"{_seconds(r['add_object_s'])} | {_seconds(r['codebook_s'])} | "
            f"{_seconds(r['onboarding_s'])} | {succ} |"
        )
    return "\n".join(lines)


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(prog="python studies/public_meshes.py", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--episodes",
        type=arg(check_int, 0, 10_000, "--episodes", base=int),
        default=100,
        help="oracle episodes per object and tier, 0..10000 (0: the objects alone; default 100)",
    )
    p.add_argument(
        "--set",
        type=arg(check_choice, list(SETS), "set"),
        default="public",
        help="the meshes: public (the oracle's check of meshes made elsewhere) or unseen (the "
        "held-out meshes of the unseen-objects track) (default public)",
    )
    p.add_argument(
        "--tiers",
        type=arg(check_names, TIER_CHOICES, "tier", "--tiers"),
        default=list(TIER_CHOICES),
        help=f"'all' or a comma list of {', '.join(TIER_CHOICES)}",
    )
    p.add_argument(
        "--meshes",
        type=arg(
            check_names, sorted({m.name for ms in SETS.values() for m in ms}), "mesh", "--meshes"
        ),
        default=None,
        help="'all' or a comma list of the set's meshes (default: all), of: "
        + "; ".join(f"{k}: {', '.join(m.name for m in ms)}" for k, ms in SETS.items()),
    )
    p.add_argument(
        "--dense",
        type=arg(check_int, 1000, 1_000_000, "--dense", base=int),
        default=None,
        metavar="FACES",
        help="also make each mesh subdivided and simplified to FACES triangles, 1000..1000000, "
        "as <name>_dense (default: not)",
    )
    add_workers_argument(p)
    add_out_argument(p, "wheels, meshes, objects and reports, reused by a rerun", "out/public")
    add_json_argument(p, "the rows")
    args = p.parse_args(argv)
    setup_rendering()
    log = summary_stream(args.json)
    objects = (args.out / "objects").resolve()
    os.environ[OBJECTS_ENV] = str(objects)  # the evaluations' workers inherit it
    rows = []
    tiers = args.tiers if args.episodes > 0 else []
    for mesh in (m for m in SETS[args.set] if args.meshes is None or m.name in args.meshes):
        path = fetch_mesh(mesh, args.out)
        made = [(mesh, path)]
        if args.dense is not None:
            made.append(dense_mesh(mesh, path, args.dense, args.out))
        for m, path in made:
            desc = make(m, path, objects)
            reports = {t: grasp(m.name, t, args.episodes, args.out, args.workers) for t in tiers}
            rows.append(row(m, desc, reports))
    print(table(rows), file=log)
    print(f"objects in {objects}: {OBJECTS_ENV}={objects} python -m sim.run_episode ...", file=log)
    if args.json is not None:
        write_json(args.json, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
