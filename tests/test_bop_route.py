"""The BOP route end to end: `sim.export_bop`, a results CSV, and `sim.evaluate --poses CSV
--from DIR` grasping on its poses in exactly the exported episodes, paired with the oracle."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from posegrasp.world.shifts import parse_shifts
from sim import compare as cmp
from sim import evaluate as ev
from sim import evaluation
from sim.evaluation.bop_results import read_export
from sim.export_bop import export_bop

SEED = 1_000_000_000
OBJECTS = ["phone", "car"]


def _bench():
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "bop_round_trip", Path(__file__).resolve().parent.parent / "studies" / "bop_round_trip.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def export(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("bop") / "export"
    export_bop(root, OBJECTS, 2, SEED, "isolated", progress=False)
    return root


def test_a_csv_of_the_truth_grasps_like_the_oracle(export: Path, tmp_path: Path, capsys) -> None:
    bench = _bench()
    csv = tmp_path / "truth.csv"
    assert bench.write_csv(export, csv, None) == 4
    out, oracle = tmp_path / "bop.json", tmp_path / "oracle.json"
    assert ev.main(["--poses", str(csv), "--from", str(export), "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "AR_VSD" in printed and "no time given" in printed and "warning" not in printed
    assert (
        ev.main(
            [
                "--estimator",
                "oracle",
                "--objects",
                ",".join(OBJECTS),
                "--episodes",
                "2",
                "--json",
                str(oracle),
            ]
        )
        == 0
    )
    r = json.loads(out.read_text())
    assert r["estimator"].startswith("bop:truth.csv@") and r["seed_start"] == SEED
    assert r["overall"]["ar_mssd"] == r["overall"]["ar_mspd"] == r["overall"]["ar_vsd"] == 1.0
    assert all(e["vsd"] == [0.0] * 10 for e in r["episodes"])
    assert r["poses"]["targets_with_a_row"] == 4 and r["poses"]["images_timed"] == 0
    # The live run has AR_VSD too, from the same per-episode errors.
    live = json.loads(oracle.read_text())
    assert live["overall"]["ar_vsd"] == 1.0 and live["per_object"]["car"]["ar_vsd"] == 1.0
    res = cmp.compare(cmp.load_report(oracle), cmp.load_report(out))
    assert res["paired_episodes"] == 4 and res["overall"]["difference"] == 0.0


def test_a_target_without_a_row_is_no_estimate(export: Path, tmp_path: Path) -> None:
    csv = tmp_path / "one.csv"
    _bench().write_csv(export, csv, None)
    car0 = read_export(export).images[("car", SEED)][0]
    lines = csv.read_text().splitlines()
    kept = [ln for ln in lines[1:] if not ln.startswith(f"{car0},0,")]
    # A time per image, in seconds, for every row left.
    kept = [ln.rsplit(",", 1)[0] + f",{0.1 * (k + 1):.1f}" for k, ln in enumerate(kept)]
    csv.write_text("\n".join([lines[0], *kept]))
    out = tmp_path / "r.json"
    assert ev.main(["--poses", str(csv), "--from", str(export), "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    car0 = next(e for e in r["episodes"] if (e["object"], e["seed"]) == ("car", SEED))
    assert car0["failure_reason"] == "no_estimate" and car0["vsd"] is None
    assert r["poses"]["targets_with_a_row"] == 3 and r["overall"]["ar_mssd"] <= 0.75
    assert r["overall"]["ar_vsd"] == 0.75
    assert r["poses"]["images_timed"] == 3 and r["poses"]["time_s_median"] == 0.2
    assert r["poses"]["time_s_p90"] == pytest.approx(0.28)


@pytest.mark.parametrize(
    "extra, needle",
    [
        (["--tier", "hard"], "leave out --tier"),
        (["--estimator", "oracle"], "leave out --estimator"),
        (["--episodes", "3"], "leave out --episodes"),
    ],
)
def test_the_poses_route_takes_its_episodes_from_the_export(
    export: Path, tmp_path: Path, capsys, extra: list[str], needle: str
) -> None:
    csv = tmp_path / "t.csv"
    _bench().write_csv(export, csv, None)
    assert ev.main(["--poses", str(csv), "--from", str(export), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err
    assert ev.main(["--poses", str(csv)]) == 2
    assert "needs --from" in capsys.readouterr().err
    assert ev.main(["--from", str(export)]) == 2
    assert ev.main(["--poses", str(tmp_path / "none.csv"), "--from", str(export)]) == 2


def test_a_csv_of_another_export_is_refused(export: Path, tmp_path: Path, capsys) -> None:
    other = tmp_path / "clutter"
    export_bop(other, OBJECTS, 2, SEED, "clutter", progress=False)
    csv = tmp_path / "clutter.csv"
    _bench().write_csv(other, csv, None)
    assert ev.main(["--poses", str(csv), "--from", str(export)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "answers another export" in err
    assert "tier isolated" in err


def _report(episodes: list[dict]) -> dict:
    return evaluation.make_report(
        episodes, evaluation.Protocol(["car"], len(episodes), SEED, "isolated"), "mine"
    )


def _failed(reason: str, notes: list[str]) -> dict:
    return {
        "object": "car",
        "seed": SEED,
        "estimator": "mine",
        "tier": "isolated",
        "success": False,
        "failure_reason": reason,
        "notes": notes,
        "pose_error": None,
        "timings_ms": {},
        "wall_ms": 1.0,
    }


def test_the_summary_says_why_episodes_failed() -> None:
    far = "estimated pose T_C_O: position is {} m from the camera, beyond 10 m: poses are in metres"
    episodes = [
        _failed("invalid_action", [far.format(575.2)]),
        _failed("invalid_action", [far.format(12.5)]),
        _failed("no_estimate", ["user object 'can' is not one this estimator knows\nsecond line"]),
        *(_failed("no_estimate", [f"note {k}"]) for k in "abcd"),
        _failed("no_estimate", []),
    ]
    notes = evaluation.failure_notes(episodes)
    # Notes alike but for their numbers count as one, shown by the first; at most 3 per reason.
    assert notes["invalid_action"] == [(far.format(575.2), 2)]
    assert len(notes["no_estimate"]) == evaluation.NOTES_SHOWN
    assert notes["no_estimate"][0][0].startswith("user object 'can'")
    text = evaluation.format_report(_report(episodes))
    assert "AR_VSD" in text.splitlines()[1]
    assert "  invalid_action: 2x estimated pose T_C_O: position is 575.2 m" in text
    line = next(ln for ln in text.splitlines() if "user object 'can'" in ln)
    assert line.startswith("  no_estimate: 1x") and line.endswith("second line")
    long = _failed("collision", ["x" * 500])
    long_line = next(
        ln for ln in evaluation.format_report(_report([long])).splitlines() if "xxx" in ln
    )
    assert len(long_line) <= len("  collision: 1x ") + evaluation.NOTE_CHARS and long_line.endswith(
        "..."
    )


def test_ar_vsd_counts_an_episode_without_vsd_as_a_miss_and_old_reports_have_none() -> None:
    ok = {**_failed("missed", []), "vsd": [0.0] * 10}
    assert evaluation.bop_scores([ok, _failed("no_estimate", [])])["ar_vsd"] == 0.5
    assert evaluation.bop_scores([_failed("no_estimate", [])])["ar_vsd"] is None


def _oracle(tmp_path: Path, name: str, *extra: str) -> dict:
    out = tmp_path / f"{name}.json"
    argv = ["--estimator", "oracle", "--objects", ",".join(OBJECTS), "--episodes", "2"]
    assert ev.main([*argv, *extra, "--json", str(out)]) == 0
    return json.loads(out.read_text())


def _outcomes(report: dict) -> dict:
    return {
        (e["object"], e["seed"]): (e["success"], e["failure_reason"]) for e in report["episodes"]
    }


def test_the_poses_route_places(export: Path, tmp_path: Path) -> None:
    """``--task place`` on the BOP route: a CSV of the truth places as the oracle does."""
    csv = tmp_path / "truth.csv"
    _bench().write_csv(export, csv, None)
    out = tmp_path / "place.json"
    argv = ["--poses", str(csv), "--from", str(export), "--task", "place", "--json", str(out)]
    assert ev.main(argv) == 0
    r = json.loads(out.read_text())
    assert r["task"] == "place" and all(e["place"] is not None for e in r["episodes"])
    assert _outcomes(r) == _outcomes(_oracle(tmp_path, "oracle_place", "--task", "place"))
    assert r["overall"]["successes"] == 4


def test_the_poses_route_grasps_in_the_exports_shifted_scenes(tmp_path: Path, capsys) -> None:
    """An export rendered under shifts records them; the route grasps in the same shifted
    scenes (the oracle's outcomes under ``--shift``), and refuses another ``--shift``."""
    spec = "camera:3,table_texture:3"
    root = tmp_path / "shifted"
    export_bop(root, OBJECTS, 2, SEED, "isolated", progress=False, shifts=parse_shifts(spec))
    csv = tmp_path / "truth.csv"
    _bench().write_csv(root, csv, None)
    out = tmp_path / "bop.json"
    assert ev.main(["--poses", str(csv), "--from", str(root), "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert r["shifts"] == ["table_texture:3", "camera:3"]
    assert r["overall"]["ar_mssd"] == 1.0 and r["poses"]["truth_match"]["nearest_own"] == 4
    oracle = _oracle(tmp_path, "oracle_shifted", "--shift", spec)
    assert _outcomes(r) == _outcomes(oracle) and oracle["shifts"] == r["shifts"]
    for e, o in zip(r["episodes"], oracle["episodes"], strict=True):
        assert e["T_C_O_true"] == o["T_C_O_true"]  # the same moved camera
    same = ["--poses", str(csv), "--from", str(root), "--shift", "table_texture:3,camera:3"]
    assert ev.main([*same, "--json", str(tmp_path / "same.json")]) == 0
    capsys.readouterr()
    assert ev.main(["--poses", str(csv), "--from", str(root), "--shift", "camera:1"]) == 2
    err = capsys.readouterr().err.strip()
    assert "rendered under table_texture:3,camera:3, not camera:1; leave out --shift" in err
    assert "\n" not in err
