"""Exact rank-sum test, Holm adjustment and power analysis of :mod:`pidlab.experiment.stats`."""

from __future__ import annotations

import dataclasses
import itertools
import math
from functools import cache

import numpy as np
import pytest
from scipy.stats import mannwhitneyu

from pidlab.experiment.stats import (
    RankSumTest,
    detectable_improvement,
    holm,
    rank_sum_test,
    smallest_p_value,
)

INF = math.inf


def _u(x: list[float], y: list[float]) -> float:
    """Mann-Whitney U of x by pair comparisons (ties count half; infinities tie)."""
    return sum(1.0 if a > b else 0.5 if a == b else 0.0 for a in x for b in y)


def _brute_force_p(x: list[float], y: list[float]) -> float:
    """Exact two-sided p-value by enumerating every split of the pooled values."""
    pooled = [*x, *y]
    n, m = len(x), len(y)
    center = n * m / 2.0
    observed = abs(_u(x, y) - center)
    hits = total = 0
    for chosen in itertools.combinations(range(n + m), n):
        rest = [pooled[i] for i in range(n + m) if i not in chosen]
        total += 1
        hits += abs(_u([pooled[i] for i in chosen], rest) - center) >= observed - 1e-9
    return hits / total


# --- rank_sum_test -------------------------------------------------------------------------------


def test_separated_samples_hand_computed() -> None:
    low = rank_sum_test([1, 2, 3], [4, 5, 6])
    assert low == RankSumTest(u=0.0, p_value=pytest.approx(0.1, abs=1e-15), n=3, m=3, testable=True)
    high = rank_sum_test([4, 5, 6], [1, 2, 3])
    assert high.u == 9.0
    assert high.p_value == pytest.approx(0.1, abs=1e-15)


def test_five_vs_five_separated() -> None:
    result = rank_sum_test([0, 1, 2, 3, 4], [5, 6, 7, 8, 9])
    assert result.u == 0.0
    assert result.p_value == pytest.approx(2 / 252, rel=1e-12)
    assert (result.n, result.m, result.testable) == (5, 5, True)


def test_identical_samples_give_p_one() -> None:
    assert rank_sum_test([1, 2, 3], [1, 2, 3]).p_value == pytest.approx(1.0)


def test_ties_against_brute_force() -> None:
    x, y = [1.0, 2.0, 2.0], [2.0, 3.0, 4.0]
    result = rank_sum_test(x, y)
    assert result.u == 1.0  # 1 loses to 2, 3, 4; each 2 ties the 2 of y (half) and loses to 3, 4
    assert result.p_value == pytest.approx(_brute_force_p(x, y), rel=1e-12)
    assert result.testable


def test_infinities_tie_with_each_other() -> None:
    x, y = [1.0, INF, INF], [INF, INF, 5.0, -INF]
    result = rank_sum_test(x, y)
    assert result.u == pytest.approx(_u(x, y))
    assert result.p_value == pytest.approx(_brute_force_p(x, y), rel=1e-12)


def test_randomized_against_brute_force() -> None:
    rng = np.random.default_rng(2024)
    values = [0.0, 1.0, 2.0, 3.0, INF, -INF]
    for _ in range(25):
        n, m = rng.integers(1, 7, size=2)
        x = [float(v) for v in rng.choice(values, size=n)]
        y = [float(v) for v in rng.choice(values, size=m)]
        result = rank_sum_test(x, y)
        assert result.u == pytest.approx(_u(x, y))
        if result.testable:
            assert result.p_value == pytest.approx(_brute_force_p(x, y), rel=1e-12)
        else:
            assert result.p_value == 1.0


def test_larger_first_sample_matches_brute_force() -> None:
    x, y = [3.0, 1.0, 4.0, 1.0, 5.0, 9.0], [2.0, 6.0, 5.0]
    assert rank_sum_test(x, y).p_value == pytest.approx(_brute_force_p(x, y), rel=1e-12)
    assert rank_sum_test(x, y).p_value == pytest.approx(rank_sum_test(y, x).p_value, rel=1e-12)


@pytest.mark.parametrize(("n", "m", "shift"), [(4, 7, 0.5), (8, 8, 1.0), (12, 9, 0.0), (20, 25, 0.7)])
def test_agrees_with_scipy_without_ties(n: int, m: int, shift: float) -> None:
    rng = np.random.default_rng(n * 100 + m)
    x, y = rng.normal(shift, 1.0, n), rng.normal(0.0, 1.0, m)
    result = rank_sum_test(x, y)
    reference = mannwhitneyu(x, y, method="exact", alternative="two-sided")
    assert result.u == pytest.approx(reference.statistic)
    assert result.p_value == pytest.approx(reference.pvalue, rel=1e-9)


