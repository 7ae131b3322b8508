"""Tests of the pose metrics against hand-computed values and invariants."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from perception import metrics as m
from perception import summaries
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.transforms import intrinsics, rot_z


def box_points(rng: np.random.Generator, n: int = 300) -> np.ndarray:
    """Random points on the surface-ish of a 0.2 x 0.1 x 0.05 m box."""
    return rng.uniform(-1.0, 1.0, size=(n, 3)) * np.array([0.1, 0.05, 0.025])


def random_pose(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    R = Rotation.random(random_state=rng).as_matrix()
    t = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), rng.uniform(0.5, 1.5)])
    return R, t


def z_symmetries(n: int) -> list[dict[str, np.ndarray]]:
    """The n-fold rotational symmetry set about the object's z axis (identity included)."""
    return [{"R": rot_z(2.0 * math.pi * k / n), "t": np.zeros((3, 1))} for k in range(n)]


# --------------------------------------------------------------------------- ADD / ADI


def test_add_and_adi_of_identical_poses_are_zero() -> None:
    rng = np.random.default_rng(0)
    pts = box_points(rng)
    R, t = random_pose(rng)
    assert m.add(R, t, R, t, pts) == pytest.approx(0.0, abs=1e-15)
    assert m.adi(R, t, R, t, pts) == pytest.approx(0.0, abs=1e-15)


def test_add_of_pure_translation_and_of_rotation_by_hand() -> None:
    pts = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 2.0]])
    R = np.eye(3)
    # Every point moves by the same offset of length 0.5.
    assert m.add(R, [0.3, 0.4, 1.0], R, [0.0, 0.0, 1.0], pts) == pytest.approx(0.5)
    # 90 deg about z: (1,0,0) -> (0,1,0) moves sqrt(2); (0,1,0) moves sqrt(2); (0,0,2) stays.
    e = m.add(rot_z(math.pi / 2.0), np.zeros((3, 1)), R, np.zeros((3, 1)), pts)
    assert e == pytest.approx(2.0 * math.sqrt(2.0) / 3.0)
    # ADI: the estimated points are (0,1,0), (-1,0,0), (0,0,2); the nearest one to gt (1,0,0)
    # is (0,1,0) at sqrt(2), gt (0,1,0) and (0,0,2) have an exact match.
    e_adi = m.adi(rot_z(math.pi / 2.0), np.zeros(3), R, np.zeros(3), pts)
    assert e_adi == pytest.approx(math.sqrt(2.0) / 3.0)


def test_adi_against_brute_force_and_below_add() -> None:
    rng = np.random.default_rng(1)
    pts = box_points(rng, 200)
    for _ in range(20):
        (R_e, t_e), (R_g, t_g) = random_pose(rng), random_pose(rng)
        est = pts @ R_e.T + t_e
        gt = pts @ R_g.T + t_g
        brute = np.linalg.norm(gt[:, None, :] - est[None, :, :], axis=2).min(axis=1).mean()
        adi = m.adi(R_e, t_e, R_g, t_g, pts)
        assert adi == pytest.approx(brute, rel=1e-12)
        assert adi <= m.add(R_e, t_e, R_g, t_g, pts) + 1e-15


def test_adi_is_zero_for_a_symmetric_pose_of_a_symmetric_object() -> None:
    # A square of points is 4-fold symmetric about z: ADI ignores the 90 deg flip, ADD does not.
    pts = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    t = np.array([0.0, 0.0, 3.0])
    assert m.adi(rot_z(math.pi / 2.0), t, np.eye(3), t, pts) == pytest.approx(0.0, abs=1e-12)
    assert m.add(rot_z(math.pi / 2.0), t, np.eye(3), t, pts) == pytest.approx(math.sqrt(2.0))


# --------------------------------------------------------------------------- MSSD / MSPD


def test_mssd_by_hand_and_with_symmetries() -> None:
    pts = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    t = np.array([0.0, 0.0, 3.0])
    R_est = rot_z(math.pi / 2.0 + 0.1)
    # Without symmetries: every point moves by the chord of (pi/2 + 0.1).
    chord = 2.0 * math.sin((math.pi / 2.0 + 0.1) / 2.0)
    assert m.mssd(R_est, t, np.eye(3), t, pts, m.identity_symmetry()) == pytest.approx(chord)
    # With the 4-fold symmetry, only the 0.1 rad residual is left.
    residual = 2.0 * math.sin(0.05)
    assert m.mssd(R_est, t, np.eye(3), t, pts, z_symmetries(4)) == pytest.approx(residual)


