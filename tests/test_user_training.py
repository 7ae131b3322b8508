"""Training on user objects, the documented command chain at a smoke size: render head-camera
data with a user object as the target, fine-tune the shipped detector with its class heads widened
for it, export into the user objects directory, and run ``hybrid-global-user`` on an episode."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from perception.detector import Detector
from perception.detector_net import DetectorConfig
from perception.training.datagen import main as datagen
from perception.training.train_detector import main as train_detector
from posegrasp.core.paths import WEIGHTS_DIR
from posegrasp.world.objects import OBJECT_NAMES
from posegrasp.world.user_objects import OBJECTS_ENV
from sim.add_object import main as add_object


def test_a_widened_config_keeps_the_built_in_labels() -> None:
    cfg = DetectorConfig().widened(["box", "phone", "can"])
    assert cfg.classes == (*OBJECT_NAMES, "box", "can") and cfg.n_classes == 9
    with pytest.raises(ValueError, match="distinct names"):
        DetectorConfig(n_classes=3, classes=("car", "car"))


@pytest.mark.slow
def test_the_chain_trains_a_detector_for_a_user_object(tmp_path, monkeypatch, capsys) -> None:
    objects, data = tmp_path / "objects", tmp_path / "data"
    monkeypatch.setenv(OBJECTS_ENV, str(objects))
    monkeypatch.setenv("POSEGRASP_DATA", str(data))
    mesh = tmp_path / "box.stl"
    trimesh.creation.box(extents=[0.06, 0.04, 0.05]).export(mesh)
    assert add_object([str(mesh), "--name", "box", "--units", "m"]) == 0

    out = data / "user"
    for split, count in (("train", 6), ("val", 2)):
        argv = ["--dist", "headcam", "--objects", "box", "--split", split]
        assert datagen([*argv, "--count", str(count), "--out", str(out), "--quiet"]) == 0
    info = json.loads((out / "info.json").read_text())
    assert info["objects"]["7"] == "box"
    assert (out / "models" / "obj_000007.ply").is_file()

    shipped = WEIGHTS_DIR / "detector.pt"
    # Without --objects the detector has no class for the box: refused, not trained blind.
    blind = ["--smoke", "--init", str(shipped), "--data", str(out), "--out", str(tmp_path / "b")]
    assert train_detector(blind) == 2
    assert "give --objects box" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()
    argv = ["--smoke", "--objects", "box", "--init", str(shipped), "--data", str(out)]
    argv += ["--out", str(tmp_path / "ckpt"), "--export", "--weights-out", str(objects)]
    assert train_detector(argv) == 0
    widened = Detector.from_weights(objects / "detector.pt")
    assert widened.cfg.classes == (*OBJECT_NAMES, "box")
    # The command the weights record runs this again: the widened classes included.
    recorded = json.loads((objects / "manifest.json").read_text())["detector"]["command"]
    assert "--objects box" in recorded
    key = "roi_heads.box_predictor.cls_score.weight"
    assert widened.model.state_dict()[key].shape[0] == len(OBJECT_NAMES) + 2
    parent = Detector.from_weights(shipped).model.state_dict()[key]
    assert parent.shape[0] == len(OBJECT_NAMES) + 1

    from sim.episodes.episode import play_episode
    from sim.episodes.registry import make_estimator

    r = play_episode("box", 1_000_000_000, make_estimator("hybrid-global-user"))
    assert r.estimator == "hybrid-global-user"
    # The user path ran (no accuracy is asked of two smoke steps): the widened detector looked
    # for the box, and the episode ended in an outcome instead of raising.
    assert "detected" in r.estimate_info and r.estimate_info["timings_ms"]["detect"] > 0
    phone = play_episode("phone", 1_000_000_000, make_estimator("hybrid-global-user"))
    assert phone.pose_error is not None and np.isfinite(phone.pose_error["rotation_deg"])


def test_without_a_user_detector_the_estimator_says_how_to_train_one(tmp_path, monkeypatch):
    from posegrasp.core.errors import AssetError
    from sim.episodes.registry import make_estimator

    monkeypatch.setenv(OBJECTS_ENV, str(tmp_path))
    with pytest.raises(AssetError, match="train_detector --objects"):
        make_estimator("hybrid-global-user")
