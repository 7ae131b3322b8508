"""The speed benchmarks of bench/: `make bench` runs each, and a bench's exit status and JSON
say what its printed verdicts say."""

from __future__ import annotations

import importlib.util
import json
import re
import sys
from pathlib import Path

import pytest

from posegrasp.core.paths import REPO_ROOT

BENCH = REPO_ROOT / "bench"


def _bench(name: str, monkeypatch):
    """A script of bench/ as a module (bench/ is no package), registered while the test runs."""
    spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, name, module)  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def _verdicts(text: str) -> list[str]:
    """The PASS / MISS verdicts a bench printed, in order."""
    return re.findall(r"\b(PASS|MISS)\b", text)


def test_make_bench_runs_every_bench() -> None:
    makefile = (REPO_ROOT / "Makefile").read_text()
    block = re.search(r"^BENCHES :=(.*?)^bench:", makefile, re.S | re.M)
    assert block is not None
    run = set(re.findall(r'"(\w+\.py)\b', block.group(1)))
    assert run == {p.name for p in BENCH.glob("*.py")}


def _check_run(status: int, out: str, json_path: Path) -> None:
    verdicts = _verdicts(out)
    met = json.loads(json_path.read_text())["targets_met"]
    assert verdicts and len(met) <= len(verdicts)
    assert status == (1 if "MISS" in verdicts else 0), out
    assert all(met.values()) == ("MISS" not in verdicts), (met, out)


def test_sim_speed_status_and_json_follow_its_verdicts(tmp_path, monkeypatch, capsys) -> None:
    main = _bench("sim_speed", monkeypatch).main
    path = tmp_path / "sim.json"
    status = main(["--seeds", "1", "--sim-seconds", "0.05", "--frames", "2", "--json", str(path)])
    _check_run(status, capsys.readouterr().out, path)


def test_estimate_latency_stages_time_the_architecture_without_weights(
    tmp_path, monkeypatch, capsys
) -> None:
    main = _bench("estimate_latency", monkeypatch).main
    path = tmp_path / "stages.json"
    argv = ["--stages", "--random-weights", "--images", "2", "--json", str(path)]
    status = main(argv)
    _check_run(status, capsys.readouterr().out, path)
    out = json.loads(path.read_text())
    assert out["weights"] == "random" and out["images"] == 2
    assert set(out["targets_met"]) == {"total_3_objects", "nets_per_object"}
    # The detector keeps as many boxes as the scene has objects: every stage sees the work.
    assert out["one_object"]["detections_per_image"] == pytest.approx(1.0)
    assert out["three_objects"]["detections_per_image"] == pytest.approx(3.0)


def test_estimate_latency_takes_objects_for_a_whole_estimate_only(monkeypatch, capsys) -> None:
    module = _bench("estimate_latency", monkeypatch)
    assert module.main(["--stages", "--random-weights", "--objects", "phone"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--objects not with --stages" in err[0]
    assert module.main(["--objects", "no-such-object"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no-such-object" in err[0]
    # The unseen estimator's own target: it also tells its target among its detections.
    assert module.TARGETS_MS["hybrid-global-unseen"] > module.TARGET_MS
