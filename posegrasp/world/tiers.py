"""Scene tiers: one named preset per axis of difficulty, the same for episodes and training data.

- ``isolated``: one upright object alone on the table, the base 0.7-0.9 m from it (the default).
- ``clutter``: 3-5 objects of the other classes on the table, two of them 3-8 cm (edge to edge)
  from the target; lights and surface colours randomised.
- ``any-pose``: the target alone, in any of its stable resting poses (found by physics,
  `posegrasp.world.resting`) that the gripper can take it in, drawn uniformly.
- ``far``: the base stands back so that the head camera sees the target 0.9-1.6 m away; the
  robot drives before it grasps.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, fields, replace

from posegrasp.core.errors import UnknownNameError
from posegrasp.core.validate import arg
from posegrasp.world.objects import check_objects
from posegrasp.world.scene import SceneConfig


@dataclass(frozen=True)
class Tier:
    """A named scene preset.

    Attributes:
        name: the tier's name.
        scene: how its scenes are sampled.
        summary: one line saying what makes it hard.
    """

    name: str
    scene: SceneConfig
    summary: str


_CLUTTER = SceneConfig(distractor_count=(3, 5), near_distractors=2, randomize_appearance=True)
_FAR = SceneConfig(camera_distance=(0.9, 1.6))
_ANY_POSE = SceneConfig(resting_pose="graspable")
_HARD = replace(
    _CLUTTER,
    camera_distance=_FAR.camera_distance,
    resting_pose="graspable",
    target_x=(0.8, 0.9),
    occluders=1,
    occlusion=(0.05, 0.4),
)

#: Tiers by name, easiest first.
TIERS: dict[str, Tier] = {
    t.name: t
    for t in (
        Tier("isolated", SceneConfig(), "one upright object alone, 0.7-0.9 m from the camera"),
        Tier("clutter", _CLUTTER, "3-5 other objects, two of them 3-8 cm from the target"),
        Tier("any-pose", _ANY_POSE, "the target in any stable resting pose it can be taken in"),
        Tier("far", _FAR, "the target 0.9-1.6 m from the camera; the base drives first"),
        Tier("hard", _HARD, "all of the above, and a neighbour hides up to 40 % of the target"),
    )
}
DEFAULT_TIER = "isolated"


def tier_scene(name: str, base: SceneConfig | None = None) -> SceneConfig:
    """The scene config of tier `name`; with `base`, the tier's sampling settings applied to it.

    Raises:
        UnknownNameError: no such tier.
    """
    if name not in TIERS:
        raise UnknownNameError("tier", name, TIERS)
    preset = TIERS[name].scene
    if base is None:
        return preset
    default = SceneConfig()
    changed = {
        f.name: getattr(preset, f.name)
        for f in fields(SceneConfig)
        if getattr(preset, f.name) != getattr(default, f.name)
    }
    return replace(base, **changed)


def check_tier(name: str) -> str:
    """`name` when it is a tier.

    Raises:
        UnknownNameError: otherwise, listing the tiers.
    """
    if name not in TIERS:
        raise UnknownNameError("tier", name, TIERS)
    return name


def check_pool(spec: str) -> tuple[str, ...]:
    """A distractor pool from the command line (`check_objects`); 'all' is the built-in ones."""
    return tuple(check_objects(spec, "--pool"))


def add_pool_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--pool LIST``: the objects the clutter and hard tiers draw distractors from
    (`SceneConfig.distractor_pool`), built-in or user objects; the built-in ones by default."""
    parser.add_argument(
        "--pool",
        default=(),
        type=arg(check_pool),
        metavar="LIST",
        help="'all' (default: the built-in objects) or a comma list of objects, built-in or "
        "user objects, that the clutter and hard tiers draw distractors from",
    )
