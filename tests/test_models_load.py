"""Every model loads and steps quietly (MuJoCo Menagerie style): the world file, the robot, each
object on a floor, and an assembled scene per object."""

from __future__ import annotations

from collections.abc import Callable

import mujoco
import numpy as np
import pytest

from posegrasp.world.objects import OBJECT_NAMES, load_object
from posegrasp.world.robot import fetch_spec, home_qpos_ctrl
from posegrasp.world.scene import WORLD_XML, SceneConfig, build_scene

Warnings = Callable[[mujoco.MjData], dict[str, int]]
N_STEPS = 200


def _step(model: mujoco.MjModel, data: mujoco.MjData) -> None:
    mujoco.mj_step(model, data, nstep=N_STEPS)
    assert np.all(np.isfinite(data.qpos)) and np.all(np.isfinite(data.qvel))


def test_world_file(mj_warnings: Warnings) -> None:
    model = mujoco.MjModel.from_xml_path(str(WORLD_XML))
    names = {model.camera(i).name for i in range(model.ncam)}
    assert "external" in names
    assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "table_top") >= 0
    data = mujoco.MjData(model)
    _step(model, data)
    assert mj_warnings(data) == {}


def test_robot_alone(mj_warnings: Warnings) -> None:
    model = fetch_spec().compile()
    data = mujoco.MjData(model)
    qpos, ctrl = home_qpos_ctrl(model)
    for adr, value in qpos.items():
        data.qpos[adr] = value
    data.ctrl[:] = ctrl
    _step(model, data)
    assert mj_warnings(data) == {}


@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_object_on_floor(name: str, mj_warnings: Warnings) -> None:
    obj = load_object(name)
    spec = mujoco.MjSpec()
    floor = spec.worldbody.add_geom()
    floor.type, floor.size = mujoco.mjtGeom.mjGEOM_PLANE, [1.0, 1.0, 0.05]
    quat = next(iter(obj.resting_poses.values()))
    obj.add_to_spec(spec, f"{name}_0", np.array([0.0, 0.0, obj.resting_height(quat) + 0.01]), quat)
    model = spec.compile()
    data = mujoco.MjData(model)
    _step(model, data)
    assert mj_warnings(data) == {}
    # It fell the centimetre and landed: resting on the floor, not through it.
    assert data.body(f"{name}_0").xpos[2] == pytest.approx(obj.resting_height(quat), abs=2e-3)


@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_assembled_scene(name: str, mj_warnings: Warnings) -> None:
    scene = build_scene(name, seed=11, config=SceneConfig(n_distractors=2, settle_time=0.0))
    assert len(scene.objects) == 3
    _step(scene.model, scene.data)
    assert mj_warnings(scene.data) == {}
