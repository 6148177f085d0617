"""Verdicts of coached conditions against no coach, on hand-made cases with known answers."""

from __future__ import annotations

from math import comb

import numpy as np
import pytest

from pidlab.experiment.comparison import MEASURE, decide, raw_comparison

INF = np.inf


def _decide(values: dict, never: dict | None = None) -> dict:
    """Verdicts of {(condition, measure): (coached, uncoached)}, all in one family."""
    arrays = {k: (np.asarray(x, dtype=float), np.asarray(y, dtype=float)) for k, (x, y) in values.items()}
    raw = {k: raw_comparison(x, y, MEASURE[k[1]], reps=200) for k, (x, y) in arrays.items()}
    return decide(raw, arrays, never or {}, "primary")


def test_hits_at_the_same_evaluation_tie():
    # IP: the coached runs' 10,003 is the grid point 10,000, so four of ten tie with the baseline's
    coached = [10000] * 4 + [15000] * 3 + [20000] * 3
    baseline = [10000] * 9 + [15000]
    key = ("fading", "env_steps_to_alone_target")
    c = _decide({key: (coached, baseline)})[key]
    # P(fewer) over 100 pairs: 4 x 1 wins (10,000 < 15,000), ties count half: 4 x 9 at 10,000, 3 x 1 at 15,000
    assert c.improvement.value == pytest.approx((4 + (4 * 9 + 3 * 1) / 2) / 100)
    assert c.test.testable and 0 < c.test.p_value < 1
    # the saving of the median: 1 - 15,000 / 10,000
    assert c.saving is not None and c.saving.value == pytest.approx(-0.5)


def test_all_missed_is_not_testable_at_this_budget_and_stays_in_the_family():
    verdicts = _decide({("pidlab", "env_steps_to_alone_target"): ([INF] * 5, [INF] * 5),
                        ("pidlab", "final_score"): ([300.0] * 5, [300.0] * 5)})  # fmt: skip
    missed = verdicts[("pidlab", "env_steps_to_alone_target")]
    assert missed.verdict == "not testable" and "no run of either condition reached" in missed.reason
    assert missed.p_holm == 1.0 and missed.family == 2 and missed.improvement.value == 0.5
    assert missed.label == "not testable at this budget"
    assert missed.saving is not None and np.isnan(missed.saving.value)  # no saving against a baseline at +inf
    same = verdicts[("pidlab", "final_score")]
    assert same.verdict == "not testable" and "same value, 300" in same.reason
    assert same.label == "not testable" and same.saving is None  # higher-is-better: no saving


def test_a_condition_that_never_trained_gets_no_verdict_but_counts_in_the_family():
    ten = [float(v) for v in range(10)]
    verdicts = _decide({("pidlab", "final_score"): ([80.0] * 10, [300.0] * 10),
                        ("a", "final_score"): ([v + 100 for v in ten], ten)}, {"pidlab": True})  # fmt: skip
    c = verdicts[("pidlab", "final_score")]
    assert c.verdict == "never trained" and c.p_holm == 1.0 and c.family == 2
    # the other test is adjusted for a family of two
    assert verdicts[("a", "final_score")].p_holm == pytest.approx(2 * 2 / comb(20, 10))


def test_significance_needs_the_holm_adjusted_exact_p():
    ten = list(range(10))
    better = [v + 100 for v in ten]
    verdicts = _decide({("a", "final_score"): (better, ten), ("a", "env_steps_to_alone_target"): (ten, ten)})
    c = verdicts[("a", "final_score")]
    assert c.test.p_value == pytest.approx(2 / comb(20, 10))
    assert c.p_holm == pytest.approx(2 * 2 / comb(20, 10)) and c.family == 2 and c.family_name == "primary"
    assert c.verdict == "better"
    assert verdicts[("a", "env_steps_to_alone_target")].verdict == "no clear difference"
    # lower is better for steps: the same separation the other way round is "worse"
    worse = _decide({("a", "env_steps_to_alone_target"): (better, ten)})[("a", "env_steps_to_alone_target")]
    assert worse.verdict == "worse" and worse.improvement.value == 0.0


def test_complete_separation_keeps_an_interval_of_p():
    ten = [float(v) for v in range(10)]
    c = _decide({("a", "final_score"): ([v + 100 for v in ten], ten)})[("a", "final_score")]
    assert c.improvement.value == 1.0 and c.improvement.high == 1.0
    # the percentile bootstrap gave [1.00, 1.00]; the score interval (Newcombe, method 5) does not
    assert c.improvement.low == pytest.approx(0.8, abs=0.01)


def test_three_seeds_give_no_verdict():
    c = _decide({("coached", "final_score"): ([900, 950, 1000], [10, 20, 30])})[("coached", "final_score")]
    assert c.smallest_p == pytest.approx(0.1) and c.test.p_value == pytest.approx(0.1)
    assert c.verdict == "no verdict possible" and "3 against 3 runs" in c.reason


def test_five_seeds_in_a_family_of_seven_give_no_verdict():
    # 2/252 is below 0.05, but Holm over 7 tests makes even the most extreme result 0.056
    five = [1.0, 2.0, 3.0, 4.0, 5.0]
    values = {(f"c{i}", "final_score"): ([v + 100 for v in five], five) for i in range(7)}
    c = _decide(values)[("c0", "final_score")]
    assert c.family == 7 and c.p_holm == pytest.approx(7 * 2 / 252)
    assert c.verdict == "no verdict possible"
    # with 6 tests the same result is significant after Holm
    six = _decide({k: v for k, v in values.items() if k[0] != "c6"})[("c0", "final_score")]
    assert six.family == 6 and six.verdict == "better"
