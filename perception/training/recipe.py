"""The recipe of the shipped weights: every training stage behind every file under
``perception/weights/``, as data (`RECIPE`), and the command that runs it
(`perception.training.shipping.recipe_stages` says how a stage runs and how the weights ship).

    python -m perception.training.recipe --dry-run   # the plan: recorded wall time, what is done
    python -m perception.training.recipe             # train every stage not done (resumes)
    python -m perception.training.recipe --only ours-tune-headcam-40k   # one stage
    python -m perception.training.recipe --ship      # ... then ship into perception/weights/
    python -m perception.training.recipe --smoke --ship --weights /tmp/w   # seconds, tiny data

Checkpoints live in ``<data>/checkpoints/<stage>/``; nothing under ``perception/weights/`` changes
until ``--ship``. The stages are those the manifests record (``pose_nets.<net>.stages``,
``detector``, ``mask_net``, ...), stage for stage: `tests/test_recipe.py` holds each stage to its
record (command, data, seeds). docs/DESIGN.md §7 says what the stages are for.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from perception.detector_net import ANY_OBJECT, DetectorConfig
from perception.mask_net import MaskNetConfig
from perception.training.data.render_split import GenConfig, generate
from perception.training.shipping.recipe_stages import (
    Artefact,
    Recipe,
    Stage,
    checkpoint_path,
    epochs_done,
    is_done,
    recorded_stages,
    run_stage,
    ship_all,
)
from perception.training.shipping.ship import plot_curves
from perception.training.trainers.checkpoints import read_checkpoint
from perception.training.trainers.detector_trainer import SMOKE as DETECTOR_SMOKE
from perception.training.trainers.masknet_trainer import PROTOCOLS
from perception.training.trainers.posenet_trainer import SMOKE as POSENET_SMOKE
from posegrasp.core.cli import ArgumentParser, command
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.paths import WEIGHTS_DIR, checkpoint_dir, data_root
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_output_dir, check_plot_path


def _stage(trainer: str) -> Callable[..., Stage]:
    """A `Stage` maker for `trainer` that takes the data as a dict and settings as keywords."""

    def make(
        name: str,
        data: dict[str, int],
        *,
        epochs: int,
        lr: float,
        init: str | None = None,
        seed: int = 0,
        **settings: Any,
    ) -> Stage:
        return Stage(
            name, trainer, tuple(data.items()), epochs, lr, init, seed, tuple(settings.items())
        )

    return make


_posenet, _detector, _masknet = _stage("posenet"), _stage("detector"), _stage("masknet")
_TIERS = {"headcam_hard": 3000, "headcam_any-pose": 3000, "headcam": 3000}
#: The mask nets' data are their protocols' (what ``train_masknet --protocol P`` trains on).
_TIERS_MORE_HARD, _TIERS_VAL = dict(PROTOCOLS["tiers"].sources), PROTOCOLS["tiers"].val
_PAPER, _PAPER_VAL = dict(PROTOCOLS["paper"].sources), PROTOCOLS["paper"].val
#: The rooms' stages: scenes in rooms drawn for training (`perception.training.data.rooms`), with
#: plain scenes the tiers' stages saw, so that the plain room is kept.
_ROOMS = {
    "headcam_hard_rooms": 2500,
    "headcam_rooms": 2500,
    "headcam_any-pose_rooms": 1000,
    "headcam_hard": 1500,
    "headcam": 1500,
}
_ROOMS_VAL = ("headcam_hard_rooms", 200)
#: Then rooms that differ in most factors at once (the ``joint`` family), with some of the first
#: rooms and plain scenes again.
_ROOMS_JOINT = {
    "headcam_hard_rooms_joint": 3000,
    "headcam_rooms_joint": 1500,
    "headcam_hard_rooms": 1000,
    "headcam_hard": 1500,
    "headcam": 500,
}
_ROOMS_JOINT_VAL = ("headcam_hard_rooms_joint", 200)
#: Then the joint rooms again, more of them, new ones among them.
_ROOMS_JOINT_MORE = {
    "headcam_hard_rooms_joint": 5500,
    "headcam_rooms_joint": 2500,
    "headcam_hard": 1500,
    "headcam_hard_rooms": 1000,
    "headcam": 500,
}
#: `hybrid-global-unseen`'s detector of any object: scenes of the training bank's meshes and of
#: generated shapes in rooms (``datagen --bank [shapes] --rooms``), never a built-in object.
_UNSEEN = {"headcam_bank_rooms": 4000, "headcam_bank_shapes_rooms": 3000}
_ANY_OBJECT = DetectorConfig(classes=(ANY_OBJECT,), n_classes=2)
_PAPER_DETECTED = {"val": _PAPER_VAL, "channels_last": True, "detector": "detector-tune-paper"}

#: Every stage behind the shipped weights, in the order they run.
STAGES: tuple[Stage, ...] = (
    # The pose net `ours`: both distributions from scratch, then ever more head-camera images,
    # the far tier joining from the fifth stage, each stage with a fresh optimiser.
    _posenet(
        "ours-scratch-paper-and-headcam", {"paper": 20000, "headcam": 5000}, epochs=16, lr=2e-3
    ),
    _posenet(
        "ours-tune-headcam-10k",
        {"headcam": 10000},
        epochs=14,
        lr=1e-3,
        init="ours-scratch-paper-and-headcam",
    ),
    _posenet(
        "ours-tune-headcam-20k", {"headcam": 20000}, epochs=6, lr=5e-4, init="ours-tune-headcam-10k"
    ),
    _posenet(
        "ours-tune-headcam-40k", {"headcam": 40000}, epochs=5, lr=5e-4, init="ours-tune-headcam-20k"
    ),
    _posenet(
        "ours-add-far-5k",
        {"headcam": 40000, "headcam_far": 5000},
        epochs=3,
        lr=2e-4,
        init="ours-tune-headcam-40k",
    ),
    _posenet(
        "ours-tune-headcam-80k-far-5k",
        {"headcam": 80000, "headcam_far": 5000},
        epochs=3,
        lr=3e-4,
        init="ours-add-far-5k",
    ),
    _posenet(
        "ours-tune-headcam-120k-far-10k",
        {"headcam": 120000, "headcam_far": 10000},
        epochs=2,
        lr=3e-4,
        init="ours-tune-headcam-80k-far-5k",
    ),
    _posenet(
        "ours-tune-headcam-160k-far-20k",
        {"headcam": 160000, "headcam_far": 20000},
        epochs=2,
        lr=3e-4,
        init="ours-tune-headcam-120k-far-10k",
    ),
    # Its expert on the hard tier, from the second stage.
    _posenet(
        "ours-hard-expert",
        {"headcam": 5000, "headcam_hard": 3000},
        epochs=5,
        lr=5e-4,
        init="ours-tune-headcam-10k",
    ),
    # The paper's variant on the paper's protocol alone, from scratch, then two more runs.
    _posenet(
        "paper-scratch",
        {"paper": 40000},
        epochs=10,
        lr=2e-3,
        variant="paper",
        batch=64,
        precision="bf16",
    ),
    _posenet(
        "paper-tune-25-epochs",
        {"paper": 40000},
        epochs=25,
        lr=1e-3,
        init="paper-scratch",
        variant="paper",
        batch=64,
        precision="bf16",
        channels_last=True,
    ),
    _posenet(
        "paper-tune-25-more-epochs",
        {"paper": 40000},
        epochs=25,
        lr=1e-3,
        init="paper-tune-25-epochs",
        variant="paper",
        batch=64,
        precision="bf16",
        channels_last=True,
    ),
    # The head camera's detector from scratch, then with the hard tier's images.
    _detector("detector-scratch-headcam", {"headcam": 5000}, epochs=8, lr=1e-3),
    _detector(
        "detector-tune-headcam-and-hard",
        {"headcam": 2500, "headcam_hard": 2500},
        epochs=1,
        lr=5e-4,
        init="detector-scratch-headcam",
    ),
    # The paper protocol's detector, from the head camera's.
    _detector(
        "detector-tune-headcam-and-paper",
        {"headcam": 2500, "paper": 2500},
        epochs=1,
        lr=5e-4,
        init="detector-tune-headcam-and-hard",
    ),
    _detector(
        "detector-tune-paper",
        {"paper": 10000},
        epochs=1,
        lr=3e-4,
        init="detector-tune-headcam-and-paper",
        precision="bf16",
        channels_last=True,
    ),
    # hybrid-global's detector, from the head camera's, on the tiers' scenes.
    _detector(
        "detector-tune-tiers",
        _TIERS,
        epochs=3,
        lr=5e-4,
        init="detector-tune-headcam-and-hard",
        precision="bf16",
        channels_last=True,
    ),
    _detector(
        "detector-tune-tiers-more-hard",
        _TIERS_MORE_HARD,
        epochs=1,
        lr=3e-4,
        init="detector-tune-tiers",
        precision="bf16",
        channels_last=True,
    ),
    # The tiers' mask net, then a stage on windows jittered afresh.
    _masknet(
        "masknet-tiers-scratch",
        _TIERS_MORE_HARD,
        epochs=5,
        lr=2e-3,
        val=_TIERS_VAL,
        channels_last=True,
    ),
    _masknet(
        "masknet-tiers-fresh-windows",
        _TIERS_MORE_HARD,
        epochs=3,
        lr=1e-3,
        init="masknet-tiers-scratch",
        seed=1,
        val=_TIERS_VAL,
        channels_last=True,
    ),
    # `hybrid-global-rooms`' detector and mask net: the tiers' ones, further on the rooms, then
    # on rooms that differ in most ways at once (the joint family).
    _detector(
        "detector-tune-tiers-rooms",
        _ROOMS,
        epochs=2,
        lr=3e-4,
        init="detector-tune-tiers-more-hard",
        precision="bf16",
        channels_last=True,
    ),
    _masknet(
        "masknet-tiers-rooms",
        _ROOMS,
        epochs=2,
        lr=5e-4,
        init="masknet-tiers-fresh-windows",
        seed=2,
        val=_ROOMS_VAL,
        channels_last=True,
    ),
    _detector(
        "detector-tune-tiers-rooms-joint",
        _ROOMS_JOINT,
        epochs=2,
        lr=2e-4,
        init="detector-tune-tiers-rooms",
        channels_last=True,
    ),
    _detector(
        "detector-tune-tiers-rooms-joint-more",
        _ROOMS_JOINT_MORE,
        epochs=1,
        lr=1.5e-4,
        init="detector-tune-tiers-rooms-joint",
        channels_last=True,
    ),
    _masknet(
        "masknet-tiers-rooms-joint",
        _ROOMS_JOINT,
        epochs=1,
        lr=3e-4,
        init="masknet-tiers-rooms",
        seed=3,
        val=_ROOMS_JOINT_VAL,
        precision="fp32",
        channels_last=True,
    ),
    # `hybrid-global-unseen`'s detector and mask net: the rooms' ones on bank scenes alone, the
    # detector made a detector of any object (its per-class layers start afresh).
    _detector(
        "detector-unseen-bank",
        _UNSEEN,
        epochs=2,
        lr=3e-4,
        init="detector-tune-tiers-rooms-joint",
        channels_last=True,
        detector=_ANY_OBJECT,
    ),
    _masknet(
        "masknet-unseen-bank",
        {"headcam_bank_rooms": 3000, "headcam_bank_shapes_rooms": 2000},
        epochs=1,
        lr=3e-4,
        init="masknet-tiers-rooms-joint",
        seed=4,
        val=("headcam_bank_held-out_rooms", 200),
        precision="fp32",
        channels_last=True,
    ),
    # The paper protocol's mask net; its last stages also learn from the windows its detector
    # cuts of the training images after the first 30,000, the very last one shipped as the
    # faucet's own net.
    _masknet(
        "masknet-paper-scratch",
        _PAPER,
        epochs=6,
        lr=2e-3,
        val=_PAPER_VAL,
        channels_last=True,
    ),
    _masknet(
        "masknet-paper-fresh-windows",
        _PAPER,
        epochs=4,
        lr=1e-3,
        init="masknet-paper-scratch",
        seed=1,
        val=_PAPER_VAL,
        channels_last=True,
    ),
    _masknet(
        "masknet-paper-fresh-windows-lower-lr",
        _PAPER,
        epochs=4,
        lr=5e-4,
        init="masknet-paper-fresh-windows",
        seed=2,
        val=_PAPER_VAL,
        channels_last=True,
    ),
    _masknet(
        "masknet-paper-detector-masks-10k",
        _PAPER,
        epochs=3,
        lr=5e-4,
        init="masknet-paper-fresh-windows-lower-lr",
        seed=3,
        detected=("paper", 30000, 10000),
        **_PAPER_DETECTED,
    ),
    _masknet(
        "masknet-paper-detector-masks-20k",
        _PAPER,
        epochs=2,
        lr=5e-4,
        init="masknet-paper-detector-masks-10k",
        seed=4,
        detected=("paper", 30000, 20000),
        **_PAPER_DETECTED,
    ),
    _masknet(
        "masknet-paper-detector-masks-40k",
        _PAPER,
        epochs=2,
        lr=5e-4,
        init="masknet-paper-detector-masks-20k",
        seed=5,
        detected=("paper", 30000, 40000),
        **_PAPER_DETECTED,
    ),
)

#: The recipe of the shipped weights: every file under ``perception/weights/`` that a manifest
#: records, and the stage whose checkpoint it is.
RECIPE = Recipe(
    STAGES,
    (
        Artefact("posenet_ours.pt", ("pose_nets", "ours"), "ours-tune-headcam-160k-far-20k"),
        Artefact("posenet_ours_hard.pt", ("pose_nets", "ours_hard"), "ours-hard-expert"),
        Artefact("posenet_paper.pt", ("pose_nets", "paper"), "paper-tune-25-more-epochs"),
        Artefact("detector.pt", ("detector",), "detector-tune-headcam-and-hard", unrecorded=1),
        Artefact("tiers/detector.pt", ("detector",), "detector-tune-tiers-more-hard", 1),
        Artefact("tiers/masknet.pt", ("mask_net",), "masknet-tiers-fresh-windows"),
        Artefact("rooms/detector.pt", ("detector",), "detector-tune-tiers-rooms-joint-more", 1),
        Artefact("rooms/masknet.pt", ("mask_net",), "masknet-tiers-rooms-joint"),
        Artefact("unseen/detector.pt", ("detector",), "detector-unseen-bank", 1),
        Artefact("unseen/masknet.pt", ("mask_net",), "masknet-unseen-bank"),
        Artefact("paper_protocol/detector.pt", ("detector",), "detector-tune-paper", 2),
        Artefact("paper_protocol/masknet.pt", ("mask_net",), "masknet-paper-detector-masks-20k"),
        Artefact(
            "paper_protocol/masknet_faucet.pt",
            ("mask_net_experts", "faucet"),
            "masknet-paper-detector-masks-40k",
        ),
    ),
)

#: The smoke recipe's data: (distribution, split, images), rendered under the data root.
SMOKE_DATA = (
    ("paper", "train", 6),
    ("paper", "val", 2),
    ("headcam", "train", 4),
    ("headcam", "val", 2),
)
_TINY_MASKNET = MaskNetConfig(size=32, widths=(4, 8, 16))
#: The trainers' own smoke settings (``--smoke``).
_TINY_POSENET = {"batch": POSENET_SMOKE.batch, "width": POSENET_SMOKE.width}
_FEW_IMAGES = {k: getattr(DETECTOR_SMOKE, k) for k in ("batch", "val_images", "workers", "threads")}

#: Every trainer for a few steps on tiny data, each with a stage that starts from another, and
#: an artefact of each: a check of a set-up (and of the recipe's machinery) in about a minute.
SMOKE = Recipe(
    (
        _posenet("pose-scratch", {"paper": 6, "headcam": 4}, epochs=1, lr=2e-3, **_TINY_POSENET),
        _posenet(
            "pose-tune-headcam",
            {"headcam": 4},
            epochs=1,
            lr=1e-3,
            init="pose-scratch",
            **_TINY_POSENET,
        ),
        _detector("detector-scratch", {"headcam": 4}, epochs=1, lr=1e-3, **_FEW_IMAGES),
        _detector(
            "detector-tune-mixed",
            {"headcam": 2, "paper": 2},
            epochs=1,
            lr=5e-4,
            init="detector-scratch",
            **_FEW_IMAGES,
        ),
        _masknet(
            "mask-scratch",
            {"headcam": 4},
            epochs=1,
            lr=2e-3,
            val=("headcam", 2),
            batch=4,
            net=_TINY_MASKNET,
        ),
        _masknet(
            "mask-fresh-windows",
            {"headcam": 4},
            epochs=1,
            lr=1e-3,
            init="mask-scratch",
            seed=1,
            val=("headcam", 2),
            batch=4,
            net=_TINY_MASKNET,
        ),
    ),
    (
        Artefact("posenet_ours.pt", ("pose_nets", "ours"), "pose-tune-headcam"),
        Artefact("detector.pt", ("detector",), "detector-tune-mixed"),
        Artefact("tiers/masknet.pt", ("mask_net",), "mask-fresh-windows"),
    ),
)


def render_smoke_data() -> None:
    """Render `SMOKE_DATA` under the data root (what is there already is kept)."""
    for dist, split, count in SMOKE_DATA:
        size = (640, 480) if dist == "headcam" else (256, 256)
        out = data_root() / dist
        generate(GenConfig(dist, split, count, out, width=size[0], height=size[1], progress=False))


def plan(recipe: Recipe, checkpoints: Path, weights: Path | None) -> list[str]:
    """The recipe as lines: each stage with its trainer, data, start, schedule, the wall time the
    manifests under `weights` record (none without) and whether it is done; then the totals."""
    records = {} if weights is None else recorded_stages(recipe, weights)
    lines, total, done = [], 0.0, 0
    for i, s in enumerate(recipe.stages, 1):
        wall = records.get(s.name, {}).get("wall_s")
        total += wall or 0.0
        have = epochs_done(s, checkpoints)
        state = "to do" if have is None else "done" if have >= s.epochs else f"{have}/{s.epochs}"
        done += state == "done"
        data = ",".join(f"{name}={n}" for name, n in s.data)
        if detected := s.setting("detected"):
            data += f" + the detector's masks of {detected[0]} {detected[1]}+{detected[2]}"
        recorded = "   -   " if wall is None else f"{wall / 3600:5.2f} h"
        lines.append(
            f"{i:2d} {s.name:38s} {s.trainer:8s} {s.epochs:2d} ep  lr {s.lr:<7g} "
            f"{recorded}  {state:6s} {data}" + (f"  <- {s.init}" if s.init else "")
        )
    lines.append(
        f"{done}/{len(recipe.stages)} stages done; the manifests record "
        f"{total / 3600:.1f} h of training; checkpoints in {checkpoints}"
    )
    return lines


def curves(recipe: Recipe, checkpoints: Path) -> dict[str, list[list[dict]]]:
    """The validation history of every stage behind each shipped pose net, by its name in the
    manifest (`perception.training.shipping.ship.plot_curves` draws them); stages not trained yet
    are left out."""
    out = {}
    for artefact in recipe.artefacts:
        chain = recipe.chain(artefact)
        if chain[-1].trainer != "posenet":
            continue
        paths = [checkpoint_path(s, checkpoints) for s in chain]
        out[artefact.key[-1]] = [read_checkpoint(p)["history"] for p in paths if p.is_file()]
    return out


def _weights_folder(given: Path | None, smoke: bool, ship: bool) -> Path | None:
    """The weights folder of a command line: the one given, else the shipped one for the recipe
    and none for the smoke recipe (whose wall times no manifest records).

    Raises:
        InvalidArgumentError: the smoke recipe with the shipped folder, or shipping without one.
    """
    if not smoke:
        return given or WEIGHTS_DIR
    if given is not None and given.resolve() == WEIGHTS_DIR.resolve():
        raise InvalidArgumentError(f"the smoke recipe never writes or reads {WEIGHTS_DIR}")
    if ship and given is None:
        raise InvalidArgumentError("--smoke --ship needs --weights DIR, a folder of its own")
    return given


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(prog="python -m perception.training.recipe", description=__doc__)
    p.add_argument("--dry-run", action="store_true", help="print the plan and train nothing")
    p.add_argument("--only", metavar="STAGE", default=None, help="train this stage alone")
    p.add_argument(
        "--ship",
        action="store_true",
        help="after training, copy every artefact's checkpoint into the weights folder, hash it "
        "and record its manifest entry (refused unless every stage behind them is done)",
    )
    p.add_argument(
        "--smoke", action="store_true", help="the smoke recipe (renders its tiny data first)"
    )
    p.add_argument(
        "--checkpoints",
        type=arg(check_output_dir, "--checkpoints", base=Path),
        default=None,
        metavar="DIR",
        help="the stages' checkpoint folders (default: <data>/checkpoints)",
    )
    p.add_argument(
        "--weights",
        type=arg(check_output_dir, "--weights", base=Path),
        default=None,
        metavar="DIR",
        help=f"where --ship writes, and whose manifests record the stages' wall times (default "
        f"{WEIGHTS_DIR}; the smoke recipe's must be a folder of its own)",
    )
    p.add_argument(
        "--plot",
        type=arg(check_plot_path),
        default=None,
        metavar="PATH",
        help="draw the pose nets' validation over their stages here (.png, .pdf or .svg)",
    )
    args = p.parse_args(argv)
    recipe = SMOKE if args.smoke else RECIPE
    weights = _weights_folder(args.weights, args.smoke, args.ship)
    stages = recipe.stages if args.only is None else (recipe.stage(args.only),)
    checkpoints = args.checkpoints or checkpoint_dir() / ("smoke" if args.smoke else "")
    if args.dry_run:
        print("\n".join(plan(recipe, checkpoints, weights)))
        return 0
    setup_rendering()
    if args.smoke:
        render_smoke_data()
    for s in stages:
        if is_done(s, checkpoints):
            print(f"{s.name}: done ({checkpoint_path(s, checkpoints)})")
            continue
        print(f"{s.name}: training ({s.trainer}, {s.epochs} epochs)", flush=True)
        run_stage(recipe, s, checkpoints)
    if args.ship and weights is not None:  # (`_weights_folder` gives one to ship into)
        for entry in ship_all(recipe, checkpoints, weights):
            print(f"shipped {entry['file']} ({entry['bytes'] / 1e6:.1f} MB) from {entry['stage']}")
    if args.plot:
        plot_curves(curves(recipe, checkpoints), args.plot)
        print(f"wrote {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
