"""Tests of the 4D representation and the camera correction (numpy and torch)."""

from __future__ import annotations

import inspect
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

import perception
from perception import crops, geometry, metrics, summaries
from perception import geometry as g
from perception import geometry_torch as gt
from perception.training.trainers import losses
from posegrasp.core import transforms as tf
from posegrasp.core.transforms import intrinsics

SQRT_EPS = math.sqrt(g.SINGULAR_EPS)


# --------------------------------------------------------------------------- helpers


def random_intrinsics(rng: np.random.Generator) -> np.ndarray:
    """A random pinhole K, with fx != fy and a principal point off the centre."""
    width, height = int(rng.integers(64, 1280)), int(rng.integers(64, 960))
    fy = height / 2.0 / math.tan(rng.uniform(math.radians(20.0), math.radians(120.0)) / 2.0)
    fx = fy * rng.uniform(0.8, 1.25)
    cx = (width - 1) / 2.0 + rng.uniform(-20.0, 20.0)
    cy = (height - 1) / 2.0 + rng.uniform(-20.0, 20.0)
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def random_pose_in_view(rng: np.random.Generator, K: np.ndarray, margin: float) -> np.ndarray:
    """A random T_C_O whose origin projects inside the image grown by ``margin`` pixels."""
    width, height = 2.0 * K[0, 2] + 1.0, 2.0 * K[1, 2] + 1.0
    uv = np.array([rng.uniform(-margin, width + margin), rng.uniform(-margin, height + margin)])
    depth = rng.uniform(0.1, 5.0)
    t = depth * np.linalg.solve(K, np.array([uv[0], uv[1], 1.0]))
    return tf.make_transform(Rotation.random(random_state=rng).as_matrix(), t)


def singular_p(rng: np.random.Generator, above: bool, band_scale: float) -> np.ndarray:
    """A camera position p with z_x^2 + z_y^2 about (band_scale * 1e-9), above or below O."""
    phi = rng.uniform(-math.pi, math.pi)
    eps = band_scale * SQRT_EPS
    direction = np.array([eps * math.cos(phi), eps * math.sin(phi), 1.0 if above else -1.0])
    return rng.uniform(0.2, 3.0) * direction / np.linalg.norm(direction)


# --------------------------------------------------------------------------- basics


def test_intrinsics_by_hand() -> None:
    K = intrinsics(math.radians(90.0), 640, 480)
    # tan(45 deg) = 1, so fy = H / 2.
    np.testing.assert_allclose(K, [[240.0, 0.0, 319.5], [0.0, 240.0, 239.5], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize(
    ("fovy", "width", "height"), [(0.0, 64, 64), (math.pi, 64, 64), (1.0, 0, 64), (1.0, 64.5, 64)]
)
def test_intrinsics_rejects_bad_input(fovy: float, width: float, height: float) -> None:
    with pytest.raises(ValueError, match=r"fovy|width"):
        intrinsics(fovy, width, height)


def test_project_by_hand_and_centre_pixel() -> None:
    K = intrinsics(math.radians(60.0), 101, 51)
    # A point on the optical axis lands on the centre of the middle pixel (50, 25).
    np.testing.assert_allclose(g.project(K, [0.0, 0.0, 2.0]), [50.0, 25.0])
    f = K[0, 0]
    uv = g.project(K, np.array([[0.5, -0.25, 2.0], [1.0, 1.0, 1.0]]))
    np.testing.assert_allclose(uv, [[50.0 + f / 4.0, 25.0 - f / 8.0], [50.0 + f, 25.0 + f]])
    with pytest.raises(ValueError, match="in front"):
        g.project(K, [0.0, 0.0, -1.0])


def test_elementary_rotations_rotate_the_right_way() -> None:
    a = 0.3
    np.testing.assert_allclose(tf.rot_z(a) @ [1.0, 0.0, 0.0], [math.cos(a), math.sin(a), 0.0])
    np.testing.assert_allclose(tf.rot_x(a) @ [0.0, 1.0, 0.0], [0.0, math.cos(a), math.sin(a)])
    np.testing.assert_allclose(tf.rot_y(a) @ [0.0, 0.0, 1.0], [math.sin(a), 0.0, math.cos(a)])


def test_invert_transform_against_matrix_inverse() -> None:
    rng = np.random.default_rng(1)
    for _ in range(20):
        T = tf.make_transform(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))
        np.testing.assert_allclose(tf.invert_transform(T), np.linalg.inv(T), atol=1e-12)


# --------------------------------------------------------------------------- R_corr


def test_r_corr_maps_axis_onto_pixel_ray() -> None:
    rng = np.random.default_rng(2)
    for _ in range(500):
        K = random_intrinsics(rng)
        uv = rng.uniform(-300.0, 1500.0, size=2)
        R = g.r_corr(uv, K)
        ray = np.linalg.solve(K, np.array([uv[0], uv[1], 1.0]))
        np.testing.assert_allclose(R @ [0.0, 0.0, 1.0], ray / np.linalg.norm(ray), atol=1e-12)
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)


