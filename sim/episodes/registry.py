"""The estimator registry of the experiment: the oracles, the learned estimators by name
(`perception.estimators`), the classical peers (`perception.peers`, which need the depth image:
`needs_depth`) and plug-ins.

Real estimators implement `posegrasp.core.contract.PoseEstimator`. The oracles are the experiment's
own instruments, not estimators a robot could run: they implement `PrivilegedEstimator` and are
handed the true pose by the episode, which no other estimator ever sees.

An estimator is named by a *spec*, which every ``--estimator`` option and `make_estimator` take:

- a built-in name (`ESTIMATORS`);
- ``package.module:factory``, a callable that returns an object implementing the contract (a
  class, a function; ``factory`` may be dotted, ``module:Class.create``); the module must be
  importable where the episodes run (installed, or on ``PYTHONPATH``);
- the name of an entry point of the group `ENTRY_POINT_GROUP` that an installed package
  declares, pointing at such a factory.

`estimator_weights` says which weights files an estimator loads, for the gate's fingerprint: a
learned estimator's as its factory opens them (`perception.estimators.weights_files`), none for
an oracle, and a plug-in's as its optional ``weights_files()`` method reports them (a sequence of
paths); `estimator_fingerprint` hashes them. `estimator_settings` adds the settings it holds,
for the leaderboard's cells.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import importlib.metadata
import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from perception.estimators import LEARNED_ESTIMATORS, weights_files
from perception.peers import PEER_ESTIMATORS, peer_weights_files
from posegrasp.core.contract import CONTRACT_VERSION, Estimate, Observation, PoseEstimator
from posegrasp.core.errors import InvalidArgumentError, PosegraspError, UnknownNameError
from posegrasp.core.files import sha256_file
from posegrasp.core.paths import REPO_ROOT, in_repo
from posegrasp.core.validate import arg, check_choice
from posegrasp.world.goals import TASKS
from posegrasp.world.sensors import SENSOR_NAMES
from sim.episodes.pose_noise import NOISE_FORMAT, PoseNoise, parse_noise, perturb_pose

#: Other objects' poses: (class, T_C_N) pairs in the camera frame.
Neighbours = Sequence[tuple[str, np.ndarray]]


@runtime_checkable
class PrivilegedEstimator(Protocol):
    """An instrument of the experiment that is given the true pose (the oracles)."""

    name: str

    def estimate_from_truth(
        self, obs: Observation, T_C_O_true: np.ndarray, neighbours: Neighbours
    ) -> Estimate:
        """The estimate to grasp on, derived from the true pose T_C_O_true (4, 4) and the other
        objects' true poses `neighbours`, (class, T_C_N) pairs in the camera frame."""
        ...


class OracleEstimator:
    """The true pose and the true neighbours."""

    name = "oracle"

    def estimate_from_truth(
        self, obs: Observation, T_C_O_true: np.ndarray, neighbours: Neighbours
    ) -> Estimate:
        return Estimate(np.array(T_C_O_true, dtype=float), tuple(neighbours))


class NoisyOracleEstimator:
    """The true pose with seeded, controlled errors (see `PoseNoise`), and the true neighbours.

    The errors of an episode come from its seed alone: at every noise level a seed draws the same
    standard-normal numbers, scaled by the level's sigmas (common random numbers), so runs at
    different levels are paired.
    """

    name = "noisy-oracle"

    def __init__(self, noise: PoseNoise | None = None) -> None:
        self.noise = noise or PoseNoise(
            ray=0.01, lateral=0.005, inplane=np.deg2rad(3), outplane=np.deg2rad(3)
        )

    def estimate_from_truth(
        self, obs: Observation, T_C_O_true: np.ndarray, neighbours: Neighbours
    ) -> Estimate:
        T = perturb_pose(np.array(T_C_O_true, dtype=float), self.noise, self.noise.rng(obs.seed))
        return Estimate(T, tuple(neighbours))


#: Estimator factories by name.
ESTIMATORS: dict[str, Callable[[], PoseEstimator | PrivilegedEstimator]] = {
    "oracle": OracleEstimator,
    "noisy-oracle": NoisyOracleEstimator,
    **LEARNED_ESTIMATORS,
    **PEER_ESTIMATORS,
}


