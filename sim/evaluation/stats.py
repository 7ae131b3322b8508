"""The statistics of paired grasp experiments: pure functions, no I/O.

Wilson intervals of a success rate, the exact McNemar test on discordant pairs (from their
counts, or from paired successes), the Wilcoxon signed-rank test of paired placement errors with
failures ranked worst, the risk-coverage curve of a confidence, and paired bootstrap intervals of
success, friction-margin, per-episode score and risk-coverage area differences (`sim.compare`,
`sim.evaluate`, `sim.gate`, `sim.board`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.stats import binomtest, rankdata, spearmanr, wilcoxon

from posegrasp.core.errors import InvalidArgumentError

#: An episode's outcome: (success, friction margin or None).
Outcome = tuple[bool, float | None]

#: Bootstrap resamples unless told otherwise.
BOOTSTRAP = 2000


def wilson_interval(successes: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (95 % for the default z).

    Returns:
        (low, high), which always holds successes / n; (0, 1) when n == 0.
    """
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    # At p = 0 or 1 a bound equals p exactly; rounding must not leave p outside its interval.
    return float(max(0.0, min(p, centre - half))), float(min(1.0, max(p, centre + half)))


def bootstrap_means(values: np.ndarray, boot: int, rng: np.random.Generator) -> np.ndarray:
    """Means of `boot` resamples (with replacement) of `values`, shape (boot,)."""
    values = np.asarray(values, float)
    return rng.choice(values, (boot, values.size)).mean(axis=1)


def margin_error_correlation(episodes: list[dict]) -> dict[str, float | int | None]:
    """Spearman rank correlation of the friction margin with each pose error (translation [m],
    rotation [deg], ADD [m]) over the episodes that have both, and their count; None where
    fewer than 5 episodes have both or either side is constant. Positive: larger errors, looser
    grasps."""
    pairs = [
        (e["friction_margin"], e["pose_error"])
        for e in episodes
        if e.get("friction_margin") is not None and e.get("pose_error")
    ]
    out: dict[str, float | int | None] = {"episodes": len(pairs)}
    for key in ("translation_m", "rotation_deg", "add_m"):
        m = np.array([p[0] for p in pairs], float)
        err = np.array([p[1].get(key, np.nan) for p in pairs], float)
        ok = np.isfinite(err)
        rho = None
        if ok.sum() >= 5 and np.ptp(m[ok]) > 0 and np.ptp(err[ok]) > 0:
            rho = float(spearmanr(m[ok], err[ok]).statistic)
        out[key] = rho
    return out


def mcnemar_exact(a_only: int, b_only: int, one_sided: bool = False) -> float:
    """Exact McNemar p-value from the discordant pair counts (1.0 when there are none):
    two-sided, or with `one_sided` the chance of at least `a_only` of the `a_only + b_only`
    discordant pairs going A's way if neither is better (the test of a loss)."""
    n = a_only + b_only
    if n == 0:
        return 1.0
    if one_sided:
        return float(binomtest(a_only, n, 0.5, alternative="greater").pvalue)
    return float(binomtest(min(a_only, b_only), n, 0.5).pvalue)


def mcnemar_paired(success_a: Sequence[bool], success_b: Sequence[bool]) -> dict:
    """McNemar's test of paired successes, exact and two-sided: A and B on the same episodes.

    McNemar (1947), "Note on the sampling error of the difference between correlated
    proportions or percentages", Psychometrika 12(2); the exact conditional form (Fagerland,
    Lydersen and Laake 2013, BMC Med. Res. Methodol. 13:91, eq. 2): only the discordant pairs
    count, and if neither is better each goes A's way with probability 1/2, so with ``b`` pairs
    that only A won and ``c`` that only B won, ``p = min(1, 2 P(X <= min(b, c)))`` for
    ``X ~ Binomial(b + c, 1/2)`` (`mcnemar_exact`); 1 without a discordant pair.

    Args:
        success_a: per episode, whether A succeeded; (N,).
        success_b: per episode, whether B succeeded, the episodes in the same order; (N,).

    Returns:
        ``episodes`` (N), ``a`` and ``b`` (their successes), ``a_only`` and ``b_only`` (the
        discordant pairs) and ``p``.

    Raises:
        InvalidArgumentError: sequences of different lengths.
    """
    if len(success_a) != len(success_b):
        raise InvalidArgumentError(
            f"mcnemar_paired: {len(success_a)} and {len(success_b)} outcomes; pair the same "
            "episodes"
        )
    a, b = np.asarray(success_a, bool), np.asarray(success_b, bool)
    a_only, b_only = int(np.sum(a & ~b)), int(np.sum(~a & b))
    return {
        "episodes": len(a),
        "a": int(a.sum()),
        "b": int(b.sum()),
        "a_only": a_only,
        "b_only": b_only,
        "p": mcnemar_exact(a_only, b_only),
    }


