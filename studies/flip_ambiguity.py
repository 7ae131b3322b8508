"""How much does an end-for-end turn change the image? The paper protocol's views, re-rendered.

    python studies/flip_ambiguity.py [--split test] [--images 1000] [--below 40] [--turns 2,5]
        [--plot PATH] [--json PATH]

Each image of the paper protocol's split is rendered again from its recorded seed (the same
camera, room, clutter, lights and colours; the re-render is checked to equal the stored image),
then with the object turned by 180 deg about its own vertical axis (z), and with it turned by
each of ``--turns`` degrees about a random axis through its origin (seeded per image). For each
it prints, per object, the mean colour change over the pixels the object covers in either image
(grey levels, 0-255, mean of R, G and B) and the silhouettes' IoU, separately for the views from
within ``--below`` deg of straight below and for the others, and the share of views whose
end-for-end turn changes the image less than the smallest turn does. Where that share is high,
no estimator that reads the image can tell the pose from its turn better than chance.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from perception.metrics import mask_iou
from perception.training.data.dataset import PoseDataset
from perception.training.data.studio import Studio, StudioConfig, StudioView
from posegrasp.core.cli import ArgumentParser, add_json_argument, command, write_json
from posegrasp.core.errors import AssetError, InvalidArgumentError
from posegrasp.core.paths import data_root
from posegrasp.core.progress import progress_bar
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.transforms import axis_angle, invert_transform
from posegrasp.core.validate import (
    arg,
    check_float,
    check_float_list,
    check_int,
    check_plot_path,
)
from posegrasp.world.objects import OBJECT_NAMES

#: The end-for-end turn: 180 deg about the object's own z axis.
FLIP = np.diag([-1.0, -1.0, 1.0])


def angle_from_below(T_C_O: np.ndarray) -> float:
    """Angle [deg] between the direction from the object to the camera and the object's -z."""
    p = invert_transform(T_C_O)[:3, 3]  # the camera in O
    return float(np.degrees(np.arccos(np.clip(-p[2] / np.linalg.norm(p), -1.0, 1.0))))


def _difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per pixel, the mean over R, G and B of |a - b| [grey levels], (H, W)."""
    return np.abs(a.astype(np.int16) - b.astype(np.int16)).mean(axis=2)


def colour_change(a: StudioView, b: StudioView) -> float:
    """Mean |RGB difference| [grey levels] over the pixels either view's object covers."""
    region = a.mask | b.mask
    return float(_difference(a.rgb, b.rgb)[region].mean()) if region.any() else 0.0


