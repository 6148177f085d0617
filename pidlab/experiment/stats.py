"""Statistics over seeds in the style of rliable (Agarwal et al., NeurIPS 2021).

- :func:`iqm`: interquartile mean, the mean of the middle 50 % of runs (robust to a few
  outlying seeds, more efficient than the median).
- :func:`bootstrap_ci`: stratified bootstrap confidence interval of any statistic: the runs of
  each task (environment) are resampled with replacement within that task, the statistic is
  taken over the pooled resample, and the interval is the percentile interval.
- :func:`probability_of_improvement`: P(X > Y), the probability that a run of condition X beats
  a run of condition Y on a task (ties count half), averaged over tasks, with a stratified
  bootstrap interval.
- :func:`mann_whitney_interval`: a score-type interval for the Mann-Whitney probability
  P(X > Y) + P(X = Y)/2 of two samples (Newcombe 2006, method 5), which stays honest under
  complete separation, where the percentile bootstrap collapses to [1, 1] or [0, 0].
- :func:`probability_with_interval`: P(X > Y) of two samples with :func:`mann_whitney_interval`.
- :func:`median_saving`: the saving 1 - median(X) / median(Y) with a percentile bootstrap
  interval that stays unbounded where runs that never reached a target (+inf) decide it.
- :func:`rank_sum_test`: the exact two-sided Wilcoxon-Mann-Whitney permutation test of two
  independent samples of one task, valid with ties and with infinite values (never reached).
- :func:`smallest_p_value`: the smallest p-value that test can reach with ``n`` and ``m`` runs.
- :func:`holm`: Holm-Bonferroni adjusted p-values for a family of tests.
- :func:`detectable_improvement`: the smallest P(X > Y) the exact test detects with a given
  power (normal location-shift model, Monte Carlo).

Everything is deterministic for a given ``seed``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

Statistic = Callable[..., Any]


@dataclass(frozen=True)
class Estimate:
    """A point estimate with its confidence interval ``[low, high]``."""

    value: float
    low: float
    high: float
    level: float = 0.95


def iqm(values: Sequence[float] | np.ndarray, axis: int | None = None) -> Any:
    """Interquartile mean: the mean of the values between the 25th and 75th percentile.

    Trims ``floor(0.25 n)`` values from each end, as ``scipy.stats.trim_mean(x, 0.25)``.
    ``+inf`` (a run that never reached a target) sorts last: with more than a quarter of the
    runs at ``+inf`` the IQM is ``+inf``.

    Parameters
    ----------
    values : array_like
    axis : int, optional
        Along which axis (default: over all values, returning a float).

    Examples
    --------
    >>> iqm([1, 2, 3, 4, 100, 5, 6, 7])
    4.5
    """
    x = np.asarray(values, dtype=float)
    if axis is None:
        x = x.ravel()
        axis = 0
    x = np.sort(np.moveaxis(x, axis, -1), axis=-1)
    n = x.shape[-1]
    if n == 0:
        return float("nan") if x.ndim == 1 else np.full(x.shape[:-1], np.nan)
    k = int(0.25 * n)
    mid = x[..., k : n - k]
    with np.errstate(invalid="ignore"):
        out = mid.mean(axis=-1)
    return float(out) if np.ndim(out) == 0 else out


def _tasks(scores: Sequence[Sequence[float]] | np.ndarray) -> list[np.ndarray]:
    tasks = [np.asarray(t, dtype=float).ravel() for t in scores]
    if not tasks or any(t.size == 0 for t in tasks):
        raise ValueError("every task needs at least one run")
    return tasks


def bootstrap_ci(
    scores: Sequence[Sequence[float]] | np.ndarray,
    statistic: Statistic = iqm,
    reps: int = 2000,
    level: float = 0.95,
    seed: int = 0,
) -> Estimate:
    """Stratified bootstrap interval of ``statistic`` over runs grouped by task.

    Parameters
    ----------
    scores : sequence of sequences
        ``scores[t]`` holds the runs (seeds) of task ``t``; tasks may have different run counts.
    statistic : callable
        ``statistic(x, axis=-1)`` of the pooled runs, vectorized over resamples (default :func:`iqm`;
        ``np.mean`` and ``np.median`` work too).
    reps : int
        Bootstrap resamples.
    level : float
        Coverage of the percentile interval.
    seed : int

    Returns
    -------
    Estimate
    """
    tasks = _tasks(scores)
    rng = np.random.default_rng(seed)
    point = float(statistic(np.concatenate(tasks), axis=-1))
    resampled = np.concatenate([t[rng.integers(0, t.size, (reps, t.size))] for t in tasks], axis=1)
    stats = np.asarray(statistic(resampled, axis=-1), dtype=float)
    low, high = _percentiles(stats, level)
    return Estimate(point, low, high, level)


def _percentiles(stats: np.ndarray, level: float) -> tuple[float, float]:
    """Percentile interval; ``+inf`` values (never reached) are kept as the largest."""
    a = (1.0 - level) / 2.0
    s = np.sort(stats)
    idx = np.clip(np.round(np.array([a, 1.0 - a]) * (s.size - 1)).astype(int), 0, s.size - 1)
    return float(s[idx[0]]), float(s[idx[1]])


def _prob_greater(x: np.ndarray, y: np.ndarray) -> Any:
    """P(X > Y) + P(X = Y) / 2 over all pairs (Mann-Whitney U / (n m)), along the last axis.

    Comparisons, not differences, so that infinities (never reached) tie with each other.
    """
    gt = x[..., :, None] > y[..., None, :]
    eq = x[..., :, None] == y[..., None, :]
    return (gt.sum(axis=(-2, -1)) + 0.5 * eq.sum(axis=(-2, -1))) / (x.shape[-1] * y.shape[-1])


def probability_of_improvement(
    x: Sequence[Sequence[float]] | np.ndarray,
    y: Sequence[Sequence[float]] | np.ndarray,
    reps: int = 2000,
    level: float = 0.95,
    seed: int = 0,
) -> Estimate:
    """P(X > Y): how likely a run of X scores higher than a run of Y on the same task.

    Parameters
    ----------
    x, y : sequence of sequences
        Runs per task of the two conditions (same tasks, in the same order). For a metric where
        lower is better (steps to a target), pass the negated values.
    reps, level, seed
        As in :func:`bootstrap_ci`; x and y are resampled independently within each task.

    Returns
    -------
    Estimate
        0.5 means no difference; above 0.5, X tends to beat Y.
    """
    xs, ys = _tasks(x), _tasks(y)
    if len(xs) != len(ys):
        raise ValueError("x and y must have the same tasks")
    point = float(np.mean([_prob_greater(a, b) for a, b in zip(xs, ys, strict=True)]))
    rng = np.random.default_rng(seed)
    per_task = [
        _prob_greater(a[rng.integers(0, a.size, (reps, a.size))], b[rng.integers(0, b.size, (reps, b.size))])
        for a, b in zip(xs, ys, strict=True)
    ]
    low, high = _percentiles(np.mean(per_task, axis=0), level)
    return Estimate(point, low, high, level)


def _newcombe_variance(theta: float, n: int, m: int) -> float:
    """Hanley-McNeil variance of U/(nm) at ``theta``, both sample sizes replaced by their mean.

    ``theta (1 - theta) [1 + k ((1 - theta)/(2 - theta) + theta/(1 + theta))] / (n m)`` with
    ``k = (n + m)/2 - 1`` (Newcombe 2006, Statistics in Medicine 25:559-573, method 5).
    """
    k = (n + m) / 2 - 1
    return theta * (1 - theta) * (1 + k * ((1 - theta) / (2 - theta) + theta / (1 + theta))) / (n * m)


def mann_whitney_interval(theta_hat: float, n: int, m: int, level: float = 0.95) -> tuple[float, float]:
    """Score-type confidence interval for the Mann-Whitney probability of two samples.

    The interval holds the ``theta`` with ``(theta_hat - theta)**2 <= z**2 V(theta)``, where ``V``
    is :func:`_newcombe_variance` and ``z`` the normal quantile of ``level``: the two roots around
    ``theta_hat``. Unlike a percentile bootstrap, it does not collapse when the samples separate
    completely (``theta_hat`` 0 or 1): 10 runs against 10 give [0.80, 1] for ``theta_hat = 1``.

    Parameters
    ----------
    theta_hat : float
        The observed P(X > Y) + P(X = Y)/2 (U / (n m)), in [0, 1].
    n, m : int
        The sizes of the two samples (at least 1 each).
    level : float
        Confidence level in (0, 1).

    Returns
    -------
    (low, high) : tuple of float
        ``low <= theta_hat <= high``, within [0, 1].
    """
    from scipy.optimize import brentq
    from scipy.stats import norm

    if not (0.0 <= theta_hat <= 1.0 and n >= 1 and m >= 1 and 0.0 < level < 1.0):
        got = f"theta_hat {theta_hat}, n {n}, m {m}, level {level}"
        raise ValueError(f"{got}: expected theta_hat in [0, 1], n and m >= 1, level in (0, 1)")
    z2 = float(norm.ppf(0.5 + level / 2)) ** 2

    def excess(theta: float) -> float:
        return (theta_hat - theta) ** 2 - z2 * _newcombe_variance(theta, n, m)

    edge = 1e-12  # V vanishes at 0 and 1: the roots lie strictly inside, or at theta_hat's own edge
    low = high = theta_hat
    if theta_hat > 0.0:
        low = float(brentq(excess, 0.0, max(theta_hat - edge, edge / 2), xtol=1e-12))
    if theta_hat < 1.0:
        high = float(brentq(excess, min(theta_hat + edge, 1 - edge / 2), 1.0, xtol=1e-12))
    return low, high


def probability_with_interval(x: Sequence[float] | np.ndarray, y: Sequence[float] | np.ndarray,
                              level: float = 0.95) -> Estimate:  # fmt: skip
    """P(X > Y) + P(X = Y)/2 of two samples with its score interval (:func:`mann_whitney_interval`).

    Examples
    --------
    >>> e = probability_with_interval([3.0, 4.0], [1.0, 2.0])
    >>> e.value, round(e.low, 3), e.high
    (1.0, 0.43, 1.0)
    """
    a, b = _sample(x, "x"), _sample(y, "y")
    theta = float(_prob_greater(a, b))
    low, high = mann_whitney_interval(theta, a.size, b.size, level)
    return Estimate(theta, low, high, level)


def _saving(mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    """``1 - mx / my`` elementwise, for medians that may be +inf (never reached).

    ``mx`` inf gives -inf; ``my`` inf or ``my <= 0`` gives nan (no saving is defined against a
    baseline that never got there).
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        out = 1.0 - mx / my
    out = np.where(np.isinf(mx) & np.isfinite(my), -np.inf, out)
    return np.where(np.isinf(my) | (my <= 0), np.nan, out)


