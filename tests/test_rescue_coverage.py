"""Rescue coverage over a named domain (pidlab.region.coverage) and starts on the floor in the
region estimates (pidlab.region.rescue).

Real MuJoCo and the coach's real law; what is checked is mechanics (which states are drawn, what
is counted, determinism), plus one reading that follows from the region's variables: a region
over the torso's pitch alone claims states whose legs the coach cannot bring back.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from scipy.stats import binomtest

from pidlab.controller.spec import load_spec
from pidlab.errors import RegionError
from pidlab.region.coverage import (
    NEAR_SCALES,
    DomainCoverage,
    DomainSettings,
    _reach,
    _round_up,
    _score,
    draw_near,
    draw_states,
    measure_domain_coverage,
)
from pidlab.region.rescue import _rescued, simulations, state_domain
from tests.helpers import TUNING, cli_in_process

IP, HOPPER = "InvertedPendulum-v5", "Hopper-v5"
IP_DOMAIN = DomainSettings(("hinge_pos", "slider_pos", "hinge_vel", "slider_vel"), (0.2, 1.0, 4.0, 1.5), states=150)
HOPPER_LEGS = ("rooty_pos", "thigh_joint_pos", "leg_joint_pos", "foot_joint_pos")


def _spec(env: str, name: str = "pidlab-rescue"):
    return load_spec(TUNING / f"{env}.{name}.toml")


def _estimate(spec, loaded, settings):
    def domain_of(card, model, y_op):
        return state_domain(settings.variables, settings.half_range, card, model, y_op)

    return simulations(spec, loaded, settings, domain_of, 1)


def test_scores_are_counted_as_by_hand() -> None:
    inside = np.array([1, 1, 1, 0, 0, 1], dtype=bool)
    rescued = np.array([1, 0, 1, 1, 0, 1], dtype=bool)
    s = _score("rescue region", inside, rescued)
    ci = binomtest(1, 4).proportion_ci(0.95)
    assert (s.inside, s.held, s.coverage, s.false_claims) == (4, 3, 0.75, 0.25)
    assert s.false_claims_ci == pytest.approx((ci.low, ci.high))
    empty = _score("box", np.zeros(6, dtype=bool), rescued)
    assert empty.inside == 0 and empty.coverage == 0.0 and np.isnan(empty.false_claims)


def test_the_rescued_states_reach_is_counted_as_by_hand() -> None:
    from types import SimpleNamespace

    domain = SimpleNamespace(lower=(-1.0, 1.0), upper=(1.0, 3.0))  # centres 0 and 2
    states = np.array([[0.1, 1.5], [-0.3, 2.2], [0.9, 2.9]])
    reach, reach95 = _reach(states, domain, np.array([True, True, False]))  # the third is not rescued
    assert reach == pytest.approx((0.3, 0.5)) and reach95 == pytest.approx((0.29, 0.485))
    nothing = _reach(states, domain, np.zeros(3, dtype=bool))
    assert all(np.isnan(v) for part in nothing for v in part)
    assert [_round_up(x) for x in (0.537, 0.54, 2.61, 0.0999, 0.0)] == [0.54, 0.54, 2.7, 0.1, 0.0]
    settings = DomainSettings(("a", "b"), (0.4, 0.45))
    found = DomainCoverage("E", "s", settings, False, 2, (), 3, 0.0, (0.3, 0.5), (0.29, 0.485))
    assert found.classifier_domain() == "a=0.3,b=0.45"  # capped at the domain's own half-width
    assert found.classifier_domain("95") == "a=0.29,b=0.45"
    assert DomainCoverage("E", "s", settings, False, 0, (), 3, 0.0, *nothing).classifier_domain() == ""


def test_a_rescue_into_the_box_must_hold_the_horizon_and_end_in_it(models) -> None:
    import dataclasses

    from pidlab.controller.analysis import analyze_coach
    from pidlab.controller.pid import Coach
    from pidlab.region.rescue import _core
    from pidlab.region.simulate import Simulator
    from pidlab.region.takeover import BoxRegion

    spec, loaded = _spec(HOPPER, "pidlab-room"), models[HOPPER]
    card = loaded.require_card()
    box = _core(spec, card, "box")
    assert isinstance(box.region, BoxRegion) and _core(spec, card).region is None  # "core": hold the horizon
    sim = Simulator(spec, loaded, analyze_coach(Coach(spec, loaded), loaded).linearization)
    upright = np.zeros(2 * loaded.model.nv)  # a deviation from the operating point
    tilted = upright.copy()
    tilted[2] = 0.15  # the torso's pitch (rooty) past the box's 0.10 rad
    assert _rescued(sim, (upright, None), 1, box)[0]  # it holds the step and ends in the box
    assert not _rescued(sim, (tilted, None), 1, box)[0]  # one step does not bring it back
    assert _rescued(sim, (tilted, None), 1, _core(spec, card))[0]  # but it holds that step
    legs = DomainSettings(HOPPER_LEGS, (0.2, 0.5, 0.5, 0.5), states=40)
    held = measure_domain_coverage(spec, loaded, legs, workers=1)
    upright_too = measure_domain_coverage(spec, loaded, dataclasses.replace(legs, into="box"), workers=1)
    assert upright_too.rescuable <= held.rescuable  # the same states: held, and upright at the end
    bare = dataclasses.replace(spec, bounds={k: v for k, v in spec.bounds.items() if k != "box"})
    with pytest.raises(RegionError, match="a rescue into the recoverable box needs \\[bounds.box\\]"):
        _core(bare, card, "box")
    with pytest.raises(RegionError, match="into='up': expected one of core, box"):
        DomainSettings(("rooty_pos",), (0.1,), into="up")


def test_a_spec_with_a_forecast_is_also_scored_as_the_model_predictor_asks_it(models) -> None:
    from pidlab.region.coverage import MODEL_KIND

    found = measure_domain_coverage(_spec(IP, "pidlab-rescue-edge-model"), models[IP], IP_DOMAIN, workers=1)
    assert [s.kind for s in found.scores] == ["rescue region", "certified core", "box", MODEL_KIND]
    region, asked = found.score("rescue region"), found.score(MODEL_KIND)
    # a box about a state proven inside holds the state itself: never more, here fewer
    assert 0 < asked.inside < region.inside and asked.held <= region.held
    plain = measure_domain_coverage(_spec(IP, "pidlab-rescue-edge"), models[IP], IP_DOMAIN, workers=1)
    assert plain.score(MODEL_KIND) is None and plain.score("rescue region") == region  # the same states


def test_the_same_seed_scores_the_same_states(models) -> None:
    a = measure_domain_coverage(_spec(IP), models[IP], IP_DOMAIN, workers=1)
    b = measure_domain_coverage(_spec(IP), models[IP], IP_DOMAIN, workers=1)
    da, db = a.to_dict(), b.to_dict()
    da.pop("elapsed_s"), db.pop("elapsed_s")
    assert json.dumps(da) == json.dumps(db)  # (nan where a region holds no state)
    assert [s.kind for s in a.scores] == ["rescue region", "certified core", "box"]
    rescue = a.score("rescue region")
    assert rescue is not None and rescue.held <= min(rescue.inside, a.rescuable)
    assert a.simulations == IP_DOMAIN.states and not a.grounded
    assert a.rescuable > 0 and len(a.reach) == len(a.reach95) == 4
    assert all(0 <= q <= r <= h for q, r, h in zip(a.reach95, a.reach, IP_DOMAIN.half_range, strict=True))
    assert da["settings"]["domain"] == dict(zip(IP_DOMAIN.variables, IP_DOMAIN.half_range, strict=True))


def test_draws_keep_the_joints_within_their_ranges(models) -> None:
    """The cart's slide joint is limited to +-1 m: a box of +-3 m keeps only states within it."""
    settings = dataclasses.replace(IP_DOMAIN, half_range=(0.2, 3.0, 4.0, 1.5))
    with _estimate(_spec(IP), models[IP], settings) as (est, _, _):
        states = draw_states(est, 300)
    cart = states[:, settings.variables.index("slider_pos")]
    assert np.all(np.abs(cart) <= 1.0) and np.abs(cart).max() > 0.8
    assert np.all(np.abs(states[:, 0]) < 0.2)  # the pole within the termination limit


