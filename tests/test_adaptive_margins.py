"""The model predictor's inputs and margins: what a network may read, and margins that follow the state.

Mechanics only: which inputs are blind on each env and that a network cannot read them, the margins
of a hand-made scale network, the calibration that covers every error it was calibrated on, the
TOML round trip and its refusals, and that the shield asks each forecast with its own margins.
"""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest

from pidlab.controller.spec import load_spec, save_spec
from pidlab.errors import CoachingError, SpecError
from pidlab.lookup import LOG_LIMIT, MarginScale, ResidualNet, parse_forecast, parse_residual
from pidlab.plant.model import load_model
from pidlab.plant.observation import observe_at
from pidlab.plant.operating_point import resolve_operating_point
from pidlab.region.forecast import (
    ClassifierMarginRegion,
    blind_inputs,
    boxes_in_classifier,
    classifier_points,
    inputs_at_points,
    kept_share,
    learned_forecast,
    margin_region,
    spec_forecast,
)
from pidlab.region.takeover import ClassifierRegion, region_from_bounds
from pidlab.rl.calibrate import _calibrated, measure_forecast
from pidlab.rl.coaching import CoachingWrapper
from pidlab.rl.predict import ModelPredictor, forecast_of
from tests.helpers import TUNING, cli_in_process

IP, IDP, HOPPER = "InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Hopper-v5"
RESCUE = TUNING / f"{IP}.pidlab-rescue.toml"  # a lookup grid
EDGE = TUNING / f"{IP}.pidlab-rescue-edge.toml"  # a classifier region


def _linear_net(w: np.ndarray, b: np.ndarray, variables: tuple[str, ...], blind: tuple[int, ...] = ()) -> ResidualNet:
    """A network with no hidden layer: ``correction(z) = z @ w + b`` (inputs unscaled)."""
    k = w.shape[0]
    return ResidualNet(variables, (0.0,) * k, (1.0,) * k, (1.0,) * w.shape[1], ((w, b),), fitted=1, blind=blind)


# ----------------------------------------------------------------------------- blind inputs


def test_the_positions_an_observation_leaves_out_are_blind() -> None:
    """Gymnasium's walkers leave out the forward position rootx (dof 0); the pendulums observe all."""
    assert blind_inputs(load_model(IP).require_card(), load_model(IP).model) == ()
    assert blind_inputs(load_model(IDP).require_card(), load_model(IDP).model) == ()
    hopper = load_model(HOPPER)
    assert blind_inputs(hopper.require_card(), hopper.model) == (0,)
    assert forecast_of(hopper).blind == (0,)


def test_a_blind_input_cannot_move_the_correction() -> None:
    w = np.array([[5.0], [1.0], [0.0]])
    net = _linear_net(w, np.array([0.5]), ("a",), blind=(0,))
    z = np.array([[0.0, 2.0, 0.0], [100.0, 2.0, 0.0]])
    assert np.allclose(net.correction(z)[:, 0], [2.5, 2.5])  # the walker 100 m on: the same correction
    seeing = dataclasses.replace(net, blind=())
    assert np.allclose(seeing.correction(z)[:, 0], [2.5, 502.5])


def test_fitting_zeroes_the_blind_inputs_and_keeps_them() -> None:
    from pidlab.region.dynamics import fit_residual

    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, size=(600, 3))
    net = fit_residual(x, x[:, 1:2] * 0.5, ("a",), width=8, epochs=3, seed=0, blind=(0,))
    assert net.blind == (0,) and net.input_mean[0] == 0.0 and net.input_scale[0] == 1.0
    moved = x.copy()
    moved[:, 0] += 50.0
    assert np.array_equal(net.correction(x), net.correction(moved))
    back = parse_residual(net.to_table())
    assert back.blind == (0,) and np.array_equal(back.correction(moved), net.correction(x))


@pytest.mark.parametrize(
    ("blind", "message"),
    [([3], r"blind: expected ascending distinct input indices in \[0, 2\]"), ([1, 0], "ascending"),
     ([0, 0], "distinct"), ([True], "input indices"), ("0", "input indices")],
)  # fmt: skip
def test_a_bad_blind_list_is_refused_by_name(blind, message) -> None:
    net = _linear_net(np.ones((3, 2)), np.zeros(2), ("a",))
    net = dataclasses.replace(net, layers=(*net.layers, (np.ones((2, 1)), np.zeros(1))), output_scale=(1.0,))
    table = net.to_table()
    assert parse_residual(table).blind == ()
    with pytest.raises(SpecError, match=message):
        parse_residual({**table, "blind": blind})