def median_saving(
    x: Sequence[float] | np.ndarray,
    y: Sequence[float] | np.ndarray,
    reps: int = 10000,
    level: float = 0.95,
    seed: int = 0,
) -> Estimate:
    """The saving ``1 - median(x) / median(y)`` of a lower-is-better measure, with a bootstrap interval.

    ``x`` (coached) and ``y`` (baseline) are resampled independently with replacement; the
    interval takes the resamples' order statistics at ``(1 - level)/2`` and ``(1 + level)/2``
    without interpolation. A resample whose saving is undefined (the baseline's median is +inf)
    counts as -inf for the lower end and +inf for the upper end, so an end that censored runs
    decide prints as unbounded instead of a number the data do not give.

    Returns
    -------
    Estimate
        ``value`` nan when the saving is not defined (the baseline's median is +inf or <= 0);
        ``-inf`` when the coached median is +inf and the baseline's is not.

    Examples
    --------
    >>> median_saving([1.0, 2.0, 3.0], [2.0, 4.0, 6.0]).value
    0.5
    """
    a, b = _sample(x, "x"), _sample(y, "y")
    if reps < 1 or not 0.0 < level < 1.0:
        raise ValueError(f"reps {reps}, level {level}: expected reps >= 1 and level in (0, 1)")
    point = float(_saving(np.median(a)[None], np.median(b)[None])[0])
    rng = np.random.default_rng(seed)
    mx = np.median(a[rng.integers(0, a.size, (reps, a.size))], axis=1)
    my = np.median(b[rng.integers(0, b.size, (reps, b.size))], axis=1)
    s = _saving(mx, my)
    q = (1.0 - level) / 2.0
    low = float(np.quantile(np.where(np.isnan(s), -np.inf, s), q, method="lower"))
    high = float(np.quantile(np.where(np.isnan(s), np.inf, s), 1.0 - q, method="higher"))
    return Estimate(point, low, high, level)


