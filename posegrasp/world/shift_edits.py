"""The edits of the scene shifts (`posegrasp.world.shifts`) on a compiled, settled scene.

Each edit is ``edit(model, data, target, level, rng)``: it changes model fields that are drawn
and never simulated (lights, textures, geom colours, the head camera's pose in its body) for
level 1, 2 or 3, drawing its choices from `rng` (the factor's own stream: the same draws at
every level, so levels differ in strength only). `data` is read, never written. Lengths [m],
angles [rad], world frame unless named otherwise.
"""

from __future__ import annotations

from collections.abc import Callable

import mujoco
import numpy as np

from posegrasp.core.transforms import quat_mul
from posegrasp.world import constants as C
from posegrasp.world.objects import VISUAL_GROUP
from posegrasp.world.shift_textures import (
    PATTERNS,
    WOOD_TONES,
    hsv,
    set_texture,
    texture_colours,
    texture_size,
    two_tone,
    wood,
)

#: Tints of the `light_colour` shift (RGB gains at full strength).
TINTS = {
    "warm": (1.0, 0.7, 0.4),
    "cold": (0.7, 0.86, 1.0),
    "blue": (0.3, 0.45, 1.0),
    "green": (0.6, 1.0, 0.5),
    "magenta": (1.0, 0.45, 0.85),
}
#: Share of the tint per level 1, 2, 3.
TINT_STRENGTH = (0.35, 0.65, 1.0)
#: Gains of the light intensity per level: (dimmer, brighter).
INTENSITY = ((0.75, 1.25), (0.5, 1.55), (0.3, 1.9))
#: The sun's angle from straight down per level [rad].
SUN_ANGLE = tuple(np.deg2rad((30.0, 55.0, 80.0)))
#: How far the other lights turn about the vertical through the table's centre, per level [rad].
LAMP_TURN = tuple(np.deg2rad((40.0, 80.0, 140.0)))
#: Share of a target part's colour replaced by its drawn colour, per level.
RECOLOUR = (0.35, 0.65, 1.0)
#: Head camera per level: height change [m] and tilt [rad] (either sign).
CAMERA_HEIGHT = (0.03, 0.06, 0.1)
CAMERA_TILT = tuple(np.deg2rad((2.5, 5.0, 8.0)))
#: Share of the way the table's, walls' and floor's colours move to drawn ones, per level.
ROOM_BLEND = (0.25, 0.6, 1.0)
#: Saturation of the drawn colours, and how far apart they are in value.
ROOM_SATURATION = 0.85
ROOM_CONTRAST = 0.55
#: The table top's texture.
TABLE_TEXTURE = "room_wood_tex"


def _sign(rng: np.random.Generator) -> float:
    return 1.0 if rng.random() < 0.5 else -1.0


def scale_lights(model: mujoco.MjModel, gain: np.ndarray) -> None:
    """Multiply every light's colours, and the headlight's, by gain (3,)."""
    for field in (model.light_diffuse, model.light_specular, model.light_ambient):
        field[:] = field * gain
    head = model.vis.headlight
    for colour in (head.diffuse, head.ambient, head.specular):
        colour[:] = colour * gain


def light_colour(
    model: mujoco.MjModel, data: mujoco.MjData, target: str, level: int, rng: np.random.Generator
) -> None:
    """Tint the lights (and the headlight) with one of `TINTS`, `TINT_STRENGTH` of the way."""
    tint = np.array(list(TINTS.values())[int(rng.integers(len(TINTS)))])
    scale_lights(model, 1.0 + TINT_STRENGTH[level - 1] * (tint - 1.0))


def light_intensity(
    model: mujoco.MjModel, data: mujoco.MjData, target: str, level: int, rng: np.random.Generator
) -> None:
    """Dim or brighten every light (and the headlight) by `INTENSITY`."""
    dim, bright = INTENSITY[level - 1]
    scale_lights(model, np.full(3, dim if rng.random() < 0.5 else bright))


