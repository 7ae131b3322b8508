"""Cameras: intrinsics, OpenCV-convention poses and lazily created renderers.

Frames: a MuJoCo camera looks along its -z with y up; posegrasp's camera frame is OpenCV's
(x right, y down, z forward), so `R_world_cv = R_world_mj @ diag(1, -1, -1)`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import mujoco
import numpy as np

from posegrasp.core.errors import AssetError, InvalidArgumentError, UnknownNameError
from posegrasp.core.runtime import gl_context_class
from posegrasp.core.transforms import intrinsics
from posegrasp.world.constants import EXTERNAL_SIZE

R_CV_FROM_MJ = np.diag([1.0, -1.0, -1.0])
MAX_RESOLUTION = (4096, 4096)


#: Millimetres per metre: 16-bit depth images count millimetres (or a share of one).
MM_PER_M = 1000.0
#: A depth at or beyond this share of the far clipping plane is where the renderer drew nothing.
FAR_SHARE = 0.999


def far_plane(model: mujoco.MjModel) -> float:
    """The far clipping plane of a model's cameras [m]: the depth `CameraRenderer.depth` gives
    where nothing is drawn."""
    return float(model.vis.map.zfar * model.stat.extent)


def depth_to_uint16(
    depth_m: np.ndarray, mm_per_value: float = 1.0, far_m: float | None = None
) -> np.ndarray:
    """A z-depth image as 16-bit values, ``round(depth [mm] / mm_per_value)`` (BOP's depth images
    with their ``depth_scale``; whole millimetres by default).

    Args:
        depth_m: depth along the optical axis, shape (H, W) [m].
        mm_per_value: millimetres per value.
        far_m: the far clipping plane [m]; a depth at or beyond `FAR_SHARE` of it is where the
            renderer drew nothing (None: not checked).

    Returns:
        Shape (H, W), uint16; 0 where the depth is not finite, not positive, past the 16-bit
        range or (with `far_m`) at the far plane: no reading.
    """
    v = np.asarray(depth_m, np.float64) * (MM_PER_M / mm_per_value)
    ok = np.isfinite(v) & (v > 0) & (v < 65535.5)
    if far_m is not None:
        ok &= v < FAR_SHARE * far_m * (MM_PER_M / mm_per_value)
    return np.where(ok, np.round(np.where(ok, v, 0.0)), 0).astype(np.uint16)


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
    """Pinhole K of a MuJoCo camera rendered at width x height
    (`posegrasp.core.transforms.intrinsics` of the camera's fovy).

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


def geom_ids_from_colours(rgb: np.ndarray, scene: mujoco.MjvScene) -> np.ndarray:
    """Geom id per pixel of a render with `mjRND_SEGMENT` and `mjRND_IDCOLOR` (scene object i
    drawn in colour i + 1, black where nothing is drawn): shape (H, W), int32, -1 where no geom.
    """
    raw = rgb.astype(np.int32)
    segid = raw[..., 0] + (raw[..., 1] << 8) + (raw[..., 2] << 16) - 1
    # Index ngeom (the last entry) stands for "nothing drawn" (segid -1).
    lut = np.full(scene.ngeom + 1, -1, np.int32)
    for i in range(scene.ngeom):
        g = scene.geoms[i]
        if g.objtype == mujoco.mjtObj.mjOBJ_GEOM:
            lut[i] = g.objid
    return lut[np.where((segid >= 0) & (segid < scene.ngeom), segid, scene.ngeom)]


def shared_gl_context() -> mujoco.GLContext:
    """This process's GL context, made current: one per process, created on first use.

    Creating a context, and the first MuJoCo render context in it, costs about half a second on
    software EGL; episodes build a new model each, so they share one GL context and only rebuild
    MuJoCo's render context (`mujoco.MjrContext`, tens of milliseconds). A forked child makes
    its own.
    """
    global _GL
    if _GL is None or _GL[0] != os.getpid():
        gl_context = gl_context_class()
        try:
            _GL = (os.getpid(), gl_context(MAX_RESOLUTION[0], MAX_RESOLUTION[1]))
        except mujoco.FatalError as exc:
            raise AssetError(
                "MuJoCo cannot open an OpenGL context with MUJOCO_GL="
                f"{os.environ['MUJOCO_GL']}: install Mesa's EGL "
                f"(libegl1, libgl1-mesa-dri); MuJoCo said: {exc}"
            ) from exc
    _GL[1].make_current()
    return _GL[1]


_GL: tuple[int, mujoco.GLContext] | None = None


#: Model arrays uploaded into a render context (`mujoco.MjrContext`): meshes and textures.
_ASSET_ARRAYS = (
    "mesh_vertadr",
    "mesh_vertnum",
    "mesh_faceadr",
    "mesh_facenum",
    "mesh_normaladr",
    "mesh_normalnum",
    "mesh_texcoordadr",
    "mesh_texcoordnum",
    "mesh_vert",
    "mesh_normal",
    "mesh_texcoord",
    "mesh_face",
    "mesh_facenormal",
    "mesh_facetexcoord",
    "tex_type",
    "tex_colorspace",
    "tex_height",
    "tex_width",
    "tex_nchannel",
    "tex_adr",
    "tex_data",
)


def _render_sizes(m: mujoco.MjModel) -> tuple[int, ...]:
    g, q = m.vis.global_, m.vis.quality
    return (m.nmesh, m.ntex, m.nmat, g.offwidth, g.offheight, q.offsamples, q.shadowsize)


def same_render_assets(a: mujoco.MjModel, b: mujoco.MjModel) -> bool:
    """Whether a render context built for model a serves model b as well: the same meshes,
    textures and offscreen buffer (compared array by array, no copies). Never for models with
    height fields, skins or flexes, whose contexts are not shared."""
    if any(m.nhfield or m.nskin or m.nflex for m in (a, b)):
        return False
    if _render_sizes(a) != _render_sizes(b):
        return False
    return all(
        np.array_equal(np.asarray(getattr(a, n, ())), np.asarray(getattr(b, n, ())))
        for n in _ASSET_ARRAYS
    )


def scene_capacity(model: mujoco.MjModel) -> int:
    """Abstract geoms a `mujoco.MjvScene` of model needs room for: every geom and site twice
    over, plus room for decorations. Allocating the scene costs time in proportion (tens of
    milliseconds for 10,000)."""
    return 2 * (model.ngeom + model.nsite) + 500


class RenderContextCache:
    """One MuJoCo render context, kept across models that share their meshes and textures.

    Building a render context uploads every mesh and texture (about 90 ms for the Fetch scenes
    on software EGL). Scenes rebuilt per episode or per image share all of them, so the context
    of the previous model is reused: only the fields a context copies from its model besides
    the assets (line width, shadow and fog ranges, material texture tables) are refreshed,
    which renders exactly what a new context would. Call `get` before every render, on the GL
    context the cache belongs to; never keep the returned context across another `get`.

    Args:
        font_scale: the contexts' `mujoco.mjtFontScale`.
    """

    def __init__(self, font_scale: int) -> None:
        self.font_scale = font_scale
        self._ctx: mujoco.MjrContext | None = None
        self._model: mujoco.MjModel | None = None

    def get(self, model: mujoco.MjModel) -> mujoco.MjrContext:
        """The render context for model (its assets are compared when the model changes)."""
        if self._ctx is not None and model is self._model:
            return self._ctx
        if self._ctx is not None and same_render_assets(self._model, model):
            _refresh(self._ctx, model)
        else:
            self.free()
            self._ctx = mujoco.MjrContext(model, self.font_scale)
        self._model = model
        return self._ctx

    def free(self) -> None:
        """Free the context (on its GL context, which must be current)."""
        if self._ctx is not None:
            self._ctx.free()
        self._ctx = self._model = None


def _refresh(ctx: mujoco.MjrContext, model: mujoco.MjModel) -> None:
    """Copy into ctx what `mujoco.MjrContext(model)` takes from model besides its assets."""
    ext, vmap = model.stat.extent, model.vis.map
    ctx.lineWidth = model.vis.global_.linewidth
    ctx.shadowClip = ext * vmap.shadowclip
    ctx.shadowScale = vmap.shadowscale
    ctx.fogStart = ext * vmap.fogstart
    ctx.fogEnd = ext * vmap.fogend
    ctx.fogRGBA[:] = model.vis.rgba.fog
    n = model.nmat
    ctx.mat_texid[: model.mat_texid.size] = model.mat_texid.reshape(-1)
    ctx.mat_texuniform[:n] = model.mat_texuniform
    ctx.mat_texrepeat[: 2 * n] = model.mat_texrepeat.reshape(-1)


#: The render contexts of the shared GL context (`shared_gl_context`): (pid, cache).
_CTX_CACHE: tuple[int, RenderContextCache] | None = None


def _shared_cache() -> RenderContextCache:
    global _CTX_CACHE
    if _CTX_CACHE is None or _CTX_CACHE[0] != os.getpid():
        _CTX_CACHE = (os.getpid(), RenderContextCache(mujoco.mjtFontScale.mjFONTSCALE_150))
    return _CTX_CACHE[1]


class CameraRenderer:
    """RGB, depth and segmentation of one model at one resolution.

    Renders on the process's shared GL context (`shared_gl_context`) into MuJoCo's offscreen
    buffer; the render context is made on first use, never at construction or import. Call
    `close()` (or use it as a context manager) to free it.
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
        self._scene: mujoco.MjvScene | None = None
        self._option = mujoco.MjvOption()
        self._rect = mujoco.MjrRect(0, 0, width, height)

    def _bind(self) -> tuple[mujoco.MjrContext, mujoco.MjvScene]:
        shared_gl_context()
        if self._scene is None:
            off = self.model.vis.global_
            off.offwidth = max(off.offwidth, self.width)
            off.offheight = max(off.offheight, self.height)
            self._scene = mujoco.MjvScene(self.model, maxgeom=scene_capacity(self.model))
            self._scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = self.options.shadows
            self._scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = self.options.reflections
        ctx = _shared_cache().get(self.model)
        ctx.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, ctx)
        return ctx, self._scene

    def _render(self, data: mujoco.MjData, camera: str | int, ids: bool) -> mujoco.MjrContext:
        """Update the scene from `data` and render it from a fixed camera (geom ids as colours
        with `ids`)."""
        ctx, scene = self._bind()
        cam = mujoco.MjvCamera()
        cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
        cam.fixedcamid = _camera_id(self.model, camera) if isinstance(camera, str) else camera
        mujoco.mjv_updateScene(
            self.model, data, self._option, None, cam, mujoco.mjtCatBit.mjCAT_ALL, scene
        )
        flags = scene.flags.copy()
        scene.flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = ids
        scene.flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = ids
        try:
            mujoco.mjr_render(self._rect, scene, ctx)
        finally:
            scene.flags[:] = flags
        return ctx

    def _read_rgb(self, ctx: mujoco.MjrContext) -> np.ndarray:
        rgb = np.empty((self.height, self.width, 3), np.uint8)
        mujoco.mjr_readPixels(rgb, None, self._rect, ctx)
        return np.flipud(rgb).copy()  # OpenGL rows run bottom to top

    def rgb(self, data: mujoco.MjData, camera: str | int) -> np.ndarray:
        """RGB image, shape (H, W, 3), uint8."""
        return self._read_rgb(self._render(data, camera, ids=False))

    def depth(self, data: mujoco.MjData, camera: str | int) -> np.ndarray:
        """Metric depth image: per pixel, the z coordinate in the OpenCV camera frame of the
        surface drawn there (along the optical axis, not the distance along the pixel's ray), so
        pixel (u, v) back-projects to ``depth[v, u] * K^-1 (u, v, 1)``; the far clipping plane's
        distance where nothing is drawn.

        The scene is drawn as for `segmentation` (no blending), from the same camera and state
        as `rgb`; the reverse-Z depth buffer is mapped back to metres with the float32 frustum
        OpenGL used, in float64 (MuJoCo's own `mujoco.Renderer` conversion).

        Returns:
            Depth [m], shape (H, W), float32.
        """
        ctx = self._render(data, camera, ids=True)  # no blending: exact depth at far range
        z = np.empty((self.height, self.width), np.float32)
        mujoco.mjr_readPixels(None, z, self._rect, ctx)
        extent = self.model.stat.extent
        near = np.float32(self.model.vis.map.znear * extent)
        far = np.float32(self.model.vis.map.zfar * extent)
        # Reverse-Z perspective depth back to metres (the float32 frustum of OpenGL).
        c = np.float32(-0.5) * (-(far + near) / (far - near)) - np.float32(0.5)
        d = np.float32(-0.5) * (-(np.float32(2) * far * near) / (far - near))
        return np.flipud((d / (z.astype(np.float64) + c)).astype(np.float32)).copy()

    def segmentation(self, data: mujoco.MjData, camera: str | int) -> np.ndarray:
        """Geom id per pixel (-1 where no geom), shape (H, W), int32."""
        ctx = self._render(data, camera, ids=True)
        return geom_ids_from_colours(self._read_rgb(ctx), self._scene)

    def close(self) -> None:
        """Drop the scene; the shared render context stays for the next model with the same
        meshes and textures (`RenderContextCache`)."""
        self._scene = None

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


def external_renderer(model: mujoco.MjModel) -> CameraRenderer:
    """A renderer of the external camera's view at `EXTERNAL_SIZE` (no shadows): what episode
    GIFs and ``GraspEval-v0.render()`` show; read it with ``.rgb(data, EXTERNAL_CAMERA)``."""
    return CameraRenderer(model, *EXTERNAL_SIZE, RenderOptions(shadows=False))
