"""Classifier rescue regions: the data and its TOML form, membership, the estimate in MuJoCo, the command.

The estimate runs on InvertedDoublePendulum-v5 with small draws: what it checks is the mechanics
(the last validation draw had no failure, so fresh states inside are rescued; the accounts of the
coverage; the spec round trip and the refusals), not the size of a full-budget region.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from pidlab.controller.spec import dumps_spec, law_digest, load_spec, loads_spec
from pidlab.errors import CoachingError, RegionError, SpecError
from pidlab.lookup import RescueClassifier, parse_classifier, parse_rescue
from pidlab.plant.model import load_model
from pidlab.region.classifier import (
    ClassifierSettings,
    calibrated_threshold,
    estimate_classifier,
    fit_layers,
    raised_threshold,
    with_classifier,
)
from pidlab.region.rescue import _core, _rescued
from pidlab.region.simulate import Simulator
from pidlab.region.takeover import ClassifierRegion, load_region
from tests.helpers import TUNING, cli_in_process

IDP = "InvertedDoublePendulum-v5"
SPEC = TUNING / f"{IDP}.pidlab-rescue.toml"
VARS = ("slider_pos", "hinge_sin", "hinge2_sin", "slider_vel", "hinge_vel", "hinge2_vel")
HALF = (0.9, 0.6, 0.9, 1.0, 2.0, 2.0)


def _tiny(threshold: float = 0.0) -> RescueClassifier:
    """One variable on [-1, 1]: score(x) = tanh(2 x) - 0.5 (hand-checkable)."""
    layers = ((np.array([[2.0]]), np.array([0.0])), (np.array([[1.0]]), np.array([-0.5])))
    return RescueClassifier(("hinge_sin",), (-1.0,), (1.0,), layers, threshold, "abc")


def test_the_score_is_the_network_computed_by_hand() -> None:
    c = _tiny()
    x = np.array([[0.5], [-0.25], [1.0]])
    assert c.scores(x) == pytest.approx([math.tanh(1.0) - 0.5, math.tanh(-0.5) - 0.5, math.tanh(2.0) - 0.5])
    # inside: in the box and a score >= threshold; tanh(2x) >= 0.5 from x = atanh(0.5) / 2 = 0.2747
    pts = np.array([[0.27], [0.28], [1.0], [1.01]])
    assert c.inside(pts).tolist() == [False, True, True, False]
    assert c.inside(pts, threshold=0.45).tolist() == [False, False, True, False]


def test_a_classifier_round_trips_through_its_toml_table() -> None:
    c = _tiny(0.25)
    assert "anchor" not in c.to_table()  # a region handing back at the operating point: as before
    back = parse_rescue(c.to_table())
    assert isinstance(back, RescueClassifier) and back == c
    anchored = dataclasses.replace(c, anchor=(0.5,))
    assert anchored.to_table()["anchor"] == [0.5] and parse_rescue(anchored.to_table()) == anchored
    x = np.linspace(-1, 1, 7)[:, None]
    assert np.array_equal(back.scores(x), c.scores(x))


def _table(**change: object) -> dict:
    t = _tiny().to_table()
    t.update(change)
    return t


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"shape": "boxes"}, r"shape: 'boxes'; expected 'classifier'"),
        ({"trigger": "reactive"}, r"trigger: 'reactive'; a classifier region is for 'predictive'"),
        ({"action_fraction": 0.5}, r"action_fraction: 0.5; expected 0"),
        ({"action_fraction": False}, r"action_fraction: False; expected 0"),
        ({"variables": []}, r"variables: expected 1 to 24"),
        ({"lower": [1.0]}, r"expected lower < upper"),
        ({"layers": [{"weights": [[1.0]], "bias": [0.0]}]}, r"layers: expected 2 to 4 layers"),
        ({"layers": [{"weights": [[1.0, 2.0]], "bias": [0.0, 0.0]}, {"weights": [[1.0]], "bias": [0.0]}]},
         r"layers\[1\].weights: expected 2 rows"),
        ({"layers": [{"weights": [[1.0]], "bias": [0.0]}, {"weights": [[1.0, 1.0]], "bias": [0.0, 0.0]}]},
         r"layers\[1\].bias: 2 entries; expected 1 output"),
        ({"layers": [{"weights": [[float("nan")]], "bias": [0.0]}, {"weights": [[1.0]], "bias": [0.0]}]},
         r"layers\[0\].weights\[0\]: expected a list of 1 finite numbers"),
        ({"threshold": float("inf")}, r"threshold: inf; expected a finite number"),
        ({"coach": ""}, r"coach: expected the digest"),
        ({"cells": [3]}, r"unknown field\(s\) \['cells'\]"),
        ({"anchor": [1.5]}, r"anchor: \[1.5\]; expected a point inside the domain box"),
        ({"anchor": [0.0, 0.0]}, r"anchor: expected a list of 1 finite numbers"),
        ({"anchor": "x"}, r"anchor: expected a list of 1 finite numbers"),
    ],
)  # fmt: skip
def test_a_damaged_classifier_table_is_one_spec_error(change: dict, message: str) -> None:
    with pytest.raises(SpecError, match=message):
        parse_classifier(_table(**change))


def test_threshold_rules_computed_by_hand() -> None:
    scores = np.array([0.1, 0.9, -0.3, 0.4])
    rescued = np.array([True, True, False, False])
    assert calibrated_threshold(scores, rescued) == 0.4  # the highest failure's score
    assert calibrated_threshold(scores, np.ones(4, dtype=bool)) == pytest.approx(-1.3)  # none failed
    t = raised_threshold(0.4, np.array([0.5, 0.45]))
    assert t > 0.5 and t == np.nextafter(0.5, np.inf)
    assert raised_threshold(0.4, np.array([])) == 0.4
    assert raised_threshold(0.6, np.array([0.5])) == np.nextafter(0.6, np.inf)


def test_the_edge_band_computed_by_hand() -> None:
    """From the threshold to the share's quantile of the scores inside (numpy's linear quantile)."""
    from pidlab.region.classifier import edge_width

    scores = np.array([0.5, 1.0, 2.0, 3.0, 4.5])  # quantile 0.25: position 1 -> 1.0
    assert edge_width(0.4, scores, 0.25) == pytest.approx(0.6)
    assert edge_width(0.4, scores, 0.5) == pytest.approx(1.6)  # the median, 2.0
    assert edge_width(0.4, scores, 0.0) == 0.0 and edge_width(0.4, np.array([]), 0.05) == 0.0
    assert edge_width(3.0, scores, 0.25) == 0.0  # never below the threshold


def test_the_focus_level_computed_by_hand() -> None:
    """The first fit's score that all but the lowest 1 % of the rescued fitted states reach."""
    from pidlab.region.classifier import FOCUS_QUANTILE, focus_level

    assert FOCUS_QUANTILE == 0.01
    scores = np.arange(101.0)  # numpy's linear quantile 0.01 of 0..100: position 1 -> 1.0
    assert focus_level(scores) == pytest.approx(1.0)
    assert focus_level(np.array([2.0, 4.0])) == pytest.approx(2.02)  # 2 + 0.01 x (4 - 2)
    with pytest.raises(RegionError, match="focus: no fitted state was rescued"):
        focus_level(np.array([]))


