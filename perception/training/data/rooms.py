"""Rooms that change, for training: a wide randomisation of a head-camera scene's look.

The scene shifts (`posegrasp.world.shifts`) are the test's rooms: named factors at three levels,
drawn from the scoring seeds. Training draws its own rooms from a wider, continuous family, with
generators of its own, so that nothing is fitted to the shifts' definitions or their seeds:

- lights: any colour (each channel's gain drawn in 0.15..1, the largest set to 1, blended in by a
  drawn share), any intensity (x0.2..2.2, log-uniform), the sun anywhere in the upper
  hemisphere, the lamps turned anywhere about the table;
- surfaces: the table top, the walls and the floor, each painted with the studio's procedural
  textures (`perception.training.data.textures.procedural_texture`: smooth noise, stripes or
  blobs in saturated, pastel or grey colours), blended a drawn share over its own;
- objects: every visual part of every annotated object moved a drawn share of the way to a
  colour of its own (any hue, saturation and value), so that an object is told by its shape;
- camera: the head camera raised or lowered up to 12 cm and tilted up to 10 deg;
- distractors: unseen visual-only meshes from the training part of the distractor bank
  (`posegrasp.world.distractor_bank.TRAINING_IDS`, never the ids the shifts score with), 2, 4
  or 7 of them, added before the scene is compiled (`room_shifts`).

Each factor is drawn on with the odds of the room's family (`FAMILIES`), from
``default_rng([seed, ROOM_STREAM])``, so an image's room depends only on its seed and family:
``wide`` rooms draw each factor on about half the images, so that a network sees each factor
alone and in small company; ``joint`` rooms draw nearly every factor at once, as when a room
differs from the plain one in many ways together. The physics and the scene's layout are those
of the plain scene of the same seed; only the camera's pose in its head link and what is drawn
change.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import cv2
import mujoco
import numpy as np

from perception.training.data.textures import procedural_texture
from posegrasp.world.shift_edits import (
    TABLE_TEXTURE,
    move_camera,
    scale_lights,
    turn_lights,
    visual_geoms,
)
from posegrasp.world.shift_textures import hsv, set_texture, texture_pixels, texture_size
from posegrasp.world.shifts import Shift

#: The second word of every room's seed sequence.
ROOM_STREAM = 0x2007
#: The families of rooms: each one's chance that a factor is drawn on in an image.
FAMILIES: dict[str, float] = {"wide": 0.5, "joint": 0.9}
#: The room's textures: the table top, the walls, the floor.
SURFACES = (TABLE_TEXTURE, "room_wall_tex", "room_floor_tex")
#: Ranges of the draws: light gain, camera height [m] and tilt [rad].
INTENSITY = (0.2, 2.2)
CAMERA_HEIGHT = 0.12
CAMERA_TILT = np.deg2rad(10.0)


def room_rng(seed: int) -> np.random.Generator:
    """The random stream of the room of the image of scene `seed`."""
    return np.random.default_rng([seed, ROOM_STREAM])


def room_shifts(seed: int, family: str = "wide") -> tuple[Shift, ...]:
    """The scene shifts the room of scene `seed` is built with: the `distractors` shift at a
    drawn level (2, 4 or 7 meshes) with the family's odds, else none; the scene draws them from
    the training bank (``SceneConfig(distractor_bank="training")``)."""
    rng = np.random.default_rng([seed, ROOM_STREAM, 1])
    if rng.random() >= FAMILIES[family]:
        return ()
    return (Shift("distractors", int(rng.integers(1, 4))),)


def _light_colour(
    model: mujoco.MjModel, data: mujoco.MjData, bodies: list[str], rng: np.random.Generator
) -> Any:
    tint = rng.uniform(0.15, 1.0, 3)
    tint /= tint.max()
    share = float(rng.uniform(0.2, 1.0))
    scale_lights(model, 1.0 + share * (tint - 1.0))
    return [round(float(v), 3) for v in (*tint, share)]


def _light_intensity(
    model: mujoco.MjModel, data: mujoco.MjData, bodies: list[str], rng: np.random.Generator
) -> Any:
    gain = float(np.exp(rng.uniform(*np.log(INTENSITY))))
    scale_lights(model, np.full(3, gain))
    return round(gain, 3)


def _light_direction(
    model: mujoco.MjModel, data: mujoco.MjData, bodies: list[str], rng: np.random.Generator
) -> Any:
    turn = float(rng.uniform(-np.pi, np.pi))

    def sun() -> tuple[float, float]:
        return float(rng.uniform(0.0, np.deg2rad(85.0))), float(rng.uniform(-np.pi, np.pi))

    turn_lights(model, data, turn, sun)
    return round(float(np.rad2deg(turn)), 1)


def _surfaces(
    model: mujoco.MjModel, data: mujoco.MjData, bodies: list[str], rng: np.random.Generator
) -> Any:
    shares = []
    for name in SURFACES:
        h, w = texture_size(model, name)
        own = texture_pixels(model, name)[:, :3].reshape(h, w, 3).astype(float)
        drawn = cv2.resize(procedural_texture(rng, 128), (w, h), interpolation=cv2.INTER_LINEAR)
        share = float(rng.uniform(0.4, 1.0))
        set_texture(model, name, np.round((1 - share) * own + share * drawn).astype(np.uint8))
        shares.append(round(share, 2))
    return shares


def _objects(
    model: mujoco.MjModel, data: mujoco.MjData, bodies: list[str], rng: np.random.Generator
) -> Any:
    shares = []
    for body in bodies:
        share = float(rng.uniform(0.2, 1.0))
        for g in visual_geoms(model, body):
            colour = hsv(
                float(rng.random()), float(rng.uniform(0.0, 1.0)), float(rng.uniform(0.1, 0.95))
            )
            model.geom_rgba[g, :3] = (1 - share) * model.geom_rgba[g, :3] + share * colour
        shares.append(round(share, 2))
    return shares


def _camera(
    model: mujoco.MjModel, data: mujoco.MjData, bodies: list[str], rng: np.random.Generator
) -> Any:
    dz = float(rng.uniform(-CAMERA_HEIGHT, CAMERA_HEIGHT))
    tilt = float(rng.uniform(-CAMERA_TILT, CAMERA_TILT))
    move_camera(model, data, dz, tilt)
    return [round(dz, 3), round(float(np.rad2deg(tilt)), 1)]


def randomize_room(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    bodies: list[str],
    seed: int,
    family: str = "wide",
) -> dict[str, Any]:
    """Draw the room of scene `seed` onto its compiled, settled model in place (the factors of
    `FACTORS`, each on with the odds of `family` in `FAMILIES`), and bring the cameras' and
    lights' world poses up to date.

    Args:
        model, data: the compiled scene and its state, kinematics up to date.
        bodies: the body names of the scene's annotated objects.
        seed: the scene's seed.
        family: the family of rooms it is drawn from.

    Returns:
        What was drawn, factor by factor (for the image's record).
    """
    rng = room_rng(seed)
    on = rng.random(len(FACTORS)) < FAMILIES[family]
    drawn: dict[str, Any] = {}
    for name, wanted in zip(FACTORS, on, strict=True):
        if wanted:
            drawn[name] = _EDITS[name](model, data, bodies, rng)
    mujoco.mj_camlight(model, data)
    return drawn


#: Each factor's edit of a compiled scene: (model, data, the annotated bodies, the room's stream)
#: -> what it drew.
_EDITS: dict[str, Callable[..., Any]] = {
    "light_colour": _light_colour,
    "light_intensity": _light_intensity,
    "light_direction": _light_direction,
    "surfaces": _surfaces,
    "objects": _objects,
    "camera": _camera,
}
#: The factors, in the order they are drawn and applied.
FACTORS = tuple(_EDITS)


def folder_suffix(family: str) -> str:
    """The end of the dataset folders of a family's rooms: ``_rooms`` for ``wide``, the first
    family, ``_rooms_<family>`` for the others."""
    return "_rooms" if family == "wide" else f"_rooms_{family}"
