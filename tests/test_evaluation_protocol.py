"""The evaluation's `Protocol`: handed whole to the episodes, the journal and the report, checked
when made; it is the one way into an evaluation (`evaluate_protocol`), and the command line's
module exports nothing that code needs."""

from __future__ import annotations

import pytest

import sim.evaluation
from posegrasp.core.errors import UnknownNameError
from sim.episodes.episode import execution_settings
from sim.evaluation import Protocol, evaluate_protocol, make_report, run_protocol

SEED = 1_000_000_000


def _episode(obj: str, seed: int, ok: bool) -> dict:
    return {
        "object": obj,
        "seed": seed,
        "estimator": "x",
        "tier": "far",
        "success": ok,
        "failure_reason": None if ok else "slipped",
        "pose_error": None,
        "notes": [],
        "timings_ms": {},
        "wall_ms": 1.0,
    }


def test_a_journal_header_at_the_defaults_is_the_one_journals_already_hold() -> None:
    # A run journaled before the protocol was a dataclass resumes: the header is unchanged.
    header = run_protocol(Protocol(["phone", "car"], 3, SEED), "oracle")
    assert header == {
        "objects": ["phone", "car"],
        "episodes_per_object": 3,
        "estimator": "oracle",
        "seed_start": SEED,
        "tier": "isolated",
        "noise": None,
        "margin": False,
        "obs_mode": "rgb",
        "execution": execution_settings(),
    }


def test_entries_away_from_their_defaults_are_recorded_in_header_and_report() -> None:
    p = Protocol(
        ("car",), 2, SEED, "far", pool=["phone"], candidates="generated", sensor="azure-tof"
    )
    extra = {"distractor_pool": ["phone"], "candidates": "generated", "sensor": "azure-tof"}
    assert {k: run_protocol(p, "x")[k] for k in extra} == extra
    report = make_report([_episode("car", SEED, True), _episode("car", SEED + 1, False)], p, "x")
    assert {k: report[k] for k in extra} == extra
    assert (report["tier"], report["seed_start"], report["episodes_per_object"]) == ("far", SEED, 2)
    assert report["overall"]["successes"] == 1


def test_the_report_has_a_group_for_every_object_of_the_protocol_in_its_order() -> None:
    p = Protocol(["pistol", "car"], 1, SEED, "far")
    report = make_report([_episode("car", SEED, True)], p, "x")
    assert list(report["per_object"]) == ["pistol", "car"]
    assert report["per_object"]["pistol"]["episodes"] == 0
    assert "sensor" not in report and "candidates" not in report


def test_every_episode_plays_with_the_protocols_settings() -> None:
    p = Protocol(["car"], 1, tier="clutter", margin=True, obs_mode="rgbd", pool=("phone", "chair"))
    cfg = p.episode_config()
    assert (cfg.tier, cfg.obs_mode, cfg.sensor) == ("clutter", "rgbd", "ideal")
    assert cfg.scene.distractor_pool == ("phone", "chair") and cfg.execution.measure_margin
    assert cfg.planner.candidates == "designed"
    p = Protocol(["phone", "car"], 2, 7)
    assert list(p.seeds()) == [("phone", 7), ("phone", 8), ("car", 7), ("car", 8)]
    assert p.total == 4


@pytest.mark.parametrize(
    "field, value, valid",
    [
        ("tier", "easy", "isolated, clutter"),
        ("obs_mode", "depth", "rgb, rgbd"),
        ("candidates", "found", "designed, generated"),
        ("sensor", "lidar", "ideal, kinect-v1"),
    ],
)
def test_a_field_that_does_not_exist_is_one_line_naming_the_valid_ones(
    field: str, value: str, valid: str
) -> None:
    with pytest.raises(UnknownNameError) as exc:
        Protocol(["phone"], 1, **{field: value})
    assert valid in str(exc.value) and len(str(exc.value).splitlines()) == 1


def test_a_protocol_run_records_its_fields() -> None:
    whole = evaluate_protocol(Protocol(["phone"], 1, SEED, "clutter", "5,5,2,2"), "noisy-oracle")
    assert (whole["tier"], whole["noise"], whole["episodes"][0]["seed"]) == (
        "clutter",
        "5,5,2,2",
        SEED,
    )


def test_code_evaluates_through_the_library_never_the_command_line() -> None:
    """Every caller (the gate, the fits, the leaderboard, the examples, the studies, the benches,
    the tests) builds a `Protocol` and calls `sim.evaluation`; from `sim.evaluate`, the command
    line, only its ``main`` (and the tests its parsing) is imported."""
    import re
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    pattern = re.compile(r"from sim\.evaluate import \(?([^)\n]*)")
    found = {}
    for path in repo.glob("*/**/*.py"):
        if ".venv" in path.parts or path.parts[len(repo.parts)].startswith("."):
            continue
        for names in pattern.findall(path.read_text(encoding="utf-8")):
            taken = {n.split(" as ")[0].strip() for n in names.split(",") if n.strip()}
            if taken - {"main"}:
                found[str(path.relative_to(repo))] = sorted(taken - {"main"})
    assert found == {}
    assert not hasattr(sim.evaluation, "evaluate")


@pytest.mark.parametrize("module", [sim.evaluation])
def test_every_name_the_evaluation_exports_exists(module) -> None:
    assert [name for name in module.__all__ if not hasattr(module, name)] == []