def test_mssd_unchanged_by_a_symmetry_of_the_estimate() -> None:
    rng = np.random.default_rng(2)
    half = box_points(rng, 150)
    # A point set with the 2-fold symmetry about z (as the sampled surface of a box has).
    pts = np.concatenate([half, half @ rot_z(math.pi).T])
    syms = z_symmetries(2)
    for _ in range(20):
        (R_e, t_e), (R_g, t_g) = random_pose(rng), random_pose(rng)
        for sym in syms:
            R_flip = R_e @ sym["R"]
            t_flip = R_e @ sym["t"].reshape(3) + t_e
            before = m.mssd(R_e, t_e, R_g, t_g, pts, syms)
            assert m.mssd(R_flip, t_flip, R_g, t_g, pts, syms) == pytest.approx(before, rel=1e-9)
            before_px = m.mspd(R_e, t_e, R_g, t_g, intrinsics(1.0, 64, 64), pts, syms)
            after_px = m.mspd(R_flip, t_flip, R_g, t_g, intrinsics(1.0, 64, 64), pts, syms)
            assert after_px == pytest.approx(before_px, rel=1e-9)
        assert m.mssd(R_e, t_e, R_g, t_g, pts, syms) <= m.mssd(
            R_e, t_e, R_g, t_g, pts, m.identity_symmetry()
        )


def test_mssd_uses_symmetry_translation() -> None:
    # Two points; the symmetry swaps them (a half turn about z through (0.5, 0, 0)).
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    sym = {"R": rot_z(math.pi), "t": np.array([[1.0], [0.0], [0.0]])}
    R_gt = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    t_gt = np.array([0.1, 0.0, 2.0])
    # The swapped pose, gt composed with the symmetry: the same point set, points exchanged.
    R_est = R_gt @ sym["R"]
    t_est = R_gt @ sym["t"].reshape(3) + t_gt
    syms = [*m.identity_symmetry(), sym]
    assert m.mssd(R_est, t_est, R_gt, t_gt, pts, syms) == pytest.approx(0.0, abs=1e-12)
    assert m.mssd(R_est, t_est, R_gt, t_gt, pts, m.identity_symmetry()) == pytest.approx(1.0)
    K = intrinsics(1.0, 64, 64)
    assert m.mspd(R_est, t_est, R_gt, t_gt, K, pts, syms) == pytest.approx(0.0, abs=1e-9)
    assert m.mspd(R_est, t_est, R_gt, t_gt, K, pts, m.identity_symmetry()) > 1.0


def test_mspd_by_hand() -> None:
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    pts = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    R = np.eye(3)
    # Shift by 1 cm sideways at 1 m depth: 5 px for every point.
    e = m.mspd(R, [0.01, 0.0, 1.0], R, [0.0, 0.0, 1.0], K, pts, m.identity_symmetry())
    assert e == pytest.approx(5.0)
    # Move 1 m -> 2 m along the axis: (0,0,0) stays at the centre, (0.1,0,0) goes from
    # u = 320 + 50 to u = 320 + 25: the maximum is 25 px.
    e = m.mspd(R, [0.0, 0.0, 2.0], R, [0.0, 0.0, 1.0], K, pts, m.identity_symmetry())
    assert e == pytest.approx(25.0)
    # An estimate behind the camera is an infinite error.
    e = m.mspd(R, [0.0, 0.0, -1.0], R, [0.0, 0.0, 1.0], K, pts, m.identity_symmetry())
    assert e == math.inf


# --------------------------------------------------------------------------- paper errors


