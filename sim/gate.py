"""The grasp-success regression gate: fixed hard scenes, compared seed by seed with a baseline.

    python -m sim.gate             # run the gate's episodes and compare (exit 1 on a regression)
    python -m sim.gate --write     # run them and write the baseline (commit it with the weights)
    python -m sim.gate --estimator hybrid          # one estimator only
    python -m sim.gate --estimator E --obs-mode rgbd   # an estimator that reads depth
    python -m sim.gate --write --task place --baseline out/gate_place.json   # a place gate
    python -m sim.gate --workers 2 [--backend ray [--address ADDR]] [--baseline PATH]

The default estimator (`GATE_ESTIMATORS`) runs `GATE_EPISODES` held-out episodes per object of
the `GATE_TIER` tier (seeds from `GATE_SEED_START`), measuring each grasp's friction margin, and
the run is paired episode by episode with the baseline in `BASELINE` (``sim/gate_baseline.json``):

- success: the gate fails when the exact one-sided McNemar test of a loss on the discordant
  pairs (episodes the baseline grasped and the run did not, and the reverse) gives p < `ALPHA`
  (with none gained, 5 lost fail and 4 pass);
- margin: on the episodes both grasped, the gate fails when the mean friction margin rose (a
  looser grasp) by more than `MARGIN_RISE` and the paired bootstrap 95 % interval of the rise
  lies above zero.

Unchanged code and weights reproduce every episode on one machine: no discordant pair and no
margin change, so the gate cannot fail them. Across machines, floating-point differences can
flip a borderline episode either way; a few such flips are not significant. The `hard` tier is
used because there pose errors cost grasps (on isolated scenes every estimator within a few
millimetres grasps everything, so no regression short of a collapse shows).
`studies/gate_power.py` measures how often the rule catches a regression from noisy-oracle at
(5 mm, 2 deg) to (10 mm, 4 deg).

The gate fails closed: a missing, empty or malformed baseline, or one recorded for another tier,
other seeds, other execution settings, another observation mode (``--obs-mode``) or other
weights, is an error that says how to rewrite it; a baseline of another protocol or other weights
is refused before any episode runs.

A baseline holds one record per estimator, of one task (``--task lift|place``) under one set of
scene shifts (``--shift``, none by default): a run of another task or other shifts is refused
before any episode runs, with the command that records a baseline of its own for it. Such a
baseline goes in a file of its own (``--write --task place --baseline PATH``, then
``--task place --baseline PATH``): ``--write`` of a place task or of shifts into the shipped
`BASELINE`, which holds the lift baselines, is refused.

The weights fingerprint holds the SHA-256 of every weights file the estimator loads, as its
factory opens them (`sim.episodes.registry.estimator_weights`): retraining any net the estimator
uses (detector, pose nets, mask net) refuses the baseline. A plug-in reports its files with a
``weights_files()`` method; one without it gets an empty fingerprint, and the gate says so.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from posegrasp.core.backends import add_backend_arguments, check_backend
from posegrasp.core.cli import ArgumentParser, add_workers_argument, command, write_json
from posegrasp.core.errors import AssetError, InvalidArgumentError, PosegraspError
from posegrasp.core.journal import journal_path, resumable
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import check_output_file
from posegrasp.world.objects import OBJECT_NAMES
from posegrasp.world.shifts import Shift
from sim.episodes.episode import execution_settings
from sim.episodes.registry import (
    DEFAULT_ESTIMATOR,
    add_estimator_arguments,
    add_obs_mode_argument,
    add_sensor_argument,
    add_shift_argument,
    add_task_argument,
    check_depth,
    estimator_fingerprint,
)
from sim.evaluation import Protocol, evaluate_protocol, format_report, run_protocol
from sim.evaluation.report_schema import validate_report
from sim.evaluation.stats import BOOTSTRAP, bootstrap_means, mcnemar_exact

BASELINE = Path(__file__).resolve().parent / "gate_baseline.json"
GATE_EPISODES = 40
GATE_TIER = "hard"
#: Held-out scenes (see `posegrasp.world.constants.EVAL_SEED_BASE`), apart from the default
#: evaluation's.
GATE_SEED_START = 1_500_000_000
GATE_ESTIMATORS = (DEFAULT_ESTIMATOR,)
#: Significance level of the paired success test.
ALPHA = 0.05
#: Smallest rise of the mean friction margin that counts as a regression.
MARGIN_RISE = 0.02
#: Bootstrap resamples of the margin rise.
#: What a baseline record must hold.
RECORD_KEYS = (
    "estimator",
    "tier",
    "seed_start",
    "episodes_per_object",
    "execution",
    "obs_mode",
    "weights",
    "episodes",
)
#: The settings a run must share with its baseline, and how a message names each.
PROTOCOL = {
    "estimator": "estimator",
    "tier": "tier",
    "seed_start": "first seed",
    "episodes_per_object": "episodes per object",
    "execution": "execution settings",
    "obs_mode": "observation mode (--obs-mode)",
    "sensor": "sensor model (--sensor; recorded when not ideal)",
    "task": "task (--task; recorded when not lift)",
    "shifts": "scene shifts (--shift; recorded when any)",
    "belief": "place belief (recorded on the place task)",
}
#: The settings of `PROTOCOL` a baseline is recorded for apart (`mismatch` says how to record
#: one), with the value a record without them has.
RECORDED_FOR = {"task": "lift", "shifts": None}


def _rewrite_hint(path: Path) -> str:
    return f"rewrite {path} with `python -m sim.gate --write`"


def load_baselines(path: Path = BASELINE) -> dict[str, dict]:
    """Baseline records by estimator.

    Raises:
        AssetError: no file, not JSON, no record, or a record without its episodes.
    """
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise AssetError(
            f"cannot read the gate baseline {path} ({exc}); {_rewrite_hint(path)}"
        ) from None
    if not isinstance(data, dict) or not data:
        raise AssetError(f"the gate baseline {path} holds no record; {_rewrite_hint(path)}")
    for name, rec in data.items():
        missing = [k for k in RECORD_KEYS if not isinstance(rec, dict) or k not in rec]
        if missing or not rec["episodes"]:
            raise AssetError(
                f"the baseline of {name} in {path} lacks {', '.join(missing) or 'episodes'}; "
                f"{_rewrite_hint(path)}"
            )
    return data


def gate_protocol(
    estimator: str,
    obs_mode: str = "rgb",
    sensor: str = "ideal",
    task: str = "lift",
    shifts: tuple[Shift, ...] = (),
) -> dict:
    """The settings of a gate run of `estimator` (`PROTOCOL`'s keys), known before it runs; the
    sensor, task and shifts only away from their defaults, as reports record them
    (`sim.evaluation.Protocol.recorded_apart`)."""
    apart = gate_run_protocol(GATE_EPISODES, obs_mode, sensor, task, shifts).recorded_apart()
    return {
        **{k: v for k, v in apart.items() if k in PROTOCOL},
        "estimator": estimator,
        "tier": GATE_TIER,
        "seed_start": GATE_SEED_START,
        "episodes_per_object": GATE_EPISODES,
        "execution": execution_settings(),
        "obs_mode": obs_mode,
    }


def _recorded_for(settings: dict) -> str:
    """The task and scene shifts a run or baseline is of, in words."""
    shifts = settings.get("shifts")
    under = f"scene shifts {','.join(shifts)}" if shifts else "no scene shift"
    return f"the {settings.get('task', 'lift')} task under {under}"


def _record_command(run: dict) -> str:
    """The command that records a baseline of the settings of `run` in a file of its own."""
    flags = [f"--estimator {run.get('estimator')}"]
    if run.get("obs_mode", "rgb") != "rgb":
        flags.append(f"--obs-mode {run['obs_mode']}")
    if "sensor" in run:
        flags.append(f"--sensor {run['sensor']}")
    flags += _track_flags(run.get("task", "lift"), run.get("shifts") or [])
    return f"python -m sim.gate --write {' '.join(flags)} --baseline PATH"


def _track_flags(task: str, shifts: Sequence[object]) -> list[str]:
    """The ``--task`` and ``--shift`` flags of a run away from the lift task without shifts."""
    return ([f"--task {task}"] if task != "lift" else []) + (
        [f"--shift {','.join(map(str, shifts))}"] if shifts else []
    )


def mismatch(run: dict, baseline: dict, weights: dict[str, str]) -> str | None:
    """Why a run of the settings in `run` (`PROTOCOL`'s keys) and weights `weights` cannot be
    paired with `baseline`, as a FAIL verdict naming the first difference; None when it can. A
    baseline of another task or other scene shifts (`RECORDED_FOR`) is not rewritten but
    recorded apart: the verdict gives the command that records one for the run."""
    if any(run.get(k, d) != baseline.get(k, d) for k, d in RECORDED_FOR.items()):
        return (
            f"FAIL: the baseline of {run.get('estimator')} was recorded for "
            f"{_recorded_for(baseline)}, not {_recorded_for(run)}; record one for this run in a "
            f"file of its own with `{_record_command(run)}` and compare with --baseline PATH"
        )
    for key, what in PROTOCOL.items():
        if run.get(key) != baseline.get(key):
            return (
                f"FAIL: the run's {what} ({run.get(key)!r}) is not the baseline's "
                f"({baseline.get(key)!r}); rewrite it with `python -m sim.gate --write`"
            )
    base = baseline["weights"]
    if base != weights:
        diff = sorted(k for k in base.keys() | weights.keys() if base.get(k) != weights.get(k))
        files = ", ".join(
            f"{k} {weights.get(k, 'not loaded')} against {base.get(k, 'not recorded')}"
            for k in diff
        )
        return (
            f"FAIL: the baseline was recorded with other weights ({files}); after retraining, "
            "rewrite it with `python -m sim.gate --write`"
        )
    return None


def run_gate(
    estimator: str = DEFAULT_ESTIMATOR,
    episodes: int = GATE_EPISODES,
    workers: int = 2,
    backend: str = "local",
    address: str | None = None,
    obs_mode: str = "rgb",
    sensor: str = "ideal",
    journal: Path | None = None,
    resume: bool = False,
    task: str = "lift",
    shifts: tuple[Shift, ...] = (),
) -> dict:
    """The gate's evaluation: `episodes` per object of `GATE_TIER` from `GATE_SEED_START`,
    friction margins measured, the estimator seeing `obs_mode` through `sensor` under the scene
    `shifts`, the robot doing `task`, on `backend` (`posegrasp.core.backends.run_map`), its
    finished episodes kept in `journal` (resumed with `resume`;
    `sim.evaluation.evaluate_protocol`)."""
    return evaluate_protocol(
        gate_run_protocol(episodes, obs_mode, sensor, task, shifts),
        estimator,
        workers=workers,
        backend=backend,
        address=address,
        journal=journal,
        resume=resume,
    )


def gate_run_protocol(
    episodes: int = GATE_EPISODES,
    obs_mode: str = "rgb",
    sensor: str = "ideal",
    task: str = "lift",
    shifts: tuple[Shift, ...] = (),
) -> Protocol:
    """The episodes of a gate run (`sim.evaluation.Protocol`)."""
    return Protocol(
        objects=tuple(OBJECT_NAMES),
        episodes=episodes,
        seed_start=GATE_SEED_START,
        tier=GATE_TIER,
        margin=True,
        obs_mode=obs_mode,
        sensor=sensor,
        task=task,
        shifts=shifts,
    )


def gate_journal(
    estimator: str,
    obs_mode: str = "rgb",
    sensor: str = "ideal",
    task: str = "lift",
    shifts: tuple[Shift, ...] = (),
) -> Path:
    """Where a gate run of `estimator` keeps its finished episodes until the gate's verdict or
    baseline is written: the data folder's runs/ (`posegrasp.core.journal.journal_path`)."""
    protocol = gate_run_protocol(GATE_EPISODES, obs_mode, sensor, task, shifts)
    return journal_path(None, "gate", run_protocol(protocol, estimator))


def _outcomes(episodes: list[dict]) -> dict[tuple[str, int], tuple[bool, float | None]]:
    return {
        (str(e["object"]), int(e["seed"])): (bool(e["success"]), e.get("friction_margin"))
        for e in episodes
    }


def compare(
    report: dict, baseline: dict, weights: dict[str, str] | None = None
) -> tuple[bool, str]:
    """(passed, verdict) of an evaluation against a baseline, paired by (object, seed).

    `weights` is the fingerprint of the weights the run used (`estimator_fingerprint` of the
    report's estimator when None); a baseline of other settings (`PROTOCOL`) or other weights
    fails (`mismatch`).
    """
    if weights is None:
        weights = estimator_fingerprint(report["estimator"])[0]
    if (why := mismatch(report, baseline, weights)) is not None:
        return False, why
    run, base = _outcomes(report["episodes"]), _outcomes(baseline["episodes"])
    if set(run) != set(base):
        return False, "FAIL: the run's episodes are not the baseline's; rewrite the baseline"
    keys = sorted(base)
    lost = sum(base[k][0] and not run[k][0] for k in keys)
    won = sum(run[k][0] and not base[k][0] for k in keys)
    p = mcnemar_exact(lost, won, one_sided=True)
    k_run, k_base = sum(run[k][0] for k in keys), sum(base[k][0] for k in keys)
    success_bad = p < ALPHA
    margins = [
        (r, b)
        for k in keys
        if run[k][0] and base[k][0]
        for r, b in [(run[k][1], base[k][1])]
        if r is not None and b is not None
    ]
    rise, lo = 0.0, 0.0
    if margins:
        d = np.array([r - b for r, b in margins])
        rise = float(d.mean())
        boot = bootstrap_means(d, BOOTSTRAP, np.random.default_rng(0))
        lo = float(np.percentile(boot, 2.5))
    margin_bad = rise > MARGIN_RISE and lo > 0.0
    ok = not (success_bad or margin_bad)
    verdict = (
        f"{'PASS' if ok else 'FAIL'}: {k_run}/{len(keys)} grasped against the baseline's "
        f"{k_base}/{len(keys)}; {lost} lost and {won} gained, one-sided McNemar p = {p:.3g} "
        f"(fails below {ALPHA}); friction margin "
        f"{rise:+.3f} on {len(margins)} grasped by both (fails above +{MARGIN_RISE} when the "
        f"bootstrap interval's low end {lo:+.3f} is above 0)"
    )
    return ok, verdict


def baseline_of(report: dict, weights: dict[str, str] | None = None) -> dict:
    """The baseline record of an evaluation: its protocol, the fingerprint `weights` of the
    weights it used (`estimator_fingerprint` of its estimator when None) and every episode's
    outcome."""
    if weights is None:
        weights = estimator_fingerprint(report["estimator"])[0]
    return {
        **{k: report[k] for k in PROTOCOL if k in report},
        "successes": report["overall"]["successes"],
        "weights": weights,
        "episodes": [
            {
                "object": e["object"],
                "seed": e["seed"],
                "success": e["success"],
                "failure_reason": e["failure_reason"],
                "friction_margin": e.get("friction_margin"),
            }
            for e in report["episodes"]
        ],
    }


def _gate_one(name: str, args, baselines: dict, journal: Path) -> bool:
    """Run the gate's episodes of one estimator (its finished ones kept in `journal`) and
    compare them with its baseline, or (``--write``) put its baseline in `baselines`; prints the
    fingerprint, the report and the verdict. Returns whether it passed (a baseline of another
    protocol or other weights fails before any episode runs)."""
    weights, note = estimator_fingerprint(name)
    if note is None:
        note = f"weights fingerprint of {', '.join(weights) or 'no file (it loads none)'}"
    print(f"{name}: {note}")
    if not args.write:
        run = gate_protocol(name, args.obs_mode, args.sensor, args.task, args.shift)
        why = mismatch(run, baselines[name], weights)
        if why is not None:
            print(f"{name}: {why}")
            return False
    with resumable(journal, gate_run_protocol(GATE_EPISODES).total):
        report = validate_report(
            run_gate(
                name,
                GATE_EPISODES,
                args.workers,
                args.backend,
                args.address,
                args.obs_mode,
                args.sensor,
                journal,
                args.resume and journal.is_file(),
                args.task,
                args.shift,
            ),
            f"the gate's run of {name}",
        )
    print(format_report(report))
    if args.write:
        baselines[name] = baseline_of(report, weights)
        return True
    ok, verdict = compare(report, baselines[name], weights)
    print(f"{name}: {verdict}")
    return ok


def _parser() -> ArgumentParser:
    """The command line of `main`."""
    p = ArgumentParser(prog="python -m sim.gate", description=__doc__.split("\n")[0])
    p.add_argument("--write", action="store_true", help="write the baseline instead of comparing")
    p.add_argument(
        "--baseline",
        type=Path,
        default=BASELINE,
        metavar="PATH",
        help="the baseline file, compared with or (--write) written (default "
        f"{BASELINE.parent.name}/{BASELINE.name})",
    )
    add_workers_argument(p)
    add_estimator_arguments(p, default=None, noise=False, purpose="only this one")
    add_obs_mode_argument(p)
    add_sensor_argument(p)
    add_task_argument(p)
    add_shift_argument(p)
    add_backend_arguments(p)
    p.add_argument(
        "--resume",
        action="store_true",
        help="finish an interrupted gate of the same arguments from its journals (one per "
        "estimator, under the data folder's runs/)",
    )
    return p


def check_write(path: Path, task: str, shifts: tuple[Shift, ...]) -> None:
    """Refuse to write a baseline of the place task or of scene shifts into the shipped
    `BASELINE`, which holds the lift baselines without shifts that CI compares with.

    Raises:
        InvalidArgumentError: in one line, naming ``--baseline PATH``.
    """
    flags = _track_flags(task, shifts)
    if flags and Path(path).resolve() == BASELINE:
        raise InvalidArgumentError(
            f"{BASELINE.parent.name}/{BASELINE.name} holds the lift baselines without scene "
            f"shifts; write the baseline of {' '.join(flags)} to a file of its own with "
            "--baseline PATH"
        )


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status (1 when the gate fails)."""
    args = _parser().parse_args(argv)
    if args.estimator:
        check_depth(args.estimator, args.obs_mode)
    setup_rendering()
    check_backend(args.backend, args.address)
    if args.write:
        check_write(args.baseline, args.task, args.shift)
        check_output_file(args.baseline, "--baseline")
        baselines = {}
        if args.estimator and args.baseline.is_file():  # one estimator keeps the others
            try:
                baselines = load_baselines(args.baseline)
            except PosegraspError:
                pass  # --write replaces an unreadable baseline
        names = [args.estimator] if args.estimator else list(GATE_ESTIMATORS)
    else:
        baselines = load_baselines(args.baseline)
        names = [args.estimator] if args.estimator else list(baselines)
        if missing := [n for n in names if n not in baselines]:
            raise AssetError(
                f"no baseline for {', '.join(missing)} in {args.baseline}; it has: "
                f"{', '.join(baselines)}; write one with `python -m sim.gate --write --estimator E`"
            )
    failed = False
    journals = [
        gate_journal(name, args.obs_mode, args.sensor, args.task, args.shift) for name in names
    ]
    for name, journal in zip(names, journals, strict=True):
        failed |= not _gate_one(name, args, baselines, journal)
    if args.write:
        write_json(args.baseline, baselines)
    for journal in journals:  # the verdicts are given, the baseline written: nothing to resume
        journal.unlink(missing_ok=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