def test_a_network_that_reads_a_walkers_forward_position_is_refused() -> None:
    """A learned correction fitted with rootx among its inputs answers for a moved walker unmeasured."""
    hopper = load_model(HOPPER)
    linear = forecast_of(hopper)
    k = linear.Ad.shape[0] + linear.Bd.shape[1]
    net = _linear_net(np.zeros((k, 1)), np.zeros(1), ("rooty_pos",))
    with pytest.raises(CoachingError, match=r"reads inputs \[\] as blind, and this env's are \[0\].*pidlab forecast"):
        learned_forecast(linear, net, hopper.require_card())
    assert learned_forecast(linear, dataclasses.replace(net, blind=(0,)), hopper.require_card()).network.blind == (0,)


# ----------------------------------------------------------------------------- adaptive margins


def test_adaptive_margins_are_the_scaled_prediction_below_the_largest() -> None:
    """sigma(z) = exp(z0 - 1): margins factor * sigma, capped by the ceiling; a NaN row gets the ceiling."""
    net = _linear_net(np.array([[1.0, 1.0], [0.0, 0.0]]), np.array([-1.0, -1.0]), ("a", "b"))
    scale = MarginScale(net, (2.0, 0.5), transitions=10)
    ceiling = np.array([1.0, 1.0])
    z = np.array([[1.0, 0.0], [0.0, 0.0], [np.nan, 0.0], [1e6, 0.0]])
    m = scale.margins(z, ceiling)
    assert np.allclose(m[0], [1.0, 0.5])  # sigma 1: 2 capped at 1, and 0.5
    assert np.allclose(m[1], [2.0 * np.exp(-1.0), 0.5 * np.exp(-1.0)])
    assert np.array_equal(m[2], ceiling) and np.array_equal(m[3], ceiling)  # not finite, or clipped at LOG_LIMIT
    assert np.isfinite(np.exp(LOG_LIMIT))


def test_the_calibration_covers_every_error_it_was_calibrated_on() -> None:
    """factor = the largest error / sigma per variable: hand-computed, and no error above its margin."""
    net = _linear_net(np.array([[1.0, 0.0], [0.0, 1.0]]), np.zeros(2), ("a", "b"))  # sigma = exp(z)
    z = np.log(np.array([[1.0, 2.0], [2.0, 1.0], [4.0, 4.0]]))
    errors = np.array([[0.5, 1.0], [3.0, 0.25], [2.0, 2.0]])
    found = _calibrated(net, errors, z, recorded=99)
    assert np.allclose(found.factors, [1.5, 0.5]) and found.transitions == 99
    margins = found.margins(z, errors.max(axis=0))
    assert np.all(errors <= margins + 1e-12)
    assert np.allclose(margins, [[1.5, 1.0], [3.0, 0.5], [3.0, 2.0]])


def test_a_spec_keeps_its_adaptive_margins_through_a_file(tmp_path, adaptive_measured) -> None:
    spec, found = adaptive_measured
    assert found.adaptive is not None and found.adaptive.transitions == 1500
    assert found.adaptive.network.variables == found.variables and found.adaptive.network.blind == ()
    assert sum(found.agreement.values()) == 400
    back = load_spec(save_spec(_with(spec, found), tmp_path / f"{IP}.x.toml"))
    again = spec_forecast(back.bounds, back.name)
    assert again == found and again.adaptive.factors == found.adaptive.factors
    z = np.random.default_rng(0).normal(size=(20, 5))
    assert np.array_equal(again.margins_at(z), found.margins_at(z))
    assert np.all(found.margins_at(z) <= np.array(found.margins))


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"transitions": 0}, r"adaptive.transitions: 0; expected an integer >= 1"),
        ({"factors": {"hinge_pos": 1.0}}, r"adaptive.factors: expected a table of the variables"),
        ({"extra": 1}, r"adaptive: unknown field\(s\) \['extra'\]"),
        ("reversed", r"adaptive.network.variables: expected the margins' variables"),
    ],
)
def test_a_bad_adaptive_table_is_refused_by_name(adaptive_measured, change, message) -> None:
    table = adaptive_measured[1].to_table()
    adaptive = table["adaptive"]
    if change == "reversed":
        net = adaptive["network"]
        change = {"network": {**net, "variables": net["variables"][::-1]}}
    with pytest.raises(SpecError, match=message):
        parse_forecast({**table, "adaptive": {**adaptive, **change}})


@pytest.fixture(scope="module")
def adaptive_measured():
    """The classifier spec of IP and a small measurement with adaptive margins."""
    spec = load_spec(EDGE)
    found = measure_forecast(spec, load_model(IP), transitions=1500, held_out=400, seed=3, adaptive=1500, width=8,
                             epochs=5)  # fmt: skip
    return spec, found


