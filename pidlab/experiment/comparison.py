"""Each coached condition against no coach: effect size, exact test, Holm correction, verdict.

For every measure of :data:`MEASURES` a :class:`Comparison` holds

- the probability of improvement P(X better than Y) with its stratified bootstrap interval (the
  effect size, :func:`pidlab.experiment.stats.probability_of_improvement`);
- the exact two-sided Wilcoxon-Mann-Whitney permutation test of "no difference"
  (:func:`pidlab.experiment.stats.rank_sum_test`; runs that never reached a target tie at +inf);
- the Holm-adjusted p-value over every testable comparison of the same env (its family);
- a verdict, decided by :func:`decide` in this order:

  1. **never trained**: every run of the coached condition made no policy update, so it tests
     the initial policy, not coaching;
  2. **not testable**: every run of both conditions has the same value (no run reached the target
     at this budget, or all scored the same): there is nothing to compare;
  3. **better** / **worse**: the Holm-adjusted p-value is below :data:`ALPHA`; when the seeds
     cannot reach it at all, even with every run of one condition beating every run of the other
     (3 seeds: the smallest exact p is 0.1; 5 seeds: 2/252, times a Holm family of 18 is 0.14), the
     verdict is read from the bootstrap interval of P instead (it excludes 0.5) and marked *indicative*;
  4. **no clear difference** otherwise;
  5. **withdrawn**: a paper's measure on training returns says *worse* while the same measure on
     the returns with the coach's rewards does not; the training return of a coached episode is
     capped at the time limit minus its coach steps, so that verdict rests on the cap.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np

from pidlab.experiment.stats import (
    Estimate,
    RankSumTest,
    detectable_improvement,
    holm,
    probability_of_improvement,
    rank_sum_test,
    smallest_p_value,
)

ALPHA = 0.05
POWER = 0.8
NEVER_TRAINED = "no run of this condition made a policy update"
MISSED = "no run of either condition reached the target"


@dataclass(frozen=True)
class Measure:
    """A measure compared between conditions.

    Attributes
    ----------
    name : str
        A field of :class:`pidlab.experiment.metrics.RunMetrics`.
    lower_better : bool
    label : str
        How sentences name it.
    uncapped : str or None
        For a measure read from capped training returns, the same measure on the returns with the
        coach's rewards.
    """

    name: str
    lower_better: bool
    label: str
    uncapped: str | None = None


MEASURES = (
    Measure("episodes_to_wins", True, "episodes to 5 wins (training returns)", "episodes_to_wins_with_coach"),
    Measure(
        "episodes_to_average",
        True,
        "episodes to the moving-average target (training returns)",
        "episodes_to_average_with_coach",
    ),
    Measure("episodes_to_wins_with_coach", True, "episodes to 5 wins (returns with the coach's rewards)"),
    Measure(
        "episodes_to_average_with_coach",
        True,
        "episodes to the moving-average target (returns with the coach's rewards)",
    ),
    Measure("env_steps_to_target", True, "env steps until the agent alone reaches the target and keeps it"),
    Measure("final_score", False, "final agent-alone score"),
    Measure("falls", True, "falls during training (terminations of the real env, agent or coach acting)"),
)
MEASURE = {m.name: m for m in MEASURES}


@dataclass(frozen=True)
class Comparison:
    """One measure of one coached condition against no coach.

    Attributes
    ----------
    measure : str
    improvement : Estimate
        P(a run of the condition beats a run without coach), ties half; 0.5: no difference.
    test : RankSumTest
        The exact two-sided test (``p_value`` unadjusted).
    p_holm : float or None
        Holm-adjusted p-value within the env's family (None: not in it, see ``verdict``).
    family : int
        How many comparisons the env's Holm family holds.
    verdict : str
        ``better``, ``worse``, ``no clear difference``, ``not testable``, ``never trained`` or
        ``withdrawn``.
    indicative : bool
        The verdict was read from the bootstrap interval because the seeds cannot reach p < ALPHA.
    reason : str
        Why, for ``not testable``, ``never trained`` and ``withdrawn`` (empty otherwise).
    """

    measure: str
    improvement: Estimate
    test: RankSumTest
    p_holm: float | None
    family: int
    verdict: str
    indicative: bool
    reason: str

    @property
    def label(self) -> str:
        """The verdict as tables print it ("not testable at this budget" when every run missed)."""
        text = self.verdict + (" at this budget" if self.reason == MISSED else "")
        return text + (" (indicative)" if self.indicative else "")

    @property
    def smallest_p(self) -> float:
        """The smallest p-value the exact test can give with these run counts."""
        return smallest_p_value(self.test.n, self.test.m)


@functools.lru_cache(maxsize=64)
def detectable(n: int, m: int) -> float | None:
    """The smallest P(improvement) that ``n`` against ``m`` runs detect with 80 % power (None: none)."""
    return detectable_improvement(n, m, alpha=ALPHA, power=POWER)


def oriented(values: np.ndarray, measure: Measure) -> np.ndarray:
    """Values with "higher is better" (a lower-is-better measure negated; +inf becomes -inf)."""
    return -values if measure.lower_better else values


def raw_comparison(x: np.ndarray, y: np.ndarray, measure: Measure, reps: int) -> Comparison:
    """Effect size and exact test of runs ``x`` (coached) against ``y`` (no coach), before any verdict.

    ``x`` and ``y`` hold the measure per run, +inf for a run that never reached a target.
    """
    a, b = oriented(x, measure), oriented(y, measure)
    p = probability_of_improvement([a.tolist()], [b.tolist()], reps=reps)
    return Comparison(measure.name, p, rank_sum_test(a, b), None, 0, "", False, "")


def _untestable_reason(x: np.ndarray, y: np.ndarray) -> str:
    pooled = np.concatenate([x, y])
    if np.all(np.isinf(pooled)):
        return MISSED
    return f"every run of both conditions has the same value, {pooled[0]:g}"


def reachable(smallest_p: float, family: int) -> bool:
    """Whether the most extreme result of a test can reach ``p < ALPHA`` after Holm over ``family`` tests."""
    return smallest_p * max(family, 1) < ALPHA


def _significance(c: Comparison) -> tuple[str, bool]:
    """(verdict, indicative) from the Holm-adjusted p, or from the interval when p < ALPHA is out of reach."""
    if not reachable(c.smallest_p, c.family):
        if c.improvement.low > 0.5:
            return "better", True
        if c.improvement.high < 0.5:
            return "worse", True
        return "no clear difference", True
    if c.p_holm is not None and c.p_holm < ALPHA:
        return ("better" if c.improvement.value > 0.5 else "worse"), False
    return "no clear difference", False


def decide(
    raw: Mapping[tuple[str, str], Comparison],
    values: Mapping[tuple[str, str], tuple[np.ndarray, np.ndarray]],
    never_trained: Mapping[str, bool],
) -> dict[tuple[str, str], Comparison]:
    """Verdicts for one env's comparisons, keyed by (condition, measure), with Holm over the family.

    Parameters
    ----------
    raw : mapping
        (condition, measure) -> :func:`raw_comparison`.
    values : mapping
        (condition, measure) -> (coached values, uncoached values), as given to ``raw_comparison``.
    never_trained : mapping
        Condition -> every run of it made no policy update.
    """
    out: dict[tuple[str, str], Comparison] = {}
    family = []
    for key, c in raw.items():
        if never_trained.get(key[0], False):
            out[key] = replace(c, verdict="never trained", reason=NEVER_TRAINED)
        elif not c.test.testable:
            out[key] = replace(c, verdict="not testable", reason=_untestable_reason(*values[key]))
        else:
            family.append(key)
    adjusted = holm([raw[k].test.p_value for k in family])
    for key, p in zip(family, adjusted, strict=True):
        c = replace(raw[key], p_holm=p, family=len(family))
        verdict, indicative = _significance(c)
        out[key] = replace(c, verdict=verdict, indicative=indicative)
    return {k: _withdraw_capped(k, out) for k in raw}


def _withdraw_capped(key: tuple[str, str], out: Mapping[tuple[str, str], Comparison]) -> Comparison:
    c = out[key]
    twin = MEASURE[c.measure].uncapped
    if c.verdict != "worse" or twin is None or (key[0], twin) not in out:
        return c
    other = out[(key[0], twin)]
    if other.verdict == "worse":
        return c
    return replace(
        c, verdict="withdrawn",
        reason=f"rests on the return cap: with the coach's rewards counted, {other.verdict}",
    )  # fmt: skip
