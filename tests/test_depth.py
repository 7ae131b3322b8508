"""The depth observation: metric z along the optical axis, checked against the known geometry."""

from __future__ import annotations

import warnings

import gymnasium as gym
import mujoco
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import posegrasp  # noqa: F401  (registers the env)
from posegrasp.core.contract import CONTRACT_VERSION, Observation
from posegrasp.core.errors import UnknownNameError
from posegrasp.core.transforms import quat_to_mat
from posegrasp.world import constants as C
from sim.env import GraspEvalEnv
from sim.episodes.episode import Episode, EpisodeConfig

W, H = 320, 240


@pytest.fixture(scope="module", params=[("phone", 3), ("chair", 5)], ids=["phone", "chair"])
def seen(request):
    """An rgbd observation, its segmentation and the episode, for one object and seed."""
    obj, seed = request.param
    ep = Episode(obj, seed, EpisodeConfig(width=W, height=H, obs_mode="rgbd"))
    obs = ep.observe()
    seg = ep.renderer.segmentation(ep.scene.data, C.HEAD_CAMERA)
    yield ep, obs, seg
    ep.close()


def _rays(K: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """K^-1 (u, v, 1) of every pixel centre, (H * W, 3), z = 1."""
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]]
    return np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3) @ np.linalg.inv(K).T


def _box_distance(x: np.ndarray, half: np.ndarray) -> np.ndarray:
    """|signed distance| of points x (N, 3), in a box's frame, to its surface (half-sizes)."""
    q = np.abs(x) - half
    return np.abs(np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0))


def _part_distance(parts, P: np.ndarray) -> np.ndarray:
    """Distance of points P (N, 3) in O to the nearest surface of an object's primitives."""
    best = np.full(len(P), np.inf)
    for p in parts:
        x = (P - p.pos) @ quat_to_mat(p.quat)
        if p.type == "box":
            d = _box_distance(x, p.size)
        elif p.type == "cylinder":
            q = np.stack([np.hypot(x[:, 0], x[:, 1]) - p.size[0], np.abs(x[:, 2]) - p.size[1]], 1)
            d = np.abs(np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0))
        else:
            d = np.abs(np.linalg.norm(x, axis=1) - p.size[0])
        best = np.minimum(best, d)
    return best


