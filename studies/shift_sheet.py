"""What does each scene shift do to the head image? One scene under every factor, mild and strong.

    python studies/shift_sheet.py [--object phone] [--seed 0] [--tier isolated]
        [--plot docs/shifts.png] [--json PATH]

The scene of ``--object`` and ``--seed`` (in tier ``--tier``) is built without shifts, under each
factor of `posegrasp.world.shifts.FACTORS` at level 1 (mild) and level 3 (strong), and under
``all:3``, and its head image is rendered as an episode observes it (640x480, no shadows). For
each shift it prints the share of the image's pixels that changed, their mean colour change
(grey levels, 0-255, mean of R, G and B), and whether the settled scene's state (joint positions
and velocities, every body's pose) is the unshifted one to the bit, as a shift promises. ``--plot``
draws the sheet: the unshifted image and ``all:3`` first, then each factor at levels 1 and 3.
The exit status is 1 when a shift changed the state.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import arg, check_plot_path, check_seed
from posegrasp.world import constants as C
from posegrasp.world.camera import CameraRenderer, RenderOptions
from posegrasp.world.objects import check_object
from posegrasp.world.scene import Scene, build_scene
from posegrasp.world.shifts import FACTORS, parse_shifts
from posegrasp.world.tiers import DEFAULT_TIER, check_tier, tier_scene

#: The shifts on the sheet, in its order: all factors at once, then each at levels 1 and 3.
SHEET = ("all:3", *(f"{f}:{level}" for f in FACTORS for level in (1, 3)))
#: Images per row of the sheet.
COLUMNS = 6


def head_image(scene: Scene) -> np.ndarray:
    """The head camera's 640x480 image as an episode renders it (no shadows), (H, W, 3) uint8."""
    with CameraRenderer(scene.model, 640, 480, RenderOptions(shadows=False)) as renderer:
        return renderer.rgb(scene.data, C.HEAD_CAMERA)


def same_state(a: Scene, b: Scene) -> bool:
    """Whether b's joint positions, velocities and body poses are a's to the bit (b may hold
    one more body, the distractors', after a's)."""
    n = a.model.nbody
    return bool(
        np.array_equal(a.data.qpos, b.data.qpos)
        and np.array_equal(a.data.qvel, b.data.qvel)
        and np.array_equal(a.data.xpos, b.data.xpos[:n])
        and np.array_equal(a.data.xquat, b.data.xquat[:n])
    )


def change(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """Share of pixels that differ, and the mean |RGB difference| over them [grey levels]."""
    diff = np.abs(a.astype(np.int16) - b.astype(np.int16)).mean(axis=2)
    changed = diff > 0
    return {
        "changed_share": round(float(changed.mean()), 4),
        "mean_change": round(float(diff[changed].mean()) if changed.any() else 0.0, 2),
    }


def plot(path: Path, images: dict[str, np.ndarray], title: str) -> None:
    """The sheet: every image with its shift above it, `COLUMNS` to a row."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = -(-len(images) // COLUMNS)
    height = 2.75 * rows + 0.45
    fig, axes = plt.subplots(rows, COLUMNS, figsize=(3.2 * COLUMNS, height), squeeze=False)
    for ax, (name, image) in zip(axes.ravel(), images.items(), strict=False):
        ax.imshow(image[::2, ::2])
        ax.set_title(name, fontsize=11, pad=3)
    for ax in axes.ravel():
        ax.set_axis_off()
    fig.suptitle(title, fontsize=12, y=1 - 0.12 / height)
    fig.subplots_adjust(
        left=0.004, right=0.996, bottom=0.004, top=1 - 0.45 / height, wspace=0.03, hspace=0.14
    )
    fig.savefig(path, dpi=100)
    plt.close(fig)


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status (1 when a shift changed the scene's state)."""
    p = ArgumentParser(prog="python studies/shift_sheet.py", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--object", type=arg(check_object), default="phone", help="the target (default: phone)"
    )
    p.add_argument(
        "--seed",
        type=arg(check_seed, "--seed", base=int),
        default=0,
        help="scene seed in 0..2**32-1 (default: 0)",
    )
    p.add_argument(
        "--tier",
        type=arg(check_tier),
        default=DEFAULT_TIER,
        help=f"the scene's tier (default: {DEFAULT_TIER})",
    )
    p.add_argument(
        "--plot",
        type=arg(check_plot_path, "--plot"),
        default=None,
        metavar="PATH",
        help="the sheet of images (.png, .pdf or .svg)",
    )
    add_json_argument(p, "each shift's change of the image and whether the state is unchanged")
    args = p.parse_args(argv)
    setup_rendering(threads=2)
    log = summary_stream(args.json)
    base_cfg = tier_scene(args.tier)
    base = build_scene(args.object, args.seed, base_cfg)
    base_image = head_image(base)
    images = {"no shift": base_image}
    rows: list[dict[str, Any]] = []
    print(
        f"{args.object}, seed {args.seed}, {args.tier}: shift, pixels changed, mean change, state",
        file=log,
    )
    for spec in SHEET:
        scene = build_scene(args.object, args.seed, replace(base_cfg, shifts=parse_shifts(spec)))
        images[spec] = head_image(scene)
        row = {
            "shift": spec,
            **change(base_image, images[spec]),
            "same_state": same_state(base, scene),
        }
        rows.append(row)
        state = "same" if row["same_state"] else "CHANGED"
        print(f"{spec:18s} {row['changed_share']:7.1%} {row['mean_change']:6.1f} {state}", file=log)
    if args.plot is not None:
        plot(args.plot, images, f"scene shifts: {args.object}, seed {args.seed}, {args.tier} tier")
        print(f"wrote {args.plot}", file=log)
    if args.json is not None:
        write_json(
            args.json, {"object": args.object, "seed": args.seed, "tier": args.tier, "shifts": rows}
        )
    return 0 if all(r["same_state"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