@settings(max_examples=100, deadline=None)
@given(
    angle=st.floats(0.0, math.pi - 1e-6, allow_nan=False),
    axis=st.tuples(*[st.floats(-1.0, 1.0, allow_nan=False)] * 3).filter(
        lambda a: sum(c * c for c in a) > 1e-2
    ),
)
def test_rotation_error_of_known_rotation_is_its_angle(
    angle: float, axis: tuple[float, float, float]
) -> None:
    rng = np.random.default_rng(3)
    R_gt = Rotation.random(random_state=rng).as_matrix()
    a = np.array(axis) / np.linalg.norm(axis)
    R_est = R_gt @ Rotation.from_rotvec(angle * a).as_matrix()
    # arccos loses precision near 0 and pi: about sqrt(machine eps) rad there.
    assert m.rotation_error_deg(R_est, R_gt) == pytest.approx(math.degrees(angle), abs=1e-5)
    assert m.rotation_error_deg(R_gt, R_est) == pytest.approx(math.degrees(angle), abs=1e-5)


def test_rotation_error_sym_by_hand() -> None:
    R_est = rot_z(math.radians(100.0))
    assert m.rotation_error_deg(R_est, np.eye(3)) == pytest.approx(100.0)
    assert m.rotation_error_sym_deg(R_est, np.eye(3), z_symmetries(4)) == pytest.approx(10.0)
    assert m.rotation_error_sym_deg(R_est, np.eye(3), m.identity_symmetry()) == pytest.approx(100.0)


def test_translation_error_pct_by_hand() -> None:
    assert m.translation_error_pct([0.0, 0.0, 1.1], [0.0, 0.0, 1.0]) == pytest.approx(10.0)
    assert m.translation_error_pct(
        np.array([[0.3], [0.4], [1.0]]), [0.0, 0.0, 1.0]
    ) == pytest.approx(50.0)
    with pytest.raises(ValueError, match="t_gt must be non-zero"):
        m.translation_error_pct([1.0, 0.0, 0.0], [0.0, 0.0, 0.0])


def test_center_error_px_by_hand() -> None:
    assert m.center_error_px([3.0, 4.0], [0.0, 0.0]) == pytest.approx(5.0)
    out = m.center_error_px(np.array([[1.0, 1.0], [6.0, 8.0]]), np.array([[1.0, 0.0], [0.0, 0.0]]))
    np.testing.assert_allclose(out, [1.0, 10.0])


def test_mask_iou_by_hand() -> None:
    a = np.zeros((4, 4), dtype=bool)
    b = np.zeros((4, 4), dtype=np.uint8)
    a[0:2, 0:2] = True  # 4 pixels
    b[1:3, 1:3] = 1  # 4 pixels, overlapping a in 1
    assert m.mask_iou(a, b) == pytest.approx(1.0 / 7.0)
    assert m.mask_iou(a, a) == 1.0
    assert m.mask_iou(a, np.zeros((4, 4))) == 0.0
    assert m.mask_iou(np.zeros((4, 4)), np.zeros((4, 4))) == 1.0
    with pytest.raises(ValueError, match="same shape"):
        m.mask_iou(a, np.zeros((4, 5)))


# --------------------------------------------------------------------------- aggregates


def test_recall_and_5cm5deg_by_hand() -> None:
    assert summaries.recall([0.01, 0.05, 0.2, np.nan], 0.05) == pytest.approx(0.25)  # strict <
    assert summaries.recall([0.01, 0.05, 0.2, 0.02], 0.1) == pytest.approx(0.75)
    t = [0.01, 0.04, 0.06, 0.01]
    r = [1.0, 6.0, 1.0, 4.9]
    assert summaries.recall_5cm5deg(t, r) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="differ in length"):
        summaries.recall_5cm5deg([0.0], [0.0, 1.0])
    with pytest.raises(ValueError, match="errors must not be empty"):
        summaries.recall([], 1.0)


def test_add_auc_by_hand() -> None:
    # Each error e < 10 cm is correct over the thresholds (e, 0.1]: a fraction 1 - e / 0.1.
    assert summaries.add_auc([0.0, 0.05, 0.2]) == pytest.approx((1.0 + 0.5 + 0.0) / 3.0)
    assert summaries.add_auc([0.025], max_threshold=0.05) == pytest.approx(0.5)
    assert summaries.add_auc([np.nan, 0.0]) == pytest.approx(0.5)


def test_add_auc_matches_a_fine_threshold_grid() -> None:
    rng = np.random.default_rng(4)
    errors = rng.exponential(0.04, size=50)
    thresholds = np.linspace(0.0, 0.1, 100001)
    curve = np.array([summaries.recall(errors, th) for th in thresholds[::100]])
    numeric = np.trapezoid(curve, thresholds[::100]) / 0.1
    assert summaries.add_auc(errors) == pytest.approx(numeric, abs=2e-3)


