"""Every built-in learned estimator gives, on the recorded held-out observations, the estimates
recorded in `tests/golden/poses/` to the bit: the pose, the neighbours and the description.

The golden files are written by `tests/golden/record_poses.py` from the commit before a change
that should move no pose (see its docstring); torch runs on the threads they were recorded with,
since its kernels sum in another order on another number of threads."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from posegrasp.core.contract import Observation

GOLDEN = Path(__file__).resolve().parent / "golden"


def _recorder() -> ModuleType:
    """`tests/golden/record_poses.py` as a module (the tests folder is no package)."""
    spec = importlib.util.spec_from_file_location("record_poses", GOLDEN / "record_poses.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


record_poses = _recorder()
RECORD: dict[str, Any] = json.loads((GOLDEN / "poses" / "estimates.json").read_text())


def _settings_left_out(record: dict[str, Any]) -> dict[str, Any]:
    """An estimate's record without the settings it reports (``info.verify.config``): their
    layout is the configuration's, not an output of the estimate."""
    out = json.loads(json.dumps(record))
    out["info"].get("verify", {}).pop("config", None)
    return out


@pytest.fixture(scope="module")
def observations() -> list[tuple[str, Observation]]:
    """The recorded observations, in the recorded order."""
    with np.load(GOLDEN / "poses" / "observations.npz") as z:
        out = []
        for o in RECORD["observations"]:
            label = o["label"]
            top = float(z[f"{label}/table_top_z"])
            obs = Observation(
                z[f"{label}/rgb"],
                z[f"{label}/K"],
                z[f"{label}/T_world_cam"],
                o["object"],
                o["seed"],
                table_top_z=None if math.isnan(top) else top,
            )
            out.append((label, obs))
    return out


@pytest.fixture(scope="module")
def golden_poses() -> dict[str, np.ndarray]:
    with np.load(GOLDEN / "poses" / "poses.npz") as z:
        return {k: z[k] for k in z.files}


@pytest.fixture
def recorded_threads():
    """Torch on the threads the golden estimates were made with, restored afterwards."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(RECORD["threads"])
    yield
    torch.set_num_threads(n)


def test_the_golden_record_covers_every_learned_estimator() -> None:
    """Each learned estimator is recorded, or recorded as one that cannot be made here."""
    from perception.estimators import LEARNED_ESTIMATORS

    recorded = set(RECORD["estimates"]) | set(RECORD["skipped"])
    assert recorded <= set(LEARNED_ESTIMATORS)
    assert len(RECORD["observations"]) == 5 * record_poses.EPISODES_PER_TIER + 2


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(RECORD["estimates"]))
def test_an_estimator_gives_its_golden_estimates_to_the_bit(
    name: str, observations, golden_poses, recorded_threads
) -> None:
    from perception.estimators import LEARNED_ESTIMATORS

    estimator = LEARNED_ESTIMATORS[name]()
    for label, obs in observations:
        record, arrays = record_poses.estimate_record(estimator.estimate(obs))
        want = RECORD["estimates"][name][label]
        where = f"{name} on {label}"
        assert record["pose"] == want["pose"], where
        keys = {k.rsplit("/", 1)[1] for k in golden_poses if k.startswith(f"{name}/{label}/")}
        assert set(arrays) == keys, where
        for key, value in arrays.items():
            assert np.array_equal(value, golden_poses[f"{name}/{label}/{key}"]), (where, key)
        got, want = _settings_left_out(record), _settings_left_out(want)
        assert record_poses.canonical(got) == record_poses.canonical(want), where


@pytest.mark.slow
def test_the_estimators_the_record_skipped_still_cannot_be_made_here() -> None:
    """The user objects' estimator needs a detector fine-tuned on user objects, which the tests'
    own (empty) user objects folder does not hold."""
    from perception.estimators import LEARNED_ESTIMATORS
    from posegrasp.core.errors import AssetError

    for name in RECORD["skipped"]:
        with pytest.raises(AssetError):
            LEARNED_ESTIMATORS[name]()