def test_failure_bounds_computed_by_hand() -> None:
    """No failure: the rule of three. Otherwise the one-sided Clopper-Pearson bound: the rate at which
    that many failures or fewer come up with probability 0.05 (1 of 2: 1 - p^2 = 0.05)."""
    from scipy.stats import binom

    from pidlab.region.classifier import allowed_failures, failure_bound

    assert failure_bound(0, 2000) == pytest.approx(0.0015) and failure_bound(0, 200) == pytest.approx(0.015)
    assert failure_bound(1, 2) == pytest.approx(math.sqrt(0.95))
    assert failure_bound(2, 2) == 1.0 and failure_bound(0, 2) == 1.0  # never above 1
    for k, n in ((1, 20), (3, 200), (8, 2000)):
        assert binom.cdf(k, n, failure_bound(k, n)) == pytest.approx(0.05)
    assert allowed_failures(2000, 0.0) == 0 and allowed_failures(2000, 0.0015) == 0  # 1 of 2,000: 0.0024
    for n, alpha in ((200, 0.03), (2000, 0.005), (2000, 0.01)):
        k = allowed_failures(n, alpha)
        assert failure_bound(k, n) <= alpha < failure_bound(k + 1, n)
    assert allowed_failures(200, 0.03) == 1 and allowed_failures(2000, 0.005) == 4


