"""Any estimator's poses, as a standard BOP results CSV, scored by grasping on them.

An export of `sim.export_bop` holds the head-camera views of an evaluation's episodes as a BOP
dataset, and its map file (`MAP_FILE`) says which episode each image is. An estimator that
reads BOP datasets writes its poses of those images as a BOP results CSV (BOP Challenge 2019
format)::

    scene_id,im_id,obj_id,score,R,t,time
    407112,0,1,0.98,r11 r12 r13 r21 r22 r23 r31 r32 r33,tx ty tz,0.12

``R`` is ``R_C_O`` row-major, ``t`` is ``t_C_O`` [mm], ``time`` the image's run time [s] or -1
when unknown. `read_bop_results` checks such a file against the export; `BopPosesEstimator`
answers each episode of the export with its rows, so that ``sim.evaluate`` grasps on them; and
`read_export` lists the export's episodes so that exactly those are run.

Each episode is one BOP scene with one image (im_id 0), its scene_id `scene_ids` of the
episode's tier, target and seed, so that exports of other tiers, objects or seeds share no
image id with it (but by rare chance) and a CSV of another export is refused by its ids. Ids
alone cannot tell a CSV of an export whose ids it happens to share: `truth_match` tests, after
the grasps, whether the CSV's poses lie nearer their own episodes' targets than chance allows.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from perception.training.data.bop import MM_PER_M, obj_id, obj_name
from posegrasp.core.contract import MAX_POSE_DISTANCE, Estimate, Observation
from posegrasp.core.errors import InvalidArgumentError, PosegraspError
from posegrasp.core.validate import check_int, check_seed
from posegrasp.world.objects import check_object, object_names
from posegrasp.world.sensors import Sensor
from posegrasp.world.shifts import Shift, parse_shifts
from posegrasp.world.tiers import check_tier

#: The export's map file: its episodes and how they map to BOP scene and image ids.
MAP_FILE = "posegrasp_episodes.json"
#: ``format`` and ``version`` of the map file.
EXPORT_FORMAT = "posegrasp-bop-export"
EXPORT_VERSION = 2
#: Largest BOP scene id: BOP names scene folders with 6 digits.
SCENE_ID_MAX = 999_999
#: A CSV whose poses lie, at the median, nearer the camera than this is taken for one written
#: in metres [mm]: the head camera sees no object within a few centimetres of it, while metres
#: read as millimetres put every pose within about 3 mm.
MIN_MEDIAN_T_MM = 10.0
#: Most problems of a bad CSV listed; a count stands for the rest.
MAX_PROBLEMS = 20
#: `truth_match` calls a CSV's poses unrelated to the export's targets when the chance of its
#: count of nearest-own-target estimates is above this.
TRUTH_MATCH_P = 1e-3
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


def scene_ids(tier: str, episodes: Sequence[tuple[str, int]]) -> dict[tuple[str, int], int]:
    """The BOP scene_id of each episode of an export (its image is im_id 0 of that scene).

    An episode's id is 1 + (the first 8 bytes of SHA-256 of ``"tier/object/seed"``) mod
    `SCENE_ID_MAX`; an id taken by an earlier episode of the list moves to the next free one.
    So the same episode has the same id in every export (but after such a clash), and two
    exports of other tiers, objects or seeds share an id only by chance (with 300 episodes
    each, a given id of one is among the other's with probability 3e-4).

    Args:
        tier: the scene tier.
        episodes: (object, seed) of each episode, in the export's order.

    Returns:
        (object, seed) -> scene_id in 1..SCENE_ID_MAX, all distinct.
    """
    if len(episodes) > SCENE_ID_MAX:
        raise InvalidArgumentError(f"at most {SCENE_ID_MAX} episodes fit one export")
    used: set[int] = set()
    out: dict[tuple[str, int], int] = {}
    for obj, seed in episodes:
        digest = hashlib.sha256(f"{tier}/{obj}/{int(seed)}".encode()).digest()
        sid = 1 + int.from_bytes(digest[:8], "big") % SCENE_ID_MAX
        while sid in used:
            sid = sid % SCENE_ID_MAX + 1
        used.add(sid)
        out[(obj, int(seed))] = sid
    return out


@dataclass(frozen=True)
class ExportEpisodes:
    """The episodes of an export, as ``sim.evaluate`` runs them.

    Attributes:
        root: the export folder.
        tier: the scene tier.
        seed_start: the first scene seed; episode i of an object plays seed ``seed_start + i``.
        objects: the target classes, in the evaluation's order.
        episodes: episodes per object.
        ground_truth: whether the export holds scene_gt.json, scene_gt_info.json and masks.
        images: (object, seed) -> (scene_id, im_id) of the episode's image.
        table_top_z: (object, seed) -> height of the table top in the world frame [m] (what
            ``Observation.table_top_z`` tells a live estimator).
        sensor: the sensor model its images were rendered through (`posegrasp.world.sensors`;
            ``ideal`` in maps written before exports recorded it).
        shifts: the scene shifts its images were rendered under (`posegrasp.world.shifts`;
            none in maps written before exports recorded them): the episodes grasp in the same
            shifted scenes.
    """

    root: Path
    tier: str
    seed_start: int
    objects: tuple[str, ...]
    episodes: int
    ground_truth: bool
    images: dict[tuple[str, int], tuple[int, int]]
    table_top_z: dict[tuple[str, int], float]
    sensor: str = "ideal"
    shifts: tuple[Shift, ...] = ()

    @property
    def image_ids(self) -> set[tuple[int, int]]:
        """The (scene_id, im_id) of every image of the export."""
        return set(self.images.values())

    def describe(self) -> str:
        """The export's episodes in a few words."""
        last = self.seed_start + self.episodes - 1
        return (
            f"tier {self.tier}, objects {','.join(self.objects)}, seeds {self.seed_start}..{last}, "
            f"sensor {self.sensor}"
            + (f", shifts {','.join(map(str, self.shifts))}" if self.shifts else "")
        )


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
        raise _bad_map(path, f"version {raw.get('version')!r}, this version reads {EXPORT_VERSION}")
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
        tables: dict[tuple[str, int], float] = {}
        for im in raw["images"]:
            key = (check_object(im["object"]), check_seed(im["seed"]))
            images[key] = (
                check_int(im["scene_id"], 1, SCENE_ID_MAX, "scene_id"),
                check_int(im["im_id"], 0, 10**6 - 1, "im_id"),
            )
            tables[key] = float(im["table_top_z"])
        ground_truth = bool(raw["ground_truth"])
        sensor = Sensor.parse(raw.get("sensor", "ideal")).name
        shifts = parse_shifts(",".join(raw.get("shifts", [])))
    except (KeyError, TypeError, ValueError) as exc:
        raise _bad_map(path, f"missing or malformed field {exc}") from None
    except PosegraspError as exc:
        raise _bad_map(path, str(exc)) from None
    wanted = {(o, seed_start + i) for o in objects for i in range(episodes)}
    if len(objects) != len(set(objects)) or set(images) != wanted:
        raise _bad_map(path, "its images are not every object x episode once")
    order = [(o, seed_start + i) for o in objects for i in range(episodes)]
    if images != {k: (sid, 0) for k, sid in scene_ids(tier, order).items()}:
        raise _bad_map(
            path,
            "its image ids are not those of its episodes (sim.evaluation.bop_results.scene_ids)",
        )
    return ExportEpisodes(
        root, tier, seed_start, objects, episodes, ground_truth, images, tables, sensor, shifts
    )


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


class _Problems:
    """The problems of a CSV, each one line naming where it is."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def add(self, where: str, problem: str) -> None:
        self.lines.append(f"{where}: {problem}")

    def raise_if_any(self, csv_path: Path) -> None:
        """Raise the problems: one line for one, else a head line and one line per problem,
        the first `MAX_PROBLEMS` of them and a count of the rest."""
        if not self.lines:
            return
        if len(self.lines) == 1:
            raise InvalidArgumentError(self.lines[0])
        shown = self.lines[:MAX_PROBLEMS]
        rest = len(self.lines) - len(shown)
        tail = [f"  ... and {rest} more"] if rest else []
        raise InvalidArgumentError(
            "\n".join(
                [
                    f"{csv_path} has {len(self.lines)} problems (a BOP results CSV: "
                    f"{','.join(CSV_COLUMNS)}, R row-major, t in mm):",
                    *(f"  {line}" for line in shown),
                    *tail,
                ]
            )
        )


def _numbers(text: str, n: int, what: str) -> tuple[np.ndarray | None, str | None]:
    """(n finite numbers, None) or (None, the problem)."""
    parts = text.split()
    try:
        values = np.array([float(p) for p in parts], np.float64)
    except ValueError:
        return None, f"{what} {text.strip()!r} is not {n} number{'s' if n > 1 else ''}"
    if values.size != n:
        return None, f"{what} has {values.size} numbers, expected {n} (space-separated)"
    if not np.all(np.isfinite(values)):
        return None, f"{what} {text.strip()!r} is not finite"
    return values, None


def _integer(text: str, what: str) -> tuple[int | None, str | None]:
    try:
        return int(text.strip()), None
    except ValueError:
        return None, f"{what} {text.strip()!r} is not an integer"


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


@dataclass(frozen=True)
class _Parsed:
    """One CSV row whose fields all parse: its key, score, R (3, 3), t [mm] and time [s]."""

    key: tuple[int, int, int]
    score: float
    R: np.ndarray
    t_mm: np.ndarray
    time: float
    where: str
    line: int


def _row(
    fields: list[str], cols: dict[str, int], where: str, line: int
) -> tuple[_Parsed | None, list[str]]:
    """One CSV row, parsed and checked on its own: (the row or None, its problems)."""
    if len(fields) != len(cols):
        return None, [
            f"{len(fields)} comma-separated fields, expected {len(cols)} ({','.join(CSV_COLUMNS)})"
        ]
    problems: list[str] = []

    def keep(value_problem: tuple[Any, str | None]) -> Any:
        value, problem = value_problem
        if problem is not None:
            problems.append(problem)
        return value

    scene_id = keep(_integer(fields[cols["scene_id"]], "scene_id"))
    im_id = keep(_integer(fields[cols["im_id"]], "im_id"))
    oid = keep(_integer(fields[cols["obj_id"]], "obj_id"))
    known = object_names()
    if oid is not None and not 1 <= oid <= len(known):
        names = ", ".join(f"{i + 1} {n}" for i, n in enumerate(known))
        problems.append(f"unknown obj_id {oid}; valid obj_ids: {names}")
    score = keep(_numbers(fields[cols["score"]], 1, "score"))
    R = keep(_numbers(fields[cols["R"]], 9, "R"))
    if R is not None:
        R = R.reshape(3, 3)
        deviation = float(np.abs(R @ R.T - np.eye(3)).max())
        det = float(np.linalg.det(R))
        if deviation > ROTATION_TOL or det <= 0.0:
            problems.append(
                f"R is not a rotation (largest entry of |R R^T - I| {deviation:.2g}, "
                f"tolerance {ROTATION_TOL:g}; det {det:.3g}, must be +1)"
            )
    t = keep(_numbers(fields[cols["t"]], 3, "t"))
    if t is not None and float(np.linalg.norm(t)) > MAX_POSE_DISTANCE * MM_PER_M:
        norm = float(np.linalg.norm(t))
        problems.append(
            f"t is {norm:.6g} mm from the camera ({norm / MM_PER_M:.4g} m), beyond the "
            f"{MAX_POSE_DISTANCE:g} m any pose may be; the CSV's t is in millimetres"
        )
    time = keep(_numbers(fields[cols["time"]], 1, "time"))
    if time is not None and time[0] < 0.0 and time[0] != -1.0:
        problems.append(f"time {time[0]:g} is not seconds >= 0 or -1 (unknown)")
    if problems:
        return None, problems
    key = (int(scene_id), int(im_id), int(oid))
    return _Parsed(key, float(score[0]), R, t, float(time[0]), where, line), []


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
        InvalidArgumentError: every problem of the CSV, one line each naming its row and line
            (the first `MAX_PROBLEMS`, and a count of the rest): a missing column, a field that
            is not a number, a rotation that is not one, an unknown obj_id, a t beyond 10 m or
            an image that is not in the export; and, as one line, a CSV none of whose images is
            the export's (a CSV of another export) or whose t are, at the median, nearer the
            camera than `MIN_MEDIAN_T_MM` (written in metres).
    """
    if not isinstance(export, ExportEpisodes):
        export = read_export(export)
    csv_path = Path(csv_path)
    problems = _Problems()
    parsed = _parse_rows(csv_path, problems)
    _check_images(csv_path, parsed, export, problems)
    norms = [float(np.linalg.norm(p.t_mm)) for p in parsed]
    if norms and float(np.median(norms)) < MIN_MEDIAN_T_MM:
        problems.lines.insert(
            0,
            f"{csv_path}: t is in millimetres, but its poses lie at a median "
            f"{float(np.median(norms)):.3g} mm from the camera, nearer than any object it sees "
            f"(at least {MIN_MEDIAN_T_MM:g} mm); written in metres? multiply t by 1000",
        )
    problems.raise_if_any(csv_path)
    return _best_rows(parsed)


def _parse_rows(csv_path: Path, problems: _Problems) -> list[_Parsed]:
    """The rows of the CSV that parse and pass the checks of one row (`_row`), in file
    order; the problems of the others are added to `problems`.

    Raises:
        InvalidArgumentError: the file cannot be read, is empty or its header lacks a column.
    """
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
    parsed: list[_Parsed] = []
    for row, (line_no, line) in enumerate(numbered[1:], start=1):
        where = f"{csv_path} row {row} (line {line_no})"
        p, found = _row(line.split(","), cols, where, line_no)
        for f in found:
            problems.add(where, f)
        if p is not None:
            parsed.append(p)
    return parsed


def _check_images(
    csv_path: Path, parsed: list[_Parsed], export: ExportEpisodes, problems: _Problems
) -> None:
    """Add to `problems` each row whose image is not one of the export's.

    Raises:
        InvalidArgumentError: none of the rows' images is the export's (a CSV of another
            export).
    """
    ours = export.image_ids
    if parsed and not any(p.key[:2] in ours for p in parsed):
        s, i = parsed[0].key[:2]
        raise InvalidArgumentError(
            f"{csv_path} answers another export: none of its images (e.g. scene_id {s}, im_id "
            f"{i}) is one of the {len(ours)} of {export.root} ({export.describe()}); grade it "
            "with --from the export it was made from"
        )
    for p in parsed:
        if p.key[:2] not in ours:
            problems.add(
                p.where,
                f"image scene_id {p.key[0]}, im_id {p.key[1]} is not in the export {export.root} "
                f"({export.describe()}; its test_targets_bop19.json lists its images)",
            )


def _best_rows(parsed: list[_Parsed]) -> dict[tuple[int, int, int], BopRow]:
    """The highest-scoring row per (scene_id, im_id, obj_id), the first of equal scores, with
    its pose T_C_O (4, 4) [m]: the nearest rotation to its R, its t in metres."""
    best: dict[tuple[int, int, int], BopRow] = {}
    for p in parsed:
        if p.key not in best or p.score > best[p.key].score:
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = nearest_rotation(p.R), p.t_mm / MM_PER_M
            best[p.key] = BopRow(T, p.score, p.time, p.line)
    return best


def time_summary(times: Sequence[float]) -> dict[str, Any]:
    """The method's run time per image, from a CSV's ``time`` column (-1: not given).

    Args:
        times: one time per image [s], -1 where unknown.

    Returns:
        ``images_timed`` (the images with a time), and over those ``time_s_median`` and
        ``time_s_p90`` [s] (None when no image has one).
    """
    given = np.array([t for t in times if t >= 0.0], np.float64)
    if not given.size:
        return {"images_timed": 0, "time_s_median": None, "time_s_p90": None}
    return {
        "images_timed": int(given.size),
        "time_s_median": float(np.median(given)),
        "time_s_p90": float(np.percentile(given, 90)),
    }


def truth_match(episodes: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Whether a CSV's poses belong to the episodes they were graded in, whatever their ids.

    For each estimate, is its position nearer its own episode's true target position than any
    other episode's of the same object? Were the poses made for other scenes, each of an
    object's m episodes would be the nearest alike (its scenes are drawn alike), so the count
    k of the n estimates is binomial(n, 1/m) at most; ``p_value`` is the chance of k or more
    under it. A poor estimator, whose errors exceed the spread of its targets, scores low too.

    Args:
        episodes: the report's episodes (object, T_C_O_true, T_C_O_est: (4, 4) [m] or None).

    Returns:
        ``estimates`` n (of objects with 2 episodes or more), ``nearest_own`` k, ``chance``
        (the expected k under unrelated poses), ``p_value``, and ``tested``: False when even n
        of n would not be below `TRUTH_MATCH_P`, too few estimates to tell; ``unrelated``:
        tested and p_value above `TRUTH_MATCH_P`.
    """
    by_object: dict[str, list[dict[str, Any]]] = {}
    for e in episodes:
        by_object.setdefault(e["object"], []).append(e)
    n = k = 0
    probs: list[float] = []
    for eps in by_object.values():
        if len(eps) < 2:
            continue
        truth = np.array([np.asarray(e["T_C_O_true"], np.float64)[:3, 3] for e in eps])
        for j, e in enumerate(eps):
            if e.get("T_C_O_est") is None:
                continue
            t = np.asarray(e["T_C_O_est"], np.float64)[:3, 3]
            d = np.linalg.norm(truth - t, axis=1)
            n += 1
            k += int(np.argmin(d) == j)
            probs.append(1.0 / len(eps))
    chance = float(sum(probs))
    p_value = _tail(probs, k)
    tested = n > 0 and _tail(probs, n) < TRUTH_MATCH_P
    return {
        "estimates": n,
        "nearest_own": k,
        "chance": chance,
        "p_value": p_value,
        "tested": bool(tested),
        "unrelated": bool(tested and p_value > TRUTH_MATCH_P),
    }


def _tail(probs: Sequence[float], k: int) -> float:
    """P(X >= k) for X the number of successes of independent trials with these chances."""
    dist = np.zeros(len(probs) + 1)
    dist[0] = 1.0
    for p in probs:
        dist[1:] = dist[1:] * (1.0 - p) + dist[:-1] * p
        dist[0] *= 1.0 - p
    return float(np.clip(dist[k:].sum(), 0.0, 1.0))


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
