"""The stage an image is put down to by studies/shift_stages.py."""

from __future__ import annotations

import importlib.util
from types import SimpleNamespace

import numpy as np

from posegrasp.core.paths import REPO_ROOT

_spec = importlib.util.spec_from_file_location(
    "shift_stages", REPO_ROOT / "studies" / "shift_stages.py"
)
study = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(study)

TRUTH = np.zeros((20, 20), bool)
TRUTH[5:15, 5:15] = True
RIGHT, WRONG = np.eye(4), np.diag([1.0, 1.0, 1.0, 2.0])


def _errors(T: np.ndarray) -> dict[str, float]:
    return {"mssd_rel_diameter": 0.0 if T[3, 3] == 1.0 else 0.5}


def _work(mask: np.ndarray | None, winner: np.ndarray | None, others=(), placed=None):
    target = None if mask is None else SimpleNamespace(mask=mask)
    ranked = [SimpleNamespace(T_C_O=T) for T in ([] if winner is None else [winner, *others])]
    return SimpleNamespace(
        target=target,
        winner=ranked[0] if ranked else None,
        ranked=ranked,
        placed=None if placed is None else SimpleNamespace(T_C_O=placed),
    )


def test_each_image_is_put_down_to_the_first_stage_that_failed_it() -> None:
    other = np.zeros_like(TRUTH)
    other[0:3, 0:3] = True  # another object's mask
    poor = np.zeros_like(TRUTH)
    poor[5:15, 5:9] = True  # 40 % of the truth
    cases = {
        "detection": [_work(None, None), _work(other, RIGHT)],
        "mask": [_work(poor, WRONG)],
        "hypotheses": [_work(TRUTH, WRONG, [WRONG])],
        "verification": [_work(TRUTH, WRONG, [RIGHT])],
        "support": [_work(TRUTH, RIGHT, placed=WRONG)],
        "right": [_work(poor, RIGHT), _work(TRUTH, WRONG, placed=RIGHT)],
    }
    for want, works in cases.items():
        for work in works:
            assert study.outcome(work, TRUTH, _errors) == want
    assert list(cases) == list(study.OUTCOMES)