@dataclass(frozen=True)
class RankSumTest:
    """Result of :func:`rank_sum_test`.

    Attributes
    ----------
    u : float
        Mann-Whitney U of x: the number of pairs with x > y, ties counting half.
    p_value : float
        Exact two-sided permutation p-value.
    n, m : int
        Sizes of x and y.
    testable : bool
        False when every pooled value is tied (then ``p_value`` is 1).
    """

    u: float
    p_value: float
    n: int
    m: int
    testable: bool


def _sample(values: Sequence[float] | np.ndarray, name: str) -> np.ndarray:
    x = np.asarray(values, dtype=float).ravel()
    if x.size == 0:
        raise ValueError(f"{name} is empty")
    if np.isnan(x).any():
        raise ValueError(f"{name} contains NaN")
    return x


def _doubled_midranks(pooled: np.ndarray) -> tuple[np.ndarray, int]:
    """Twice the midranks (integers; ties share the average rank) and the number of distinct values.

    Equal values tie, so ``+inf`` ties with ``+inf``.
    """
    _, inverse, counts = np.unique(pooled, return_inverse=True, return_counts=True)
    starts = np.cumsum(counts) - counts
    return (2 * starts + counts + 1)[inverse.ravel()].astype(np.int64), counts.size


def _rank_sum_counts(ranks: np.ndarray, k: int) -> np.ndarray:
    """``counts[s]``: how many subsets of ``k`` of the (non-negative integer) ``ranks`` sum to ``s``.

    Dynamic programming over items; the counts are floats (exact up to 2**53, relative error
    about 1e-16 beyond).
    """
    ranks = np.sort(np.asarray(ranks, dtype=np.int64))
    total = ranks.size
    dp = np.zeros((k + 1, int(ranks.sum()) + 1))  # dp[j, s]: subsets of j items so far summing to s
    dp[0, 0] = 1.0
    reach = 0
    for i, r in enumerate(ranks.tolist()):
        reach += r
        # rows that are reachable after i + 1 items and can still grow to k with the items left
        lo, hi = max(1, k - (total - 1 - i)), min(k, i + 1)
        for j in range(hi, lo - 1, -1):  # downwards, so row j - 1 still holds the old counts
            dp[j, r : reach + 1] += dp[j - 1, : reach + 1 - r]
    return dp[k]


