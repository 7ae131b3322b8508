"""Pose errors of symmetric objects: measured against the equivalent true pose ``T_true S`` of
least MSSD (`perception.metrics.closest_symmetry`, `sim.episodes.episode.pose_errors`), checked
against a brute force over the symmetry set, on hand-made boxes and cylinders and through an
episode of a user object; objects without symmetries keep their errors to the bit."""

from __future__ import annotations

import itertools

import jsonschema
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from perception import metrics
from posegrasp.core.transforms import axis_angle
from posegrasp.world.objects import OBJECT_NAMES, load_object
from sim.episodes.episode import Episode, object_symmetries, pose_errors
from sim.evaluation.report_schema import report_schema

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
#: The keys of `pose_errors` that measure against one pose, and so vanish for a symmetric twin.
PER_POSE_KEYS = (
    "translation_m",
    "translation_pct",
    "rotation_deg",
    "add_m",
    "add_rel_diameter",
    "ray_m",
    "lateral_m",
    "inplane_deg",
    "outplane_deg",
    "mssd_m",
)


def _T(R: np.ndarray, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _turned(T: np.ndarray, axis_C: np.ndarray, deg: float, dt_C) -> np.ndarray:
    """T turned by deg about axis_C (camera frame) through its own origin, then moved by dt_C."""
    out = T.copy()
    out[:3, :3] = axis_angle(axis_C, np.radians(deg)) @ T[:3, :3]
    out[:3, 3] += dt_C
    return out


def _S(sym: metrics.Symmetry) -> np.ndarray:
    return _T(sym["R"], np.reshape(sym["t"], 3))


def _box(centre=(0.0, 0.0, 0.0), extents=(0.18, 0.07, 0.26)) -> np.ndarray:
    """Corners and face centres of a box centred on `centre` in O, (14, 3) [m]."""
    half = np.asarray(extents) / 2
    corners = np.array(list(itertools.product(*[(-h, h) for h in half])))
    faces = np.vstack([np.diag(half), -np.diag(half)])
    return np.vstack([corners, faces]) + centre


def _half_turns(centre: np.ndarray, axes: str = "xyz") -> list[metrics.Symmetry]:
    """The identity and the half turns about axes through `centre` (a box's symmetries)."""
    syms = metrics.identity_symmetry()
    for a in axes:
        R = axis_angle(np.eye(3)["xyz".index(a)], np.pi)
        syms.append({"R": R, "t": (centre - R @ centre).reshape(3, 1)})
    return syms


def _true_pose() -> np.ndarray:
    return _T(axis_angle(np.array([1.0, 0.4, -0.2]), 1.1), (0.05, -0.03, 0.85))


def _angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(R_a @ R_b.T).magnitude()))


@pytest.mark.parametrize("centre", [(0.0, 0.0, 0.0), (0.03, -0.02, 0.01)])
def test_an_estimate_turned_by_a_symmetry_has_no_error(centre) -> None:
    centre = np.asarray(centre)
    pts, syms = _box(centre), _half_turns(centre)
    d = metrics.diameter(pts)
    T_true = _true_pose()
    for k, sym in enumerate(syms):
        T_est = T_true @ _S(sym)
        e = pose_errors(T_est, T_true, pts, d, K, syms)
        for key in PER_POSE_KEYS:
            assert e[key] == pytest.approx(0.0, abs=1e-5), (k, key, e[key])
        assert e["symmetry_index"] == k and e["mspd_px"] == pytest.approx(0.0, abs=1e-6)
        if k:  # without its symmetries the same estimate is half a turn off
            assert pose_errors(T_est, T_true, pts, d)["rotation_deg"] == pytest.approx(180.0)


def test_a_half_turn_of_a_two_fold_box_keeps_only_the_residual_error() -> None:
    pts, syms = _box(), _half_turns(np.zeros(3), "z")
    d = metrics.diameter(pts)
    T_true = _T(axis_angle(np.array([0.3, 1.0, 0.2]), 0.7), (0.0, 0.0, 0.8))  # on the axis
    flipped = T_true @ _S(syms[1])
    # Turned about its origin by 5 deg about the ray (in-plane) and moved 3 mm along it; then
    # turned 4 deg about the camera's x (out-of-plane, perpendicular to the ray), moved 2 mm across.
    in_plane = _turned(flipped, np.array([0.0, 0.0, 1.0]), 5.0, (0.0, 0.0, 0.003))
    out_plane = _turned(flipped, np.array([1.0, 0.0, 0.0]), 4.0, (0.002, 0.0, 0.0))
    for T_est, rot, inp, outp, ray, lat in [
        (in_plane, 5.0, 5.0, 0.0, 0.003, 0.0),
        (out_plane, 4.0, 0.0, 4.0, 0.0, 0.002),
    ]:
        e = pose_errors(T_est, T_true, pts, d, K, syms)
        assert e["symmetry_index"] == 1
        assert e["rotation_deg"] == pytest.approx(rot, abs=1e-9)
        assert e["inplane_deg"] == pytest.approx(inp, abs=1e-6)
        assert e["outplane_deg"] == pytest.approx(outp, abs=1e-6)
        assert e["ray_m"] == pytest.approx(ray, abs=1e-12)
        assert e["lateral_m"] == pytest.approx(lat, abs=1e-12)
        # The moved origin: the ray or lateral offset itself, as the flip keeps the origin.
        assert e["translation_m"] == pytest.approx(max(ray, lat), abs=1e-12)
        assert e["translation_pct"] == pytest.approx(max(ray, lat) / 0.8 * 100, abs=1e-9)
        # ADD by hand, point by point, against the flipped truth.
        want = np.mean(
            [np.linalg.norm((T_est - flipped)[:3, :3] @ x + (T_est - flipped)[:3, 3]) for x in pts]
        )
        assert e["add_m"] == pytest.approx(want, rel=1e-12)
        assert e["add_rel_diameter"] == pytest.approx(want / d, rel=1e-12)
        plain = pose_errors(T_est, T_true, pts, d)
        assert plain["rotation_deg"] > 170.0 and "symmetry_index" not in plain