def test_a_tolerated_false_claim_rate_accepts_a_draw_with_few_failures(monkeypatch) -> None:
    """The validation loop's rule, on set outcomes (the labels here stand in for MuJoCo's; the
    estimate's own run is tested on IDP below): a draw with more failures than the rate allows raises
    the threshold past them, and the next draw, within it, is accepted with its failures kept."""
    from types import SimpleNamespace

    from pidlab.region import classifier

    states = np.linspace(-1.0, 1.0, 200)[:, None]
    outcomes = iter([np.arange(200) >= 3, np.arange(200) != 150])  # 3 failures, then 1
    est = SimpleNamespace(rescued=lambda drawn, label: (next(outcomes), None))
    monkeypatch.setattr(classifier, "draw_states", lambda est, n, keep, kept: states[:n])
    work = SimpleNamespace(settings=_small(validation=200, false_claims=0.03), est=est)
    clf, (rounds, removed, kept), scores = classifier._until_clean(
        work, _tiny(-5.0), 200, lambda c: c.inside, "validation"
    )
    assert (rounds, removed, kept) == (2, 3, 1)  # 1 of 200 is within 3 %; 3 of 200 is not (0.038)
    assert clf.threshold == np.nextafter(float(_tiny().scores(states[2:3])[0]), np.inf)
    assert len(scores) == 200
    with pytest.raises(RegionError, match=r"false_claims=0.01: 200 validation state\(s\) with no failure"):
        _small(validation=200, false_claims=0.01)


def test_no_edge_share_means_no_edge_draw() -> None:
    from types import SimpleNamespace

    from pidlab.region.classifier import _validate_edge

    work = SimpleNamespace(settings=_small(edge_share=0.0))  # nothing simulated: no estimate is needed
    assert _validate_edge(work, _tiny(0.0), np.array([1.0, 2.0]))[1] == (0, 0, 0, 0.0)


def test_the_fit_is_deterministic_and_learns_a_separable_rule() -> None:
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (2000, 2))
    y = x[:, 0] + 0.5 * x[:, 1] > 0.1
    a = fit_layers(x, y, width=8, epochs=40, negative_weight=3.0, seed=1)
    b = fit_layers(x, y, width=8, epochs=40, negative_weight=3.0, seed=1)
    assert all(
        np.array_equal(wa, wb) and np.array_equal(ba, bb) for (wa, ba), (wb, bb) in zip(a, b, strict=True)
    )
    assert [w.shape for w, _ in a] == [(2, 8), (8, 8), (8, 1)]
    c = RescueClassifier(("a", "b"), (-1.0, -1.0), (1.0, 1.0), a, 0.0, "x")
    assert np.mean((c.scores(x) >= 0) == y) > 0.95


def test_the_region_object_tests_observations_and_narrows_for_the_hand_back() -> None:
    names = ("slider_pos", "hinge_sin", "hinge_vel")
    region = ClassifierRegion(_tiny(), names)
    assert region.kind == "rescue" and region.trigger == "predictive"
    assert region.operating_score == pytest.approx(-0.5)  # the box's centre, x = 0
    assert region.contains(np.array([9.0, 0.5, 9.0])) and not region.contains(np.array([0.0, 0.1, 0.0]))
    assert not region.contains(np.array([0.0, 1.5, 0.0]))  # outside the domain box
    # the operating point scores below the threshold here, so narrowing cannot move the threshold
    assert region.inner(0.5).threshold == region.threshold
    high = ClassifierRegion(_tiny(-0.9), names, operating_score=-0.5)
    assert high.inner(0.5).threshold == pytest.approx(-0.7)  # halfway from -0.9 to the operating score
    assert high.inner(0.5).inner(0.5).threshold == pytest.approx(-0.6)
    with pytest.raises(CoachingError, match="expected the env's observation, 3 numbers"):
        region.contains(np.zeros(2))


