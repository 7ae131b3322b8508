"""Which stage of a learned estimator fails when the room changes?

    python studies/shift_stages.py [--estimators hybrid-global,hybrid-global-rooms]
        [--tier isolated] [--shifts factors:3,all:3] [--episodes 20] [--dev] [--json PATH]

For each shift setting (`sim.board.tracks.check_shift_settings`), the head camera's first image of
the held-out episodes the board plays (`--episodes` per object, seeds from
`posegrasp.world.constants.EVAL_SEED_BASE`; with ``--dev`` the development episodes from
``DEV_SEED_BASE``, for choosing between candidates) goes through each estimator's stages
(`perception.stages.run_stages`), and each image is put down to the first stage that failed it:

- ``detection``: no target detected, or the target's mask covers under 10 % of the true visible
  mask (another object taken for it);
- ``mask``: the (redrawn) mask's IoU with the true visible mask under 0.7;
- ``hypotheses``: none of the verified poses is right (MSSD under 10 % of the diameter);
- ``verification``: a verified pose is right, but another won;
- ``support``: the winner is right, but the neighbours' support moved it off;
- ``right``: the estimate is right.

The board's success and failure reasons come from the episodes; this tells where in the
estimator they begin. Every estimator sees the same images.
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np

from perception.metrics import mask_iou
from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.progress import progress_bar
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_choice, check_int, check_names
from posegrasp.world import constants as C
from posegrasp.world.camera import body_mask
from posegrasp.world.objects import OBJECT_NAMES
from posegrasp.world.tiers import TIERS

#: The stages an image can be put down to, in pipeline order, then the images that went right.
OUTCOMES = ("detection", "mask", "hypotheses", "verification", "support", "right")
#: A mask is another object's below this share of the true visible mask, poor below this IoU.
WRONG_OBJECT_SHARE, MASK_IOU = 0.1, 0.7
#: A pose is right within this MSSD, relative to the object's diameter (the board's measure).
RIGHT_MSSD = 0.1


def outcome(work: Any, truth: np.ndarray, errors: Any) -> str:
    """The first stage that failed one image's `Work` (after every stage ran): `truth` is the
    target's true visible mask, `errors(T_C_O)` a pose's errors (`Episode.pose_errors`)."""

    def right(T: np.ndarray) -> bool:
        return bool(errors(T)["mssd_rel_diameter"] < RIGHT_MSSD)

    target = work.target
    if target is None or (target.mask & truth).sum() < WRONG_OBJECT_SHARE * truth.sum():
        return "detection"
    final = work.placed.T_C_O if work.placed is not None else None
    if final is None and work.winner is not None:
        final = work.winner.T_C_O
    if final is not None and right(final):
        return "right"
    if mask_iou(target.mask, truth) < MASK_IOU:
        return "mask"
    if not any(right(v.T_C_O) for v in work.ranked):
        return "hypotheses"
    if work.winner is not None and right(work.winner.T_C_O):
        return "support"
    return "verification"


def _count(
    estimators: dict[str, Any], tier: str, setting: str, seeds: tuple[int, int], bar: Any
) -> dict[str, dict[str, int]]:
    """Each estimator's images per outcome under one shift setting: the first images of
    `seeds` (episodes per object, first seed), one scene at a time, each estimator on the same
    image."""
    from perception.stages import Work, run_stages
    from sim.board.tracks import shifts_of
    from sim.episodes.episode import Episode
    from sim.evaluation import Protocol

    shifts = shifts_of(setting)
    protocol = Protocol(OBJECT_NAMES, *seeds, tier, shifts=shifts)
    counts = {name: dict.fromkeys(OUTCOMES, 0) for name in estimators}
    for name, seed in protocol.seeds():
        ep = Episode(name, seed, protocol.episode_config())
        try:
            seg = ep.renderer.segmentation(ep.scene.data, C.HEAD_CAMERA)
            truth = body_mask(ep.scene.model, seg, ep.scene.target.body)
            obs = ep.observe()
            for est_name, est in estimators.items():
                work = run_stages(est.stages, Work.of(obs), {})
                counts[est_name][outcome(work, truth, ep.pose_errors)] += 1
        finally:
            ep.close()
        bar.update(1)
    return counts


def _parser() -> ArgumentParser:
    from perception.estimators import LEARNED_ESTIMATORS

    global_ones = [n for n in LEARNED_ESTIMATORS if n.startswith("hybrid-global")]
    p = ArgumentParser(prog="python studies/shift_stages.py", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--estimators",
        default="hybrid-global,hybrid-global-rooms",
        type=arg(check_names, global_ones, "estimator", "--estimators"),
        help=f"comma list of: {', '.join(global_ones)} (default hybrid-global,hybrid-global-rooms)",
    )
    p.add_argument(
        "--tier",
        default="isolated",
        type=arg(check_choice, list(TIERS), "tier"),
        help=f"one of: {', '.join(TIERS)} (default isolated)",
    )
    p.add_argument(
        "--shifts",
        default="factors:3,all:3",
        help="shift settings, as the board's --shifts (default factors:3,all:3)",
    )
    p.add_argument(
        "--episodes",
        default=20,
        type=arg(check_int, 1, 1000, "--episodes", base=int),
        help="episodes per object, 1..1000 (default 20)",
    )
    p.add_argument(
        "--dev",
        action="store_true",
        help="the development episodes (seeds from DEV_SEED_BASE), for choosing between "
        "candidates, instead of the held-out ones the board scores",
    )
    add_json_argument(p, "the images per outcome, per estimator and shift setting")
    return p


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    from perception.estimators import LEARNED_ESTIMATORS
    from sim.board.tracks import check_shift_settings

    args = _parser().parse_args(argv)
    settings = check_shift_settings(args.shifts)
    setup_rendering(threads=2)
    estimators = {name: LEARNED_ESTIMATORS[name]() for name in args.estimators}
    log = summary_stream(args.json)
    rows: dict[str, dict[str, dict[str, int]]] = {}
    bar = progress_bar(total=len(settings) * args.episodes * len(OBJECT_NAMES), desc="images")
    for setting in settings:
        seeds = (args.episodes, C.DEV_SEED_BASE if args.dev else C.EVAL_SEED_BASE)
        rows[setting] = _count(estimators, args.tier, setting, seeds, bar)
    bar.close()
    print(f"{'shift':<18} {'estimator':<22} " + " ".join(f"{o:>12}" for o in OUTCOMES), file=log)
    for setting, per in rows.items():
        for name, c in per.items():
            print(
                f"{setting:<18} {name:<22} " + " ".join(f"{c[o]:>12}" for o in OUTCOMES), file=log
            )
    if args.json is not None:
        write_json(
            args.json, {"tier": args.tier, "episodes_per_object": args.episodes, "rows": rows}
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
