"""How much of an object the other objects hide from a camera.

The object's pixels are counted in a segmentation render of the scene as it is, then with every
other object moved far below the floor; the share of its silhouette that is missing in the first
is its occlusion. The robot stays in both renders, so only objects count as occluders.
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np

from posegrasp.world import constants as C
from posegrasp.world.camera import CameraRenderer, RenderOptions, body_mask

#: Resolution of the occlusion renders (a quarter of the head camera's pixels).
WIDTH, HEIGHT = 320, 240


def occlusion(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    target: str,
    others: Sequence[str],
    camera: str = C.HEAD_CAMERA,
) -> float:
    """Share of body `target`'s silhouette that the bodies `others` hide from `camera`, in
    [0, 1]; 1 when the target is not in the image at all. `data` is left as it was."""
    with CameraRenderer(model, WIDTH, HEIGHT, RenderOptions(shadows=False)) as renderer:
        visible = int(body_mask(model, renderer.segmentation(data, camera), target).sum())
        saved = data.qpos.copy()
        try:
            for body in others:
                adr = model.joint(model.body(body).jntadr[0]).qposadr[0]
                data.qpos[adr + 2] -= 10.0
            mujoco.mj_kinematics(model, data)
            whole = int(body_mask(model, renderer.segmentation(data, camera), target).sum())
        finally:
            data.qpos[:] = saved
            mujoco.mj_forward(model, data)
    return 1.0 if whole == 0 else float(np.clip(1.0 - visible / whole, 0.0, 1.0))