def test_r_corr_is_identity_at_principal_point() -> None:
    K = intrinsics(1.0, 64, 48)
    np.testing.assert_allclose(g.r_corr(K[:2, 2], K), np.eye(3), atol=1e-15)


# --------------------------------------------------------------------------- 4D representation


def test_rotation_from_p_theta_axes() -> None:
    rng = np.random.default_rng(3)
    for _ in range(200):
        p = rng.normal(size=3)
        R0 = g.rotation_from_p_theta(p, 0.0)
        np.testing.assert_allclose(R0.T @ R0, np.eye(3), atol=1e-12)
        assert np.linalg.det(R0) == pytest.approx(1.0)
        np.testing.assert_allclose(R0[:, 2], -p / np.linalg.norm(p), atol=1e-12)
        assert abs(R0[2, 0]) < 1e-12  # x is horizontal in O at theta = 0
        theta = rng.uniform(-math.pi, math.pi)
        R = g.rotation_from_p_theta(p, theta)
        # Rolling about the optical axis keeps the axis and turns x by theta towards y.
        np.testing.assert_allclose(R[:, 2], R0[:, 2], atol=1e-12)
        np.testing.assert_allclose(
            R[:, 0], math.cos(theta) * R0[:, 0] + math.sin(theta) * R0[:, 1], atol=1e-12
        )


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_singularity_uses_world_x(sign: float) -> None:
    x, y, z = g.axes_from_p(np.array([0.0, 0.0, sign * 0.7]))
    np.testing.assert_array_equal(x, [1.0, 0.0, 0.0])
    np.testing.assert_array_equal(z, [0.0, 0.0, -sign])
    np.testing.assert_allclose(y, np.cross(z, x))


def test_singular_band_stays_orthonormal() -> None:
    rng = np.random.default_rng(4)
    for above in (True, False):
        for _ in range(50):
            p = singular_p(rng, above, band_scale=0.9)
            R = g.rotation_from_p_theta(p, rng.uniform(-3.0, 3.0))
            np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)


def test_decode_puts_object_on_virtual_axis() -> None:
    rng = np.random.default_rng(5)
    K = intrinsics(math.radians(45.0), 320, 240)
    p, theta, uv = rng.normal(size=3), 0.4, np.array([12.0, 200.0])
    T_C_O = g.decode(p, theta, uv, K)
    T_Cv_O = tf.invert_transform(tf.make_transform(g.rotation_from_p_theta(p, theta), p))
    np.testing.assert_allclose(T_Cv_O[:3, 3], [0.0, 0.0, np.linalg.norm(p)], atol=1e-12)
    np.testing.assert_allclose(g.project(K, T_C_O[:3, 3]), uv, atol=1e-9)
    # C and C' share their origin, so the camera sits at p in the object frame.
    np.testing.assert_allclose(tf.invert_transform(T_C_O)[:3, 3], p, atol=1e-12)


def test_encode_decode_round_trip_many_random_cases() -> None:
    rng = np.random.default_rng(6)
    n = 2000
    err_T, err_uv, err_p, thetas = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    for i in range(n):
        K = random_intrinsics(rng) if i % 2 else intrinsics(rng.uniform(0.3, 2.0), 640, 480)
        T = random_pose_in_view(rng, K, margin=100.0 if i % 3 == 0 else 0.0)
        p, thetas[i], uv = g.encode(T, K)
        err_uv[i] = np.abs(uv - g.project(K, T[:3, 3])).max()
        # C and C' share their origin: p is the camera position in O.
        err_p[i] = np.abs(p - tf.invert_transform(T)[:3, 3]).max()
        err_T[i] = np.abs(g.decode(p, thetas[i], uv, K) - T).max()
    assert np.all(np.abs(thetas) <= math.pi)
    assert err_uv.max() < 1e-9
    assert err_p.max() < 1e-9
    assert err_T.max() < 1e-9