def _plot(
    path: Path,
    rows: list[dict],
    example: tuple[np.ndarray, np.ndarray],
    below: float,
    key: str,
) -> None:
    """The figure: the example's two images and their difference; every view's change of the
    end-for-end turn over that of the `key` deg turn, by its angle from below."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(17, 4.2), width_ratios=[1, 1, 1, 1.8])
    a, b = example
    diff = np.clip(_difference(a, b) * 8, 0, 255)
    for ax, img, title in zip(
        axes[:3],
        (a, b, diff),
        ("a car seen from below", "turned end for end", "|difference| x 8"),
        strict=True,
    ):
        ax.imshow(img, cmap="gray" if img.ndim == 2 else None, vmin=0, vmax=255)
        ax.set_title(title)
        ax.axis("off")
    ax = axes[3]
    for name in OBJECT_NAMES:
        pts = [r for r in rows if r["object"] == name]
        if pts:
            # An image the turn leaves unchanged is drawn at the axis' floor.
            ratio = [max(r["flip"] / max(r["turns"][key], 1e-3), 0.01) for r in pts]
            ax.scatter([r["below_deg"] for r in pts], ratio, s=6, label=name)
    ax.axhline(1.0, color="k", lw=0.8)
    ax.axvline(below, color="k", lw=0.8, ls="--")
    ax.set_yscale("log")
    ax.set_xlabel("camera's angle from straight below [deg]")
    ax.set_ylabel(f"change of the end-for-end turn / of a {key} deg turn")
    ax.legend(fontsize=8, markerscale=2)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def _parser() -> ArgumentParser:
    p = ArgumentParser(
        prog="python studies/flip_ambiguity.py", description=__doc__.split("\n\n")[0]
    )
    p.add_argument("--split", default="test", help="the paper protocol's split (default test)")
    p.add_argument(
        "--images",
        type=arg(check_int, 1, 1000000, "--images", base=int),
        default=1000,
        help="the first N images of the split, 1..1000000 (default 1000)",
    )
    p.add_argument(
        "--below",
        type=arg(check_float, 0.0, 180.0, "--below", base=float),
        default=40.0,
        help="views from within this many deg of straight below count as below (default 40)",
    )
    p.add_argument(
        "--turns",
        type=arg(check_float_list, 0.1, 90.0, "--turns"),
        default=[2.0, 5.0],
        help="comma list of reference turns [deg] about a random axis (default 2,5)",
    )
    p.add_argument(
        "--plot", type=check_plot_path, help="write the figure (a car from below, every view) here"
    )
    add_json_argument(p, "the changes per view")
    return p


def _measure(
    split: str, images: int, turns: list[float], below_deg: float
) -> tuple[list[dict], tuple[np.ndarray, np.ndarray] | None]:
    """Per image of paper/`split`: the colour changes of the end-for-end turn and of each of
    `turns`; and the car view nearest to below (within `below_deg`), plain and turned."""
    ds = PoseDataset(data_root() / "paper", split)
    studio = Studio(StudioConfig(width=ds[0].rgb.shape[1], height=ds[0].rgb.shape[0]))
    rows: list[dict] = []
    example: tuple[np.ndarray, np.ndarray] | None = None  # the car view nearest to below
    best_below = float(below_deg)
    for i in progress_bar(range(min(images, len(ds))), desc="re-rendered", mininterval=5):
        s = ds[i]
        obj = s.objects[0]
        view = studio.render(obj.name, np.random.default_rng(int(s.seed)))
        if not np.array_equal(view.rgb, s.rgb):
            raise AssetError(
                f"image {i} of paper/{split} does not re-render from its seed: the data was "
                "made by another version of the generator; render it again with "
                "`python -m perception.training.datagen`"
            )
        flipped = studio.render_turned(obj.name, FLIP)
        rng = np.random.default_rng(i)
        changes = {}
        for a in turns:
            axis = rng.normal(size=3)
            R = axis_angle(axis / np.linalg.norm(axis), np.radians(a))
            changes[str(a)] = colour_change(view, studio.render_turned(obj.name, R))
        below = angle_from_below(view.T_C_O)
        rows.append(
            {
                "image": i,
                "object": obj.name,
                "below_deg": below,
                "flip": colour_change(view, flipped),
                "flip_iou": mask_iou(view.mask, flipped.mask),
                "turns": changes,
            }
        )
        if obj.name == "car" and below < best_below:
            best_below, example = below, (view.rgb, flipped.rgb)
    studio.close()
    return rows, example


def _summarise(rows: list[dict], turns: list[float], below_deg: float) -> dict[str, dict]:
    """Per object, for the views from below and the others: the medians of the changes and
    the share of end-for-end turns that change less than the smallest turn; printed."""
    key = str(turns[0])
    head = " ".join(f"{a:g} deg" for a in turns)
    print(f"{'object':8} {'views':>10}  n   end-for-end  IoU    {head}   turn < {turns[0]:g} deg")
    summary: dict[str, dict] = {}
    for name in OBJECT_NAMES:
        for part, pick in (("below", True), ("other", False)):
            sel = [r for r in rows if r["object"] == name and (r["below_deg"] < below_deg) == pick]
            if not sel:
                continue
            flip = np.array([r["flip"] for r in sel])
            ref = {a: np.median([r["turns"][str(a)] for r in sel]) for a in turns}
            less = 100.0 * float(np.mean(flip < [r["turns"][key] for r in sel]))
            iou = float(np.median([r["flip_iou"] for r in sel]))
            summary.setdefault(name, {})[part] = {
                "views": len(sel),
                "flip_median": float(np.median(flip)),
                "flip_iou_median": iou,
                "turn_medians": {str(a): float(v) for a, v in ref.items()},
                "flip_below_smallest_turn_pct": less,
            }
            refs = " ".join(f"{ref[a]:{len(f'{a:g} deg')}.1f}" for a in turns)
            print(
                f"{name:8} {part:>10} {len(sel):3d}  {np.median(flip):10.1f}  {iou:5.3f}  "
                f"{refs}   {less:5.1f} %"
            )
    return summary


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    args = _parser().parse_args(argv)
    setup_rendering(threads=1)
    turns = sorted(args.turns)
    rows, example = _measure(args.split, args.images, turns, args.below)
    print(
        f"paper/{args.split}, {len(rows)} images: mean colour change [grey levels] over the "
        f"object's pixels; below = within {args.below:g} deg of straight below"
    )
    summary = _summarise(rows, turns, args.below)
    if args.plot is not None:
        if example is None:
            raise InvalidArgumentError(
                f"--plot: no car seen from within {args.below:g} deg of below among these images"
            )
        _plot(args.plot, rows, example, args.below, str(turns[0]))
        print(f"figure: {args.plot}")
    if args.json is not None:
        write_json(
            args.json,
            {"split": args.split, "below_deg": args.below, "summary": summary, "views": rows},
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
