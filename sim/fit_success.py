"""Fit P(grasp success | pose error) per object and tier from noisy-oracle episodes.

    python -m sim.fit_success --tier isolated --episodes 100 [--task lift] [--workers N] \
        [--models docs/success_model.json]
    python -m sim.fit_success --refit                  # refit every model from its stored episodes
    python -m sim.fit_success --check run.json ...     # predicted against measured success

For every object, `--episodes` held-out noisy-oracle episodes run with the noise `SPREAD`: each
episode draws its own sigma for each component (along and across the camera ray [mm], in-plane
and out-of-plane [deg]) uniformly up to the given figure, then Gaussian errors, so the sample
covers every mix of the four components. Each episode's error components and outcome train a
`perception.success_model.SuccessModel` whose bandwidths maximise the leave-one-out likelihood.
The models of a tier replace that tier's in `--models` and keep the others. A model is of one task
(`--task`, `sim.episodes.registry.add_task_argument`): the lift's are stored as
``<object>/<tier>``, the place's as ``<object>/<tier>/place`` (`model_key`).
``perception.training.tables --success-model`` then reports the grasp success the test-split
poses should reach, without running a robot. `--refit` fits every model in `--models` again from the
episodes it stores (no episodes are run). `--check` takes reports of ``sim.evaluate --json`` and
prints, per report, the mean predicted probability of its episodes that have a pose estimate
(each from its own pose errors, with the model of its object and tier) beside their measured
success rate.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from perception.success_model import COMPONENTS, SuccessModel, components_of, load_models
from posegrasp.core.cli import ArgumentParser, add_workers_argument, command, write_json
from posegrasp.core.errors import AssetError
from posegrasp.core.paths import DOCS_DIR
from posegrasp.core.validate import arg, check_int, check_names, check_output_file
from posegrasp.world.objects import OBJECT_NAMES
from posegrasp.world.tiers import DEFAULT_TIER, TIERS, check_tier
from sim.episodes.registry import add_task_argument
from sim.evaluation import Protocol, evaluate_protocol

#: The noise of the sampled episodes (`--noise` of noisy-oracle): largest sigmas along and across
#: the ray [mm] and in and out of the image plane [deg].
SPREAD = "spread:40,40,16,16"
#: Held-out scenes of their own (see `posegrasp.world.constants.EVAL_SEED_BASE`).
SEED_START = 1_700_000_000
DEFAULT_MODELS = DOCS_DIR / "success_model.json"


def model_key(obj: str, tier: str, task: str = "lift") -> str:
    """The key of an object's model on a tier and task: ``<object>/<tier>`` for the lift (as
    every model was stored before tasks), ``<object>/<tier>/<task>`` otherwise."""
    return f"{obj}/{tier}" if task == "lift" else f"{obj}/{tier}/{task}"


def sample(
    objects: list[str], episodes: int, tier: str, workers: int, task: str = "lift"
) -> list[dict]:
    """Noisy-oracle episodes of every object on the task, each as its error components and
    outcome: [{"object", "seed", "x" (4,), "success"}]."""
    protocol = Protocol(tuple(objects), episodes, SEED_START, tier, SPREAD, task=task)
    report = evaluate_protocol(protocol, "noisy-oracle", workers=workers)
    return [
        {
            "object": e["object"],
            "seed": e["seed"],
            "x": components_of(e["pose_error"]).tolist(),
            "success": bool(e["success"]),
        }
        for e in report["episodes"]
        if e.get("pose_error") is not None
    ]


def _record(model: SuccessModel) -> dict:
    """A model as stored: its JSON, its episode count and success rate."""
    return model.to_json() | {"episodes": len(model.y), "success_rate": model.rate}


def fit(samples: list[dict], objects: list[str], tier: str, task: str = "lift") -> dict[str, dict]:
    """One model per object from its samples, by `model_key`."""
    models = {}
    for o in objects:
        mine = [s for s in samples if s["object"] == o]
        X = np.array([s["x"] for s in mine])
        y = np.array([s["success"] for s in mine], float)
        models[model_key(o, tier, task)] = _record(SuccessModel.fit(X, y))
    return models


def refit(models: dict[str, dict]) -> dict[str, dict]:
    """Every model fitted again from the episodes it stores."""
    out = {}
    for key, raw in models.items():
        m = SuccessModel.from_json(raw)
        out[key] = _record(SuccessModel.fit(m.X, m.y))
    return out


def check(models: dict[str, SuccessModel], report: dict) -> tuple[float, int, int]:
    """(mean predicted success, measured successes, episodes) over a report's episodes that have
    a pose estimate.

    Raises:
        AssetError: a report without episodes, or an object, tier or task no model covers.
    """
    episodes = [e for e in report.get("episodes", []) if e.get("pose_error") is not None]
    if not episodes:
        raise AssetError("the report lists no episode with a pose error (sim.evaluate --json)")
    p = []
    for e in episodes:
        tier = e.get("tier", report.get("tier"))
        key = model_key(e["object"], tier, report.get("task", "lift"))
        if key not in models:
            raise AssetError(f"no success model for {key}; fit it with `python -m sim.fit_success`")
        p.append(float(models[key].predict(components_of(e["pose_error"]))))
    return float(np.mean(p)), sum(bool(e["success"]) for e in episodes), len(episodes)


def _read_json(path: Path, what: str) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise AssetError(f"cannot read {what} {path} ({exc})") from None


def _parser() -> ArgumentParser:
    """The command line: the episodes, the models' file and the mode."""
    p = ArgumentParser(prog="python -m sim.fit_success", description=__doc__.split("\n")[0])
    p.add_argument(
        "--objects",
        default=list(OBJECT_NAMES),
        type=arg(check_names, OBJECT_NAMES, "object", "--objects"),
        help=f"'all' or a comma list of {', '.join(OBJECT_NAMES)}",
    )
    p.add_argument(
        "--episodes",
        type=arg(check_int, 3, 10_000, "--episodes", base=int),
        default=100,
        help="episodes per object, 3..10000",
    )
    p.add_argument(
        "--tier",
        default=DEFAULT_TIER,
        type=arg(check_tier),
        help=f"scene tier, one of: {', '.join(TIERS)}",
    )
    add_task_argument(p)
    add_workers_argument(p)
    p.add_argument(
        "--models",
        type=arg(check_output_file, "--models"),
        default=DEFAULT_MODELS,
        metavar="PATH",
        help="the success models' JSON file: read, and updated unless --check (default "
        f"{DEFAULT_MODELS.parent.name}/{DEFAULT_MODELS.name})",
    )
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--refit", action="store_true", help="refit the models from their episodes")
    mode.add_argument("--check", type=Path, nargs="+", metavar="RUN", help="sim.evaluate reports")
    return p


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    args = _parser().parse_args(argv)
    if args.check:
        loaded = load_models(args.models)
        for path in args.check:
            report = _read_json(path, "report")
            pred, k, n = check(loaded, report)
            print(
                f"{path}: {report.get('estimator')} on {report.get('tier')}: predicted "
                f"{pred:.1%}, measured {k / n:.1%} ({k}/{n} episodes with an estimate)"
            )
        return 0
    old: dict = {}
    if args.models.is_file():
        try:
            old = _read_json(args.models, "success models")["models"]
        except (KeyError, TypeError) as exc:
            raise AssetError(f"{args.models} is not a file of success models ({exc})") from None
    if args.refit:
        if not old:
            raise AssetError(f"{args.models} holds no models to refit")
        models = refit(old)
    else:
        samples = sample(args.objects, args.episodes, args.tier, args.workers, args.task)
        models = {**old, **fit(samples, args.objects, args.tier, args.task)}
    mine = {model_key(o, args.tier, args.task) for o in args.objects}
    shown = sorted(models) if args.refit else sorted(k for k in models if k in mine)
    for key in shown:
        m = models[key]
        bw = ", ".join(f"{c} {h:g}" for c, h in zip(COMPONENTS, m["bandwidth"], strict=True))
        print(
            f"{key:<18} {m['episodes']:>4} episodes, success {m['success_rate']:.1%}, "
            f"LOO log-likelihood {m['log_likelihood']:.3f}, bandwidths {bw}"
        )
    write_json(args.models, {"noise": SPREAD, "seed_start": SEED_START, "models": models})
    return 0


if __name__ == "__main__":
    sys.exit(main())
