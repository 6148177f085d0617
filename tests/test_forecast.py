"""The model predictor: the linear forecast, its measured error, the shrunk region, and the shield it drives.

What is checked is mechanics: the forecast is MuJoCo's own step to first order near the operating
point, the erosion of a grid by hand-computed cases, the measurement's accounts and determinism,
the spec's checks of a stale or incomplete measurement, and that the shield with the model
predictor vetoes exactly the actions whose forecast leaves the shrunk region.
"""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest

from pidlab.controller.spec import load_spec, save_spec
from pidlab.errors import CoachingError, SpecError
from pidlab.lookup import (
    ForecastError,
    LookupGrid,
    RescueClassifier,
    parse_forecast,
    parse_lookup,
    parse_rescue,
    region_digest,
)
from pidlab.plant.model import load_model
from pidlab.plant.operating_point import resolve_operating_point
from pidlab.region import forecast as forecast_module
from pidlab.region.forecast import (
    ClassifierMarginRegion,
    MarginRegion,
    box_in_classifier,
    boxes_in_classifier,
    check_forecastable,
    domain_box,
    forecastable,
    in_domain,
    kept_share,
    margin_region,
    spec_forecast,
)
from pidlab.region.relaxation import lowest_scores
from pidlab.region.takeover import ClassifierRegion, GridRegion, region_from_bounds
from pidlab.rl.calibrate import measure_forecast
from pidlab.rl.coaching import CoachingWrapper
from pidlab.rl.predict import ModelPredictor, forecast_of
from tests.helpers import TUNING, cli_in_process

IP = "InvertedPendulum-v5"
RESCUE = TUNING / f"{IP}.pidlab-rescue.toml"
EDGE = TUNING / f"{IP}.pidlab-rescue-edge.toml"  # a classifier region


@pytest.fixture(scope="module")
def ip():
    return load_model(IP)


@pytest.fixture(scope="module")
def measured(ip):
    """The rescue spec of IP and a small forecast measurement of it."""
    spec = load_spec(RESCUE)
    return spec, measure_forecast(spec, ip, transitions=300, held_out=200, seed=3)


def _with(spec, found: ForecastError):
    return dataclasses.replace(spec, bounds={**spec.bounds, "forecast": found.to_table()})


# ----------------------------------------------------------------------------- the forecast


def test_the_forecast_at_the_operating_point_is_the_operating_point(ip) -> None:
    f = forecast_of(ip)
    op = resolve_operating_point(ip)
    obs = f.observation(ip.model, op.qpos, op.qvel, np.zeros(ip.model.na), op.ctrl)
    card = ip.require_card()
    from pidlab.plant.observation import observe_at

    assert np.allclose(obs, observe_at(card, ip.model, op.qpos, op.qvel), atol=1e-12)


def test_the_forecast_is_mujocos_step_to_first_order(ip) -> None:
    """Halving a perturbation quarters the forecast's error: it is exact to first order."""
    f = forecast_of(ip)
    env = gym.make(IP)
    env.reset(seed=0)
    u = env.unwrapped
    op = resolve_operating_point(ip)
    direction = np.array([0.01, 0.02, -0.05, 0.1])  # slider, hinge, their velocities
    action = np.array([0.3])
    errors = []
    for scale in (1.0, 0.5):
        qpos = op.qpos + scale * direction[:2]
        qvel = op.qvel + scale * direction[2:]
        u.set_state(qpos, qvel)
        guess = f.observation(ip.model, qpos, qvel, u.data.act, scale * action)
        obs, *_ = env.step(scale * action)
        errors.append(np.abs(obs - guess).max())
    env.close()
    assert errors[0] < 1e-3
    assert errors[1] < errors[0] / 3  # quadratic in the perturbation (a 4x drop, with slack)


def test_the_forecast_clamps_the_action_as_mujoco_does(ip) -> None:
    f = forecast_of(ip)
    op = resolve_operating_point(ip)
    act = np.zeros(ip.model.na)
    high = ip.model.actuator_ctrlrange[0, 1]
    at_limit = f.observation(ip.model, op.qpos, op.qvel, act, np.array([high]))
    beyond = f.observation(ip.model, op.qpos, op.qvel, act, np.array([10 * high]))
    assert np.array_equal(at_limit, beyond)


def test_columns_no_joint_state_gives_are_nan() -> None:
    idp = load_model("InvertedDoublePendulum-v5")
    card = idp.require_card()
    f = forecast_of(idp)
    op = resolve_operating_point(idp)
    obs = f.observation(idp.model, op.qpos, op.qvel, np.zeros(idp.model.na), op.ctrl)
    names = card.observation_names
    assert [names[i] for i in np.flatnonzero(np.isnan(obs))] == ["slider_constraint"]
    assert "slider_constraint" not in forecastable(card)
    with pytest.raises(CoachingError, match="slider_constraint.*qfrc_constraint.*predictor = 'exact'"):
        check_forecastable(card, ["hinge_sin", "slider_constraint"], "here")


# ----------------------------------------------------------------------------- the shrunk region


NAMES = ("slider_pos", "hinge_pos", "slider_vel", "hinge_vel")