#: What the CLIs and the gate use unless told otherwise: the estimator that grasps best on every
#: tier (docs/RESULTS.md, "How often does each estimator's grasp succeed per tier?").
DEFAULT_ESTIMATOR = "hybrid-global"


#: The leaderboard's rows unless told otherwise, in order: the true pose, our estimators, the
#: classical peers and the crude example (an installed entry point, `examples/crude-estimator`).
BOARD_ESTIMATORS: tuple[str, ...] = (
    "oracle",
    DEFAULT_ESTIMATOR,
    "hybrid",
    "hybrid-global-icp",
    "ppf",
    "ppf-det",
    "fpfh-icp",
    "fpfh-icp-det",
    "crude",
)
#: The classical depth peers, the field's own methods (`perception.peers`), that the board holds
#: `DEFAULT_ESTIMATOR` against; the other peer, ``hybrid-global-icp``, is ours with ICP.
CLASSICAL_PEERS: tuple[str, ...] = tuple(n for n in PEER_ESTIMATORS if n != "hybrid-global-icp")


#: The entry-point group through which installed packages offer estimators (each entry point
#: names a factory, as ``package.module:factory``).
ENTRY_POINT_GROUP = "posegrasp.estimators"


def entry_point_estimators() -> dict[str, importlib.metadata.EntryPoint]:
    """The estimators installed packages declare in `ENTRY_POINT_GROUP`, by name; a name that a
    built-in estimator already has is left out (the built-in one wins)."""
    eps = importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)
    return {ep.name: ep for ep in sorted(eps, key=lambda e: e.name) if ep.name not in ESTIMATORS}


def _spec_choices() -> list[str]:
    return [*ESTIMATORS, *entry_point_estimators(), "package.module:factory"]


def _load_factory(spec: str) -> Callable[[], Any]:
    """The factory of a ``module:attr`` spec, imported.

    Raises:
        InvalidArgumentError: a malformed spec, a module that does not import, a missing
            attribute or one that is not callable.
    """
    module, _, attr = spec.partition(":")
    if not module or not attr or ":" in attr:
        raise InvalidArgumentError(
            f"invalid estimator {spec!r}; a plug-in is package.module:factory"
        )
    try:
        obj: Any = importlib.import_module(module)
    except Exception as exc:  # any import failure of foreign code is one line
        raise InvalidArgumentError(
            f"estimator {spec!r}: cannot import {module!r} ({type(exc).__name__}: {exc}); "
            "install its package or put it on PYTHONPATH"
        ) from None
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise InvalidArgumentError(f"estimator {spec!r}: {module!r} has no {attr!r}")
        obj = getattr(obj, part)
    if not callable(obj):
        raise InvalidArgumentError(f"estimator {spec!r}: {attr!r} is not callable")
    return obj


def check_estimator(estimator: Any, spec: str) -> PoseEstimator | PrivilegedEstimator:
    """`estimator` when it implements the contract: a ``name`` string and a callable
    ``estimate``.

    Raises:
        InvalidArgumentError: it does not, naming what is missing and the contract version.
    """
    if isinstance(estimator, PrivilegedEstimator):
        return estimator
    missing = [
        what
        for what, ok in (
            ("a callable estimate(obs)", callable(getattr(estimator, "estimate", None))),
            ("a str name", isinstance(getattr(estimator, "name", None), str)),
        )
        if not ok
    ]
    if missing:
        raise InvalidArgumentError(
            f"estimator {spec!r} made a {type(estimator).__name__} without "
            f"{' and '.join(missing)} (posegrasp.core.contract, version {CONTRACT_VERSION})"
        )
    return estimator


def check_estimator_spec(spec: str) -> str:
    """A spec (see the module docstring) returned as given once it resolves: a built-in or
    entry-point name, or a ``module:factory`` whose factory imports (it is not called).

    Raises:
        UnknownNameError: a name that is neither built in nor installed, listing the valid ones.
        InvalidArgumentError: a plug-in spec that does not import.
    """
    spec = str(spec)
    if spec in ESTIMATORS:
        return spec
    if ":" in spec:
        _load_factory(spec)
        return spec
    eps = entry_point_estimators()
    if spec not in eps:
        raise UnknownNameError("estimator", spec, _spec_choices())
    return spec


