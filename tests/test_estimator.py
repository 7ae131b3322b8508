"""The hybrid estimator end to end (random weights): detections, crops, nets, exact decoding."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from perception.crops import crop_and_resize, crop_to_image, from_unit, square_box
from perception.detector_net import DetectorConfig, build_detector, state_dict_fp16
from perception.geometry import decode
from perception.hybrid import (
    DEFAULT_CROP_SCALE,
    STAGES,
    HybridEpisodeEstimator,
    HybridPoseEstimator,
    PoseDetection,
)
from perception.nets import CROP, NetConfig, PoseNet, normalise
from posegrasp.core.contract import Observation
from posegrasp.core.errors import AssetError, InvalidArgumentError, UnknownNameError
from posegrasp.core.paths import WEIGHTS_DIR
from posegrasp.world import constants as C
from posegrasp.world.camera import CameraRenderer, camera_intrinsics
from posegrasp.world.objects import OBJECT_NAMES
from posegrasp.world.scene import SceneConfig, build_scene

pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def head_image() -> tuple[np.ndarray, np.ndarray]:
    """A 640x480 head-camera image of a phone and two distractors, and its K."""
    scene = build_scene("phone", 3, SceneConfig(n_distractors=2))
    with CameraRenderer(scene.model, 640, 480) as r:
        rgb = r.rgb(scene.data, C.HEAD_CAMERA)
    return rgb, camera_intrinsics(scene.model, C.HEAD_CAMERA, 640, 480)


@pytest.fixture(scope="module")
def estimator() -> HybridPoseEstimator:
    return HybridPoseEstimator.with_random_weights(seed=0, max_detections=3)


def test_end_to_end_poses_are_rigid_and_consistent(
    estimator: HybridPoseEstimator, head_image: tuple[np.ndarray, np.ndarray]
) -> None:
    rgb, K = head_image
    found, timings = estimator.estimate_timed(rgb, K)
    assert 1 <= len(found) <= 3
    assert set(timings) == {*STAGES, "total"} and all(v >= 0 for v in timings.values())
    assert timings["total"] == pytest.approx(sum(timings[s] for s in STAGES))
    scores = [d.score for d in found]
    assert scores == sorted(scores, reverse=True)
    for d in found:
        assert isinstance(d, PoseDetection) and d.name in OBJECT_NAMES
        assert d.mask.shape == rgb.shape[:2] and d.mask.dtype == bool
        T = d.T_C_O
        assert T.shape == (4, 4) and np.all(np.isfinite(T))
        np.testing.assert_allclose(T[3], [0, 0, 0, 1], atol=0)
        R = T[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-9)
        assert T[2, 3] > 0
        # The decoded origin projects exactly onto the pixel 2D-NET predicted.
        proj = K @ T[:3, 3]
        np.testing.assert_allclose(proj[:2] / proj[2], d.uv, atol=1e-6)
        # The crop is the centred square of the mean training scale.
        x0, y0, x1, y1 = d.box_xyxy
        side = max(x1 - x0, y1 - y0) * DEFAULT_CROP_SCALE
        np.testing.assert_allclose(d.crop_box[2], side, rtol=1e-9)
        np.testing.assert_allclose(d.crop_box[0] + side / 2, (x0 + x1) / 2, atol=1e-9)
        assert d.timings_ms is timings


def test_batched_nets_match_one_detection_at_a_time(
    estimator: HybridPoseEstimator, head_image: tuple[np.ndarray, np.ndarray]
) -> None:
    """Each pose equals the crop -> net -> decode chain run for that detection alone."""
    rgb, K = head_image
    for d in estimator.estimate(rgb, K):
        box = square_box(d.box_xyxy, scale=DEFAULT_CROP_SCALE)
        crop = torch.from_numpy(crop_and_resize(rgb, box, CROP)[None])
        cls = torch.tensor([OBJECT_NAMES.index(d.name)])
        with torch.no_grad():
            scale = torch.tensor([box[2] / K[0, 0]], dtype=torch.float32)
            out = estimator.posenet(normalise(crop), cls, scale)
        uv = crop_to_image(from_unit(out.uv_unit[0].double().numpy(), CROP), box, CROP)
        T = decode(out.p[0].double().numpy(), float(out.theta[0]), uv, K)
        np.testing.assert_allclose(d.T_C_O, T, atol=1e-5)


def test_nothing_detected_gives_an_empty_list(head_image: tuple[np.ndarray, np.ndarray]) -> None:
    rgb, K = head_image
    est = HybridPoseEstimator.with_random_weights(score_threshold=1.01)
    found, timings = est.estimate_timed(rgb, K)
    assert found == [] and timings["nets"] >= 0
    obs = Observation(rgb, K, np.eye(4), "phone", 0)
    none = est.as_episode_estimator().estimate(obs)
    assert none.T_C_O is None and none.info["detected"] is False


def test_a_wanted_score_lowers_the_bar_for_the_requested_class_alone(head_image) -> None:
    """With `wanted_score`, the requested class's detections need that score and the others
    the detector's threshold, from one detection pass."""
    rgb, K = head_image
    low = HybridPoseEstimator.with_random_weights(seed=0, score_threshold=0.0)
    high = HybridPoseEstimator.with_random_weights(seed=0, score_threshold=1.01)
    found = low.detector.detect(rgb)
    name = found[0].name
    absent = next(n for n in OBJECT_NAMES if n not in {d.name for d in found})
    want, _, _ = low.estimate_split(rgb, K, classes=(name,))
    got, _, _ = high.estimate_split(rgb, K, classes=(name,), wanted_score=0.0)
    assert want and [d.score for d in got] == [d.score for d in want]
    for a, b in zip(got, want, strict=True):
        np.testing.assert_allclose(a.T_C_O, b.T_C_O)
    _, other, _ = low.estimate_split(rgb, K, classes=(absent,), others=True)
    _, rest, _ = high.estimate_split(rgb, K, classes=(absent,), others=True, wanted_score=0.0)
    assert other and rest == []  # the other classes keep the detector's threshold
    assert high.estimate_split(rgb, K, classes=(name,))[0] == []