def test_all_tied_is_not_testable() -> None:
    result = rank_sum_test([INF, INF, INF], [INF, INF])
    assert not result.testable
    assert result.p_value == 1.0
    assert result.u == 3.0  # all 6 pairs tie
    assert not rank_sum_test([2.0], [2.0, 2.0]).testable


def test_single_runs() -> None:
    result = rank_sum_test([1.0], [2.0])
    assert (result.u, result.p_value, result.testable) == (0.0, 1.0, True)


def test_fast_for_a_hundred_runs_each() -> None:
    rng = np.random.default_rng(0)
    x = rng.integers(0, 20, 100).astype(float)
    y = rng.integers(2, 22, 100).astype(float)
    x[:7] = INF
    result = rank_sum_test(x, y)
    assert 0.0 <= result.p_value <= 1.0
    assert result.u == pytest.approx(float((x[:, None] > y).sum() + 0.5 * (x[:, None] == y).sum()))


@pytest.mark.parametrize(
    ("x", "y"), [([], [1.0]), ([1.0], []), ([1.0, math.nan], [2.0]), ([1.0], [math.nan])]
)
def test_bad_samples_raise(x: list[float], y: list[float]) -> None:
    with pytest.raises(ValueError):
        rank_sum_test(x, y)


def test_result_is_frozen() -> None:
    result = rank_sum_test([1, 2], [3, 4])
    with pytest.raises(dataclasses.FrozenInstanceError):
        result.p_value = 0.0  # type: ignore[misc]


# --- smallest_p_value ----------------------------------------------------------------------------


def test_smallest_p_value_hand_computed() -> None:
    assert smallest_p_value(3, 3) == pytest.approx(0.1)
    assert smallest_p_value(5, 5) == pytest.approx(2 / 252)
    assert smallest_p_value(10, 10) == pytest.approx(2 / 184756)
    assert smallest_p_value(1, 1) == 1.0
    assert smallest_p_value(1, 2) == pytest.approx(2 / 3)


def test_smallest_p_value_is_reached_by_the_test() -> None:
    for n, m in [(2, 5), (4, 4), (6, 3)]:
        x = list(range(n))
        y = list(range(n, n + m))
        assert rank_sum_test(x, y).p_value == pytest.approx(smallest_p_value(n, m), rel=1e-12)


def test_smallest_p_value_rejects_empty_designs() -> None:
    with pytest.raises(ValueError):
        smallest_p_value(0, 3)


# --- holm ----------------------------------------------------------------------------------------


def test_holm_hand_computed() -> None:
    assert holm([0.01, 0.04, 0.03, 0.005]) == pytest.approx((0.03, 0.06, 0.06, 0.02))


def test_holm_edge_cases() -> None:
    assert holm([]) == ()
    assert holm([0.2]) == (0.2,)
    assert holm([0.5, 0.6]) == (1.0, 1.0)  # capped at 1
    assert holm(np.array([0.04, 0.01])) == pytest.approx((0.04, 0.02))
    assert isinstance(holm([0.1, 0.2]), tuple)


def test_holm_never_below_raw_and_preserves_order() -> None:
    p = np.random.default_rng(3).uniform(0.0, 0.2, 12)
    adjusted = np.array(holm(p))
    assert (adjusted >= p).all()
    order = np.argsort(p)
    assert (np.diff(adjusted[order]) >= 0).all()


# --- detectable_improvement ----------------------------------------------------------------------


@cache
def _detectable(n: int, m: int) -> float | None:
    return detectable_improvement(n, m)


@pytest.mark.parametrize(("n", "expected"), [(5, 0.95), (10, 0.84), (20, 0.75)])
def test_detectable_improvement_sanity_values(n: int, expected: float) -> None:
    value = _detectable(n, n)
    assert value is not None
    assert value == pytest.approx(expected, abs=0.01)


def test_detectable_improvement_none_when_significance_unreachable() -> None:
    assert smallest_p_value(3, 3) > 0.05
    assert _detectable(3, 3) is None


def test_detectable_improvement_decreases_with_runs() -> None:
    values = [_detectable(n, n) for n in (5, 10, 20)]
    assert all(v is not None for v in values)
    assert values[0] > values[1] > values[2] > 0.5  # type: ignore[operator]


def test_detectable_improvement_is_deterministic() -> None:
    first = detectable_improvement(6, 5, draws=2000, seed=7)
    assert first is not None
    assert detectable_improvement(6, 5, draws=2000, seed=7) == first


def test_detectable_improvement_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError):
        detectable_improvement(0, 5)
    with pytest.raises(ValueError):
        detectable_improvement(5, 5, alpha=0.0)
    with pytest.raises(ValueError):
        detectable_improvement(5, 5, power=1.5)


