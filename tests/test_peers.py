"""The classical peers (`perception.peers`): their geometry checked against independent
computations, their contract (no depth, no extra), and their poses on ideal depth of one object
alone on the table."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from perception.metrics import rotation_error_sym_deg
from perception.peers import PEER_ESTIMATORS, extra
from perception.peers.estimator import PeerEstimator, Registered
from perception.peers.points import (
    CropConfig,
    back_project,
    model_surface,
    nearest_rigid,
    object_points,
)
from posegrasp.core.contract import Observation, pose_problem
from posegrasp.core.errors import AssetError, InvalidArgumentError
from posegrasp.world.constants import EVAL_SEED_BASE
from posegrasp.world.objects import OBJECT_NAMES, load_object
from sim.episodes.registry import ESTIMATORS, check_depth, make_estimator, needs_depth

HAS_PPF = extra.has_ppf()
HAS_OPEN3D = extra.has_open3d()
needs_ppf = pytest.mark.skipif(not HAS_PPF, reason="the extra peers is not installed")
needs_open3d = pytest.mark.skipif(not HAS_OPEN3D, reason="the extra peers is not installed")
#: A training seed (below `EVAL_SEED_BASE`) for the scenes of these tests.
SEED = 1000


def _scene(obj: str, seed: int = SEED) -> tuple[Observation, np.ndarray]:
    """An isolated-tier scene of obj with ideal depth: its observation and the true T_C_O."""
    from sim.episodes.episode import Episode, EpisodeConfig

    assert seed < EVAL_SEED_BASE
    ep = Episode(obj, seed, EpisodeConfig(obs_mode="rgbd"))
    try:
        return ep.observe(), ep.T_C_O_true.copy()
    finally:
        ep.close()


def _errors(obj: str, T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(rotation error up to the object's symmetries [deg], translation error [mm])."""
    from sim.episodes.episode import object_symmetries

    syms = object_symmetries(load_object(obj))
    rot = rotation_error_sym_deg(T_est[:3, :3], T_true[:3, :3], syms)
    return rot, 1000 * float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))


class _Unreachable:
    """A registration stage that must not be reached."""

    def register(self, model, points_C, seed) -> Registered:
        raise AssertionError("registration reached")


def test_every_peer_is_registered_and_needs_depth() -> None:
    assert set(PEER_ESTIMATORS) == {"ppf", "ppf-det", "fpfh-icp", "fpfh-icp-det",
                                    "hybrid-global-icp"}  # fmt: skip
    for name in PEER_ESTIMATORS:
        assert name in ESTIMATORS and needs_depth(name)
        check_depth(name, "rgbd")
    assert not needs_depth("hybrid-global") and not needs_depth("oracle")


def test_a_peer_without_depth_is_refused_in_one_line() -> None:
    with pytest.raises(InvalidArgumentError) as exc:
        check_depth("fpfh-icp", "rgb")
    message = str(exc.value)
    assert "\n" not in message and "--obs-mode rgbd" in message and "fpfh-icp" in message
    check_depth("hybrid-global", "rgb")


def test_without_depth_there_is_no_estimate_and_the_note_says_why() -> None:
    rgb = np.zeros((4, 4, 3), np.uint8)
    obs = Observation(rgb, np.eye(3), np.eye(4), "phone", 1, table_top_z=0.55)
    est = PeerEstimator("ppf", _Unreachable()).estimate(obs)
    assert est.T_C_O is None and "--obs-mode rgbd" in est.info["note"]
    obs.depth, obs.table_top_z = np.ones((4, 4), np.float32), None
    est = PeerEstimator("ppf", _Unreachable()).estimate(obs)
    assert est.T_C_O is None and "table" in est.info["note"]


