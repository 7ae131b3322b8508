"""Support-plane refinement: exact on resting poses, robust to tilt and range errors."""

import numpy as np
import pytest

from perception.support import refine_on_support, snap_to_resting
from posegrasp.core.transforms import quat_to_mat
from posegrasp.world.objects import load_object
from posegrasp.world.resting import upright_quat

SUPPORT_Z = 0.72


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """T_world_cam of an OpenCV camera (z forward, y down) at eye looking at target."""
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, z])
    T[:3, 3] = eye
    return T


def rot(axis: str, deg: float) -> np.ndarray:
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def resting_truth(name: str, pose: str, yaw_deg: float, xy=(0.9, 0.1)):
    model = load_object(name)
    q = model.resting_poses[pose]
    T_w_o = np.eye(4)
    T_w_o[:3, :3] = rot("z", yaw_deg) @ quat_to_mat(q)
    T_w_o[:3, 3] = [xy[0], xy[1], SUPPORT_Z + model.resting_height(q)]
    T_w_c = look_at(np.array([0.1, 0.0, 1.4]), T_w_o[:3, 3])
    return model, T_w_c, np.linalg.inv(T_w_c) @ T_w_o


def rot_err_deg(Ra, Rb):
    return np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1)))


@pytest.mark.parametrize("name", ["phone", "car", "pistol"])
def test_resting_pose_is_a_fixed_point(name):
    model = load_object(name)
    for pose in model.resting_poses:
        _, T_w_c, T_c_o = resting_truth(name, pose, 37.0)
        ref = refine_on_support(T_c_o, T_w_c, model, SUPPORT_Z)
        assert ref.resting_pose == pose
        assert ref.applied == ("rotation", "translation")
        np.testing.assert_allclose(ref.T_C_O, T_c_o, atol=1e-9)
        assert ref.tilt_deg < 1e-4 and abs(ref.shift_m) < 1e-9


def test_tilt_and_range_errors_are_removed():
    model, T_w_c, T_c_o = resting_truth(
        "phone", next(iter(load_object("phone").resting_poses)), 120
    )
    est = T_c_o.copy()
    # 10 degrees of tilt about a horizontal world axis, 8 % too far along the ray.
    R_w = T_w_c[:3, :3] @ T_c_o[:3, :3]
    est[:3, :3] = T_w_c[:3, :3].T @ rot("x", 10.0) @ R_w
    est[:3, 3] *= 1.08
    assert rot_err_deg(est[:3, :3], T_c_o[:3, :3]) > 9.9
    ref = refine_on_support(est, T_w_c, model, SUPPORT_Z)
    assert rot_err_deg(ref.T_C_O[:3, :3], T_c_o[:3, :3]) < 2.0
    # The ray is exact and the resting height does not depend on yaw: the origin is exact.
    np.testing.assert_allclose(ref.T_C_O[:3, 3], T_c_o[:3, 3], atol=1e-9)
    assert ref.shift_m == pytest.approx(-0.08 * np.linalg.norm(T_c_o[:3, 3]), rel=1e-6)


def test_yaw_is_kept():
    model = load_object("car")
    pose = next(iter(model.resting_poses))
    R_k = quat_to_mat(model.resting_poses[pose])
    for yaw in (-170.0, -30.0, 0.0, 45.0, 179.0):
        R, name, ang, h = snap_to_resting(rot("z", yaw) @ R_k, model)
        assert name == pose and ang < 1e-4
        np.testing.assert_allclose(R, rot("z", yaw) @ R_k, atol=1e-9)
        assert h == pytest.approx(model.resting_height(model.resting_poses[pose]))


def test_far_from_every_resting_pose_is_left_alone():
    model, T_w_c, T_c_o = resting_truth("phone", next(iter(load_object("phone").resting_poses)), 0)
    # Resting on a corner of its base: the body diagonal up, more than 45 degrees from the up
    # direction of every resting pose the phone has.
    up = np.array([1.0, 1.0, 1.0]) / np.sqrt(3.0)
    assert all(
        quat_to_mat(q)[2] @ up < np.cos(np.deg2rad(45.0)) for q in model.resting_poses.values()
    )
    est = T_c_o.copy()
    est[:3, :3] = T_w_c[:3, :3].T @ quat_to_mat(upright_quat(up))
    ref = refine_on_support(est, T_w_c, model, SUPPORT_Z, max_tilt_deg=45.0)
    assert ref.applied == () and ref.resting_pose is None
    np.testing.assert_array_equal(ref.T_C_O, est)


