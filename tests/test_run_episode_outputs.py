"""What `python -m sim.run_episode` shows of what the estimator saw: the sensor's depth image
(metric 16-bit PNG and a coloured view with its scale) under ``--out``, the sensor in the
summary, and one note when a depth sensor's depth goes unused."""

from __future__ import annotations

import pytest

from posegrasp.core.errors import UnknownNameError
from posegrasp.world.sensors import SENSOR_NAMES
from sim.estimators import depth_unused_note


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
