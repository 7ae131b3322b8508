"""BOP results CSVs against an export's map file, and the estimator that answers with them."""

from __future__ import annotations

import json
import pickle
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from posegrasp.core.contract import Observation
from posegrasp.core.errors import InvalidArgumentError
from sim.evaluation import bop_results as br

SEED = 1_000_000_000
HEADER = "scene_id,im_id,obj_id,score,R,t,time"
IDS = br.scene_ids("clutter", [(o, SEED + i) for o in ("car", "phone") for i in range(2)])
#: The scene ids of the car's and the phone's episodes 0 and 1.
CAR0, CAR1 = IDS[("car", SEED)], IDS[("car", SEED + 1)]
PHONE0, PHONE1 = IDS[("phone", SEED)], IDS[("phone", SEED + 1)]


def write_map(root: Path, complete: bool = True, **changes) -> Path:
    """A map file of a clutter export of car and phone, 2 episodes each."""
    root.mkdir(parents=True, exist_ok=True)
    images = [
        {
            "scene_id": IDS[(o, SEED + i)],
            "im_id": 0,
            "object": o,
            "seed": SEED + i,
            "table_top_z": 0.4,
        }
        for o in ("car", "phone")
        for i in range(2)
    ]
    raw = {
        "format": br.EXPORT_FORMAT,
        "version": br.EXPORT_VERSION,
        "complete": complete,
        "tier": "clutter",
        "objects": ["car", "phone"],
        "episodes": 2,
        "seed_start": SEED,
        "ground_truth": False,
        "images": images,
        **changes,
    }
    (root / br.MAP_FILE).write_text(json.dumps(raw))
    return root


@pytest.fixture
def export(tmp_path: Path) -> Path:
    return write_map(tmp_path / "export")


def row(scene: int, im: int, oid: int, score: float, R: np.ndarray, t_mm, time=-1) -> str:
    """A CSV row, every number printed in full."""
    r = " ".join(repr(float(x)) for x in R.reshape(-1))
    t = " ".join(repr(float(x)) for x in t_mm)
    return f"{scene},{im},{oid},{score},{r},{t},{time}"


def obs(obj: str, seed: int) -> Observation:
    return Observation(np.zeros((4, 4, 3), np.uint8), np.eye(3), np.eye(4), obj, seed)


def test_read_export_lists_the_episodes(export: Path) -> None:
    ex = br.read_export(export)
    assert (ex.tier, ex.seed_start, ex.objects, ex.episodes) == (
        "clutter",
        SEED,
        ("car", "phone"),
        2,
    )
    assert ex.images[("phone", SEED + 1)] == (PHONE1, 0)
    assert ex.image_ids == {(CAR0, 0), (CAR1, 0), (PHONE0, 0), (PHONE1, 0)}
    assert ex.table_top_z[("car", SEED)] == 0.4


def test_read_export_refuses_a_missing_incomplete_or_inconsistent_map(tmp_path: Path) -> None:
    with pytest.raises(InvalidArgumentError, match=r"no posegrasp_episodes\.json"):
        br.read_export(tmp_path)
    with pytest.raises(InvalidArgumentError, match="interrupted"):
        br.read_export(write_map(tmp_path / "a", complete=False))
    with pytest.raises(InvalidArgumentError, match="every object x episode"):
        br.read_export(write_map(tmp_path / "b", episodes=3))
    with pytest.raises(InvalidArgumentError, match="unknown tier"):
        br.read_export(write_map(tmp_path / "c", tier="nope"))
    # The ids of another tier's episodes, or of an export of the layout before.
    with pytest.raises(InvalidArgumentError, match="not those of its episodes"):
        br.read_export(write_map(tmp_path / "d", tier="isolated"))
    with pytest.raises(InvalidArgumentError, match="version 1, this version reads 2"):
        br.read_export(write_map(tmp_path / "e", version=1))


