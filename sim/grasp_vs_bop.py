"""What BOP scores say about grasps: how pose errors and AR relate to grasp success.

Pure functions over `sim.evaluate` episodes and leaderboard cells (`sim.leaderboard`):

- `separation_auc`: how well one pose error separates the grasps that held from those that did
  not (the area under the ROC curve of "fails when the error is large", Mann-Whitney);
- `spearman_with_interval`: Spearman's rank correlation of AR against grasp success over cells,
  with a percentile bootstrap interval over the cells;
- `ar_for_success`: the AR at which a logistic fit of grasp success on AR reaches a target
  success (e.g. 95 %), per tier.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from scipy.optimize import minimize
from scipy.stats import rankdata, spearmanr

from posegrasp.core.errors import InvalidArgumentError

#: The per-episode errors whose separation of success from failure is measured: name -> how to
#: read it from an episode (None when the episode has no estimate or lacks that error).
EPISODE_ERRORS: dict[str, Callable[[dict], float | None]] = {
    "MSSD": lambda e: _pose(e, "mssd_rel_diameter"),
    "MSPD": lambda e: _pose(e, "mspd_px"),
    "VSD": lambda e: None if e.get("vsd") is None else float(np.mean(e["vsd"])),
    "ADD-S": lambda e: _pose(e, "adi_m"),
    "along-ray": lambda e: _abs(_pose(e, "ray_m")),
    "across-ray": lambda e: _abs(_pose(e, "lateral_m")),
    "rotation": lambda e: _pose(e, "rotation_deg"),
}


def _pose(episode: dict, key: str) -> float | None:
    err = episode.get("pose_error")
    return None if not err or err.get(key) is None else float(err[key])


def _abs(v: float | None) -> float | None:
    return None if v is None else abs(v)


def separation_auc(errors: Sequence[float], success: Sequence[bool]) -> float | None:
    """The probability that a failed grasp's error exceeds a held grasp's (ties count half):
    1 when the error separates them perfectly, 0.5 when it says nothing.

    Args:
        errors: per episode, the pose error (larger is worse).
        success: per episode, whether the grasp held.

    Returns:
        The AUC, or None when either class is empty.

    Raises:
        InvalidArgumentError: the sequences differ in length.
    """
    if len(errors) != len(success):
        raise InvalidArgumentError(f"{len(errors)} errors for {len(success)} episodes")
    err = np.asarray(errors, float)
    held = np.asarray(success, bool)
    n_fail, n_held = int((~held).sum()), int(held.sum())
    if n_fail == 0 or n_held == 0:
        return None
    ranks = rankdata(err)
    # Mann-Whitney U of the failed episodes' errors against the held ones'.
    u = ranks[~held].sum() - n_fail * (n_fail + 1) / 2
    return float(u / (n_fail * n_held))


def episode_aucs(episodes: Sequence[dict]) -> dict[str, dict]:
    """`separation_auc` of each of `EPISODE_ERRORS` over the episodes that have it.

    Returns:
        error name -> ``{"auc": float | None, "episodes": n}``.
    """
    out = {}
    for name, read in EPISODE_ERRORS.items():
        pairs = [(v, bool(e["success"])) for e in episodes if (v := read(e)) is not None]
        auc = separation_auc([v for v, _ in pairs], [s for _, s in pairs]) if pairs else None
        out[name] = {"auc": auc, "episodes": len(pairs)}
    return out


def spearman_with_interval(
    x: Sequence[float], y: Sequence[float], boot: int = 2000, seed: int = 0
) -> dict[str, float | int | None]:
    """Spearman's rank correlation of x and y with a 95 % percentile bootstrap interval over the
    pairs (resamples whose ranks are constant are skipped).

    Returns:
        ``rho``, ``low``, ``high`` (None with fewer than 3 pairs or a constant side) and ``n``.
    """
    xa, ya = np.asarray(x, float), np.asarray(y, float)
    n = len(xa)
    none: dict[str, float | int | None] = {"rho": None, "low": None, "high": None, "n": n}
    if n < 3 or np.ptp(xa) == 0 or np.ptp(ya) == 0:
        return none
    rho = float(spearmanr(xa, ya).statistic)
    rng = np.random.default_rng(seed)
    draws = []
    for _ in range(boot):
        i = rng.integers(0, n, n)
        if np.ptp(xa[i]) > 0 and np.ptp(ya[i]) > 0:
            draws.append(spearmanr(xa[i], ya[i]).statistic)
    if not draws:
        return {**none, "rho": rho}
    low, high = np.percentile(draws, [2.5, 97.5])
    return {"rho": rho, "low": float(low), "high": float(high), "n": n}


def logistic_fit(ar: Sequence[float], successes: Sequence[int], episodes: Sequence[int]):
    """Maximum-likelihood fit of ``P(success) = 1 / (1 + exp(-(a + b * AR)))`` to binomial
    counts per cell. Returns (a, b)."""
    x = np.asarray(ar, float)
    k = np.asarray(successes, float)
    n = np.asarray(episodes, float)

    def nll(p: np.ndarray) -> float:
        z = p[0] + p[1] * x
        # -log-likelihood of k successes in n, written stably: log(1 + e^z) = logaddexp(0, z)
        return float(np.sum(n * np.logaddexp(0.0, z) - k * z))

    res = minimize(nll, np.zeros(2), method="Nelder-Mead", options={"xatol": 1e-8, "fatol": 1e-10})
    return float(res.x[0]), float(res.x[1])


def ar_for_success(
    ar: Sequence[float], successes: Sequence[int], episodes: Sequence[int], target: float = 0.95
) -> dict[str, float | str | None]:
    """The AR at which the logistic fit of success on AR over cells reaches `target`.

    Returns:
        ``ar`` (None when the fit does not reach the target within AR 0..1, or success does not
        rise with AR), ``a``, ``b`` (the fit) and ``note`` saying why there is no AR.
    """
    if len(ar) < 3 or np.ptp(np.asarray(ar, float)) == 0:
        return {"ar": None, "a": None, "b": None, "note": "fewer than 3 cells of distinct AR"}
    a, b = logistic_fit(ar, successes, episodes)
    if b <= 0:
        return {"ar": None, "a": a, "b": b, "note": "success does not rise with AR here"}
    need = (np.log(target / (1 - target)) - a) / b
    if not 0.0 <= need <= 1.0:
        note = (
            f"the fit stays below {target:.0%} up to AR 1"
            if need > 1
            else f"the fit is above {target:.0%} at every AR"
        )
        return {"ar": None, "a": a, "b": b, "note": note}
    return {"ar": float(need), "a": a, "b": b, "note": ""}
