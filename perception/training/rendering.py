"""Offscreen RGB and segmentation renders of a MuJoCo model's fixed cameras, one GL context."""

from __future__ import annotations

import sim  # noqa: F401  # isort: skip  (defaults MUJOCO_GL before mujoco is imported)
import mujoco
import numpy as np

from sim.world.camera import geom_ids_from_colours


class OffscreenRenderer:
    """Offscreen RGB and segmentation renders of fixed cameras, for one model at a time.

    One GL context lives as long as the renderer; MuJoCo's render context (textures, meshes) is
    rebuilt only when a different model is passed, so a stream of freshly compiled scenes costs
    no new GL context each. Shadows, reflections and the skybox are off. The GL context is made
    on first use; call `close()` to free it.

    Args:
        width, height: image size [px].
    """

    def __init__(self, width: int, height: int) -> None:
        self.width, self.height = width, height
        self._gl: mujoco.GLContext | None = None
        self._model: mujoco.MjModel | None = None
        self._ctx: mujoco.MjrContext | None = None
        self._scene: mujoco.MjvScene | None = None
        self._cam = mujoco.MjvCamera()
        self._cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._pert = mujoco.MjvPerturb()
        self._rect = mujoco.MjrRect(0, 0, width, height)
        self._buf = np.empty((height, width, 3), np.uint8)

    def _bind(self, model: mujoco.MjModel) -> tuple[mujoco.MjrContext, mujoco.MjvScene]:
        if self._gl is None:
            self._gl = mujoco.GLContext(self.width, self.height)
        self._gl.make_current()
        if model is not self._model or self._ctx is None or self._scene is None:
            if self._ctx is not None:
                self._ctx.free()
            vis = model.vis.global_
            vis.offwidth, vis.offheight = (
                max(vis.offwidth, self.width),
                max(vis.offheight, self.height),
            )
            self._ctx = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_50)
            mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._ctx)
            self._scene = mujoco.MjvScene(model, maxgeom=10000)
            for flag in ("mjRND_SHADOW", "mjRND_REFLECTION", "mjRND_SKYBOX"):
                self._scene.flags[getattr(mujoco.mjtRndFlag, flag)] = False
            self._model = model
        return self._ctx, self._scene

    def render(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        camera: int,
        opt: mujoco.MjvOption | None = None,
        segment: bool = False,
    ) -> np.ndarray:
        """RGB image, or segmentation id colours if segment (black where nothing is drawn).

        Needs up-to-date kinematics and camera poses in data. Returns shape (H, W, 3), uint8.
        """
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
        mujoco.mjr_readPixels(self._buf, None, self._rect, ctx)
        return np.flipud(self._buf).copy()

    def geom_ids(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        camera: int,
        opt: mujoco.MjvOption | None = None,
    ) -> np.ndarray:
        """Geom id per pixel (-1 where no geom is drawn), shape (H, W), int32."""
        rgb = self.render(model, data, camera, opt, segment=True)
        return geom_ids_from_colours(rgb, self._bind(model)[1])

    def close(self) -> None:
        """Free the render and GL contexts."""
        if self._ctx is not None:
            self._ctx.free()
            self._ctx = None
        if self._gl is not None:
            self._gl.free()
            self._gl = None
        self._model = self._scene = None
