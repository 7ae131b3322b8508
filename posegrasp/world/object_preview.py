"""The preview sheet of a mesh object: the object, its collision hulls, and each resting pose with
its best grasps drawn, rendered with MuJoCo (call `posegrasp.core.runtime.setup_rendering()`
first).

A grasp is drawn as the two finger pads closed to its width (the pads' 77 x 27 mm, 14 mm thick,
in the grasp frame) and a short line up its approach; one colour per grasp.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence

import mujoco
import numpy as np
from PIL import Image, ImageDraw

from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.transforms import mat_to_quat, quat_to_mat
from posegrasp.world.camera import CameraRenderer, RenderOptions
from posegrasp.world.objects import COLLISION_GROUP, VISUAL_GROUP, ObjectModel

#: One panel's size [px] and the panels per row.
PANEL = (320, 240)
COLUMNS = 4
#: Grasps drawn per resting pose.
DRAWN = 3

_SCENE_XML = """<mujoco>
  <visual><global offwidth="640" offheight="480"/><quality offsamples="4"/>
    <headlight ambient="0.35 0.35 0.35" diffuse="0.5 0.5 0.5" specular="0.1 0.1 0.1"/></visual>
  <asset>
    <texture name="grid" type="2d" builtin="checker" rgb1="0.86 0.86 0.84" rgb2="0.78 0.78 0.76"
             width="128" height="128"/>
    <material name="grid" texture="grid" texrepeat="8 8"/>
  </asset>
  <worldbody>
    <light pos="0.3 -0.3 1.0" dir="-0.3 0.3 -1" diffuse="0.5 0.5 0.5"/>
    <geom name="floor" type="plane" size="1 1 0.01" material="grid" contype="0" conaffinity="0"/>
  </worldbody>
