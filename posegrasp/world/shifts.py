"""Scene shifts: named, purely visual changes of a scene, one factor each, at three levels.

A shift changes what the head camera sees and nothing of the physics: the lights' colour,
intensity or direction, the textures of the table, walls and floor, visual-only distractors on
the table (no contact, no mass), the target's colours, or the head camera's own pose in its head
link (not the head's joints). `parse_shifts("light_colour:3,camera")` reads shifts from text;
`SceneConfig.shifts` asks `posegrasp.world.scene.build_scene` for them.

Levels: 1 mild, 2 medium, 3 strong; a factor named without a level is at level 2 (medium), and
``all[:LEVEL]`` is every factor at that level. Each factor draws from its own random stream,
``numpy.random.default_rng([seed, SHIFT_STREAM, k])`` for factor number k of `FACTORS` and the
episode's seed, so the scene's layout and physics draws are the same whatever the shifts, a
factor looks the same alone and among others, and its levels differ in strength only.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from posegrasp.core.errors import InvalidArgumentError, UnknownNameError
from posegrasp.world.distractor_bank import DISTRACTOR_IDS, add_distractors, bank_dir
from posegrasp.world.shift_edits import (
    CAMERA_HEIGHT,
    CAMERA_TILT,
    INTENSITY,
    LAMP_TURN,
    RECOLOUR,
    ROOM_BLEND,
    SUN_ANGLE,
    TINT_STRENGTH,
    TINTS,
    camera_pose,
    light_colour,
    light_direction,
    light_intensity,
    table_texture,
    target_colour,
    walls,
)
from posegrasp.world.shift_textures import PATTERNS

#: The stream of scene shifts: the second word of every shift's seed sequence.
SHIFT_STREAM = 0x5F1F7
#: What the levels are called.
LEVELS = {1: "mild", 2: "medium", 3: "strong"}
#: The level of a factor named without one.
DEFAULT_LEVEL = 2
#: The name that asks for every factor.
ALL = "all"

#: Edit of a compiled, settled scene: (model, data, target body, level, the factor's stream).
ModelEdit = Callable[[mujoco.MjModel, mujoco.MjData, str, int, np.random.Generator], None]


@dataclass(frozen=True)
class Factor:
    """One factor of variation.

    Attributes:
        name: its name in shift specs.
        summary: what its levels 1, 2, 3 do, one line.
        edit: how it changes the compiled scene; None for `distractors`, which adds geoms to the
            spec before it is compiled (`shift_spec`).
    """

    name: str
    summary: str
    edit: ModelEdit | None


def _per_level(values: Sequence[float], unit: str = "", scale: float = 1.0) -> str:
    """Values of levels 1, 2, 3 as text: ``"3 / 6 / 10 cm"``."""
    return " / ".join(f"{v * scale:g}" for v in values) + unit


#: Distractors per level.
DISTRACTOR_COUNTS = {1: 2, 2: 4, 3: 7}
_DIM, _BRIGHT = zip(*INTENSITY, strict=True)

#: The factors by name, in the order they are applied; each summary gives levels 1 / 2 / 3.
FACTORS: dict[str, Factor] = {
    f.name: f
    for f in (
        Factor(
            "light_colour",
            f"lights tinted ({', '.join(TINTS)}) {_per_level(TINT_STRENGTH, ' %', 100)} of the way",
            light_colour,
        ),
        Factor(
            "light_intensity",
            f"lights dimmed x{_per_level(_DIM)} or brightened x{_per_level(_BRIGHT)}",
            light_intensity,
        ),
        Factor(
            "light_direction",
            f"sun {_per_level(SUN_ANGLE, ' deg', 180 / np.pi)} from straight down, lamps turned "
            f"{_per_level(LAMP_TURN, ' deg', 180 / np.pi)} about the table",
            light_direction,
        ),
        Factor(
            "table_texture",
            f"table top: a wood tone / {', '.join(PATTERNS)} in colours "
            f"{_per_level(ROOM_BLEND[1:], ' %', 100)} of the way to saturated ones",
            table_texture,
        ),
        Factor(
            "walls",
            f"walls and floor in colours {_per_level(ROOM_BLEND, ' %', 100)} of the way to "
            f"saturated ones; new patterns ({', '.join(PATTERNS)}) from level 2",
            walls,
        ),
        Factor(
            "distractors",
            f"{_per_level(list(DISTRACTOR_COUNTS.values()))} unseen visual-only meshes on the "
            "table around the target",
            None,
        ),
        Factor(
            "target_colour",
            f"the target's parts {_per_level(RECOLOUR, ' %', 100)} of the way to colours of "
            "their own",
            target_colour,
        ),
        Factor(
            "camera",
            f"head camera {_per_level(CAMERA_HEIGHT, ' cm', 100)} higher or lower, tilted "
            f"{_per_level(CAMERA_TILT, ' deg', 180 / np.pi)} up or down",
            camera_pose,
        ),
    )
}


def _levels_hint() -> str:
    levels = ", ".join(f"{k} {v}" for k, v in LEVELS.items())
    return f"; NAME[:LEVEL] or {ALL}[:LEVEL], levels {levels} (default {DEFAULT_LEVEL})"


@dataclass(frozen=True)
class Shift:
    """One factor at one level.

    Attributes:
        factor: a name of `FACTORS`.
        level: 1 (mild), 2 (medium) or 3 (strong).

    Raises:
        UnknownNameError: an unknown factor.
        InvalidArgumentError: a level outside 1..3.
    """

    factor: str
    level: int = DEFAULT_LEVEL

    def __post_init__(self) -> None:
        if self.factor not in FACTORS:
            err = UnknownNameError("scene shift", str(self.factor), [*FACTORS, ALL])
            err.args = (f"{err}{_levels_hint()}",)
            raise err
        if isinstance(self.level, bool) or self.level not in LEVELS:
            raise InvalidArgumentError(
                f"invalid level {self.level!r} of scene shift {self.factor!r}{_levels_hint()}"
            )

    def __str__(self) -> str:
        return f"{self.factor}:{self.level}"


def _level(name: str, text: str) -> int:
    if text.strip() not in {str(k) for k in LEVELS}:
        raise InvalidArgumentError(
            f"invalid level {text!r} of scene shift {name!r}{_levels_hint()}"
        )
    return int(text)


def parse_shifts(spec: str) -> tuple[Shift, ...]:
    """Shifts from text: ``NAME[:LEVEL]`` items separated by commas, ``all[:LEVEL]`` for every
    factor; empty or ``none`` for none.

    Returns:
        The shifts in the order of `FACTORS` (each factor once).

    Raises:
        UnknownNameError: an unknown factor (the message lists the factors and levels).
        InvalidArgumentError: a bad level, an empty item or a factor asked for twice.
        AssetError: `distractors` without pybullet installed.
    """
    text = spec.strip()
    if text in ("", "none"):
        return ()
    shifts: list[Shift] = []
    for item in text.split(","):
        name, sep, level_text = item.partition(":")
        name = name.strip()
        if not name:
            raise InvalidArgumentError(f"empty scene shift in {spec!r}{_levels_hint()}")
        level = _level(name, level_text) if sep else DEFAULT_LEVEL
        if name == ALL:
            shifts += [Shift(f, level) for f in FACTORS]
        else:
            shifts.append(Shift(name, level))
    if any(s.factor == "distractors" for s in shifts):
        bank_dir()  # missing pybullet is said now, not when the first scene is built
    return canonical(shifts)


def canonical(shifts: Sequence[Shift]) -> tuple[Shift, ...]:
    """The shifts in the order of `FACTORS`.

    Raises:
        InvalidArgumentError: not `Shift` values, or a factor given twice.
    """
    if not all(isinstance(s, Shift) for s in shifts):
        raise InvalidArgumentError(
            f"scene shifts are Shift values (parse_shifts('camera:3')), not {list(shifts)!r}"
        )
    seen = [s.factor for s in shifts]
    twice = sorted({f for f in seen if seen.count(f) > 1})
    if twice:
        raise InvalidArgumentError(f"scene shift {', '.join(twice)} asked for more than once")
    order = list(FACTORS)
    return tuple(sorted(shifts, key=lambda s: order.index(s.factor)))


def shift_rng(seed: int, factor: str) -> np.random.Generator:
    """The random stream of a factor in the scene of `seed`."""
    return np.random.default_rng([seed, SHIFT_STREAM, list(FACTORS).index(factor)])


def shift_spec(
    spec: mujoco.MjSpec,
    shifts: Sequence[Shift],
    seed: int,
    footprints: list[np.ndarray],
    table_top_z: float,
    ids: Sequence[int] = DISTRACTOR_IDS,
) -> None:
    """The shifts' additions to a scene's spec before it is compiled: the `distractors`.

    Args:
        spec: the scene spec with every object added.
        shifts: the scene's shifts (`canonical` order or not).
        seed: the scene's seed.
        footprints: the objects' footprints in world xy [m], the target first
            (`posegrasp.world.layout.footprint`, placed).
        table_top_z: height of the table top [m].
        ids: the distractor bank's ids (the held-out ones unless told).

    Raises:
        AssetError: `distractors` without pybullet installed.
    """
    for s in canonical(shifts):
        if FACTORS[s.factor].edit is None:
            rng = shift_rng(seed, s.factor)
            add_distractors(spec, DISTRACTOR_COUNTS[s.level], footprints, table_top_z, rng, ids=ids)


def apply_shifts(
    model: mujoco.MjModel, data: mujoco.MjData, shifts: Sequence[Shift], seed: int, target: str
) -> None:
    """Apply the shifts' edits to a compiled, settled scene in place: only model fields that
    are drawn and never simulated change (lights, textures, colours, the head camera's pose in
    its body), so stepping `data` goes on exactly as without them. Of `data`, only the world
    poses of the cameras and lights are brought up to date (`mujoco.mj_camlight`).

    Args:
        model, data: the compiled scene and its state, kinematics up to date (`mj_forward`).
        shifts: the scene's shifts.
        seed: the scene's seed.
        target: the target's body name.
    """
    for s in canonical(shifts):
        edit = FACTORS[s.factor].edit
        if edit is not None:
            edit(model, data, target, s.level, shift_rng(seed, s.factor))
    mujoco.mj_camlight(model, data)
