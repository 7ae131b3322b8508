"""What a training recipe is made of, and how it runs and ships (`perception.training.recipe`
holds the recipe itself).

A `Stage` is one training run: a trainer, its data, the stage it starts from, its
hyperparameters and seed. It runs as one library call to its trainer's ``train(config)``
(`run_stage`), its checkpoint in a folder of its own, ``<checkpoints>/<stage>/``, outside the
repository. A stage whose checkpoint holds all its epochs is done; one that was stopped resumes
where it stopped. A folder records the stage it belongs to (``stage.json``), so a stage changed
in the recipe never resumes or counts as done from another stage's checkpoint.

An `Artefact` is a shipped file and the stage whose checkpoint it is; the stages behind it are
that stage's chain of starts. Nothing under the weights folder changes until `ship` runs: it
copies every artefact's checkpoint there (float16, `perception.training.shipping.ship.ship`), hashes
it and records its manifest entry, the stages behind it one by one.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from types import ModuleType
from typing import Any

from perception.training.data.dataset import PoseDataset
from perception.training.shipping.ship import checkpoint_record, ship, stamp_manifest
from perception.training.trainers import detector_trainer, masknet_trainer, posenet_trainer
from perception.training.trainers.checkpoints import read_checkpoint
from perception.training.trainers.manifest import MANIFEST_NAME, read_manifest, stage_record
from posegrasp.core.errors import AssetError, InvalidArgumentError, UnknownNameError
from posegrasp.core.files import atomic_write_json
from posegrasp.core.paths import data_root

#: The trainers a stage may use: their modules, each with ``train(config)`` and
#: ``command_line(config)``.
TRAINERS: dict[str, ModuleType] = {
    "posenet": posenet_trainer,
    "detector": detector_trainer,
    "masknet": masknet_trainer,
}
#: Each trainer's config class.
CONFIGS: dict[str, type] = {
    "posenet": posenet_trainer.PoseNetTrainConfig,
    "detector": detector_trainer.DetectorTrainConfig,
    "masknet": masknet_trainer.MaskTrainConfig,
}
#: The checkpoint file of a stage of each trainer, in the stage's folder.
CHECKPOINT_FILES = {"posenet": "posenet.pt", "detector": "detector.pt", "masknet": "last.pt"}
#: The record of the stage a checkpoint folder belongs to.
STAGE_FILE = "stage.json"
#: The config fields a stage sets itself (the rest of a trainer's config is its `settings`).
_OWN_FIELDS = {"dists", "dist_limits", "limit", "data", "also", "limits", "sources"}
_OWN_FIELDS |= {"epochs", "lr", "seed", "init", "out", "name"}


@dataclass(frozen=True)
class Stage:
    """One training run.

    Attributes:
        name: what the stage does (``ours-tune-headcam-40k``); its checkpoint folder's name.
        trainer: the trainer (`TRAINERS`).
        data: (dataset folder under the data root, training images) pairs, in order; the
            detector and the mask net validate on the first folder's val split unless told.
        epochs: passes over the data.
        lr: peak learning rate.
        init: the stage whose checkpoint the run starts from (None: from scratch), with a fresh
            optimiser and schedule.
        seed: of the run's initialisation, order and augmentation.
        settings: the trainer's further config fields, (field, value) pairs (``variant``,
            ``batch``, ``precision``, ...); a mask net's ``detector`` names the stage whose
            detector cuts its ``detected`` windows.
    """

    name: str
    trainer: str
    data: tuple[tuple[str, int], ...]
    epochs: int
    lr: float
    init: str | None = None
    seed: int = 0
    settings: tuple[tuple[str, Any], ...] = ()

    def __post_init__(self) -> None:
        if self.trainer not in TRAINERS:
            raise UnknownNameError("trainer", self.trainer, TRAINERS)
        if not self.name or "/" in self.name or not self.data or self.epochs < 1:
            raise InvalidArgumentError(
                f"stage {self.name!r} needs a plain name, data and at least one epoch"
            )
        valid = {f.name for f in fields(CONFIGS[self.trainer])} - _OWN_FIELDS
        if bad := sorted({k for k, _ in self.settings} - valid):
            raise InvalidArgumentError(
                f"stage {self.name}: unknown settings {bad}; valid: {', '.join(sorted(valid))}"
            )

    def setting(self, key: str, default: Any = None) -> Any:
        """The value of a setting, `default` when the stage does not set it."""
        return dict(self.settings).get(key, default)

    def detector_stage(self) -> str | None:
        """The detector stage that cuts a mask net's windows (a detector's own ``detector``
        setting is its architecture, not a stage)."""
        return self.setting("detector") if self.trainer == "masknet" else None

    def needs(self) -> tuple[str, ...]:
        """The stages whose checkpoints this one reads: its start and its `detector_stage`."""
        return tuple(n for n in (self.init, self.detector_stage()) if n is not None)

    def spec(self) -> dict[str, Any]:
        """The stage as plain JSON data (what its folder's `STAGE_FILE` records)."""
        return json.loads(json.dumps(asdict(self)))


@dataclass(frozen=True)
class Artefact:
    """A shipped file and the stage whose checkpoint it is.

    Attributes:
        file: its path under the weights folder (``tiers/masknet.pt``); its manifest is the
            ``manifest.json`` beside it.
        key: its entry in that manifest, e.g. ``("pose_nets", "ours")``, ``("detector",)``.
        stage: the last stage of its chain.
        unrecorded: how many of the first stages of its chain its manifest entry, written before
            the recipe shipped it, does not record (an entry the recipe ships records them all,
            each by name).
    """

    file: str
    key: tuple[str, ...]
    stage: str
    unrecorded: int = 0


@dataclass(frozen=True)
class Recipe:
    """Stages in the order they run (each after the stages it needs) and the artefacts they
    make.

    Raises:
        InvalidArgumentError: a name twice, or a stage that needs one not before it, or an
            artefact of no stage.
    """

    stages: tuple[Stage, ...]
    artefacts: tuple[Artefact, ...]

    def __post_init__(self) -> None:
        seen: dict[str, str] = {}  # name -> trainer
        for s in self.stages:
            if s.name in seen:
                raise InvalidArgumentError(f"stage {s.name} twice in the recipe")
            if missing := [n for n in s.needs() if n not in seen]:
                raise InvalidArgumentError(f"stage {s.name} needs {missing}, not before it")
            detector = s.detector_stage()
            if (s.init and seen[s.init] != s.trainer) or (
                detector and seen[detector] != "detector"
            ):
                raise InvalidArgumentError(
                    f"stage {s.name} starts from a stage of its own trainer ({s.trainer}), and "
                    "its detector is a detector stage's"
                )
            seen[s.name] = s.trainer
        for a in self.artefacts:
            self.stage(a.stage)

    def names(self) -> tuple[str, ...]:
        """The stages' names in run order."""
        return tuple(s.name for s in self.stages)

    def stage(self, name: str) -> Stage:
        """The stage called `name`.

        Raises:
            UnknownNameError: no such stage (the message lists them).
        """
        for s in self.stages:
            if s.name == name:
                return s
        raise UnknownNameError("stage", name, self.names())

    def chain(self, artefact: Artefact) -> tuple[Stage, ...]:
        """The stages behind an artefact, first to last (its stage and that stage's starts)."""
        name: str | None
        out, name = [], artefact.stage
        while name is not None:
            out.append(self.stage(name))
            name = out[-1].init
        return tuple(out[::-1])


def checkpoint_path(stage: Stage, checkpoints: Path) -> Path:
    """Where a stage keeps its checkpoint."""
    return _checkpoint(stage.name, stage.trainer, checkpoints)


def _checkpoint(name: str, trainer: str, checkpoints: Path) -> Path:
    """The checkpoint of stage `name` of `trainer`."""
    return checkpoints / name / CHECKPOINT_FILES[trainer]


def stage_config(stage: Stage, checkpoints: Path) -> Any:
    """The trainer's config of a stage: its data, schedule and settings, its start the
    checkpoint of its `init` stage, its checkpoint in ``<checkpoints>/<stage>/``."""
    out = checkpoints / stage.name
    init = None if stage.init is None else _checkpoint(stage.init, stage.trainer, checkpoints)
    names = tuple(name for name, _ in stage.data)
    settings = dict(stage.settings)
    common = {"epochs": stage.epochs, "lr": stage.lr, "seed": stage.seed, "out": out}
    if stage.trainer == "posenet":
        return CONFIGS["posenet"](
            dists=names,
            dist_limits=stage.data,
            init=None if init is None else str(init),
            name=Path(CHECKPOINT_FILES["posenet"]).stem,
            **common,
            **settings,
        )
    if stage.trainer == "detector":
        return CONFIGS["detector"](
            data=Path(names[0]), also=names[1:], limits=stage.data, init=init, **common, **settings
        )
    if (detector := settings.get("detector")) is not None:
        settings["detector"] = _checkpoint(detector, "detector", checkpoints)
    return CONFIGS["masknet"](sources=stage.data, init=init, **common, **settings)


def stage_command(stage: Stage, checkpoints: Path) -> str:
    """The trainer's command line that runs a stage by itself."""
    return TRAINERS[stage.trainer].command_line(stage_config(stage, checkpoints))


def epochs_done(stage: Stage, checkpoints: Path) -> int | None:
    """Whole epochs a stage's checkpoint holds (None: no checkpoint, or one of another stage).

    Raises:
        AssetError: the checkpoint cannot be read.
    """
    folder = checkpoints / stage.name
    path = checkpoint_path(stage, checkpoints)
    if not path.is_file() or _recorded_spec(folder) != stage.spec():
        return None
    try:
        return int(read_checkpoint(path)["epoch"])
    except Exception as exc:
        raise AssetError(f"checkpoint {path} is corrupt ({exc}); delete {folder}") from exc


def is_done(stage: Stage, checkpoints: Path) -> bool:
    """The stage's checkpoint holds all its epochs."""
    done = epochs_done(stage, checkpoints)
    return done is not None and done >= stage.epochs


def _recorded_spec(folder: Path) -> dict[str, Any] | None:
    """The stage a checkpoint folder belongs to, as it recorded it (None: none recorded)."""
    path = folder / STAGE_FILE
    return json.loads(path.read_text()) if path.is_file() else None


def missing_images(stage: Stage) -> list[str]:
    """The folders of a stage's data that hold fewer training images than the stage takes of
    them, each as ``NAME: HAVE of WANT``: a count in the recipe is what the stage trains on,
    where a trainer's own limit is only a cap."""
    out = []
    for name, want in stage.data:
        root = data_root() / name
        have = len(PoseDataset(root, "train")) if (root / "info.json").is_file() else 0
        if have < want:
            out.append(f"{name}: {have} of {want}")
    return out


def run_stage(recipe: Recipe, stage: Stage, checkpoints: Path) -> dict[str, Any]:
    """Train one stage (resuming its checkpoint when it has one): one call to its trainer's
    ``train(config)``.

    Returns:
        The trainer's result.

    Raises:
        AssetError: a stage it needs is not done, or its folder holds another stage's
            checkpoint (delete the folder to train it afresh).
    """
    for need in stage.needs():
        if not is_done(recipe.stage(need), checkpoints):
            raise AssetError(
                f"stage {stage.name} needs stage {need}, which is not trained; run it first "
                f"(--only {need}) or the whole recipe"
            )
    if short := missing_images(stage):
        raise AssetError(
            f"stage {stage.name} trains on more images than are rendered ({'; '.join(short)}); "
            "render them first (make data)"
        )
    folder = checkpoints / stage.name
    recorded = _recorded_spec(folder)
    if recorded is not None and recorded != stage.spec():
        raise AssetError(
            f"{folder} holds the checkpoint of another version of stage {stage.name} "
            f"({recorded}); delete the folder to train the stage as the recipe says"
        )
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_json(folder / STAGE_FILE, stage.spec())
    return TRAINERS[stage.trainer].train(stage_config(stage, checkpoints))


def manifest_entry(weights: Path, artefact: Artefact) -> dict[str, Any] | None:
    """An artefact's entry in the manifest beside it (None: none recorded)."""
    entry: Any = read_manifest((weights / artefact.file).parent / MANIFEST_NAME)
    for part in artefact.key:
        entry = entry.get(part) if isinstance(entry, dict) else None
    return entry if isinstance(entry, dict) else None


def artefact_records(
    recipe: Recipe, artefact: Artefact, weights: Path
) -> list[tuple[Stage, dict[str, Any]]]:
    """The stages behind an artefact paired with their records in its manifest entry under
    `weights` (`stage_record`s; none when there is no entry).

    An entry the recipe shipped names the stage of each record; an older one is matched to the
    artefact's chain from its end, its first `Artefact.unrecorded` stages without a record.

    Raises:
        AssetError: an entry whose records are not the chain's stages.
    """
    entry = manifest_entry(weights, artefact)
    if entry is None:
        return []
    records = entry.get("stages") or [stage_record(entry)]
    chain = recipe.chain(artefact)
    if all("stage" in r for r in records):
        names = [r["stage"] for r in records]
        if names != [s.name for s in chain]:
            raise AssetError(f"{artefact.file}: its manifest records stages {names}")
        return list(zip(chain, records, strict=True))
    recorded = chain[artefact.unrecorded :]
    if len(recorded) != len(records):
        raise AssetError(
            f"{artefact.file}: its manifest records {len(records)} stages, the recipe "
            f"{len(recorded)} ({', '.join(s.name for s in recorded)})"
        )
    return list(zip(recorded, records, strict=True))


def recorded_stages(recipe: Recipe, weights: Path) -> dict[str, dict[str, Any]]:
    """Each stage's record in the manifests under `weights` (`artefact_records`), by stage
    name; a stage behind several artefacts takes the first record that gives a wall time.

    Raises:
        AssetError: an entry whose records are not its artefact's stages.
    """
    out: dict[str, dict[str, Any]] = {}
    for artefact in recipe.artefacts:
        for stage, record in artefact_records(recipe, artefact, weights):
            if out.get(stage.name, {}).get("wall_s") is None:
                out[stage.name] = record
    return out


def ship_all(recipe: Recipe, checkpoints: Path, weights: Path) -> list[dict[str, Any]]:
    """Ship every artefact: its stage's checkpoint copied into `weights` (float16), hashed and
    recorded in the manifest beside it with each stage behind it (`checkpoint_record`, named).

    Returns:
        The manifest entries, in the order of the artefacts.

    Raises:
        AssetError: a stage behind an artefact is not done (nothing is written then).
    """
    needed = {s.name for a in recipe.artefacts for s in recipe.chain(a)}
    if undone := [
        n for n in recipe.names() if n in needed and not is_done(recipe.stage(n), checkpoints)
    ]:
        raise AssetError(
            f"not trained yet: {', '.join(undone)}; run `python -m perception.training.recipe` "
            "first (nothing was shipped)"
        )
    entries = []
    for artefact in recipe.artefacts:
        chain = recipe.chain(artefact)
        earlier = [
            {
                "stage": s.name,
                **checkpoint_record(read_checkpoint(checkpoint_path(s, checkpoints))),
                "command": stage_command(s, checkpoints),
            }
            for s in chain[:-1]
        ]
        last = chain[-1]
        state = read_checkpoint(checkpoint_path(last, checkpoints))
        kind = last.trainer
        dest = weights / artefact.file
        command = stage_command(last, checkpoints)
        entries.append(ship(state, kind, dest, artefact.key, command, earlier, stage=last.name))
    stamp_manifest(weights)
    return entries