def _table_centre(model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    return np.asarray(data.geom("table_top").xpos, float)


def light_direction(
    model: mujoco.MjModel, data: mujoco.MjData, target: str, level: int, rng: np.random.Generator
) -> None:
    """Turn the directional lights `SUN_ANGLE` from straight down (towards a drawn azimuth), and
    move the other lights `LAMP_TURN` about the vertical through the table's centre, aimed at
    it (lights of the worldbody: their pose is in world coordinates)."""
    azimuth = float(rng.uniform(-np.pi, np.pi))
    turn = _sign(rng) * LAMP_TURN[level - 1]
    turn_lights(model, data, turn, lambda: (SUN_ANGLE[level - 1], azimuth))


def turn_lights(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    turn: float,
    sun: Callable[[], tuple[float, float]],
) -> None:
    """Point each directional light `sun()` = (angle from straight down, azimuth) [rad], asked
    once per such light in order, and move the other lights `turn` about the vertical through
    the table's centre, aimed at it (lights of the worldbody: their pose is in world
    coordinates)."""
    centre = _table_centre(model, data)
    c, s = np.cos(turn), np.sin(turn)
    for i in range(model.nlight):
        if model.light_type[i] == mujoco.mjtLightType.mjLIGHT_DIRECTIONAL:
            a, azimuth = sun()
            model.light_dir[i] = [
                np.sin(a) * np.cos(azimuth),
                np.sin(a) * np.sin(azimuth),
                -np.cos(a),
            ]
        else:
            p = model.light_pos[i] - centre
            model.light_pos[i] = centre + np.array([c * p[0] - s * p[1], s * p[0] + c * p[1], p[2]])
            d = centre - model.light_pos[i]
            model.light_dir[i] = d / np.linalg.norm(d)


def _drawn_colours(rng: np.random.Generator) -> np.ndarray:
    """Two saturated colours of one drawn hue (the second's hue nearby), `ROOM_CONTRAST` apart
    in value: (2, 3)."""
    hue, value = float(rng.random()), float(rng.uniform(0.45, 0.75))
    a = hsv(hue, ROOM_SATURATION, value - ROOM_CONTRAST / 2)
    b = hsv(hue + float(rng.uniform(-0.1, 0.1)), ROOM_SATURATION, value + ROOM_CONTRAST / 2)
    return np.stack([a, b])


def _repaint(
    model: mujoco.MjModel, name: str, kind: str, level: int, rng: np.random.Generator
) -> None:
    """Paint texture `name` with pattern `kind` in its own two colours moved `ROOM_BLEND` of
    the way to two drawn ones (`two_tone`; ``checker`` of level 1 in 2 x 2 squares)."""
    own = texture_colours(model, name)
    a, b = own + ROOM_BLEND[level - 1] * (_drawn_colours(rng) - own)
    h, w = texture_size(model, name)
    set_texture(model, name, two_tone(kind, h, w, a, b, rng, 2 if level == 1 else None))


def table_texture(
    model: mujoco.MjModel, data: mujoco.MjData, target: str, level: int, rng: np.random.Generator
) -> None:
    """The table top's texture: level 1 wood grain in one of `WOOD_TONES`; levels 2 and 3 one
    of `PATTERNS` (checker, stripes, smooth noise) in its colours moved 65 % and all the way to
    two saturated, contrasting ones (`ROOM_BLEND`)."""
    tone = np.array(WOOD_TONES[int(rng.integers(len(WOOD_TONES)))])
    kind = PATTERNS[int(rng.integers(len(PATTERNS)))]
    if level == 1:
        h, w = texture_size(model, TABLE_TEXTURE)
        set_texture(model, TABLE_TEXTURE, wood(h, w, tone, rng))
    else:
        _repaint(model, TABLE_TEXTURE, kind, level, rng)


def walls(
    model: mujoco.MjModel, data: mujoco.MjData, target: str, level: int, rng: np.random.Generator
) -> None:
    """The walls' and the floor's textures, each in its colours moved `ROOM_BLEND` (35, 65,
    100 %) of the way to two saturated, contrasting ones: level 1 in their own patterns (plain
    walls, a checker floor), levels 2 and 3 in one of `PATTERNS` each."""
    for name, own in (("room_wall_tex", "noise"), ("room_floor_tex", "checker")):
        kind = PATTERNS[int(rng.integers(len(PATTERNS)))]
        _repaint(model, name, own if level == 1 else kind, level, rng)


def visual_geoms(model: mujoco.MjModel, body: str) -> np.ndarray:
    """Ids of a body's drawn, contact-free geoms (an object's visual parts)."""
    bid = model.body(body).id
    return np.flatnonzero(
        (model.geom_bodyid == bid)
        & (model.geom_group == VISUAL_GROUP)
        & (model.geom_contype == 0)
        & (model.geom_conaffinity == 0)
    )


def target_colour(
    model: mujoco.MjModel, data: mujoco.MjData, target: str, level: int, rng: np.random.Generator
) -> None:
    """Move each visual part of the target `RECOLOUR` of the way to a colour of its own (drawn
    hue, saturation 0.5-1, value 0.35-0.9); transparency kept."""
    for g in visual_geoms(model, target):
        colour = hsv(
            float(rng.random()), float(rng.uniform(0.5, 1.0)), float(rng.uniform(0.35, 0.9))
        )
        k = RECOLOUR[level - 1]
        model.geom_rgba[g, :3] = (1 - k) * model.geom_rgba[g, :3] + k * colour


def camera_pose(
    model: mujoco.MjModel, data: mujoco.MjData, target: str, level: int, rng: np.random.Generator
) -> None:
    """Raise or lower the head camera `CAMERA_HEIGHT` along world z and tilt it `CAMERA_TILT`
    up or down about its own x axis (right), by editing its pose in its body: the head's joints,
    and so the robot's physics, are unchanged, and the camera's world pose follows."""
    dz = _sign(rng) * CAMERA_HEIGHT[level - 1]
    tilt = _sign(rng) * CAMERA_TILT[level - 1]
    move_camera(model, data, dz, tilt)


def move_camera(model: mujoco.MjModel, data: mujoco.MjData, dz: float, tilt: float) -> None:
    """Raise the head camera `dz` [m] along world z and tilt it `tilt` [rad] up about its own x
    axis, by editing its pose in its body (the head's joints are unchanged)."""
    cam = model.camera(C.HEAD_CAMERA).id
    R_world_body = data.xmat[model.cam_bodyid[cam]].reshape(3, 3)
    model.cam_pos[cam] = model.cam_pos[cam] + R_world_body.T @ np.array([0.0, 0.0, dz])
    # A MuJoCo camera looks along its -z with y up: turning about +x by -tilt looks down.
    turn = np.array([np.cos(-tilt / 2), np.sin(-tilt / 2), 0.0, 0.0])
    model.cam_quat[cam] = quat_mul(model.cam_quat[cam], turn)