def _region(table: list[list[int]], guard: dict[str, tuple[float, float]] | None = None) -> GridRegion:
    """hinge_pos over [-0.2, 0.2] rad, hinge_vel over [-2, 2] rad/s."""
    t = np.array(table, dtype=bool)
    grid = LookupGrid(("hinge_pos", "hinge_vel"), (-0.2, -2.0), (0.2, 2.0), t.shape, t, guard or {})
    return GridRegion(grid, NAMES)


def _obs(hinge_pos: float, hinge_vel: float, slider_pos: float = 0.0) -> np.ndarray:
    return np.array([slider_pos, hinge_pos, 0.0, hinge_vel])


def test_the_margin_box_must_touch_only_marked_cells() -> None:
    # 4 x 4 cells of 0.1 rad by 1 rad/s; the cell at hinge_pos [0.1, 0.2], hinge_vel [1, 2] unmarked
    base = _region([[1, 1, 1, 1]] * 3 + [[1, 1, 1, 0]])
    r = MarginRegion(base, {"hinge_pos": 0.02, "hinge_vel": 0.1})
    assert base.contains(_obs(0.09, 1.5)) and r.contains(_obs(0.07, 1.5))
    assert not r.contains(_obs(0.09, 1.5))  # its box reaches 0.11 rad, into the unmarked cell
    assert r.contains(_obs(0.15, 0.85))  # up to 0.95 rad/s: the marked cell below
    assert not r.contains(_obs(0.15, 0.95))
    assert not r.contains(_obs(-0.19, 0.0))  # the box leaves the grid at -0.21 rad
    assert not r.contains(_obs(np.nan, 0.0))
    assert r.inner(0.5).grid is r.grid  # the hand-back asks the rescue region itself of a real state


def test_the_guard_narrows_by_its_margin() -> None:
    region = _region([[1, 1]] * 2, {"slider_pos": (-0.1, 0.1)})
    r = MarginRegion(region, {"hinge_pos": 0.0, "hinge_vel": 0.0, "slider_pos": 0.03})
    assert r.contains(_obs(0.0, 0.0, 0.07)) and not r.contains(_obs(0.0, 0.0, 0.0701))
    with pytest.raises(CoachingError, match="slider_pos.*at least half.*predictor = 'exact'"):
        MarginRegion(region, {"hinge_pos": 0.0, "hinge_vel": 0.0, "slider_pos": 0.1})
    with pytest.raises(CoachingError, match="hinge_vel"):
        MarginRegion(region, {"hinge_pos": 0.0, "hinge_vel": 2.0, "slider_pos": 0.0})


def test_a_forecast_the_shrunk_region_passes_lies_in_the_regions_domain_box() -> None:
    region = _region([[1, 1]] * 2, {"slider_pos": (-0.1, 0.1)})
    lo, hi = domain_box(region)
    assert lo.tolist() == [-0.2, -2.0, -0.1] and hi.tolist() == [0.2, 2.0, 0.1]  # grid, then the guard
    assert in_domain(region, [[0.0, 1.9, 0.1], [0.0, 2.1, 0.0]]).tolist() == [True, False]
    shrunk = MarginRegion(region, {"hinge_pos": 0.01, "hinge_vel": 0.1, "slider_pos": 0.01})
    rng = np.random.default_rng(5)
    for y in rng.uniform(-2.5, 2.5, size=(400, 3)) * [0.1, 1.0, 0.05]:
        if shrunk.contains(_obs(y[0], y[1], y[2])):
            assert in_domain(region, y[None, :])[0]


def test_the_kept_share_of_a_full_grid_is_the_shrunk_volume() -> None:
    region = _region([[1] * 4] * 4, {"slider_pos": (-0.1, 0.1)})
    margins = {"hinge_pos": 0.04, "hinge_vel": 0.5, "slider_pos": 0.05}
    expected = (0.32 / 0.4) * (3.0 / 4.0) * (0.1 / 0.2)  # each range less twice its margin
    assert kept_share(region, margins, samples=40000) == pytest.approx(expected, abs=0.01)
    assert kept_share(region, {**margins, "slider_pos": 0.1}) == 0.0


# ----------------------------------------------------------------------------- a classifier region


def _net(w1, b1, w2, b2, lower=(-1.0,), upper=(1.0,), threshold=0.0) -> RescueClassifier:
    layers = ((np.array(w1, dtype=float), np.array(b1, dtype=float)),
              (np.array(w2, dtype=float), np.array(b2, dtype=float)))  # fmt: skip
    return RescueClassifier(("hinge_pos",), lower, upper, layers, threshold)


def test_the_score_bound_of_a_monotone_network_is_its_value_at_the_box_end() -> None:
    # score = tanh(2 x) on [-1, 1] (scaled x is x): over 0.5 +- 0.25 the lowest is tanh(0.5)
    up = _net([[2.0]], [0.0], [[1.0]], [0.0])
    assert lowest_scores(up, np.array([[0.5]]), np.array([0.25]))[0] == pytest.approx(np.tanh(0.5), abs=1e-12)
    down = _net([[2.0]], [0.0], [[-1.0]], [0.0])  # -tanh(2 x): the lowest at the upper end
    assert lowest_scores(down, np.array([[0.5]]), np.array([0.25]))[0] == pytest.approx(-np.tanh(1.5), abs=1e-12)
    points = np.array([[-0.7], [0.1], [0.9]])
    assert np.array_equal(lowest_scores(up, points, np.zeros(1)), up.scores(points))  # no margin: the score