def _with(spec, found):
    return dataclasses.replace(spec, bounds={**spec.bounds, "forecast": found.to_table()})


def test_the_classifier_region_asks_each_query_with_its_own_margins(adaptive_measured) -> None:
    spec, found = adaptive_measured
    loaded = load_model(IP)
    names = loaded.require_card().observation_names
    region = region_from_bounds(spec.bounds, names, "rescue", spec.name)
    assert isinstance(region, ClassifierRegion)
    shrunk = margin_region(region, found.margin, found.bound, found.pieces, found.adaptive)
    assert isinstance(shrunk, ClassifierMarginRegion)
    clf = region.classifier
    rng = np.random.default_rng(1)
    lo, hi = np.array(clf.lower), np.array(clf.upper)
    ys = lo + (hi - lo) * rng.random((150, len(lo)))
    z = rng.normal(scale=0.3, size=(150, 5))
    per_row = found.margins_at(z)[:, [found.variables.index(v) for v in clf.variables]]
    expected = np.zeros(150, dtype=bool)
    fits = np.all((ys >= lo + per_row) & (ys <= hi - per_row), axis=1)
    expected[fits] = boxes_in_classifier(clf, ys[fits], per_row[fits], region.threshold, bound=found.bound)
    assert np.array_equal(shrunk.hold(ys, z), expected)
    assert np.array_equal(shrunk.hold(ys), shrunk.hold(ys, None))  # no inputs: the largest margins
    obs = np.zeros((150, len(names)))
    obs[:, [names.index(v) for v in clf.variables]] = ys
    assert [shrunk.contains(o, zz) for o, zz in zip(obs, z, strict=True)] == list(expected)


def test_adaptive_margins_are_refused_for_a_lookup_grid(ip_grid_found) -> None:
    spec, found = ip_grid_found
    region = region_from_bounds(spec.bounds, load_model(IP).require_card().observation_names, "rescue", spec.name)
    scale = MarginScale(_linear_net(np.zeros((5, 4)), np.zeros(4), found.variables), (1.0,) * 4, 10)
    with pytest.raises(CoachingError, match="adaptive margins need a classifier rescue region"):
        margin_region(region, found.margin, adaptive=scale)
    with pytest.raises(CoachingError, match="adaptive margins need a classifier rescue region"):
        measure_forecast(spec, load_model(IP), transitions=10, held_out=0, adaptive=1000)


@pytest.fixture(scope="module")
def ip_grid_found():
    spec = load_spec(RESCUE)
    return spec, measure_forecast(spec, load_model(IP), transitions=200, held_out=0, seed=3)


def test_the_model_shield_passes_each_forecasts_inputs(adaptive_measured) -> None:
    """Veto by veto, the shield asks the region with the inputs the predictor made the forecast from."""
    spec, found = adaptive_measured
    loaded = load_model(IP)
    env = CoachingWrapper(gym.make(IP), _with(spec, found), mode="takeover", region="rescue",
                          trigger="predictive", handback=0.5, loaded=loaded, seed=0, predictor="model")  # fmt: skip
    assert isinstance(env.lookahead, ModelPredictor) and env.region.adaptive is not None
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    asked = []
    original = env.region.contains
    env.region.contains = lambda obs, inputs=None: asked.append(inputs) or original(obs, inputs)
    for _ in range(200):
        action = rng.uniform(-3, 3, 1).astype(np.float32)
        d = env.unwrapped.data
        z = env.lookahead.forecast.inputs(loaded.model, d.qpos, d.qvel, d.act, action)
        n = len(asked)
        _, _, terminated, truncated, _ = env.step(action)
        if len(asked) > n:
            assert np.array_equal(asked[n], z)
        if terminated or truncated:
            env.reset()
    assert len(asked) > 50


def test_observed_inputs_read_the_state_back_from_its_observation() -> None:
    """At the operating point: zero; a tilted double pendulum: the hinge read back from its sine."""
    loaded = load_model(IDP)
    card, op, linear = loaded.require_card(), resolve_operating_point(loaded), forecast_of(loaded)
    at_op = observe_at(card, loaded.model, op.qpos, op.qvel)
    assert np.allclose(linear.observed_inputs(loaded.model, at_op), 0.0, atol=1e-12)
    q, v = op.qpos.copy(), op.qvel.copy()
    q[1], v[2] = q[1] + 0.3, v[2] - 0.7
    z = linear.observed_inputs(loaded.model, observe_at(card, loaded.model, q, v))[0]
    nv = loaded.model.nv
    assert np.isclose(z[1], 0.3) and np.isclose(z[nv + 2], -0.7) and np.allclose(z[2 * nv :], 0.0)