def test_summary_stats_and_outlier_rate_by_hand() -> None:
    stats = summaries.summary_stats([1.0, 2.0, 3.0, 4.0, 10.0])
    assert stats["mean"] == pytest.approx(4.0)
    assert stats["std"] == pytest.approx(math.sqrt((9 + 4 + 1 + 0 + 36) / 5.0))
    assert stats["median"] == pytest.approx(3.0)
    assert stats["p90"] == pytest.approx(4.0 + 0.6 * 6.0)  # index 3.6 between 4 and 10
    assert summaries.outlier_rate([1.0, 16.0, 15.0, 90.0]) == pytest.approx(0.5)  # strict >
    assert summaries.outlier_rate([1.0, 16.0], threshold=20.0) == 0.0


def test_iou_accuracy_and_invalid_rate_by_hand() -> None:
    ious = [1.0, 0.6, 0.5, 0.2, np.nan]
    assert summaries.iou_accuracy(ious) == pytest.approx(0.4)  # strict >, NaN fails
    assert summaries.invalid_rate(ious) == pytest.approx(0.6)  # <= 0.5 and NaN
    assert summaries.iou_accuracy(ious, threshold=0.1) == pytest.approx(0.8)
    with pytest.raises(InvalidArgumentError, match="threshold"):
        summaries.iou_accuracy(ious, threshold=1.0)


def test_add_metric_name_follows_the_symmetry_set() -> None:
    assert m.add_metric_name(m.identity_symmetry()) == "ADD"
    assert m.add_metric_name(z_symmetries(1)) == "ADD"
    assert m.add_metric_name(z_symmetries(2)) == "ADD-S"
    shifted = [{"R": np.eye(3), "t": np.array([[0.0], [0.0], [0.01]])}]
    assert m.add_metric_name(m.identity_symmetry() + shifted) == "ADD-S"
    with pytest.raises(InvalidArgumentError, match="at least one"):
        m.add_metric_name([])


def test_diameter_by_hand() -> None:
    rng = np.random.default_rng(5)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-2, 2) for z in (-0.5, 0.5)]) * 0.1
    inner = rng.uniform(-1.0, 1.0, size=(500, 3)) * np.array([0.1, 0.2, 0.05])
    pts = np.concatenate([inner, corners])
    expected = 2.0 * math.sqrt(0.1**2 + 0.2**2 + 0.05**2)
    assert m.diameter(pts) == pytest.approx(expected)
    # A flat (degenerate) point set takes the fallback path.
    flat = pts.copy()
    flat[:, 2] = 0.0
    assert m.diameter(flat) == pytest.approx(2.0 * math.sqrt(0.1**2 + 0.2**2))


def test_diameter_of_many_hull_points_is_exact() -> None:
    # Every vertex of a dense ellipsoid is on its hull: the grouped search gives what the
    # comparison of every pair gives, here and on clouds of other shapes.
    import trimesh
    from scipy.spatial.distance import cdist

    ellipsoid = trimesh.creation.icosphere(subdivisions=5, radius=0.02).vertices * [1.1, 1, 0.97]
    rng = np.random.default_rng(3)
    clouds = [ellipsoid, rng.normal(size=(20000, 3)) * [1, 2, 0.5], rng.uniform(size=(3000, 3))]
    for pts in clouds:
        exact = max(cdist(pts[a : a + 2000], pts).max() for a in range(0, len(pts), 2000))
        assert m.diameter(pts) == pytest.approx(exact, rel=1e-12)


def test_input_validation() -> None:
    pts = np.zeros((3, 3))
    with pytest.raises(ValueError, match="t_est must be a finite vector"):
        m.add(np.eye(3), np.zeros(4), np.eye(3), np.zeros(3), pts)
    with pytest.raises(ValueError, match=r"pts must be a finite \(N, 3\)"):
        m.add(np.eye(3), np.zeros(3), np.eye(3), np.zeros(3), np.zeros((0, 3)))
    with pytest.raises(ValueError, match="keys 'R' and 't'"):
        m.mssd(np.eye(3), np.zeros(3), np.eye(3), np.zeros(3), pts, [{"R": np.eye(3)}])
    with pytest.raises(ValueError, match="at least one"):
        m.mssd(np.eye(3), np.zeros(3), np.eye(3), np.zeros(3), pts, [])


