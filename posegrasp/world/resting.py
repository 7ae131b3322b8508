"""Stable resting poses of an object, found by physics.

The object is dropped from many uniformly random orientations onto a plane, with the contact
settings of the scenes (`scenes/world.xml`), and left to come to rest. Where it ends up is
described by the direction in O that points up (the resting pose up to a free yaw about the
plane's normal). Those directions are clustered; a cluster is a resting pose when it keeps its
orientation when placed afresh and left alone for a second. Its share is the fraction of drops
that ended in it.

`python -m posegrasp.world.resting --object phone` prints what the drops find;
`--write` stores it in `scenes/objects/<name>.json` (`resting_poses`), the pose the object was
designed to stand in first (the canonical one, used by the `isolated` tier). The functions take an
object's name or any `ObjectModel`, so a mesh object being made (`sim.add_object`) is dropped
the same way.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from posegrasp.core.cli import ArgumentParser, command
from posegrasp.core.errors import AssetError, InvalidArgumentError
from posegrasp.core.paths import SCENES_DIR
from posegrasp.core.progress import progress_bar
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.transforms import quat_to_mat
from posegrasp.core.validate import arg, check_choice, check_int, check_seed
from posegrasp.world.objects import OBJECT_NAMES, ObjectModel, check_object, load_object

#: A plane with the world's contact class (`scenes/world.xml`, class "world") and its options.
PLANE_XML = """<mujoco>
  <option timestep="0.002" integrator="implicitfast" cone="elliptic" impratio="10"/>
  <worldbody>
    <geom name="plane" type="plane" size="20 20 0.05" contype="1" conaffinity="3" condim="3"
          friction="1 0.005 0.0001"/>
  </worldbody>
</mujoco>"""

#: Up directions closer than this belong to one resting pose [deg].
CLUSTER_DEG = 8.0
#: A resting pose must keep its up direction within this when placed and left alone [deg].
STABLE_DEG = 3.0
#: Poses reached by fewer drops than this share are left out (too unlikely to be met).
MIN_SHARE = 0.03


@dataclass(frozen=True)
class RestingPose:
    """One stable resting pose.

    Attributes:
        name: its name (`up_<axis>` after the axis of O nearest the up direction).
        quat: an orientation of O resting in it, wxyz (any yaw about the vertical is the same pose).
        up: the unit direction in O that points up.
        share: fraction of random drops that ended in it.
    """

    name: str
    quat: np.ndarray
    up: np.ndarray
    share: float


def upright_quat(up: np.ndarray) -> np.ndarray:
    """The smallest rotation that turns direction `up` (in O) to the world's +z, as wxyz."""
    u = np.asarray(up, float) / np.linalg.norm(up)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(u, z)
    s, c = float(np.linalg.norm(axis)), float(u @ z)
    if s < 1e-9:
        return np.array([1.0, 0.0, 0.0, 0.0]) if c > 0 else np.array([0.0, 1.0, 0.0, 0.0])
    q = np.zeros(4)
    mujoco.mju_axisAngle2Quat(q, axis / s, float(np.arctan2(s, c)))
    return q


def _model(obj: str | ObjectModel) -> ObjectModel:
    """The object itself, or the known object of that name (UnknownNameError otherwise)."""
    return obj if isinstance(obj, ObjectModel) else load_object(check_object(obj))


