"""The six procedural objects: frames, sizes, masses and the loader's errors."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from posegrasp.core.errors import UnknownNameError
from posegrasp.world.objects import COLLISION_GROUP, OBJECT_NAMES, VISUAL_GROUP, load_object


def test_six_objects() -> None:
    assert OBJECT_NAMES == ("car", "faucet", "chair", "phone", "screen", "pistol")


@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_mesh_frame_and_size(name: str) -> None:
    obj = load_object(name)
    assert obj.name == name
    assert len(obj.mesh.faces) > 0 and obj.mesh.area > 0
    lo, hi = obj.mesh.bounds
    assert np.abs((lo + hi) / 2).max() < 1e-9
    assert 0.08 <= obj.extents.max() <= 0.25
    assert obj.diameter >= obj.extents.max()
    assert obj.diameter <= np.linalg.norm(obj.extents) + 1e-9


@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_resting_poses(name: str) -> None:
    obj = load_object(name)
    assert obj.resting_poses
    for quat in obj.resting_poses.values():
        assert np.linalg.norm(quat) == pytest.approx(1.0)
        # O's origin is the bounding-box centre: it rests above the support, at most half the
        # diameter above it.
        assert 0.0 < obj.resting_height(quat) <= obj.diameter / 2 + 1e-9


def test_unknown_name_lists_valid_names() -> None:
    with pytest.raises(UnknownNameError) as info:
        load_object("teapot")
    message = str(info.value)
    assert "'teapot'" in message
    for name in OBJECT_NAMES:
        assert name in message
    assert info.value.choices == list(OBJECT_NAMES)
    assert isinstance(info.value, ValueError)


@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_compiled_body(name: str) -> None:
    obj = load_object(name)
    spec = mujoco.MjSpec()
    obj.add_to_spec(spec, f"{name}_0", np.array([0.0, 0.0, 0.5]), np.array([1.0, 0, 0, 0]))
    model = spec.compile()
    body = model.body(f"{name}_0")
    assert body.mass[0] > 0
    assert body.mass[0] == pytest.approx(obj.mass, rel=1e-6)
    assert model.body_dofnum[body.id] == 6
    geoms = np.flatnonzero(model.geom_bodyid == body.id)
    visual = [g for g in geoms if model.geom_group[g] == VISUAL_GROUP]
    collision = [g for g in geoms if model.geom_group[g] == COLLISION_GROUP]
    assert len(visual) == len(obj.parts)
    assert len(collision) == sum(p.collision for p in obj.parts) > 0
    assert all(model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0 for g in visual)
    assert all(model.geom_contype[g] != 0 for g in collision)