@pytest.mark.parametrize("above", [True, False])
@pytest.mark.parametrize("band_scale", [0.0, 0.5, 0.999, 1.001, 2.0, 100.0])
def test_round_trip_at_and_near_singularity(above: bool, band_scale: float) -> None:
    rng = np.random.default_rng(7)
    for _ in range(100):
        K = random_intrinsics(rng)
        width, height = 2.0 * K[0, 2] + 1.0, 2.0 * K[1, 2] + 1.0
        # Objects anywhere in the image, including its corners.
        uv = np.array(
            [rng.choice([0.0, width - 1.0, rng.uniform(0, width)]), rng.uniform(0, height)]
        )
        p0 = singular_p(rng, above, band_scale)
        theta0 = rng.uniform(-math.pi, math.pi)
        T = g.decode(p0, theta0, uv, K)
        p, theta, uv1 = g.encode(T, K)
        np.testing.assert_allclose(p, p0, atol=1e-9)
        assert math.remainder(theta - theta0, 2.0 * math.pi) == pytest.approx(0.0, abs=1e-9)
        np.testing.assert_allclose(uv1, uv, atol=1e-8)
        np.testing.assert_allclose(g.decode(p, theta, uv1, K), T, atol=1e-9)


def test_camera_straight_above_upright_object() -> None:
    """Camera 1 m above the object, looking down at it through the image centre."""
    K = intrinsics(1.0, 64, 64)
    R_C_O = np.diag([1.0, -1.0, -1.0]) @ tf.rot_z(0.3)
    T = tf.make_transform(R_C_O, [0.0, 0.0, 1.0])
    p, theta, uv = g.encode(T, K)
    np.testing.assert_allclose(p, [0.0, 0.0, 1.0], atol=1e-15)
    np.testing.assert_allclose(uv, [31.5, 31.5])
    assert abs(abs(theta) - 0.3) < 1e-12
    np.testing.assert_allclose(g.decode(p, theta, uv, K), T, atol=1e-15)


finite = {"allow_nan": False, "allow_infinity": False}


@settings(max_examples=200, deadline=None)
@given(
    quat=st.tuples(*[st.floats(-1.0, 1.0, **finite)] * 4).filter(
        lambda q: sum(c * c for c in q) > 1e-3
    ),
    u=st.floats(-0.2, 1.2, **finite),
    v=st.floats(-0.2, 1.2, **finite),
    depth=st.floats(0.05, 20.0, **finite),
    fovy=st.floats(0.2, 2.5, **finite),
    width=st.integers(16, 2000),
    height=st.integers(16, 2000),
)
def test_round_trip_property(
    quat: tuple[float, float, float, float],
    u: float,
    v: float,
    depth: float,
    fovy: float,
    width: int,
    height: int,
) -> None:
    K = intrinsics(fovy, width, height)
    uv = np.array([u * width, v * height])
    t = depth * np.linalg.solve(K, np.array([uv[0], uv[1], 1.0]))
    T = tf.make_transform(Rotation.from_quat(quat).as_matrix(), t)
    p, theta, uv1 = g.encode(T, K)
    np.testing.assert_allclose(g.decode(p, theta, uv1, K), T, atol=1e-9, rtol=0.0)


@settings(max_examples=200, deadline=None)
@given(
    p=st.tuples(*[st.floats(-3.0, 3.0, **finite)] * 3).filter(
        lambda p: sum(c * c for c in p) > 1e-2
    ),
    theta=st.floats(-math.pi + 1e-6, math.pi, **finite),
    u=st.floats(-100.0, 740.0, **finite),
    v=st.floats(-100.0, 580.0, **finite),
)
def test_decode_encode_property(
    p: tuple[float, float, float], theta: float, u: float, v: float
) -> None:
    K = intrinsics(0.8, 640, 480)
    p0, uv0 = np.array(p), np.array([u, v])
    p1, theta1, uv1 = g.encode(g.decode(p0, theta, uv0, K), K)
    np.testing.assert_allclose(p1, p0, atol=1e-9)
    assert math.remainder(theta1 - theta, 2.0 * math.pi) == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(uv1, uv0, atol=1e-8)


