"""Shared test set-up: software EGL rendering and a MuJoCo-warning helper."""

from __future__ import annotations

from collections.abc import Callable

import mujoco
import pytest
import torch

from posegrasp.core.runtime import setup_rendering

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