def rank_sum_test(x: Sequence[float] | np.ndarray, y: Sequence[float] | np.ndarray) -> RankSumTest:
    """Exact two-sided Wilcoxon-Mann-Whitney permutation test of two independent samples.

    The values are pooled and given midranks; under the null hypothesis every split of the
    pooled values into ``n`` and ``m`` is equally likely, and the p-value is the exact share of
    the ``C(n + m, n)`` splits whose rank sum of x lies at least as far from its mean as the
    observed one. Ties and infinite values (``+inf``: never reached) are handled exactly.

    Parameters
    ----------
    x, y : array_like
        Runs of the two conditions on one task.

    Returns
    -------
    RankSumTest

    Raises
    ------
    ValueError
        If a sample is empty or contains NaN.

    Examples
    --------
    >>> rank_sum_test([1, 2, 3], [4, 5, 6]).p_value
    0.1
    """
    a, b = _sample(x, "x"), _sample(y, "y")
    n, m = a.size, b.size
    doubled, distinct = _doubled_midranks(np.concatenate([a, b]))
    s_x = int(doubled[:n].sum())
    u = s_x / 2.0 - n * (n + 1) / 2.0
    if distinct == 1:
        return RankSumTest(u, 1.0, n, m, False)
    return RankSumTest(u, _exact_p(doubled, n, s_x), n, m, True)


