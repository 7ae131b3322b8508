"""The shipped weights end to end on held-out head-camera episodes (real Mask R-CNN, real nets)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from perception.hybrid import HybridPoseEstimator
from perception.training import overlays as estimator_cli
from posegrasp.world import constants as C
from sim.episodes.episode import Episode

pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def shipped() -> HybridPoseEstimator:
    return HybridPoseEstimator.from_weights()


def _rot_err_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1))))


@pytest.mark.parametrize("name", ["phone", "pistol"])
def test_shipped_estimators_on_a_held_out_episode(shipped: HybridPoseEstimator, name: str) -> None:
    ep = Episode(name, C.EVAL_SEED_BASE + 7)
    try:
        obs = ep.observe()
    finally:
        ep.close()
    truth = ep.T_C_O_true
    plain = shipped.as_episode_estimator()
    e = plain.estimate(obs)
    T = e.T_C_O
    assert T is not None and e.info["class"] == name and e.info["score"] > 0.5
    assert np.linalg.norm(T[:3, 3] - truth[:3, 3]) < 0.06
    table = shipped.as_episode_estimator(support=True)
    assert table.name == "hybrid-table"
    et = table.estimate(obs)
    Tt, info = et.T_C_O, et.info["support"]
    assert info["applied"] == ["rotation", "translation", "mask_fit"]
    assert info["mask_iou_after"] >= info["mask_iou_before"] > 0.5
    # The refined pose rests on the table: the model's lowest point is at the table's height.
    model = ep.scene.target.model
    pts_w = (obs.T_world_cam @ Tt)[:3, :3] @ np.asarray(model.mesh.vertices).T
    lowest = pts_w[2].min() + (obs.T_world_cam @ Tt)[2, 3]
    assert lowest == pytest.approx(obs.table_top_z, abs=1e-6)
    assert np.linalg.norm(Tt[:3, 3] - truth[:3, 3]) < 0.02
    assert _rot_err_deg(Tt[:3, :3], truth[:3, :3]) < 10.0


def test_estimator_cli_on_an_image_file(tmp_path, capsys) -> None:
    ep = Episode("car", C.EVAL_SEED_BASE + 3)
    try:
        obs = ep.observe()
    finally:
        ep.close()
    img = tmp_path / "head.png"
    cv2.imwrite(str(img), obs.rgb[..., ::-1])
    K = obs.K
    argv = [
        "--image",
        str(img),
        "--K",
        f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}",
        "--save",
        str(tmp_path / "out"),
    ]
    assert estimator_cli.main(argv) == 0
    assert "car" in capsys.readouterr().out
    drawn = cv2.imread(str(tmp_path / "out" / "head.png"))
    assert (
        drawn.shape == (480, 640, 3) and np.abs(drawn[..., ::-1].astype(int) - obs.rgb).max() > 100
    )
    assert estimator_cli.main(["--image", str(img), "--save", str(tmp_path / "o")]) == 2
    assert "--K fx,fy,cx,cy" in capsys.readouterr().err
