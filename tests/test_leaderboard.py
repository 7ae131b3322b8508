"""`python -m sim.leaderboard`: the cells, the board's figures, its Markdown and plots, and a
whole small board run, read back and resumed."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sim import leaderboard
from sim.stats import wilson_interval


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
            **{key: 0.5 for key in leaderboard.AR_KEYS},
        },
    }


def test_the_wall_time_is_the_episodes_own_shared_over_the_workers() -> None:
    """A cell read back from its report (or resumed from its journal) counts the time its
    episodes took, not the moment it took to read them."""
    reports = [_report([True] * 4, workers=2), _report([False] * 3, workers=1, wall_ms=1000.0)]
    assert leaderboard.run_time_s(reports) == pytest.approx(4 * 0.5 / 2 + 3 * 1.0)


def test_a_cell_summary_holds_its_rate_inside_its_interval() -> None:
    s = leaderboard.cell_summary(_report([True] * 4))
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
            "summary": leaderboard.cell_summary(_report(oks)),
        }
        for name, oks in (("oracle", [True] * 4), ("crude", [True, False, False, False]))
    ]
    spearman = {key: {"rho": None} for key in leaderboard.AR_KEYS}
    board = {
        "cells": cells,
        "sensors": ["ideal"],
        "tiers": ["isolated"],
        "analysis": {"spearman": spearman},
    }
    leaderboard.plots(board, tmp_path)
    assert {p.name for p in tmp_path.iterdir()} == {
        "success.png",
        "ar_vs_success.png",
        "risk_coverage.png",
    }


def test_a_bad_name_is_one_line_naming_the_choices(capsys) -> None:
    assert leaderboard.main(["--tiers", "moon"]) == 2
    err = capsys.readouterr().err
    assert "moon" in err and "isolated" in err and "Traceback" not in err


def test_a_small_board_runs_reads_back_and_writes_its_files(tmp_path: Path, capsys) -> None:
    argv = [
        "--estimators",
        "oracle,crude",
        "--tiers",
        "isolated",
        "--sensors",
        "ideal",
        "--objects",
        "phone",
        "--episodes",
        "2",
        "--workers",
        "1",
        "--out",
        str(tmp_path / "out"),
        "--markdown",
        str(tmp_path / "LEADERBOARD.md"),
        "--plots",
        str(tmp_path / "plots"),
        "--json",
        str(tmp_path / "board.json"),
    ]
    assert leaderboard.main(argv) == 0
    board = json.loads((tmp_path / "board.json").read_text())
    assert [c["estimator"] for c in board["cells"]] == ["oracle", "crude"]
    oracle = board["cells"][0]["summary"]
    assert (oracle["episodes"], oracle["successes"]) == (2, 2)
    assert board["wall_s"] > 0
    text = (tmp_path / "LEADERBOARD.md").read_text()
    assert "python -m sim.leaderboard --estimators oracle,crude" in text
    assert "| oracle | rgb | 2/2 |" in text
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
    from sim.estimators import settings_of

    one = settings_of(PeerEstimator("ppf", PpfRegistration(PpfConfig())))
    other = settings_of(PeerEstimator("ppf", PpfRegistration(PpfConfig(hypotheses=5))))
    assert one["registration"]["config"]["hypotheses"] == 2
    assert other["registration"]["config"]["hypotheses"] == 5
    assert one["crop"] == other["crop"] and one["name"] == "ppf"
    assert leaderboard._differences(one, other) == "registration.config.hypotheses"


def test_the_findings_name_the_tiers_a_peer_wins_and_the_time_shares() -> None:
    def cell(name: str, tier: str, oks: list[bool], ms: float) -> dict:
        summary = leaderboard.cell_summary(_report(oks))
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
    text = "\n".join(leaderboard.findings(board))
    assert "on 1 of 2 tiers; a peer grasps more on hard (ppf 2 against 1)" in text
    assert "ppf's 0.10-0.25" in text
