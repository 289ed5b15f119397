"""Paired McNemar test and its power: the exact power against a simulation, the detectable difference and the
run sizing solved back and forth."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import binomtest

from evaluation.stats import (
    detectable_difference,
    max_discordance,
    mcnemar_exact,
    mcnemar_power,
    pairs_needed,
    pooled_mcnemar,
)


def test_mcnemar_counts_the_discordant_pairs_and_takes_the_binomial_p():
    a = [1] * 8 + [0] * 1 + [1] * 5 + [0] * 6
    b = [0] * 8 + [1] * 1 + [1] * 5 + [0] * 6
    r = mcnemar_exact(a, b)
    assert (r["a_only"], r["b_only"], r["n"]) == (8, 1, 20)
    assert r["p_value"] == pytest.approx(binomtest(8, 9, 0.5).pvalue) and r["p_value"] < 0.05
    assert r["sr_diff"] == pytest.approx(0.35) and r["discordant"] == pytest.approx(0.45)
    assert math.isnan(mcnemar_exact([1, 0, 1], [1, 0, 1])["p_value"])


@pytest.mark.parametrize("n,psi,delta", [(234, 0.3, 0.1), (75, 0.2, 0.15), (30, 0.1, 0.05)])
def test_exact_power_matches_a_simulation_of_the_test(n, psi, delta):
    rng = np.random.default_rng(0)
    reps = 2000
    hits = 0
    for _ in range(reps):
        u = rng.random(n)
        a10 = int(np.sum(u < (psi + delta) / 2))
        a01 = int(np.sum((u >= (psi + delta) / 2) & (u < psi)))
        hits += a10 + a01 > 0 and binomtest(a10, a10 + a01, 0.5).pvalue < 0.05
    p = mcnemar_power(n, psi, delta)
    se = math.sqrt(p * (1 - p) / reps)
    assert abs(hits / reps - p) < 4 * se + 1e-3, (hits / reps, p)


def test_detectable_difference_is_where_the_power_reaches_80_percent():
    d = detectable_difference(75, 0.2)
    assert 0.1 < d < 0.2
    assert mcnemar_power(75, 0.2, d) >= 0.8 > mcnemar_power(75, 0.2, d - 0.005)
    assert detectable_difference(450, 0.2) < d  # more pairs, smaller detectable difference
    assert detectable_difference(75, 0.4) > d  # more disagreement, larger
    assert math.isnan(detectable_difference(75, 0.0)) and math.isnan(detectable_difference(0, 0.2))
    assert math.isinf(detectable_difference(5, 0.2))  # 1 discordant pair expected: nothing is detectable


def test_run_sizing_solves_the_same_relation():
    n = pairs_needed(0.1, 0.3)
    assert mcnemar_power(n, 0.3, 0.1) >= 0.8 and mcnemar_power(n - 25, 0.3, 0.1) < 0.8
    psi = max_discordance(450, 0.1)  # the default run: 6 cells x 75 pairs
    assert 0.3 < psi < 0.8
    assert mcnemar_power(450, psi, 0.1) >= 0.8 > mcnemar_power(450, psi + 0.02, 0.1)
    with pytest.raises(ValueError):
        pairs_needed(0.3, 0.2)


def test_pooled_test_concatenates_the_cells():
    cells = [([1, 1, 0, 1], [0, 1, 0, 0]), ([1, 0, 1], [1, 0, 0])]
    r = pooled_mcnemar(cells)
    assert (r["a_only"], r["b_only"], r["n"]) == (3, 0, 7)
