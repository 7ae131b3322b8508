"""The place task: goals drawn from the seed, the set-down planned on the robot's belief of the
object in its hand, and where the object rests scored against its goal."""

from __future__ import annotations

import math

import numpy as np
import pytest

from grasping.place import PlaceConfig, held_transform, predicted_hold, set_down_pose
from perception.metrics import rotation_error_deg
from posegrasp.core.errors import InvalidArgumentError, UnknownNameError
from posegrasp.world.goals import GoalConfig, draw_goal, footprint, table_top_bounds
from posegrasp.world.scene import SceneConfig, build_scene
from posegrasp.world.tiers import tier_scene
from sim.episodes.episode import PLACE_TOLERANCE, EpisodeConfig, play_episode
from sim.episodes.registry import make_estimator


@pytest.mark.parametrize("tier", ["isolated", "clutter"])
def test_a_goal_is_the_resting_pose_moved_and_turned_clear_of_the_others(tier: str) -> None:
    scene = build_scene("pistol", 1000000003, tier_scene(tier, SceneConfig()))
    goal = draw_goal(scene)
    again = draw_goal(build_scene("pistol", 1000000003, tier_scene(tier, SceneConfig())))
    assert np.array_equal(goal.T_world_O, again.T_world_O)  # from the seed alone
    T0 = scene.object_pose()
    # Turned about the vertical only: the same face down, at the same height.
    assert abs(goal.T_world_O[2, 3] - T0[2, 3]) < 1e-12
    assert abs((goal.T_world_O[:3, :3] @ T0[:3, :3].T)[2, 2] - 1) < 1e-9
    turn = rotation_error_deg(goal.T_world_O[:3, :3], T0[:3, :3])
    assert math.isclose(turn, abs(goal.turned_deg), abs_tol=1e-6)
    moved = float(np.linalg.norm(goal.T_world_O[:2, 3] - T0[:2, 3]))
    assert math.isclose(moved, goal.moved_m, abs_tol=1e-9)
    xy = footprint(np.asarray(scene.target.model.mesh.vertices), goal.T_world_O)
    lo, hi = table_top_bounds(scene)
    assert (xy > lo).all() and (xy < hi).all()
    for o in scene.objects[1:]:
        other = footprint(np.asarray(o.model.mesh.vertices), scene.object_pose(o.body))
        gap = np.linalg.norm(xy[:, None] - other[None], axis=2).min()
        assert gap >= goal.clearance_m - 1e-9