def test_near_draws_lie_in_boxes_about_their_centres_at_every_scale(models) -> None:
    """Each centre in turn; each state within half the domain of its own centre, some very near it."""
    settings = dataclasses.replace(IP_DOMAIN, half_range=(0.2, 1.0, 4.0, 1.5))
    half = np.array(settings.half_range)
    centres = np.array([[0.0, 0.0, 0.0, 0.0], [0.1, -0.5, 1.0, 0.0]])
    with _estimate(_spec(IP), models[IP], settings) as (est, _, _):
        states = draw_near(est, 400, centres)
    assert states.shape == (400, 4)
    lo, hi = np.array([-0.2, -1.0, -4.0, -1.5]), np.array([0.2, 1.0, 4.0, 1.5])
    assert np.all(states >= lo) and np.all(states <= hi)  # clipped to the domain
    nearest = np.min([np.max(np.abs(states - c) / half, axis=1) for c in centres], axis=0)
    assert np.all(nearest <= NEAR_SCALES[1] + 1e-12)
    assert np.mean(nearest < 0.05) > 0.2 and np.mean(nearest > 0.2) > 0.2  # log-uniform scales: near and far
    assert np.abs(states[:, 0]).max() < 0.2  # only states the env can be in (the pole's limit)


def test_a_standing_robot_starts_on_the_floor_in_the_estimates(models) -> None:
    """Hopper's rescue simulations put a tilted, crouched start on the floor; the pendulum's are as drawn."""
    settings = DomainSettings(HOPPER_LEGS, (0.2, 0.5, 0.5, 0.5), states=10)
    spec, loaded = _spec(HOPPER), models[HOPPER]
    with _estimate(spec, loaded, settings) as (est, _, _):
        assert est.grounded
        sim = est.pool.sim
        x = est.domain.to_plant(np.array([0.1, -0.4, -0.4, 0.2]), sim)
        _, floor_obs = _rescued(sim, (x, None), 1, est.core, grounded=True)
        _, air_obs = _rescued(sim, (x, None), 1, est.core, grounded=False)
    z = loaded.require_card().observation_names.index("rootz_pos")
    assert floor_obs[z] < air_obs[z] - 0.01  # a crouched hopper stands lower
    with _estimate(_spec(IP), models[IP], IP_DOMAIN) as (est, _, _):
        assert not est.grounded