def test_ray_parallel_to_the_table_keeps_the_distance():
    model = load_object("phone")
    pose = next(iter(model.resting_poses))
    T_w_o = np.eye(4)
    T_w_o[:3, :3] = quat_to_mat(model.resting_poses[pose])
    T_w_o[:3, 3] = [1.0, 0.0, SUPPORT_Z + model.resting_height(model.resting_poses[pose])]
    T_w_c = look_at(np.array([0.0, 0.0, T_w_o[2, 3]]), T_w_o[:3, 3])  # level with the object
    est = np.linalg.inv(T_w_c) @ T_w_o
    est[:3, 3] *= 1.1
    ref = refine_on_support(est, T_w_c, model, SUPPORT_Z)
    assert ref.applied == ("rotation",)
    np.testing.assert_allclose(ref.T_C_O[:3, 3], est[:3, 3])


def test_error_components_recover_applied_noise():
    from perception.metrics import error_components
    from sim.episodes.pose_noise import PoseNoise, perturb_pose

    _model, _T_w_c, T_c_o = resting_truth("car", next(iter(load_object("car").resting_poses)), 10)
    rng = np.random.default_rng(0)
    for ray, lat, inp, outp in [
        (0.02, 0.0, 0, 0),
        (0, 0.015, 0, 0),
        (0, 0, 12, 0),
        (0, 0, 0, 7.5),
        (0.01, 0.02, 20, 9),
    ]:
        noise = PoseNoise(ray, lat, np.radians(inp), np.radians(outp), mode="fixed")
        e = error_components(perturb_pose(T_c_o, noise, rng), T_c_o)
        assert e["ray_m"] == pytest.approx(ray, abs=1e-9)
        assert e["lateral_m"] == pytest.approx(lat, abs=1e-9)
        assert e["inplane_deg"] == pytest.approx(inp, abs=1e-6)
        assert e["outplane_deg"] == pytest.approx(outp, abs=1e-6)


@pytest.mark.parametrize("name", ["car", "pistol"])
def test_mask_fit_recovers_yaw_and_position(name):
    from perception.overlay import silhouette
    from perception.support import refine_with_mask

    model, T_w_c, T_c_o = resting_truth(name, next(iter(load_object(name).resting_poses)), 60)
    K = np.array([[550.0, 0, 320], [0, 550.0, 240], [0, 0, 1]])
    mesh = model.mesh
    mask = silhouette(T_c_o, K, np.asarray(mesh.vertices), np.asarray(mesh.faces), (480, 640))
    # The estimate: yaw off by 14 degrees and the origin 6 mm off, still resting on the table.
    T_w_o = T_w_c @ T_c_o
    T_w_e = T_w_o.copy()
    T_w_e[:3, :3] = rot("z", 14.0) @ T_w_o[:3, :3]
    T_w_e[:3, 3] += [0.006, -0.004, 0.0]
    est = np.linalg.inv(T_w_c) @ T_w_e
    fit = refine_with_mask(est, T_w_c, K, model, mask)
    assert fit.iou_after > fit.iou_before and fit.iou_after > 0.9
    assert rot_err_deg(fit.T_C_O[:3, :3], T_c_o[:3, :3]) < 2.0
    assert np.linalg.norm(fit.T_C_O[:3, 3] - T_c_o[:3, 3]) < 0.004
    # Still resting: the same height above the table.
    assert (T_w_c @ fit.T_C_O)[2, 3] == pytest.approx(T_w_o[2, 3], abs=1e-9)


def test_mask_fit_with_an_empty_mask_keeps_the_pose():
    from perception.support import refine_with_mask

    model, T_w_c, T_c_o = resting_truth("phone", next(iter(load_object("phone").resting_poses)), 0)
    K = np.array([[550.0, 0, 320], [0, 550.0, 240], [0, 0, 1]])
    fit = refine_with_mask(T_c_o, T_w_c, K, model, np.zeros((480, 640), bool))
    np.testing.assert_array_equal(fit.T_C_O, T_c_o)
    assert fit.renders == 0
