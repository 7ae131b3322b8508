"""The grasp-success regression gate: a fixed-seed evaluation compared with a committed baseline.

    python -m sim.gate             # run the gate's episodes and compare (exit 1 on a regression)
    python -m sim.gate --write     # run them and write the baseline (commit it with the weights)
    python -m sim.gate --estimator hybrid          # one estimator only

The gate runs `GATE_EPISODES` held-out episodes per object (seeds from `GATE_SEED_START`) with
each of `GATE_ESTIMATORS` and compares each success count with its baseline in `BASELINE`
(``sim/gate_baseline.json``): the default estimator, and the paper's pipeline alone, whose
success depends on the pose nets' accuracy without the table prior to correct it.

Margin. Episodes are seeded, so on one machine the same code and weights give the same count.
Across machines, floating-point differences in rendering, networks and physics can flip a few
borderline episodes. The gate therefore fails only when the success rate falls below the lower
end of the baseline's Wilson 95 % interval, ``p0 - wilson_low(k0, n)`` below the baseline rate
p0: a drop that a binomial sample of n episodes at rate p0 would show less than 2.5 % of the time.
With 60 episodes and p0 = 0.95 that margin is 8.7 points: 52 of 60 still pass, 51 fail.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

from sim.core.cli import ArgumentParser, fail, write_json
from sim.core.errors import PosegraspError
from sim.core.paths import REPO_ROOT
from sim.estimators import DEFAULT_ESTIMATOR, ESTIMATORS
from sim.evaluate import evaluate, format_report, wilson_interval
from sim.world.objects import OBJECT_NAMES

BASELINE = Path(__file__).resolve().parent / "gate_baseline.json"
GATE_EPISODES = 10
#: Held-out scenes (see `sim.world.constants.EVAL_SEED_BASE`), apart from the default evaluation's.
GATE_SEED_START = 1_500_000_000
WEIGHTS = ("perception/weights/detector.pt", "perception/weights/posenet_ours.pt")
GATE_ESTIMATORS = (DEFAULT_ESTIMATOR, "hybrid-table")


def load_baselines(path: Path = BASELINE) -> dict[str, dict]:
    """Baseline records by estimator (a file holding one record is read as that estimator's)."""
    data = json.loads(Path(path).read_text())
    return {data["estimator"]: data} if "estimator" in data else data


def weights_fingerprint() -> dict[str, str]:
    """SHA-256 (first 16 hex digits) of each shipped weights file, "missing" when absent."""
    out = {}
    for rel in WEIGHTS:
        p = REPO_ROOT / rel
        out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()[:16] if p.is_file() else "missing"
    return out


def margin(successes: int, episodes: int) -> float:
    """How far below the baseline rate a run may fall: the baseline's Wilson 95 % half-width
    below its rate."""
    return successes / episodes - wilson_interval(successes, episodes)[0]


def run_gate(
    estimator: str = DEFAULT_ESTIMATOR, episodes: int = GATE_EPISODES, workers: int = 2
) -> dict:
    """The gate's evaluation: `episodes` per object from `GATE_SEED_START`."""
    return evaluate(list(OBJECT_NAMES), episodes, estimator, GATE_SEED_START, workers)


def compare(report: dict, baseline: dict) -> tuple[bool, str]:
    """(passed, one-line verdict) of an evaluation against a baseline."""
    if (report["estimator"], report["episodes_per_object"], report["seed_start"]) != (
        baseline["estimator"],
        baseline["episodes_per_object"],
        baseline["seed_start"],
    ):
        return False, (
            "the run does not match the baseline's estimator, episodes and seeds; "
            "rewrite it with `python -m sim.gate --write`"
        )
    n = report["overall"]["episodes"]
    k, k0 = report["overall"]["successes"], baseline["successes"]
    m = margin(k0, n)
    floor = k0 / n - m
    ok = k / n >= floor - 1e-12
    verdict = (
        f"{'PASS' if ok else 'FAIL'}: {k}/{n} successes ({k / n:.1%}) against the baseline's "
        f"{k0}/{n} ({k0 / n:.1%}); the floor is {floor:.1%} (baseline minus its Wilson 95 % "
        f"half-width {m:.1%})"
    )
    return ok, verdict


def baseline_of(report: dict) -> dict:
    """The baseline record of an evaluation."""
    return {
        "estimator": report["estimator"],
        "episodes_per_object": report["episodes_per_object"],
        "seed_start": report["seed_start"],
        "episodes": report["overall"]["episodes"],
        "successes": report["overall"]["successes"],
        "success_rate": report["overall"]["success_rate"],
        "per_object": {o: g["successes"] for o, g in report["per_object"].items()},
        "weights": weights_fingerprint(),
    }


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status (1 when the gate fails)."""
    p = ArgumentParser(prog="python -m sim.gate", description=__doc__.split("\n")[0])
    p.add_argument("--write", action="store_true", help="write the baseline instead of comparing")
    p.add_argument("--baseline", type=Path, default=BASELINE)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument(
        "--estimator", default=None, help=f"only this one; one of: {', '.join(ESTIMATORS)}"
    )
    args = p.parse_args(argv)
    if args.workers < 1:
        return fail("--workers must be at least 1")
    if args.estimator is not None and args.estimator not in ESTIMATORS:
        return fail(
            f"unknown estimator {args.estimator!r}; valid estimators: {', '.join(ESTIMATORS)}"
        )
    baselines: dict[str, dict] = {}
    if args.baseline.is_file():
        try:
            baselines = load_baselines(args.baseline)
        except (ValueError, KeyError, TypeError) as exc:
            return fail(f"{args.baseline} is not a gate baseline ({exc}); rewrite it with --write")
    elif not args.write:
        return fail(f"no baseline at {args.baseline}; write one with `python -m sim.gate --write`")
    if args.estimator:
        names = [args.estimator]
    else:
        names = list(GATE_ESTIMATORS) if args.write else list(baselines)
    if not args.write and (missing := [n for n in names if n not in baselines]):
        return fail(
            f"no baseline for {', '.join(missing)} in {args.baseline}; it has: "
            f"{', '.join(baselines)}; write one with `python -m sim.gate --write --estimator E`"
        )
    failed = False
    for name in names:
        try:
            report = run_gate(name, GATE_EPISODES, args.workers)
        except PosegraspError as exc:
            return fail(str(exc))
        print(format_report(report))
        if args.write:
            baselines[name] = baseline_of(report)
            continue
        ok, verdict = compare(report, baselines[name])
        if baselines[name].get("weights") != weights_fingerprint():
            print("note: the shipped weights differ from the baseline's; rewrite the baseline")
        print(f"{name}: {verdict}")
        failed |= not ok
    if args.write:
        write_json(args.baseline, baselines)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
