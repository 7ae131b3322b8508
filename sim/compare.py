"""Paired comparison of two evaluations on the seeds both ran.

    python -m sim.compare A.json B.json [--json PATH] [--boot 2000]
    python -m sim.compare A.json B.json C.json ... --curve [--plot PATH] [--json PATH]

A and B are reports of `python -m sim.evaluate --json`. Episodes pair up by (object, tier, seed):
the same scene, so the difference in success is measured without the scene-to-scene variance.
The success difference B - A comes with the exact McNemar p-value (two-sided binomial test on
the discordant pairs) and a paired bootstrap 95 % interval, overall and per object; when both
reports measured friction margins (`sim.evaluate --margin`), the mean margin difference on the
episodes both grasped comes with its paired bootstrap interval too. BOP's average recalls are
linear in the episodes, so they pair too: the difference B - A of AR_MSSD, AR_MSPD and, when
both reports hold every episode's VSD errors (``vsd``), AR_VSD, each with its paired bootstrap
interval (an episode without an estimate counts 0). The risk-coverage area of each estimator's
confidence (`sim.evaluation.stats.risk_coverage`) over the shared episodes pairs too: both areas
and B - A with a paired bootstrap interval when both give a confidence (reports written before the
area was recorded hold it in their episodes' ``confidence``).

Reports whose grasps ran with different execution settings (``execution``), or whose estimators
observed through different sensor models (``sensor``, `posegrasp.world.sensors`; a report that
records none observed the ideal camera), are different experiments: they are refused in one line.
Runs are labelled by their estimator (and noise), with the file only where the labels would
coincide. A one-line warning goes to standard error when the runs saw different observations
(``obs_mode``), or when a success difference's bootstrap interval and its exact McNemar test
disagree or rest on fewer than `MIN_PAIRS` episodes: the exact test is then the one to read.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from perception import metrics
from posegrasp.core.cli import (
    ArgumentParser,
    add_json_argument,
    command,
    summary_stream,
    write_json,
)
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.validate import arg, check_int, check_plot_path
from sim.evaluation.report_schema import read_report
from sim.evaluation.stats import (
    BOOTSTRAP,
    Outcome,
    margin_difference,
    margin_error_correlation,
    paired,
    paired_area_difference,
    paired_mean_difference,
    wilson_interval,
)

Key = tuple[str, str, int]

#: The head camera's width the episodes render at [px] (`sim.episodes.episode.EpisodeConfig.width`,
#: repeated here so that comparing imports no episode machinery; a test keeps the two equal).
IMAGE_WIDTH = 640
#: Fewer paired episodes than this make the percentile bootstrap of a success difference
#: unreliable: the comparison then says to read the exact McNemar test.
MIN_PAIRS = 30
#: Significance level at which the bootstrap interval and the exact test are held to agree.
ALPHA = 0.05
#: BOP's average recalls the comparison pairs, in print order.
RECALLS = ("ar_mssd", "ar_mspd", "ar_vsd")


def outcomes_of(report: dict, source: str) -> dict[Key, Outcome]:
    """(success, friction margin or None) by (object, tier, seed) of a validated report.

    Raises:
        InvalidArgumentError: a pair listed twice, naming `source`.
    """
    out: dict[Key, Outcome] = {}
    for e in report["episodes"]:
        key = (str(e["object"]), str(e["tier"]), int(e["seed"]))
        if key in out:
            raise InvalidArgumentError(f"{source} lists episode {key} twice")
        margin = e.get("friction_margin")
        out[key] = (bool(e["success"]), None if margin is None else float(margin))
    return out


def load_report(path: Path) -> dict[tuple[str, str, int], Outcome]:
    """(success, friction margin or None) by (object, tier, seed) of one evaluation report,
    validated against the report schema (`sim.evaluation.report_schema`) first.

    Raises:
        InvalidArgumentError: unreadable, not conforming to the schema (naming the field), or a
            pair listed twice.
    """
    return outcomes_of(read_report(path), str(path))


def episode_recalls(report: dict, source: str) -> dict[Key, dict[str, float]]:
    """Each episode's contribution to BOP's average recalls, by (object, tier, seed): its AR_MSSD
    (thresholds 0.05..0.5 of the diameter), AR_MSPD (5..50 px at `IMAGE_WIDTH`) and, when it
    holds ``vsd`` errors (one per tau, None without an estimate), AR_VSD, each
    `perception.metrics`' average recall of that one episode. An episode without an estimate
    scores 0; a recall that no episode's errors hold while some episode has an estimate (a
    report written before it was measured) is left out of every episode.

    The report's own recall is the mean of its episodes' (the recalls are linear in episodes).

    Raises:
        InvalidArgumentError: an episode's ``vsd`` of the wrong length, naming `source`.
    """
    eps = report["episodes"]
    errors = [e.get("pose_error") or {} for e in eps]
    estimated = any(e.get("pose_error") for e in eps)
    keys = {"ar_mssd": "mssd_rel_diameter", "ar_mspd": "mspd_px"}
    measured = {r for r, k in keys.items() if not estimated or any(k in pe for pe in errors)}
    out: dict[Key, dict[str, float]] = {}
    for e, pe in zip(eps, errors, strict=True):
        key = (str(e["object"]), str(e["tier"]), int(e["seed"]))
        row: dict[str, float] = {}
        if "ar_mssd" in measured:
            row["ar_mssd"] = metrics.ar_mssd([pe.get("mssd_rel_diameter")], 1.0)
        if "ar_mspd" in measured:
            row["ar_mspd"] = metrics.ar_mspd([pe.get("mspd_px")], IMAGE_WIDTH)
        if "vsd" in e:
            try:
                row["ar_vsd"] = metrics.ar_vsd([e["vsd"]])
            except InvalidArgumentError as exc:
                raise InvalidArgumentError(f"{source}: episode {key}: vsd: {exc}") from None
        out[key] = row
    return out


def recall_differences(
    a: dict[Key, dict[str, float]],
    b: dict[Key, dict[str, float]],
    boot: int = BOOTSTRAP,
    seed: int = 0,
) -> dict[str, dict]:
    """The paired difference B - A of each average recall (`RECALLS`) that every episode both
    ran holds in both reports (`episode_recalls`), with its paired bootstrap 95 % interval
    (`sim.evaluation.stats.paired_mean_difference`); {} when they share no episode."""
    common = sorted(set(a) & set(b))
    rng = np.random.default_rng(seed)
    out = {}
    for name in RECALLS:
        if common and all(name in a[k] and name in b[k] for k in common):
            ra = np.array([a[k][name] for k in common])
            rb = np.array([b[k][name] for k in common])
            out[name] = paired_mean_difference(ra, rb, boot, rng)
    return out


def episode_confidences(report: dict) -> dict[Key, tuple[float | None, bool]]:
    """Each episode's confidence (None where its estimator gave none) and success, by (object,
    tier, seed), of a validated report (one that lists no pair twice, `outcomes_of`)."""
    return {
        (str(e["object"]), str(e["tier"]), int(e["seed"])): (
            None if e.get("confidence") is None else float(e["confidence"]),
            bool(e["success"]),
        )
        for e in report["episodes"]
    }


def area_difference(
    a: dict[Key, tuple[float | None, bool]],
    b: dict[Key, tuple[float | None, bool]],
    boot: int = BOOTSTRAP,
    seed: int = 0,
) -> dict:
    """The risk-coverage areas of A and B over the episodes both ran (`episode_confidences`)
    and their difference B - A with its paired bootstrap 95 % interval
    (`sim.evaluation.stats.paired_area_difference`; a side without a confidence has area None)."""
    common = sorted(set(a) & set(b))
    return paired_area_difference(
        [a[k][0] for k in common],
        [a[k][1] for k in common],
        [b[k][0] for k in common],
        [b[k][1] for k in common],
        boot,
        np.random.default_rng(seed),
    )


def run_labels(a: dict, b: dict, path_a: Path | str, path_b: Path | str) -> tuple[str, str]:
    """Labels of two reports: the estimator (with its noise), the observation mode when the two
    differ in it, and the file only when the labels would still coincide."""

    def label(r: dict, mode: bool) -> str:
        text = str(r["estimator"]) + (f" [{r['noise']}]" if r.get("noise") else "")
        return text + (f" ({r['obs_mode']})" if mode else "")

    mode = a["obs_mode"] != b["obs_mode"]
    la, lb = label(a, mode), label(b, mode)
    if la == lb:
        la, lb = f"{la} ({path_a})", f"{lb} ({path_b})"
    return la, lb


def comparison_warnings(res: dict, obs_a: str, obs_b: str) -> list[str]:
    """One-line warnings about a comparison (`compare`): the runs saw different observations;
    a success difference whose bootstrap interval and exact McNemar test disagree at `ALPHA`,
    or whose overall count is below `MIN_PAIRS` (then the exact test is the one to read)."""
    out = []
    if obs_a != obs_b:
        out.append(
            f"warning: A saw {obs_a} and B {obs_b} (obs_mode): the difference is the estimator's "
            "and the observation's together"
        )
    reasons = []
    n = res["overall"]["episodes"]
    if n < MIN_PAIRS:
        reasons.append(f"only {n} paired episodes (fewer than {MIN_PAIRS})")
    per_object = list(res["per_object"].items()) if len(res["per_object"]) > 1 else []
    rows = [*per_object, ("overall", res["overall"])]
    disagree = []
    for name, r in rows:
        excludes = r["bootstrap_low"] > 0 or r["bootstrap_high"] < 0
        if excludes != (r["mcnemar_p"] < ALPHA):
            side = "excludes" if excludes else "includes"
            disagree.append(f"{name} (interval {side} 0, p = {r['mcnemar_p']:.3g})")
    if disagree:
        reasons.append(
            f"the bootstrap interval and the exact McNemar test at {ALPHA} disagree on "
            + ", ".join(disagree)
        )
    if reasons:
        out.append(
            f"warning: {'; '.join(reasons)}: read the exact McNemar p, not the bootstrap interval"
        )
    return out


def compare_reports(path_a: Path, path_b: Path, boot: int = BOOTSTRAP) -> dict:
    """The paired comparison of two report files (`compare`), with their labels
    (`run_labels`), the paired average recalls (``average_recall``, `recall_differences`), the
    paired risk-coverage area (``risk_coverage_area``, `area_difference`) and the warnings
    (`comparison_warnings`).

    Raises:
        InvalidArgumentError: a report unreadable or not conforming, or no shared episode.
    """
    ra, rb = read_report(path_a), read_report(path_b)
    res = compare(outcomes_of(ra, str(path_a)), outcomes_of(rb, str(path_b)), boot)
    res["label_a"], res["label_b"] = run_labels(ra, rb, path_a, path_b)
    res["obs_mode_a"], res["obs_mode_b"] = ra["obs_mode"], rb["obs_mode"]
    res["average_recall"] = recall_differences(
        episode_recalls(ra, str(path_a)), episode_recalls(rb, str(path_b)), boot
    )
    res["risk_coverage_area"] = area_difference(
        episode_confidences(ra), episode_confidences(rb), boot
    )
    res["warnings"] = comparison_warnings(res, ra["obs_mode"], rb["obs_mode"])
    return res


def check_same_execution(paths: list[Path]) -> None:
    """Refuse to pair reports whose grasps ran with different execution settings (the
    ``execution`` record of `sim.evaluate`).

    Raises:
        InvalidArgumentError: a report does not conform to the schema, or two record different
            settings, naming the first that differs.
    """
    seen: tuple[Path, dict] | None = None
    for path in paths:
        settings = read_report(path)["execution"]
        if seen is None:
            seen = (path, settings)
            continue
        first, ref = seen
        diff = sorted(k for k in ref.keys() | settings.keys() if ref.get(k) != settings.get(k))
        if diff:
            k = diff[0]
            raise InvalidArgumentError(
                f"{first} and {path} grasped with different execution settings ({k}: "
                f"{ref.get(k)!r} against {settings.get(k)!r}); pair runs of one protocol"
            )


def report_sensor(report: dict, source: str) -> str:
    """The sensor model a validated report's estimator observed through: its ``sensor`` field,
    else the one its episodes record (`sim.episodes.episode.EpisodeResult.sensor`), else ``ideal``
    (what a report that records none observed, as every report did before sensors were recorded).

    Raises:
        InvalidArgumentError: episodes of more than one sensor, naming `source`.
    """
    if "sensor" in report:
        return str(report["sensor"])
    named = sorted(
        {str(e["sensor"]) for e in report["episodes"] if e.get("sensor", "ideal") != "ideal"}
    )
    if len(named) > 1:
        raise InvalidArgumentError(
            f"{source} holds episodes of several sensors ({', '.join(named)}); one report is one "
            "sensor"
        )
    return named[0] if named else "ideal"


def _first_differing(
    paths: list[Path], value: Callable[[Path], str]
) -> tuple[tuple[Path, str], tuple[Path, str]] | None:
    """The first report and the first after it whose `value` differs from its, or None."""
    first = (paths[0], value(paths[0]))
    for path in paths[1:]:
        if (v := value(path)) != first[1]:
            return first, (path, v)
    return None


def check_same_task(paths: list[Path]) -> None:
    """Refuse to pair reports of different tasks (a report's ``task``; ``lift`` when it records
    none): a placed object and a lifted one are different outcomes.

    Raises:
        InvalidArgumentError: two reports name different tasks, naming the first that differs.
    """
    found = _first_differing(paths, lambda p: str(read_report(p).get("task", "lift")))
    if found is not None:
        (a, ta), (b, tb) = found
        raise InvalidArgumentError(
            f"{a} is of the {ta} task and {b} of the {tb} task; pair runs of one task"
        )


def check_same_sensor(paths: list[Path]) -> None:
    """Refuse to pair reports whose estimators observed through different sensor models
    (`report_sensor`).

    Raises:
        InvalidArgumentError: a report does not conform to the schema or mixes sensors, or two
            name different sensors, naming the first that differs.
    """
    found = _first_differing(paths, lambda p: report_sensor(read_report(p), str(p)))
    if found is not None:
        (a, sa), (b, sb) = found
        raise InvalidArgumentError(
            f"{a} observed through sensor {sa!r} and {b} through {sb!r}; pair runs of one sensor"
        )


def compare(
    a: dict[tuple[str, str, int], Outcome],
    b: dict[tuple[str, str, int], Outcome],
    boot: int = BOOTSTRAP,
    seed: int = 0,
) -> dict:
    """Overall and per-object paired comparison of B against A on the pairs both ran.

    Raises:
        InvalidArgumentError: the two share no episode.
    """
    common = sorted(set(a) & set(b))
    if not common:
        raise InvalidArgumentError("the two reports share no (object, tier, seed) episode")
    rng = np.random.default_rng(seed)
    sa = np.array([a[k][0] for k in common])
    sb = np.array([b[k][0] for k in common])
    objects = sorted({k[0] for k in common})
    per_object = {}
    for o in objects:
        m = np.array([k[0] == o for k in common])
        per_object[o] = paired(sa[m], sb[m], boot, rng)
    return {
        "paired_episodes": len(common),
        "only_in_a": len(set(a) - set(b)),
        "only_in_b": len(set(b) - set(a)),
        "overall": paired(sa, sb, boot, rng),
        "per_object": per_object,
        "friction_margin": margin_difference(
            [a[k] for k in common], [b[k] for k in common], boot, rng
        ),
    }


def format_comparison(res: dict, name_a: str, name_b: str) -> str:
    """The comparison as a table."""
    rows = [
        f"B = {name_b} against A = {name_a}: {res['paired_episodes']} paired episodes "
        f"({res['only_in_a']} only in A, {res['only_in_b']} only in B)",
        f"{'object':<8} {'n':>5} {'A':>6} {'B':>6} {'B - A':>7} {'bootstrap 95%':>17} "
        f"{'A only':>7} {'B only':>7} {'McNemar p':>10}",
    ]
    for name, r in [*res["per_object"].items(), ("overall", res["overall"])]:
        n = r["episodes"]
        rows.append(
            f"{name:<8} {n:>5} {r['success_a'] / n:>6.1%} {r['success_b'] / n:>6.1%} "
            f"{r['difference']:>+7.1%} [{r['bootstrap_low']:>+6.1%}, {r['bootstrap_high']:>+6.1%}] "
            f"{r['a_only']:>7} {r['b_only']:>7} {r['mcnemar_p']:>10.4f}"
        )
    m = res.get("friction_margin")
    if m is not None:
        rows.append(
            f"friction margin B - A on {m['pairs']} episodes both grasped: "
            f"{m['difference']:+.4f} [{m['bootstrap_low']:+.4f}, {m['bootstrap_high']:+.4f}] "
            "(bootstrap 95 %; positive: B's grasps are looser)"
        )
    for name, r in res.get("average_recall", {}).items():
        rows.append(
            f"{name.upper():<8} A {r['a']:.3f} B {r['b']:.3f}, B - A "
            f"{r['difference']:+.3f} [{r['bootstrap_low']:+.3f}, {r['bootstrap_high']:+.3f}] "
            f"(paired over {r['episodes']} episodes, bootstrap 95 %)"
        )
    if (area := res.get("risk_coverage_area")) is not None:
        rows.append(format_area(area))
    return "\n".join(rows)


def format_area(r: dict) -> str:
    """The paired risk-coverage area (`area_difference`) as one line."""
    if r["a"] is None and r["b"] is None:
        return "RC area  neither estimator gives a confidence"
    if r["a"] is None or r["b"] is None:
        side = "A" if r["a"] is None else "B"
        return (
            f"RC area  A {_area(r['a'])} B {_area(r['b'])}: {side} gives no confidence, "
            "so the areas do not pair"
        )
    if r["bootstrap_low"] is None:
        interval = "no resample held both confidences"
    else:
        interval = f"[{r['bootstrap_low']:+.3f}, {r['bootstrap_high']:+.3f}]"
    return (
        f"RC area  A {r['a']:.3f} B {r['b']:.3f}, B - A {r['difference']:+.3f} {interval} "
        f"(risk-coverage area, paired over {r['episodes']} episodes, bootstrap 95 %)"
    )


def _area(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


def curve(paths: list[Path], boot: int = BOOTSTRAP) -> list[dict]:
    """A chain of reports run on the same scenes (e.g. noisy-oracle at growing sigma): per
    report its label (noise or estimator), success and mean friction margin, and the paired
    comparison of each report with the one before it. The last row also holds, per object,
    the rank correlation of margin and pose error over the episodes of every report
    (`pooled_margin_error_spearman`).

    Raises:
        InvalidArgumentError: an unreadable report, or two neighbours that share no episode.
    """
    rows = []
    prev = None
    pooled: dict[str, list[dict]] = {}
    for path in paths:
        outcomes = load_report(path)
        report = read_report(path)
        for e in report["episodes"]:
            pooled.setdefault(str(e["object"]), []).append(e)
        ok = sum(s for s, _ in outcomes.values())
        margins = [m for s, m in outcomes.values() if s and m is not None]
        row = {
            "report": str(path),
            "label": report["noise"] or report["estimator"],
            "episodes": len(outcomes),
            "successes": int(ok),
            "friction_margin_mean": float(np.mean(margins)) if margins else None,
            "against_previous": None if prev is None else compare(prev, outcomes, boot),
        }
        rows.append(row)
        prev = outcomes
    rows[-1]["pooled_margin_error_spearman"] = {
        o: margin_error_correlation(eps) for o, eps in sorted(pooled.items())
    }
    return rows


def format_curve(rows: list[dict]) -> str:
    """The chain as a table: success, margin, and the paired step from the report before."""
    out = [f"{'report':<24} {'success':>13} {'margin':>7} {'lost':>5} {'won':>4} {'McNemar p':>10}"]
    for r in rows:
        m = r["friction_margin_mean"]
        step = r["against_previous"]
        lost = won = p = ""
        if step is not None:
            o = step["overall"]
            lost, won, p = o["a_only"], o["b_only"], f"{o['mcnemar_p']:.3g}"
        out.append(
            f"{r['label']!s:<24} {r['successes']:>5}/{r['episodes']:<4} "
            f"{r['successes'] / r['episodes']:>5.1%} {'' if m is None else f'{m:.3f}':>7} "
            f"{lost:>5} {won:>4} {p:>10}"
        )
    pooled = rows[-1].get("pooled_margin_error_spearman") if rows else None
    if pooled:
        out.append("margin vs pose error over all these episodes, Spearman per object:")
        for o, rho in pooled.items():
            vals = ", ".join(
                f"{k} {rho[k]:+.2f}"
                for k in ("translation_m", "rotation_deg", "add_m")
                if rho.get(k) is not None
            )
            out.append(f"  {o:<8} {vals or 'too few'} ({rho['episodes']} grasped)")
    return "\n".join(out)


def plot_curve(rows: list[dict], path: Path, title: str) -> None:
    """Success (Wilson 95 % bars) and mean friction margin along the chain."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.arange(len(rows))
    rate = np.array([r["successes"] / r["episodes"] for r in rows])
    ci = np.array([wilson_interval(r["successes"], r["episodes"]) for r in rows])
    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    ax.errorbar(x, 100 * rate, yerr=100 * np.abs(ci.T - rate), fmt="o-", capsize=3)
    ax.set_xticks(x, [str(r["label"]) for r in rows], rotation=15, fontsize=8)
    ax.set_ylabel("grasp success [%]")
    ax.set_title(title, fontsize=10)
    ax2 = ax.twinx()
    m = [np.nan if r["friction_margin_mean"] is None else r["friction_margin_mean"] for r in rows]
    ax2.plot(x, m, "s--", color="tab:orange")
    ax2.set_ylabel("mean friction margin", color="tab:orange")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


