"""The pictures: an episode's grasp strip and a report's plot of success against pose error."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from posegrasp.world import constants as C
from sim import run_episode
from sim.episodes.episode import Episode
from sim.episodes.pose_noise import parse_noise
from sim.episodes.registry import NoisyOracleEstimator, OracleEstimator

FINGERS = np.array([3, 4])


def _commands(segments: list[tuple[int, bool, bool]]) -> np.ndarray:
    """Commands (N, 5) of frames in segments of (frames, arm moving, fingers shut)."""
    rows, arm = [], np.zeros(3)
    for count, moving, shut in segments:
        for _ in range(count):
            if moving:
                arm = arm + 0.01
            rows.append([*arm, *([0.0, 0.0] if shut else [C.FINGER_TRAVEL] * 2)])
    return np.array(rows)


def test_stages_follow_the_executors_commands() -> None:
    # transit (moving), pre-grasp pause, approach (moving), settle, close, lift, hold
    ctrl = _commands(
        [
            *[(6, True, False), (2, False, False), (3, True, False), (3, False, False)],
            *[(4, False, True), (5, True, True), (4, False, True)],
        ]
    )
    stages = run_episode.label_stages(ctrl, FINGERS)
    # The first still frame of a pause is the one after the last move: its arm command equals
    # the one beforun_episode.
    assert stages == (
        ["transit"] * 8 + ["approach"] * 6 + ["close"] * 4 + ["lift"] * 5 + ["hold"] * 4
    )
    assert run_episode.strip_frames(stages) == [7, 13, 17, 20, 26]


def test_a_missed_grasp_ends_with_the_close_and_no_approach_move_is_one_pause() -> None:
    ctrl = _commands([(5, True, False), (5, False, False), (4, False, True)])
    stages = run_episode.label_stages(ctrl, FINGERS)
    assert stages == ["transit"] * 5 + ["approach"] * 5 + ["close"] * 4
    assert [stages[i] for i in run_episode.strip_frames(stages)] == ["transit", "approach", "close"]
    assert run_episode.label_stages(np.zeros((0, 5)), FINGERS) == []


def test_the_close_up_frames_its_points_about_the_centre() -> None:
    rng = np.random.default_rng(0)
    points = rng.uniform([0.4, -0.2, 0.7], [0.7, 0.1, 1.0], (12, 3))
    forward = np.array([-0.85, 0.52, -0.3])
    fovy = 55.0
    pos, R = run_episode.close_up_pose(points, forward, fovy)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    # MuJoCo's camera looks along its -z: project with a pinhole of that field of view.
    f = 1 / math.tan(math.radians(fovy) / 2)  # in units of the half height
    cam = (points - pos) @ R
    depth = -cam[:, 2]
    assert (depth > 0).all()
    uv = f * cam[:, :2] / depth[:, None]
    assert np.abs(uv).max() < 1.0  # all inside the view (square or wider)
    centre = (points.min(0) + points.max(0)) / 2
    c = (centre - pos) @ R
    np.testing.assert_allclose(c[:2], 0.0, atol=1e-12)  # the centre is on the axis
    assert np.abs(uv).max() > 0.5 * run_episode.CLOSE_UP_FILL  # close: the points fill the view


def _film(estimator, seed: int = C.EVAL_SEED_BASE) -> tuple[run_episode.Film, Episode, object]:
    ep = Episode("phone", seed)
    film = run_episode.Film()
    _, result = ep.run(estimator, film)
    return film, ep, result


def test_a_real_grasp_goes_through_the_stages_in_order() -> None:
    film, ep, result = _film(OracleEstimator())
    try:
        assert result.success
        model = ep.scene.model
        stages = run_episode.label_stages(
            np.array([s.ctrl for s in film.snapshots]), run_episode.finger_actuators(model)
        )
        order = [run_episode.STAGES.index(s) for s in stages]
        assert order == sorted(order) and set(stages) == set(run_episode.STAGES)
        # What the stages mean, measured in the recorded states: the gripper comes down in the
        # approach, the object rises in the lift and stays up in the hold.
        data = mujoco.MjData(model)
        target, gripper = model.body(ep.scene.target.body).id, model.body(C.GRIPPER_BODY).id

        def heights(i: int) -> tuple[float, float]:
            data.qpos[:] = film.snapshots[i].qpos
            mujoco.mj_kinematics(model, data)
            return float(data.xpos[gripper][2]), float(data.xpos[target][2])

        last = {s: max(i for i, t in enumerate(stages) if t == s) for s in run_episode.STAGES}
        assert heights(last["approach"])[0] < heights(last["transit"])[0]
        assert heights(last["hold"])[1] > heights(last["close"])[1] + 0.1
        strip = run_episode.grasp_strip(model, film, ep.scene.target.body, result)
    finally:
        ep.close()
    w, h = C.EXTERNAL_SIZE
    assert strip is not None and strip.shape == (h, 5 * w, 3)
    band = strip[-20:, -w:].reshape(-1, 3).mean(0)  # the outcome under the last frame
    assert band[1] > band[0] + 40  # green: held


def test_a_failed_grasp_says_so_in_red() -> None:
    film, ep, result = _film(NoisyOracleEstimator(parse_noise("0,0,60,0")))
    try:
        assert not result.success
        strip = run_episode.grasp_strip(ep.scene.model, film, ep.scene.target.body, result)
    finally:
        ep.close()
    assert run_episode.outcome_text(result) == f"failed: {result.failure_reason}"
    w = C.EXTERNAL_SIZE[0]
    band = strip[-20:, -w:].reshape(-1, 3).mean(0)
    assert band[0] > band[1] + 40  # red: failed


def test_the_plot_draws_only_the_reports_objects_with_the_legend_below(
    monkeypatch, tmp_path
) -> None:
    import matplotlib.pyplot as plt

    from sim import evaluation

    def episode(obj: str, ok: bool, err: float) -> dict:
        e = {"translation_m": 0.0}
        for key, scale, _ in evaluation.COMPONENTS.values():
            e[key] = err / scale
        return {"object": obj, "success": ok, "pose_error": e}

    report = {
        "estimator": "noisy-oracle",
        "episodes": [episode("phone", True, 3.0), episode("car", False, 25.0)],
    }
    curve = {"levels": [0.0, 10.0, 20.0], "success_rate": [1.0, 0.8, 0.2]}
    tolerance = {
        obj: dict.fromkeys(evaluation.COMPONENTS, curve) for obj in ("phone", "car", "chair")
    }
    figures = []
    monkeypatch.setattr(plt, "close", figures.append)
    evaluation.plot_success_vs_error(report, tmp_path / "p.png", tolerance)
    (fig,) = figures
    assert (tmp_path / "p.png").stat().st_size > 10_000
    assert all(ax.get_legend() is None for ax in fig.axes)
    (legend,) = fig.legends
    labels = [t.get_text() for t in legend.get_texts()]
    assert [x for x in labels if x.endswith("alone")] == [
        "car: true pose + this error alone",
        "phone: true pose + this error alone",
    ]
    assert not any("chair" in x or "(alone)" in x for x in labels)
    fig.canvas.draw()
    box = legend.get_window_extent()
    assert all(box.y1 <= ax.get_window_extent().y0 for ax in fig.axes)  # below the panels
    curves = [ln for ln in fig.axes[0].get_lines() if ln.get_label().endswith("alone")]
    colours = {ln.get_label(): ln.get_color() for ln in curves}
    assert len(curves) == 2 and len(set(colours.values())) == 2
    for ax in fig.axes[1:]:  # one colour per object in every panel
        for ln in ax.get_lines():
            if ln.get_label() in colours:
                assert ln.get_color() == colours[ln.get_label()]
    plt.close(fig)