def test_validation_messages() -> None:
    K = intrinsics(1.0, 64, 64)
    with pytest.raises(ValueError, match="T_C_O must have shape"):
        g.encode(np.eye(3), K)
    with pytest.raises(ValueError, match="proper rotation"):
        g.encode(np.diag([1.0, 1.0, -1.0, 1.0]), K)
    with pytest.raises(ValueError, match="p must be non-zero"):
        g.rotation_from_p_theta(np.zeros(3), 0.0)
    with pytest.raises(ValueError, match="theta must be finite"):
        g.rotation_from_p_theta(np.ones(3), float("nan"))
    with pytest.raises(ValueError, match="K must have positive"):
        g.r_corr(np.zeros(2), -K)
    with pytest.raises(ValueError, match="uv must have shape"):
        g.decode(np.ones(3), 0.0, np.zeros(3), K)


# --------------------------------------------------------------------------- torch


def t64(x: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x), dtype=torch.float64)


def mixed_p(rng: np.random.Generator, n: int) -> np.ndarray:
    """Random camera positions, a quarter of them at or inside the singular band."""
    p = rng.normal(size=(n, 3))
    for i in range(0, n, 4):
        p[i] = singular_p(rng, bool(i % 8), band_scale=float(rng.choice([0.0, 0.5, 1.5])))
    return p


def test_torch_rotation_matches_numpy() -> None:
    rng = np.random.default_rng(8)
    p, theta = mixed_p(rng, 256), rng.uniform(-math.pi, math.pi, size=256)
    R = gt.rotation_from_p_theta(t64(p), t64(theta)).numpy()
    expected = np.stack([g.rotation_from_p_theta(pi, th) for pi, th in zip(p, theta, strict=True)])
    np.testing.assert_allclose(R, expected, atol=1e-12)
    cs = rng.uniform(0.1, 5.0, size=(256, 1)) * np.stack((np.cos(theta), np.sin(theta)), axis=1)
    np.testing.assert_allclose(gt.rotation_from_p_cs(t64(p), t64(cs)).numpy(), expected, atol=1e-9)


def test_torch_decode_matches_numpy() -> None:
    rng = np.random.default_rng(9)
    n = 128
    p, theta = mixed_p(rng, n), rng.uniform(-math.pi, math.pi, size=n)
    uv = rng.uniform(-50.0, 700.0, size=(n, 2))
    Ks = np.stack([random_intrinsics(rng) for _ in range(n)])
    T = gt.decode_torch(t64(p), t64(theta), t64(uv), t64(Ks)).numpy()
    for i in range(n):
        np.testing.assert_allclose(T[i], g.decode(p[i], theta[i], uv[i], Ks[i]), atol=1e-12)
    # A single shared K broadcasts over the batch.
    T_shared = gt.decode_torch(t64(p), t64(theta), t64(uv), t64(Ks[0])).numpy()
    np.testing.assert_allclose(T_shared[5], g.decode(p[5], theta[5], uv[5], Ks[0]), atol=1e-12)


def test_torch_r_corr_matches_numpy_with_skew() -> None:
    rng = np.random.default_rng(10)
    K = random_intrinsics(rng)
    K[0, 1] = 3.0
    uv = rng.uniform(0.0, 500.0, size=(16, 2))
    R = gt.r_corr(t64(uv), t64(K)).numpy()
    for i in range(16):
        np.testing.assert_allclose(R[i], g.r_corr(uv[i], K), atol=1e-12)


def test_geodesic_distance_of_known_rotations() -> None:
    angles = np.array([0.1, 1.0, 2.5, 3.0])
    axes = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 1.0], [0.0, -1.0, 2.0]])
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    R1 = Rotation.random(4, random_state=np.random.default_rng(11)).as_matrix()
    R2 = R1 @ Rotation.from_rotvec(axes * angles[:, None]).as_matrix()
    d = gt.geodesic_distance(t64(R1), t64(R2)).numpy()
    np.testing.assert_allclose(d, angles, atol=1e-9)


def test_pose_loss_by_hand() -> None:
    p_gt = t64([[0.0, 0.3, 0.4], [1.0, 2.0, 2.0]])
    theta = t64([0.2, -1.0])
    # Same position, rolls differing by 0.5 rad: only the rotation term, lam * 0.5.
    loss = losses.pose_loss_4d(p_gt, theta + 0.5, p_gt, theta, lam=2.0)
    assert loss.item() == pytest.approx(1.0, abs=1e-6)
    # Position off by (0, 0, 0.1) and (0, 0, 0.3): |dp|/|p| = 0.1/0.5 and 0.3/3.
    p_pred = p_gt + t64([[0.0, 0.0, 0.1], [0.0, 0.0, 0.3]])
    loss0 = losses.pose_loss_4d(p_pred, theta, p_gt, theta, lam=0.0)
    assert loss0.item() == pytest.approx((0.2 + 0.1) / 2.0, abs=1e-9)
    # (cos, sin) predictions give the same loss as the angles.
    cs = torch.stack((torch.cos(theta + 0.5), torch.sin(theta + 0.5)), dim=1) * 3.0
    loss_cs = losses.pose_loss_4d(p_gt, cs, p_gt, theta, lam=2.0)
    assert loss_cs.item() == pytest.approx(loss.item(), abs=1e-6)