def test_the_best_row_is_the_estimate_and_other_objects_are_neighbours(
    export: Path, tmp_path: Path
) -> None:
    R1 = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    R2 = Rotation.from_euler("xyz", [-40, 5, 90], degrees=True).as_matrix()
    csv = tmp_path / "r.csv"
    csv.write_text(
        "\n".join(
            [
                HEADER,
                row(CAR0, 0, 1, 0.5, np.eye(3), [0, 0, 900], 0.25),
                row(CAR0, 0, 1, 0.9, R1, [10, -20, 800], 0.25),  # the best car row
                row(CAR0, 0, 1, 0.7, np.eye(3), [0, 0, 700], 0.25),
                row(CAR0, 0, 3, 0.4, R2, [-100, 5, 950], 0.25),  # a chair beside it
                "",
                row(PHONE1, 0, 4, 1.0, R2, [10, 20, 600]),
            ]
        )
        + "\n"
    )
    est = br.BopPosesEstimator(csv, export)
    assert est.name == "bop:r.csv"
    e = est.estimate(obs("car", SEED))
    np.testing.assert_allclose(e.T_C_O[:3, :3], R1, atol=1e-14)
    np.testing.assert_allclose(e.T_C_O[:3, 3], [0.01, -0.02, 0.8], atol=1e-15)
    assert e.info == {"score": 0.9, "time": 0.25, "csv_line": 3, "scene_id": CAR0, "im_id": 0}
    assert [n for n, _ in e.neighbours] == ["chair"]
    np.testing.assert_allclose(e.neighbours[0][1][:3, 3], [-0.1, 0.005, 0.95], atol=1e-15)
    np.testing.assert_allclose(e.neighbours[0][1][:3, :3], R2, atol=1e-14)
    # No row for the phone's first episode: no estimate; its second one has no neighbours.
    none = est.estimate(obs("phone", SEED))
    assert none.T_C_O is None and none.info["note"] == "no row for this target"
    assert est.estimate(obs("phone", SEED + 1)).neighbours == ()
    with pytest.raises(InvalidArgumentError, match="not in the export"):
        est.estimate(obs("car", SEED + 2))


def test_the_estimator_pickles(export: Path, tmp_path: Path) -> None:
    csv = tmp_path / "r.csv"
    csv.write_text(f"{HEADER}\n{row(CAR1, 0, 1, 0.3, np.eye(3), [0, 0, 600], 1.5)}\n")
    est = pickle.loads(pickle.dumps(br.BopPosesEstimator(csv, export, name="mine")))
    e = est.estimate(obs("car", SEED + 1))
    assert est.name == "mine" and e.info["time"] == 1.5
    np.testing.assert_array_equal(e.T_C_O[:3, 3], [0, 0, 0.6])


def test_a_rotation_printed_with_4_decimals_is_accepted_as_the_nearest_rotation(
    export: Path, tmp_path: Path
) -> None:
    R = Rotation.from_euler("zyx", [33, -71, 12], degrees=True).as_matrix()
    r = " ".join(f"{x:.4f}" for x in R.reshape(-1))
    t = "1.0 2.0 500.0"
    csv = tmp_path / "r.csv"
    csv.write_text(f"{HEADER}\n{CAR0},0,1,1,{r},{t},-1\n")
    T = br.BopPosesEstimator(csv, export).estimate(obs("car", SEED)).T_C_O
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(T[:3, :3], R, atol=1e-4)


GOOD_R = " ".join(["1", "0", "0", "0", "1", "0", "0", "0", "1"])
SCALED_R = " ".join(["1.01", "0", "0", "0", "1", "0", "0", "0", "1"])
MIRROR_R = " ".join(["-1", "0", "0", "0", "1", "0", "0", "0", "1"])


C = f"{CAR0},0"  # the car's first image
T = "0 0 500"  # a t [mm] at a plausible distance
GOOD = f"{C},1,1,{GOOD_R},{T},-1"  # a good row


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("scene_id,im_id,obj_id,score,R,t\n", r"line 1: missing column\(s\) time"),
        (f"scene_id,im_id,obj_id,score,R,t,time,extra\n{C},1,1,{GOOD_R},{T},-1,x\n", "unknown"),
        (f"{HEADER}\n{C},1,1,{GOOD_R},{T}\n", r"row 1 \(line 2\): 6 comma-separated fields"),
        (f"{HEADER}\n{C},1,high,{GOOD_R},{T},-1\n", "row 1 .*score 'high' is not 1 number"),
        (f"{HEADER}\n{C},one,1,{GOOD_R},{T},-1\n", "row 1 .*obj_id 'one' is not an integer"),
        (f"{HEADER}\n{GOOD}\n{C},1,1,1 0 0,{T},-1\n", "row 2 .*R has 3 numbers"),
        (f"{HEADER}\n{C},1,1,{GOOD_R},0 0 x,-1\n", "row 1 .*t '0 0 x' is not 3 numbers"),
        (f"{HEADER}\n{C},1,1,{GOOD_R},0 0 nan,-1\n", "row 1 .*t '0 0 nan' is not finite"),
        (f"{HEADER}\n{C},1,1,{SCALED_R},{T},-1\n", r"row 1 .*R is not a rotation \(largest"),
        (f"{HEADER}\n{C},1,1,{MIRROR_R},{T},-1\n", "row 1 .*R is not a rotation.*det -1"),
        (f"{HEADER}\n{C},7,1,{GOOD_R},{T},-1\n", "row 1 .*unknown obj_id 7; valid obj_ids: 1 car"),
        (f"{HEADER}\n{GOOD}\n7,0,1,1,{GOOD_R},{T},-1\n", "row 2 .*scene_id 7, im_id 0 is not in"),
        (f"{HEADER}\n{GOOD}\n{CAR0},5,1,1,{GOOD_R},{T},-1\n", "row 2 .*im_id 5 is not in the"),
        (f"{HEADER}\n{C},1,1,{GOOD_R},{T},-2\n", "row 1 .*time -2 is not seconds"),
        (
            f"{HEADER}\n{C},1,1,{GOOD_R},0 0 575000,-1\n",
            r"row 1 .*t is 575000 mm from the camera \(575 m\), beyond the 10 m any pose may "
            "be; the CSV's t is in millimetres",
        ),
        ("\n\n", "is empty"),
    ],
)
def test_a_bad_csv_is_one_line_naming_its_row(
    export: Path, tmp_path: Path, text: str, problem: str
) -> None:
    csv = tmp_path / "bad.csv"
    csv.write_text(text)
    with pytest.raises(InvalidArgumentError, match=problem) as info:
        br.read_bop_results(csv, export)
    assert "\n" not in str(info.value)
    assert str(csv) in str(info.value)


