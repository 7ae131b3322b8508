"""`python -m sim.leaderboard`: the cells, the board's figures, its Markdown and plots, and a
whole small board run, read back and resumed."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from posegrasp.world.constants import EVAL_SEED_BASE
from sim import leaderboard
from sim.board import cell_summaries as board_summary
from sim.board import cells as board_cells
from sim.board.analysis import findings
from sim.board.figures import plots
from sim.evaluation.stats import wilson_interval


def _report(successes: list[bool], workers: int = 2, wall_ms: float = 500.0) -> dict:
    """An evaluate report of len(successes) episodes, each `wall_ms` long."""
    eps = [
        {
            "success": ok,
            "failure_reason": None if ok else "missed",
            "timings_ms": {"estimate": 10.0 + i},
            "wall_ms": wall_ms,
            "confidence": None,
        }
        for i, ok in enumerate(successes)
    ]
    n, k = len(eps), sum(successes)
    return {
        "episodes": eps,
        "workers": workers,
        "overall": {
            "episodes": n,
            "successes": k,
            "success_rate": k / n,
            "pose_correct": k,
            "grasped_wrong_pose": 0,
            **{key: 0.5 for key in board_summary.AR_KEYS},
        },
    }


def test_the_wall_time_is_the_episodes_own_shared_over_the_workers() -> None:
    """A cell read back from its report (or resumed from its journal) counts the time its
    episodes took, not the moment it took to read them."""
    reports = [_report([True] * 4, workers=2), _report([False] * 3, workers=1, wall_ms=1000.0)]
    assert board_summary.run_time_s(reports) == pytest.approx(4 * 0.5 / 2 + 3 * 1.0)


def test_a_cell_summary_holds_its_rate_inside_its_interval() -> None:
    s = board_summary.cell_summary(_report([True] * 4))
    assert s["success_rate"] == 1.0
    assert s["wilson"][0] <= s["success_rate"] <= s["wilson"][1]
    assert s["wilson"] == list(wilson_interval(4, 4))
    assert s["failures"] == []
    assert (s["time_ms_median"], s["wall_s"]) == (11.5, 1.0)


def test_the_plots_draw_a_cell_where_every_grasp_held(tmp_path: Path) -> None:
    """4/4 puts the rate on the interval's upper bound; the bar's error must not go negative."""
    cells = [
        {
            "estimator": name,
            "tier": "isolated",
            "sensor": "ideal",
            "run_key": f"isolated__ideal__{name}",
            "summary": board_summary.cell_summary(_report(oks)),
        }
        for name, oks in (("oracle", [True] * 4), ("crude", [True, False, False, False]))
    ]
    spearman = {key: {"rho": None} for key in board_summary.AR_KEYS}
    board = {
        "cells": cells,
        "sensors": ["ideal"],
        "tiers": ["isolated"],
        "analysis": {"spearman": spearman},
    }
    plots(board, tmp_path)
    assert {p.name for p in tmp_path.iterdir()} == {
        "success.png",
        "ar_vs_success.png",
        "risk_coverage.png",
    }


def test_a_bad_name_is_one_line_naming_the_choices(capsys) -> None:
    assert leaderboard.main(["--tiers", "moon"]) == 2
    err = capsys.readouterr().err
    assert "moon" in err and "isolated" in err and "Traceback" not in err


def _board_argv(out: Path, estimators: str, *extra: str, objects: str = "phone") -> list[str]:
    return [
        "--estimators",
        estimators,
        "--tiers",
        "isolated",
        "--sensors",
        "ideal",
        "--objects",
        objects,
        "--episodes",
        "2",
        "--workers",
        "1",
        "--out",
        str(out),
        *extra,
    ]


def test_a_small_board_runs_reads_back_and_writes_its_files(tmp_path: Path, capsys) -> None:
    argv = _board_argv(
        tmp_path / "out",
        "oracle,crude",
        "--markdown",
        str(tmp_path / "LEADERBOARD.md"),
        "--plots",
        str(tmp_path / "plots"),
        "--json",
        str(tmp_path / "board.json"),
        objects="phone,car",  # read back whatever order the report keeps its objects in
    )
    assert leaderboard.main(argv) == 0
    board = json.loads((tmp_path / "board.json").read_text())
    assert [c["estimator"] for c in board["cells"]] == ["oracle", "crude"]
    oracle = board["cells"][0]["summary"]
    assert (oracle["episodes"], oracle["successes"]) == (4, 4)
    assert board["wall_s"] > 0
    text = (tmp_path / "LEADERBOARD.md").read_text()
    assert "python -m sim.leaderboard --estimators oracle,crude" in text
    assert "| oracle | rgb | 4/4 |" in text
    assert (tmp_path / "plots" / "success.png").exists()
    # A second run reads the cells back: the same board, the same figures.
    assert leaderboard.main(argv) == 0
    again = json.loads((tmp_path / "board.json").read_text())
    assert again["cells"] == board["cells"] and again["wall_s"] == board["wall_s"]
    # A cell run with other settings of its estimator is refused, naming the cell and the key.
    recorded = tmp_path / "out" / "cells" / "isolated__ideal__crude.settings.json"
    settings = json.loads(recorded.read_text())
    assert "settings" in settings and "weights" in settings
    recorded.write_text(json.dumps(settings | {"settings": {"noise_m": 0.5}}))
    capsys.readouterr()
    assert leaderboard.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "isolated__ideal__crude (settings" in err
    recorded.unlink()  # a cell that records none is refused too
    assert leaderboard.main(argv) == 2
    assert "no settings recorded" in capsys.readouterr().err


def test_the_settings_of_an_estimator_tell_its_configs_apart() -> None:
    from perception.peers.estimator import PeerEstimator
    from perception.peers.ppf import PpfConfig, PpfRegistration
    from sim.episodes.registry import settings_of

    one = settings_of(PeerEstimator("ppf", PpfRegistration(PpfConfig())))
    other = settings_of(PeerEstimator("ppf", PpfRegistration(PpfConfig(hypotheses=5))))
    assert one["registration"]["config"]["hypotheses"] == 2
    assert other["registration"]["config"]["hypotheses"] == 5
    assert one["crop"] == other["crop"] and one["name"] == "ppf"
    assert board_cells.differences(one, other) == "registration.config.hypotheses"


def test_the_findings_name_the_tiers_a_peer_wins_and_the_time_shares() -> None:
    def cell(name: str, tier: str, oks: list[bool], ms: float) -> dict:
        summary = board_summary.cell_summary(_report(oks))
        summary["time_ms_median"] = ms
        return {"estimator": name, "sensor": "kinect-v1", "tier": tier, "summary": summary}

    board = {
        "sensors": ["kinect-v1"],
        "tiers": ["isolated", "hard"],
        "cells": [
            cell("hybrid-global", "isolated", [True] * 4, 100.0),
            cell("ppf", "isolated", [True, False, False, False], 400.0),
            cell("hybrid-global", "hard", [True, False, False, False], 100.0),
            cell("ppf", "hard", [True, True, False, False], 1000.0),
        ],
        "analysis": {"spearman": {}, "auc": {}, "ar_for_success": {}},
    }
    text = "\n".join(findings(board))
    assert "on 1 of 2 tiers; a peer grasps more on hard (ppf 2 against 1)" in text
    assert "ppf's 0.10-0.25" in text


def _images_resolve(page: Path) -> list[str]:
    """The page's image links, each checked to name a file from the page's folder."""
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", page.read_text())
    assert links, f"{page} shows no image"
    for link in links:
        assert (page.parent / link).is_file(), f"{page} links {link}, which is not there"
    return links


def test_a_plug_in_and_a_bop_csv_are_rows_beside_the_built_in_ones(tmp_path: Path) -> None:
    """A plug-in's ``package.module:factory`` and the poses of a BOP results CSV of a method run
    elsewhere (here: the truth, written as BOP's CSV) rank beside the oracle on the same
    episodes; the board and its page go under --out, the page's plots resolve from there."""
    from sim.export_bop import export_bop
    from studies.bop_round_trip import write_csv

    export = tmp_path / "export"
    export_bop(export, ["phone"], 2, EVAL_SEED_BASE, "isolated", progress=False)
    csv = tmp_path / "mymethod_posegrasp-test.csv"
    assert write_csv(export, csv, None) == 2
    out = tmp_path / "out"
    plug = "posegrasp_crude:CrudeTableEstimator"
    argv = _board_argv(out, f"oracle,{plug}", "--poses", str(csv), str(export))
    assert leaderboard.main(argv) == 0
    board = json.loads((out / "leaderboard.json").read_text())
    assert [c["estimator"] for c in board["cells"]] == ["oracle", plug, "bop:mymethod"]
    cells = {c["estimator"]: c for c in board["cells"]}
    assert all(c["summary"]["episodes"] == 2 for c in cells.values())
    # The truth's CSV grasps as the oracle does, and every row played the same episodes.
    assert cells["bop:mymethod"]["summary"]["successes"] == cells["oracle"]["summary"]["successes"]
    played = {
        name: [
            (e["object"], e["seed"])
            for e in json.loads((out / "cells" / f"{c['run_key']}.json").read_text())["episodes"]
        ]
        for name, c in cells.items()
    }
    assert played["oracle"] == played[plug] == played["bop:mymethod"]
    page = out / "LEADERBOARD.md"
    assert "| bop:mymethod | rgb | 2/2 |" in page.read_text()
    assert _images_resolve(page) == [
        "leaderboard/success.png",
        "leaderboard/ar_vs_success.png",
        "leaderboard/risk_coverage.png",
    ]
    # A page written elsewhere links the plots from where it is.
    elsewhere = tmp_path / "site" / "docs" / "board.md"
    plots = tmp_path / "images"
    again = [*argv, "--markdown", str(elsewhere), "--plots", str(plots)]
    assert leaderboard.main(again) == 0
    assert _images_resolve(elsewhere)[0] == "../../images/success.png"
    # An export of other episodes than the board's is refused in one line.
    other = _board_argv(tmp_path / "other", "oracle", "--poses", str(csv), str(export))
    other[other.index("--episodes") + 1] = "3"
    assert leaderboard.main(other) == 2


def test_a_missing_extra_is_refused_before_any_cell_runs(tmp_path, monkeypatch, capsys) -> None:
    from perception.peers import extra

    monkeypatch.setattr(extra, "has_open3d", lambda: False)
    out = tmp_path / "out"
    assert leaderboard.main(_board_argv(out, "oracle,fpfh-icp")) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "pip install" in err and "fpfh-icp" in err
    assert not (out / "cells").exists()


def test_a_cell_that_holds_a_stopped_episode_is_refused(tmp_path: Path, capsys) -> None:
    """A cell written by a run that scored an interruption as a failed grasp is not a result:
    the board refuses it and says how to redo it."""
    out = tmp_path / "out"
    argv = _board_argv(out, "oracle")
    assert leaderboard.main(argv) == 0
    cell = out / "cells" / "isolated__ideal__oracle.json"
    report = json.loads(cell.read_text())
    report["episodes"][1].update(
        success=False, failure_reason="error", notes=["Interrupted: SIGTERM"]
    )
    cell.write_text(json.dumps(report))
    capsys.readouterr()
    assert leaderboard.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "stopped, not played" in err and "python -m sim.leaderboard --estimators oracle" in err


def test_the_default_outputs_stay_under_out(tmp_path: Path, monkeypatch) -> None:
    """A newcomer's board never writes the shipped page: only --publish does."""
    monkeypatch.setattr(
        leaderboard,
        "PUBLISHED",
        {k: tmp_path / "docs" / Path(v).name for k, v in leaderboard.PUBLISHED.items()},
    )
    out = tmp_path / "out"
    assert leaderboard.main(_board_argv(out, "oracle")) == 0
    assert not (tmp_path / "docs").exists()
    assert {p.name for p in out.iterdir()} == {
        "cells",
        "leaderboard",
        "leaderboard.json",
        "LEADERBOARD.md",
    }
    assert leaderboard.main([*_board_argv(out, "oracle"), "--publish"]) == 0
    assert {p.name for p in (tmp_path / "docs").iterdir()} == {
        "leaderboard",
        "leaderboard.json",
        "LEADERBOARD.md",
    }
    _images_resolve(tmp_path / "docs" / "LEADERBOARD.md")


def test_every_flag_has_help() -> None:
    for action in leaderboard._parser()._actions:
        assert action.help, f"{action.option_strings} has no help"


def test_the_shift_settings_read_as_the_help_says() -> None:
    from sim.board.tracks import check_shift_settings, check_tasks

    assert check_shift_settings("none, camera:3, all:3, camera:3+light_colour:3") == [
        "none",
        "camera:3",
        "all:3",
        "light_colour:3+camera:3",  # factors in their own order, whatever order given
    ]
    assert check_shift_settings("camera") == ["camera:2"]
    each = check_shift_settings("factors:1")
    assert each[0] == "none" and "walls:1" in each and len(each) == 9
    assert check_tasks("place,lift") == ["place", "lift"]


@pytest.mark.parametrize(
    "flag, value, says",
    [
        ("--tasks", "lift,carry", "valid tasks: lift, place"),
        ("--tasks", "lift,lift", "more than once"),
        ("--shifts", "none,fog:3", "light_colour"),
        ("--shifts", "camera:4", "levels 1 mild"),
        ("--shifts", "none,camera:3,camera:3", "camera:3 twice"),
    ],
)
def test_a_bad_track_is_one_line_naming_the_choices(flag, value, says, capsys) -> None:
    assert leaderboard.main([flag, value]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and says in err and "Traceback" not in err


def test_todays_track_keeps_its_cells_files() -> None:
    cells = board_cells.cells_of(
        ["oracle", "ppf"], ["isolated"], ["kinect-v1"], (), ["lift", "place"], ["none", "all:3"]
    )
    keys = [c.run_key for c in cells]
    assert keys[:2] == ["isolated__ideal__oracle", "isolated__kinect-v1__ppf"]
    assert keys[2:4] == [
        "isolated__ideal__shift-all_3__oracle",
        "isolated__kinect-v1__shift-all_3__ppf",
    ]
    assert keys[4] == "isolated__ideal__place__oracle"
    assert keys[7] == "isolated__kinect-v1__place__shift-all_3__ppf"
    assert {(c.task, c.shifts) for c in cells} == {
        (t, s) for t in ("lift", "place") for s in ("none", "all:3")
    }


def test_a_verdict_needs_both_tests_on_the_place_task() -> None:
    from sim.board.pairs import compare_pair, verdict

    inf = float("inf")
    # A lifts and places all 12, B none: both tests say A.
    a = {("phone", i): (True, 0.001) for i in range(12)}
    b = {("phone", i): (False, inf) for i in range(12)}
    assert verdict("a", "b", compare_pair(a, b, place=False)) == "a > b"
    assert verdict("b", "a", compare_pair(b, a, place=True)) == "a > b"
    # Both place every time, A always closer: successes tie, the rank test does not.
    closer = {k: (True, 0.001) for k in a}
    farther = {k: (True, 0.01 + k[1] * 1e-4) for k in a}
    test = compare_pair(closer, farther, place=True)
    assert verdict("a", "b", test) == "a > b in error only"
    assert verdict("a", "b", compare_pair(closer, closer, place=False)) == "tied at the ceiling"
    half = {k: (k[1] % 2 == 0, 0.001) for k in a}
    assert verdict("a", "b", compare_pair(half, half, place=False)) == "tied"


def _played(out: Path, run_key: str) -> list[tuple[str, int]]:
    report = json.loads((out / "cells" / f"{run_key}.json").read_text())
    return [(e["object"], e["seed"]) for e in report["episodes"]]


def test_a_board_of_tracks_pairs_its_cells_resumes_and_refuses(tmp_path: Path, capsys) -> None:
    """Today's cells are read back by a board with tracks; every cell plays the same episodes;
    the page shows the pairs, the drops with the oracle unchanged, and the place columns; a
    report or a journal of another track is refused in one line."""
    out = tmp_path / "out"
    today = _board_argv(out, "oracle,noisy-oracle,crude")
    assert leaderboard.main(today) == 0
    first = out / "cells" / "isolated__ideal__crude.json"
    stamp = first.stat().st_mtime_ns
    argv = [*today, "--tasks", "lift,place", "--shifts", "none,camera:3"]
    assert leaderboard.main(argv) == 0
    assert first.stat().st_mtime_ns == stamp  # read back, not run again
    board = json.loads((out / "leaderboard.json").read_text())
    assert (board["tasks"], board["shifts"]) == (["lift", "place"], ["none", "camera:3"])
    keys = [c["run_key"] for c in board["cells"]]
    assert len(keys) == 12 and "isolated__ideal__place__shift-camera_3__crude" in keys
    assert len({tuple(_played(out, k)) for k in keys}) == 1  # the same seeds everywhere
    a = board["analysis"]
    assert len(a["pairs"]) == 4 and a["oracle_shifts"] == {"rows": 2, "changed": []}
    assert {p["rank"] is None for p in a["pairs"] if p["task"] == "lift"} == {True}
    assert {"lift", "place"} <= set(a["success_by_error"])
    text = (out / "LEADERBOARD.md").read_text()
    for shown in (
        "## isolated, sensor `ideal`, place, shift camera:3",
        "| lifted | rests from goal (med mm, deg) |",
        "## Pairs of estimators",
        "| isolated | ideal | noisy-oracle | crude |",
        "rank p (R-, R+)",
        "## Scene shifts: the drop per factor",
        "| estimator | none | camera:3 |",
        "| oracle (instrument) | 2/2 | 2/2, drop 0 pp, p 1 |",
        "The oracle's row shows no change",
        "wall time ",
    ):
        assert shown in text, shown
    assert "leaderboard/success_vs_error.png" in _images_resolve(out / "LEADERBOARD.md")
    # A cell stopped half way resumes alone; the board is the same.
    (out / "cells" / "isolated__ideal__place__crude.json").unlink()
    assert leaderboard.main(argv) == 0
    again = json.loads((out / "leaderboard.json").read_text())
    assert [c["summary"]["successes"] for c in again["cells"]] == [
        c["summary"]["successes"] for c in board["cells"]
    ]
    # A report of another track in a cell's place is refused, naming both tracks.
    lift = out / "cells" / "isolated__ideal__shift-camera_3__crude.json"
    place = out / "cells" / "isolated__ideal__place__shift-camera_3__crude.json"
    lift.write_text(place.read_text())
    capsys.readouterr()
    assert leaderboard.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "task place with shifts camera:3, not lift with camera:3" in err
    # So is the journal of another track.
    lift.unlink()
    header = {"journal": "evaluate", "version": 1, "protocol": {"task": "place"}}
    lift.with_suffix(".journal.jsonl").write_text(json.dumps(header) + "\n")
    assert leaderboard.main(argv) == 2
    assert "task place with shifts none, not lift" in capsys.readouterr().err
    lift.with_suffix(".journal.jsonl").unlink()
    # A place report from before the predicted belief (none recorded: the grasp-time estimate)
    # is refused, not read as today's place.
    old = json.loads(place.read_text())
    assert old["belief"] == "predicted"
    del old["belief"]
    place.write_text(json.dumps(old))
    assert leaderboard.main(argv) == 2
    assert "placed on the belief estimate, not predicted" in capsys.readouterr().err


def test_the_tracks_cells_run_on_the_boards_backend(tmp_path: Path, monkeypatch) -> None:
    """A track's cell goes through the one way into an evaluation with the board's backend,
    workers and address, its protocol holding the task and the shifts."""
    import sim.evaluation

    seen = []
    real = sim.evaluation.evaluate_protocol

    def spy(protocol, estimator, **run):
        seen.append((protocol.task, [str(s) for s in protocol.shifts], run["backend"]))
        return real(protocol, estimator, **{**run, "backend": "local"})

    monkeypatch.setattr(sim.evaluation, "evaluate_protocol", spy)
    argv = [*_board_argv(tmp_path, "oracle"), "--tasks", "place", "--shifts", "camera:1"]
    argv[argv.index("--episodes") + 1] = "1"
    assert leaderboard.main([*argv, "--backend", "ray"]) == 0
    assert seen == [("place", ["camera:1"], "ray")]


@pytest.mark.slow
def test_a_tracks_cell_on_ray_is_the_local_one(tmp_path: Path) -> None:
    """A place cell under a shift played by a Ray started here holds the episodes the local
    pool plays."""
    extra = ["--tasks", "place", "--shifts", "camera:3"]
    local, ray = tmp_path / "local", tmp_path / "ray"
    assert leaderboard.main([*_board_argv(local, "crude"), *extra]) == 0
    argv = [*_board_argv(ray, "crude"), *extra, "--backend", "ray"]
    argv[argv.index("--workers") + 1] = "2"
    assert leaderboard.main(argv) == 0
    key = "isolated__ideal__place__shift-camera_3__crude"

    def kept(out: Path) -> list:
        eps = json.loads((out / "cells" / f"{key}.json").read_text())["episodes"]
        return [(e["seed"], e["success"], e.get("place"), e["T_C_O_est"]) for e in eps]

    assert kept(ray) == kept(local)


def test_a_board_of_user_objects_records_each_ones_revision(monkeypatch, tmp_path) -> None:
    from posegrasp.world.user_objects import DESCRIPTION_FILE, OBJECTS_ENV

    monkeypatch.setenv(OBJECTS_ENV, str(tmp_path))
    (tmp_path / "can").mkdir()
    description = tmp_path / "can" / DESCRIPTION_FILE
    description.write_text('{"name": "can"}')
    cells = board_cells.cells_of(["crude"], ["isolated"], ["ideal"], [], ["lift"], ["none"])
    built_in = board_cells.today_settings(cells, ["phone"])
    assert "user_objects" not in built_in[cells[0]]
    first = board_cells.today_settings(cells, ["phone", "can"])[cells[0]]
    assert set(first["user_objects"]) == {"can"}
    description.write_text('{"name": "can", "made": "again"}')  # the object made anew
    again = board_cells.today_settings(cells, ["phone", "can"])[cells[0]]
    assert board_cells.differences(first, again) == "user_objects.can"
    # Distractors drawn from user objects: the pool is recorded, and each one's revision.
    pooled = board_cells.today_settings(cells, ["phone"], ["can"])[cells[0]]
    assert pooled["pool"] == ["can"] and set(pooled["user_objects"]) == {"can"}