def test_halving_proves_a_box_the_interval_bound_alone_cannot() -> None:
    # score = tanh(3 x) + tanh(-3 x) = 0 everywhere; the interval bound over x in [-0.5, 0.5] is
    # -2 tanh(1.5) < -0.1, over each of 256 pieces -2 tanh(3 * 0.5 / 256) > -0.1
    flat = _net([[3.0, -3.0]], [0.0, 0.0], [[1.0], [1.0]], [0.0])
    centre, margin = np.array([0.0]), np.array([0.5])
    assert lowest_scores(flat, centre[None, :], margin)[0] == pytest.approx(-2 * np.tanh(1.5))
    assert not box_in_classifier(flat, centre, margin, -0.1, splits=0)
    assert box_in_classifier(flat, centre, margin, -0.1, splits=8)
    assert not box_in_classifier(flat, centre, margin, 0.1, splits=8)  # no state scores 0.1: never proven
    bump = _net([[2.0]], [0.0], [[1.0]], [0.0])  # tanh(2 x): a piece's centre below the threshold fails
    assert not box_in_classifier(bump, np.array([0.0]), np.array([0.3]), 0.0, splits=8)


def test_a_cap_on_a_querys_boxes_refuses_exactly_the_proofs_that_need_more(monkeypatch) -> None:
    # tanh(3 x) + tanh(-3 x) >= -0.1 over 0 +- 0.5: the bound of a piece c +- r is
    # tanh(3 c - 3 r) - tanh(3 c + 3 r). Pieces of r = 0.5, 0.25, 0.125 prove none (1, 2, 4 boxes);
    # of the 8 of r = 0.0625 only c = +-0.4375 (tanh(1.125) - tanh(1.5) = -0.096); the 6 open ones
    # halve into 12 of r = 0.03125, of which c = +-0.34375, +-0.28125 prove (-0.099, -0.098); the
    # 8 open ones into 16 of r = 0.015625, all proven (the worst, c = r: -tanh(0.09375) = -0.093).
    # So the proof asks 1 + 2 + 4 + 8 + 12 + 16 = 43 boxes, at most 16 at one halving.
    flat = _net([[3.0, -3.0]], [0.0, 0.0], [[1.0], [1.0]], [0.0])
    asked: list[int] = []
    proven = forecast_module._proven

    def counted(clf, c, m, threshold, bound):
        asked.append(len(c))
        return proven(clf, c, m, threshold, bound)

    monkeypatch.setattr(forecast_module, "_proven", counted)
    found = {}
    for pieces in (None, 16, 15, 8, 1):
        asked.clear()
        found[pieces] = (box_in_classifier(flat, np.array([0.0]), np.array([0.5]), -0.1, pieces=pieces), list(asked))
    assert found[None] == found[16] == (True, [1, 2, 4, 8, 12, 16])
    assert found[15] == (False, [1, 2, 4, 8, 12])  # the next halving would ask 16 boxes
    assert found[8] == (False, [1, 2, 4, 8])  # 12 > 8
    assert found[1] == (False, [1])  # no halving at all


def test_a_capped_query_proves_a_subset_of_the_uncapped_ones() -> None:
    clf = parse_rescue(load_spec(EDGE).bounds["rescue"])
    lo, hi = np.array(clf.lower), np.array(clf.upper)
    margins = (hi - lo) * 0.02
    centres = lo + margins + (hi - lo - 2 * margins) * np.random.default_rng(5).random((300, len(lo)))
    free = boxes_in_classifier(clf, centres, margins, clf.threshold, bound="linear")
    assert np.array_equal(boxes_in_classifier(clf, centres, margins, clf.threshold, bound="linear", pieces=256), free)
    proofs = [free.sum()]
    for pieces in (16, 4, 1):
        capped = boxes_in_classifier(clf, centres, margins, clf.threshold, bound="linear", pieces=pieces)
        assert not np.any(capped & ~free)  # a cap only refuses
        one_by_one = [box_in_classifier(clf, c, margins, clf.threshold, bound="linear", pieces=pieces) for c in centres]
        assert capped.tolist() == one_by_one  # the cap is per query, also in a batch
        proofs.append(capped.sum())
    assert proofs == sorted(proofs, reverse=True) and proofs[-1] < proofs[0]