# --------------------------------------------------------------------------- BOP sets and AR


def test_symmetry_set_discretises_a_continuous_symmetry_as_bop_does() -> None:
    offset = np.array([0.01, -0.02, 0.0])
    syms = m.symmetry_set(continuous=[{"axis": [0.0, 0.0, 2.0], "offset": offset}])
    # ceil(pi / 0.01) = 315 rotations by 2 pi k / 315 about z through the offset point.
    assert len(syms) == 315
    for k in (0, 1, 100, 314):
        np.testing.assert_allclose(syms[k]["R"], rot_z(2.0 * math.pi * k / 315), atol=1e-12)
        # The axis through the offset is fixed by every one.
        p = offset + np.array([0.0, 0.0, 0.3])
        np.testing.assert_allclose(syms[k]["R"] @ p + syms[k]["t"][:, 0], p, atol=1e-15)
    # With a discrete half turn about x, each discretised rotation follows it (discrete-major).
    flip = np.eye(4)
    flip[:3, :3] = np.diag([1.0, -1.0, -1.0])
    both = m.symmetry_set([flip], [{"axis": [0, 0, 1], "offset": [0, 0, 0]}])
    assert len(both) == 630
    np.testing.assert_allclose(both[315 + 7]["R"], rot_z(2 * math.pi * 7 / 315) @ flip[:3, :3])
    assert (
        len(
            m.symmetry_set(
                continuous=[{"axis": [1, 0, 0], "offset": [0, 0, 0]}], max_sym_disc_step=0.5
            )
        )
        == 7
    )


def test_symmetries_from_models_info_reads_mm() -> None:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rot_z(math.pi), [10.0, 0.0, 0.0]
    syms = m.symmetries_from_models_info({"symmetries_discrete": [list(T.reshape(-1))]})
    assert len(syms) == 2
    np.testing.assert_allclose(syms[0]["R"], np.eye(3))
    np.testing.assert_allclose(syms[1]["t"][:, 0], [0.01, 0.0, 0.0])
    assert len(m.symmetries_from_models_info({})) == 1


def test_mssd_and_mspd_with_a_continuous_symmetry_by_hand() -> None:
    # A ring of radius r about z, facing the camera at depth z0, turned by a about its axis.
    r, z0, a = 0.05, 0.8, 0.3
    angles = np.linspace(0.0, 2.0 * math.pi, 360, endpoint=False)
    pts = np.stack([r * np.cos(angles), r * np.sin(angles), np.zeros_like(angles)], axis=1)
    t = np.array([0.0, 0.0, z0])
    syms = m.symmetry_set(continuous=[{"axis": [0, 0, 1], "offset": [0, 0, 0]}])
    # The nearest discretised turn leaves |a - 2 pi k / 315|; every point moves by its chord.
    step = 2.0 * math.pi / 315
    residual = abs(a - round(a / step) * step)
    chord = 2.0 * r * math.sin(residual / 2.0)
    assert m.mssd(rot_z(a), t, np.eye(3), t, pts, syms) == pytest.approx(chord, rel=1e-9)
    assert m.mssd(rot_z(a), t, np.eye(3), t, pts, m.identity_symmetry()) == pytest.approx(
        2.0 * r * math.sin(a / 2.0), rel=1e-9
    )
    # In the image the ring is a circle of radius f r / z0: the same chord, scaled by f / z0.
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    assert m.mspd(rot_z(a), t, np.eye(3), t, K, pts, syms) == pytest.approx(
        500.0 / z0 * chord, rel=1e-9
    )


