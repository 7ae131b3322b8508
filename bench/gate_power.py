"""How often the gate catches a known regression, and how often it cries wolf.

    python bench/gate_power.py [--runs 20] [--workers 2] [--json out.json]

The gate's protocol (`sim.gate`: `GATE_TIER` scenes from `GATE_SEED_START`, `GATE_EPISODES` per
object, friction margins measured) is run once with ``noisy-oracle`` at sigma (5 mm, 2 deg) on
all four error components; that report is the baseline. Each of `--runs` runs then draws its
own, independent errors (`sim.pose_noise.PoseNoise.draw` 1, 2, ...) at (10 mm, 4 deg) and is
compared with the baseline by the gate's rule (`sim.gate.compare`). Printed: the number of runs
flagged (target: at least 19 of 20), each run's verdict, and a rerun of the baseline's own
errors, which must pass. With `--false-alarm-runs N`, N runs at (5 mm, 2 deg) with other draws
are compared too: how often the gate flags a change of errors that is no regression.
`--first-draw K` starts the regressed runs at draw K (to add runs to an earlier batch). With
`--no-margin` the friction margins are not measured (half the time), so only the success rule
can flag: the figure is then a lower bound on the gate's. With `--json`, the baseline and every
verdict are saved after each run, and running again with the same file resumes where it stopped.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from posegrasp.core.files import atomic_write_json
from posegrasp.core.runtime import setup_rendering
from posegrasp.world.objects import OBJECT_NAMES
from sim import gate
from sim.evaluate import evaluate

BASE_NOISE = "5,5,2,2"
WORSE_NOISE = "10,10,4,4"
FINGERPRINT = {"noisy-oracle": "no weights"}


def _run(noise: str, workers: int, margin: bool = True) -> dict:
    return evaluate(
        list(OBJECT_NAMES), gate.GATE_EPISODES, "noisy-oracle", gate.GATE_SEED_START, workers,
        gate.GATE_TIER, noise=noise, margin=margin,
    )  # fmt: skip


def _baseline(report: dict) -> dict:
    record = gate.baseline_of(report)
    record["weights"] = FINGERPRINT
    return record


def _protocol(margin: bool) -> dict:
    return {
        "tier": gate.GATE_TIER, "seed_start": gate.GATE_SEED_START,
        "episodes_per_object": gate.GATE_EPISODES, "objects": list(OBJECT_NAMES),
        "base_noise": BASE_NOISE, "worse_noise": WORSE_NOISE, "margin": margin,
    }  # fmt: skip


def _resume(path: Path | None, protocol: dict) -> dict:
    """The state saved by an earlier, interrupted run of the same protocol (else a fresh one)."""
    if path is not None and path.is_file():
        try:
            state = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise SystemExit(f"error: cannot resume from {path}: {e}") from None
        if state.get("protocol") == protocol and "baseline" in state:
            print(f"resuming from {path}: {len(state['regressed'])} regressed run(s) done")
            return state
        raise SystemExit(f"error: {path} holds another protocol; pass another --json")
    return {"protocol": protocol, "regressed": [], "redrawn": [], "rerun": [True, "not run"]}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--runs", type=int, default=20, help="regressed runs, each its own draw")
    p.add_argument("--false-alarm-runs", type=int, default=0, help="unregressed redraws")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--no-margin", action="store_true", help="success rule only (faster)")
    p.add_argument("--first-draw", type=int, default=1, help="draw of the first regressed run")
    p.add_argument("--no-rerun", action="store_true", help="skip the rerun of the baseline")
    p.add_argument("--json", type=Path, help="every verdict, saved after each run (resumes)")
    args = p.parse_args()
    setup_rendering()
    margin = not args.no_margin
    if not 1 <= args.runs <= 1000 or not 0 <= args.false_alarm_runs <= 1000:
        p.error("--runs must be in 1..1000 and --false-alarm-runs in 0..1000")
    if not 1 <= args.first_draw <= 100_000:
        p.error("--first-draw must be in 1..100000")
    t0 = time.perf_counter()
    state = _resume(args.json, _protocol(margin))

    def save() -> None:
        if args.json:
            atomic_write_json(args.json, state)

    if "baseline" not in state:
        state["baseline"] = _baseline(_run(BASE_NOISE, args.workers, margin))
        save()
    baseline = state["baseline"]
    if not args.no_rerun and state["rerun"][1] == "not run":
        ok, text = gate.compare(_run(BASE_NOISE, args.workers, margin), baseline, FINGERPRINT)
        state["rerun"] = [ok, text]
        save()
    if not args.no_rerun:
        print(f"rerun of the baseline: {state['rerun'][1]}")
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
            print(f"{kind} run {r}: {done[r][1]}")
    wanted = set(range(args.first_draw, args.first_draw + args.runs))
    regressed = [v for v in state["regressed"] if v[2] in wanted]
    flagged = sum(not v[0] for v in regressed)
    alarms = sum(not v[0] for v in state["redrawn"] if v[2] <= args.false_alarm_runs)
    print(
        f"\n(5 mm, 2 deg) -> (10 mm, 4 deg) on {gate.GATE_TIER}, "
        f"{gate.GATE_EPISODES * len(OBJECT_NAMES)} episodes a run: flagged in {flagged} of "
        f"{args.runs} runs (target >= 19 of 20)"
        + ("; margins not measured: success rule only" if not margin else "")
    )
    if not args.no_rerun:
        print(f"rerun of unchanged errors flagged: {0 if state['rerun'][0] else 1} of 1")
    if args.false_alarm_runs:
        print(f"redrawn (5 mm, 2 deg) errors flagged: {alarms} of {args.false_alarm_runs}")
    print(f"wall time {time.perf_counter() - t0:.0f} s")
    if args.json:
        state["flagged"], state["runs"] = flagged, args.runs
        save()
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
