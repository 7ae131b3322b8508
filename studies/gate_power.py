"""How often the gate catches a known regression, and how often it cries wolf.

    python studies/gate_power.py [--runs 20] [--workers N] [--json PATH]

The gate's protocol (`sim.gate`: `GATE_TIER` scenes from `GATE_SEED_START`, `GATE_EPISODES` per
object, friction margins measured) is run once with ``noisy-oracle`` at sigma (5 mm, 2 deg) on
all four error components; that report is the baseline. Each of `--runs` runs then draws its
own, independent errors (`sim.episodes.pose_noise.PoseNoise.draw` 1, 2, ...) at (10 mm, 4 deg) and
is compared with the baseline by the gate's rule (`sim.gate.compare`). Printed: the number of runs
flagged (target: at least 19 of 20), each run's verdict, and a rerun of the baseline's own
errors, which must pass. With `--false-alarm-runs N`, N runs at (5 mm, 2 deg) with other draws
are compared too: how often the gate flags a change of errors that is no regression.
`--first-draw K` starts the regressed runs at draw K (to add runs to an earlier batch). With
`--no-margin` the friction margins are not measured (half the time), so only the success rule
can flag: the figure is then a lower bound on the gate's. With `--json PATH`, the baseline and
every verdict are saved after each run, and running again with the same file resumes where it
stopped (``--json -`` prints them once at the end, and resumes nothing).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import TextIO

from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    add_workers_argument,
    command,
    summary_stream,
    target,
    write_json,
)
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.files import atomic_write_json
from posegrasp.core.runtime import setup_rendering
from posegrasp.core.validate import STDOUT, arg, check_int
from posegrasp.world.objects import OBJECT_NAMES
from sim import gate
from sim.evaluation import Protocol, evaluate_protocol

BASE_NOISE = "5,5,2,2"
WORSE_NOISE = "10,10,4,4"
FINGERPRINT = {"noisy-oracle": "no weights"}


def _run(noise: str, workers: int, margin: bool = True) -> dict:
    protocol = Protocol(
        OBJECT_NAMES, gate.GATE_EPISODES, gate.GATE_SEED_START, gate.GATE_TIER, noise, margin
    )
    return evaluate_protocol(protocol, "noisy-oracle", workers=workers)


def _baseline(report: dict) -> dict:
    record = gate.baseline_of(report)
    record["weights"] = FINGERPRINT
    return record


def _protocol(margin: bool) -> dict:
    return {
        "tier": gate.GATE_TIER,
        "seed_start": gate.GATE_SEED_START,
        "episodes_per_object": gate.GATE_EPISODES,
        "objects": list(OBJECT_NAMES),
        "base_noise": BASE_NOISE,
        "worse_noise": WORSE_NOISE,
        "margin": margin,
    }


def _resume(path: Path | None, protocol: dict) -> dict:
    """The state saved by an earlier, interrupted run of the same protocol (else a fresh one).

    Raises:
        InvalidArgumentError: the file is unreadable or holds another protocol.
    """
    if path is not None and path.is_file():
        try:
            state = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise InvalidArgumentError(f"cannot resume from {path}: {e}") from None
        if state.get("protocol") == protocol and "baseline" in state:
            print(f"resuming from {path}: {len(state['regressed'])} regressed run(s) done")
            return state
        raise InvalidArgumentError(f"{path} holds another protocol; pass another --json")
    return {"protocol": protocol, "regressed": [], "redrawn": [], "rerun": [True, "not run"]}


def _parser() -> ArgumentParser:
    p = ArgumentParser(prog="python studies/gate_power.py", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--runs",
        type=arg(check_int, 1, 1000, "--runs", base=int),
        default=20,
        help="regressed runs, each its own draw, 1..1000 (default 20)",
    )
    alarms = arg(check_int, 0, 1000, "--false-alarm-runs", base=int)
    p.add_argument(
        "--false-alarm-runs",
        type=alarms,
        default=0,
        help="unregressed redraws, 0..1000 (default 0)",
    )
    add_workers_argument(p)
    p.add_argument("--no-margin", action="store_true", help="success rule only (faster)")
    p.add_argument(
        "--first-draw",
        type=arg(check_int, 1, 100_000, "--first-draw", base=int),
        default=1,
        help="draw of the first regressed run, 1..100000",
    )
    p.add_argument("--no-rerun", action="store_true", help="skip the rerun of the baseline")
    add_json_argument(p, "the baseline and every verdict, after each run (a file resumes)")
    return p


def _collect(
    state: dict, args: argparse.Namespace, margin: bool, record: Path | None, log: TextIO
) -> None:
    """Run what `state` lacks: the baseline, its rerun, the regressed and the redrawn runs;
    `state` is saved to `record` after each, and each verdict printed to `log`."""

    def save() -> None:
        if record is not None:
            atomic_write_json(record, state)

    if "baseline" not in state:
        state["baseline"] = _baseline(_run(BASE_NOISE, args.workers, margin))
        save()
    baseline = state["baseline"]
    if not args.no_rerun and state["rerun"][1] == "not run":
        ok, text = gate.compare(_run(BASE_NOISE, args.workers, margin), baseline, FINGERPRINT)
        state["rerun"] = [ok, text]
        save()
    if not args.no_rerun:
        print(f"rerun of the baseline: {state['rerun'][1]}", file=log)
    for kind, noise, draws in (
        ("regressed", WORSE_NOISE, range(args.first_draw, args.first_draw + args.runs)),
        ("redrawn", BASE_NOISE, range(1, args.false_alarm_runs + 1)),
    ):
        done = {v[2]: v for v in state[kind] if len(v) == 3}
        for r in draws:
            if r not in done:
                report = _run(f"{noise}@{r}", args.workers, margin)
                done[r] = [*gate.compare(report, baseline, FINGERPRINT), r]
                state[kind] = sorted(done.values(), key=lambda v: v[2])
                save()
            print(f"{kind} run {r}: {done[r][1]}", file=log)


def _summarise(state: dict, args: argparse.Namespace, margin: bool, log: TextIO) -> int:
    """Print to `log` how many of the asked-for runs were flagged (and of the rerun and the
    redrawn runs); returns the regressed runs flagged."""
    wanted = set(range(args.first_draw, args.first_draw + args.runs))
    regressed = [v for v in state["regressed"] if v[2] in wanted]
    flagged = sum(not v[0] for v in regressed)
    alarms = sum(not v[0] for v in state["redrawn"] if v[2] <= args.false_alarm_runs)
    print(
        f"\n(5 mm, 2 deg) -> (10 mm, 4 deg) on {gate.GATE_TIER}, "
        f"{gate.GATE_EPISODES * len(OBJECT_NAMES)} episodes a run: flagged in {flagged} of "
        f"{args.runs} runs "
        + target(">= 19 of 20", flagged >= 0.95 * args.runs)
        + ("; margins not measured: success rule only" if not margin else ""),
        file=log,
    )
    if not args.no_rerun:
        print(f"rerun of unchanged errors flagged: {0 if state['rerun'][0] else 1} of 1", file=log)
    if args.false_alarm_runs:
        print(
            f"redrawn (5 mm, 2 deg) errors flagged: {alarms} of {args.false_alarm_runs}", file=log
        )
    return flagged


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    args = _parser().parse_args(argv)
    setup_rendering()
    log = summary_stream(args.json)
    record = None if args.json in (None, STDOUT) else args.json
    margin = not args.no_margin
    t0 = time.perf_counter()
    state = _resume(record, _protocol(margin))
    _collect(state, args, margin, record, log)
    flagged = _summarise(state, args, margin, log)
    print(f"wall time {time.perf_counter() - t0:.0f} s", file=log)
    if args.json is not None:
        state["flagged"], state["runs"] = flagged, args.runs
        write_json(args.json, state)
    return 0


if __name__ == "__main__":
    sys.exit(main())