def test_gradients_are_finite_everywhere() -> None:
    rng = np.random.default_rng(12)
    p_gt = np.concatenate(
        [
            [[0.0, 0.0, 0.8], [0.0, 0.0, -0.5], [1e-6, 0.0, 0.9]],
            [singular_p(rng, True, 1.0)],
            rng.normal(size=(4, 3)),
        ]
    )
    n = p_gt.shape[0]
    theta_gt = t64(rng.uniform(-math.pi, math.pi, size=n))
    for p_pred_np in (p_gt, p_gt + 1e-3 * rng.normal(size=p_gt.shape)):
        for angle in (theta_gt.clone(), torch.stack((theta_gt.cos(), theta_gt.sin()), dim=1)):
            p_pred = t64(p_pred_np).requires_grad_(True)
            angle.requires_grad_(True)
            loss = losses.pose_loss_4d(p_pred, angle, t64(p_gt), theta_gt, lam=1.0)
            loss.backward()
            assert torch.isfinite(loss)
            assert p_pred.grad is not None and angle.grad is not None
            assert torch.all(torch.isfinite(p_pred.grad))
            assert torch.all(torch.isfinite(angle.grad))
    uv = t64(rng.uniform(0.0, 64.0, size=(n, 2))).requires_grad_(True)
    p = t64(p_gt).requires_grad_(True)
    T = gt.decode_torch(p, theta_gt, uv, t64(intrinsics(1.0, 64, 64)))
    T.sum().backward()
    assert p.grad is not None and torch.all(torch.isfinite(p.grad))
    assert uv.grad is not None and torch.all(torch.isfinite(uv.grad))


def test_gradients_match_finite_differences() -> None:
    rng = np.random.default_rng(13)
    p = t64(rng.normal(size=(3, 3))).requires_grad_(True)
    theta = t64(rng.uniform(-3.0, 3.0, size=3)).requires_grad_(True)
    uv = t64(rng.uniform(0.0, 64.0, size=(3, 2))).requires_grad_(True)
    K = t64(intrinsics(1.0, 64, 64))
    assert torch.autograd.gradcheck(lambda a, b: gt.rotation_from_p_theta(a, b), (p, theta))
    assert torch.autograd.gradcheck(lambda a, b, c: gt.decode_torch(a, b, c, K), (p, theta, uv))


def test_torch_float32_and_shape_errors() -> None:
    p = torch.tensor([[0.1, 0.2, 0.9]], dtype=torch.float32)
    R = gt.rotation_from_p_theta(p, torch.tensor([0.3]))
    assert R.dtype == torch.float32 and R.shape == (1, 3, 3)
    with pytest.raises(ValueError, match=r"p must have shape \(B, 3\)"):
        gt.rotation_from_p_theta(p[0], torch.tensor([0.3]))
    with pytest.raises(ValueError, match="theta has batch"):
        gt.rotation_from_p_theta(p, torch.tensor([0.3, 0.1]))
    with pytest.raises(ValueError, match=r"\(B,\) \(theta\) or \(B, 2\)"):
        losses.pose_loss_4d(p, torch.zeros(1, 3), p, torch.zeros(1), lam=1.0)


# --------------------------------------------------------------------------- package


def test_all_is_honest() -> None:
    exported = set(perception.__all__)
    assert all(hasattr(perception, name) for name in exported)
    public = {
        name
        for module in (crops, geometry, metrics, summaries)
        for name, obj in vars(module).items()
        if inspect.isfunction(obj)
        and obj.__module__ == module.__name__
        and not name.startswith("_")
    }
    from_transforms = {"intrinsics", "invert_transform", "make_transform", "rot_x", "rot_y"}
    lazy = {"HybridPoseEstimator", "PoseDetection"}
    assert exported == public | from_transforms | {"rot_z"} | lazy


def test_import_does_not_pull_torch_or_cv2() -> None:
    code = "import sys, perception; print('torch' in sys.modules, 'cv2' in sys.modules)"
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=root
    )
    assert out.stdout.split() == ["False", "False"]