def _drop_model(
    obj: ObjectModel, quats: np.ndarray, spacing: float
) -> tuple[mujoco.MjModel, list[str]]:
    spec = mujoco.MjSpec.from_string(PLANE_XML)
    bodies = []
    side = int(np.ceil(np.sqrt(len(quats))))
    for i, q in enumerate(quats):
        xy = spacing * np.array([i % side, i // side], float)
        z = obj.resting_height(q) + 0.01
        bodies.append(f"drop{i}")
        obj.add_to_spec(spec, bodies[-1], np.array([xy[0], xy[1], z]), q)
    return spec.compile(), bodies


def _settle(obj: str | ObjectModel, quats: np.ndarray, seconds: float) -> np.ndarray:
    """Up directions in O (n, 3) after dropping copies of the object with orientations quats."""
    obj = _model(obj)
    spacing = 1.5 * obj.diameter + 0.1
    model, bodies = _drop_model(obj, quats, spacing)
    data = mujoco.MjData(model)
    mujoco.mj_step(model, data, nstep=round(seconds / model.opt.timestep))
    return np.array([data.body(b).xmat.reshape(3, 3)[2] for b in bodies])


def _cluster(ups: np.ndarray) -> list[tuple[np.ndarray, int]]:
    """Greedy clustering of unit vectors by angle: (mean direction, count), largest first."""
    cos = np.cos(np.deg2rad(CLUSTER_DEG))
    left = list(range(len(ups)))
    out = []
    while left:
        counts = [sum(ups[i] @ ups[j] > cos for j in left) for i in left]
        centre = left[int(np.argmax(counts))]
        members = [j for j in left if ups[centre] @ ups[j] > cos]
        mean = ups[members].mean(axis=0)
        out.append((mean / np.linalg.norm(mean), len(members)))
        left = [j for j in left if j not in members]
    return out


def axis_name(up: np.ndarray, taken: set[str]) -> str:
    """``up_<sign><axis>`` after the axis of O nearest the up direction `up` (3,), with a
    number appended when `taken` holds that name already."""
    k = int(np.argmax(np.abs(up)))
    base = f"up_{'+' if up[k] > 0 else '-'}{'xyz'[k]}"
    name, n = base, 2
    while name in taken:
        name, n = f"{base}_{n}", n + 1
    return name


def find_resting_poses(
    name: str | ObjectModel,
    drops: int = 96,
    seed: int = 0,
    seconds: float = 3.0,
    progress: bool = False,
    settled: bool = False,
) -> list[RestingPose]:
    """The stable resting poses of an object, most frequent first.

    Args:
        name: object class, or the object itself.
        drops: random orientations dropped.
        seed: seed of the orientations.
        seconds: simulated time each drop is given to come to rest [s].
        progress: show a progress bar.
        settled: describe each pose by the up direction its stability check ends in (the mean
            over the four yaws) instead of its cluster's mean; an object that rocks a little
            before it rests is then described where it rests.

    Raises:
        UnknownNameError: an unknown object.
        InvalidArgumentError: drops < 1.
    """
    obj = _model(name)
    if drops < 1:
        raise InvalidArgumentError(f"drops must be at least 1, got {drops}")
    rng = np.random.default_rng(seed)
    quats = rng.normal(size=(drops, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    ups = []
    batch = 16
    for i in progress_bar(range(0, drops, batch), desc=f"drops {obj.name}", disable=not progress):
        ups.append(_settle(obj, quats[i : i + batch], seconds))
    clusters = _cluster(np.vstack(ups))
    found: list[RestingPose] = []
    taken: set[str] = set()
    for up, count in clusters:
        share = count / drops
        if share < MIN_SHARE:
            continue
        quat = upright_quat(up)
        after = _stability(obj, quat)
        if after is None:
            continue
        if settled:
            up = after / np.linalg.norm(after)
            quat = upright_quat(up)
        pose_name = axis_name(up, taken)
        taken.add(pose_name)
        found.append(RestingPose(pose_name, quat, up, share))
    return found


def is_stable(name: str | ObjectModel, quat: np.ndarray, seconds: float = 1.0) -> bool:
    """Whether an object (its class, or the object itself) placed on a plane in orientation quat
    (wxyz) keeps its up direction within `STABLE_DEG` for `seconds`, at four yaws."""
    return _stability(name, quat, seconds) is not None


def _stability(
    name: str | ObjectModel, quat: np.ndarray, seconds: float = 1.0
) -> np.ndarray | None:
    """The mean up direction (in O) the object ends in after `is_stable`'s test, None when it
    does not keep its up direction."""
    up = quat_to_mat(np.asarray(quat, float))[2]
    yaws = np.deg2rad([0.0, 90.0, 180.0, 270.0])
    placed = []
    for yaw in yaws:
        q = np.zeros(4)
        mujoco.mju_mulQuat(q, np.array([np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]), quat)
        placed.append(q)
    after = _settle(name, np.array(placed), seconds)
    cos = after @ up
    if not np.all(cos > np.cos(np.deg2rad(STABLE_DEG))):
        return None
    return after.mean(axis=0)


def merged_poses(name: str, found: list[RestingPose]) -> list[dict]:
    """The `resting_poses` entries for the object file: the pose the object was designed to
    stand in (the first listed now) first, then every other pose found. A found pose that an
    existing entry already describes keeps that entry's name and orientation.

    Raises:
        AssetError: the canonical pose is not stable.
    """
    obj = load_object(name)
    existing = list(obj.resting_poses.items())
    canon_name, canon_quat = existing[0]
    if not is_stable(name, canon_quat):
        raise AssetError(f"the canonical resting pose {canon_name!r} of {name} is not stable")
    cos = np.cos(np.deg2rad(CLUSTER_DEG))
    entries: dict[str, dict] = {
        canon_name: {"name": canon_name, "quat": _rounded(canon_quat), "share": 0.0}
    }
    for p in found:
        match = next(
            ((n, q) for n, q in existing if p.up @ quat_to_mat(q)[2] > cos), (p.name, p.quat)
        )
        entry = entries.setdefault(
            match[0], {"name": match[0], "quat": _rounded(match[1]), "share": 0.0}
        )
        entry["share"] = round(entry["share"] + p.share, 3)
    for entry in entries.values():
        if entry["name"] in obj.ungraspable:
            entry["graspable"] = False
    return list(entries.values())


def _rounded(q: np.ndarray) -> list[float]:
    q = np.asarray(q, float)
    return [round(float(v), 6) for v in q / np.linalg.norm(q)]


def _parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m posegrasp.world.resting", description=__doc__)
    names = [*OBJECT_NAMES, "all"]
    p.add_argument(
        "--object",
        default="all",
        type=arg(check_choice, names, "object"),
        help=f"one of {', '.join(OBJECT_NAMES)} or all (default all)",
    )
    p.add_argument(
        "--drops",
        type=arg(check_int, 1, 4096, "--drops", base=int),
        default=96,
        help="random drops per object, 1..4096 (default 96)",
    )
    p.add_argument(
        "--seed",
        type=arg(check_seed, "--seed", base=int),
        default=0,
        help="seed of the drops, 0..2**32-1 (default 0)",
    )
    p.add_argument("--write", action="store_true", help="store the poses in the object files")
    return p


@command
def main(argv: list[str] | None = None) -> int:
    """Find (and with --write store) the resting poses of one object or all; the exit status."""
    args = _parser().parse_args(argv)
    setup_rendering()
    names = OBJECT_NAMES if args.object == "all" else (args.object,)
    _run(names, args.drops, args.seed, args.write)
    return 0


def _run(names: tuple[str, ...], drops: int, seed: int, write: bool) -> None:
    for name in names:
        found = find_resting_poses(name, drops, seed, progress=True)
        entries = merged_poses(name, found)
        for e in entries:
            up = quat_to_mat(np.asarray(e["quat"]))[2]
            print(f"{name:7s} {e['name']:14s} share {e['share']:.3f}  up in O {np.round(up, 3)}")
        if write:
            _write_poses(SCENES_DIR / "objects" / f"{name}.json", entries)


def _write_poses(path: Path, entries: list[dict]) -> None:
    """Replace the `resting_poses` list of an object file, one entry a line, the rest of the
    file as it was."""
    text = path.read_text()
    key = '"resting_poses":'
    start = text.index(key) + len(key)
    rest = text[start:].lstrip()
    _, length = json.JSONDecoder().raw_decode(rest)
    stop = len(text) - len(rest) + length
    body = ",\n".join("    " + json.dumps(e) for e in entries)
    path.write_text(text[:start] + " [\n" + body + "\n  ]" + text[stop:])


if __name__ == "__main__":
    sys.exit(main())