def test_a_coach_that_regulates_elsewhere_hands_back_at_its_anchor() -> None:
    """The hand-back region tightens toward the score where the coach regulates to, not the box's centre."""
    names = ("slider_pos", "hinge_sin", "hinge_vel")
    anchored = ClassifierRegion(dataclasses.replace(_tiny(-0.9), anchor=(0.5,)), names)
    assert anchored.operating_score == pytest.approx(math.tanh(1.0) - 0.5)  # scored at x = 0.5
    assert anchored.inner(0.5).threshold == pytest.approx((-0.9 + math.tanh(1.0) - 0.5) / 2)
    assert anchored.inner(0.5).contains(np.array([0.0, 0.5, 0.0]))  # the anchor is in the hand-back region


def _small(**kw: object) -> ClassifierSettings:
    base = ClassifierSettings(VARS, HALF, samples=10000, calibration=2000, validation=200, coverage=600,
                              width=16, epochs=100, seed=3, focus=1000, near=300)  # fmt: skip
    return dataclasses.replace(base, **kw)


@pytest.fixture(scope="module")
def idp_classifier() -> tuple[object, object]:
    spec = load_spec(SPEC)
    return spec, estimate_classifier(spec, load_model(IDP), _small(), workers=2)


def test_fresh_states_inside_the_classifier_region_are_rescued(idp_classifier: tuple) -> None:
    spec, r = idp_classifier
    loaded = load_model(IDP)
    from pidlab.controller.analysis import analyze_coach
    from pidlab.controller.pid import Coach

    sim = Simulator(spec, loaded, analyze_coach(Coach(spec, loaded), loaded).linearization)
    region = ClassifierRegion(r.classifier, loaded.require_card().observation_names)
    core, rng, checked = _core(spec, loaded.require_card()), np.random.default_rng(77), 0
    while checked < 15:
        x = np.zeros(6)
        x[:3] = rng.uniform([-0.9, -0.6, -0.9], [0.9, 0.6, 0.9])  # slider, hinge, hinge2 (angles ~ sines)
        x[3:] = rng.uniform([-1.0, -2.0, -2.0], [1.0, 2.0, 2.0])
        obs = sim.start(x)
        if sim.terminated(obs) or not region.contains(obs):
            continue
        ok, _ = _rescued(sim, (x, None), 60, core)
        assert ok, f"a state in the classifier region was not rescued: {obs}"
        checked += 1


def test_classifier_accounts_add_up(idp_classifier: tuple) -> None:
    spec, r = idp_classifier
    p = r.provenance
    assert p["validation_samples"] == 200 and p["validation_failures"] == 0
    assert p["validation_rounds"] == r.validation_rounds >= 1
    assert 0 < p["coverage_rescuable"] <= 600
    assert p["coverage_rescue"] == r.coverage and 0.0 <= r.coverage <= 1.0
    assert r.coverage_grid is not None and 0.0 <= r.coverage_grid <= 1.0  # the shipped grid, same states
    assert 0.0 < r.volume <= 1.0 and 0.0 < r.rescued_fraction < 1.0
    # labels, focus, near, validation, its edge, coverage
    assert p["simulations"] >= 10000 + 2000 + 1000 + 300 + 200 + 200 + 600
    # the states drawn near the operating point (the IDP coach's own): nearly all rescued
    assert p["near"] == 300 and p["near_rescued"] > 2 * r.rescued_fraction and r.classifier.anchor is None
    # the focused states were drawn where the first fit scores like the rescued ones: far richer in rescues
    assert p["focus"] == 1000 and p["focus_rescued"] > 2 * r.rescued_fraction
    assert p["edge_samples"] == 200 and p["edge_share"] == 0.05 and p["edge_band"] > 0.0
    assert p["edge_rounds"] == r.edge_rounds >= 1 and p["edge_failures_removed"] == r.edge_failures_removed
    assert r.classifier.coach == law_digest(spec)
    lo, hi = np.array(r.classifier.lower), np.array(r.classifier.upper)
    assert hi - lo == pytest.approx(2 * np.array(HALF))