def _brute_force(T_est, T_true, pts, d, syms) -> tuple[int, dict[str, float]]:
    """The errors against every T_true S, and those of least MSSD, computed point by point."""
    best, best_mssd, best_T = -1, np.inf, None
    for k, sym in enumerate(syms):
        T_ref = T_true @ _S(sym)
        worst = max(
            np.linalg.norm(T_est[:3, :3] @ x + T_est[:3, 3] - T_ref[:3, 3] - T_ref[:3, :3] @ x)
            for x in pts
        )
        if worst < best_mssd:
            best, best_mssd, best_T = k, worst, T_ref
    dt = T_est[:3, 3] - best_T[:3, 3]
    add = np.mean([np.linalg.norm(T_est[:3, :3] @ x + dt - best_T[:3, :3] @ x) for x in pts])
    u = best_T[:3, 3] / np.linalg.norm(best_T[:3, 3])
    # Twist about u and swing of R_est R_ref^T from its quaternion (x, y, z, w): the swing's
    # scalar part is sqrt(w^2 + (v . u)^2).
    *v, w = Rotation.from_matrix(T_est[:3, :3] @ best_T[:3, :3].T).as_quat()
    along = abs(float(np.dot(v, u)))
    return best, {
        "translation_m": float(np.linalg.norm(dt)),
        "translation_pct": float(np.linalg.norm(dt) / np.linalg.norm(best_T[:3, 3]) * 100),
        "rotation_deg": _angle_deg(T_est[:3, :3], best_T[:3, :3]),
        "add_m": float(add),
        "add_rel_diameter": float(add / d),
        "ray_m": float(abs(dt @ u)),
        "lateral_m": float(np.linalg.norm(dt - (dt @ u) * u)),
        "inplane_deg": float(np.degrees(2 * np.arctan2(along, abs(w)))),
        "outplane_deg": float(np.degrees(2 * np.arccos(min(1.0, np.hypot(w, along))))),
        "mssd_m": float(best_mssd),
    }


def test_pose_errors_match_a_brute_force_over_the_symmetry_set() -> None:
    rng = np.random.default_rng(3)
    # A can: a ring at each end; its set turns it about its axis in 11 steps and end over end.
    ang = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    ring = np.column_stack([0.03 * np.cos(ang), 0.03 * np.sin(ang), np.zeros_like(ang)])
    pts = np.vstack([ring - np.array([0, 0, 0.06]), ring + np.array([0, 0, 0.06])])
    flip = _T(axis_angle(np.array([1.0, 0.0, 0.0]), np.pi))
    syms = metrics.symmetry_set(
        [flip], [{"axis": np.array([0, 0, 1.0]), "offset": np.zeros(3)}], 0.3
    )
    assert len(syms) == 2 * 11
    d = metrics.diameter(pts)
    T_true = _true_pose()
    for _ in range(12):
        S = _S(syms[int(rng.integers(len(syms)))])
        noise = _T(Rotation.from_rotvec(rng.normal(0, 0.15, 3)).as_matrix(), rng.normal(0, 0.01, 3))
        T_est = noise @ T_true @ S
        e = pose_errors(T_est, T_true, pts, d, K, syms)
        k, want = _brute_force(T_est, T_true, pts, d, syms)
        assert e["symmetry_index"] == k
        R_e, t_e, R_g, t_g = T_est[:3, :3], T_est[:3, 3], T_true[:3, :3], T_true[:3, 3]
        index, mssd = metrics.closest_symmetry(R_e, t_e, R_g, t_g, pts, syms)
        assert index == k and mssd == pytest.approx(want["mssd_m"], rel=1e-12)
        for key, value in want.items():
            assert e[key] == pytest.approx(value, rel=1e-9, abs=1e-9), key
        # Twist and swing compose to the rotation: neither exceeds it, together they reach it.
        assert max(e["inplane_deg"], e["outplane_deg"]) <= e["rotation_deg"] + 1e-9
        assert e["inplane_deg"] + e["outplane_deg"] >= e["rotation_deg"] - 1e-9