def test_every_problem_of_a_csv_is_listed_one_line_each_bounded(
    export: Path, tmp_path: Path
) -> None:
    bad = [f"{C},1,high,{GOOD_R},0 0 x,-1"] + [f"{C},{k + 10},1,{GOOD_R},{T},-1" for k in range(24)]
    csv = tmp_path / "bad.csv"
    csv.write_text("\n".join([HEADER, GOOD, *bad]) + "\n")
    with pytest.raises(InvalidArgumentError) as info:
        br.read_bop_results(csv, export)
    lines = str(info.value).splitlines()
    # Row 2 has two problems; 24 rows one each: 26, the first 20 listed, then the rest counted.
    assert lines[0].startswith(f"{csv} has 26 problems") and "t in mm" in lines[0]
    assert len(lines) == 1 + br.MAX_PROBLEMS + 1 and lines[-1] == "  ... and 6 more"
    assert "row 2 (line 3): score 'high'" in lines[1] and "row 2 (line 3): t '0 0 x'" in lines[2]
    assert "row 3 (line 4): unknown obj_id 10" in lines[3]


def test_a_csv_in_metres_is_refused_as_such(export: Path, tmp_path: Path) -> None:
    R = " ".join(["1", "0", "0", "0", "1", "0", "0", "0", "1"])
    rows = [f"{CAR0},0,1,1,{R},0.01 -0.02 0.8,-1", f"{PHONE1},0,4,1,{R},0.1 0.0 0.95,-1"]
    csv = tmp_path / "m.csv"
    csv.write_text("\n".join([HEADER, *rows]) + "\n")
    with pytest.raises(InvalidArgumentError) as info:
        br.read_bop_results(csv, export)
    msg = str(info.value)
    assert "\n" not in msg and "t is in millimetres" in msg
    assert "median 0.878 mm from the camera" in msg and "multiply t by 1000" in msg
    # The same poses in millimetres are taken.
    mm = [f"{CAR0},0,1,1,{R},10 -20 800,-1", f"{PHONE1},0,4,1,{R},100 0 950,-1"]
    csv.write_text("\n".join([HEADER, *mm]) + "\n")
    assert len(br.read_bop_results(csv, export)) == 2


def test_a_csv_of_another_export_is_refused_in_one_line(export: Path, tmp_path: Path) -> None:
    # The same objects and seeds exported from another tier: no image id is shared.
    other = br.scene_ids("isolated", [(o, SEED + i) for o in ("car", "phone") for i in range(2)])
    assert not set(other.values()) & set(IDS.values())
    rows = [f"{sid},0,{1 if o == 'car' else 4},1,{GOOD_R},{T},-1" for (o, _), sid in other.items()]
    csv = tmp_path / "other.csv"
    csv.write_text("\n".join([HEADER, *rows]) + "\n")
    with pytest.raises(InvalidArgumentError, match="answers another export") as info:
        br.read_bop_results(csv, export)
    assert "\n" not in str(info.value) and "tier clutter, objects car,phone" in str(info.value)


