"""Shared test set-up: software EGL rendering and a MuJoCo-warning helper."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

# torch (with torchvision and torch._dynamo, which loads triton) must be imported before any
# MuJoCo GL context exists: importing triton afterwards crashes the process (docs/DESIGN.md §11).
import torch  # noqa: I001
import torch._dynamo
import torchvision  # noqa: F401

from collections.abc import Callable

import mujoco
import pytest


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
