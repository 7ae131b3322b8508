"""The Fetch as converted by `posegrasp.world.robot`: names, no mocap or weld, holds its posture."""

from __future__ import annotations

from collections.abc import Callable

import mujoco
import numpy as np
import pytest

from posegrasp.world import constants as C
from posegrasp.world.robot import fetch_spec, home_qpos_ctrl

Warnings = Callable[[mujoco.MjData], dict[str, int]]


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return fetch_spec().compile()


def test_joints_and_actuators(model: mujoco.MjModel) -> None:
    joints = [model.joint(i).name for i in range(model.njnt)]
    assert joints == list(C.ACTUATED_JOINTS)
    actuators = [model.actuator(i).name for i in range(model.nu)]
    assert actuators == list(C.ACTUATORS)
    for i, joint in enumerate(C.ACTUATED_JOINTS):
        assert model.actuator_trntype[i] == mujoco.mjtTrn.mjTRN_JOINT
        assert model.actuator_trnid[i, 0] == model.joint(joint).id
    base_types = [model.joint(j).type[0] for j in C.BASE_JOINTS]
    assert base_types == [mujoco.mjtJoint.mjJNT_SLIDE] * 2 + [mujoco.mjtJoint.mjJNT_HINGE]


def test_named_frames_exist(model: mujoco.MjModel) -> None:
    for kind, name in (
        (mujoco.mjtObj.mjOBJ_CAMERA, C.HEAD_CAMERA),
        (mujoco.mjtObj.mjOBJ_SITE, C.GRASP_SITE),
        (mujoco.mjtObj.mjOBJ_BODY, C.BASE_BODY),
        (mujoco.mjtObj.mjOBJ_BODY, C.GRIPPER_BODY),
        *((mujoco.mjtObj.mjOBJ_BODY, b) for b in C.FINGER_BODIES),
    ):
        assert mujoco.mj_name2id(model, kind, name) >= 0, name


def test_no_mocap_no_weld(model: mujoco.MjModel) -> None:
    assert model.nmocap == 0
    assert model.neq == 0
    assert mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, C.PREFIX + "mocap") < 0
    assert not np.any(model.body_mocapid >= 0)


def test_home_posture_within_limits(model: mujoco.MjModel) -> None:
    qpos, ctrl = home_qpos_ctrl(model)
    assert len(qpos) == model.nu
    for i in range(model.nu):
        lo, hi = model.actuator_ctrlrange[i]
        assert lo <= ctrl[i] <= hi, model.actuator(i).name
    for joint in C.ACTUATED_JOINTS:
        j = model.joint(joint)
        if model.jnt_limited[j.id]:
            assert j.range[0] <= qpos[int(j.qposadr[0])] <= j.range[1], joint


def test_holds_home_posture_under_gravity(model: mujoco.MjModel, mj_warnings: Warnings) -> None:
    assert model.opt.gravity[2] == pytest.approx(-9.81)
    data = mujoco.MjData(model)
    qpos, ctrl = home_qpos_ctrl(model)
    for adr, value in qpos.items():
        data.qpos[adr] = value
    data.ctrl[:] = ctrl
    mujoco.mj_forward(model, data)
    q0 = data.qpos.copy()
    mujoco.mj_step(model, data, nstep=round(2.0 / model.opt.timestep))
    assert data.time == pytest.approx(2.0)
    assert mj_warnings(data) == {}
    assert np.abs(data.qpos - q0).max() < 1e-3


def test_servos_track_a_new_target(model: mujoco.MjModel) -> None:
    """The position actuators really drive the joints (the posture test is not vacuous)."""
    data = mujoco.MjData(model)
    qpos, ctrl = home_qpos_ctrl(model)
    for adr, value in qpos.items():
        data.qpos[adr] = value
    target = ctrl.copy()
    elbow = model.actuator("act_elbow_flex_joint").id
    target[elbow] -= 0.3
    data.ctrl[:] = target
    mujoco.mj_step(model, data, nstep=round(2.0 / model.opt.timestep))
    q = data.qpos[model.joint(C.ARM_JOINTS[3]).qposadr[0]]
    assert q == pytest.approx(target[elbow], abs=0.02)