def test_scene_ids_are_distinct_and_exports_of_other_tiers_or_seeds_share_none() -> None:
    objects = ["car", "faucet", "chair", "phone", "screen", "pistol"]
    eps = [(o, SEED + i) for o in objects for i in range(5)]
    clutter, isolated = br.scene_ids("clutter", eps), br.scene_ids("isolated", eps)
    later = br.scene_ids("clutter", [(o, SEED + 5 + i) for o in objects for i in range(5)])
    for ids in (clutter, isolated, later):
        assert len(set(ids.values())) == 30 and all(1 <= v <= br.SCENE_ID_MAX for v in ids.values())
    assert not set(clutter.values()) & (set(isolated.values()) | set(later.values()))
    # The same episode has the same id in any export; ids that clash move to free ones.
    assert br.scene_ids("clutter", eps[3:4]) == {eps[3]: clutter[eps[3]]}
    many = br.scene_ids("hard", [("car", s) for s in range(5000)])
    assert len(set(many.values())) == 5000


def test_time_summary_of_the_csv_time_column() -> None:
    assert br.time_summary([-1.0, -1.0]) == {
        "images_timed": 0,
        "time_s_median": None,
        "time_s_p90": None,
    }
    s = br.time_summary([0.1, 0.2, 0.3, 0.4, -1.0, 1.0])
    assert s["images_timed"] == 5 and s["time_s_median"] == pytest.approx(0.3)
    assert s["time_s_p90"] == pytest.approx(np.percentile([0.1, 0.2, 0.3, 0.4, 1.0], 90))


def _episodes(rng: np.random.Generator, m: int, shuffle: bool) -> list[dict]:
    """m episodes of each of two objects, targets scattered on a table 0.6..1.2 m away, each
    estimated 5 mm off (or, shuffled, the estimate of another episode of the object)."""
    eps = []
    for obj in ("car", "phone"):
        truth = [np.eye(4) for _ in range(m)]
        for T in truth:
            T[:3, 3] = rng.uniform([-0.3, -0.2, 0.6], [0.3, 0.2, 1.2])
        est = [T.copy() for T in truth]
        for T in est:
            T[:3, 3] += rng.normal(0, 0.005, 3)
        if shuffle:
            est = est[1:] + est[:1]
        eps += [
            {"object": obj, "T_C_O_true": a.tolist(), "T_C_O_est": b.tolist()}
            for a, b in zip(truth, est, strict=True)
        ]
    eps[0]["T_C_O_est"] = None  # no estimate: not counted
    return eps


def test_truth_match_tells_poses_of_other_scenes_whatever_their_ids() -> None:
    rng = np.random.default_rng(3)
    right = br.truth_match(_episodes(rng, 5, shuffle=False))
    assert (
        right["estimates"] == 9
        and right["nearest_own"] == 9
        and right["chance"] == pytest.approx(9 / 5)
    )
    assert right["tested"] and not right["unrelated"] and right["p_value"] < 1e-5
    wrong = br.truth_match(_episodes(rng, 5, shuffle=True))
    assert wrong["tested"] and wrong["unrelated"] and wrong["nearest_own"] == 0
    assert wrong["p_value"] == 1.0
    # Two episodes per object: even 3 of 3 right is no evidence (chance 1/8).
    few = br.truth_match(_episodes(rng, 2, shuffle=True))
    assert not few["tested"] and not few["unrelated"]


def test_the_tail_is_the_binomial_one() -> None:
    from math import comb

    n, p = 12, 0.2
    for k in (0, 3, 7, 12):
        expected = sum(comb(n, j) * p**j * (1 - p) ** (n - j) for j in range(k, n + 1))
        assert br._tail([p] * n, k) == pytest.approx(expected, rel=1e-12)


def test_nearest_rotation_of_a_rotation_is_itself() -> None:
    R = Rotation.from_euler("xyz", [1, 2, 3]).as_matrix()
    np.testing.assert_allclose(br.nearest_rotation(R), R, atol=1e-14)


def test_read_export_reads_its_sensor_and_the_poses_route_takes_it(tmp_path: Path) -> None:
    from sim import evaluate as ev

    assert br.read_export(write_map(tmp_path / "a")).sensor == "ideal"  # maps from before
    ex = br.read_export(write_map(tmp_path / "b", sensor="kinect-v1+camera"))
    assert ex.sensor == "kinect-v1+camera" and "sensor kinect-v1+camera" in ex.describe()
    with pytest.raises(InvalidArgumentError, match="unknown sensor 'sonar'"):
        br.read_export(write_map(tmp_path / "c", sensor="sonar"))
    poses = SimpleNamespace(export=ex)
    args = ev._parser().parse_args([])
    assert ev._protocol(args, poses).sensor == "kinect-v1+camera"
    args.sensor = "azure-tof"
    with pytest.raises(InvalidArgumentError, match="rendered through sensor kinect-v1\\+camera"):
        ev._protocol(args, poses)
