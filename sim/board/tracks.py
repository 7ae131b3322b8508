"""The board's tracks: what the robot does (``--tasks``) and the scene shifts every episode is
seen under (``--shifts``), read from the command line and named as the cells and the page name
them.

A shift setting is one scene as the estimator sees it: ``none`` (the room as it is), one factor
``NAME[:LEVEL]``, several at once joined by ``+`` (``light_colour:3+camera:3``), or every factor
at once ``all[:LEVEL]`` (`posegrasp.world.shifts`; a factor without a level is at level 2).
``--shifts`` is a comma list of settings, each a track of its own; ``factors[:LEVEL]`` stands for
``none`` and each factor alone at that level. Every setting plays the same seeds, so a shifted
cell pairs with its unshifted one episode by episode.
"""

from __future__ import annotations

from posegrasp.core.errors import InvalidArgumentError, PosegraspError
from posegrasp.core.validate import check_choice
from posegrasp.world.goals import TASKS
from posegrasp.world.shifts import ALL, DEFAULT_LEVEL, FACTORS, LEVELS, Shift, parse_shifts

#: The shift setting of the room as it is.
NO_SHIFT = "none"
#: The word of ``--shifts`` that stands for no shift and each factor alone.
EACH_FACTOR = "factors"
#: The task of today's cells (their files and keys are as before tracks).
BASE_TASK = "lift"
#: How ``--shifts`` reads, for its help and its errors.
SHIFTS_SYNTAX = (
    f"a comma list of settings, each {NO_SHIFT}, NAME[:LEVEL], NAME:LEVEL+NAME:LEVEL (at once) "
    f"or {ALL}[:LEVEL] (every factor at once); {EACH_FACTOR}[:LEVEL] is {NO_SHIFT} and each "
    f"factor alone; factors: {', '.join(FACTORS)}; levels "
    f"{', '.join(f'{k} {v}' for k, v in LEVELS.items())} (default {DEFAULT_LEVEL})"
)


def check_tasks(value: str) -> list[str]:
    """``--tasks``: a comma list of `posegrasp.world.goals.TASKS`.

    Raises:
        UnknownNameError: a task that does not exist, listing the valid ones.
        InvalidArgumentError: an empty list or a task given twice.
    """
    names = [v.strip() for v in value.split(",") if v.strip()]
    if not names:
        raise InvalidArgumentError(f"--tasks needs at least one of {', '.join(TASKS)}")
    if twice := sorted({n for n in names if names.count(n) > 1}):
        raise InvalidArgumentError(f"--tasks names {', '.join(twice)} more than once")
    return [check_choice(n, TASKS, "task") for n in names]


def shift_label(shifts: tuple[Shift, ...]) -> str:
    """A shift setting's name: ``none``, ``all:LEVEL`` for every factor at one level, else its
    factors ``NAME:LEVEL`` in `posegrasp.world.shifts.FACTORS` order joined by ``+``."""
    if not shifts:
        return NO_SHIFT
    levels = {s.level for s in shifts}
    if len(shifts) == len(FACTORS) and len(levels) == 1:
        return f"{ALL}:{levels.pop()}"
    return "+".join(str(s) for s in shifts)


def shifts_of(label: str) -> tuple[Shift, ...]:
    """The shifts a setting's name (`shift_label`) stands for.

    Raises:
        UnknownNameError, InvalidArgumentError: a name that is not a shift setting.
    """
    return parse_shifts(label.replace("+", ","))


def _expand(item: str) -> list[str]:
    """The settings one item of ``--shifts`` stands for, each named by `shift_label`."""
    name, sep, level = item.partition(":")
    if name.strip() == EACH_FACTOR:
        suffix = f":{level.strip()}" if sep else f":{DEFAULT_LEVEL}"
        return [NO_SHIFT, *(shift_label(parse_shifts(f + suffix)) for f in FACTORS)]
    return [shift_label(shifts_of(item))]


def check_shift_settings(value: str) -> list[str]:
    """``--shifts``: the shift settings of the board (`SHIFTS_SYNTAX`), each named by
    `shift_label`, in the order given.

    Raises:
        InvalidArgumentError: an empty list, a setting given twice, a bad item (one line naming
            the syntax, the factors and the levels).
    """
    items = [v.strip() for v in value.split(",") if v.strip()]
    if not items:
        raise InvalidArgumentError(f"--shifts needs at least one setting: {SHIFTS_SYNTAX}")
    labels: list[str] = []
    for item in items:
        try:
            labels += _expand(item)
        except PosegraspError as exc:
            first = str(exc).splitlines()[0].split(";")[0]
            raise InvalidArgumentError(f"--shifts {item!r}: {first}; {SHIFTS_SYNTAX}") from None
    if twice := sorted({n for n in labels if labels.count(n) > 1}):
        raise InvalidArgumentError(f"--shifts names the setting {', '.join(twice)} twice")
    return labels


def track_key(task: str, shifts: str) -> str:
    """The part of a cell's file stem its track adds: empty for today's track (``lift``, no
    shift), so today's cells keep their files; else ``__place`` and ``__shift-<setting>``."""
    key = "" if task == BASE_TASK else f"__{task}"
    return key + ("" if shifts == NO_SHIFT else f"__shift-{shifts}")


def track_title(task: str, shifts: str) -> str:
    """A track as the page names it: ``lift``, ``place``, ``lift, shift camera:3``."""
    return task if shifts == NO_SHIFT else f"{task}, shift {shifts}"
