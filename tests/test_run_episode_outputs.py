"""What `python -m sim.run_episode` shows of what the estimator saw: the sensor's depth image
(metric 16-bit PNG and a coloured view with its scale) under ``--out``, the sensor in the
summary, and one note when a depth sensor's depth goes unused."""

from __future__ import annotations

import io
from pathlib import Path

import cv2
import numpy as np
import pytest

from posegrasp.core.contract import Estimate, Observation
from posegrasp.core.errors import UnknownNameError
from posegrasp.world.sensors import SENSOR_NAMES
from sim import render_scene, run_episode
from sim.episodes.episode import EpisodeResult
from sim.episodes.registry import depth_unused_note

SEED = 1_000_000_002


@pytest.mark.parametrize("sensor", SENSOR_NAMES)
def test_the_depth_goes_unused_only_for_a_depth_model_without_depth(sensor: str) -> None:
    depth_model = sensor.split("+")[0]
    assert depth_unused_note("rgbd", sensor) is None
    note = depth_unused_note("rgb", sensor)
    if depth_model == "ideal":
        assert note is None
    else:
        assert note is not None and note.startswith("note: ") and "\n" not in note
        assert sensor in note and "--obs-mode rgbd" in note


def test_the_note_refuses_an_unknown_sensor_or_mode() -> None:
    with pytest.raises(UnknownNameError, match="valid sensors: ideal, kinect-v1"):
        depth_unused_note("rgb", "lidar")
    with pytest.raises(UnknownNameError, match="valid observation modes: rgb, rgbd"):
        depth_unused_note("depth", "kinect-v1")


class _Seeing:
    """An estimator that keeps every observation it is handed and answers no pose (so no grasp
    is executed and the episode is quick)."""

    name = "seeing"

    def __init__(self) -> None:
        self.seen: list[Observation] = []

    def estimate(self, obs: Observation) -> Estimate:
        self.seen.append(obs)
        return Estimate(None)


def _depth_run(folder: Path, obs_mode: str, sensor: str) -> tuple[Observation, str]:
    """Play an episode saving into `folder`: the observation the estimator was handed and what
    was printed."""
    seeing, log = _Seeing(), io.StringIO()
    run_episode._run("phone", SEED, seeing, folder, log=log, obs_mode=obs_mode, sensor=sensor)
    (obs,) = seeing.seen
    return obs, log.getvalue()


def _png16(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None and img.dtype == np.uint16 and img.ndim == 2
    return img


def test_out_writes_the_depth_the_estimator_saw_and_says_whether_it_saw_it(tmp_path) -> None:
    sensor = "kinect-v1"
    metric, view = run_episode.depth_names(sensor)
    assert sensor in metric and sensor in view
    obs, log = _depth_run(tmp_path / "rgbd", "rgbd", sensor)
    written = _png16(tmp_path / "rgbd" / metric)
    # Millimetres of the very image the estimator was handed, its holes 0.
    assert obs.depth is not None and written.shape == obs.depth.shape
    holes = obs.depth == 0
    assert holes.any() and (written[holes] == 0).all()
    mm = np.rint(obs.depth[~holes] * 1000.0)
    np.testing.assert_array_equal(written[~holes], mm.astype(np.uint16))
    assert f"the depth of sensor {sensor}, seen by the estimator" in log
    # Observing colour only, the episode still writes its sensor's depth, the same image, and
    # says the estimator was not given it.
    obs_rgb, log_rgb = _depth_run(tmp_path / "rgb", "rgb", sensor)
    assert obs_rgb.depth is None
    np.testing.assert_array_equal(_png16(tmp_path / "rgb" / metric), written)
    assert "not given to the estimator (--obs-mode rgb)" in log_rgb
    coloured = cv2.imread(str(tmp_path / "rgb" / view))
    assert coloured is not None and coloured.shape[2] == 3
    h, w = written.shape
    assert coloured.shape[:2] == (h + render_scene.CAPTION_H, w + render_scene.SCALE_W)
    assert coloured[render_scene.CAPTION_H :, :w].std() > 10  # the depth in colour


def test_a_depth_view_colours_near_and_far_apart_and_holes_apart_from_both() -> None:
    mm = np.full((40, 60), 800, np.uint16)
    mm[:, 30:] = 2000
    mm[:5, :5] = 0
    view = render_scene.depth_view(mm, "test")
    body = view[render_scene.CAPTION_H :, :60].astype(int)
    near, far, hole = body[20, 10], body[20, 50], body[2, 2]
    assert np.abs(near - far).sum() > 100
    assert tuple(hole) == render_scene.NO_READING_RGB
    assert tuple(near) != render_scene.NO_READING_RGB and tuple(far) != render_scene.NO_READING_RGB


def test_depth_in_millimetres_has_no_reading_where_nothing_was_measured() -> None:
    depth = np.array([[0.8004, 0.0, np.nan], [2.5, 70.0, 9.995]], np.float32)
    got = render_scene.depth_to_mm(depth, far_m=10.0)
    np.testing.assert_array_equal(got, [[800, 0, 0], [2500, 0, 0]])


def test_the_summary_names_the_sensor_even_the_ideal_one() -> None:
    result = EpisodeResult(
        "phone",
        SEED,
        "oracle",
        "isolated",
        False,
        "no_estimate",
        np.eye(4),
        None,
        None,
        0.0,
        None,
        {"total": 1.0},
    )
    assert "tier=isolated  sensor=ideal" in run_episode.summary(result).splitlines()[0]


class _Started(Exception):
    """Raised by a stub in place of the episode."""


def _stub(*args, **kwargs):
    raise _Started


@pytest.mark.parametrize(
    ("obs_mode", "sensor", "noted"),
    [
        ("rgb", "kinect-v1", True),
        ("rgb", "azure-tof+camera", True),
        ("rgbd", "kinect-v1", False),
        ("rgb", "ideal+camera", False),
    ],
)
def test_run_episode_notes_once_that_a_depth_sensor_goes_unused(
    obs_mode, sensor, noted, monkeypatch, capsys
) -> None:
    monkeypatch.setattr(run_episode, "_run", _stub)
    argv = ["--estimator", "oracle", "--obs-mode", obs_mode, "--sensor", sensor]
    with pytest.raises(_Started):
        run_episode.main(argv)
    notes = [x for x in capsys.readouterr().err.splitlines() if x.startswith("note: ")]
    assert notes == ([depth_unused_note(obs_mode, sensor)] if noted else [])
