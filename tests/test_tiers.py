"""Scene tiers (`posegrasp.world.tiers`), footprint layouts, clean grasps and the base drive."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from grasping.clearance import intrusion
from grasping.execute import Executor
from grasping.planner import GraspPlanner
from posegrasp.core.errors import UnknownNameError
from posegrasp.core.transforms import quat_to_mat
from posegrasp.world import constants as C
from posegrasp.world.layout import gap
from posegrasp.world.objects import load_object
from posegrasp.world.occlusion import occlusion
from posegrasp.world.scene import SceneConfig, build_scene
from posegrasp.world.tiers import DEFAULT_TIER, TIERS, check_tier, tier_scene

FAST = SceneConfig(settle_time=0.0)


def _footprints(scene) -> list[np.ndarray]:
    out = []
    for o in scene.objects:
        T = scene.object_pose(o.body)
        xy = (np.asarray(o.model.mesh.vertices) @ T[:3, :3].T + T[:3, 3])[:, :2]
        out.append(xy[ConvexHull(xy).vertices])
    return out


def test_the_default_tier_is_todays_scenes() -> None:
    assert DEFAULT_TIER == "isolated"
    assert tier_scene("isolated") == SceneConfig()
    assert tier_scene("isolated", FAST) == FAST


def test_unknown_tier_names_the_valid_ones() -> None:
    with pytest.raises(
        UnknownNameError, match="valid tiers: isolated, clutter, any-pose, far, hard"
    ):
        check_tier("banana")
    with pytest.raises(UnknownNameError):
        tier_scene("banana")
    assert check_tier("far") == "far"
    assert list(TIERS) == ["isolated", "clutter", "any-pose", "far", "hard"]


def test_gap_of_convex_polygons_by_hand() -> None:
    sq = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    assert gap(sq, sq + np.array([3.0, 0.0])) == pytest.approx(2.0)
    assert gap(sq, sq + np.array([2.0, 2.0])) == pytest.approx(np.sqrt(2.0))  # corner to corner
    assert gap(sq, sq + np.array([0.5, 0.5])) == 0.0  # overlapping
    tri = np.array([[0, 2.5], [1, 2.5], [0.5, 3.5]], float)
    assert gap(sq, tri) == pytest.approx(1.5)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_clutter_puts_two_neighbours_3_to_8_cm_from_the_target(seed: int) -> None:
    scene = build_scene("phone", 1_000_000_000 + seed, tier_scene("clutter", FAST))
    assert 4 <= len(scene.objects) <= 6
    names = [o.name for o in scene.objects]
    assert len(set(names)) == len(names) and names[0] == "phone"
    prints = _footprints(scene)
    gaps = np.array(sorted(gap(prints[0], F) for F in prints[1:]))
    assert gaps.min() >= 0.03 - 1e-3
    assert np.sum(gaps <= 0.08 + 1e-3) >= 2


def test_clutter_scenes_are_reproducible() -> None:
    a = build_scene("car", 1_000_000_005, tier_scene("clutter", FAST))
    b = build_scene("car", 1_000_000_005, tier_scene("clutter", FAST))
    assert [o.name for o in a.objects] == [o.name for o in b.objects]
    np.testing.assert_array_equal(a.data.qpos, b.data.qpos)
    np.testing.assert_array_equal(a.model.light_diffuse, b.model.light_diffuse)


@pytest.mark.parametrize("seed", [0, 3])
def test_far_puts_the_camera_0_9_to_1_6_m_from_the_target(seed: int) -> None:
    scene = build_scene("screen", 1_000_000_000 + seed, tier_scene("far", FAST))
    cam = scene.model.camera(C.HEAD_CAMERA).id
    d = float(np.linalg.norm(scene.data.cam_xpos[cam] - scene.object_pose()[:3, 3]))
    assert 0.85 <= d <= 1.65


def test_a_far_object_is_grasped_after_a_drive() -> None:
    scene = build_scene("phone", 1_000_000_004, tier_scene("far"))
    q = scene.data.qpos.copy()
    base0 = np.array([q[scene.model.joint(j).qposadr[0]] for j in C.BASE_JOINTS[:2]])
    T = scene.object_pose()
    assert np.linalg.norm(T[:2, 3] - base0) > 0.9
    plan = GraspPlanner(scene.model).plan("phone", T, q)
    drive = plan.transit[0]
    assert np.linalg.norm(drive[:2] - T[:2, 3]) == pytest.approx(0.62, abs=1e-9)
    outcome = Executor(scene).execute(plan)
    assert outcome.success, outcome.failure_reason


def test_clearance_sees_a_neighbour_between_the_fingers() -> None:
    T_G = np.eye(4)
    T_G[:3, :3] = np.column_stack([[0, 0, -1.0], [0, 1.0, 0], [1.0, 0, 0]])  # approach down
    T_G[:3, 3] = [0.6, 0.0, 0.6]
    near = np.eye(4)
    near[:3, 3] = [0.6, 0.05, 0.58]  # at the finger's side
    far = np.eye(4)
    far[:3, 3] = [0.6, 0.4, 0.58]
    assert intrusion(T_G, [("phone", near)]) > 0
    assert intrusion(T_G, [("phone", far)]) == 0
    assert intrusion(T_G, []) == 0


def test_a_moved_neighbour_makes_the_grasp_unclean() -> None:
    scene = build_scene("phone", 1_000_000_001, SceneConfig(n_distractors=2))
    ex = Executor(scene)
    poses0 = {o.body: scene.object_pose(o.body) for o in scene.objects[1:]}
    assert ex.disturbed(poses0) == []
    body = scene.objects[1].body
    adr = scene.model.body(body).jntadr[0]
    qadr = scene.model.jnt_qposadr[adr]
    scene.data.qpos[qadr : qadr + 3] += [0.05, 0.0, 0.0]
    import mujoco

    mujoco.mj_kinematics(scene.model, scene.data)
    assert [s.split(" ")[0] for s in ex.disturbed(poses0)] == [body]


def test_neighbours_an_estimator_reports_are_validated() -> None:
    """An unknown class is refused; a neighbour pose that is no rigid transform fails the
    episode as invalid_action, naming the neighbour."""
    from sim.episodes.episode import Episode

    ep = Episode("phone", 1_000_000_000)
    try:
        with pytest.raises(UnknownNameError):
            ep.act(ep.T_C_O_true, "test", neighbours=[("teapot", np.eye(4))])
    finally:
        ep.close()
    ep = Episode("phone", 1_000_000_000)
    try:
        r = ep.act(ep.T_C_O_true, "test", neighbours=[("car", np.ones((4, 4)))])
    finally:
        ep.close()
    assert r.failure_reason == "invalid_action" and "neighbour 0 ('car')" in r.notes[0]


@pytest.mark.parametrize("seed", range(6))
def test_any_pose_draws_graspable_resting_poses(seed: int) -> None:
    name = ("phone", "screen", "car", "chair", "faucet", "pistol")[seed]
    scene = build_scene(name, 1_000_000_000 + seed, tier_scene("any-pose"))
    obj = load_object(name)
    rest = scene.target.resting
    assert rest in obj.resting_poses and rest not in obj.ungraspable
    # The object lies in that pose: its listed up direction points up, within 5 degrees.
    up_in_O = quat_to_mat(obj.resting_poses[rest])[2]
    assert scene.object_pose()[:3, :3] @ up_in_O @ [0, 0, 1] > np.cos(np.deg2rad(5))


def test_any_pose_covers_every_graspable_pose() -> None:
    cfg = replace(tier_scene("any-pose"), settle_time=0.0)
    seen = {build_scene("phone", 2_000_000 + i, cfg).target.resting for i in range(40)}
    obj = load_object("phone")
    assert seen == set(obj.resting_poses) - set(obj.ungraspable)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_hard_hides_part_of_the_target_behind_a_neighbour(seed: int) -> None:
    cfg = tier_scene("hard")
    scene = build_scene("chair", 1_000_000_000 + seed, cfg)
    assert cfg.occlusion is not None
    lo, hi = cfg.occlusion
    assert lo <= scene.occlusion <= hi
    # Measured again from scratch, the same figure: the measure leaves the scene as it was.
    again = occlusion(
        scene.model, scene.data, scene.target.body, [o.body for o in scene.objects[1:]]
    )
    assert again == pytest.approx(scene.occlusion, abs=1e-9)
    # Hiding nothing hides nothing.
    assert occlusion(scene.model, scene.data, scene.target.body, []) == 0.0
    cam = np.linalg.norm(
        scene.data.cam_xpos[scene.model.camera(C.HEAD_CAMERA).id] - scene.object_pose()[:3, 3]
    )
    assert 0.85 <= cam <= 1.65


def test_hard_scenes_are_reproducible() -> None:
    a = build_scene("car", 1_000_000_007, tier_scene("hard"))
    b = build_scene("car", 1_000_000_007, tier_scene("hard"))
    assert a.occlusion == b.occlusion
    np.testing.assert_array_equal(a.data.qpos, b.data.qpos)
