"""The render-and-compare refiner (perception/refine.py) and its estimator ``hybrid-refine``."""

from __future__ import annotations

import numpy as np
import pytest

from perception.metrics import mask_iou, rotation_error_deg
from perception.overlay import silhouette
from perception.refine import PoseRefiner, RefineConfig
from posegrasp.core.errors import InvalidArgumentError, PosegraspError, UnknownNameError
from posegrasp.core.transforms import axis_angle, intrinsics, rot_x, rot_z
from posegrasp.world.objects import load_object

K = intrinsics(np.radians(50.0), 640, 480)


def true_pose(yaw_deg: float = 30.0) -> np.ndarray:
    """An object 0.8 m ahead, slightly off the image centre, seen from above at 40 deg."""
    T = np.eye(4)
    T[:3, :3] = rot_x(np.radians(-130.0)) @ rot_z(np.radians(yaw_deg))
    T[:3, 3] = (0.03, 0.02, 0.8)
    return T


def perturbed(T: np.ndarray, deg: float = 3.0, shift_m: float = 0.006, seed: int = 0) -> np.ndarray:
    """T turned by `deg` about a random axis through its origin and moved by `shift_m`."""
    rng = np.random.default_rng(seed)
    out = T.copy()
    out[:3, :3] = axis_angle(rng.normal(size=3), np.radians(deg)) @ T[:3, :3]
    d = rng.normal(size=3)
    out[:3, 3] += shift_m * d / np.linalg.norm(d)
    return out