def test_the_linear_bound_is_the_hand_computed_relaxation() -> None:
    # tanh(3 x) + tanh(-3 x) over 0.5 +- 0.25: the units' pre-activations span [0.75, 2.25] and
    # [-2.25, -0.75], both relaxed by lines of slope k = 1 - tanh(2.25)^2; the x terms cancel and
    # the lower lines' offsets give tanh(0.75) - tanh(2.25) + 1.5 k (the interval bound: tanh(0.75) - tanh(2.25))
    flat = _net([[3.0, -3.0]], [0.0, 0.0], [[1.0], [1.0]], [0.0])
    k = 1.0 - np.tanh(2.25) ** 2
    expected = np.tanh(0.75) - np.tanh(2.25) + 1.5 * k
    centre, margin = np.array([[0.5]]), np.array([0.25])
    assert lowest_scores(flat, centre, margin, "linear")[0] == pytest.approx(expected, abs=1e-12)
    assert lowest_scores(flat, centre, margin)[0] == pytest.approx(np.tanh(0.75) - np.tanh(2.25), abs=1e-12)
    up = _net([[2.0]], [0.0], [[1.0]], [0.0])  # monotone: the line through the box's low end is exact there
    assert lowest_scores(up, centre, margin, "linear")[0] == pytest.approx(np.tanh(0.5), abs=1e-12)
    # -0.343 by intervals, -0.278 by lines: only the linear bound proves -0.3 without a halving
    assert box_in_classifier(flat, centre[0], margin, -0.3, splits=0, bound="linear")
    assert not box_in_classifier(flat, centre[0], margin, -0.3, splits=0)


@pytest.mark.parametrize("spec_file", [EDGE, TUNING / "InvertedDoublePendulum-v5.pidlab-rescue-full-learned.toml"])
def test_the_linear_bound_is_sound_and_proves_more(spec_file) -> None:
    """No state of a box (corners included) scores below either bound, at every box size; the linear
    bound proves at least every box the interval bound proves, and more on the forecast's small boxes."""
    clf = parse_rescue(load_spec(spec_file).bounds["rescue"])
    lo, hi = np.array(clf.lower), np.array(clf.upper)
    rng = np.random.default_rng(4)
    for size in (0.005, 0.05, 0.3):
        margins = (hi - lo) * size
        centres = lo + (hi - lo) * rng.random((200, len(lo)))
        linear, interval = lowest_scores(clf, centres, margins, "linear"), lowest_scores(clf, centres, margins)
        samples = centres[:, None, :] + margins * rng.choice([-1.0, 1.0, 0.3, -0.7], size=(200, 40, len(lo)))
        lowest = clf.scores(samples.reshape(-1, len(lo))).reshape(200, 40).min(axis=1)
        assert np.all(lowest >= linear - 1e-9) and np.all(lowest >= interval - 1e-9)
    margins = (hi - lo) * 0.01
    centres = lo + margins + (hi - lo - 2 * margins) * rng.random((300, len(lo)))
    by_interval = boxes_in_classifier(clf, centres, margins, clf.threshold)
    by_linear = boxes_in_classifier(clf, centres, margins, clf.threshold, bound="linear")
    assert np.all(by_linear >= by_interval) and by_linear.sum() > by_interval.sum()


@pytest.mark.parametrize("bound", ["interval", "linear"])
def test_a_proven_box_holds_no_state_below_the_threshold(bound) -> None:
    spec = load_spec(EDGE)
    clf = parse_rescue(spec.bounds["rescue"])
    lo, hi = np.array(clf.lower), np.array(clf.upper)
    rng = np.random.default_rng(1)
    margins = (hi - lo) * 0.02
    proven = 0
    centres = lo + margins + (hi - lo - 2 * margins) * rng.random((300, len(lo)))
    one_by_one = [box_in_classifier(clf, centre, margins, clf.threshold, bound=bound) for centre in centres]
    assert boxes_in_classifier(clf, centres, margins, clf.threshold, bound=bound).tolist() == one_by_one
    for centre, ok in zip(centres, one_by_one, strict=True):
        if ok:
            proven += 1
            inside = centre + margins * rng.uniform(-1, 1, size=(200, len(lo)))
            corners = centre + margins * rng.choice([-1.0, 1.0], size=(64, len(lo)))
            assert clf.scores(np.vstack([inside, corners])).min() >= clf.threshold
    assert proven > 0


def test_the_classifier_margin_region_asks_the_whole_box(ip) -> None:
    spec = load_spec(EDGE)
    names = ip.require_card().observation_names
    region = region_from_bounds(spec.bounds, names, "rescue", spec.name)
    assert isinstance(region, ClassifierRegion)
    none = {v: 0.0 for v in region.variables}
    exact = margin_region(region, none)
    assert isinstance(exact, ClassifierMarginRegion)
    rng = np.random.default_rng(2)
    clf = region.classifier
    lo, hi = np.array(clf.lower), np.array(clf.upper)
    for y in lo + (hi - lo) * rng.random((200, len(lo))):
        obs = np.zeros(len(names))
        obs[[names.index(v) for v in clf.variables]] = y
        assert exact.contains(obs) == region.contains(obs)  # zero margins: the region itself
    wide = margin_region(region, {v: 0.5 * (h - lo_) * 0.1 for v, lo_, h in zip(clf.variables, lo, hi, strict=True)})
    assert wide.inner(0.5).threshold == region.inner(0.5).threshold  # the hand-back: real states
    assert not wide.contains(np.full(len(names), np.nan)) and wide.scale == 1.0
    with pytest.raises(CoachingError, match="hinge_pos.*at least half.*predictor = 'exact'"):
        margin_region(region, {**none, "hinge_pos": 0.2})
    with pytest.raises(CoachingError, match="bound='cubic': expected one of interval, linear"):
        margin_region(region, none, "cubic")
    with pytest.raises(CoachingError, match=r"pieces=0: expected an integer in \[1, 65536\] \(or none: no cap\)"):
        margin_region(region, none, "linear", 0)
    assert margin_region(region, none, "linear", 4).pieces == 4
    assert kept_share(region, none, samples=2000) == 1.0
    assert 0.0 < kept_share(region, {v: 0.02 * (h - lo_) for v, lo_, h in zip(clf.variables, lo, hi, strict=True)},
                            samples=2000) < 1.0  # fmt: skip