def _exact_p(doubled: np.ndarray, n: int, s_x: int) -> float:
    """Two-sided p-value of the doubled rank sum ``s_x`` of the first ``n`` of the ``doubled`` midranks."""
    total = doubled.size
    # count subsets of the smaller sample: |S_y - E[S_y]| = |S_x - E[S_x]|
    k, s_obs = (n, s_x) if 2 * n <= total else (total - n, int(doubled.sum()) - s_x)
    g = int(np.gcd.reduce(doubled))
    counts = _rank_sum_counts(doubled // g, k)
    center = k * (total + 1)  # E[doubled rank sum of k items]; the doubled midranks sum to N (N + 1)
    sums = np.arange(counts.size, dtype=np.int64) * g
    extreme = np.abs(sums - center) >= abs(s_obs - center)
    return min(1.0, float(counts[extreme].sum() / counts.sum()))


def smallest_p_value(n: int, m: int) -> float:
    """The smallest two-sided p-value :func:`rank_sum_test` can reach with ``n`` and ``m`` runs.

    Reached by the most extreme split without ties: ``min(1, 2 / C(n + m, n))``.

    Parameters
    ----------
    n, m : int
        Sample sizes (at least 1).

    Returns
    -------
    float

    Examples
    --------
    >>> smallest_p_value(3, 3)
    0.1
    """
    if n < 1 or m < 1:
        raise ValueError("n and m must be at least 1")
    return min(1.0, 2.0 / math.comb(n + m, n))


def holm(p_values: Sequence[float] | np.ndarray) -> tuple[float, ...]:
    """Holm-Bonferroni adjusted p-values (step-down), in the input order.

    With the ``k`` p-values sorted ascending, the ``i``-th (from 0) is adjusted to
    ``max over j <= i of min(1, (k - j) p_(j))``. Rejecting the adjusted p-values at or below
    ``alpha`` controls the family-wise error rate at ``alpha``.

    Parameters
    ----------
    p_values : array_like

    Returns
    -------
    tuple of float

    Examples
    --------
    >>> holm([0.01, 0.04, 0.03, 0.005])
    (0.03, 0.06, 0.06, 0.02)
    """
    p = np.asarray(p_values, dtype=float).ravel()
    if p.size == 0:
        return ()
    if np.isnan(p).any() or (p < 0).any() or (p > 1).any():
        raise ValueError("p-values must lie in [0, 1]")
    order = np.argsort(p, kind="stable")
    scaled = np.minimum(1.0, (p.size - np.arange(p.size)) * p[order])
    adjusted = np.empty_like(p)
    adjusted[order] = np.maximum.accumulate(scaled)
    return tuple(float(v) for v in adjusted)


def _critical_deviation(n: int, m: int, alpha: float) -> int | None:
    """Smallest ``c`` with ``P(|2 S - n (N + 1)| >= c) <= alpha`` under the no-ties null.

    ``S`` is the rank sum of x over the ranks ``1..N``, ``N = n + m``. None when even the most
    extreme split is more likely than ``alpha``.
    """
    total = n + m
    counts = _rank_sum_counts(np.arange(1, total + 1), n)
    possible = counts > 0
    deviation = np.abs(2 * np.arange(counts.size)[possible] - n * (total + 1))
    probs = counts[possible] / counts.sum()
    order = np.argsort(-deviation, kind="stable")
    deviation, tail = deviation[order], np.cumsum(probs[order])
    # the tail P(dev >= d) of a deviation counts every split with an equal deviation
    last_of_value = np.r_[deviation[1:] != deviation[:-1], True]
    ok = last_of_value & (tail <= alpha * (1.0 + 1e-12))
    return int(deviation[ok].min()) if ok.any() else None


def _power(zx: np.ndarray, zy: np.ndarray, delta: float, critical: int) -> float:
    """Share of the draws (rows) that the exact test rejects once x is shifted by ``delta``."""
    n, total = zx.shape[1], zx.shape[1] + zy.shape[1]
    order = np.argsort(np.concatenate([zx + delta, zy], axis=1), axis=1)
    rank_sum = ((order < n) * np.arange(1, total + 1)).sum(axis=1)
    return float(np.mean(np.abs(2 * rank_sum - n * (total + 1)) >= critical))


def detectable_improvement(
    n: int, m: int, alpha: float = 0.05, power: float = 0.8, draws: int = 20000, seed: int = 0
) -> float | None:
    """Smallest P(X > Y) that :func:`rank_sum_test` at level ``alpha`` detects with probability ``power``.

    Under a normal location-shift model, X ~ N(delta, 1) and Y ~ N(0, 1), so
    P(X > Y) = Phi(delta / sqrt(2)). The rejection region comes from the exact no-ties null
    distribution; the power is estimated by Monte Carlo with common random numbers (one fixed
    draw of standard normals, shifted by delta) and delta is found by bisection to about 1e-4.

    Parameters
    ----------
    n, m : int
        Runs of x and y.
    alpha : float
        Two-sided significance level.
    power : float
        Required probability of rejecting.
    draws : int
        Monte Carlo draws.
    seed : int

    Returns
    -------
    float or None
        The detectable P(X > Y), or None when the design cannot reach significance at
        ``alpha`` (``smallest_p_value(n, m) > alpha``).
    """
    if n < 1 or m < 1 or draws < 1:
        raise ValueError("n, m and draws must be at least 1")
    if not (0.0 < alpha < 1.0 and 0.0 < power <= 1.0):
        raise ValueError("alpha must lie in (0, 1) and power in (0, 1]")
    critical = _critical_deviation(n, m, alpha)
    if critical is None:
        return None
    rng = np.random.default_rng(seed)
    zx, zy = rng.standard_normal((draws, n)), rng.standard_normal((draws, m))
    delta = _smallest_shift(lambda d: _power(zx, zy, d, critical) >= power)
    return 0.5 * (1.0 + math.erf(delta / 2.0))  # Phi(delta / sqrt(2))


def _smallest_shift(enough: Callable[[float], bool], tol: float = 1e-4) -> float:
    """Smallest shift ``>= 0`` (to ``tol``) for which ``enough`` holds, by doubling then bisection."""
    lo, hi = 0.0, 1.0
    while not enough(hi) and hi < 1e3:
        lo, hi = hi, 2.0 * hi
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if enough(mid) else (mid, hi)
    return hi
