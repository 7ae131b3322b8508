"""Expert pose nets in the hybrid estimator: per detection, the pose whose silhouette agrees best
with the detected mask wins (`perception.overlay.silhouette_agreement`)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from perception.crops import image_to_crop, square_box, to_unit
from perception.detector import Detection
from perception.geometry import encode
from perception.hybrid import DEFAULT_CROP_SCALE, SWITCH_IOU, HybridPoseEstimator
from perception.nets import CROP, NetConfig, PoseNet, PoseOutput
from perception.overlay import silhouette, silhouette_agreement
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.world.objects import OBJECT_NAMES, load_object

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
SHAPE = (480, 640)


def _pose(yaw_deg: float = 0.0, x: float = 0.0) -> np.ndarray:
    """The object 0.6 m in front of the camera, seen from above at an angle."""
    a, b = np.deg2rad(yaw_deg), np.deg2rad(120.0)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    Rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    T = np.eye(4)
    T[:3, :3] = Rx @ Rz
    T[:3, 3] = [x, 0.0, 0.6]
    return T


def _mask(name: str, T: np.ndarray) -> np.ndarray:
    mesh = load_object(name).mesh
    return silhouette(T, K, np.asarray(mesh.vertices), np.asarray(mesh.faces), SHAPE)


def test_agreement_ranks_the_true_pose_first_and_ignores_hidden_pixels() -> None:
    T = _pose()
    mask = _mask("phone", T)
    iou = silhouette_agreement("phone", [T, _pose(x=0.02), _pose(yaw_deg=60)], K, mask, [])
    assert iou[0] == pytest.approx(1.0)
    assert iou[1] < 0.9 and iou[2] < 0.9
    # A neighbour hides the left half: the hidden pixels count for neither pose.
    cols = np.nonzero(mask.any(axis=0))[0]
    hider = np.zeros(SHAPE, bool)
    hider[:, : (cols.min() + cols.max()) // 2] = True
    hidden_iou = silhouette_agreement("phone", [T], K, mask & ~hider, [hider])
    assert hidden_iou[0] == pytest.approx(1.0)
    assert silhouette_agreement("phone", [T], K, mask & ~hider, [])[0] < 0.8
    assert silhouette_agreement("phone", [T], K, np.zeros(SHAPE, bool), [])[0] == 0.0


class _FixedNet(PoseNet):
    """A pose net that answers every crop with the encoding of one pose (for a known box)."""

    def __init__(self, T: np.ndarray, box: tuple[float, float, float]) -> None:
        super().__init__(NetConfig(n_classes=len(OBJECT_NAMES)))
        p, theta, uv = encode(T, K)
        self.out = (
            torch.tensor(to_unit(image_to_crop(uv, box, CROP), CROP), dtype=torch.float32),
            torch.tensor(p, dtype=torch.float32),
            torch.tensor([np.cos(theta), np.sin(theta)], dtype=torch.float32),
        )

    def forward(self, x, cls, size) -> PoseOutput:
        n = len(x)
        return PoseOutput(*(t.expand(n, -1) for t in self.out))


class _OneDetection:
    def __init__(self, det: Detection) -> None:
        self.det = det

    def detect(self, rgb: np.ndarray) -> list[Detection]:
        return [self.det]


@pytest.fixture(scope="module")
def scene() -> tuple[Detection, tuple[float, float, float], np.ndarray]:
    T = _pose(yaw_deg=20)
    mask = _mask("phone", T)
    ys, xs = np.nonzero(mask)
    det = Detection("phone", 0.9, np.array([xs.min(), ys.min(), xs.max(), ys.max()], float), mask)
    return det, square_box(det.box_xyxy, scale=DEFAULT_CROP_SCALE), T


def _estimate(det: Detection, main: PoseNet, experts: list[PoseNet]) -> np.ndarray:
    est = HybridPoseEstimator(_OneDetection(det), main, experts=experts)  # type: ignore[arg-type]
    (found,) = est.estimate(np.zeros((*SHAPE, 3), np.uint8), K)
    return found.T_C_O


def test_an_expert_replaces_the_main_pose_only_when_its_silhouette_agrees_better(scene) -> None:
    det, box, T = scene
    right, wrong = _FixedNet(T, box), _FixedNet(_pose(yaw_deg=110), box)
    np.testing.assert_allclose(_estimate(det, wrong, [right]), T, atol=1e-4)
    np.testing.assert_allclose(_estimate(det, right, [wrong]), T, atol=1e-4)
    # Without experts the main net's pose stands, right or wrong.
    assert not np.allclose(_estimate(det, wrong, []), T, atol=1e-2)
    # A nearly equal expert does not replace the main net (the switch needs SWITCH_IOU more).
    near = _pose(yaw_deg=21)
    iou = silhouette_agreement("phone", [near, T], K, det.mask, [])
    assert iou[1] - iou[0] < SWITCH_IOU
    np.testing.assert_allclose(
        _estimate(det, _FixedNet(near, box), [_FixedNet(T, box)]), near, atol=1e-4
    )


def test_experts_must_share_the_classes(scene) -> None:
    det, box, T = scene
    other = PoseNet(NetConfig(n_classes=3))
    with pytest.raises(InvalidArgumentError, match="same classes"):
        HybridPoseEstimator(_OneDetection(det), _FixedNet(T, box), experts=[other])  # type: ignore[arg-type]
