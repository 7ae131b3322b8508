"""Grasp execution settings: the kinematic transit, its fall-back to physics, the time step."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from grasping.execute import TRANSIT_MODES, ExecutionConfig, Executor
from grasping.planner import PLANNED_JOINTS, GraspPlanner
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.world import constants as C
from posegrasp.world.scene import build_scene


def _site(model: mujoco.MjModel) -> int:
    return model.site(C.GRASP_SITE).id


def _to_pregrasp(transit: str, torso_shift: float = 0.0):
    """Scene, executor and plan after the transit and the 0.2 s settle of `execute`; the
    pre-grasp's torso is moved by `torso_shift` [m] first."""
    s = build_scene("phone", 11)
    plan = GraspPlanner(s.model).plan("phone", s.object_pose(), s.data.qpos.copy())
    plan.pregrasp = plan.pregrasp.copy()
    plan.pregrasp[PLANNED_JOINTS.index(C.TORSO_JOINT)] += torso_shift
    ex = Executor(s, ExecutionConfig(transit=transit))
    before = {o.body: s.object_pose(o.body) for o in s.objects}
    ex.set_fingers(C.FINGER_TRAVEL)
    ex._transit(plan)
    ex._advance(0.2)
    return s, ex, plan, before


def _planned_site(s, plan) -> np.ndarray:
    m = s.model
    d = mujoco.MjData(m)
    d.qpos[:] = s.data.qpos
    d.qpos[[m.joint(j).qposadr[0] for j in PLANNED_JOINTS]] = plan.pregrasp
    mujoco.mj_kinematics(m, d)
    return d.site_xpos[_site(m)].copy()


def test_kinematic_transit_arrives_at_the_planned_pregrasp_like_the_simulated_one() -> None:
    kin, ex_k, plan_k, before_k = _to_pregrasp("kinematic")
    dyn, _, _, _ = _to_pregrasp("dynamic")
    site_k = kin.data.site_xpos[_site(kin.model)]
    site_d = dyn.data.site_xpos[_site(dyn.model)]
    # Played back, the gripper is where the plan put it (gravity is compensated) ...
    assert np.linalg.norm(site_k - _planned_site(kin, plan_k)) < 1e-3
    # ... and within the simulated servo's lag (a few millimetres) of the simulated transit.
    assert np.linalg.norm(site_k - site_d) < 0.01
    assert kin.data.time == pytest.approx(dyn.data.time)
    assert not ex_k.events and not ex_k.table_hit
    for body, T in before_k.items():  # nothing in the scene moved
        assert np.abs(kin.object_pose(body) - T).max() < 1e-6


def test_a_transit_that_touches_the_scene_is_simulated_from_there() -> None:
    # A pre-grasp with the torso 0.3 m lower drives the arm into the table and the phone.
    s, ex, plan, _ = _to_pregrasp("kinematic", torso_shift=-0.3)
    assert any("transit touched the scene" in e for e in ex.events)
    # Physics took over: contact holds the robot off (pressing with the torso's full force, it
    # sinks in by a soft contact's centimetre or so) instead of letting it pass through.
    assert np.linalg.norm(s.data.site_xpos[_site(s.model)] - _planned_site(s, plan)) > 0.05
    assert s.data.ncon > 0 and s.data.contact.dist.min() > -0.03


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"transit": "teleport"}, "valid: " + ", ".join(TRANSIT_MODES)),
        ({"timestep": 0.004}, "divide control_dt"),
        ({"timestep": 0.0}, "divide control_dt"),
        ({"timestep": 0.02}, "divide control_dt"),
    ],
)
def test_bad_execution_settings_are_one_line(kwargs, message) -> None:
    with pytest.raises(InvalidArgumentError, match=message) as err:
        ExecutionConfig(**kwargs)
    assert "\n" not in str(err.value)


def test_the_grasp_runs_at_the_execution_timestep() -> None:
    s = build_scene("phone", 11)
    assert s.model.opt.timestep == pytest.approx(0.002)  # the scene settles at the world's step
    Executor(s, ExecutionConfig(timestep=0.0025))
    assert s.model.opt.timestep == pytest.approx(0.0025)
