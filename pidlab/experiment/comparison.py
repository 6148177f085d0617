"""Each coached condition against no coach: effect size, exact test, Holm correction, verdict.

The families and measures are the pre-registered analysis plan's (docs/analysis-plan.md,
:mod:`pidlab.experiment.plan`): per env, a **primary** family (falls, env steps to the agent-alone
target, final agent-alone score) and a **secondary** family (the paper's measures in env episodes,
and the paper's target in env steps where the agent-alone target differs), each holding every
coached condition's tests. For every measure a :class:`Comparison` holds

- the probability of improvement P(X better than Y), ties half, with the score interval of
  Newcombe (2006, method 5) (:func:`pidlab.experiment.stats.probability_with_interval`), which does
  not collapse under complete separation;
- for a lower-is-better measure, the saving 1 - median(coached) / median(no coach) with its
  bootstrap interval (:func:`pidlab.experiment.stats.median_saving`);
- the exact two-sided Wilcoxon-Mann-Whitney permutation test of "no difference"
  (:func:`pidlab.experiment.stats.rank_sum_test`; runs that never reached a target tie at +inf);
- the Holm-adjusted p-value over the whole family, whose size is fixed: a test that cannot run
  stays in it with p = 1;
- a verdict, decided by :func:`decide` in this order:

  1. **never trained**: every run of the coached condition made no policy update, so it tests
     the initial policy, not coaching;
  2. **not testable**: every run of both conditions has the same value (no run reached the target
     at this budget, or all scored the same): there is nothing to compare;
  3. **no verdict possible**: the seeds cannot reach p < :data:`ALPHA` after Holm even when every
     run of one condition beats every run of the other (3 against 3 seeds: the smallest exact p
     is 0.1);
  4. **better** / **worse**: the Holm-adjusted p-value is below :data:`ALPHA`;
  5. **no clear difference** otherwise.
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
    median_saving,
    probability_with_interval,
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
    """

    name: str
    lower_better: bool
    label: str


MEASURES = (
    Measure("falls", True, "falls during training (terminations of the real env, agent or coach acting)"),
    Measure(
        "env_steps_to_alone_target",
        True,
        "env steps until the agent alone reaches the agent-alone target and keeps it",
    ),
    Measure("final_score", False, "final agent-alone score"),
    Measure("env_episodes_to_wins", True, "env episodes to 5 wins (training returns, the paper's target)"),
    Measure(
        "env_episodes_to_average",
        True,
        "env episodes to the moving-average target (training returns, the paper's)",
    ),
    Measure(
        "env_steps_to_target", True, "env steps until the agent alone reaches the paper's target and keeps it"
    ),
)
MEASURE = {m.name: m for m in MEASURES}


@dataclass(frozen=True)
class Comparison:
    """One measure of one coached condition against no coach.

    Attributes
    ----------
    measure : str
    improvement : Estimate
        P(a run of the condition beats a run without coach), ties half; 0.5: no difference; with
        its score interval.
    test : RankSumTest
        The exact two-sided test (``p_value`` unadjusted).
    saving : Estimate or None
        ``1 - median(coached) / median(no coach)`` with its bootstrap interval (lower-is-better
        measures; None otherwise).
    p_holm : float or None
        Holm-adjusted p-value within the family (None: before :func:`decide`).
    family : int
        How many tests the family holds.
    family_name : str
        ``primary`` or ``secondary``.
    verdict : str
        ``better``, ``worse``, ``no clear difference``, ``not testable``, ``never trained`` or
        ``no verdict possible``.
    reason : str
        Why, for the last three (empty otherwise).
    """

    measure: str
    improvement: Estimate
    test: RankSumTest
    saving: Estimate | None
    p_holm: float | None
    family: int
    family_name: str
    verdict: str
    reason: str

    @property
    def label(self) -> str:
        """The verdict as tables print it ("not testable at this budget" when every run missed)."""
        return self.verdict + (" at this budget" if self.reason == MISSED else "")

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


def raw_comparison(x: np.ndarray, y: np.ndarray, measure: Measure, reps: int = 10000) -> Comparison:
    """Effect size, saving and exact test of ``x`` (coached runs) against ``y`` (no coach), before a verdict.

    ``x`` and ``y`` hold the measure per run, +inf for a run that never reached a target;
    ``reps``: bootstrap resamples of the saving.
    """
    a, b = oriented(x, measure), oriented(y, measure)
    saving = median_saving(x, y, reps=reps) if measure.lower_better else None
    p = probability_with_interval(a, b)
    return Comparison(measure.name, p, rank_sum_test(a, b), saving, None, 0, "", "", "")


def _untestable_reason(x: np.ndarray, y: np.ndarray) -> str:
    pooled = np.concatenate([x, y])
    if np.all(np.isinf(pooled)):
        return MISSED
    return f"every run of both conditions has the same value, {pooled[0]:g}"


def reachable(smallest_p: float, family: int) -> bool:
    """Whether the most extreme result of a test can reach ``p < ALPHA`` after Holm over ``family`` tests."""
    return smallest_p * max(family, 1) < ALPHA


def _unreachable_reason(c: Comparison) -> str:
    return (
        f"{c.test.n} against {c.test.m} runs: the smallest exact p, {c.smallest_p:.2g}, times the family of "
        f"{c.family} is not below {ALPHA:g}"
    )


def decide(
    raw: Mapping[tuple[str, str], Comparison],
    values: Mapping[tuple[str, str], tuple[np.ndarray, np.ndarray]],
    never_trained: Mapping[str, bool],
    family_name: str,
) -> dict[tuple[str, str], Comparison]:
    """Verdicts for one family of one env, keyed by (condition, measure), with Holm over the family.

    The family holds every key of ``raw``; a test that cannot run (never trained, not testable)
    stays in it with p = 1, so the family's size is the design's, not the data's.

    Parameters
    ----------
    raw : mapping
        (condition, measure) -> :func:`raw_comparison`.
    values : mapping
        (condition, measure) -> (coached values, uncoached values), as given to ``raw_comparison``.
    never_trained : mapping
        Condition -> every run of it made no policy update.
    family_name : str
        ``primary`` or ``secondary``.
    """
    keys = list(raw)
    runnable = {k: raw[k].test.testable and not never_trained.get(k[0], False) for k in keys}
    adjusted = holm([raw[k].test.p_value if runnable[k] else 1.0 for k in keys])
    out: dict[tuple[str, str], Comparison] = {}
    for key, p in zip(keys, adjusted, strict=True):
        c = replace(raw[key], p_holm=p, family=len(keys), family_name=family_name)
        if never_trained.get(key[0], False):
            c = replace(c, verdict="never trained", reason=NEVER_TRAINED)
        elif not c.test.testable:
            c = replace(c, verdict="not testable", reason=_untestable_reason(*values[key]))
        elif not reachable(c.smallest_p, c.family):
            c = replace(c, verdict="no verdict possible", reason=_unreachable_reason(c))
        elif p < ALPHA:
            c = replace(c, verdict="better" if c.improvement.value > 0.5 else "worse")
        else:
            c = replace(c, verdict="no clear difference")
        out[key] = c
    return out
