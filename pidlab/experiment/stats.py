"""Statistics over seeds in the style of rliable (Agarwal et al., NeurIPS 2021).

- :func:`iqm`: interquartile mean, the mean of the middle 50 % of runs (robust to a few
  outlying seeds, more efficient than the median).
- :func:`bootstrap_ci`: stratified bootstrap confidence interval of any statistic: the runs of
  each task (environment) are resampled with replacement within that task, the statistic is
  taken over the pooled resample, and the interval is the percentile interval.
- :func:`probability_of_improvement`: P(X > Y), the probability that a run of condition X beats
  a run of condition Y on a task (ties count half), averaged over tasks, with a stratified
  bootstrap interval.

Everything is deterministic for a given ``seed``.
"""

from __future__ import annotations

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