def test_average_recall_by_hand() -> None:
    # Thresholds 0.05..0.5 x diameter 1: 0.01 passes all 10, 0.12 passes 0.15..0.5 (8),
    # 0.32 passes 0.35..0.5 (4), a missing estimate none.
    assert m.ar_mssd([0.01, 0.12, 0.32, None], 1.0) == pytest.approx(22 / 40)
    # Per-object diameters: 0.12 of a 0.5 m object is 0.24 of it: passes 0.25..0.5 (6).
    assert m.ar_mssd([0.01, 0.12], [1.0, 0.5]) == pytest.approx(16 / 20)
    # MSPD at 640 px: 4 px passes all, 22 px 25..50 (6), nan none; at 1280 px wide 22 px passes
    # the thresholds 30..100 (8).
    assert m.ar_mspd([4.0, 22.0, float("nan")]) == pytest.approx(16 / 30)
    assert m.ar_mspd([22.0], image_width=1280) == pytest.approx(8 / 10)
    # VSD: one image with errors 0.12 at every tau passes 8 of 10 thresholds at each tau.
    assert m.ar_vsd([[0.12] * 10, None]) == pytest.approx(80 / 200)
    assert m.average_recall([0.2, 0.4], [0.3]) == 0.5
    with pytest.raises(InvalidArgumentError, match="must not be empty"):
        m.ar_mssd([], 1.0)
    with pytest.raises(InvalidArgumentError, match="one column per tau"):
        m.ar_vsd([[0.1, 0.2]])


# --------------------------------------------------------------------------- VSD

SQUARE_FACES = np.array([[0, 1, 2], [0, 2, 3]])


def square(half: float) -> np.ndarray:
    """A square of side 2 half [m] in the object's xy-plane (two triangles, SQUARE_FACES)."""
    return np.array(
        [[-half, -half, 0.0], [half, -half, 0.0], [half, half, 0.0], [-half, half, 0.0]]
    )


K100 = np.array([[100.0, 0.0, 50.0], [0.0, 100.0, 50.0], [0.0, 0.0, 1.0]])


def test_render_depth_of_a_square_by_hand() -> None:
    # Side 0.205 m at 1 m: u from 39.75 to 60.25, so the pixels 40..60 in both directions.
    d = m.render_depth(square(0.1025), SQUARE_FACES, np.eye(3), [0.0, 0.0, 1.0], K100, 100, 100)
    assert np.count_nonzero(d) == 21 * 21
    np.testing.assert_allclose(d[40:61, 40:61], 1.0, rtol=1e-12)
    # Tilted by 30 deg about y: the depth at each covered pixel is the plane's along its ray.
    R = Rotation.from_euler("y", 30, degrees=True).as_matrix()
    d = m.render_depth(square(0.1), SQUARE_FACES, R, [0.0, 0.0, 1.0], K100, 100, 100)
    ys, xs = np.nonzero(d)
    n = R[:, 2]  # the plane through (0, 0, 1) with normal n: n . (z ray) = n . (0, 0, 1)
    ray = np.stack([(xs - 50) / 100, (ys - 50) / 100, np.ones_like(xs, float)], axis=1)
    np.testing.assert_allclose(d[ys, xs], n[2] / (ray @ n), rtol=1e-12)
    # Behind the camera: nothing.
    assert not m.render_depth(
        square(0.1), SQUARE_FACES, np.eye(3), [0, 0, -1.0], K100, 100, 100
    ).any()


def test_vsd_by_hand() -> None:
    verts = square(0.1025)
    diam = 2 * 0.1025 * math.sqrt(2.0)
    t_gt = np.array([0.0, 0.0, 1.0])
    test = m.render_depth(verts, SQUARE_FACES, np.eye(3), t_gt, K100, 100, 100)
    same = m.vsd(np.eye(3), t_gt, np.eye(3), t_gt, test, K100, verts, SQUARE_FACES, diam)
    np.testing.assert_array_equal(same, np.zeros(10))
    # 5 cm further: 19 x 19 pixels (u from 40.24 to 59.76), all inside the true 21 x 21, each
    # 0.05..0.0505 m (0.172..0.175 diameters) off: wrong at tau 0.05..0.15, right from 0.2;
    # the 80 pixels of the true square it leaves are wrong at every tau.
    e = m.vsd(
        np.eye(3),
        np.array([0.0, 0.0, 1.05]),
        np.eye(3),
        t_gt,
        test,
        K100,
        verts,
        SQUARE_FACES,
        diam,
    )
    np.testing.assert_allclose(e, [1.0] * 3 + [80 / 441] * 7, rtol=1e-12)
    # Out of the image: nothing of it is visible, the error is 1.
    far = m.vsd(np.eye(3), [5.0, 0, 1], np.eye(3), t_gt, test, K100, verts, SQUARE_FACES, diam)
    np.testing.assert_array_equal(far, np.ones(10))