def test_written_into_a_spec_it_is_the_takeover_region_and_refused_for_another_coach(
    idp_classifier: tuple,
) -> None:
    spec, r = idp_classifier
    text = dumps_spec(with_classifier(spec, r))
    again = loads_spec(text)
    assert again.bounds["takeover"] == "rescue" and "forecast" not in again.bounds
    region = load_region(again)
    assert isinstance(region, ClassifierRegion) and region.classifier == r.classifier
    # the same table on a coach with another gain: fitted for another coach, refused in one line
    other = text.replace(f"kp = {spec.loops[0].kp!r}", f"kp = {spec.loops[0].kp * 1.5!r}", 1)
    assert other != text
    with pytest.raises(SpecError, match="the classifier was fitted for another coach"):
        loads_spec(other)


def test_the_model_predictor_asks_a_classifier_region_for_its_measurement(idp_classifier: tuple) -> None:
    from pidlab.rl.coaching import model_region

    spec, r = idp_classifier
    new = with_classifier(spec, r)
    loaded = load_model(IDP)
    region = load_region(new)
    with pytest.raises(CoachingError, match="no \\[bounds.forecast\\].*pidlab forecast SPEC --write"):
        model_region(new, loaded, region)


def test_settings_out_of_range_are_refused() -> None:
    with pytest.raises(RegionError, match="expected 1 to 24 distinct variables"):
        ClassifierSettings(("a", "a"), (1.0, 1.0))
    with pytest.raises(RegionError, match="half-range of a"):
        ClassifierSettings(("a",), (0.0,))
    with pytest.raises(RegionError, match="samples"):
        _small(samples=10)
    with pytest.raises(RegionError, match="focus"):
        _small(focus=-5)
    for share in (-0.1, 1.5, math.nan):
        with pytest.raises(RegionError, match="edge_share"):
            _small(edge_share=share)
    with pytest.raises(RegionError, match="into='floor': expected one of core, box"):
        _small(into="floor")


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["--domain", "hinge_sin=0"],
            "--domain 'hinge_sin=0': expected VARIABLE=HALF-WIDTH with a half-width > 0",
        ),
        (["--domain", "hinge_sin=1,hinge_sin=2"], "--domain: 'hinge_sin' is given twice"),
        (["--domain", "slider_constraint=1"], "slider_constraint: a rescue region's variable must be"),
        (["--domain", "hinge_sin=1", "--samples", "5"], "--samples 5: expected an integer in [100, 2000000]"),
        (["--domain", "hinge_sin=1", "--write", "-o", "x.toml"], "--write and --output: choose one"),
        (["--domain", "hinge_sin=1", "--edge-share", "2"], "--edge-share 2"),
        (["--domain", "hinge_sin=1", "--focus", "-1"], "--focus -1: expected an integer in [0, 2000000]"),
        (["--domain", "hinge_sin=1", "--near", "-1"], "--near -1: expected an integer in [0, 2000000]"),
        (["--domain", "hinge_sin=1", "--into", "up"], "--into 'up': expected one of core, box"),
        (["--domain", "hinge_sin=1", "--false-claims", "0.5"], "--false-claims 0.5: expected a finite number"),
        (["--domain", "hinge_sin=1", "--false-claims", "0.001"], "--false-claims 0.001: 2000 validation state(s)"),
    ],
)
def test_the_command_refuses_bad_input_in_one_line(args: list[str], message: str) -> None:
    code, err = cli_in_process("rescue-classifier", str(SPEC), *args)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1
    assert lines[0].startswith("pidlab: error: ") and message in lines[0]