def make_estimator(
    spec: str, noise: PoseNoise | None = None
) -> PoseEstimator | PrivilegedEstimator:
    """The estimator a spec names (see the module docstring): a built-in one, a plug-in's
    ``package.module:factory`` or an installed entry point; `noise` sets the errors of
    ``noisy-oracle``.

    Raises:
        UnknownNameError: an unknown name.
        InvalidArgumentError: `noise` given for another estimator; a plug-in that does not
            import, or whose factory fails or returns an object without the contract.
    """
    if noise is not None:
        if spec != "noisy-oracle":
            raise InvalidArgumentError(f"--noise applies to noisy-oracle only, not to {spec}")
        return NoisyOracleEstimator(noise)
    if spec in ESTIMATORS:
        return ESTIMATORS[spec]()
    check_estimator_spec(spec)
    if ":" in spec:
        factory = _load_factory(spec)
    else:
        try:
            factory = entry_point_estimators()[spec].load()
        except Exception as exc:  # a broken installed package is one line
            raise InvalidArgumentError(
                f"estimator {spec!r}: its entry point does not load ({type(exc).__name__}: {exc})"
            ) from None
    try:
        estimator = factory()
    except PosegraspError:
        raise
    except Exception as exc:  # foreign code: its failure is one line, not a traceback
        raise InvalidArgumentError(
            f"estimator {spec!r}: its factory failed ({type(exc).__name__}: {exc})"
        ) from None
    return check_estimator(estimator, spec)


def estimator_weights(spec: str) -> tuple[Path, ...] | None:
    """The weights files the estimator a spec names loads: a learned estimator's as its factory
    opens them (`perception.estimators.weights_files`), () for an oracle, a plug-in's as its
    ``weights_files()`` method reports them; None for a plug-in without that method (its weights
    are unknown). Makes the estimator to find out.

    Raises:
        UnknownNameError: an unknown name.
        InvalidArgumentError: a plug-in that does not load, or whose ``weights_files()`` fails or
            gives something other than paths.
        AssetError: a learned estimator's weights are missing or corrupt.
    """
    if spec in LEARNED_ESTIMATORS:
        return weights_files(spec)
    if spec in PEER_ESTIMATORS:
        return peer_weights_files(spec)
    if spec in ESTIMATORS:
        return ()
    report = getattr(make_estimator(spec), "weights_files", None)
    if not callable(report):
        return None
    try:
        return tuple(Path(f) for f in report())
    except Exception as exc:  # foreign code: its failure is one line, not a traceback
        raise InvalidArgumentError(
            f"estimator {spec!r}: its weights_files() failed ({type(exc).__name__}: {exc}); "
            "it must return a sequence of paths"
        ) from None


#: The packages whose objects `estimator_settings` looks into.
OWN_PACKAGES = ("perception", "sim", "posegrasp", "grasping", "examples")


def weights_fingerprint(files: Sequence[Path]) -> dict[str, str]:
    """SHA-256 (first 16 hex digits) of each weights file, "missing" when absent, by its path
    (relative to the repository, POSIX, when inside it)."""
    out = {}
    for f in files:
        p = Path(f).resolve()
        key = p.relative_to(REPO_ROOT).as_posix() if p.is_relative_to(REPO_ROOT) else str(p)
        out[key] = sha256_file(p)[:16] if p.is_file() else "missing"
    return out


def estimator_fingerprint(estimator: str) -> tuple[dict[str, str], str | None]:
    """The fingerprint of the weights files `estimator` loads (`weights_fingerprint` of
    `sim.episodes.registry.estimator_weights`), and a note when it reports none (a plug-in without
    ``weights_files()``: the fingerprint is then empty)."""
    files = estimator_weights(estimator)
    if files is None:
        return {}, (
            f"{estimator} does not report the weights files it loads (no weights_files() "
            "method): its fingerprint is empty, so the gate cannot tell its weights changed"
        )
    return weights_fingerprint(files), None


