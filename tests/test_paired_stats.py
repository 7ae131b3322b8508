"""The paired tests of the leaderboard (`sim.evaluation.stats`): McNemar's exact test of paired
successes and the Wilcoxon signed-rank test of paired placement errors with failures ranked
worst, against hand computations and scipy."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import binomtest, wilcoxon

from posegrasp.core.errors import InvalidArgumentError
from sim.evaluation.stats import mcnemar_paired, wilcoxon_worst_ranked

INF = math.inf


def test_mcnemar_paired_counts_only_the_discordant_pairs() -> None:
    # 1 pair only A won, 6 only B won, 3 both, 2 neither: p = 2 (C(7,0) + C(7,1)) / 2^7.
    a = [True] * 1 + [False] * 6 + [True] * 3 + [False] * 2
    b = [False] * 1 + [True] * 6 + [True] * 3 + [False] * 2
    m = mcnemar_paired(a, b)
    assert (m["episodes"], m["a"], m["b"], m["a_only"], m["b_only"]) == (12, 4, 9, 1, 6)
    assert m["p"] == pytest.approx(2 * (1 + 7) / 128)
    assert m["p"] == pytest.approx(binomtest(1, 7, 0.5).pvalue)
    assert mcnemar_paired(b, a)["p"] == pytest.approx(m["p"])  # two-sided: symmetric


def test_mcnemar_paired_without_a_discordant_pair_is_one() -> None:
    assert mcnemar_paired([True, False], [True, False])["p"] == 1.0
    assert mcnemar_paired([], [])["p"] == 1.0
    with pytest.raises(InvalidArgumentError, match="pair the same episodes"):
        mcnemar_paired([True], [True, False])


def test_wilcoxon_on_finite_errors_is_scipys() -> None:
    rng = np.random.default_rng(3)
    a, b = rng.gamma(2.0, 0.01, 15), rng.gamma(2.0, 0.012, 15)
    w = wilcoxon_worst_ranked(a, b)
    ref = wilcoxon(a - b)
    assert w["p"] == pytest.approx(ref.pvalue)
    assert min(w["r_plus"], w["r_minus"]) == pytest.approx(ref.statistic)
    assert w["r_plus"] + w["r_minus"] == pytest.approx(15 * 16 / 2)


def test_wilcoxon_by_hand() -> None:
    # Six pairs all A's way: R- = 1 + ... + 6 = 21, exact two-sided p = 2 / 2^6.
    w = wilcoxon_worst_ranked([0.01] * 6, [0.02, 0.03, 0.04, 0.05, 0.06, 0.07])
    assert (w["ranked"], w["r_plus"], w["r_minus"]) == (6, 0.0, 21.0)
    assert w["p"] == pytest.approx(2 / 64)


def test_a_failure_ranks_worst_and_two_failures_tie() -> None:
    """A never lifted on pair 1, B on pair 2: both differences share the top ranks (2 and 3,
    2.5 each), signed against the side that failed; pair 3 differs by 0.5 (rank 1); pair 4
    failed on both sides, a tie left out."""
    a = [INF, 1.0, 2.0, INF]
    b = [0.5, INF, 1.5, INF]
    w = wilcoxon_worst_ranked(a, b)
    assert (w["episodes"], w["ranked"]) == (4, 3)
    assert (w["r_plus"], w["r_minus"]) == (2.5 + 1.0, 2.5)
    assert w["p"] == pytest.approx(wilcoxon([10.0, -10.0, 0.5]).pvalue)
    # Never lifting loses to any placement, however far off.
    w = wilcoxon_worst_ranked([5.0, 9.0, 0.1, 7.0, 3.0, 2.0], [INF] * 6)
    assert (w["r_plus"], w["r_minus"]) == (0.0, 21.0)
    assert w["p"] == pytest.approx(2 / 64)
    both = wilcoxon_worst_ranked([INF, INF], [INF, INF])
    assert (both["ranked"], both["p"]) == (0, 1.0)


def test_wilcoxon_refuses_what_is_not_an_error() -> None:
    with pytest.raises(InvalidArgumentError, match=r"\+inf"):
        wilcoxon_worst_ranked([float("nan")], [1.0])
    with pytest.raises(InvalidArgumentError, match=r"\+inf"):
        wilcoxon_worst_ranked([-INF], [1.0])
    with pytest.raises(InvalidArgumentError, match="pair the same episodes"):
        wilcoxon_worst_ranked([1.0], [1.0, 2.0])
