"""Regions of attraction and critical bounds: certified against MuJoCo, honest about failure."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pidlab.controller.pid import Coach
from pidlab.controller.spec import dumps_spec, load_spec, loads_spec
from pidlab.errors import PidlabError, UnknownSignalError
from pidlab.region.bounds import derive_bounds, with_bounds
from pidlab.region.roa import METHOD_LYAPUNOV, METHOD_SIMULATION, RegionError, estimate_roa
from tests.helpers import cli_in_process

TUNING = Path(__file__).resolve().parents[1] / "tuning"


@pytest.fixture(scope="module")
def ip_region(models):
    spec = load_spec(TUNING / "InvertedPendulum-v5.pidlab-robust.toml")
    roa, kept = estimate_roa(
        spec,
        models["InvertedPendulum-v5"],
        samples=150,
        keep_trajectories=10,
        record=("hinge_pos", "hinge_vel"),
    )
    return spec, roa, kept


def test_ip_region_is_certified_with_zero_failures(ip_region):
    _, roa, kept = ip_region
    assert roa.method == METHOD_LYAPUNOV
    assert roa.check.samples == 150 and roa.check.failures == 0
    assert roa.check.failure_bound_95 == pytest.approx(3 / 150)
    assert roa.level > 0
    # the Lyapunov function is one: A' P A - P = -Q
    L = roa.lyapunov
    np.testing.assert_allclose(L.A_cl.T @ L.P @ L.A_cl - L.P, -L.Q, atol=1e-6 * np.abs(L.P).max())
    # the certified set stays inside the termination limit on the pole angle (|hinge| <= 0.2)
    i = L.variables.index("hinge_pos")
    half = np.sqrt(roa.level * np.linalg.inv(L.P_y)[i, i])
    assert abs(L.center[i]) + half <= 0.2 + 1e-9
    assert len(kept) == 10 and all(t.recovered for t in kept) and kept[0].path.shape[1] == 2


def test_independent_samples_inside_the_certified_set_recover(ip_region, models):
    """A fresh seed: states drawn in {V <= c} do not fail either (what the certificate claims)."""
    from pidlab.controller.analysis import analyze_coach
    from pidlab.controller.pid import Coach
    from pidlab.region.roa import _check_level
    from pidlab.region.simulate import SimulationPool

    spec, roa, _ = ip_region
    loaded = models["InvertedPendulum-v5"]
    lin = analyze_coach(Coach(spec, loaded), loaded).linearization
    with SimulationPool(spec, loaded, lin, workers=1) as pool:
        term, nonconv, _ = _check_level(pool, roa.lyapunov, roa.level, 100, 75, np.random.default_rng(12345))
        assert term == 0 and nonconv == 0
        # and far outside it the coach does fail: the check can fail
        term, nonconv, _ = _check_level(pool, roa.lyapunov, 200 * roa.level, 30, 75, np.random.default_rng(1))
        assert term + nonconv > 0


def test_bounds_round_trip_in_the_spec(ip_region, models):
    spec, roa, _ = ip_region
    b = derive_bounds(roa, spec, models["InvertedPendulum-v5"], check_samples=30)
    assert b.one_step_check == (30, 0)
    assert 0 < b.rho <= 1
    lo, hi = b.box["hinge_vel"]
    assert lo < 0 < hi
    spec2 = with_bounds(spec, b)
    text = dumps_spec(spec2)
    assert loads_spec(text) == spec2 and dumps_spec(loads_spec(text)) == text
    assert spec2.bounds["provenance"]["samples"] == 150
    assert spec2.bounds["ellipsoid"]["variables"] == ["slider_pos", "hinge_pos", "slider_vel", "hinge_vel"]


def test_unknown_variable_lists_valid_names(ip_region, models):
    spec, roa, _ = ip_region
    with pytest.raises(UnknownSignalError, match="valid names: slider_pos, hinge_pos, slider_vel, hinge_vel"):
        derive_bounds(roa, spec, models["InvertedPendulum-v5"], variables=["pole_rate"])


def test_unstable_coach_has_no_region(models):
    spec = load_spec(TUNING / "InvertedPendulum-v5.paper.toml")
    with pytest.raises(RegionError, match="no region of attraction: closed loop is unstable; poles"):
        estimate_roa(spec, models["InvertedPendulum-v5"], samples=10)


def test_region_that_certifies_nothing(models):
    """A coach that barely holds the pole: every level fails -> say so, write nothing."""
    spec = load_spec(TUNING / "InvertedPendulum-v5.pidlab-robust.toml")
    text = dumps_spec(spec).replace("kp = 4.991143175184444", "kp = 1.53", 1)
    weak = loads_spec(text)
    with pytest.raises(RegionError, match="c -> 0|no useful bound|no region"):
        roa, _ = estimate_roa(weak, models["InvertedPendulum-v5"], samples=20, bisection_samples=20)
        derive_bounds(roa, weak, models["InvertedPendulum-v5"], check_samples=10)


def test_contact_rich_env_uses_simulation_only(models):
    spec = load_spec(TUNING / "Hopper-v5.pidlab-robust.toml")
    roa, _ = estimate_roa(
        spec, models["Hopper-v5"], samples=12, bisection_samples=8, bisection_rounds=4, horizon_s=1.0
    )
    assert roa.method == METHOD_SIMULATION and roa.lyapunov is None
    assert set(roa.box) == {"rooty_pos", "rooty_vel"} and roa.box["rooty_vel"] > 0


def test_cli_roa_and_bounds_bad_input(tmp_path):
    def run(*a):
        return subprocess.run(
            [sys.executable, "-m", "pidlab", *a], capture_output=True, text=True, timeout=300
        )

    res = run("roa", str(TUNING / "InvertedPendulum-v5.paper.toml"))
    assert res.returncode == 2 and "no region of attraction: closed loop is unstable; poles" in res.stderr
    code, stderr = cli_in_process(
        "bounds", str(TUNING / "InvertedPendulum-v5.pidlab-robust.toml"), "--variables", "pole_rate"
    )
    assert code == 2 and "valid names: slider_pos" in stderr
    assert len(stderr.strip().splitlines()) == 1
    code, stderr = cli_in_process(
        "roa", str(TUNING / "InvertedPendulum-v5.pidlab-robust.toml"), "--samples", "0"
    )
    assert code == 2 and "positive" in stderr


def test_shrink_until_clean_keeps_each_call_sites_factor():
    """The one final-check loop: value, value*f, value*f*f, ... (the same floats as `value *= f`)."""
    from pidlab.region.shrink import shrink_until_clean

    seen = []

    def check(value):
        seen.append(value)
        return 3 if value > 0.3 else 0

    found = shrink_until_clean(check, lambda failures: failures == 0, 1.0, 0.7)
    expected = [1.0]
    for _ in range(4):
        expected.append(expected[-1] * 0.7)
    assert seen == expected and found is not None
    assert (found.value, found.outcome, found.tries) == (expected[-1], 0, 5)
    # failures persist: at most six checks, then None (the caller raises)
    seen.clear()
    assert shrink_until_clean(check, lambda failures: failures == 0, 1.0, 0.99) is None
    assert len(seen) == 6


def test_bisections_find_the_largest_passing_factor():
    from pidlab.region.shrink import geometric_bisect, halving_bisect

    assert geometric_bisect(lambda r: True) == 1.0 and halving_bisect(lambda r: True, 8) == 1.0
    assert geometric_bisect(lambda r: False) == 0.0 and halving_bisect(lambda r: False, 8) == 0.0
    assert 0.2 < geometric_bisect(lambda r: r <= 0.3, 12) <= 0.3
    assert 0.28 < halving_bisect(lambda r: r <= 0.3, 12) <= 0.3
    calls = []
    halving_bisect(lambda r: calls.append(r) or r <= 0.3, 5)
    assert calls == [1.0, 0.5, 0.25, 0.375, 0.3125]


def test_a_level_set_over_contacts_is_drawn_about_the_balance_posture(models):
    """Walker2d's balance coach: a level set at its design posture, certified by simulation alone."""
    from pidlab.controller.balance import design_observation
    from pidlab.region.roa import region_start, region_value
    from pidlab.region.simulate import Simulator

    loaded = models["Walker2d-v5"]
    spec = load_spec(TUNING / "Walker2d-v5.pidlab-balance.toml")
    roa, _ = estimate_roa(
        spec, loaded, samples=10, bisection_samples=6, bisection_rounds=6, method="lyapunov"
    )
    lyap = roa.lyapunov
    assert roa.method == METHOD_LYAPUNOV and roa.check.failures == 0 and roa.level > 0
    assert roa.c_optimization is None  # no symbolic model covers the contacts
    # the observable part: every observation variable but none for the forward position
    assert len(lyap.variables) == 17 and "rootx_pos" not in lyap.variables and len(lyap.tangent) == 17
    assert np.allclose(lyap.center, design_observation(spec, loaded, lyap.variables))
    from pidlab.region.roa import contact_analysis

    sim = Simulator(spec, loaded, contact_analysis(spec, loaded, Coach(spec, loaded)).linearization)
    y = np.linspace(-0.01, 0.01, 17)
    obs, v0 = region_start(sim, lyap, y)  # each variable moved by its own deviation
    names = loaded.require_card().observation_names
    seen = np.array([obs[names.index(v)] for v in lyap.variables]) - lyap.center
    assert np.allclose(seen, y, atol=1e-12)
    assert v0 == pytest.approx(float(y @ lyap.P_y @ y)) == pytest.approx(region_value(sim, lyap, obs))