def test_the_shield_lets_an_agent_act_only_where_the_classifier_region_holds_the_next_state(
    idp_classifier: tuple,
) -> None:
    """Predictive trigger, exact copy: an action runs only if the state after it is in the region."""
    import gymnasium as gym

    from pidlab.rl.coaching import CoachingWrapper

    spec, r = idp_classifier
    shielded = with_classifier(spec, r)
    env = CoachingWrapper(gym.make(IDP), shielded, mode="takeover", region="rescue", trigger="predictive",
                          view="penalty")  # fmt: skip
    region = load_region(shielded)
    assert isinstance(env.region, ClassifierRegion)
    obs, _ = env.reset(seed=0)
    rng = np.random.default_rng(0)
    acted = vetoed = 0
    for _ in range(200):
        obs, _, terminated, truncated, info = env.step(rng.uniform(-1, 1, 1).astype(np.float32))
        if info["coach_steps"] == 0:
            acted += 1
            assert region.contains(obs), obs  # the agent's own step kept the state in the region
        vetoed += bool(info.get("vetoed"))
        if terminated or truncated:
            obs, _ = env.reset()
    assert acted > 0 and vetoed > 0


def test_a_domain_the_termination_rule_leaves_empty_is_refused_in_one_line() -> None:
    """Both poles tilted past the termination height everywhere in the box: nothing to label."""
    from pidlab.region import classifier
    from pidlab.region.coverage import draw_states

    spec, loaded = load_spec(SPEC), load_model(IDP)
    settings = ClassifierSettings(
        ("hinge_sin",), (1.0,), samples=100, calibration=100, validation=10, coverage=10
    )
    with classifier._working(spec, loaded, settings, 1, None) as work:
        # a box whose every state leans the lower pole beyond 0.9 in sine: the env ends them all
        work.est.domain = dataclasses.replace(work.est.domain, lower=np.array([0.9]), upper=np.array([1.0]))
        with pytest.raises(RegionError, match=r"after [0-9,]+ uniform draws only 0 of 10 states lay in the "
                           r"region's domain \(the termination rule or the joint ranges"):
            draw_states(work.est, 10)


def test_a_region_too_thin_to_draw_from_says_which_draw_and_how_to_skip_it() -> None:
    """A validation draw whose band holds none of the first draws names it (not the domain) in one line."""
    from pidlab.region import classifier
    from pidlab.region.coverage import FIRST_DRAWS, draw_states

    spec, loaded = load_spec(SPEC), load_model(IDP)
    settings = ClassifierSettings(("hinge_sin",), (0.1,), samples=100, calibration=100, validation=10, coverage=10)
    with classifier._working(spec, loaded, settings, 1, None) as work:
        never = lambda v: np.zeros(len(v), dtype=bool)  # noqa: E731
        with pytest.raises(RegionError) as err:
            draw_states(work.est, 10, keep=never, kept=classifier.KEPT["edge validation"])
    assert str(err.value) == (
        f"after {FIRST_DRAWS:,} uniform draws only 0 of 10 states lay in the region's edge band: too thin a share "
        "of its domain to draw from uniformly (--edge-share 0 skips the edge draw)"
    )


def test_one_step_room_is_read_from_the_spec_s_region() -> None:
    """benchmarks/one_step_room.py: the shipped full-state region holds a small first action, not a full one."""
    from tests.helpers import benchmark

    room = benchmark("one_step_room")
    rows = {size: (plus, minus) for size, plus, minus, _ in room.one_step_inside(
        str(TUNING / f"{IDP}.pidlab-rescue-full.toml"), (0.05, 1.0))}  # fmt: skip
    assert rows[0.05] == (True, True) and rows[1.0] == (False, False)
    assert room.share_at_least(0.0, 1.0) == 1.0
    assert room.share_at_least(1.96, 1.0) == pytest.approx(0.05, abs=1e-3)  # the normal's 95 % point


def test_the_estimate_is_the_same_on_one_worker(idp_classifier: tuple) -> None:
    spec, r = idp_classifier  # estimated on two workers
    again = estimate_classifier(spec, load_model(IDP), _small(), workers=1)
    assert again.classifier == r.classifier and again.classifier.threshold == r.classifier.threshold
    assert all(
        np.array_equal(a[0], b[0]) for a, b in zip(again.classifier.layers, r.classifier.layers, strict=True)
    )
    assert (again.coverage, again.validation_rounds) == (r.coverage, r.validation_rounds)
