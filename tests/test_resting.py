"""Resting poses found by physics (`posegrasp.world.resting`) and the tiers that use them."""

from __future__ import annotations

import numpy as np
import pytest

from posegrasp.core.transforms import quat_to_mat
from posegrasp.world.objects import OBJECT_NAMES, load_object
from posegrasp.world.resting import find_resting_poses, is_stable, main, upright_quat


def test_upright_quat_turns_the_direction_up() -> None:
    for up in ([0, 0, 1], [0, 0, -1], [1, 0, 0], [0.3, -0.5, 0.8]):
        u = np.asarray(up, float) / np.linalg.norm(up)
        R = quat_to_mat(upright_quat(u))
        np.testing.assert_allclose(R @ u, [0, 0, 1], atol=1e-9)


@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_every_listed_resting_pose_is_stable(name: str) -> None:
    """Placed on a plane and left alone for a second, at four yaws, each pose stays put."""
    for pose, quat in load_object(name).resting_poses.items():
        assert is_stable(name, quat), f"{name} {pose}"


def test_a_pose_balanced_on_an_edge_is_not_stable() -> None:
    # The phone on one corner of its base: up along the base's diagonal.
    up = np.array([1.0, 1.0, 1.0]) / np.sqrt(3)
    assert not is_stable("phone", upright_quat(up))


def test_drops_find_the_listed_poses() -> None:
    """A fresh set of drops (another seed) finds the car's four resting poses again, each
    within 8 degrees of the listed one."""
    obj = load_object("car")
    found = find_resting_poses("car", drops=48, seed=7)
    listed = [quat_to_mat(q)[2] for q in obj.resting_poses.values()]
    for p in found:
        assert max(float(p.up @ u) for u in listed) > np.cos(np.deg2rad(8.0))
    assert len(found) == len(listed)
    assert sum(p.share for p in found) <= 1.0


def test_bad_arguments_are_one_line(capsys) -> None:
    assert main(["--object", "teapot"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "valid objects" in err
    assert main(["--drops", "0"]) == 2
    assert "1..4096" in capsys.readouterr().err