def test_a_phase_portrait_over_contacts_starts_about_the_posture(models):
    """``method='lyapunov'`` on Walker2d: the grid is laid about the balance coach's posture, each of
    the two variables moved by its own offset (the others at the posture); the card's method keeps
    the operating point."""
    from pidlab.controller.balance import design_observation
    from pidlab.region.roa import phase_portrait

    loaded = models["Walker2d-v5"]
    spec = load_spec(TUNING / "Walker2d-v5.pidlab-balance.toml")
    pair = ("thigh_joint_pos", "rooty_vel")
    paths = phase_portrait(spec, loaded, pair, (0.02, 0.3), grid=2, horizon_s=0.024, method="lyapunov")
    centre = design_observation(spec, loaded, pair)
    firsts = np.array([p[0] for p in paths])
    offsets = np.array([(a, b) for a in (-0.02, 0.02) for b in (-0.3, 0.3)])
    assert np.allclose(firsts, centre + offsets, atol=1e-9)
    assert all(len(p) == 4 for p in paths)  # 0.024 s: 3 control periods of 8 ms, and the start
    card_op = phase_portrait(spec, loaded, pair, (0.02, 0.3), grid=2, horizon_s=0.024)
    assert not np.allclose(np.array([p[0] for p in card_op]), firsts)  # the reset pose, not the posture


