"""Record the golden poses: every built-in learned estimator on held-out observations.

The observations are the head camera's on two held-out episodes per scene tier (seeds from
`posegrasp.world.constants.EVAL_SEED_BASE` up, the objects varied) and two held-out images of the
paper's protocol (the test split's first two,
`perception.training.data.distributions.PaperGenerator`, seeds from the test split's base, no camera
pose). For each learned estimator (`perception.estimators.LEARNED_ESTIMATORS`) that can be made
here, each estimate is stored: its ``T_C_O`` exactly, its neighbours (class and pose) and its
``info`` without wall times.
`tests/test_golden_poses.py` recomputes them and compares to the bit, so a refactoring of an
estimator that changes no pose is shown to change none.

Files, in `--out` (default: ``tests/golden/poses`` beside this script):

- ``observations.npz``: the observations, ``<label>/rgb`` (H, W, 3) uint8, ``<label>/K`` (3, 3)
  [px], ``<label>/T_world_cam`` (4, 4), ``<label>/table_top_z`` [m] (NaN: none);
- ``poses.npz``: ``<estimator>/<label>/T_C_O`` (4, 4) [m] and ``<estimator>/<label>/n<i>`` the
  i-th neighbour's T_C_N (4, 4) [m];
- ``estimates.json``: the observations' labels, objects, seeds and sources; per estimator and
  label, whether a pose came, the neighbours' classes and the info; the estimators that could
  not be made here, with the reason; the torch threads used.

Run from the commit whose poses are golden, e.g. in a separate worktree::

    git worktree add /tmp/golden HEAD
    cd /tmp/golden && PYTHONPATH=/tmp/golden python /path/to/tests/golden/record_poses.py

The estimates are those of this machine's CPU kernels, which differ from another processor's
in the last bits: the files go to this CPU kind's set (`golden_cpu.py`), with the kind noted.
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

if str(Path(__file__).resolve().parent) not in sys.path:  # run as a script or loaded by a test
    sys.path.insert(0, str(Path(__file__).resolve().parent))
import golden_cpu as CPU

#: Where the golden files live.
GOLDEN_DIR = Path(__file__).resolve().parent / "poses"
#: Head-camera episodes per tier.
EPISODES_PER_TIER = 2
#: Paper-protocol test images.
PAPER_IMAGES = 2
#: Torch's compute threads while estimating: two, so that work shared between processes runs.
THREADS = 2
#: Info keys that hold wall times, left out of the record.
TIME_KEYS = ("timings_ms", "time_ms")


def observations() -> list[tuple[str, Any, str]]:
    """The held-out observations: (label, `Observation`, source), head camera first."""
    from perception.training.data.distributions import PaperGenerator
    from perception.training.data.render_split import SEED_BASES
    from posegrasp.core.contract import Observation
    from posegrasp.world.constants import EVAL_SEED_BASE
    from posegrasp.world.objects import OBJECT_NAMES
    from posegrasp.world.tiers import TIERS
    from sim.episodes.episode import Episode, EpisodeConfig

    out = []
    for t, tier in enumerate(TIERS):
        for k in range(EPISODES_PER_TIER):
            obj = OBJECT_NAMES[(EPISODES_PER_TIER * t + k) % len(OBJECT_NAMES)]
            seed = EVAL_SEED_BASE + k
            obs = Episode(obj, seed, EpisodeConfig(tier=tier)).observe()
            out.append((f"{tier}-{k}", obs, f"episode {tier} {obj} {seed}"))
    paper = PaperGenerator(256, 256)
    try:
        for i in range(PAPER_IMAGES):
            obj, seed = OBJECT_NAMES[i % len(OBJECT_NAMES)], SEED_BASES["test"] + i
            image = paper.render(obj, seed)
            obs = Observation(image.rgb, image.K, np.eye(4), obj, seed)
            out.append((f"paper-{i}", obs, f"paper test {obj} {seed}"))
    finally:
        paper.close()
    return out


def without_times(value: Any) -> Any:
    """`value` (an estimate's info) with every wall-time entry (`TIME_KEYS`) left out, as
    plain JSON types."""
    if isinstance(value, dict):
        return {str(k): without_times(v) for k, v in value.items() if k not in TIME_KEYS}
    if isinstance(value, list | tuple):
        return [without_times(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def canonical(value: Any) -> str:
    """The JSON text two records are compared by (keys sorted, floats as Python writes them,
    which reads back to the same float)."""
    return json.dumps(value, sort_keys=True, allow_nan=True)


def estimate_record(estimate: Any) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """An `Estimate` as (its JSON record, its arrays by key suffix)."""
    arrays = {} if estimate.T_C_O is None else {"T_C_O": np.asarray(estimate.T_C_O)}
    for i, (_, T) in enumerate(estimate.neighbours):
        arrays[f"n{i}"] = np.asarray(T)
    record = {
        "pose": estimate.T_C_O is not None,
        "neighbours": [str(name) for name, _ in estimate.neighbours],
        "info": json.loads(canonical(without_times(estimate.info))),
    }
    return record, arrays


def made_estimators() -> tuple[dict[str, Callable[[], Any]], dict[str, str]]:
    """The learned estimators' factories, and those that cannot be made here with the reason
    (the exception's type: a missing asset, such as the user objects' detector)."""
    from perception.estimators import LEARNED_ESTIMATORS
    from posegrasp.core.errors import AssetError

    made, skipped = {}, {}
    for name, factory in LEARNED_ESTIMATORS.items():
        try:
            est = factory()
        except AssetError as e:
            skipped[name] = type(e).__name__
            continue
        made[name] = lambda est=est: est
    return made, skipped


def record(out: Path) -> dict[str, Any]:
    """Make every estimate and write the golden files to `out`; returns the JSON record."""
    import torch

    from posegrasp.core.runtime import setup_rendering

    setup_rendering()
    torch.set_num_threads(THREADS)
    made, skipped = made_estimators()  # the nets load before the first render
    obs = observations()
    saved: dict[str, np.ndarray] = {}
    for label, o, _ in obs:
        saved[f"{label}/rgb"] = o.rgb
        saved[f"{label}/K"] = o.K
        saved[f"{label}/T_world_cam"] = o.T_world_cam
        top = math.nan if o.table_top_z is None else float(o.table_top_z)
        saved[f"{label}/table_top_z"] = np.array(top)
    estimates: dict[str, dict[str, Any]] = {}
    poses: dict[str, np.ndarray] = {}
    for name, get in made.items():
        est = get()
        estimates[name] = {}
        for label, o, _ in obs:
            rec, arrays = estimate_record(est.estimate(o))
            estimates[name][label] = rec
            poses.update({f"{name}/{label}/{k}": v for k, v in arrays.items()})
            print(f"{name} {label}: pose {rec['pose']}", file=sys.stderr, flush=True)
    doc = {
        "observations": [
            {"label": label, "object": o.object, "seed": int(o.seed), "source": src}
            for label, o, src in obs
        ],
        "threads": THREADS,
        "skipped": skipped,
        "estimates": estimates,
    }
    out.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out / "observations.npz", **saved)
    np.savez_compressed(out / "poses.npz", **poses)
    (out / "estimates.json").write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n")
    return doc


def main(argv: list[str] | None = None) -> int:
    """Record the golden poses (see the module docstring); returns the exit status."""
    from posegrasp.core.cli import ArgumentParser

    parser = ArgumentParser(
        prog="python tests/golden/record_poses.py", description=__doc__.splitlines()[0]
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="folder of the files (default: this CPU kind's set in the golden folder)",
    )
    args = parser.parse_args(argv)
    out = args.out or CPU.default_out(GOLDEN_DIR)
    doc = record(out)
    CPU.note_kind(out)
    n = sum(len(v) for v in doc["estimates"].values())
    print(f"{n} estimates of {len(doc['estimates'])} estimators written to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
