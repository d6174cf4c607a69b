"""95 % intervals and tests over seeds for the experiments' tables: a Student-t interval of a mean (Wilson's
score interval for one seed's success rate); for the difference of two arms' means (A − B), or of their means over
tasks, Welch's t interval and p-value (`welch_difference`, which says why t and not a bootstrap: it keeps its 95 %
at 5 seeds an arm); Holm's correction where several checks decide one claim (`holm`); for two fractions of seeds
(e.g. the seeds that lift), Fisher's exact test; for one seed's successes against a task's floor, a one-sided
binomial test (`above_p`).

The paper (Sec. IV) reports means and standard deviations over runs without intervals; these say how
far our few seeds (5 a run) pin a figure or a difference down. All are pure functions of their inputs.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import numpy as np

LEVEL = 0.95
Z95 = 1.959963984540054  # the standard normal's 97.5th percentile


def _sample(values: np.ndarray, name: str, batched: bool = False) -> np.ndarray:
    """`values` as float64: a non-empty 1-D array of finite values ([..., S] where `batched`); ValueError else."""
    values = np.asarray(values, np.float64)
    if (values.ndim < 1 if batched else values.ndim != 1) or values.size == 0 or not np.isfinite(values).all():
        raise ValueError(f"{name}: expected a non-empty {'' if batched else '1-D '}array of finite values, got shape "
                         f"{values.shape}")
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


@dataclasses.dataclass(frozen=True)
class Difference:
    """A difference of arms' means with its 95 % Welch interval and two-sided p-value (nan: undefined); arrays of
    the batch shape where `welch_difference` was given batches of samples."""

    point: float | np.ndarray
    low: float | np.ndarray
    high: float | np.ndarray
    p: float | np.ndarray


def welch_difference(a: Sequence[np.ndarray], b: Sequence[np.ndarray],
                     weights: Sequence[float] | None = None) -> Difference:
    """Σ_g w_g (mean(A_g) − mean(B_g)) over groups g (e.g. tasks; one group for one run), each arm's group its
    seeds' values [..., S] (leading batch axes allowed, the same in every group), w_g = 1/G by default (the mean
    over groups; a contrast such as +1 on one task and −1/3 on three others is as valid), with its 95 % Welch t
    interval and two-sided p: variance Σ_g w_g² (s²_Ag/n_Ag + s²_Bg/n_Bg) (s² the seeds' sample variance), degrees
    of freedom by Welch-Satterthwaite over all those terms. Undefined (nan) where a group has one seed or no term
    varies.

    Why a t interval: with 5 seeds an arm, a percentile bootstrap undercovers (its resamples have the spread of
    the population's n − 1 over n, and the normal's quantiles instead of t's with 4 degrees of freedom: about
    87 % where it claims 95), while Welch's interval holds 95 % within a point or two for normal, bounded and
    skewed per-seed figures (success rates near 1, Beta, exponential; tests/experiments/test_stats.py simulates
    it). It does not hold where an arm's seeds split into a rare failing mode (one seed in ten failing), which
    5 seeds cannot show to any method."""
    if not a or not b or len(a) != len(b):
        raise ValueError(f"welch_difference: each arm needs the same number (≥ 1) of groups, got {len(a)} and {len(b)}")
    weights = np.full(len(a), 1.0 / len(a)) if weights is None else np.asarray(weights, np.float64)
    if weights.shape != (len(a),):
        raise ValueError(f"welch_difference: {len(a)} groups but {weights.size} weights")
    groups = [_sample(g, f"arm {arm}, group {i}", batched=True)
              for arm, arms in (("A", a), ("B", b)) for i, g in enumerate(arms)]
    signs = np.concatenate([weights, -weights])
    point = sum(s * g.mean(axis=-1) for s, g in zip(signs, groups))
    # a group without spread adds exactly 0 (its sample variance may round to a speck above it)
    terms = [np.where(np.ptp(g, axis=-1) > 0, s**2 * g.var(axis=-1, ddof=1) / g.shape[-1], 0.0) if g.shape[-1] > 1
             else np.full(g.shape[:-1], np.nan) for s, g in zip(signs, groups)]
    variance = sum(terms)
    from scipy import stats

    with np.errstate(divide="ignore", invalid="ignore"):
        df = variance**2 / sum(t**2 / (g.shape[-1] - 1) for t, g in zip(terms, groups) if g.shape[-1] > 1)
        df = np.where(variance > 0, df, np.nan)
        scale = np.where(variance > 0, np.sqrt(variance), np.nan)
        half = stats.t.ppf(0.5 + LEVEL / 2, df) * scale
        p = 2 * stats.t.sf(np.abs(point) / scale, df)
    shaped = (lambda x: float(x)) if np.ndim(point) == 0 else np.asarray
    return Difference(shaped(point), shaped(point - half), shaped(point + half), shaped(p))


def welch_interval(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float]:
    """(difference, low, high) of mean(a) − mean(b) with Welch's 95 % t interval (`welch_difference` of one
    group); the interval is (nan, nan) when an arm has one seed or neither arm varies."""
    found = welch_difference([_sample(a, "a")], [_sample(b, "b")])
    return found.point, found.low, found.high


def holm(pvalues: Sequence[float]) -> np.ndarray:
    """Holm's step-down adjusted p-values of `pvalues` (nan stays nan and counts as 1): a check rejects at level α
    when its adjusted p is below α, which holds the chance of any false rejection among them at α."""
    p = np.asarray(pvalues, np.float64)
    filled = np.where(np.isnan(p), 1.0, p)
    order = np.argsort(filled)
    adjusted = np.maximum.accumulate((len(p) - np.arange(len(p))) * filled[order])
    out = np.empty_like(filled)
    out[order] = np.minimum(adjusted, 1.0)
    return np.where(np.isnan(p), np.nan, out)


def above_p(successes: int, n: int, floor: float) -> float:
    """One-sided p-value of the binomial test that a policy's success rate is at most `floor`, from `successes`
    of `n` episodes: P(X ≥ successes) for X ~ Binomial(n, floor). Episodes of several epochs of a learning policy
    may pool: where every epoch's rate is at most the floor, their sum is stochastically at most that binomial."""
    if not (0 <= successes <= n and n >= 1 and 0.0 <= floor <= 1.0):
        raise ValueError(f"above_p: expected 0 <= successes <= n, n >= 1, floor in [0, 1]; got {successes}/{n}, "
                         f"floor {floor}")
    from scipy import stats

    return float(stats.binom.sf(successes - 1, n, floor))


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