def test_a_pitch_only_region_claims_states_the_coach_cannot_rescue(models) -> None:
    """Hopper's shipped region tests pitch and its rate; with the legs bent the coach falls from most."""
    settings = DomainSettings(HOPPER_LEGS, (0.2, 2.62, 2.62, 0.79), states=60)
    found = measure_domain_coverage(_spec(HOPPER), models[HOPPER], settings, workers=1)
    rescue = found.score("rescue region")
    assert found.grounded and rescue is not None
    assert rescue.inside > 0 and rescue.false_claims > 0.5


def test_a_spec_without_a_certified_core_is_refused(models) -> None:
    with pytest.raises(RegionError, match=r"no certified core \(\[bounds\]\); run `pidlab bounds SPEC --write`"):
        bare = dataclasses.replace(_spec(HOPPER, "pidlab-room"), bounds=None)
        measure_domain_coverage(bare, models[HOPPER], DomainSettings(HOPPER_LEGS, (0.1,) * 4))


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--domain", "hinge_pos=0.2,nope_pos=1"], "'nope_pos' is not an observation variable of InvertedPendulum-v5"),
        (["--domain", "hinge_pos=0.2", "--seed", "-1"], "--seed -1: expected an integer in [0, 4294967295]"),
        (["--domain", "hinge_pos=-1"], "--domain 'hinge_pos=-1': expected VARIABLE=HALF-WIDTH with a half-width > 0"),
        (["--domain", "hinge_pos=0.2", "--states", "0"], "--states 0: expected an integer in [1, 1000000]"),
        (["--domain", "hinge_pos=0.2", "--horizon", "nan"], "--horizon nan: expected a finite number in (0, 600] (s)"),
        (
            ["--domain", "hinge_pos=0.2", str(TUNING / "Hopper-v5.pidlab-robust.toml")],
            "coaches of Hopper-v5, InvertedPendulum-v5; expected",
        ),
    ],
)
def test_coverage_cli_refuses_bad_input_in_one_line(args, message) -> None:
    code, err = cli_in_process("rescue-coverage", str(TUNING / "InvertedPendulum-v5.pidlab-rescue.toml"), *args)
    assert code == 2 and message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("command", ["rescue-coverage", "rescue-classifier"])