</mujoco>"""

_GRASP_COLOURS = ((0.9, 0.15, 0.15), (0.15, 0.45, 0.95), (0.1, 0.7, 0.2), (0.95, 0.6, 0.05))


def _palette(n: int) -> list[tuple[float, float, float]]:
    """n distinct colours (golden-ratio hues)."""
    out = []
    for i in range(n):
        h = (i * 0.61803398875) % 1.0
        k = np.array([5.0, 3.0, 1.0])
        r, g, b = 1.0 - (0.85 - 0.6 * np.clip(np.minimum(np.abs((h * 6 + k) % 6 - 3) - 1, 1), 0, 1))
        out.append((float(r), float(g), float(b)))
    return out


def _look_at(spec: mujoco.MjSpec, name: str, target: np.ndarray, distance: float) -> None:
    """A fixed camera `distance` [m] from `target`, 35 degrees above it, from the front left."""
    elev, azim = math.radians(35.0), math.radians(-60.0)
    f = -np.array(
        [math.cos(elev) * math.cos(azim), math.cos(elev) * math.sin(azim), math.sin(elev)]
    )
    pos = target - distance * f
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, f)
    cam = spec.worldbody.add_camera()
    cam.name = name
    cam.pos = pos
    cam.quat = mat_to_quat(np.column_stack([right, up, -f]))
    cam.fovy = 40.0


def _add_grasp(spec: mujoco.MjSpec, T: np.ndarray, width: float, rgb) -> None:
    """Pads and approach line of a grasp at world pose T (4, 4)."""
    rgba = [*rgb, 0.6]
    for side in (1.0, -1.0):
        g = spec.worldbody.add_geom()
        g.type = mujoco.mjtGeom.mjGEOM_BOX
        g.size = [0.0385, 0.007, 0.0135]
        centre = T @ np.array([-0.025, side * (width / 2 + 0.007), 0.0, 1.0])
        g.pos = centre[:3]
        g.quat = mat_to_quat(T[:3, :3])
        g.rgba, g.contype, g.conaffinity, g.group = rgba, 0, 0, VISUAL_GROUP
    line = spec.worldbody.add_geom()
    line.type = mujoco.mjtGeom.mjGEOM_CAPSULE
    line.fromto = [*(T[:3, 3]), *(T[:3, 3] - 0.08 * T[:3, 0])]
    line.size = [0.0025, 0, 0]
    line.rgba, line.contype, line.conaffinity, line.group = rgba, 0, 0, VISUAL_GROUP


def _panel(
    obj: ObjectModel,
    quat: np.ndarray,
    grasps: Sequence[tuple[np.ndarray, float]] = (),
    hulls: bool = False,
) -> np.ndarray:
    """One render (H, W, 3) uint8 of the object resting in orientation quat, optionally with its
    hulls in colour instead of its visual mesh and grasps drawn."""
    spec = mujoco.MjSpec.from_string(_SCENE_XML)
    quat = np.asarray(quat, float)
    z = obj.resting_height(quat)
    obj.add_to_spec(spec, "object", np.array([0.0, 0.0, z]), quat)
    T_world_O = np.eye(4)
    T_world_O[:3, :3] = quat_to_mat(quat)
    T_world_O[:3, 3] = [0.0, 0.0, z]
    for (T_O_G, width), rgb in zip(grasps, _GRASP_COLOURS, strict=False):
        _add_grasp(spec, T_world_O @ T_O_G, width, rgb)
    _look_at(spec, "view", np.array([0.0, 0.0, z * 0.8]), 2.6 * max(obj.diameter, 0.05))
    model = spec.compile()
    if hulls:
        body = model.body("object").id
        geoms = np.flatnonzero(model.geom_bodyid == body)
        colours = iter(_palette(len(geoms)))
        for g in geoms:
            if model.geom_group[g] == COLLISION_GROUP:
                model.geom_group[g] = VISUAL_GROUP
                model.geom_rgba[g] = [*next(colours), 1.0]
            else:
                model.geom_rgba[g, 3] = 0.0
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    with CameraRenderer(model, *PANEL, RenderOptions(shadows=True)) as r:
        return r.rgb(data, "view")


def preview_sheet(
    obj: ObjectModel,
    poses: list[dict],
    grasps: dict[str, list[tuple[np.ndarray, float]]],
    title: str,
) -> bytes:
    """The preview sheet as PNG bytes.

    Args:
        obj: the object, in its frame O.
        poses: its resting poses as stored (``name``, ``quat``, ``share``, ``graspable``).
        grasps: pose name -> (T_O_G (4, 4), width [m]) of its grasps, best first (one finger
            order each).
        title: the sheet's heading.
    """
    if obj.geometry is None:
        raise InvalidArgumentError(
            f"{obj.name} is a built-in object; a preview sheet is of a user mesh"
        )
    canon = np.asarray(poses[0]["quat"], float)
    panels = [
        (_panel(obj, canon), "visual mesh"),
        (_panel(obj, canon, hulls=True), f"{len(obj.geometry.hulls)} collision hulls"),
    ]
    for p in poses:
        gs = grasps.get(p["name"], [])
        label = f"{p['name']}  {p['share'] * 100:.0f} %  "
        label += f"{len(gs)} grasps" if gs else "not graspable"
        panels.append((_panel(obj, np.asarray(p["quat"], float), gs[:DRAWN]), label))
    rows = math.ceil(len(panels) / COLUMNS)
    w, h = PANEL
    head = 28
    sheet = Image.new("RGB", (COLUMNS * w, head + rows * (h + 18)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    draw.text((8, 8), title, fill=(0, 0, 0))
    for i, (img, label) in enumerate(panels):
        x, y = (i % COLUMNS) * w, head + (i // COLUMNS) * (h + 18)
        sheet.paste(Image.fromarray(img), (x, y))
        draw.text((x + 6, y + h + 3), label, fill=(0, 0, 0))
    buf = io.BytesIO()
    sheet.save(buf, format="PNG")
    return buf.getvalue()
