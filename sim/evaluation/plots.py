"""Plot of grasp success against each component of the estimated pose's error, with the
tolerance curves of `sim.tolerance` beside it."""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from sim.evaluation.stats import wilson_interval

if TYPE_CHECKING:
    from collections.abc import Iterable

    from matplotlib.artist import Artist
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

#: The error components of `perception.metrics.error_components`, as the tolerance study names them
#: (``sim.tolerance``: key, unit scale from the episode's SI value, bin edges).
COMPONENTS: dict[str, tuple[str, float, tuple[float, ...]]] = {
    "ray_mm": ("ray_m", 1000.0, (0, 5, 10, 15, 20, 30, 45, 70)),
    "lateral_mm": ("lateral_m", 1000.0, (0, 5, 10, 15, 20, 30, 45, 70)),
    "inplane_deg": ("inplane_deg", 1.0, (0, 2.5, 5, 7.5, 10, 15, 20, 30, 45)),
    "outplane_deg": ("outplane_deg", 1.0, (0, 2.5, 5, 7.5, 10, 15, 20, 30, 45)),
}


def _plot_tolerance_curves(
    ax: Axes, kind: str, curves: dict[str, dict], colour: dict[str, str]
) -> None:
    """Draw on ``ax`` each object's tolerance curve of the error component ``kind``.

    Args:
        ax: The component's panel.
        kind: The component, a key of `COMPONENTS` (e.g. ``"ray_mm"``).
        curves: Per object, its `sim.tolerance` curves by component: ``levels`` (the error, in
            ``kind``'s unit) and ``success_rate`` (0 to 1), one value per level.
        colour: Per object of ``curves``, its line colour (the same in every panel).
    """
    for obj, kinds in curves.items():
        if kind in kinds:
            c = kinds[kind]
            ax.plot(
                c["levels"],
                c["success_rate"],
                lw=1.5,
                alpha=0.8,
                color=colour[obj],
                label=f"{obj}: true pose + this error alone",
            )


def _plot_binned_success(ax: Axes, x: np.ndarray, ok: np.ndarray, edges: tuple[float, ...]) -> None:
    """Draw on ``ax`` the episodes as ticks and, per bin of error, their success rate.

    The last bin runs from ``edges[-1]`` to past the largest error; its mark is drawn at most
    30 % past ``edges[-1]``, to keep the panel's scale.

    Args:
        ax: The component's panel.
        x: Shape (N,): each episode's error of the component, in its unit (mm or degrees); N > 0.
        ok: Shape (N,), bool: whether each episode's grasp succeeded.
        edges: The component's bin edges, increasing, in the same unit as ``x``.
    """
    top = max(edges[-1], float(x.max()) * 1.05)
    bins = [*edges, top]
    ax.plot(
        x,
        np.where(ok, 1.04, -0.04),
        "|",
        color="k",
        alpha=0.3,
        ms=8,
        label="one episode (top: grasped, bottom: failed)",
    )
    for lo, hi in itertools.pairwise(bins):
        sel = (x >= lo) & (x < hi) if hi < top else (x >= lo)
        n = int(sel.sum())
        if n == 0:
            continue
        k = int(ok[sel].sum())
        wlo, whi = wilson_interval(k, n)
        mid = (lo + min(hi, edges[-1] * 1.3)) / 2
        err = [[max(0.0, k / n - wlo)], [max(0.0, whi - k / n)]]
        ax.errorbar(
            mid,
            k / n,
            yerr=err,
            fmt="o",
            color="k",
            ms=4 + 6 * min(1.0, n / 50),
            capsize=3,
            label="episodes in a bin: success rate, Wilson 95 %, count beside",
        )
        ax.annotate(str(n), (mid, k / n), textcoords="offset points", xytext=(4, -12), fontsize=7)


def _add_shared_legend(fig: Figure, axes: Iterable[Axes]) -> None:
    """Add below the panels one legend naming each distinct label of ``axes`` once."""
    named: dict[str, Artist] = {}  # one entry per label, over all panels
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            named.setdefault(label, handle)
    if named:
        fig.legend(
            list(named.values()),
            list(named),
            loc="lower center",
            ncol=min(4, len(named)),
            fontsize=8,
            frameon=False,
        )


def plot_success_vs_error(report: dict, path: Path, tolerance: dict | None = None) -> None:
    """PNG of grasp success against each component of the estimated pose's error.

    One panel per component (ray, lateral, in-plane, out-of-plane): the episodes binned by that
    component's error, success rate per bin with its Wilson 95 % interval and count, each
    episode as a tick (top: success, bottom: failure), and, when given, the tolerance curves of
    `sim.tolerance` of the report's objects (success with the true pose plus that error alone,
    one line per object, one colour per object in every panel). The episodes carry all
    components at once, so a bin's rate is a marginal, not a single-factor curve. One legend
    below the panels names every line and mark.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    eps = [e for e in report["episodes"] if e.get("pose_error")]
    scored = sorted({str(e["object"]) for e in report["episodes"]})
    curves = {o: (tolerance or {})[o] for o in scored if o in (tolerance or {})}
    colour = {o: f"C{i}" for i, o in enumerate(curves)}
    fig, axes = plt.subplots(1, 4, figsize=(17, 4.2), sharey=True)
    for ax, (kind, (key, scale, edges)) in zip(axes, COMPONENTS.items(), strict=True):
        _plot_tolerance_curves(ax, kind, curves, colour)
        x = np.array([e["pose_error"][key] * scale for e in eps if key in e["pose_error"]])
        ok = np.array([bool(e["success"]) for e in eps if key in e["pose_error"]])
        if len(x):
            _plot_binned_success(ax, x, ok, edges)
        name, unit = kind.rsplit("_", 1)
        ax.set_xlabel(f"{name} error [{unit}]")
        ax.set_ylim(-0.1, 1.1)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("grasp success rate")
    fig.suptitle(
        f"{report['estimator']}: grasp success against each component of the pose error "
        f"({', '.join(scored)})"
    )
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    _add_shared_legend(fig, axes)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