@pytest.fixture(scope="module")
def edge_measured(ip):
    """The classifier spec of IP and a small forecast measurement of it."""
    spec = load_spec(EDGE)
    return spec, measure_forecast(spec, ip, transitions=300, held_out=200, seed=3)


def test_the_model_shield_proves_each_forecasts_box_in_a_classifier_region(ip, edge_measured) -> None:
    spec, found = edge_measured
    assert found.variables == tuple(spec.bounds["rescue"]["variables"])
    assert sum(found.agreement.values()) == 200
    env = _shield(_with(spec, found), ip, predictor="model")
    assert isinstance(env.region, ClassifierMarginRegion) and env.region.margins == found.margin
    assert env.region.pieces is None
    capped = _shield(_with(spec, dataclasses.replace(found, pieces=8)), ip, predictor="model")
    assert capped.region.pieces == 8  # the spec's cap is the shield's
    _vetoes_exactly_the_boxes_that_leave(env, 300)


# ----------------------------------------------------------------------------- the measurement


def test_the_measurement_accounts_for_every_action_and_repeats(ip, measured) -> None:
    spec, found = measured
    rescue = spec.bounds["rescue"]
    grid = parse_lookup(rescue)
    assert found.variables == (*grid.variables, *grid.guard)
    assert found.region == region_digest(rescue)
    assert sum(found.agreement.values()) == found.held_out == 200
    assert 0 <= found.escapes <= 200
    assert all(m >= p >= d >= 0 for m, p, d in zip(found.margins, found.p99, found.median, strict=True))
    assert max(found.margins) > 0
    assert measure_forecast(spec, ip, transitions=300, held_out=200, seed=3) == found
    assert parse_forecast(found.to_table()) == found
    assert found.bound == "linear" and found.to_table()["bound"] == "linear"
    assert found.scope == "domain" and 0 < found.in_scope <= 300 and found.held_out_in_scope <= 200
    assert found.escapes <= found.held_out_in_scope
    older = ("bound", "scope", "in_scope", "held_out_in_scope")  # measured before these fields
    published = {k: v for k, v in found.to_table().items() if k not in older}
    assert parse_forecast(published).bound == "interval" and parse_forecast(published).scope == "all"
    assert "pieces" not in found.to_table() and found.pieces is None  # no cap: the table as before
    capped = dataclasses.replace(found, pieces=32)
    assert capped.to_table()["pieces"] == 32 and parse_forecast(capped.to_table()) == capped


def test_no_forecast_in_scope_is_refused_in_one_line() -> None:
    from pidlab.rl.calibrate import _in_scope

    err = np.ones((10, 2))
    with pytest.raises(CoachingError, match="no forecast of the 6 transitions lies in the rescue region's domain box"):
        _in_scope("x", err, np.array([False] * 6 + [True] * 4), 6)
    fitted, check = _in_scope("x", err, np.array([True, False] * 5), 6)
    assert len(fitted) == 3 and len(check) == 2


def test_margins_over_all_transitions_cover_those_in_the_domain(ip, measured) -> None:
    """The same recording: the margins of every transition are at least those whose forecast lies in
    the region's domain box, a subset of them."""
    spec, found = measured
    every = measure_forecast(spec, ip, transitions=300, held_out=200, seed=3, scope="all")
    assert every.scope == "all" and every.in_scope is None and "in_scope" not in every.to_table()
    assert all(a >= d for a, d in zip(every.margins, found.margins, strict=True))
    assert every.margins != found.margins  # here 19 of the 300 forecasts left the domain box