def estimator_settings(spec: str) -> dict[str, Any]:
    """What besides the code shapes the estimates of the estimator `spec` names, as JSON: the
    `weights_fingerprint` of the weights files it loads (None where a plug-in does not say) and
    its settings, as `settings_of` reads them from a freshly made estimator.

    Raises:
        as `make_estimator` and `estimator_weights`.
    """
    files = estimator_weights(spec)
    weights = None if files is None else weights_fingerprint(files)
    return {"weights": weights, "settings": settings_of(make_estimator(spec))}


def settings_of(obj: Any, depth: int = 0) -> Any:
    """The settings an object holds: every ``...Config`` dataclass and plain value (bool, int,
    float, str, and lists of them) among the public attributes of the object and of its parts of
    posegrasp's own classes (`OWN_PACKAGES`), down to 5 levels, as JSON; {} where there is none.
    A path inside the repository is written relative to it, so that every checkout reads the
    same."""
    if isinstance(obj, bool | int | float):
        return obj
    if isinstance(obj, str | Path):
        return str(in_repo(obj)) if Path(obj).is_absolute() else str(obj)
    if isinstance(obj, list | tuple) and all(isinstance(v, bool | int | float | str) for v in obj):
        return list(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        if type(obj).__name__.endswith("Config"):
            fields = {f.name: settings_of(getattr(obj, f.name), 0) for f in dataclasses.fields(obj)}
            return json.loads(json.dumps(fields, default=str))
    own = type(obj).__module__.split(".")[0] in OWN_PACKAGES
    if depth >= 5 or not own or not hasattr(obj, "__dict__"):
        return {}
    out = {}
    for key, value in sorted(vars(obj).items()):
        if not key.startswith("_"):
            found = settings_of(value, depth + 1)
            if found != {}:
                out[key] = found
    return out


def check_noise(spec: str) -> str:
    """A ``--noise`` value (`sim.episodes.pose_noise.NOISE_FORMAT`), returned as given once it
    parses.

    Raises:
        InvalidArgumentError: not of the format.
    """
    parse_noise(spec)
    return spec


def add_estimator_arguments(
    parser: argparse.ArgumentParser,
    default: str | None = DEFAULT_ESTIMATOR,
    noise: bool = True,
    purpose: str | None = None,
    also: Sequence[str] = (),
) -> None:
    """Add ``--estimator SPEC`` (a built-in name, an installed entry point or
    ``package.module:factory``; see the module docstring) and, with `noise`, ``--noise SIGMAS``
    (noisy-oracle's errors), both checked while parsing; `make_estimator` refuses ``--noise``
    for another estimator.

    Args:
        parser: the command line.
        default: the estimator unless told otherwise (None: none).
        noise: add ``--noise``.
        purpose: what the estimator is for, shown before the list of names.
        also: further names the command accepts beside `ESTIMATORS`.
    """
    names = [*ESTIMATORS, *entry_point_estimators(), *also]
    lead = f"{purpose}; " if purpose else ""
    tail = "" if default is None else f" (default {default})"

    def check(spec: str) -> str:
        if spec in also:
            return spec
        try:
            return check_estimator_spec(spec)
        except UnknownNameError:
            raise UnknownNameError("estimator", spec, [*also, *_spec_choices()]) from None

    parser.add_argument(
        "--estimator",
        default=default,
        type=arg(check),
        metavar="SPEC",
        help=f"{lead}one of: {', '.join(names)}, or a plug-in package.module:factory{tail}",
    )
    if noise:
        parser.add_argument(
            "--noise",
            default=None,
            type=arg(check_noise),
            metavar="SIGMAS",
            help=f"noisy-oracle's Gaussian sigmas: {NOISE_FORMAT}",
        )


#: What an observation holds (`sim.episodes.episode.OBS_MODES`, repeated here so that parsing a
#: command line imports no episode machinery; a test keeps the two equal).
OBS_MODES = ("rgb", "rgbd")


def add_obs_mode_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--obs-mode {rgb,rgbd}``: ``rgbd`` hands the estimator the head camera's depth image
    too (`posegrasp.core.contract.Observation.depth`)."""
    parser.add_argument(
        "--obs-mode",
        default="rgb",
        type=arg(check_choice, OBS_MODES, "observation mode"),
        help="what the estimator sees: rgb (default) or rgbd (adds depth, float32 metres, z along "
        "the optical axis)",
    )


def add_sensor_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--sensor NAME``: the head camera's sensor model the estimator observes through
    (`posegrasp.world.sensors.SENSOR_NAMES`, `sim.episodes.episode.EpisodeConfig.sensor`); a bad
    name is one line listing the valid ones."""
    parser.add_argument(
        "--sensor",
        default="ideal",
        type=arg(check_choice, SENSOR_NAMES, "sensor"),
        metavar="NAME",
        help=f"the head camera's sensor model, one of: {', '.join(SENSOR_NAMES)} (default ideal: "
        "the rendered images; a depth model changes the depth image, seen with --obs-mode rgbd; "
        "+camera adds a colour camera's noise)",
    )


def add_task_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--task lift|place``: what the robot does with the object
    (`posegrasp.world.goals.TASKS`); a bad name is one line listing the valid ones."""
    parser.add_argument(
        "--task",
        default="lift",
        type=arg(check_choice, TASKS, "task"),
        help="lift: grasp, lift and hold (default); place: then carry the object to a goal pose "
        "drawn from the seed, set it down and score where it rests (2 cm, 10 deg)",
    )


def add_shift_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--shift SPEC``: the scene shifts every episode is seen under
    (`posegrasp.world.shifts.parse_shifts`: ``NAME[:LEVEL]``, a comma list, ``all[:LEVEL]``);
    a bad spec is one line listing the factors and levels."""
    from posegrasp.world.shifts import FACTORS, parse_shifts

    parser.add_argument(
        "--shift",
        default=(),
        type=arg(parse_shifts),
        metavar="SPEC",
        help=f"purely visual scene shifts: NAME[:LEVEL], a comma list or all[:LEVEL]; factors: "
        f"{', '.join(FACTORS)}; levels 1 mild, 2 medium (a bare name), 3 strong (default: none)",
    )


def needs_depth(spec: str) -> bool:
    """Whether the estimator a spec names needs the depth image (the classical peers,
    `perception.peers.PEER_ESTIMATORS`); a plug-in is not known to."""
    return spec in PEER_ESTIMATORS


def check_depth(spec: str, obs_mode: str) -> None:
    """Refuse an estimator that needs depth in an observation mode without it.

    Raises:
        InvalidArgumentError: `needs_depth(spec)` and `obs_mode` is not ``rgbd``.
    """
    if needs_depth(spec) and obs_mode != "rgbd":
        raise InvalidArgumentError(
            f"estimator {spec} needs the depth image: add --obs-mode rgbd (observation mode "
            f"{obs_mode!r} has none)"
        )


def depth_unused_note(obs_mode: str, sensor: str) -> str | None:
    """The note a command prints (one line, on standard error) when the sensor's depth model
    changes the depth image but the estimator sees none: an RGB-only observation (``obs_mode``
    ``rgb``) through a sensor whose depth model is not ``ideal`` (``kinect-v1``,
    ``azure-tof+camera``, ...) observes exactly what it would with that sensor's colour model
    alone.

    Args:
        obs_mode: the observation mode, one of `OBS_MODES`.
        sensor: the sensor's name, one of `posegrasp.world.sensors.SENSOR_NAMES`.

    Returns:
        The line, starting with ``note: ``; None when the depth is seen (``rgbd``) or the depth
        model is ``ideal``.

    Raises:
        UnknownNameError: an observation mode not in `OBS_MODES` or a sensor not in
            `SENSOR_NAMES`.
    """
    check_choice(obs_mode, OBS_MODES, "observation mode")
    depth = check_choice(sensor, SENSOR_NAMES, "sensor").partition("+")[0]
    if obs_mode == "rgbd" or depth == "ideal":
        return None
    return (
        f"note: the depth of sensor {sensor} goes unused: --obs-mode {obs_mode} hands the "
        "estimator no depth image (--obs-mode rgbd does)"
    )