def test_a_portrait_pair_outside_the_posture_level_set_is_refused_before_any_simulation(models):
    """``pidlab roa --plots --slice`` asks :func:`check_portrait_variables` before estimating: two
    variables of Walker2d's level set pass; a variable the level set is not drawn in is one error
    naming the flag's parameter and the variables it could take."""
    import dataclasses

    from pidlab.region.roa import (
        Coach,
        Simulator,
        _check_posture_pair,
        check_portrait_variables,
        lyapunov_function,
        region_analysis,
    )

    loaded = models["Walker2d-v5"]
    spec = load_spec(TUNING / "Walker2d-v5.pidlab-balance.toml")
    check_portrait_variables(spec, loaded, ("thigh_joint_pos", "rooty_vel"), "lyapunov")
    with pytest.raises(PidlabError, match="'nope' is not an observation variable of Walker2d-v5"):
        check_portrait_variables(spec, loaded, ("rooty_pos", "nope"), "lyapunov", param="slice_vars")
    coach = Coach(spec, loaded)
    analysis = region_analysis(spec, loaded, coach, "lyapunov")
    lyap = lyapunov_function(analysis, coach, Simulator(spec, loaded, analysis.linearization).y_op)
    assert lyap.tangent is not None and "rooty_vel" in lyap.variables
    fewer = dataclasses.replace(lyap, variables=tuple(v for v in lyap.variables if v != "rooty_vel"))
    with pytest.raises(RegionError, match="slice_vars=rooty_pos,rooty_vel: 'rooty_vel' is not among") as err:
        _check_posture_pair(fewer, spec.name, ("rooty_pos", "rooty_vel"), "slice_vars")
    assert err.value.param == "slice_vars" and "expected two of rooty" not in str(err.value)


def test_a_level_set_over_contacts_needs_a_balance_coach_and_a_known_method(models):
    robust = load_spec(TUNING / "Walker2d-v5.pidlab-robust.toml")
    with pytest.raises(RegionError, match="balance coach") as err:
        estimate_roa(robust, models["Walker2d-v5"], samples=4, method="lyapunov")
    assert err.value.param == "method" and "\n" not in str(err.value)
    with pytest.raises(RegionError, match=r"method='grid': expected one of lyapunov, simulation"):
        estimate_roa(robust, models["Walker2d-v5"], samples=4, method="grid")
    ip = load_spec(TUNING / "InvertedPendulum-v5.pidlab-robust.toml")
    with pytest.raises(RegionError, match="names no \\[region\\] variables"):
        estimate_roa(ip, models["InvertedPendulum-v5"], samples=4, method="simulation")


def test_cli_bounds_method_bad_input():
    spec = str(TUNING / "Walker2d-v5.pidlab-robust.toml")
    code, stderr = cli_in_process("bounds", spec, "--method", "grid")
    assert code == 2 and stderr.strip() == "pidlab: error: --method grid: expected one of lyapunov, simulation"
    code, stderr = cli_in_process("bounds", spec, "--method", "lyapunov", "--samples", "4")
    assert code == 2 and "balance coach" in stderr and len(stderr.strip().splitlines()) == 1
    code, stderr = cli_in_process("roa", spec, "--method", "grid")
    assert code == 2 and stderr.strip() == "pidlab: error: --method grid: expected one of lyapunov, simulation"
    code, stderr = cli_in_process("roa", spec, "--method", "lyapunov", "--samples", "4")
    assert code == 2 and "balance coach" in stderr and len(stderr.strip().splitlines()) == 1