@pytest.mark.parametrize("name", ["ppf", "fpfh-icp", "hybrid-global-icp"])
def test_without_the_extra_a_peer_is_one_line_saying_how_to_install_it(
    name: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(extra, "has_ppf", lambda: False)
    monkeypatch.setattr(extra, "has_open3d", lambda: False)
    with pytest.raises(AssetError) as exc:
        make_estimator(name)
    message = str(exc.value)
    assert "\n" not in message and "pip install -e '.[peers]'" in message and name in message


def test_back_projection_inverts_the_pinhole_projection() -> None:
    rng = np.random.default_rng(0)
    K = np.array([[520.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])
    depth = rng.uniform(0.5, 2.0, (48, 64)).astype(np.float32)
    depth[3, 5], depth[7, 9] = 0.0, np.nan  # no depth: no point
    pts = back_project(depth, K)
    assert pts.shape == (48 * 64 - 2, 3)
    uv = pts @ K.T
    uv = uv[:, :2] / uv[:, 2:]
    v, u = np.nonzero(np.isfinite(depth) & (depth > 0))
    np.testing.assert_allclose(uv, np.stack([u, v], axis=1), atol=1e-9)
    np.testing.assert_allclose(pts[:, 2], depth[v, u], rtol=1e-6)


def test_nearest_rigid_is_a_rotation_and_keeps_a_rotation() -> None:
    rng = np.random.default_rng(1)
    T = np.eye(4)
    T[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    T[:3, :3] *= np.sign(np.linalg.det(T[:3, :3]))
    T[:3, 3] = (0.1, -0.2, 0.8)
    np.testing.assert_allclose(nearest_rigid(T), T, atol=1e-12)
    skewed = T.copy()
    skewed[:3, :3] += 1e-4 * rng.normal(size=(3, 3))
    assert pose_problem(skewed) is not None and pose_problem(nearest_rigid(skewed)) is None


def _plane_depth(part, points: np.ndarray) -> np.ndarray:
    """How far each point lies outside a convex part's face planes (< 0: inside), shape (N,)."""
    mesh = part.mesh()
    normals = np.asarray(mesh.face_normals)
    offsets = np.einsum("ij,ij->i", normals, np.asarray(mesh.triangles)[:, 0])
    return (points @ normals.T - offsets).max(axis=1)


def test_model_samples_lie_on_the_visible_surface() -> None:
    model = load_object("car")
    pts, normals = model_surface(model, 4000, 0)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-9)
    depths = np.stack([_plane_depth(part, pts) for part in model.parts])
    # On the boundary of one part, inside none: the car's parts overlap, and the samples on
    # faces hidden inside another part were dropped.
    assert np.abs(depths).min(axis=0).max() < 1e-6
    assert depths.min(axis=0).min() > -1e-5
    assert 0 < len(pts) < 4000


def test_the_objects_points_lie_on_the_object() -> None:
    from scipy.spatial import cKDTree

    obs, T_true = _scene("phone")
    model = load_object("phone")
    pts = object_points(
        obs.depth, obs.K, obs.T_world_cam, obs.table_top_z, model.diameter, CropConfig()
    )
    assert len(pts) > 1000
    R, t = T_true[:3, :3], T_true[:3, 3]
    pts_O = (pts - t) @ R
    surface, normals = model_surface(model, 50000, 1)
    _, nearest = cKDTree(surface).query(pts_O)
    off_plane = np.abs(np.einsum("ij,ij->i", pts_O - surface[nearest], normals[nearest]))
    assert np.percentile(off_plane, 99) < 0.002


#: A peer's score from which its pose is taken as found (the ICP fitness of ``fpfh-icp``).
CONFIDENT = 0.9


@needs_open3d
@pytest.mark.slow
def test_fpfh_icp_is_exact_when_confident_on_ideal_depth() -> None:
    # RANSAC's global search, even from three seeds, misses some views (the screen's flat
    # panel fits turned, explaining well under CONFIDENT of the scene): a confident pose must
    # be exact, and every object but one is confident.
    estimator = make_estimator("fpfh-icp")
    confident = 0
    for obj in OBJECT_NAMES:
        obs, T_true = _scene(obj)
        est = estimator.estimate(obs)
        assert est.T_C_O is not None, (obj, est.info)
        assert {"features", "ransac", "icp"} <= set(est.info["timings_ms"])
        rot, trans = _errors(obj, est.T_C_O, T_true)
        if est.info["score"] >= CONFIDENT:
            confident += 1
            assert rot < 2.0 and trans < 2.0, (obj, rot, trans, est.info)
    assert confident >= len(OBJECT_NAMES) - 1


@needs_open3d
@pytest.mark.slow
@pytest.mark.parametrize("name", ["fpfh-icp-det", "hybrid-global-icp"])
def test_the_detection_and_learned_peers_on_ideal_depth(name: str) -> None:
    estimator = make_estimator(name)
    confident = 0
    for obj in ("phone", "pistol", "car"):
        obs, T_true = _scene(obj)
        est = estimator.estimate(obs)
        assert est.T_C_O is not None, (obj, est.info)
        assert "score" in est.info and "icp" in est.info["timings_ms"]
        rot, trans = _errors(obj, est.T_C_O, T_true)
        if est.info["score"] >= CONFIDENT:
            confident += 1
            assert rot < 2.0 and trans < 2.0, (name, obj, rot, trans)
    assert confident >= 2


@needs_ppf
@pytest.mark.slow
@pytest.mark.parametrize("name", ["ppf", "ppf-det"])
@pytest.mark.xfail(
    strict=True,
    reason="OpenCV's PPF finds the faucet, the chair and (ppf) the pistol within 2 deg and 2 mm; "
    "the car, the phone and the screen come back turned end for end, or ICP fails",
)
def test_ppf_finds_each_object_alone_on_ideal_depth(name: str) -> None:
    estimator = make_estimator(name)
    for obj in OBJECT_NAMES:
        obs, T_true = _scene(obj)
        est = estimator.estimate(obs)
        assert est.T_C_O is not None and pose_problem(est.T_C_O) is None
        assert {"match", "icp"} <= set(est.info["timings_ms"]) and est.info["votes"] > 0
        rot, trans = _errors(obj, est.T_C_O, T_true)
        assert rot < 2.0 and trans < 2.0, (name, obj, rot, trans)


@pytest.mark.slow
@needs_open3d
@needs_ppf
def test_peers_pickle_without_their_trained_models() -> None:
    obs, _ = _scene("phone")
    for name in ("ppf", "fpfh-icp"):
        estimator = make_estimator(name)
        first = estimator.estimate(obs)
        copy = pickle.loads(pickle.dumps(estimator))
        assert copy.registration._models == {} and copy.registration.config == (
            estimator.registration.config
        )
        again = copy.estimate(obs)
        np.testing.assert_array_equal(first.T_C_O, again.T_C_O)


@needs_open3d
@pytest.mark.slow
def test_a_peer_runs_in_evaluate_workers() -> None:
    from sim.evaluation import Protocol, evaluate_protocol

    protocol = Protocol(["phone", "pistol"], 1, SEED, obs_mode="rgbd")
    report = evaluate_protocol(protocol, "fpfh-icp", workers=2)
    episodes = report["episodes"]
    assert len(episodes) == 2
    for ep in episodes:
        assert ep["estimator"] == "fpfh-icp" and ep["pose_error"] is not None, ep["notes"]
        assert ep["estimate_info"]["score"] > 0.9
        assert ep["pose_error"]["rotation_deg"] < 2.0


@needs_open3d
def test_fpfh_restarts_are_checked_under_their_own_name() -> None:
    from perception.peers.fpfh import FpfhConfig

    with pytest.raises(InvalidArgumentError, match="restarts must be >= 1, not 0"):
        FpfhConfig(restarts=0)


@needs_open3d
@needs_ppf
def test_the_peers_defaults_are_the_points_their_tuning_chose() -> None:
    """`studies/peer_tuning.json` records each grid and the point its rule chose; the configs'
    defaults are those points, and the rule picks the fastest point near the most correct."""
    import json
    from dataclasses import asdict
    from pathlib import Path

    from perception.peers.fpfh import FpfhConfig
    from perception.peers.ppf import PpfConfig

    studies = Path(__file__).resolve().parents[1] / "studies"
    record = json.loads((studies / "peer_tuning.json").read_text())
    for config, name in ((PpfConfig(), "ppf"), (FpfhConfig(), "fpfh-icp")):
        assert json.loads(json.dumps(asdict(config))) == record[name]["best"]

    import importlib.util

    spec = importlib.util.spec_from_file_location("peer_tuning", studies / "peer_tuning.py")
    assert spec is not None and spec.loader is not None
    study = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(study)
    rows = [
        {"values": {"a": 1}, "correct": 40, "images": 48, "time_s_median": 3.0},
        {"values": {"a": 2}, "correct": 39, "images": 48, "time_s_median": 1.0},
        {"values": {"a": 3}, "correct": 37, "images": 48, "time_s_median": 0.5},
    ]
    assert study.chosen(rows)["values"] == {"a": 2}  # SE of 40/48 is 2.6 poses: 37 is outside
    assert study.chosen(rows[:1] + rows[2:])["values"] == {"a": 1}
    for name in ("ppf", "fpfh-icp"):
        assert study.chosen(record[name]["points"])["values"] == record[name]["chosen"]


@needs_ppf
def test_ppf_reports_no_pose_when_opencv_icp_fails_on_every_hypothesis(monkeypatch) -> None:
    """OpenCV's ICP marks a failure with a residual of 1e10 and leaves the pose wherever its
    iterations went (metres away): that is no estimate, not a pose to grasp."""
    from types import SimpleNamespace

    import cv2

    from perception.peers.ppf import PpfConfig, PpfRegistration

    model = load_object("chair")
    pts, _ = model_surface(model, 3000, 0)
    scene = pts + np.array([0.0, 0.0, 0.9])
    stage = PpfRegistration(PpfConfig())
    found = stage.register(model, scene, 0)
    assert found.T_C_O is not None and found.info["icp_residual_diameters"] < 0.05

    class FailingIcp:
        def __init__(self, *args) -> None:
            pass

        @staticmethod
        def registerModelToScene(pc, scene, poses):
            far = np.eye(4)
            far[:3, 3] = (0.0, 0.0, 90.0)
            return 0, [SimpleNamespace(residual=1e10, pose=far) for _ in poses]

    monkeypatch.setattr(cv2.ppf_match_3d, "ICP", FailingIcp)
    failed = stage.register(model, scene, 0)
    assert failed.T_C_O is None and failed.info["note"] == "ICP failed"


@pytest.mark.slow
def test_the_table_band_grows_with_the_sensors_noise_and_not_on_ideal_depth(monkeypatch) -> None:
    """Ideal depth: the table's measured spread is nil and the points are those of the
    configured band, to the bit. A noisy table top (kinect-v1): the band grows to three robust
    standard deviations, and the table's noise no longer stays in the scene as points."""
    from perception.peers import points as P
    from sim.episodes.episode import Episode, EpisodeConfig

    def cut(obs: Observation) -> np.ndarray:
        model = load_object(obs.object)
        assert obs.depth is not None and obs.table_top_z is not None
        return P.object_points(
            obs.depth, obs.K, obs.T_world_cam, obs.table_top_z, model.diameter, P.CropConfig()
        )

    views = {}
    for sensor in ("ideal", "kinect-v1"):
        ep = Episode("pistol", SEED, EpisodeConfig(obs_mode="rgbd", sensor=sensor))
        views[sensor] = ep.observe()
        ep.close()
    adaptive = {s: cut(o) for s, o in views.items()}
    monkeypatch.setattr(P, "table_noise", lambda height: 0.0)
    fixed = {s: cut(o) for s, o in views.items()}
    assert np.array_equal(adaptive["ideal"], fixed["ideal"])
    model = load_object("pistol")
    far = [
        np.linalg.norm(p - np.median(p, axis=0), axis=1) > model.diameter for p in fixed.values()
    ]
    assert far[0].mean() < 0.01  # ideal: every point near the object
    assert far[1].mean() > 0.2  # kinect-v1 at the configured band: the table's noise stays
    stray = np.linalg.norm(adaptive["kinect-v1"] - np.median(adaptive["kinect-v1"], axis=0), axis=1)
    assert (stray > model.diameter).mean() < 0.05


@needs_open3d
def test_icp_gives_the_same_pose_for_the_same_start() -> None:
    """ICP's sums over several threads add in a varying order; on one thread the same scene and
    start give the same pose to the bit, whatever threads Open3D was left with."""
    import open3d as o3d

    from perception.peers.icp import PointToPlaneIcp

    model = load_object("phone")
    pts, _ = model_surface(model, 4000, seed=3)
    T_true = np.eye(4)
    T_true[:3, 3] = (0.02, -0.01, 0.7)
    rng = np.random.default_rng(0)
    points_C = pts @ T_true[:3, :3].T + T_true[:3, 3] + rng.normal(0, 0.001, pts.shape)
    start = T_true.copy()
    start[:3, 3] += (0.004, -0.003, 0.005)
    icp = PointToPlaneIcp()
    threads = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(max(2, threads))
    try:
        poses = [icp.refine(model, points_C, start).T_C_O for _ in range(6)]
    finally:
        o3d.utility.set_max_threads(threads)
    for T in poses[1:]:
        np.testing.assert_array_equal(T, poses[0])
    assert o3d.utility.get_max_threads() == threads
