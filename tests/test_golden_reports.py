"""`python -m sim.evaluate` writes, to the bit, the golden reports and summaries of
`tests/golden/record_reports.py` (every tier with the default estimator, the oracles, ``--margin``
and the BOP route), with only wall times and paths left out.

A change meant to alter them re-records them: ``python tests/golden/record_reports.py``. They
are kept per CPU kind (`tests/golden/golden_cpu.py`): equal to the bit to any recorded set
passes; on a kind with a set of its own nothing else does; on a kind with none, the printed
summary must be a set's, and the test says that it fell back.
"""

from __future__ import annotations

import importlib.util
import json
import warnings
from pathlib import Path

import pytest

GOLDEN = Path(__file__).resolve().parent / "golden"


def _recorder():
    spec = importlib.util.spec_from_file_location("record_reports", GOLDEN / "record_reports.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


rec = _recorder()


def _differences(a, b, path: str = "") -> list[str]:
    """Where two JSON values differ, as paths (``episodes[1].pose_error.ray_m``)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = [f"{path}.{k}".lstrip(".") for k in sorted(set(a) ^ set(b))]
        for k in sorted(set(a) & set(b)):
            out += _differences(a[k], b[k], f"{path}.{k}".lstrip("."))
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [
            d
            for i, (x, y) in enumerate(zip(a, b, strict=True))
            for d in _differences(x, y, f"{path}[{i}]")
        ]
    return [] if rec.canonical(a) == rec.canonical(b) else [f"{path}: {a!r} != {b!r}"]


@pytest.mark.slow
@pytest.mark.parametrize("case", list(rec.CASES))
def test_the_report_is_the_golden_one(case: str, tmp_path: Path) -> None:
    report, text = rec.run_case(case, tmp_path)
    sets = rec.CPU.golden_sets(rec.GOLDEN_DIR)
    golden = {
        f: (f / f"{case}.json", f / f"{case}.txt") for f in sets if (f / f"{case}.json").exists()
    }
    if any(
        rec.canonical(report) == j.read_text() and text == t.read_text() for j, t in golden.values()
    ):
        return
    own = rec.CPU.own_set(rec.GOLDEN_DIR)
    if own is not None:
        j, t = golden[own]
        diff = _differences(report, json.loads(j.read_text()))
        assert not diff, f"{len(diff)} difference(s) from this CPU kind's {case} report: {diff[:8]}"
        assert text == t.read_text()
    assert any(text == t.read_text() for _, t in golden.values()), (
        f"the {case} summary is no golden set's:\n{text}"
    )
    warnings.warn(
        f"no golden reports recorded on this CPU kind ({rec.CPU.cpu_kind()}): the {case} summary "
        "compared, not the report; record its set with python tests/golden/record_reports.py",
        stacklevel=1,
    )
