"""The tolerance study's arithmetic, its report of a bound, and its held-out scenes."""

from __future__ import annotations

import json

import pytest

from posegrasp.core.validate import check_tolerance_curves
from posegrasp.world import constants as C
from sim import tolerance as tol


def test_tolerance_interpolates_to_the_first_crossing() -> None:
    levels = [0.0, 10.0, 20.0, 30.0]
    # 1.0 at 10 and 0.8 at 20: 0.9 is crossed halfway, at 15.
    assert tol.tolerance_of(levels, [1.0, 1.0, 0.8, 1.0]) == pytest.approx(15.0)
    assert tol.tolerance_of(levels, [0.5, 1.0, 1.0, 1.0]) == 0.0
    assert tol.tolerance_of(levels, [1.0, 0.9, 0.9, 0.9]) is None  # at the threshold: held


def test_a_curve_that_never_falls_is_a_bound_not_a_tolerance() -> None:
    held = tol.curve_record([0, 5, 10, 20, 30, 45], [1.0, 1.0, 1.0, 1.0, 0.9, 1.0])
    assert held["tolerance"] is None and held["at_least"] == 45.0
    fell = tol.curve_record([0, 5, 10, 20, 30, 45], [1.0, 1.0, 1.0, 0.7, 0.4, 0.0])
    assert fell["tolerance"] == pytest.approx(10 + 0.1 / 0.3 * 10) and "at_least" not in fell
    result = {
        "phone": {k: fell for k in tol.LEVELS} | {"inplane_deg": held},
        "car": {k: fell for k in tol.LEVELS},
    }
    check_tolerance_curves(result)  # sim.evaluate --tolerance still reads the curves
    text = tol.format_tolerances(result)
    phone = next(line for line in text.splitlines() if line.startswith("phone"))
    assert ">= 45.0" in phone and phone.count("13.3") == 3
    assert "success never fell below 90% up to the largest level tested" in text
    assert "never fell" not in tol.format_tolerances({"car": result["car"]})


def test_default_scenes_are_held_out_from_training() -> None:
    args = tol.parser().parse_args([])
    assert args.seed_start == C.EVAL_SEED_BASE >= C.DATA_SEED_LIMIT
    assert tol.parser().parse_args(["--seed-start", "7"]).seed_start == 7


def test_the_place_task_study_scores_the_place(tmp_path, monkeypatch, capsys) -> None:
    """``--task place``: success is the place's; the journal's protocol names the task (a lift
    study's does not), the JSON is curves as sim.evaluate --tolerance reads them."""
    monkeypatch.setattr(tol, "LEVELS", {k: (0, 60) for k in tol.LEVELS})
    out = tmp_path / "place.json"
    argv = ["--object", "phone", "--episodes", "1", "--workers", "1", "--task", "place"]
    assert tol.main([*argv, "--json", str(out), "--plot", str(tmp_path / "p.png")]) == 0
    curves = check_tolerance_curves(json.loads(out.read_text()))
    assert set(curves) == {"phone"} and curves["phone"]["lateral_mm"]["success_rate"][0] == 1.0
    # 60 mm beside the truth, the phone is lifted, if at all, and set down off its goal.
    assert curves["phone"]["lateral_mm"]["success_rate"][1] == 0.0
    assert "where place success drops below 90%" in capsys.readouterr().out
    assert tol.study_protocol(["phone"], 1, 0, "isolated", "place")["task"] == "place"
    assert "task" not in tol.study_protocol(["phone"], 1, 0, "isolated")
    assert tol.main(["--task", "carry"]) == 2
    err = capsys.readouterr().err.strip()
    assert "valid tasks: lift, place" in err and "\n" not in err