def test_the_other_detections_may_skip_the_expert(head_image) -> None:
    """Without `others_experts`, the other detections' poses are the main net's alone (as an
    estimator without experts gives them); the requested class's keep the expert's choice."""
    rgb, K = head_image
    base = HybridPoseEstimator.with_random_weights(seed=0, score_threshold=0.0)
    expert = HybridPoseEstimator.with_random_weights(seed=5).posenet
    est = HybridPoseEstimator(base.detector, base.posenet, experts=[expert])
    found = est.detector.detect(rgb)
    name = found[0].name
    absent = next(n for n in OBJECT_NAMES if n not in {d.name for d in found})
    _, fast, _ = est.estimate_split(rgb, K, classes=(absent,), others=True, others_experts=False)
    _, ref, _ = base.estimate_split(rgb, K, classes=(absent,), others=True)
    assert fast and [d.score for d in fast] == [d.score for d in ref]
    for a, b in zip(fast, ref, strict=True):
        np.testing.assert_allclose(a.T_C_O, b.T_C_O)
    kept, _, _ = est.estimate_split(rgb, K, classes=(name,), others=True, others_experts=False)
    full, _, _ = est.estimate_split(rgb, K, classes=(name,), others=True)
    assert kept
    for a, b in zip(kept, full, strict=True):
        np.testing.assert_allclose(a.T_C_O, b.T_C_O)


def test_class_filter(estimator: HybridPoseEstimator, head_image) -> None:
    rgb, K = head_image
    found = estimator.estimate(rgb, K)
    name = found[0].name
    only = estimator.estimate(rgb, K, classes=[name])
    assert only and all(d.name == name for d in only)
    with pytest.raises(UnknownNameError, match="valid objects"):
        estimator.estimate(rgb, K, classes=["teapot"])


def test_episode_estimator(estimator: HybridPoseEstimator, head_image) -> None:
    rgb, K = head_image
    found = estimator.estimate(rgb, K)
    ep = estimator.as_episode_estimator()
    assert isinstance(ep, HybridEpisodeEstimator) and ep.name == "hybrid"
    best = max((d for d in found if d.name == found[0].name), key=lambda d: d.score)
    e = ep.estimate(Observation(rgb, K, np.eye(4), best.name, 0))
    np.testing.assert_allclose(e.T_C_O, best.T_C_O)
    assert e.info["class"] == best.name and e.info["score"] == pytest.approx(best.score)
    others = sorted(d.name for d in found if d.name != best.name)
    assert sorted(n for n, _ in e.neighbours) == others
    missing = next(n for n in OBJECT_NAMES if n not in {d.name for d in found})
    assert ep.estimate(Observation(rgb, K, np.eye(4), missing, 0)).T_C_O is None
    with pytest.raises(UnknownNameError):
        ep.estimate(Observation(rgb, K, np.eye(4), "teapot", 0))


