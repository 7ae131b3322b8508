"""Camera model of `posegrasp.world.camera`, checked against renders (docs/DESIGN.md §4).

Small spheres are placed in front of a camera; the centroid of each sphere's rendered
segmentation mask must agree with its centre projected by `intrinsics()` and `T_world_cam()`.
The sphere positions are computed in this file from the camera's MJCF pose, independently of
`T_world_cam`.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from posegrasp.core.errors import InvalidArgumentError, UnknownNameError
from posegrasp.world import constants as C
from posegrasp.world.camera import (
    CameraRenderer,
    RenderOptions,
    T_world_cam,
    _shared_cache,
    camera_intrinsics,
    check_resolution,
    same_render_assets,
    scene_capacity,
)

FOVY_DEG = 50.0
CAM_POS = np.array([0.3, -0.2, 1.1])
#: Camera axes in the world (MuJoCo convention: x right, y up, looking along -z).
CAM_X = np.array([0.8, 0.6, 0.0])
CAM_Y = np.array([-0.3 * 0.6, 0.3 * 0.8, np.sqrt(1 - 0.3**2)])
#: Sphere centres as (horizontal, vertical) fractions of the half field of view and depth [m].
SPHERE_DIRS = [(0.0, 0.0), (0.5, -0.3), (-0.85, 0.8), (0.85, -0.8), (-0.9, -0.1), (0.2, 0.88)]
SPHERE_DEPTH = (1.0, 1.4, 0.9, 1.2, 1.1, 1.3)


def _sphere_centres(aspect: float, radius_px: float, height: int) -> tuple[np.ndarray, float]:
    """World centres of the spheres for an image of the given aspect, and their radius [m].

    Directions are built from the camera's own axes and fovy, not from `posegrasp.world.camera`.
    """
    z_mj = np.cross(CAM_X, CAM_Y)
    tan_y = np.tan(np.deg2rad(FOVY_DEG) / 2)
    f_px = (height / 2) / tan_y
    centres = []
    for (a, b), depth in zip(SPHERE_DIRS, SPHERE_DEPTH, strict=True):
        x = a * tan_y * aspect * depth
        y = b * tan_y * depth
        centres.append(CAM_POS + x * CAM_X + y * CAM_Y - depth * z_mj)
    # A radius that renders about radius_px pixels at the nearest depth.
    radius = radius_px / f_px * min(SPHERE_DEPTH)
    return np.array(centres), radius


def _sphere_scene(centres: np.ndarray, radius: float) -> mujoco.MjModel:
    xyaxes = " ".join(f"{v:.17g}" for v in (*CAM_X, *CAM_Y))
    spheres = "".join(
        f'<geom name="s{i}" type="sphere" size="{radius:.17g}" pos="{c[0]:.17g} {c[1]:.17g} '
        f'{c[2]:.17g}" rgba="1 1 1 1"/>'
        for i, c in enumerate(centres)
    )
    xml = (
        '<mujoco><visual><global offwidth="800" offheight="800"/></visual><worldbody>'
        f'<camera name="cam" pos="{" ".join(map(str, CAM_POS))}" xyaxes="{xyaxes}" '
        f'fovy="{FOVY_DEG}"/>{spheres}</worldbody></mujoco>'
    )
    return mujoco.MjModel.from_xml_string(xml)


def _project(K: np.ndarray, T_w_c: np.ndarray, p_world: np.ndarray) -> np.ndarray:
    p_cam = np.linalg.inv(T_w_c) @ np.append(p_world, 1.0)
    uvw = K @ p_cam[:3]
    return uvw[:2] / uvw[2]


@pytest.mark.parametrize(("width", "height"), [(640, 480), (321, 241), (200, 300), (256, 256)])
def test_sphere_centroids_match_projection(width: int, height: int) -> None:
    # About 5 px radius: the mask centroid of an off-axis sphere is then within a few hundredths
    # of a pixel of the projected centre (perspective shift ~ f tan(angle) (r / z)^2); what is
    # left is the quantisation of a ~80 px disk. A half-pixel error in cx, cy (e.g. W/2 instead
    # of (W-1)/2) breaks both bounds.
    centres, radius = _sphere_centres(width / height, radius_px=5.0, height=height)
    model = _sphere_scene(centres, radius)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    K = camera_intrinsics(model, "cam", width, height)
    T = T_world_cam(model, data, "cam")
    with CameraRenderer(model, width, height, RenderOptions(shadows=False)) as renderer:
        seg = renderer.segmentation(data, "cam")
    assert seg.shape == (height, width)
    errors = []
    for i, c in enumerate(centres):
        mask = seg == model.geom(f"s{i}").id
        v, u = np.nonzero(mask)
        assert mask.sum() > 30, f"sphere {i} barely visible"
        # Fully inside the image: the centroid is not clipped.
        assert u.min() > 0 and v.min() > 0 and u.max() < width - 1 and v.max() < height - 1
        centroid = np.array([u.mean(), v.mean()])
        errors.append(np.linalg.norm(centroid - _project(K, T, c)))
    errors = np.array(errors)
    assert errors.max() < 0.5, errors
    assert errors.mean() < 0.2, errors


def test_T_world_cam_is_rigid_and_matches_mjcf_axes() -> None:
    centres, radius = _sphere_centres(4 / 3, radius_px=5.0, height=480)
    model = _sphere_scene(centres, radius)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    T = T_world_cam(model, data, "cam")
    R = T[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_array_equal(T[3], [0.0, 0.0, 0.0, 1.0])
    np.testing.assert_allclose(T[:3, 3], CAM_POS, atol=1e-12)
    # OpenCV axes: x right = MuJoCo x, y down = -MuJoCo y, z forward = -MuJoCo z.
    np.testing.assert_allclose(R[:, 0], CAM_X, atol=1e-9)
    np.testing.assert_allclose(R[:, 1], -CAM_Y, atol=1e-9)
    np.testing.assert_allclose(R[:, 2], -np.cross(CAM_X, CAM_Y), atol=1e-9)
    # Every sphere is in front of the camera.
    p_cam = (np.linalg.inv(T) @ np.c_[centres, np.ones(len(centres))].T)[:3]
    assert np.all(p_cam[2] > 0.5)


def test_depth_at_sphere_centres() -> None:
    width, height = 320, 240
    centres, radius = _sphere_centres(width / height, radius_px=8.0, height=height)
    model = _sphere_scene(centres, radius)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    K = camera_intrinsics(model, "cam", width, height)
    T_c_w = np.linalg.inv(T_world_cam(model, data, "cam"))
    with CameraRenderer(model, width, height, RenderOptions(shadows=False)) as renderer:
        depth = renderer.depth(data, "cam")
    assert depth.shape == (height, width) and depth.dtype == np.float32
    for c in centres:
        c_cam = (T_c_w @ np.append(c, 1.0))[:3]
        u, v = np.rint(_project(K, np.linalg.inv(T_c_w), c)).astype(int)
        # Exact depth of the sphere's surface along the ray through that pixel centre.
        d = np.linalg.solve(K, [u, v, 1.0])
        dc, dd = d @ c_cam, d @ d
        t = (dc - np.sqrt(dc**2 - dd * (c_cam @ c_cam - radius**2))) / dd
        assert depth[v, u] == pytest.approx(t * d[2], abs=1e-3)
        assert c_cam[2] - radius - 1e-3 <= depth[v, u] <= c_cam[2]


def test_background_is_minus_one() -> None:
    centres, radius = _sphere_centres(1.0, radius_px=5.0, height=64)
    model = _sphere_scene(centres, radius)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    with CameraRenderer(model, 64, 64, RenderOptions(shadows=False)) as renderer:
        seg = renderer.segmentation(data, "cam")
    assert seg.dtype == np.int32
    assert seg[0, 0] == -1
    assert set(np.unique(seg)) <= {-1, *range(model.ngeom)}


def test_intrinsics_formula() -> None:
    centres, radius = _sphere_centres(1.0, radius_px=5.0, height=100)
    model = _sphere_scene(centres, radius)
    K = camera_intrinsics(model, "cam", 101, 60)
    f = 30 / np.tan(np.deg2rad(FOVY_DEG) / 2)
    np.testing.assert_allclose(K, [[f, 0, 50.0], [0, f, 29.5], [0, 0, 1]])


def test_head_camera_intrinsics_use_its_fovy() -> None:
    from posegrasp.world.robot import fetch_spec

    model = fetch_spec().compile()
    fovy = model.cam_fovy[model.camera(C.HEAD_CAMERA).id]
    K = camera_intrinsics(model, C.HEAD_CAMERA, 640, 480)
    assert K[1, 1] == pytest.approx(240 / np.tan(np.deg2rad(fovy) / 2))


def test_bad_camera_and_resolution() -> None:
    centres, radius = _sphere_centres(1.0, radius_px=5.0, height=64)
    model = _sphere_scene(centres, radius)
    with pytest.raises(UnknownNameError, match="valid cameras: cam"):
        camera_intrinsics(model, "nope", 64, 64)
    for w, h in ((0, 10), (10, -1), (5000, 10)):
        with pytest.raises(InvalidArgumentError, match=r"1\.\.4096"):
            check_resolution(w, h)
        with pytest.raises(InvalidArgumentError):
            CameraRenderer(model, w, h)


def test_render_context_shared_across_scenes_renders_what_a_fresh_one_does() -> None:
    # Scenes rebuilt with other objects share the robot's meshes and the room's textures, so the
    # second renderer reuses the first's render context; its images must be a fresh context's.
    from posegrasp.world.scene import SceneConfig, build_scene

    cfg = SceneConfig(n_distractors=2, randomize_appearance=True)
    first = build_scene("car", 3, cfg)
    second = build_scene("phone", 4, cfg)
    assert same_render_assets(first.model, second.model)
    bigger = build_scene("phone", 4, cfg).model
    bigger.vis.global_.offwidth += 1  # another offscreen buffer: not the same context
    assert not same_render_assets(first.model, bigger)
    retextured = build_scene("phone", 4, cfg).model
    retextured.tex_data[0] ^= 1  # another texture: not the same context
    assert not same_render_assets(first.model, retextured)
    with CameraRenderer(first.model, 160, 120) as r:
        r.rgb(first.data, C.HEAD_CAMERA)
    with CameraRenderer(second.model, 160, 120) as r:  # reuses the cached context
        reused = (r.rgb(second.data, C.HEAD_CAMERA), r.segmentation(second.data, C.HEAD_CAMERA))
    _shared_cache().free()
    with CameraRenderer(second.model, 160, 120) as r:  # builds a new one
        fresh = (r.rgb(second.data, C.HEAD_CAMERA), r.segmentation(second.data, C.HEAD_CAMERA))
    assert np.array_equal(reused[0], fresh[0]) and np.array_equal(reused[1], fresh[1])
    assert reused[0].std() > 0 and (reused[1] >= 0).any()


def test_scene_capacity_covers_every_geom() -> None:
    from posegrasp.world.scene import SceneConfig, build_scene

    model = build_scene("chair", 0, SceneConfig(n_distractors=3)).model
    assert scene_capacity(model) > 2 * model.ngeom