def render(name: str, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The object's silhouette at T and a flat two-colour image of it, (480, 640): rendered at 4x
    the resolution, a pixel is in when most of it is covered."""
    mesh = load_object(name).mesh
    K4 = np.diag([4.0, 4.0, 1.0]) @ K + np.array([[0, 0, 1.5], [0, 0, 1.5], [0, 0, 0]])
    fine = silhouette(T, K4, np.asarray(mesh.vertices), np.asarray(mesh.faces), (1920, 2560))
    mask = fine.reshape(480, 4, 640, 4).mean(axis=(1, 3)) > 0.5
    rgb = np.full((480, 640, 3), 60, np.uint8)
    rgb[mask] = (210, 140, 40)
    return mask, rgb


def full_iou(name: str, T_a: np.ndarray, T_b: np.ndarray) -> float:
    return mask_iou(render(name, T_a)[0], render(name, T_b)[0])


@pytest.mark.parametrize("name", ["phone", "chair", "pistol"])
@pytest.mark.parametrize("use_rgb", [False, True])
def test_a_perturbed_pose_is_pulled_back_towards_the_truth(name: str, use_rgb: bool) -> None:
    T_true = true_pose()
    mask, rgb = render(name, T_true)
    T0 = perturbed(T_true)
    T, info = PoseRefiner().refine(name, T0, K, mask, rgb if use_rgb else None)
    assert info["accepted"]
    assert info["iou_after"] > info["iou_before"]
    rot0 = rotation_error_deg(T0[:3, :3], T_true[:3, :3])
    rot1 = rotation_error_deg(T[:3, :3], T_true[:3, :3])
    assert rot1 < 0.5 * rot0
    assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 0.5 * np.linalg.norm(
        T0[:3, 3] - T_true[:3, 3]
    )
    assert full_iou(name, T, T_true) > full_iou(name, T0, T_true)
    assert info["edge_points"] > 0 if use_rgb else info["edge_points"] == 0


def test_the_true_pose_stays_put() -> None:
    T_true = true_pose(-70.0)
    mask, rgb = render("car", T_true)
    T, _ = PoseRefiner().refine("car", T_true, K, mask, rgb)
    assert rotation_error_deg(T[:3, :3], T_true[:3, :3]) < 0.5
    assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 0.004  # 0.5 % of the distance


def test_an_occluded_part_of_the_mask_is_not_held_against_the_pose() -> None:
    T_true = true_pose(10.0)
    mask, rgb = render("screen", T_true)
    xs = np.nonzero(mask)[1]
    occluder = np.zeros_like(mask)
    occluder[:, int(np.percentile(xs, 70)) :] = True  # something stands in front of the right
    visible = mask & ~occluder
    rgb[occluder] = (30, 200, 90)
    T0 = perturbed(T_true, seed=3)
    T, info = PoseRefiner().refine("screen", T0, K, visible, rgb, occluder)
    assert info["accepted"]
    assert rotation_error_deg(T[:3, :3], T_true[:3, :3]) < rotation_error_deg(
        T0[:3, :3], T_true[:3, :3]
    )
    assert full_iou("screen", T, T_true) > full_iou("screen", T0, T_true)


def test_turning_about_one_axis_only() -> None:
    """Started off in heading only, about the object's vertical (its z axis, in the camera frame),
    the refiner restricted to that axis turns about it alone and recovers the heading."""
    T_true = true_pose(20.0)
    mask, rgb = render("car", T_true)
    up = T_true[:3, 2].copy()
    T0 = T_true.copy()
    T0[:3, :3] = axis_angle(up, np.radians(6.0)) @ T_true[:3, :3]
    T0[:3, 3] += (0.004, -0.003, 0.01)
    T, info = PoseRefiner().refine("car", T0, K, mask, rgb, axis=up)
    assert info["accepted"]
    turn = T[:3, :3] @ T0[:3, :3].T  # the rotation applied, about `up` only
    np.testing.assert_allclose(turn @ up, up, atol=1e-9)
    assert rotation_error_deg(T[:3, :3], T_true[:3, :3]) < 1.0
    assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 0.004
    with pytest.raises(InvalidArgumentError, match="unit 3-vector"):
        PoseRefiner().refine("car", T0, K, mask, rgb, axis=np.array([0.0, 0.0, 2.0]))


def test_an_empty_mask_keeps_the_pose() -> None:
    T0 = true_pose()
    T, info = PoseRefiner().refine("phone", T0, K, np.zeros((480, 640), bool))
    np.testing.assert_array_equal(T, T0)
    assert not info["accepted"] and info["reason"] == "empty mask"


def test_bad_inputs_give_clear_errors() -> None:
    ref = PoseRefiner()
    T, mask = true_pose(), np.ones((480, 640), bool)
    with pytest.raises(UnknownNameError, match="phone"):
        ref.refine("banana", T, K, mask)
    bad = T.copy()
    bad[:3, :3] *= 2
    with pytest.raises(InvalidArgumentError, match="T_C_O"):
        ref.refine("phone", bad, K, mask)
    behind = T.copy()
    behind[2, 3] = -0.5
    with pytest.raises(InvalidArgumentError, match="in front of the camera"):
        ref.refine("phone", behind, K, mask)
    with pytest.raises(InvalidArgumentError, match="mask must be"):
        ref.refine("phone", T, K, mask.astype(np.uint8))
    with pytest.raises(InvalidArgumentError, match="rgb must be a uint8 array of shape"):
        ref.refine("phone", T, K, mask, np.zeros((480, 640), np.uint8))
    with pytest.raises(InvalidArgumentError, match="occluder must be a bool array"):
        ref.refine("phone", T, K, mask, None, np.zeros((48, 64), bool))
    with pytest.raises(PosegraspError):
        ref.refine("phone", T, np.eye(3) * -1, mask)
    with pytest.raises(InvalidArgumentError, match="iterations"):
        RefineConfig(iterations=0)
    with pytest.raises(InvalidArgumentError, match="huber_px"):
        RefineConfig(huber_px=float("nan"))


def test_hybrid_refine_is_registered() -> None:
    from sim.episodes.registry import ESTIMATORS

    assert "hybrid-refine" in ESTIMATORS


def test_the_episode_adapter_refines_with_the_detected_mask() -> None:
    from perception.hybrid import HybridEpisodeEstimator, PoseDetection
    from posegrasp.core.contract import Observation

    T_true = true_pose()
    mask, rgb = render("pistol", T_true)
    T0 = perturbed(T_true, seed=1)
    det = PoseDetection(
        "pistol", 0.9, np.array([0, 0, 1, 1.0]), mask, T0, np.zeros(2), (0, 0, 1), {}
    )

    class Stub:
        def estimate_split(self, rgb, K, classes=None, others=False, **_):
            return [det], [], {"total": 1.0}

    est = HybridEpisodeEstimator(Stub(), refine=True)  # type: ignore[arg-type]
    assert est.name == "hybrid-refine"
    obs = Observation(rgb=rgb, K=K, T_world_cam=np.eye(4), object="pistol", seed=0)
    e = est.estimate(obs)
    T = e.T_C_O
    assert T is not None
    assert e.info["refine"]["accepted"]
    assert "refine" in e.info["timings_ms"]
    assert rotation_error_deg(T[:3, :3], T_true[:3, :3]) < rotation_error_deg(
        T0[:3, :3], T_true[:3, :3]
    )


def test_a_start_drawn_off_the_window_keeps_the_pose() -> None:
    """A start whose outline lies outside the mask's window leaves no contour point to compare:
    the refiner stops and returns the start unchanged, it does not fail."""
    T_true = true_pose()
    mask, rgb = render("phone", T_true)
    T0 = T_true.copy()
    T0[:3, 3] += (0.5, 0.0, 0.0)  # far to the side, still in front of the camera
    T, info = PoseRefiner().refine("phone", T0, K, mask, rgb)
    assert np.array_equal(T, T0)
    assert info["points"] < 12 and info["rotation_deg"] == 0 and info["shift_m"] == 0
