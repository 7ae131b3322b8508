"""Shared test set-up: folders of the tests' own, software EGL rendering and a MuJoCo-warning
helper.

The tests are hermetic: before anything is imported, the user objects folder, ``XDG_DATA_HOME``
and the data folder point at folders of the tests' own, so the tests never read or write a
user's objects, datasets or caches, and pass the same with user objects installed. The data
folder (codebooks are cached there) is ``.test-data/`` in the repository, kept between runs;
the objects folder is a new empty one per run. Subprocesses inherit both.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

#: The tests' own data folder (git-ignored), kept between runs for the codebooks cached there.
TEST_DATA = Path(__file__).resolve().parents[1] / ".test-data"
#: The tests' own user objects folder and XDG data home: empty at the start of every run.
TEST_HOME = Path(tempfile.mkdtemp(prefix="posegrasp-tests-"))
os.environ["POSEGRASP_DATA"] = str(TEST_DATA)
os.environ["POSEGRASP_OBJECTS"] = str(TEST_HOME / "objects")
os.environ["XDG_DATA_HOME"] = str(TEST_HOME / "xdg")

import mujoco  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

from posegrasp.core.runtime import setup_rendering  # noqa: E402

# Loads torch (and triton) before any MuJoCo GL context exists (docs/DESIGN.md §11).
setup_rendering()


def _warnings(data: mujoco.MjData) -> dict[str, int]:
    return {
        mujoco.mjtWarning(i).name: int(w.number)
        for i, w in enumerate(data.warning)
        if w.number != 0
    }


@pytest.fixture
def mj_warnings() -> Callable[[mujoco.MjData], dict[str, int]]:
    """`mj_warnings(data)`: the MuJoCo warnings counted in data, by name ({} when none)."""
    return _warnings


@pytest.fixture(scope="module")
def torch_one_thread():
    """Two torch threads on a busy 2-core machine are far slower than one; restore afterwards."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
