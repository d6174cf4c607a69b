"""95 % intervals over seeds for the experiments' tables: a Student-t interval of a mean (Wilson's score
interval for one seed's success rate), and for the difference of two arms' means (A − B) a percentile
bootstrap over seeds and Welch's t interval; for two fractions of seeds (e.g. the seeds that lift), Fisher's
exact test.

The paper (Sec. IV) reports means and standard deviations over runs without intervals; these say how
far our few seeds (5 a run) pin a figure or a difference down. All are pure functions of their inputs:
the bootstrap draws from a numpy Generator of a fixed seed.
"""

from __future__ import annotations

import math
import warnings
from typing import Sequence

import numpy as np

LEVEL = 0.95
RESAMPLES = 10_000
Z95 = 1.959963984540054  # the standard normal's 97.5th percentile
BOOTSTRAP_SEED = 0


def _sample(values: np.ndarray, name: str) -> np.ndarray:
    values = np.asarray(values, np.float64)
    if values.ndim != 1 or values.size == 0 or not np.isfinite(values).all():
        raise ValueError(f"{name}: expected a non-empty 1-D array of finite values, got shape {values.shape}")
    return values


def student_interval(values: np.ndarray) -> tuple[float, float, float]:
    """(mean, low, high): the 95 % Student-t interval of the mean of `values` [S]; (mean, nan, nan) for one value."""
    from scipy import stats

    values = _sample(values, "values")
    mean = float(values.mean())
    if values.size < 2:
        return mean, math.nan, math.nan
    half = stats.t.ppf(0.5 + LEVEL / 2, values.size - 1) * values.std(ddof=1) / math.sqrt(values.size)
    return mean, float(mean - half), float(mean + half)


def wilson_interval(successes: int, n: int) -> tuple[float, float]:
    """95 % Wilson score interval of a binomial success rate."""
    p = successes / n
    centre = (p + Z95**2 / (2 * n)) / (1 + Z95**2 / n)
    half = Z95 * math.sqrt(p * (1 - p) / n + Z95**2 / (4 * n * n)) / (1 + Z95**2 / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def rate_interval(rates: np.ndarray) -> tuple[float, float, float]:
    """(mean, low, high): `student_interval` of success rates [S] clipped to [0, 1], the range of a rate (over a
    few seeds near 0 or 1 the t interval would leave it, e.g. 0.8 over rates 1, 1, 1, 1, 0: 0.245-1.355)."""
    mean, low, high = student_interval(rates)
    low, high = np.clip([low, high], 0.0, 1.0)  # nan (one value) stays nan
    return mean, float(low), float(high)


def mean_interval(success: np.ndarray) -> tuple[float, float, float]:
    """(mean, low, high) of the seeds' success rates [S, N]: Student-t over seeds (`rate_interval`), or Wilson for
    one seed."""
    rates = success.mean(axis=1)
    if len(rates) == 1:
        return (float(rates[0]), *wilson_interval(int(success.sum()), success.size))
    return rate_interval(rates)


def bootstrap_difference(a: Sequence[np.ndarray], b: Sequence[np.ndarray], resamples: int = RESAMPLES,
                         seed: int = BOOTSTRAP_SEED) -> tuple[float, float, float]:
    """(difference, low, high) of mean(A) − mean(B), each arm's statistic the mean over its groups
    (e.g. tasks; one group for one run) of the group's mean over seeds; the 95 % percentile interval of
    `resamples` bootstrap replicates that resample the seeds of every group with replacement."""
    if not a or not b:
        raise ValueError("bootstrap_difference: each arm needs at least one group of seeds")
    a = [_sample(group, f"arm A, group {i}") for i, group in enumerate(a)]
    b = [_sample(group, f"arm B, group {i}") for i, group in enumerate(b)]
    rng = np.random.default_rng(seed)

    def replicates(groups: Sequence[np.ndarray]) -> np.ndarray:
        return np.mean([g[rng.integers(0, g.size, (resamples, g.size))].mean(axis=1) for g in groups], axis=0)

    point = float(np.mean([g.mean() for g in a]) - np.mean([g.mean() for g in b]))
    low, high = np.percentile(replicates(a) - replicates(b), [50 * (1 - LEVEL), 50 * (1 + LEVEL)])
    return point, float(low), float(high)


def welch_interval(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float]:
    """(difference, low, high) of mean(a) − mean(b) with Welch's 95 % t interval (scipy.stats); the
    interval is (nan, nan) when an arm has one seed or neither arm varies."""
    from scipy import stats

    a, b = _sample(a, "a"), _sample(b, "b")
    point = float(a.mean() - b.mean())
    flat_a, flat_b = np.ptp(a) == 0, np.ptp(b) == 0
    if min(a.size, b.size) < 2 or (flat_a and flat_b):
        return point, math.nan, math.nan
    with warnings.catch_warnings():
        if flat_a or flat_b:
            # an arm without spread (e.g. every seed censored at its run's env steps) has variance exactly 0;
            # scipy calls that a loss of precision, but the interval is then the other arm's, and exact
            warnings.filterwarnings("ignore", "Precision loss occurred", RuntimeWarning)
        low, high = stats.ttest_ind(a, b, equal_var=False).confidence_interval(LEVEL)
    return point, float(low), float(high)


def fisher_p(hits_a: int, n_a: int, hits_b: int, n_b: int) -> float:
    """Two-sided p-value of Fisher's exact test that two arms' success fractions (hits of n, e.g. seeds that
    learn a skill) are equal: exact for the few seeds of a run, where a normal approximation is not."""
    from scipy import stats

    if not (0 <= hits_a <= n_a and 0 <= hits_b <= n_b and min(n_a, n_b) >= 1):
        raise ValueError(f"fisher_p: expected 0 <= hits <= n and n >= 1, got {hits_a}/{n_a} and {hits_b}/{n_b}")
    return float(stats.fisher_exact([[hits_a, n_a - hits_a], [hits_b, n_b - hits_b]]).pvalue)


def interval_text(low: float, high: float, digits: int = 3) -> str:
    """"[low, high]", or "—" for an undefined interval."""
    if math.isnan(low) or math.isnan(high):
        return "—"
    return f"[{low:,.{digits}f}, {high:,.{digits}f}]"