def _worst_ranked(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The paired differences A - B (N,) of `wilcoxon_worst_ranked`: a failure on both sides is
    a tie (0); a failure on one side is the largest magnitude, shared by every such pair, signed
    towards the side that failed."""
    fail_a, fail_b = np.isinf(a), np.isinf(b)
    one, both_ran = fail_a ^ fail_b, ~(fail_a | fail_b)
    d = np.zeros_like(a)
    d[both_ran] = a[both_ran] - b[both_ran]
    top = 1.0 + 2.0 * float(np.max(np.abs(d), initial=0.0))
    d[one] = np.where(fail_a[one], top, -top)
    return d


def wilcoxon_worst_ranked(errors_a: Sequence[float], errors_b: Sequence[float]) -> dict:
    """The Wilcoxon signed-rank test of paired errors (A and B on the same episodes), two-sided,
    an episode that failed before it had an error (``inf``) ranked worst.

    Wilcoxon (1945), "Individual comparisons by ranking methods", Biometrics Bulletin 1(6): the
    differences ``d = A - B`` are ranked by magnitude (ties share their mean rank), zero
    differences left out (Wilcoxon's own rule, ``zero_method="wilcox"``), and ``R+``, ``R-``
    are the rank sums of the positive and negative ones; the p-value is
    `scipy.stats.wilcoxon`'s (exact for small samples without ties, else the normal
    approximation with the tie correction).

    A failure (``inf``: the object was never lifted, so it rests nowhere near its goal) is worse
    than any error: a pair where both failed is a tie (left out, like any zero difference), a
    pair where one failed has a difference larger in magnitude than every finite one and equal
    to every other such pair's (they share the top ranks), signed against the side that failed.

    Args:
        errors_a: per episode, A's error (any unit, the same for both; ``inf``: failed); (N,).
        errors_b: B's, the episodes in the same order; (N,).

    Returns:
        ``episodes`` (N), ``ranked`` (the pairs with a nonzero difference), ``r_plus`` and
        ``r_minus`` (rank sums: ``r_minus > r_plus`` says A's errors are the smaller), and ``p``
        (1 when no pair differs).

    Raises:
        InvalidArgumentError: sequences of different lengths, NaN or a negative infinity.
    """
    a, b = np.asarray(errors_a, float), np.asarray(errors_b, float)
    if a.shape != b.shape or a.ndim != 1:
        raise InvalidArgumentError(
            f"wilcoxon_worst_ranked: {a.shape} and {b.shape} errors; pair the same episodes"
        )
    if np.isnan(a).any() or np.isnan(b).any() or (np.minimum(a, b) == -np.inf).any():
        raise InvalidArgumentError("wilcoxon_worst_ranked: errors are numbers or +inf (failed)")
    d = _worst_ranked(a, b)
    nz = d[d != 0]
    ranks = rankdata(np.abs(nz))
    out = {
        "episodes": int(a.size),
        "ranked": int(nz.size),
        "r_plus": float(ranks[nz > 0].sum()),
        "r_minus": float(ranks[nz < 0].sum()),
        "p": 1.0,
    }
    if nz.size:
        out["p"] = float(wilcoxon(nz, zero_method="wilcox", alternative="two-sided").pvalue)
    return out


def paired(a: np.ndarray, b: np.ndarray, boot: int, rng: np.random.Generator) -> dict:
    """Success of A and B on the same episodes (bool arrays) and their paired difference."""
    n = len(a)
    a_only, b_only = int(np.sum(a & ~b)), int(np.sum(~a & b))
    diff = float(b.mean() - a.mean())
    idx = rng.integers(0, n, size=(boot, n))
    d = b[idx].mean(axis=1) - a[idx].mean(axis=1)
    lo, hi = np.percentile(d, [2.5, 97.5])
    return {
        "episodes": n,
        "success_a": int(a.sum()),
        "success_b": int(b.sum()),
        "difference": diff,
        "bootstrap_low": float(lo),
        "bootstrap_high": float(hi),
        "a_only": a_only,
        "b_only": b_only,
        "mcnemar_p": mcnemar_exact(a_only, b_only),
    }


def paired_mean_difference(
    a: np.ndarray, b: np.ndarray, boot: int, rng: np.random.Generator
) -> dict:
    """Means of per-episode scores of A and B on the same episodes, (N,) each, and the mean of
    the paired differences B - A with its paired bootstrap 95 % interval (episodes resampled
    with replacement).

    Raises:
        InvalidArgumentError: no episode, or arrays of different shapes.
    """
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.shape != b.shape or a.ndim != 1 or a.size == 0:
        raise InvalidArgumentError(
            f"paired scores must be two non-empty (N,) arrays, got {a.shape} and {b.shape}"
        )
    d = b - a
    lo, hi = np.percentile(bootstrap_means(d, boot, rng), [2.5, 97.5])
    return {
        "episodes": int(d.size),
        "a": float(a.mean()),
        "b": float(b.mean()),
        "difference": float(d.mean()),
        "bootstrap_low": float(lo),
        "bootstrap_high": float(hi),
    }


def margin_difference(
    a: list[Outcome], b: list[Outcome], boot: int, rng: np.random.Generator
) -> dict | None:
    """Mean friction-margin difference B - A on the pairs both grasped with a margin, with its
    paired bootstrap 95 % interval; None when there is no such pair."""
    d = np.array(
        [
            mb - ma
            for (sa, ma), (sb, mb) in zip(a, b, strict=True)
            if sa and sb and ma is not None and mb is not None
        ]
    )
    if d.size == 0:
        return None
    means = bootstrap_means(d, boot, rng)
    lo, hi = np.percentile(means, [2.5, 97.5])
    return {
        "pairs": int(d.size),
        "difference": float(d.mean()),
        "bootstrap_low": float(lo),
        "bootstrap_high": float(hi),
    }


def risk_coverage(confidence: Sequence[float | None], success: Sequence[bool]) -> dict | None:
    """Success among the grasps attempted when the robot attempts only the estimates at or
    above each confidence threshold (the selective-prediction risk-coverage curve, read as
    success rather than risk).

    An episode without a confidence (no estimate, or an estimator that did not say) is never
    attempted, so the curve ends at the share of episodes with one. Thresholds are the distinct
    confidences, highest first; ties are attempted together.

    Args:
        confidence: per episode, the estimate's confidence or None.
        success: per episode, whether the grasp held.

    Returns:
        None when no episode has a confidence; else ``coverage`` (attempted / all episodes),
        ``success`` (held / attempted) and ``threshold`` per point, highest threshold first,
        and ``area``: the mean success over the attempted episodes ranked by confidence, the
        area under success against coverage scaled to the covered share (1 when every attempt
        up to full coverage held; for a confidence that says nothing, about the success rate).

    Raises:
        InvalidArgumentError: the two sequences differ in length.
    """
    if len(confidence) != len(success):
        raise InvalidArgumentError(
            f"risk_coverage: {len(confidence)} confidences for {len(success)} episodes"
        )
    pairs = [(float(c), bool(s)) for c, s in zip(confidence, success, strict=True) if c is not None]
    if not pairs:
        return None
    n = len(confidence)
    conf, cum, ends, area = _ranked(
        np.array([c for c, _ in pairs]), np.array([s for _, s in pairs], dtype=float)
    )
    attempted = ends + 1
    return {
        "threshold": conf[ends].tolist(),
        "coverage": (attempted / n).tolist(),
        "success": (cum[ends] / attempted).tolist(),
        "area": area,
    }


def _ranked(conf: np.ndarray, held: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The attempted episodes of `risk_coverage` (confidences and successes, (N,) each) ranked
    by confidence, highest first: their confidences (N,), the running count of successes (N,),
    the last index of each run of equal confidences, and the area."""
    order = np.argsort(-conf, kind="stable")
    conf, held = conf[order], held[order]
    cum = np.cumsum(held)
    # The last index of each run of equal confidences: a threshold attempts the whole run.
    ends = np.flatnonzero(np.append(conf[1:] != conf[:-1], True))
    # Each attempted episode counts the success rate of the threshold that first attempts it.
    group_end = ends[np.searchsorted(ends, np.arange(len(conf)))]
    return conf, cum, ends, float(np.mean(cum[group_end] / (group_end + 1)))


def _area_or_nan(conf: np.ndarray, held: np.ndarray) -> float:
    """`risk_coverage`'s area of episodes whose confidence is NaN where they have none (N,);
    NaN when none has one."""
    ok = ~np.isnan(conf)
    return _ranked(conf[ok], held[ok])[3] if ok.any() else float("nan")


def paired_area_difference(
    confidence_a: Sequence[float | None],
    success_a: Sequence[bool],
    confidence_b: Sequence[float | None],
    success_b: Sequence[bool],
    boot: int,
    rng: np.random.Generator,
) -> dict:
    """The risk-coverage areas (`risk_coverage`) of A and B on the same episodes and their
    difference B - A, with its paired bootstrap 95 % interval: the episodes are resampled
    with replacement and both areas computed on each resample (a resample in which either side
    has no confidence is left out).

    Args:
        confidence_a: per episode, A's confidence or None; (N,) like the others.
        success_a: per episode, whether A's grasp held.
        confidence_b: B's confidences, the episodes in the same order.
        success_b: B's successes.
        boot: bootstrap resamples.
        rng: the resampling's generator.

    Returns:
        ``episodes``, ``a`` and ``b`` (each None when that side has no confidence), and
        ``difference``, ``bootstrap_low`` and ``bootstrap_high`` (None unless both have one).

    Raises:
        InvalidArgumentError: sequences of different lengths.
    """
    n = len(confidence_a)
    if not n == len(success_a) == len(confidence_b) == len(success_b):
        raise InvalidArgumentError(
            f"paired_area_difference: {len(confidence_a)}, {len(success_a)}, "
            f"{len(confidence_b)} and {len(success_b)} values; pair the same episodes"
        )
    ra, rb = risk_coverage(confidence_a, success_a), risk_coverage(confidence_b, success_b)
    out: dict = {
        "episodes": n,
        "a": None if ra is None else ra["area"],
        "b": None if rb is None else rb["area"],
        "difference": None,
        "bootstrap_low": None,
        "bootstrap_high": None,
    }
    if ra is None or rb is None:
        return out

    def arrays(conf: Sequence[float | None], held: Sequence[bool]) -> tuple[np.ndarray, ...]:
        c = np.array([np.nan if v is None else float(v) for v in conf])
        return c, np.array(held, dtype=float)

    (ca, ha), (cb, hb) = arrays(confidence_a, success_a), arrays(confidence_b, success_b)
    idx = rng.integers(0, n, size=(boot, n))
    d = np.array([_area_or_nan(cb[i], hb[i]) - _area_or_nan(ca[i], ha[i]) for i in idx])
    out["difference"] = rb["area"] - ra["area"]
    d = d[~np.isnan(d)]
    if d.size:
        out["bootstrap_low"], out["bootstrap_high"] = (
            float(v) for v in np.percentile(d, [2.5, 97.5])
        )
    return out