def test_the_set_down_puts_the_believed_object_on_the_goal() -> None:
    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    T_G = np.eye(4)
    T_G[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T_G[:3, 3] = [0.6, 0.1, 0.8]
    T_O = np.eye(4)
    T_O[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T_O[:3, 3] = [0.62, 0.08, 0.75]
    T_G_O = held_transform(T_G, T_O)
    goal = np.eye(4)
    goal[:3, 3] = [0.7, -0.1, 0.6]
    T_set = set_down_pose(goal, T_G_O, 0.01)
    believed = T_set @ T_G_O
    assert np.allclose(believed[:3, :3], goal[:3, :3]) and np.allclose(
        believed[:3, 3], goal[:3, 3] + [0, 0, 0.01]
    )


def test_bad_task_and_belief_names_are_one_line_errors() -> None:
    with pytest.raises(UnknownNameError, match="lift, place"):
        EpisodeConfig(task="stack")
    with pytest.raises(UnknownNameError, match="predicted, estimate, truth"):
        PlaceConfig(belief="guess")
    with pytest.raises(InvalidArgumentError, match=r"GoalConfig\.distance"):
        GoalConfig(distance=(0.2, 0.1))


def test_the_oracle_places_and_its_lift_is_the_lift_tasks() -> None:
    oracle = make_estimator("oracle")
    lift = play_episode("phone", 1000000000, oracle, EpisodeConfig())
    place = play_episode("phone", 1000000000, oracle, EpisodeConfig(task="place"))
    assert lift.success and lift.place is None and "place" not in lift.to_json()
    assert place.success and place.failure_reason is None and place.place is not None
    errors = place.place["errors"]
    assert errors["translation_m"] < PLACE_TOLERANCE[0] / 4
    assert errors["rotation_deg"] < PLACE_TOLERANCE[1] / 4
    assert place.place["goal"]["moved_m"] >= GoalConfig().distance[0]
    # The same grasp as the lift task's, up to the lift.
    assert place.grasp_part == lift.grasp_part
    assert place.lift_height == lift.lift_height
    assert place.timings_ms.keys() > {"exec_carry", "exec_set_down", "exec_release"}


@pytest.mark.parametrize("task", ["lift", "place"])
def test_a_pose_turned_about_the_vertical_is_lifted_but_not_placed(task: str) -> None:
    """An estimate of the car turned 30 degrees about the vertical still lifts it (the fingers
    close across it), but the robot sets it down turned by about as much: off target."""
    from sim.episodes.episode import Episode

    ep = Episode("car", 1000000000, EpisodeConfig(task=task))
    try:
        c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
        T_world_O = ep.T_world_cam @ ep.T_C_O_true
        T_world_O[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ T_world_O[:3, :3]
        res = ep.act(np.linalg.inv(ep.T_world_cam) @ T_world_O, "turned")
    finally:
        ep.close()
    if task == "lift":
        assert res.success
        return
    assert res.place is not None and not res.success and res.failure_reason == "off_target"
    assert res.place["errors"]["rotation_deg"] > PLACE_TOLERANCE[1]


def test_a_protocol_carries_the_place_belief_and_records_it_apart() -> None:
    from sim.evaluation import Protocol

    truth = Protocol(["phone"], 1, task="place", belief="truth")
    assert truth.episode_config().place.belief == "truth"
    assert truth.recorded_apart() == {"task": "place", "belief": "truth"}
    scored = Protocol(["phone"], 1, task="place")
    assert scored.recorded_apart() == {"task": "place", "belief": "predicted"}
    # Records without a belief were placed on the grasp-time estimate, and read so.
    assert "belief" not in Protocol(["phone"], 1, task="place", belief="estimate").recorded_apart()
    assert Protocol(["phone"], 1).recorded_apart() == {}  # a lift has no belief
    with pytest.raises(UnknownNameError, match="predicted, estimate, truth"):
        Protocol(["phone"], 1, task="place", belief="guess")


def test_the_predicted_belief_is_the_belief_moved_as_the_check_moved_the_object() -> None:
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(1)

    def pose(spread: float) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(rng.normal(0, spread, 3)).as_matrix()
        T[:3, 3] = rng.normal(0, 0.02, 3)
        return T

    T_O_G, held, error = pose(1.0), pose(0.3), pose(0.05)
    planned = np.linalg.inv(T_O_G)
    # Believed where the check's hand held it: where the check left it.
    assert np.allclose(predicted_hold(planned, T_O_G, held), held)
    # Believed off by an error in the hand's frame: the check's motion applied to that belief.
    moved = predicted_hold(error @ planned, T_O_G, held)
    assert np.allclose(moved, held @ T_O_G @ error @ planned)
    assert np.allclose(moved @ np.linalg.inv(error @ planned), held @ T_O_G)


def test_the_predicted_belief_places_an_object_the_grasp_turns_in_the_hand() -> None:
    """Lying on its side, the screen is taken by its base, far from its centre of mass, and
    turns in the fingers as the arm lifts it: placed on the pose at grasp time it lands off
    target; on that pose moved as the grasp's physics check predicts, on target."""
    oracle = make_estimator("oracle")

    def play(belief: str):
        cfg = EpisodeConfig(tier="any-pose", task="place", place=PlaceConfig(belief=belief))
        return play_episode("screen", 500000003, oracle, cfg)

    grasp_time, predicted = play("estimate"), play("predicted")
    assert grasp_time.grasp_part == predicted.grasp_part == "base"
    assert grasp_time.lift_height == predicted.lift_height  # the same lift
    assert grasp_time.failure_reason == "off_target"
    assert grasp_time.place is not None and predicted.place is not None
    assert grasp_time.place["errors"]["translation_m"] > PLACE_TOLERANCE[0]
    assert predicted.success and predicted.timings_ms["place_predict"] > 0
    assert "place_predict" not in grasp_time.timings_ms