def test_a_domain_variable_the_env_lacks_is_refused_before_anything_is_said(command, tmp_path) -> None:
    from typer.testing import CliRunner

    from pidlab.cli import app

    spec = tmp_path / "coach.toml"
    spec.write_bytes((TUNING / "InvertedPendulum-v5.pidlab-rescue.toml").read_bytes())
    result = CliRunner().invoke(app, [command, str(spec), "--domain", "hinge_pos=0.2,nope_pos=1"])
    assert result.exit_code == 2 and result.stdout == ""  # no journal announced for work never done
    assert result.stderr.strip().splitlines() == [
        "pidlab: error: 'nope_pos' is not an observation variable of InvertedPendulum-v5; valid names: "
        "slider_pos, hinge_pos, slider_vel, hinge_vel"
    ]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["coach.toml"]


def test_coverage_cli_prints_and_writes_the_figures(tmp_path) -> None:
    from typer.testing import CliRunner

    from pidlab.cli import app

    out_file = tmp_path / "coverage.json"
    result = CliRunner().invoke(app, [
        "rescue-coverage", str(TUNING / "InvertedPendulum-v5.pidlab-rescue.toml"),
        str(TUNING / "InvertedPendulum-v5.pidlab-robust.toml"),
        "--domain", "hinge_pos=0.2,slider_pos=1,hinge_vel=4,slider_vel=1.5", "--states", "40",
        "--workers", "1", "--json", str(out_file),
    ])  # fmt: skip
    assert result.exit_code == 0, result.stderr
    assert "rescue region" in result.stdout and "false claims" in result.stdout
    assert "pidlab-rescue: the rescued states lie within" in result.stdout
    assert "a classifier domain holding them all: --domain hinge_pos=" in result.stdout
    data = json.loads(out_file.read_text())
    assert [d["spec_name"] for d in data] == ["pidlab-rescue", "pidlab-robust"]
    for d in data:
        assert d["rescuable_share"] == d["rescuable"] / 40
        for s in d["scores"]:
            assert s["held"] <= min(s["inside"], d["rescuable"])


def test_a_grid_estimate_on_a_standing_robot_records_starts_on_the_floor(models) -> None:
    from pidlab.region.rescue import STARTS_ON_FLOOR, RescueSettings, estimate_rescue

    settings = RescueSettings(("rooty_pos", "rooty_vel"), (0.02, 0.2), (2, 2), probes=1, horizon_s=0.5,
                              validation=20, coverage=20)  # fmt: skip
    found = estimate_rescue(_spec(HOPPER), models[HOPPER], settings, workers=1)
    assert found.provenance["starts"] == STARTS_ON_FLOOR
    ip = estimate_rescue(_spec(IP), models[IP], RescueSettings(("hinge_pos", "hinge_vel"), (0.02, 0.2), (2, 2),
                         probes=1, horizon_s=0.5, validation=20, coverage=20), workers=1)  # fmt: skip
    assert "starts" not in ip.provenance