def test_the_score_interval_of_the_mann_whitney_probability_against_hand_computed_cases():
    from pidlab.experiment.stats import _newcombe_variance, mann_whitney_interval

    # n = m = 10: k = (10 + 10)/2 - 1 = 9. At theta = 0.8:
    # V = 0.8 * 0.2 * (1 + 9 * (0.2/1.2 + 0.8/1.8)) / 100 = 0.16 * 6.5 / 100 = 0.0104
    assert _newcombe_variance(0.8, 10, 10) == pytest.approx(0.0104, rel=1e-12)
    # complete separation: (1 - theta)^2 = 1.959964^2 V(theta); at 0.8 the left side (0.04) still
    # exceeds the right (3.841459 * 0.0104 = 0.039951), so the root lies just above 0.8
    low, high = mann_whitney_interval(1.0, 10, 10)
    assert high == 1.0 and 0.8 < low < 0.801
    assert (1 - low) ** 2 == pytest.approx(1.959963985**2 * _newcombe_variance(low, 10, 10), rel=1e-8)
    # the interval does not collapse, is symmetric under swapping the samples, and holds theta_hat
    assert mann_whitney_interval(0.0, 10, 10) == pytest.approx((0.0, 1 - low))
    for theta, n, m in [(0.5, 10, 10), (0.82, 10, 10), (0.3, 5, 7), (1.0, 3, 3)]:
        lo, hi = mann_whitney_interval(theta, n, m)
        lo2, hi2 = mann_whitney_interval(1 - theta, m, n)
        assert 0 < lo <= theta <= hi <= 1 and hi - lo > 0.1
        assert (lo, hi) == pytest.approx((1 - hi2, 1 - lo2))
    # more seeds, a narrower interval
    assert mann_whitney_interval(1.0, 30, 30)[0] > mann_whitney_interval(1.0, 10, 10)[0]
    with pytest.raises(ValueError):
        mann_whitney_interval(1.2, 10, 10)


def test_probability_with_interval_is_u_over_nm_with_the_score_interval():
    from pidlab.experiment.stats import mann_whitney_interval, probability_with_interval

    x, y = [1.0, 2.0, 3.0, INF], [2.0, 2.0, INF]
    # pairs: 1 loses to 2, 2; ties 2 with 2 twice; 3 beats 2, 2; INF beats 2, 2 and ties INF; 1, 2, 3 lose to INF
    u = 0 + (0.5 + 0.5) + 2 + (2 + 0.5)
    e = probability_with_interval(x, y)
    assert e.value == pytest.approx(u / 12) and e.level == 0.95
    assert (e.low, e.high) == pytest.approx(mann_whitney_interval(u / 12, 4, 3))
    with pytest.raises(ValueError):
        probability_with_interval([], [1.0])


def test_median_saving_hand_computed():
    from pidlab.experiment.stats import median_saving

    # medians 2 and 4: saving 1 - 2/4
    e = median_saving([1.0, 2.0, 3.0], [2.0, 4.0, 6.0], reps=2000)
    assert e.value == 0.5 and e.low <= 0.5 <= e.high
    # every resample of x is at most 3 and of y at least 2, so no resample saves less than 1 - 3/2
    assert e.low >= -0.5 and e.high <= 1 - 1 / 6
    # constant samples: every resample gives the same saving, so the interval is that point
    flat = median_saving([5.0] * 4, [10.0] * 4, reps=500)
    assert (flat.value, flat.low, flat.high) == (0.5, 0.5, 0.5)
    # the same seed gives the same interval
    assert median_saving([1.0, 2.0, 3.0], [2.0, 4.0, 6.0], reps=2000) == e


def test_median_saving_with_runs_that_never_reached():
    from pidlab.experiment.stats import median_saving

    # the coached median never reached: the saving is -inf, and so is the lower end
    e = median_saving([INF, INF, 1.0], [2.0, 2.0, 2.0], reps=500)
    assert e.value == -INF and e.low == -INF
    # the baseline's median never reached: no saving is defined, and both ends are unbounded
    n = median_saving([1.0, 1.0, 1.0], [INF, INF, 2.0], reps=500)
    assert math.isnan(n.value) and n.low == -INF and n.high == INF
    # one censored run of five in the baseline: the median is finite, but a resample draws it 3 or
    # more times with probability 0.058 > 0.025, so both ends are left unbounded
    m = median_saving([1.0] * 5, [2.0, 2.0, 2.0, 2.0, INF], reps=2000)
    assert m.value == 0.5 and (m.low, m.high) == (-INF, INF)
    # one of ten: P(Binom(10, 0.1) >= 5) = 0.0016, and every defined resample saves exactly 0.5
    t = median_saving([1.0] * 10, [2.0] * 9 + [INF], reps=2000)
    assert (t.value, t.low, t.high) == (0.5, 0.5, 0.5)
    with pytest.raises(ValueError):
        median_saving([1.0], [1.0], reps=0)
