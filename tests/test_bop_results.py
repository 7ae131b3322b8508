"""BOP results CSVs against an export's map file, and the estimator that answers with them."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from posegrasp.core.contract import Observation
from posegrasp.core.errors import InvalidArgumentError
from sim import bop_results as br

SEED = 1_000_000_000
HEADER = "scene_id,im_id,obj_id,score,R,t,time"


def write_map(root: Path, complete: bool = True, **changes) -> Path:
    """A map file of an export of car (scene 1) and phone (scene 4), 2 episodes each."""
    root.mkdir(parents=True, exist_ok=True)
    images = [
        {"scene_id": sid, "im_id": i, "object": o, "seed": SEED + i}
        for o, sid in (("car", 1), ("phone", 4))
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
    assert ex.images[("phone", SEED + 1)] == (4, 1)
    assert ex.image_ids == {(1, 0), (1, 1), (4, 0), (4, 1)}


def test_read_export_refuses_a_missing_incomplete_or_inconsistent_map(tmp_path: Path) -> None:
    with pytest.raises(InvalidArgumentError, match=r"no posegrasp_episodes\.json"):
        br.read_export(tmp_path)
    with pytest.raises(InvalidArgumentError, match="interrupted"):
        br.read_export(write_map(tmp_path / "a", complete=False))
    with pytest.raises(InvalidArgumentError, match="every object x episode"):
        br.read_export(write_map(tmp_path / "b", episodes=3))
    with pytest.raises(InvalidArgumentError, match="unknown tier"):
        br.read_export(write_map(tmp_path / "c", tier="nope"))


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
                row(1, 0, 1, 0.5, np.eye(3), [0, 0, 900], 0.25),
                row(1, 0, 1, 0.9, R1, [10, -20, 800], 0.25),  # the best car row
                row(1, 0, 1, 0.7, np.eye(3), [0, 0, 700], 0.25),
                row(1, 0, 3, 0.4, R2, [-100, 5, 950], 0.25),  # a chair beside it
                "",
                row(4, 1, 4, 1.0, R2, [1, 2, 3]),
            ]
        )
        + "\n"
    )
    est = br.BopPosesEstimator(csv, export)
    assert est.name == "bop:r.csv"
    e = est.estimate(obs("car", SEED))
    np.testing.assert_allclose(e.T_C_O[:3, :3], R1, atol=1e-14)
    np.testing.assert_allclose(e.T_C_O[:3, 3], [0.01, -0.02, 0.8], atol=1e-15)
    assert e.info == {"score": 0.9, "time": 0.25, "csv_line": 3, "scene_id": 1, "im_id": 0}
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
    csv.write_text(f"{HEADER}\n{row(1, 1, 1, 0.3, np.eye(3), [0, 0, 600], 1.5)}\n")
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
    csv.write_text(f"{HEADER}\n1,0,1,1,{r},{t},-1\n")
    T = br.BopPosesEstimator(csv, export).estimate(obs("car", SEED)).T_C_O
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(T[:3, :3], R, atol=1e-4)


GOOD_R = " ".join(["1", "0", "0", "0", "1", "0", "0", "0", "1"])
SCALED_R = " ".join(["1.01", "0", "0", "0", "1", "0", "0", "0", "1"])
MIRROR_R = " ".join(["-1", "0", "0", "0", "1", "0", "0", "0", "1"])


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("scene_id,im_id,obj_id,score,R,t\n", r"line 1: missing column\(s\) time"),
        (f"scene_id,im_id,obj_id,score,R,t,time,extra\n1,0,1,1,{GOOD_R},0 0 1,-1,x\n", "unknown"),
        (f"{HEADER}\n1,0,1,1,{GOOD_R},0 0 1\n", r"row 1 \(line 2\): 6 comma-separated fields"),
        (f"{HEADER}\n1,0,1,high,{GOOD_R},0 0 1,-1\n", "row 1 .*score 'high' is not 1 number"),
        (f"{HEADER}\n1,0,one,1,{GOOD_R},0 0 1,-1\n", "row 1 .*obj_id 'one' is not an integer"),
        (
            f"{HEADER}\n1,0,1,1,{GOOD_R},0 0 1,-1\n1,0,1,1,1 0 0,0 0 1,-1\n",
            "row 2 .*R has 3 numbers",
        ),
        (f"{HEADER}\n1,0,1,1,{GOOD_R},0 0 x,-1\n", "row 1 .*t '0 0 x' is not 3 numbers"),
        (f"{HEADER}\n1,0,1,1,{GOOD_R},0 0 nan,-1\n", "row 1 .*t '0 0 nan' is not finite"),
        (f"{HEADER}\n1,0,1,1,{SCALED_R},0 0 1,-1\n", r"row 1 .*R is not a rotation \(largest"),
        (f"{HEADER}\n1,0,1,1,{MIRROR_R},0 0 1,-1\n", "row 1 .*R is not a rotation.*det -1"),
        (
            f"{HEADER}\n1,0,7,1,{GOOD_R},0 0 1,-1\n",
            "row 1 .*unknown obj_id 7; valid obj_ids: 1 car",
        ),
        (
            f"{HEADER}\n2,0,1,1,{GOOD_R},0 0 1,-1\n",
            "row 1 .*scene_id 2, im_id 0 is not in the export",
        ),
        (f"{HEADER}\n1,5,1,1,{GOOD_R},0 0 1,-1\n", "row 1 .*im_id 5 is not in the export"),
        (f"{HEADER}\n1,0,1,1,{GOOD_R},0 0 1,-2\n", "row 1 .*time -2 is not seconds"),
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


def test_nearest_rotation_of_a_rotation_is_itself() -> None:
    R = Rotation.from_euler("xyz", [1, 2, 3]).as_matrix()
    np.testing.assert_allclose(br.nearest_rotation(R), R, atol=1e-14)
