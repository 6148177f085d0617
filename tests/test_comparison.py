"""Verdicts of coached conditions against no coach, on hand-made cases with known answers."""

from __future__ import annotations

from math import comb

import numpy as np
import pytest

from pidlab.experiment.comparison import MEASURE, decide, raw_comparison

INF = np.inf


def _decide(values: dict, never: dict | None = None) -> dict:
    """Verdicts of {(condition, measure): (coached, uncoached)}."""
    arrays = {k: (np.asarray(x, dtype=float), np.asarray(y, dtype=float)) for k, (x, y) in values.items()}
    raw = {k: raw_comparison(x, y, MEASURE[k[1]], reps=200) for k, (x, y) in arrays.items()}
    return decide(raw, arrays, never or {})


def test_hits_at_the_same_evaluation_tie():
    # IP: the coached runs' 10,003 is the grid point 10,000, so four of ten tie with the baseline's
    coached = [10000] * 4 + [15000] * 3 + [20000] * 3
    baseline = [10000] * 9 + [15000]
    c = _decide({("fading", "env_steps_to_target"): (coached, baseline)})[("fading", "env_steps_to_target")]
    # P(fewer) over 100 pairs: 4 x 1 wins (10,000 < 15,000), ties count half: 4 x 9 at 10,000, 3 x 1 at 15,000
    assert c.improvement.value == pytest.approx((4 + (4 * 9 + 3 * 1) / 2) / 100)
    assert c.test.testable and 0 < c.test.p_value < 1


def test_all_missed_is_not_testable_at_this_budget():
    verdicts = _decide({("pidlab", "env_steps_to_target"): ([INF] * 5, [INF] * 5),
                        ("pidlab", "final_score"): ([300.0] * 5, [300.0] * 5)})  # fmt: skip
    missed = verdicts[("pidlab", "env_steps_to_target")]
    assert missed.verdict == "not testable" and "no run of either condition reached" in missed.reason
    assert missed.p_holm is None and missed.improvement.value == 0.5
    assert missed.label == "not testable at this budget"
    same = verdicts[("pidlab", "final_score")]
    assert same.verdict == "not testable" and "same value, 300" in same.reason
    assert same.label == "not testable"


def test_a_condition_that_never_trained_gets_no_coaching_verdict():
    c = _decide({("pidlab", "final_score"): ([80.0] * 5, [300.0] * 5)}, {"pidlab": True})[("pidlab", "final_score")]
    assert c.verdict == "never trained" and c.p_holm is None


def test_significance_needs_the_holm_adjusted_exact_p():
    ten = list(range(10))
    better = [v + 100 for v in ten]
    verdicts = _decide({("a", "final_score"): (better, ten), ("a", "env_steps_to_target"): (ten, ten)})
    c = verdicts[("a", "final_score")]
    assert c.test.p_value == pytest.approx(2 / comb(20, 10))
    assert c.p_holm == pytest.approx(2 * 2 / comb(20, 10)) and c.family == 2
    assert c.verdict == "better" and not c.indicative
    assert verdicts[("a", "env_steps_to_target")].verdict == "no clear difference"
    # lower is better for steps: the same separation the other way round is "worse"
    worse = _decide({("a", "env_steps_to_target"): (better, ten)})[("a", "env_steps_to_target")]
    assert worse.verdict == "worse" and worse.improvement.value == 0.0


def test_three_seeds_give_indicative_verdicts_only():
    c = _decide({("coached", "final_score"): ([900, 950, 1000], [10, 20, 30])})[("coached", "final_score")]
    assert c.smallest_p == pytest.approx(0.1) and c.test.p_value == pytest.approx(0.1)
    assert c.verdict == "better" and c.indicative


def test_a_worse_verdict_that_rests_on_the_return_cap_is_withdrawn():
    # a heavy coach: training returns never reach the target, returns with the coach's rewards do
    ten = [float(v) for v in range(100, 110)]
    verdicts = _decide({
        ("pidlab", "episodes_to_wins"): ([INF] * 10, ten),
        ("pidlab", "episodes_to_wins_with_coach"): ([v - 50 for v in ten], ten),
    })  # fmt: skip
    capped = verdicts[("pidlab", "episodes_to_wins")]
    assert capped.verdict == "withdrawn" and "return cap" in capped.reason and "better" in capped.reason
    assert verdicts[("pidlab", "episodes_to_wins_with_coach")].verdict == "better"
    # worse on both kinds of return: the verdict stands
    both = _decide({
        ("pidlab", "episodes_to_wins"): ([INF] * 10, ten),
        ("pidlab", "episodes_to_wins_with_coach"): ([INF] * 10, ten),
    })  # fmt: skip
    assert both[("pidlab", "episodes_to_wins")].verdict == "worse"


def test_five_seeds_in_a_family_of_many_comparisons_give_indicative_verdicts():
    # 2/252 is below 0.05, but Holm over 7 comparisons makes even the most extreme result 0.056
    five = [1.0, 2.0, 3.0, 4.0, 5.0]
    values = {(f"c{i}", "final_score"): ([v + 100 for v in five], five) for i in range(7)}
    verdicts = _decide(values)
    c = verdicts[("c0", "final_score")]
    assert c.family == 7 and c.p_holm == pytest.approx(7 * 2 / 252)
    assert c.verdict == "better" and c.indicative
    # with 6 comparisons the same result is significant after Holm
    six = _decide({k: v for k, v in values.items() if k[0] != "c6"})[("c0", "final_score")]
    assert six.family == 6 and six.verdict == "better" and not six.indicative
