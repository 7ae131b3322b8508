"""Offscreen RGB, depth and segmentation renders of fixed cameras, one GL context."""

from __future__ import annotations

import mujoco
import numpy as np

from posegrasp.core.errors import StateError
from posegrasp.core.runtime import gl_context_class
from posegrasp.world.camera import RenderContextCache, scene_capacity


class OffscreenRenderer:
    """Offscreen RGB and segmentation renders of fixed cameras, for one model at a time.

    One GL context lives as long as the renderer; MuJoCo's render context (textures, meshes) is
    kept across models with the same meshes and textures
    (`posegrasp.world.camera.RenderContextCache`),
    so a stream of freshly compiled scenes costs no new GL or render context each.
    Shadows, reflections and the skybox are off. The GL context is made on first use; call
    `close()` to free it.

    Args:
        width, height: image size [px].
    """

    def __init__(self, width: int, height: int) -> None:
        self.width, self.height = width, height
        self._gl: mujoco.GLContext | None = None
        self._contexts = RenderContextCache(mujoco.mjtFontScale.mjFONTSCALE_50)
        self._model: mujoco.MjModel | None = None
        self._scene: mujoco.MjvScene | None = None
        self._cam = mujoco.MjvCamera()
        self._cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._pert = mujoco.MjvPerturb()
        self._rect = mujoco.MjrRect(0, 0, width, height)
        self._buf = np.empty((height, width, 3), np.uint8)
        self._drawn: mujoco.MjrContext | None = None  # the render context of the last draw

    def _bind(self, model: mujoco.MjModel) -> tuple[mujoco.MjrContext, mujoco.MjvScene]:
        if self._gl is None:
            self._gl = gl_context_class()(self.width, self.height)
        self._gl.make_current()
        if model is not self._model or self._scene is None:
            vis = model.vis.global_
            # The offscreen buffer at the image size: software rendering clears all of it on
            # every draw, so a larger one costs time and draws the same pixels.
            vis.offwidth, vis.offheight = self.width, self.height
            self._scene = mujoco.MjvScene(model, maxgeom=scene_capacity(model))
            for flag in ("mjRND_SHADOW", "mjRND_REFLECTION", "mjRND_SKYBOX"):
                self._scene.flags[getattr(mujoco.mjtRndFlag, flag)] = False
            self._model = model
        ctx = self._contexts.get(model)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, ctx)
        return ctx, self._scene

    def draw(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        camera: int,
        opt: mujoco.MjvOption | None = None,
        segment: bool = False,
    ) -> None:
        """Render a view into the offscreen buffer without reading it back (`read_rgb`,
        `read_depth` read it). Needs up-to-date kinematics and camera poses in data; segment
        draws segmentation id colours."""
        ctx, scene = self._bind(model)
        self._cam.fixedcamid = camera
        mujoco.mjv_updateScene(
            model,
            data,
            opt or mujoco.MjvOption(),
            self._pert,
            self._cam,
            mujoco.mjtCatBit.mjCAT_ALL,
            scene,
        )
        scene.flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = segment
        scene.flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = segment
        mujoco.mjr_render(self._rect, scene, ctx)
        self._drawn = ctx

    def _drawn_context(self) -> mujoco.MjrContext:
        if self._drawn is None:
            raise StateError("nothing is drawn yet: call draw() before reading pixels back")
        assert self._gl is not None  # draw() made it
        self._gl.make_current()
        return self._drawn

    def read_rgb(self) -> np.ndarray:
        """The colours of the last `draw`, shape (H, W, 3), uint8."""
        mujoco.mjr_readPixels(self._buf, None, self._rect, self._drawn_context())
        return np.flipud(self._buf).copy()

    def read_depth(self, window: tuple[int, int, int, int] | None = None) -> np.ndarray:
        """The depth buffer of the last `draw` (OpenGL window depth in [0, 1], 1 where nothing is
        drawn), only inside window (x0, y0, x1, y1) when given: shape (y1 - y0, x1 - x0), else
        (H, W); float32, top row first. Two draws of the same geom under the same camera write
        the same depths, so comparing them tells which surface is in front."""
        ctx = self._drawn_context()
        x0, y0, x1, y1 = window if window is not None else (0, 0, self.width, self.height)
        out = np.ones((max(0, y1 - y0), max(0, x1 - x0)), np.float32)
        if out.size:  # OpenGL rows run bottom to top
            rect = mujoco.MjrRect(x0, self.height - y1, x1 - x0, y1 - y0)
            mujoco.mjr_readPixels(None, out, rect, ctx)
        return np.flipud(out)

    def render(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        camera: int,
        opt: mujoco.MjvOption | None = None,
        segment: bool = False,
    ) -> np.ndarray:
        """RGB image, or segmentation id colours if segment (black where nothing is drawn):
        `draw` then `read_rgb`. Returns shape (H, W, 3), uint8."""
        self.draw(model, data, camera, opt, segment)
        return self.read_rgb()

    def close(self) -> None:
        """Free the render and GL contexts."""
        if self._gl is not None:
            self._gl.make_current()
            self._contexts.free()
            self._gl.free()
            self._gl = None
        self._model = self._scene = self._drawn = None
