"""Cameras: intrinsics, OpenCV-convention poses and lazily created renderers.

Frames: a MuJoCo camera looks along its -z with y up; posegrasp's camera frame is OpenCV's
(x right, y down, z forward), so `R_world_cv = R_world_mj @ diag(1, -1, -1)`.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from sim.core.errors import AssetError, InvalidArgumentError, UnknownNameError
from sim.core.transforms import intrinsics

R_CV_FROM_MJ = np.diag([1.0, -1.0, -1.0])
MAX_RESOLUTION = (4096, 4096)


def camera_names(model: mujoco.MjModel) -> list[str]:
    """Names of every camera in the model."""
    return [model.camera(i).name for i in range(model.ncam)]


def _camera_id(model: mujoco.MjModel, camera: str) -> int:
    cid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
    if cid < 0:
        raise UnknownNameError("camera", camera, camera_names(model))
    return cid


def check_resolution(width: int, height: int) -> None:
    """Raise InvalidArgumentError unless 1 <= width, height <= 4096."""
    if not (1 <= width <= MAX_RESOLUTION[0] and 1 <= height <= MAX_RESOLUTION[1]):
        raise InvalidArgumentError(
            f"invalid resolution {width}x{height}; width and height must be in 1..4096"
        )


def camera_intrinsics(model: mujoco.MjModel, camera: str, width: int, height: int) -> np.ndarray:
    """Pinhole K of a MuJoCo camera rendered at width x height (`sim.core.transforms.intrinsics`
    of the camera's fovy).

    Returns:
        K, shape (3, 3), in pixels.

    Raises:
        InvalidArgumentError: a resolution outside 1..4096.
        UnknownNameError: no such camera.
    """
    check_resolution(width, height)
    return intrinsics(np.deg2rad(model.cam_fovy[_camera_id(model, camera)]), width, height)


def T_world_cam(model: mujoco.MjModel, data: mujoco.MjData, camera: str) -> np.ndarray:
    """Pose of the camera in the world, OpenCV convention (x right, y down, z forward).

    Needs up-to-date kinematics (mj_forward or mj_kinematics).

    Returns:
        T_world_cam, shape (4, 4): maps camera coordinates to world coordinates [m].
    """
    cid = _camera_id(model, camera)
    T = np.eye(4)
    T[:3, :3] = data.cam_xmat[cid].reshape(3, 3) @ R_CV_FROM_MJ
    T[:3, 3] = data.cam_xpos[cid]
    return T


@dataclass(frozen=True)
class RenderOptions:
    """What the renderer draws.

    Attributes:
        shadows: cast shadows (about 3x slower on software rendering).
        reflections: draw reflections.
    """

    shadows: bool = True
    reflections: bool = False


def _preload_torch() -> None:
    """Import torch, torch._dynamo and torchvision, when installed, before the first GL context.

    Importing them once a MuJoCo GL context exists crashes the process (inside triton). A user
    who renders first (e.g. `GraspEval-v0.reset`) and loads a network afterwards would hit that;
    importing them here, once per process, makes the order irrelevant.
    """
    global _TORCH_PRELOADED
    if _TORCH_PRELOADED:
        return
    _TORCH_PRELOADED = True
    import importlib.util

    if importlib.util.find_spec("torchvision") is None:
        return
    import torch
    import torch._dynamo  # noqa: F401
    import torchvision  # noqa: F401


_TORCH_PRELOADED = False


class CameraRenderer:
    """RGB, depth and segmentation of one model at one resolution.

    The GL context is created on first use, never at construction or import. Call `close()` (or
    use it as a context manager) to free it.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        width: int = 640,
        height: int = 480,
        options: RenderOptions | None = None,
    ) -> None:
        check_resolution(width, height)
        self.model = model
        self.width = width
        self.height = height
        self.options = options or RenderOptions()
        self._renderer: mujoco.Renderer | None = None

    def _get(self) -> mujoco.Renderer:
        if self._renderer is None:
            off = self.model.vis.global_
            off.offwidth = max(off.offwidth, self.width)
            off.offheight = max(off.offheight, self.height)
            _preload_torch()
            try:
                self._renderer = mujoco.Renderer(self.model, self.height, self.width)
            except mujoco.FatalError as exc:
                raise AssetError(
                    "MuJoCo cannot open an OpenGL context: set MUJOCO_GL=egl before mujoco is "
                    "imported (import sim first, or export MUJOCO_GL=egl) and install Mesa's EGL "
                    f"(libegl1, libgl1-mesa-dri); MuJoCo said: {exc}"
                ) from exc
            flags = self._renderer.scene.flags
            flags[mujoco.mjtRndFlag.mjRND_SHADOW] = self.options.shadows
            flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = self.options.reflections
        return self._renderer

    def _update(self, data: mujoco.MjData, camera: str | int) -> mujoco.Renderer:
        r = self._get()
        cam = _camera_id(self.model, camera) if isinstance(camera, str) else camera
        r.update_scene(data, camera=cam)
        return r

    def rgb(self, data: mujoco.MjData, camera: str | int) -> np.ndarray:
        """RGB image, shape (H, W, 3), uint8."""
        r = self._update(data, camera)
        return r.render().copy()

    def depth(self, data: mujoco.MjData, camera: str | int) -> np.ndarray:
        """Depth along the optical axis [m], shape (H, W), float32."""
        r = self._get()
        r.enable_depth_rendering()
        try:
            self._update(data, camera)
            return r.render().astype(np.float32)
        finally:
            r.disable_depth_rendering()

    def segmentation(self, data: mujoco.MjData, camera: str | int) -> np.ndarray:
        """Geom id per pixel (-1 where no geom), shape (H, W), int32."""
        r = self._get()
        r.enable_segmentation_rendering()
        try:
            self._update(data, camera)
            seg = r.render()
        finally:
            r.disable_segmentation_rendering()
        ids = seg[..., 0].astype(np.int32)
        ids[seg[..., 1] != int(mujoco.mjtObj.mjOBJ_GEOM)] = -1
        return ids

    def close(self) -> None:
        """Free the GL context."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def __enter__(self) -> CameraRenderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def body_mask(model: mujoco.MjModel, seg: np.ndarray, body: str) -> np.ndarray:
    """Pixels of a segmentation (geom ids) that belong to a body's geoms, shape (H, W), bool."""
    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    if bid < 0:
        raise UnknownNameError("body", body, [model.body(i).name for i in range(model.nbody)])
    geoms = np.flatnonzero(model.geom_bodyid == bid)
    return np.isin(seg, geoms)