def test_symmetric_pose_composes_and_leaves_the_identity_bit_for_bit() -> None:
    T_true = _true_pose()
    T_true[0, 3] = -0.0
    same = metrics.symmetric_pose(T_true, metrics.identity_symmetry()[0])
    assert same.tobytes() == T_true.tobytes() and same is not T_true
    sym = _half_turns(np.array([0.01, 0.02, -0.03]), "y")[1]
    np.testing.assert_allclose(metrics.symmetric_pose(T_true, sym), T_true @ _S(sym), atol=1e-15)


@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_a_built_in_object_has_no_symmetry_and_keeps_its_errors_to_the_bit(name: str) -> None:
    obj = load_object(name)
    assert obj.symmetries == ()
    pts, d = np.asarray(obj.mesh.vertices), obj.diameter
    rng = np.random.default_rng(OBJECT_NAMES.index(name))
    T_true = _true_pose()
    T_est = T_true.copy()  # turned about its origin at random, and moved
    T_est[:3, :3] = Rotation.from_rotvec(rng.normal(0, 1.0, 3)).as_matrix() @ T_true[:3, :3]
    T_est[:3, 3] += rng.normal(0, 0.03, 3)
    R_e, t_e, R_g, t_g = T_est[:3, :3], T_est[:3, 3], T_true[:3, :3], T_true[:3, 3]
    add = metrics.add(R_e, t_e, R_g, t_g, pts)
    mssd = metrics.mssd(R_e, t_e, R_g, t_g, pts, metrics.identity_symmetry())
    plain = {
        "translation_m": float(np.linalg.norm(t_e - t_g)),
        "translation_pct": float(metrics.translation_error_pct(t_e, t_g)),
        "rotation_deg": float(metrics.rotation_error_deg(R_e, R_g)),
        "add_m": float(add),
        "adi_m": float(metrics.adi(R_e, t_e, R_g, t_g, pts)),
        "add_rel_diameter": float(add / d),
        **metrics.error_components(T_est, T_true),
        "mssd_m": float(mssd),
        "mssd_rel_diameter": float(mssd / d),
        "mspd_px": float(metrics.mspd(R_e, t_e, R_g, t_g, K, pts, metrics.identity_symmetry())),
    }
    assert pose_errors(T_est, T_true, pts, d, K, object_symmetries(obj)) == plain
    assert pose_errors(T_est, T_true, pts, d, K) == plain


class _Flipped:
    """An estimator that answers a fixed pose."""

    name = "flipped"

    def __init__(self, T_C_O: np.ndarray) -> None:
        self.T_C_O = T_C_O

    def estimate(self, obs):
        from posegrasp.core.contract import Estimate

        return Estimate(self.T_C_O.copy())


@pytest.mark.slow
def test_an_episode_of_a_symmetric_user_box_scores_a_flipped_estimate_as_exact(
    monkeypatch, tmp_path
) -> None:
    from posegrasp.world.user_objects import OBJECTS_ENV
    from sim import render_scene
    from sim.add_object import main as add_object

    monkeypatch.setenv(OBJECTS_ENV, str(tmp_path / "objects"))
    trimesh.creation.box(extents=[0.06, 0.04, 0.03]).export(tmp_path / "box.stl")
    argv = [str(tmp_path / "box.stl"), "--name", "cereal", "--units", "m"]
    assert add_object([*argv, "--drops", "16", "--keep", "1"]) == 0
    ep = Episode("cereal", 3)
    try:
        model = ep.scene.target.model
        assert len(model.symmetries) == 3  # half turns about x, y and z
        T_true = ep.T_C_O_true
        for k, S in enumerate(model.symmetries, start=1):
            e = ep.pose_errors(T_true @ S)
            assert e["symmetry_index"] == k
            for key in PER_POSE_KEYS:
                assert e[key] == pytest.approx(0.0, abs=1e-5), (k, key)
        T_flip = T_true @ model.symmetries[0]
        obs = ep.observe()
        _, label, _ = render_scene._estimate_on_head(ep, obs, _Flipped(T_flip))
        assert label.endswith("0 mm, 0.0 deg off"), label
        r = ep.act(T_flip, "flipped")
    finally:
        ep.close()
    assert r.pose_error["rotation_deg"] == pytest.approx(0.0, abs=1e-5)
    assert r.pose_error["add_m"] == pytest.approx(0.0, abs=1e-9)
    assert r.pose_correct is True
    assert r.to_json()["pose_error"]["symmetry_index"] == 1
    # The report's schema takes the index among the pose errors.
    schema = report_schema()["$defs"]["episode"]["properties"]["pose_error"]
    jsonschema.Draft202012Validator(schema).validate(r.to_json()["pose_error"])