@command
def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status."""
    p = ArgumentParser(prog="python -m sim.compare", description=__doc__.split("\n")[0])
    p.add_argument("a", type=Path, help="report A (python -m sim.evaluate --json)")
    p.add_argument("b", type=Path, help="report B")
    p.add_argument("more", type=Path, nargs="*", help="with --curve: further reports")
    p.add_argument(
        "--curve",
        action="store_true",
        help="a chain of reports on the same scenes: each against the one before",
    )
    p.add_argument(
        "--plot",
        type=arg(check_plot_path),
        default=None,
        metavar="PATH",
        help="with --curve: plot success and margin along the chain here (.png, .pdf or .svg)",
    )
    add_json_argument(p, "the comparison")
    p.add_argument(
        "--boot",
        type=arg(check_int, 100, 100_000, "--boot", base=int),
        default=BOOTSTRAP,
        help="bootstrap resamples (100..100000)",
    )
    args = p.parse_args(argv)
    if (args.more or args.plot) and not args.curve:
        raise InvalidArgumentError("more than two reports, or --plot, need --curve")
    log = summary_stream(args.json)
    check_same_execution([args.a, args.b, *args.more])
    check_same_sensor([args.a, args.b, *args.more])
    check_same_task([args.a, args.b, *args.more])
    if args.curve:
        rows = curve([args.a, args.b, *args.more], args.boot)
        print(format_curve(rows), file=log)
        if args.plot is not None:
            tier = read_report(args.a)["tier"]
            plot_curve(rows, args.plot, f"tier {tier}: paired runs on the same scenes")
        res: dict | list = rows
    else:
        res = compare_reports(args.a, args.b, args.boot)
        print(format_comparison(res, res["label_a"], res["label_b"]), file=log)
        for line in res["warnings"]:
            print(line, file=sys.stderr)
    if args.json is not None:
        write_json(args.json, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