def test_a_spec_keeps_its_forecast_through_a_file(tmp_path, measured) -> None:
    spec, found = measured
    path = save_spec(_with(spec, found), tmp_path / f"{IP}.x.toml")
    back = load_spec(path)
    assert spec_forecast(back.bounds, back.name) == found


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"model": "quadratic"}, r"model: 'quadratic'; expected one of linear"),
        ({"region": ""}, r"region: expected the digest"),
        ({"transitions": 0}, r"transitions: 0; expected an integer >= 1"),
        ({"escapes": 10**6}, r"escapes: 1000000 of 200 held-out"),
        ({"margins": {"hinge_pos": -1.0}}, r"margins: expected a table"),
        ({"median": {"hinge_pos": 0.0}}, r"median: expected a table of the variables"),
        (
            {"agreement": {"both": 1, "exact_only": 0, "model_only": 0, "neither": 0}},
            r"add up to 1, not to the 200",
        ),
        ({"extra": 1}, r"unknown field\(s\) \['extra'\]"),
        ({"bound": "cubic"}, r"bound: 'cubic'; expected one of interval, linear"),
        ({"bound": ["linear"]}, r"bound: \['linear'\]; expected one of"),
        ({"scope": "everywhere"}, r"scope: 'everywhere'; expected one of all, domain"),
        ({"pieces": 0}, r"pieces: 0; expected an integer in \[1, 65536\] \(or no pieces: no cap\)"),
        ({"pieces": True}, r"pieces: True; expected an integer in \[1, 65536\]"),
        ({"pieces": 2.5}, r"pieces: 2.5; expected an integer in \[1, 65536\]"),
        ({"pieces": 65537}, r"pieces: 65537; expected an integer in \[1, 65536\]"),
        ({"in_scope": 301}, r"in_scope: 301; expected an integer in \[1, transitions = 300\]"),
        ({"held_out_in_scope": -1}, r"held_out_in_scope: -1; expected an integer in \[0, held_out = 200\]"),
        ({"scope": "all"}, r"scope 'domain' needs in_scope and held_out_in_scope; scope 'all' has neither"),
    ],
)
def test_a_bad_forecast_table_is_refused_by_name(measured, change, message) -> None:
    table = {**measured[1].to_table(), **change}
    with pytest.raises(SpecError, match=message):
        parse_forecast(table)


def test_the_model_predictor_needs_a_current_complete_measurement(measured) -> None:
    spec, found = measured
    with pytest.raises(CoachingError, match="no \\[bounds.forecast\\].*pidlab forecast SPEC --write"):
        spec_forecast(spec.bounds, spec.name)
    stale = dataclasses.replace(found, region="0" * 16)
    with pytest.raises(CoachingError, match="another rescue region"):
        spec_forecast(_with(spec, stale).bounds, spec.name)
    partial = dataclasses.replace(found, variables=found.variables[:1], margins=found.margins[:1],
                                  median=found.median[:1], p99=found.p99[:1])  # fmt: skip
    with pytest.raises(CoachingError, match="no margin for"):
        spec_forecast(_with(spec, partial).bounds, spec.name)


# ----------------------------------------------------------------------------- the shield


def _shield(spec, ip, **kwargs):
    return CoachingWrapper(gym.make(IP), spec, mode="takeover", region="rescue", trigger="predictive",
                           handback=0.5, view="terminal", loaded=ip, seed=0, **kwargs)  # fmt: skip


def test_the_model_shield_vetoes_exactly_the_forecasts_whose_box_leaves_the_region(ip, measured) -> None:
    spec, found = measured
    env = _shield(_with(spec, found), ip, predictor="model")
    assert isinstance(env.lookahead, ModelPredictor)
    assert isinstance(env.region, MarginRegion) and env.region.margins == found.margin
    with pytest.raises(CoachingError, match="pieces=8: a cap on a query's boxes is for a classifier region"):
        _shield(_with(spec, dataclasses.replace(found, pieces=8)), ip, predictor="model")  # a grid: no boxes
    _vetoes_exactly_the_boxes_that_leave(env, 400)


def _vetoes_exactly_the_boxes_that_leave(env, steps: int) -> None:
    """Random actions: each is vetoed exactly when its forecast's box leaves the region (or the env ends it)."""
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    vetoes = 0
    for _ in range(steps):
        action = rng.uniform(-3, 3, size=1).astype(np.float32)
        outside = not env.region.contains(env.lookahead.predict(action))
        terminal = env.lookahead.terminal  # a forecast state the env's termination rule ends
        _, _, terminated, truncated, info = env.step(action)
        assert info["vetoed"] == (outside or terminal)
        vetoes += int(info["vetoed"])
        if terminated or truncated:
            env.reset()
    assert vetoes > 0 and env.total_falls == 0
    env.close()


def test_the_model_predictor_is_refused_where_it_cannot_serve(ip, measured) -> None:
    spec, found = measured
    with pytest.raises(CoachingError, match="no \\[bounds.forecast\\]"):
        _shield(spec, ip, predictor="model")
    with pytest.raises(CoachingError, match="use trigger = 'predictive'"):
        CoachingWrapper(gym.make(IP), spec, mode="takeover", region="rescue", predictor="model", loaded=ip)
    with pytest.raises(CoachingError, match="predictor 'oracle': expected one of exact, model"):
        _shield(spec, ip, predictor="oracle")
    coarse = dataclasses.replace(found, margins=tuple(10.0 for _ in found.margins))
    with pytest.raises(CoachingError, match="nothing is left"):
        _shield(_with(spec, coarse), ip, predictor="model")


# ----------------------------------------------------------------------------- the command


