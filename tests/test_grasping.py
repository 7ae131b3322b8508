"""Grasp candidates, planner reachability and input checks, execution and the success check."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from grasping.candidates import grasp_candidates
from grasping.execute import Executor
from grasping.mesh_grasps import CHECK_BUDGET, CHECKED, KEEP, checks_per_pose
from grasping.planner import GraspPlanner, PlanningError
from grasping.top_grasps import clear, top_grasp_points, top_grasps
from posegrasp.core.errors import InvalidArgumentError, UnknownNameError
from posegrasp.core.transforms import quat_to_mat
from posegrasp.world import constants as C
from posegrasp.world.objects import OBJECT_NAMES, load_object
from posegrasp.world.scene import build_scene


@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_candidates_are_valid_top_grasps(name: str) -> None:
    obj = load_object(name)
    cands = grasp_candidates(name)
    assert len(cands) >= 8
    for c in cands:
        R = c.T_O_G[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
        assert np.linalg.det(R) == pytest.approx(1.0)
        # The approach is straight down in the resting pose the candidate was made for.
        up = quat_to_mat(obj.resting_poses[c.pose])[2]
        np.testing.assert_allclose(R[:, 0], -up, atol=1e-6)
        assert 0.0 < c.width < 2 * C.FINGER_TRAVEL - 0.01  # the gripper opens wide enough
    # Each position and closing line comes with both finger orders.
    orders = Counter(
        (tuple(np.round(c.T_O_G[:3, 3], 6)), tuple(np.round(c.T_O_G[:3, 1] * k, 6)))
        for c in cands
        for k in (1, -1)
    )
    assert set(orders.values()) == {2}


@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_every_graspable_resting_pose_has_candidates(name: str) -> None:
    obj = load_object(name)
    per_pose = Counter(c.pose for c in grasp_candidates(name))
    for pose in obj.resting_poses:
        if pose in obj.ungraspable:
            assert per_pose[pose] == 0, f"{name} {pose} is marked ungraspable but has grasps"
        else:
            assert per_pose[pose] >= 2, f"{name} {pose} has no grasp from above"


def test_generated_grasps_keep_the_fingers_off_other_parts() -> None:
    """A generated grasp of the pistol lying on its back closes on a part, and the finger sweep
    of a grasp moved 2 cm sideways onto the neighbouring geometry is rejected."""
    obj = load_object("pistol")
    up = quat_to_mat(obj.resting_poses["up_-y"])[2]
    grasps = top_grasps(obj, up)
    assert grasps
    pts = np.asarray(obj.mesh.vertices)
    low = float((pts @ up).min())
    for _part, T, width in grasps:
        assert clear(T, width, top_grasp_points("pistol"), float(T[:3, 3] @ up) - low)
    # The same grasp sunk 3 cm deeper puts the fingertips through the table or the body.
    _part, T, width = grasps[0]
    T = T.copy()
    T[:3, 3] -= 0.03 * up
    assert not clear(T, width, top_grasp_points("pistol"), float(T[:3, 3] @ up) - low)


def test_unknown_object_candidates() -> None:
    with pytest.raises(UnknownNameError, match="valid objects"):
        grasp_candidates("teapot")


@pytest.fixture(scope="module")
def phone_scene():
    return build_scene("phone", 11)


def test_an_unknown_candidate_source_is_one_line() -> None:
    with pytest.raises(UnknownNameError, match=r"candidate source 'found'.*designed, generated"):
        grasp_candidates("phone", "found")


def test_evaluate_refuses_an_unknown_candidate_source_in_one_line(capsys) -> None:
    from sim.evaluate import main as evaluate_main

    assert evaluate_main(["--candidates", "found", "--episodes", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "designed, generated" in err[0]


@pytest.mark.slow
def test_generated_candidates_of_a_built_in_object(tmp_path, monkeypatch) -> None:
    """The generator of user objects' candidates makes a built-in object's from its convex
    parts, for every graspable resting pose, and keeps them in the data folder."""
    from grasping import candidates as gc

    monkeypatch.setenv("POSEGRASP_DATA", str(tmp_path))
    monkeypatch.setattr(gc, "_GENERATED", {})
    made = grasp_candidates("phone", "generated")
    obj = load_object("phone")
    graspable = set(obj.resting_poses) - set(obj.ungraspable)
    assert {c.pose for c in made} == graspable
    assert all(c.part == gc.GENERATED_PART and c.table_margin is not None for c in made)
    kept = list((tmp_path / "candidates").glob("phone_*.json"))
    assert len(kept) == 1
    gc._GENERATED.clear()
    again = grasp_candidates("phone", "generated")  # read back, not made again
    assert [c.T_O_G.tolist() for c in again] == [c.T_O_G.tolist() for c in made]
    # The designed ones stay the default.
    assert gc.GENERATED_PART not in {c.part for c in grasp_candidates("phone")}


def test_planner_reaches_true_pose(phone_scene) -> None:
    s = phone_scene
    plan = GraspPlanner(s.model).plan("phone", s.object_pose(), s.data.qpos.copy())
    assert plan.approach and plan.tried >= 1
    # Pre-grasp sits 10 cm back along the approach from the grasp.
    assert plan.T_world_G[:3, 0] @ np.array([0, 0, -1.0]) > 0.99


def test_planner_far_object_is_unreachable(phone_scene) -> None:
    s = phone_scene
    T = s.object_pose()
    T[0, 3] += 3.0
    with pytest.raises(PlanningError) as err:
        GraspPlanner(s.model).plan("phone", T, s.data.qpos.copy())
    assert err.value.reason == "unreachable"


def test_planner_out_of_arm_workspace_is_ik_infeasible(phone_scene) -> None:
    s = phone_scene
    T = s.object_pose()
    T[2, 3] += 1.5  # far above anything the gripper can reach
    with pytest.raises(PlanningError) as err:
        GraspPlanner(s.model).plan("phone", T, s.data.qpos.copy())
    assert err.value.reason == "ik_infeasible"


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda T: T.__setitem__((0, 3), np.nan), "NaN"),
        (lambda T: T.__setitem__((0, 0), 2.0), "orthonormal"),
    ],
)
def test_planner_rejects_bad_poses(phone_scene, mutate, message) -> None:
    s = phone_scene
    T = s.object_pose()
    mutate(T)
    with pytest.raises(InvalidArgumentError, match=message):
        GraspPlanner(s.model).plan("phone", T, s.data.qpos.copy())


def test_dropped_object_is_not_a_success() -> None:
    s = build_scene("car", 5)
    plan = GraspPlanner(s.model).plan("car", s.object_pose(), s.data.qpos.copy())
    ex = Executor(s)
    outcome = ex.execute(plan)
    assert outcome.success and ex.held() and ex.lift_height() >= 0.10
    ex.set_fingers(C.FINGER_TRAVEL)  # let go
    ex._advance(1.5)
    assert not ex.held()
    assert ex.lift_height() < 0.10


def test_physics_check_outcomes_of_a_grasp_on_the_object_beside_it_and_in_the_table() -> None:
    """The physics check of candidates (`grasping.grasp_check`): the best antipodal grasp of the
    upright phone holds; moved 20 cm aside the fingers close on nothing; moved aside with the
    fingertips 1 cm below the table the hand runs into it. Batches run in threads give the
    same outcomes; each hand carries the gripper link's own mesh only (not every mesh of the
    robot)."""
    from grasping import grasp_check
    from grasping.antipodal import antipodal_grasps, hull_points
    from grasping.mesh_grasps import convex_pieces
    from grasping.top_grasps import FINGER_X

    obj = load_object("phone")
    quat = obj.resting_poses["upright"]
    up = quat_to_mat(quat)[2]
    hulls, com = convex_pieces(obj)
    points, normals = hull_points(hulls)
    best = antipodal_grasps(points, normals, up, com)[0].T_O_G
    tip_height = float(best[:3, 3] @ up - (points @ up).min()) - FINGER_X[1]
    aside, into_table = best.copy(), best.copy()
    aside[:3, 3] += 0.2 * best[:3, 2]
    into_table[:3, 3] = aside[:3, 3] - (tip_height + 0.01) * up

    def check(trials, cfg=None):
        return grasp_check.check_grasps_in_poses(obj, [(quat, trials)], cfg)[0]

    assert check([best, aside, into_table]) == ["success", "missed", "collision"]
    # One grasp alone, as the place task predicts the object in the hand: the same outcome,
    # and a grasp that holds keeps the object within millimetres of where it was planned.
    outcome, held = grasp_check.held_in_hand(obj, quat, best)
    assert outcome == "success"
    planned = np.linalg.inv(best)
    assert np.linalg.norm(held[:3, 3] - planned[:3, 3]) < 0.005
    assert (
        np.degrees(np.arccos(np.clip((np.trace(held[:3, :3].T @ planned[:3, :3]) - 1) / 2, -1, 1)))
        < 3
    )
    assert grasp_check.held_in_hand(obj, quat, aside)[0] == "missed"
    # A batch a thread: the same outcomes, in the candidates' order, as one batch after another.
    one, two = (grasp_check.CheckConfig(batch=1, threads=k) for k in (1, 2))
    trials = [into_table, best, aside]
    assert check(trials, two) == check(trials, one)
    assert [m.name for m in grasp_check._gripper_source().meshes] == [C.GRIPPER_BODY]


def test_the_poses_of_an_object_checked_together_give_each_pose_its_own_outcomes() -> None:
    # Two resting poses' batches in one pool (each pose's last batch short): each pose gets
    # exactly the outcomes it gets checked alone.
    from grasping import grasp_check
    from grasping.antipodal import antipodal_grasps, hull_points
    from grasping.mesh_grasps import convex_pieces

    obj = load_object("phone")
    hulls, com = convex_pieces(obj)
    points, normals = hull_points(hulls)
    jobs = []
    for pose in ("upright", "up_-y"):
        quat = obj.resting_poses[pose]
        found = antipodal_grasps(points, normals, quat_to_mat(quat)[2], com)
        aside = found[0].T_O_G.copy()
        aside[:3, 3] += 0.2 * aside[:3, 2]
        jobs.append((quat, [found[0].T_O_G, aside, found[-1].T_O_G]))
    cfg = grasp_check.CheckConfig(batch=2, threads=2)
    together = grasp_check.check_grasps_in_poses(obj, jobs, cfg)
    assert together == [grasp_check.check_grasps_in_poses(obj, [j], cfg)[0] for j in jobs]
    assert [o[1] for o in together] == ["missed", "missed"]


def test_an_object_of_many_resting_poses_checks_fewer_grasps_in_each() -> None:
    # Up to CHECK_BUDGET / CHECKED poses, each checks CHECKED; beyond, the budget is shared,
    # never below KEEP a pose (so every grasp that holds can be kept).
    few = CHECK_BUDGET // CHECKED
    assert [checks_per_pose(n) for n in (1, few)] == [CHECKED, CHECKED]
    assert checks_per_pose(few + 1) < CHECKED
    last = CHECKED
    for n in range(few + 1, 40):
        per = checks_per_pose(n)
        assert KEEP <= per <= last and (per == KEEP or per * n < CHECK_BUDGET + n)
        last = per
    assert checks_per_pose(13) == KEEP
