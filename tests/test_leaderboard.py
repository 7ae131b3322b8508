"""`python -m sim.leaderboard`: the cells, the board's figures, its Markdown and plots, and a
whole small board run, read back and resumed."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from posegrasp.world.constants import EVAL_SEED_BASE
from sim import leaderboard
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
            **{key: 0.5 for key in board_cells.AR_KEYS},
        },
    }


def test_the_wall_time_is_the_episodes_own_shared_over_the_workers() -> None:
    """A cell read back from its report (or resumed from its journal) counts the time its
    episodes took, not the moment it took to read them."""
    reports = [_report([True] * 4, workers=2), _report([False] * 3, workers=1, wall_ms=1000.0)]
    assert board_cells.run_time_s(reports) == pytest.approx(4 * 0.5 / 2 + 3 * 1.0)


def test_a_cell_summary_holds_its_rate_inside_its_interval() -> None:
    s = board_cells.cell_summary(_report([True] * 4))
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
            "summary": board_cells.cell_summary(_report(oks)),
        }
        for name, oks in (("oracle", [True] * 4), ("crude", [True, False, False, False]))
    ]
    spearman = {key: {"rho": None} for key in board_cells.AR_KEYS}
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
        summary = board_cells.cell_summary(_report(oks))
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
