"""Any estimator's poses, as a standard BOP results CSV, scored by grasping on them.

An export of `sim.export_bop` holds the head-camera views of an evaluation's episodes as a BOP
dataset, and its map file (`MAP_FILE`) says which episode each image is. An estimator that
reads BOP datasets writes its poses of those images as a BOP results CSV (BOP Challenge 2019
format)::

    scene_id,im_id,obj_id,score,R,t,time
    1,0,1,0.98,r11 r12 r13 r21 r22 r23 r31 r32 r33,tx ty tz,0.12

``R`` is ``R_C_O`` row-major, ``t`` is ``t_C_O`` [mm], ``time`` the image's run time [s] or -1
when unknown. `read_bop_results` checks such a file against the export; `BopPosesEstimator`
answers each episode of the export with its rows, so that ``sim.evaluate`` grasps on them; and
`read_export` lists the export's episodes so that exactly those are run.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from perception.training.bop import MM_PER_M, obj_id, obj_name
from posegrasp.core.contract import Estimate, Observation
from posegrasp.core.errors import InvalidArgumentError, PosegraspError
from posegrasp.core.validate import check_int, check_seed
from posegrasp.world.objects import check_object, object_names
from posegrasp.world.tiers import check_tier

#: The export's map file: its episodes and how they map to BOP scene and image ids.
MAP_FILE = "posegrasp_episodes.json"
#: ``format`` and ``version`` of the map file.
EXPORT_FORMAT = "posegrasp-bop-export"
EXPORT_VERSION = 1
#: The columns of a BOP 2019 results CSV, in BOP's order.
CSV_COLUMNS = ("scene_id", "im_id", "obj_id", "score", "R", "t", "time")
#: Largest entry of ``|R R^T - I|`` accepted for a CSV rotation. BOP CSVs print a limited number
#: of digits: a rotation rounded to 4 decimals is off by at most about 3e-4 here (float32 values,
#: as most estimators print, by about 1e-7); 1e-3 admits those and refuses anything visibly not a
#: rotation. A matrix within it is replaced by the nearest rotation (`nearest_rotation`), whose
#: points differ from the printed matrix's by at most 0.1 % of their distance from the origin,
#: since an episode refuses a pose further than `posegrasp.core.contract.ROTATION_TOL` (1e-6)
#: from a rotation.
ROTATION_TOL = 1e-3


# --- the export's map file -----------------------------------------------------------------


@dataclass(frozen=True)
class ExportEpisodes:
    """The episodes of an export, as ``sim.evaluate`` runs them.

    Attributes:
        root: the export folder.
        tier: the scene tier.
        seed_start: the first scene seed; episode i of an object plays seed ``seed_start + i``.
        objects: the target classes, in the evaluation's order.
        episodes: episodes per object.
        ground_truth: whether the export holds scene_gt.json and scene_gt_info.json.
        images: (object, seed) -> (scene_id, im_id) of the episode's image.
    """

    root: Path
    tier: str
    seed_start: int
    objects: tuple[str, ...]
    episodes: int
    ground_truth: bool
    images: dict[tuple[str, int], tuple[int, int]]

    @property
    def image_ids(self) -> set[tuple[int, int]]:
        """The (scene_id, im_id) of every image of the export."""
        return set(self.images.values())


def _bad_map(path: Path, problem: str) -> InvalidArgumentError:
    return InvalidArgumentError(
        f"{path} is not a complete posegrasp BOP export map ({problem}); write the export with "
        f"python -m sim.export_bop --out {path.parent}"
    )


def read_export(root: Path | str) -> ExportEpisodes:
    """The episodes of an export folder of ``python -m sim.export_bop``, checked.

    Args:
        root: the export folder (its `MAP_FILE` is read).

    Returns:
        The export's episodes: every object x episode index once, seeds from ``seed_start``.

    Raises:
        InvalidArgumentError: the folder holds no map file, an unreadable or inconsistent one,
            or an export that was interrupted.
    """
    root = Path(root)
    path = root / MAP_FILE
    if not path.is_file():
        raise InvalidArgumentError(
            f"{root} is not a posegrasp BOP export: it has no {MAP_FILE}; write one with "
            f"python -m sim.export_bop --out {root}"
        )
    try:
        raw = json.loads(path.read_text())
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise _bad_map(path, f"unreadable JSON: {exc}") from None
    if not isinstance(raw, dict) or raw.get("format") != EXPORT_FORMAT:
        raise _bad_map(path, f"no format {EXPORT_FORMAT!r}")
    if raw.get("version") != EXPORT_VERSION:
        raise _bad_map(path, f"version {raw.get('version')!r}, expected {EXPORT_VERSION}")
    if raw.get("complete") is not True:
        raise InvalidArgumentError(
            f"the export in {root} was interrupted before it finished; run the same "
            "python -m sim.export_bop command again to complete it"
        )
    try:
        tier = check_tier(raw["tier"])
        episodes = check_int(raw["episodes"], 1, 10**6, "episodes")
        seed_start = check_seed(raw["seed_start"], "seed_start", episodes)
        objects = tuple(check_object(o) for o in raw["objects"])
        images: dict[tuple[str, int], tuple[int, int]] = {}
        for im in raw["images"]:
            key = (check_object(im["object"]), check_seed(im["seed"]))
            images[key] = (
                check_int(im["scene_id"], 0, 10**6 - 1, "scene_id"),
                check_int(im["im_id"], 0, 10**6 - 1, "im_id"),
            )
        ground_truth = bool(raw["ground_truth"])
    except (KeyError, TypeError) as exc:
        raise _bad_map(path, f"missing or malformed field {exc}") from None
    except PosegraspError as exc:
        raise _bad_map(path, str(exc)) from None
    wanted = {(o, seed_start + i) for o in objects for i in range(episodes)}
    if len(objects) != len(set(objects)) or set(images) != wanted:
        raise _bad_map(path, "its images are not every object x episode once")
    if len(set(images.values())) != len(images):
        raise _bad_map(path, "two episodes share an image id")
    return ExportEpisodes(root, tier, seed_start, objects, episodes, ground_truth, images)


# --- the results CSV -----------------------------------------------------------------------


@dataclass(frozen=True)
class BopRow:
    """One pose of a results CSV.

    Attributes:
        T_C_O: the pose in the camera frame (OpenCV), shape (4, 4) [m], its rotation the
            nearest rotation to the CSV's ``R``.
        score: the estimator's confidence.
        time: the image's run time [s], -1 when unknown.
        line: the line of the CSV it was read from (the header is line 1).
    """

    T_C_O: np.ndarray
    score: float
    time: float
    line: int


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    """The rotation nearest to R in the Frobenius norm (SVD projection onto SO(3)).

    Args:
        R: a (3, 3) matrix with positive determinant.

    Returns:
        The rotation, shape (3, 3).
    """
    U, _, Vt = np.linalg.svd(R)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))])
    return U @ D @ Vt


def _numbers(text: str, n: int, what: str, where: str) -> np.ndarray:
    parts = text.split()
    try:
        values = np.array([float(p) for p in parts], np.float64)
    except ValueError:
        raise InvalidArgumentError(f"{where}: {what} {text.strip()!r} is not {n} numbers") from None
    if values.size != n:
        raise InvalidArgumentError(
            f"{where}: {what} has {values.size} numbers, expected {n} (space-separated)"
        )
    if not np.all(np.isfinite(values)):
        raise InvalidArgumentError(f"{where}: {what} {text.strip()!r} is not finite")
    return values


def _integer(text: str, what: str, where: str) -> int:
    try:
        return int(text.strip())
    except ValueError:
        raise InvalidArgumentError(f"{where}: {what} {text.strip()!r} is not an integer") from None


def _header(line: str, where: str) -> dict[str, int]:
    names = [c.strip() for c in line.split(",")]
    expected = ",".join(CSV_COLUMNS)
    missing = [c for c in CSV_COLUMNS if c not in names]
    if missing:
        raise InvalidArgumentError(
            f"{where}: missing column(s) {', '.join(missing)}; the header of a BOP results "
            f"CSV is {expected}"
        )
    extra = sorted({c for c in names if c not in CSV_COLUMNS or names.count(c) > 1})
    if extra:
        raise InvalidArgumentError(
            f"{where}: unknown or repeated column(s) {', '.join(extra)}; the header of a BOP "
            f"results CSV is {expected}"
        )
    return {c: names.index(c) for c in CSV_COLUMNS}


def _row(
    fields: list[str], cols: dict[str, int], export: ExportEpisodes, where: str
) -> tuple[tuple[int, int, int], float, np.ndarray, float]:
    """(scene_id, im_id, obj_id), score, T_C_O [m] and time of one checked CSV row."""
    if len(fields) != len(cols):
        raise InvalidArgumentError(
            f"{where}: {len(fields)} comma-separated fields, expected {len(cols)} "
            f"({','.join(CSV_COLUMNS)})"
        )
    scene_id = _integer(fields[cols["scene_id"]], "scene_id", where)
    im_id = _integer(fields[cols["im_id"]], "im_id", where)
    oid = _integer(fields[cols["obj_id"]], "obj_id", where)
    known = object_names()
    if not 1 <= oid <= len(known):
        names = ", ".join(f"{i + 1} {n}" for i, n in enumerate(known))
        raise InvalidArgumentError(f"{where}: unknown obj_id {oid}; valid obj_ids: {names}")
    if (scene_id, im_id) not in export.image_ids:
        scenes = sorted({s for s, _ in export.image_ids})
        raise InvalidArgumentError(
            f"{where}: image scene_id {scene_id}, im_id {im_id} is not in the export "
            f"{export.root} (scene_ids {', '.join(map(str, scenes))}, im_ids "
            f"0..{export.episodes - 1})"
        )
    score = float(_numbers(fields[cols["score"]], 1, "score", where)[0])
    R = _numbers(fields[cols["R"]], 9, "R", where).reshape(3, 3)
    deviation = float(np.abs(R @ R.T - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if deviation > ROTATION_TOL or det <= 0.0:
        raise InvalidArgumentError(
            f"{where}: R is not a rotation (largest entry of |R R^T - I| {deviation:.2g}, "
            f"tolerance {ROTATION_TOL:g}; det {det:.3g}, must be +1)"
        )
    t = _numbers(fields[cols["t"]], 3, "t", where) / MM_PER_M
    time = float(_numbers(fields[cols["time"]], 1, "time", where)[0])
    if time < 0.0 and time != -1.0:
        raise InvalidArgumentError(f"{where}: time {time:g} is not seconds >= 0 or -1 (unknown)")
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = nearest_rotation(R), t
    return (scene_id, im_id, oid), score, T, time


def read_bop_results(
    csv_path: Path | str, export: ExportEpisodes | Path | str
) -> dict[tuple[int, int, int], BopRow]:
    """The poses of a BOP results CSV of an export's images, checked; the highest-scoring row
    per (scene_id, im_id, obj_id) (the first of equal scores).

    Args:
        csv_path: the CSV (header `CSV_COLUMNS`, in any order; blank lines are skipped).
        export: the export it answers, or its folder.

    Returns:
        (scene_id, im_id, obj_id) -> its row.

    Raises:
        InvalidArgumentError: one line naming the CSV's line (and its row) and the problem: a
            missing column, a field that is not a number, a rotation that is not one, an unknown
            obj_id or an image that is not in the export.
    """
    if not isinstance(export, ExportEpisodes):
        export = read_export(export)
    csv_path = Path(csv_path)
    try:
        lines = csv_path.read_text(encoding="utf-8-sig").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InvalidArgumentError(f"cannot read BOP results {csv_path}: {exc}") from None
    numbered = [(k + 1, line) for k, line in enumerate(lines) if line.strip()]
    if not numbered:
        raise InvalidArgumentError(
            f"{csv_path} is empty; a BOP results CSV starts with the header {','.join(CSV_COLUMNS)}"
        )
    first, header = numbered[0]
    cols = _header(header, f"{csv_path} line {first}")
    best: dict[tuple[int, int, int], BopRow] = {}
    for row, (line_no, line) in enumerate(numbered[1:], start=1):
        where = f"{csv_path} row {row} (line {line_no})"
        key, score, T, time = _row(line.split(","), cols, export, where)
        if key not in best or score > best[key].score:
            best[key] = BopRow(T, score, time, line_no)
    return best


# --- the estimator -------------------------------------------------------------------------


class BopPosesEstimator:
    """The poses of a BOP results CSV, answered episode by episode (the estimator contract,
    `posegrasp.core.contract.PoseEstimator`).

    The observation's (object, seed) names the episode; the export's map file names its image;
    the CSV's row of that image and the target's obj_id is the estimate, and the image's rows
    of other objects are its neighbours. It holds plain arrays and dicts, so it pickles to
    evaluation workers; it reads no file after construction.

    Attributes:
        name: what reports call it.
        export: the export's episodes.
    """

    def __init__(
        self, csv_path: Path | str, export: ExportEpisodes | Path | str, name: str | None = None
    ) -> None:
        """Read and check the CSV against the export.

        Args:
            csv_path: the BOP results CSV.
            export: the export (or its folder) the CSV answers.
            name: what reports call the estimator (default ``bop:<CSV file name>``).

        Raises:
            InvalidArgumentError: a bad CSV or export (`read_bop_results`, `read_export`).
        """
        self.export = export if isinstance(export, ExportEpisodes) else read_export(export)
        self.name = name or f"bop:{Path(csv_path).name}"
        self._by_image: dict[tuple[int, int], dict[int, BopRow]] = {}
        for (scene_id, im_id, oid), row in sorted(read_bop_results(csv_path, self.export).items()):
            self._by_image.setdefault((scene_id, im_id), {})[oid] = row

    def estimate(self, obs: Observation) -> Estimate:
        """The CSV's pose of the episode's target, the image's other rows as neighbours.

        Args:
            obs: the episode's observation (only ``object`` and ``seed`` are read).

        Returns:
            ``Estimate(T_C_O [m], ((class, T_C_N), ...), info)`` with info ``score``, ``time``
            [s] (-1: unknown), ``scene_id``, ``im_id`` and ``csv_line``; ``Estimate(None,
            info={"note": "no row for this target", ...})`` when the CSV has no row for it.

        Raises:
            InvalidArgumentError: the episode is not one of the export's.
        """
        key = (obs.object, int(obs.seed))
        if key not in self.export.images:
            raise InvalidArgumentError(
                f"episode {obs.object} seed {obs.seed} is not in the export {self.export.root} "
                f"({', '.join(self.export.objects)}, seeds {self.export.seed_start}.."
                f"{self.export.seed_start + self.export.episodes - 1}, tier {self.export.tier})"
            )
        scene_id, im_id = self.export.images[key]
        rows = self._by_image.get((scene_id, im_id), {})
        where: dict[str, Any] = {"scene_id": scene_id, "im_id": im_id}
        oid = obj_id(obs.object)
        target = rows.get(oid)
        if target is None:
            return Estimate(None, info={"note": "no row for this target", **where})
        neighbours = tuple(
            (obj_name(other), row.T_C_O.copy()) for other, row in rows.items() if other != oid
        )
        info = {
            "score": target.score,
            "time": target.time,
            "csv_line": target.line,
            **where,
        }
        return Estimate(target.T_C_O.copy(), neighbours, info)


# --- VSD against the export's depth ----------------------------------------------------------


def vsd_errors(export: ExportEpisodes, episodes: list[dict[str, Any]]) -> list[list[float] | None]:
    """BOP's VSD of each episode's estimate against its exported depth image (one error per
    tau, `perception.metrics.BOP_VSD_TAUS`), None for an episode without an estimate.

    Args:
        export: the export the episodes ran (its depth images and cameras are read).
        episodes: the episodes as a report holds them (object, seed, T_C_O_true, T_C_O_est).

    Raises:
        AssetError: a depth image or camera file of the export is missing or unreadable.
    """
    import cv2

    from perception import metrics
    from perception.training.bop import read_json, scene_dir
    from posegrasp.world.objects import load_object

    cameras: dict[int, dict[str, Any]] = {}
    out: list[list[float] | None] = []
    for e in episodes:
        if e.get("T_C_O_est") is None:
            out.append(None)
            continue
        scene_id, im_id = export.images[(e["object"], int(e["seed"]))]
        sdir = scene_dir(export.root, "test", scene_id)
        if scene_id not in cameras:
            cameras[scene_id] = read_json(sdir / "scene_camera.json", export.root, "test")
        cam = cameras[scene_id][str(im_id)]
        path = sdir / "depth" / f"{im_id:06d}.png"
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None or raw.dtype != np.uint16:
            from posegrasp.core.errors import AssetError

            raise AssetError(f"{path} is not a 16-bit depth image of the export")
        depth = raw.astype(np.float64) * float(cam["depth_scale"]) / MM_PER_M
        K = np.asarray(cam["cam_K"], np.float64).reshape(3, 3)
        model = load_object(e["object"])
        T_gt, T_est = np.asarray(e["T_C_O_true"]), np.asarray(e["T_C_O_est"])
        err = metrics.vsd(
            T_est[:3, :3],
            T_est[:3, 3],
            T_gt[:3, :3],
            T_gt[:3, 3],
            depth,
            K,
            np.asarray(model.mesh.vertices),
            np.asarray(model.mesh.faces),
            model.diameter,
        )
        out.append([float(v) for v in err])
    return out
