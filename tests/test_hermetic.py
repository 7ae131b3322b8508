"""The tests never touch a user's objects or data folders."""

from __future__ import annotations

from pathlib import Path

from posegrasp.core.paths import REPO_ROOT, data_root
from posegrasp.world.user_objects import objects_dir, user_object_names


def test_the_user_objects_folder_is_the_tests_own_and_starts_empty():
    home = Path.home() / ".local" / "share" / "posegrasp" / "objects"
    assert objects_dir() != home
    assert "posegrasp-tests-" in str(objects_dir())
    assert user_object_names() == ()


def test_the_data_folder_is_the_tests_own():
    assert data_root() != REPO_ROOT / "data"
    assert data_root() == REPO_ROOT / ".test-data"