@pytest.mark.parametrize(
    ("rgb", "K", "match"),
    [
        (np.zeros((48, 64, 3), np.float64), np.eye(3), "uint8"),
        (np.zeros((48, 64), np.uint8), np.eye(3), r"\(H, W, 3\)"),
        (np.zeros((0, 64, 3), np.uint8), np.eye(3), "empty"),
        (np.zeros((48, 64, 3), np.uint8), np.eye(4), "K must"),
        (np.zeros((48, 64, 3), np.uint8), np.diag([-1.0, 1.0, 1.0]), "positive focal"),
        (np.zeros((48, 64, 3), np.uint8), np.full((3, 3), np.nan), "finite"),
        (np.zeros((48, 64, 3), np.uint8), "K", "K must"),
    ],
)
def test_bad_inputs(estimator: HybridPoseEstimator, rgb: object, K: object, match: str) -> None:
    with pytest.raises(InvalidArgumentError, match=match):
        estimator.estimate(rgb, K)  # type: ignore[arg-type]


def test_from_weights(tmp_path: Path, head_image) -> None:
    with pytest.raises(AssetError, match="make weights"):
        HybridPoseEstimator.from_weights(tmp_path / "d.pt", tmp_path / "p.pt")
    cfg = DetectorConfig()
    torch.save(
        {"model": state_dict_fp16(build_detector(cfg)), "model_config": cfg.to_dict()},
        tmp_path / "d.pt",
    )
    with pytest.raises(AssetError, match="make weights"):  # the pose nets are still missing
        HybridPoseEstimator.from_weights(tmp_path / "d.pt", tmp_path / "p.pt")
    net = PoseNet(NetConfig())
    torch.save({"model": net.state_dict(), "model_config": net.cfg.to_dict()}, tmp_path / "p.pt")
    est = HybridPoseEstimator.from_weights(tmp_path / "d.pt", tmp_path / "p.pt", 0.0, 1.2, 2)
    rgb, K = head_image
    found = est.estimate(rgb, K)
    assert len(found) == 2 and est.crop_scale == 1.2
    assert all(np.isfinite(d.T_C_O).all() for d in found)
    with pytest.raises(InvalidArgumentError, match="crop_scale"):
        HybridPoseEstimator(est.detector, est.posenet, crop_scale=0.0)


def test_weights_files_are_the_files_the_default_estimator_loads(monkeypatch) -> None:
    """`weights_files` reports exactly the .pt files torch.load opens while the default
    estimator is made."""
    from perception.estimators import load_estimator, weights_files
    from sim.episodes.registry import DEFAULT_ESTIMATOR

    opened: list[Path] = []
    load = torch.load

    def spy(f, *args, **kwargs):
        opened.append(Path(f).resolve())
        return load(f, *args, **kwargs)

    monkeypatch.setattr(torch, "load", spy)
    estimator, reported = load_estimator(DEFAULT_ESTIMATOR)
    assert estimator.name == DEFAULT_ESTIMATOR
    assert [p for p in opened if p.suffix == ".pt"] == list(reported)
    assert WEIGHTS_DIR / "tiers" / "masknet.pt" in reported
    with pytest.raises(UnknownNameError, match="valid learned estimators: hybrid"):
        weights_files("oracle")


def test_a_missing_shipped_file_is_restored_from_git_first() -> None:
    missing = WEIGHTS_DIR / "tiers" / "no_such_detector.pt"
    with pytest.raises(AssetError) as err:
        HybridPoseEstimator.from_weights(detector_path=missing)
    text = str(err.value)
    git = "git checkout -- perception/weights/tiers/no_such_detector.pt"
    assert git in text and "git restore perception/weights/tiers/no_such_detector.pt" in text
    assert text.index(git) < text.index("make weights") and "\n" not in text