def test_forecast_writes_a_named_copy_of_the_spec(tmp_path) -> None:
    out = tmp_path / f"{IP}.my-model.toml"
    code, text = cli_in_process(
        "forecast", str(RESCUE), "--transitions", "100", "--held-out", "50", "-o", str(out)
    )
    assert code == 0, text
    spec = load_spec(out)
    assert spec.name == "my-model"
    assert spec_forecast(spec.bounds, spec.name).transitions == 100
    assert load_spec(RESCUE).bounds.get("forecast") is None  # the source spec is untouched


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--write", "-o", "x.toml"], "--write and --output: choose one"),
        (["--transitions", "0"], "--transitions 0: expected an integer in [1, 1000000]"),
        (["--transitions", "9" * 20], "expected an integer in [1, 1000000]"),  # not hours of recording
        (["--held-out", "-1"], "--held-out -1: expected an integer in [0, 1000000]"),
        (["--seed", "-1"], "--seed -1: expected an integer in [0, 4294967295]"),
        (["--model", "quadratic"], "--model 'quadratic': expected one of linear, learned"),
        (["--model", "learned", "--fit", "10"], "--fit 10: expected an integer in [100, 1000000]"),
        (["--model", "learned", "--width", "1"], "--width 1: expected an integer in [2, 512]"),
        (["--width", "-1"], "--width: sets a network (--model learned or --adaptive N); expected it with one"),
        (["--epochs", "5"], "--epochs: sets a network (--model learned or --adaptive N); expected it with one"),
        (["--fit", "200"], "--fit: the actions a learned correction is fitted on; expected it with --model learned"),
        (["--adaptive", "1000", "--fit", "200"], "--fit: the actions a learned correction is fitted on"),
        (["--bound", "cubic"], "--bound 'cubic': expected one of interval, linear"),
        (["--scope", "near"], "--scope 'near': expected one of all, domain"),
        (["--pieces", "0"], "--pieces 0: expected an integer in [1, 65536] (or none: no cap)"),
        (["--pieces", "9" * 23], "expected an integer in [1, 65536]"),  # TOML holds no such integer
        (["--pieces", "64"], "--pieces 64: a cap on a query's boxes is for a classifier region; this rescue "
         "region is a lookup grid"),  # RESCUE's region is a grid
    ],
)
def test_forecast_refuses_bad_options_in_one_line(args, message) -> None:
    code, text = cli_in_process("forecast", str(RESCUE), *args)
    assert code == 2
    assert message in text
    assert "Traceback" not in text


def test_forecast_refuses_a_spec_without_a_rescue_region() -> None:
    code, text = cli_in_process("forecast", str(TUNING / f"{IP}.paper.toml"))
    assert code == 2
    assert "no rescue region; run `pidlab rescue SPEC --write` first" in text


def test_the_published_forecast_tables_are_the_files_own() -> None:
    """docs/rescue.md's forecast rows that take seconds are what benchmarks/forecast_table.py makes.

    Every row but Hopper's classifier rows, and the training table; the whole page is checked by
    ``benchmarks/recompute.py`` (the audit), as those rows take minutes.
    """
    import sys

    from tests.helpers import ROOT

    sys.path.insert(0, str(ROOT / "benchmarks"))
    import forecast_table

    page = forecast_table.page_tables().splitlines()
    quick = forecast_table.quick_specs()
    assert 0 < len(quick) < len(forecast_table.SPECS)
    for spec in quick:
        assert forecast_table.row(*spec) in page, f"{spec[:2]}: run benchmarks/forecast_table.py"
    assert forecast_table.training_table() in forecast_table.page_tables()


def test_the_audit_checks_the_whole_forecast_page(monkeypatch) -> None:
    """benchmarks/recompute.py compares the page's tables with all of forecast_table.py's (slow rows too)."""
    import sys

    from tests.helpers import ROOT

    sys.path.insert(0, str(ROOT / "benchmarks"))
    import forecast_table
    import recompute

    monkeypatch.setattr(forecast_table, "tables", lambda: forecast_table.page_tables() + "\n| one row more |")
    assert recompute.check_forecast() == [forecast_table.MISMATCH]
    monkeypatch.setattr(forecast_table, "tables", lambda: "\n" + forecast_table.page_tables() + "\n")
    assert recompute.check_forecast() == []


@pytest.mark.parametrize("lean", [0.195, -0.195])
def test_both_predictors_say_when_the_next_state_is_one_the_env_ends(lean):
    """A state past a termination limit lies in no rescue region: each look-ahead flags it."""
    from pidlab.rl.predict import Predictor, observed_limits

    loaded = load_model(IP)
    card = loaded.require_card()
    assert [(card.observation_names[i], k.signal) for i, k in observed_limits(card)] == [
        ("hinge_pos", "hinge_pos")
    ]
    env = gym.make(IP)
    env.reset(seed=0)
    exact, model = Predictor(env, card), ModelPredictor(env, loaded)
    d = env.unwrapped.data
    hinge = card.observation_names.index("hinge_pos")
    for rate, ends in ((0.0, False), (np.sign(lean) * 3.0, True)):  # 3 rad/s outward: past 0.2 rad in 0.04 s
        d.qpos[:] = [0.0, lean]
        d.qvel[:] = [0.0, rate]
        for p in (exact, model):
            obs = p.predict(np.zeros(1))
            assert p.terminal is ends and bool(abs(obs[hinge]) > 0.2) is ends