def _ray_cast_z(triangles: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """z of the first hit of rays from the origin along `rays` (N, 3) on `triangles` (M, 3, 3)
    (Moller-Trumbore), nan where none is hit."""
    v0, e1, e2 = (
        triangles[:, 0],
        triangles[:, 1] - triangles[:, 0],
        triangles[:, 2] - triangles[:, 0],
    )
    first = np.full(len(rays), np.inf)
    for s in range(0, len(rays), 1024):
        d = rays[s : s + 1024, None, :]
        p = np.cross(d, e2[None])
        det = (e1[None] * p).sum(-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            q = np.cross(-v0[None], e1[None])
            a = (-v0[None] * p).sum(-1) * inv
            b = (d * q).sum(-1) * inv
            t = (e2[None] * q).sum(-1) * inv
        hit = (np.abs(det) > 1e-15) & (a >= 0) & (b >= 0) & (a + b <= 1) & (t > 0)
        first[s : s + 1024] = np.where(hit, t, np.inf).min(axis=1)
    return np.where(np.isfinite(first), first * rays[:, 2], np.nan)


def test_depth_is_float32_metres_of_the_image_size(seen) -> None:
    _, obs, _ = seen
    assert obs.depth.shape == (H, W) and obs.depth.dtype == np.float32
    assert np.all(np.isfinite(obs.depth)) and obs.depth.min() > 0.3  # nothing nearer the head
    assert obs.depth.max() < 10.0  # the room's walls, not the far clipping plane


def test_table_pixels_lie_on_the_table_plane(seen) -> None:
    ep, obs, seg = seen
    table = ep.scene.model.geom("table_top").id
    on_table = (seg == table).reshape(-1)
    rays = _rays(obs.K, obs.depth.shape)
    # Each pixel's ray meets the plane z = table_top_z (world) at camera depth s.
    R, t = obs.T_world_cam[:3, :3], obs.T_world_cam[:3, 3]
    s = (obs.table_top_z - t[2]) / (rays @ R.T)[:, 2]
    err = np.abs(obs.depth.reshape(-1) - s)[on_table]
    assert on_table.sum() > 10_000
    assert np.median(err) < 1e-4  # 0.1 mm
    assert np.mean(err < 1e-3) > 0.9  # the rest: the top's 3 cm thick sides
    # Every table-top pixel back-projects onto the surface of the table-top box.
    P = rays[on_table] * obs.depth.reshape(-1)[on_table, None]
    g = ep.scene.data.geom(table)
    x = (P @ R.T + t - g.xpos) @ g.xmat.reshape(3, 3)
    assert np.percentile(_box_distance(x, ep.scene.model.geom_size[table]), 99) < 1e-3


def test_object_pixels_lie_on_the_object_surface(seen) -> None:
    ep, obs, seg = seen
    m, target = ep.scene.model, ep.scene.target
    body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, target.body)
    mine = np.isin(seg, np.flatnonzero(m.geom_bodyid == body)).reshape(-1)
    assert mine.sum() > 500
    rays = _rays(obs.K, obs.depth.shape)[mine]
    z = obs.depth.reshape(-1)[mine].astype(float)
    # Back-projected with the true pose, each pixel is on one of the object's primitives.
    T = ep.T_C_O_true
    P_O = (rays * z[:, None] - T[:3, 3]) @ T[:3, :3]
    dist = _part_distance(target.model.parts, P_O)
    assert np.median(dist) < 1e-4 and np.percentile(dist, 99) < 1e-3
    # And agrees with a ray cast of the object's mesh (the metrics' model) at the true pose.
    tri = np.asarray(target.model.mesh.triangles) @ T[:3, :3].T + T[:3, 3]
    sample = np.arange(0, len(rays), max(1, len(rays) // 2000))
    z_mesh = _ray_cast_z(tri, rays[sample])
    hit = np.isfinite(z_mesh)
    assert hit.mean() > 0.98
    err = np.abs(z[sample][hit] - z_mesh[hit])
    assert np.median(err) < 1e-4 and np.percentile(err, 95) < 1e-3


def test_rgb_is_the_same_with_and_without_depth() -> None:
    obs, timings = {}, {}
    for mode in ("rgb", "rgbd"):
        ep = Episode("faucet", 4, EpisodeConfig(width=W, height=H, obs_mode=mode))
        try:
            obs[mode], timings[mode] = ep.observe(), dict(ep.timings_ms)
        finally:
            ep.close()
    assert obs["rgb"].rgb.tobytes() == obs["rgbd"].rgb.tobytes()
    assert obs["rgb"].depth is None and obs["rgbd"].depth is not None
    assert "render_depth" in timings["rgbd"] and "render_depth" not in timings["rgb"]


def test_the_contract_names_depth_as_an_optional_field() -> None:
    assert CONTRACT_VERSION >= 2
    obs = Observation(np.zeros((2, 2, 3), np.uint8), np.eye(3), np.eye(4), "car", 0)
    assert obs.depth is None  # a version-1 observation is still a valid one


def test_a_bad_obs_mode_names_the_valid_ones() -> None:
    with pytest.raises(UnknownNameError, match="valid observation modes: rgb, rgbd"):
        EpisodeConfig(obs_mode="depth")
    with pytest.raises(UnknownNameError, match="valid observation modes: rgb, rgbd"):
        GraspEvalEnv(obs_mode="rgb-d")


def test_env_rgbd_observes_depth_and_passes_check_env() -> None:
    env = GraspEvalEnv(object="screen", width=64, height=48, obs_mode="rgbd")
    assert env.observation_space["depth"].shape == (48, 64)
    assert env.observation_space["depth"].dtype == np.float32
    obs, _ = env.reset(seed=6)
    assert obs in env.observation_space and obs["depth"].min() > 0.0
    ep = Episode("screen", 6, EpisodeConfig(width=64, height=48, obs_mode="rgbd"))
    try:
        np.testing.assert_array_equal(obs["depth"], ep.observe().depth)
    finally:
        ep.close()
    env.close()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # advisory warnings about unbounded Box spaces
        made = gym.make(
            "posegrasp:GraspEval-v0", object="screen", width=64, height=48, obs_mode="rgbd"
        )
        check_env(made.unwrapped)
        made.close()
