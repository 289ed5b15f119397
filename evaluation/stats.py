"""Paired tests and statistical power for the benchmark's success rates.

Every method of a run faces the same seeded episodes, so two methods' successes are *paired* binary outcomes:

* :func:`mcnemar_exact` — the exact McNemar test on the discordant pairs (one method succeeds, the other fails);
* :func:`mcnemar_power` — the exact power of that test for ``n`` pairs, a discordant fraction ``psi`` and an SR
  difference ``delta`` (summed over the binomial distributions, no normal approximation: at N = 75 the exact
  test is conservative, and Connor's 1987 formula overstates its power by ~3–5 points);
* :func:`detectable_difference` — the smallest SR difference detected with probability ``power`` (80 %) at
  level ``alpha`` (5 %), for ``n`` pairs whose discordant fraction is ``psi``;
* :func:`max_discordance` and :func:`pairs_needed` — the same relation solved for ψ and for ``n`` (sizing a run);
* :func:`pooled_mcnemar` — the test over several cells' pairs at once (pairs are independent across cells).

The discordant proportion is the unknown that decides power: two policies that fail on the same episodes
(ψ small) are told apart by fewer pairs than two that fail on different ones. The report uses the observed ψ of
each comparison, and states a planning ψ for the sizing of the default run.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.stats import binom, binomtest, norm


def mcnemar_exact(a: Sequence[float], b: Sequence[float]) -> dict[str, float]:
    """Exact McNemar test for paired binary outcomes: ``a_only`` (a succeeds, b fails), ``b_only``, two-sided p,
    ``n`` pairs, ``sr_diff`` = mean(a) - mean(b), ``discordant`` = the discordant proportion ψ."""
    x, y = np.asarray(a) > 0.5, np.asarray(b) > 0.5
    if x.shape != y.shape:
        raise ValueError(f"mcnemar_exact needs equally long inputs, got {x.size} and {y.size}")
    a_only, b_only = int(np.sum(x & ~y)), int(np.sum(~x & y))
    p = float(binomtest(a_only, a_only + b_only, 0.5).pvalue) if a_only + b_only else math.nan
    n = int(x.size)
    return {"a_only": a_only, "b_only": b_only, "p_value": p, "n": n,
            "sr_diff": float(x.mean() - y.mean()) if n else math.nan,
            "discordant": (a_only + b_only) / n if n else math.nan}


def _check(alpha: float, power: float) -> None:
    if not (0 < alpha < 1 and 0 < power < 1):
        raise ValueError(f"expected 0 < alpha < 1 and 0 < power < 1, got {alpha}, {power}")


def mcnemar_power(n: int, psi: float, delta: float, alpha: float = 0.05) -> float:
    """Exact power of :func:`mcnemar_exact` (two-sided, level ``alpha``) on ``n`` pairs when a fraction ``psi``
    is discordant and the SR difference is ``delta`` (so one method alone succeeds on (ψ+δ)/2 of the pairs, the
    other on (ψ−δ)/2): the number of discordant pairs D ~ Bin(n, ψ), the first method's share of them
    ~ Bin(D, (ψ+δ)/2ψ), and the test rejects when that share is in the exact binomial test's tails."""
    _check(alpha, 0.5)
    d_abs = abs(delta)
    if n <= 0 or not 0 < psi <= 1 or d_abs > psi:
        return 0.0
    d = np.arange(n + 1)
    p_d = binom.pmf(d, n, psi)
    # c_d: the largest count whose two-sided exact p (2 P(X <= c), X ~ Bin(d, 1/2)) is <= alpha; -1 when none
    c = binom.ppf(alpha / 2, d, 0.5).astype(int)
    c = np.where(2 * binom.cdf(c, d, 0.5) <= alpha, c, c - 1)
    q = (psi + d_abs) / (2 * psi)
    reject = binom.cdf(c, d, q) + binom.sf(d - c - 1, d, q) * (c >= 0)
    reject = np.where(c >= 0, np.minimum(reject, 1.0), 0.0)
    return float(np.sum(p_d * reject))


def detectable_difference(n: int, psi: float, alpha: float = 0.05, power: float = 0.8) -> float:
    """The smallest SR difference that :func:`mcnemar_exact` on ``n`` pairs detects with ``power`` at level
    ``alpha`` when a fraction ``psi`` of the pairs is discordant (exact, :func:`mcnemar_power`); nan without pairs
    or discordance (nothing to compare), inf when even δ = ψ (every discordant pair one way) is not detected."""
    _check(alpha, power)
    if n <= 0 or not psi > 0 or not math.isfinite(psi):
        return math.nan
    psi = min(float(psi), 1.0)
    if mcnemar_power(n, psi, psi, alpha) < power:
        return math.inf
    lo, hi = 0.0, psi
    for _ in range(40):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if mcnemar_power(n, psi, mid, alpha) < power else (lo, mid)
    return hi


def max_discordance(n: int, delta: float, alpha: float = 0.05, power: float = 0.8) -> float:
    """The largest discordant fraction ψ at which ``n`` pairs still detect an SR difference ``delta`` with
    ``power`` (0 when none does): more disagreement between two methods means more noise around the same δ."""
    _check(alpha, power)
    lo, hi = abs(delta), 1.0
    if mcnemar_power(n, hi, delta, alpha) >= power:
        return 1.0
    if mcnemar_power(n, lo, delta, alpha) < power:
        return 0.0
    for _ in range(40):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if mcnemar_power(n, mid, delta, alpha) >= power else (lo, mid)
    return lo


def pairs_needed(delta: float, psi: float, alpha: float = 0.05, power: float = 0.8) -> int:
    """The fewest pairs from which on :func:`mcnemar_exact` detects ``delta`` with ``power`` at discordance
    ``psi`` (exact; starts from Connor's 1987 normal approximation); raises ValueError when |δ| > ψ."""
    _check(alpha, power)
    if not 0 < abs(delta) <= psi <= 1:
        raise ValueError(f"expected 0 < |delta| <= psi <= 1, got delta {delta}, psi {psi}")
    za, zb = float(norm.ppf(1 - alpha / 2)), float(norm.ppf(power))
    n = max(1, int((za * math.sqrt(psi) + zb * math.sqrt(psi - delta * delta)) ** 2 / delta ** 2 * 0.8))
    while mcnemar_power(n, psi, delta, alpha) < power or mcnemar_power(n + 1, psi, delta, alpha) < power:
        n += 1  # exact power saw-tooths in n: the first n from which on two in a row reach it
    return n


def pooled_mcnemar(pairs: Sequence[tuple[Sequence[float], Sequence[float]]]) -> dict[str, float]:
    """:func:`mcnemar_exact` over the concatenated pairs of several cells (independent episodes)."""
    a = [v for x, _ in pairs for v in x]
    b = [v for _, y in pairs for v in y]
    return mcnemar_exact(a, b)