# ----------------------------------------------------------------------------- a learned correction


def test_a_fitted_correction_learns_what_the_linear_model_misses_and_repeats() -> None:
    from pidlab.region.dynamics import fit_residual

    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, size=(3000, 3))
    missed = np.stack([np.sin(2 * x[:, 0]) * 0.1, x[:, 1] * x[:, 2]], axis=1)
    net = fit_residual(x[:2500], missed[:2500], ("a", "b"), width=32, epochs=200, seed=1)
    assert net.fitted == 2500 and net.inputs == 3 and net.variables == ("a", "b")
    error, raw = np.abs(net.correction(x[2500:]) - missed[2500:]), np.abs(missed[2500:])
    assert np.all(np.median(error, axis=0) < 0.1 * np.median(raw, axis=0))  # on transitions it never saw
    assert np.all(error.max(axis=0) < 0.25 * raw.max(axis=0))
    again = fit_residual(x[:2500], missed[:2500], ("a", "b"), width=32, epochs=200, seed=1)
    assert all(np.array_equal(w1, w2) and np.array_equal(b1, b2)
               for (w1, b1), (w2, b2) in zip(net.layers, again.layers, strict=True))  # fmt: skip


@pytest.fixture(scope="module")
def learned(ip):
    """The rescue spec of IP and a small learned forecast measurement of it."""
    spec = load_spec(RESCUE)
    return spec, measure_forecast(spec, ip, transitions=300, held_out=200, seed=3, model="learned", fit=400,
                                  width=8, epochs=5)  # fmt: skip


def test_the_learned_measurement_keeps_its_network_through_a_file(tmp_path, learned) -> None:
    spec, found = learned
    assert found.model == "learned" and found.network is not None and found.network.fitted == 400
    assert found.network.variables == found.variables
    assert sum(found.agreement.values()) == 200
    back = load_spec(save_spec(_with(spec, found), tmp_path / f"{IP}.x.toml"))
    again = spec_forecast(back.bounds, back.name)
    assert again == found
    assert all(np.array_equal(w1, w2) for (w1, _), (w2, _) in zip(again.network.layers, found.network.layers,
                                                                     strict=True))  # fmt: skip


def test_the_model_shield_asks_the_learned_forecast(ip, learned) -> None:
    from pidlab.region.forecast import LearnedForecast

    spec, found = learned
    env = _shield(_with(spec, found), ip, predictor="model")
    assert isinstance(env.lookahead.forecast, LearnedForecast)
    _vetoes_exactly_the_boxes_that_leave(env, 300)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"model": "linear"}, r"network: only model = 'learned' has a network"),
        ({"network": None}, r"network: a learned model needs its network"),
        ({"network": {"fitted": 0}}, r"network.fitted: 0; expected an integer >= 1"),
        ({"network": {"output_scale": [-1.0] * 4}}, r"input_scale and output_scale must be > 0"),
        ({"network": {"variables": []}}, r"network.variables: expected distinct observation variable names"),
        ({"network": {"extra": 1}}, r"network: unknown field\(s\) \['extra'\]"),
        ({"network": {"variables": ["hinge_pos"], "output_scale": [1.0]}}, r"network.layers\[2\].bias: 4 entries"),
        ("reversed", r"network.variables: expected the margins' variables"),
    ],
)
def test_a_bad_learned_table_is_refused_by_name(learned, change, message) -> None:
    table = learned[1].to_table()
    if change == "reversed":
        change = {"network": {**table["network"], "variables": table["network"]["variables"][::-1]}}
    if "network" in change and isinstance(change["network"], dict):
        change = {"network": {**table["network"], **change["network"]}}
    table = {k: v for k, v in {**table, **change}.items() if v is not None}
    with pytest.raises(SpecError, match=message):
        parse_forecast(table)


def test_a_learned_network_for_another_model_is_refused(ip, learned) -> None:
    from pidlab.region.forecast import learned_forecast

    net = learned[1].network
    card = ip.require_card()
    short = dataclasses.replace(net, input_mean=net.input_mean[:-1], input_scale=net.input_scale[:-1])
    with pytest.raises(CoachingError, match="fitted for another model"):
        learned_forecast(forecast_of(ip), short, card)
    with pytest.raises(CoachingError, match="corrects 'pole'"):
        learned_forecast(forecast_of(ip), dataclasses.replace(net, variables=("pole", *net.variables[1:])), card)
    # refused before any run: where a run (or an experiment's conditions) asks for the model region
    from pidlab.rl.coaching import model_region

    (w, b), *rest = net.layers
    fitting = dataclasses.replace(short, layers=((w[:-1], b), *rest))  # a consistent network of 4 inputs
    spec = _with(learned[0], dataclasses.replace(learned[1], network=fitting))
    region = region_from_bounds(spec.bounds, card.observation_names, "rescue", spec.name)
    with pytest.raises(CoachingError, match="pidlab-rescue: the learned forecast takes 4 inputs.*another model"):
        model_region(spec, ip, region)