def test_the_kept_share_asks_each_point_with_its_own_margins(adaptive_measured) -> None:
    spec, found = adaptive_measured
    loaded = load_model(IP)
    card = loaded.require_card()
    region = region_from_bounds(spec.bounds, card.observation_names, "rescue", spec.name)
    op = resolve_operating_point(loaded)
    base = observe_at(card, loaded.model, op.qpos, op.qvel)
    inputs_of = inputs_at_points(forecast_of(loaded), loaded.model, base, card.observation_names,
                                 region.classifier.variables)  # fmt: skip
    adaptive = kept_share(region, found.margin, samples=500, bound=found.bound, adaptive=found.adaptive,
                          inputs_of=inputs_of)  # fmt: skip
    shrunk = margin_region(region, found.margin, found.bound, None, found.adaptive)
    points = classifier_points(region.classifier, region.threshold, 500, np.random.default_rng(0))
    assert adaptive == float(np.mean(shrunk.hold(points, inputs_of(points))))
    z = inputs_of(points)
    order = [region.classifier.variables.index(n) for n in ("slider_pos", "hinge_pos", "slider_vel", "hinge_vel")]
    assert np.allclose(z[:, :4], points[:, order] - np.r_[op.qpos, op.qvel]) and np.allclose(z[:, 4], 0.0)
    assert kept_share(region, found.margin, samples=500, bound=found.bound) == float(np.mean(shrunk.hold(points)))


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--adaptive", "-1"], "--adaptive -1: expected an integer in [0, 1000000]"),
        (["--adaptive", "10"], "--adaptive 10: expected 0 (constant margins) or at least 1000 transitions"),
        (["--adaptive", "2000"], "adaptive margins need a classifier rescue region"),  # RESCUE: a grid
    ],
)
def test_forecast_refuses_bad_adaptive_options_in_one_line(args, message) -> None:
    code, text = cli_in_process("forecast", str(RESCUE), *args)
    assert code == 2 and message in text and "Traceback" not in text


def test_coverage_asks_each_state_with_the_margins_of_a_forecast_made_there(adaptive_measured) -> None:
    from pidlab.region.coverage import _through_margins

    spec, found = adaptive_measured
    spec = _with(spec, found)
    loaded = load_model(IP)
    names = loaded.require_card().observation_names
    region = region_from_bounds(spec.bounds, names, "rescue", spec.name)
    clf = region.classifier
    rng = np.random.default_rng(4)
    obs = np.zeros((120, len(names)))
    idx = [names.index(v) for v in clf.variables]
    obs[:, idx] = np.array(clf.lower) + (np.array(clf.upper) - np.array(clf.lower)) * rng.random((120, len(idx)))
    shrunk = margin_region(region, found.margin, found.bound, found.pieces, found.adaptive)
    z = forecast_of(loaded).observed_inputs(loaded.model, obs)
    expected = [shrunk.contains(o, zz) for o, zz in zip(obs, z, strict=True)]
    assert list(_through_margins(spec, loaded, names, obs)) == expected
    constant = _with(spec, dataclasses.replace(found, adaptive=None))
    assert list(_through_margins(constant, loaded, names, obs)) == [shrunk.contains(o) for o in obs]


def test_a_grid_with_adaptive_margins_is_refused_not_scored_as_empty(ip_grid_found) -> None:
    """A hand-made spec with adaptive margins on a lookup grid: one line, not a silent 0 % coverage."""
    from pidlab.region.coverage import _through_margins

    spec, found = ip_grid_found
    loaded = load_model(IP)
    names = loaded.require_card().observation_names
    net = _linear_net(np.zeros((5, 3)), np.zeros(3), found.variables)
    net = dataclasses.replace(net, layers=(*net.layers, (np.zeros((3, 4)), np.zeros(4))), output_scale=(1.0,) * 4)
    scale = MarginScale(net, (1.0,) * 4, 10)  # two layers, as a spec's network must have
    bad = _with(spec, dataclasses.replace(found, adaptive=scale))
    with pytest.raises(CoachingError, match="adaptive margins need a classifier rescue region"):
        _through_margins(bad, loaded, names, np.zeros((3, len(names))))
    region = region_from_bounds(spec.bounds, names, "rescue", spec.name)
    with pytest.raises(CoachingError, match="adaptive margins need a classifier rescue region"):
        kept_share(region, found.margin, samples=10, adaptive=scale)
    other = {**spec.bounds["rescue"], "action_fraction": 0.25}  # another region than the one measured on
    stale = dataclasses.replace(spec, bounds={**_with(spec, found).bounds, "rescue": other})
    with pytest.raises(CoachingError, match="measured on another rescue region"):
        _through_margins(stale, loaded, names, np.zeros((3, len(names))))
