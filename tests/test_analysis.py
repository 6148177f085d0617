"""Closed-loop analysis: margins against python-control's references, pole cross-check, theory vs MuJoCo."""

from __future__ import annotations

from pathlib import Path

import control as ct
import mujoco
import numpy as np
import pytest

from pidlab.controller.analysis import analyze_coach, coach_to_continuous, loop_margins, step_metrics
from pidlab.controller.pid import Coach, law
from pidlab.controller.spec import load_spec
from pidlab.plant.observation import observe

TUNING = Path(__file__).resolve().parents[1] / "tuning"
s = ct.tf("s")

# (loop, gm, pm, sm, wpc, wgc): reference values from python-control's own margin tests
REFERENCES = [
    (ct.tf([1], [1, 2, 3, 4]), 2.0, np.inf, 0.4170, 1.7321, np.nan),
    (
        ct.ss([[1.0, 4.0], [3.0, 2.0]], [[1.0], [-4.0]], [[1.0, 0.0]], [[0.0]]),
        np.inf,
        147.0743,
        np.nan,
        np.nan,
        2.5483,
    ),
    (
        (8.75 * (4 * s**2 + 0.4 * s + 1))
        / ((100 * s + 1) * (s**2 + 0.22 * s + 1))
        / (s**2 / 10.0**2 + 2 * 0.04 * s / 10.0 + 1),
        2.2716,
        97.5941,
        0.5591,
        10.0053,
        0.0850,
    ),
    (0.01 * (10 - s) / (2 + s) / (1 + s), 300.0, np.inf, 0.9917, 5.6569, np.nan),
]


@pytest.mark.parametrize(("L", "gm", "pm", "sm", "wpc", "wgc"), REFERENCES)
def test_margins_match_python_control_reference_cases(L, gm, pm, sm, wpc, wgc):
    m = loop_margins(ct.ss(L), "u")
    assert 10 ** (m.gain_margin_db / 20) == pytest.approx(gm, rel=2e-3)
    assert m.phase_margin_deg == pytest.approx(pm, rel=2e-3)
    if np.isfinite(sm):
        assert 1 / m.ms == pytest.approx(sm, rel=2e-3)
    if np.isfinite(wpc):
        assert m.phase_crossover == pytest.approx(wpc, rel=2e-3)
    if np.isfinite(wgc):
        assert m.gain_crossover == pytest.approx(wgc, rel=2e-3)
        if len(m.crossovers) == 1:  # with several crossovers the delay margin is their minimum
            assert m.delay_margin_s == pytest.approx(np.deg2rad(pm) / wgc, rel=2e-3)


def test_discrete_margins_agree_with_python_control():
    L = ct.sample_system(ct.ss(ct.tf([1], [1, 2, 3, 4])), 0.05)
    with pytest.warns(UserWarning, match="Falling back"):
        gm, _pm, sm, wpc, _wgc, _ = ct.stability_margins(L)
    m = loop_margins(L, "u")
    assert 10 ** (m.gain_margin_db / 20) == pytest.approx(gm, rel=1e-3)
    assert m.phase_crossover == pytest.approx(wpc, rel=1e-3)
    assert 1 / m.ms == pytest.approx(sm, rel=2e-3)


def test_inverse_tustin_inverts_bilinear_sampling():
    sys = ct.ss([[-1.0, 2.0], [0.0, -3.0]], [[1.0, 0.0], [0.5, 1.0]], [[1.0, 1.0]], [[0.0, 0.2]])
    back = coach_to_continuous(ct.sample_system(sys, 0.04, method="bilinear"))
    np.testing.assert_allclose(ct.evalfr(back, 2j), ct.evalfr(sys, 2j), rtol=1e-10)


@pytest.mark.parametrize(
    ("env", "kind", "stable"),
    [
        ("InvertedPendulum-v5", "pidlab-robust", True),
        ("InvertedDoublePendulum-v5", "pidlab-robust", True),
        ("InvertedPendulum-v5", "paper", False),  # cart drift: a slow pole just outside the unit circle
    ],
)
def test_closed_loop_poles_cross_check_and_stability(models, env, kind, stable):
    loaded = models[env]
    spec = load_spec(TUNING / f"{env}.{kind}.toml")
    a = analyze_coach(Coach(spec, loaded), loaded)
    assert a.discrete.pole_check < 1e-9 and a.continuous.pole_check < 1e-9
    assert a.stable is stable
    assert len(a.discrete.margins) == 1 and a.discrete.margins[0].actuator == "slide"


def _linear_prediction_error(loaded, spec, size: float, steps: int = 25) -> float:
    """Max observation error between MuJoCo + coach and the linear closed loop, from a pole tilt."""
    from pidlab.linear.linearize import linearize

    lin = linearize(loaded)
    m = loaded.model
    d = mujoco.MjData(m)
    sig = loaded.card.observation_names.index("hinge_pos")
    x0 = np.linalg.pinv(lin.C)[:, sig] * size
    q = lin.op.qpos.copy()
    mujoco.mj_integratePos(m, q, x0[: m.nv], 1.0)
    d.qpos[:] = q
    d.qvel[:] = lin.op.qvel + x0[m.nv :]
    mujoco.mj_forward(m, d)
    coach = Coach(spec, loaded)
    obs = observe(loaded.card, m, d)
    coach.reset(obs)
    # linear: plant deviation x, driven by the same (unsaturated) coach law
    y_op = obs - lin.C @ x0
    lay = coach.layout
    state = coach.state.copy()
    x = x0.copy()
    worst = 0.0
    for _ in range(steps):
        u = coach.act(obs)
        d.ctrl[:] = u
        mujoco.mj_step(m, d, nstep=loaded.frame_skip)
        obs = observe(loaded.card, m, d)
        state, u_lin, _ = law(lay, state, y_op + lin.C @ x, lay.setpoints, saturate=False)
        x = lin.Ad @ x + lin.Bd @ (u_lin - lin.op.ctrl)
        worst = max(worst, float(np.max(np.abs(obs - (y_op + lin.C @ x)))))
    return worst


def test_nonlinear_response_matches_linear_prediction(models):
    loaded = models["InvertedPendulum-v5"]
    spec = load_spec(TUNING / "InvertedPendulum-v5.pidlab-robust.toml")
    e2 = _linear_prediction_error(loaded, spec, 0.02)
    e1 = _linear_prediction_error(loaded, spec, 0.01)
    assert e1 < 0.05 * 0.01  # within 5 % of the perturbation
    assert e2 / e1 > 2.5  # and the mismatch is nonlinear (second order or higher)


def test_step_response_equals_python_control_forced_response(models):
    import warnings

    from pidlab.controller.analysis import step_response

    loaded = models["InvertedDoublePendulum-v5"]
    spec = load_spec(TUNING / "InvertedDoublePendulum-v5.pidlab-robust.toml")
    result = analyze_coach(Coach(spec, loaded), loaded)
    cl = result.discrete.sys
    steps = 200
    t = np.arange(steps) * result.dt
    for j in range(cl.ninputs):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ref = ct.forced_response(cl, T=t, U=np.vstack([np.eye(cl.ninputs)[j]] * steps).T)
        assert np.allclose(step_response(cl, j, steps), np.asarray(ref.outputs).T, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize(
    ("env", "name"),
    [
        ("InvertedPendulum-v5", "pidlab-robust"),
        ("Hopper-v5", "paper"),
        ("Walker2d-v5", "pidlab-robust"),
        ("Walker2d-v5", "pidlab-weak"),
    ],
)
def test_gain_crossovers_are_real_crossovers(models, env, name):
    """python-control's polynomial method returns spurious crossovers on these discrete loops
    (e.g. 0.093 rad/s where |L| = 4 dB on InvertedPendulum, and misses the real one of
    Walker2d's ankle loop at 2.5 rad/s); every reported crossover must have |L| = 1, and every
    crossing of |L| = 1 seen on a dense grid must be reported."""
    from pidlab.controller.analysis import _frequency_grid, loop_at_actuator
    from pidlab.linear.lti import siso_frequency_response

    loaded = models[env]
    spec = load_spec(TUNING / f"{env}.{name}.toml")
    coach = Coach(spec, loaded)
    result = analyze_coach(coach, loaded)
    coach_d = coach.linear_model()
    for m in result.discrete.margins:
        i = list(result.plant.input_labels).index(m.actuator)
        L = loop_at_actuator(result.plant, coach_d, i)
        if m.crossovers:
            mags = np.abs(siso_frequency_response(L, np.array(m.crossovers)))
            assert np.allclose(mags, 1.0, atol=1e-3), (m.actuator, m.crossovers, mags)
            ph = np.angle(siso_frequency_response(L, np.array(m.crossovers)), deg=True)
            assert m.phase_margin_deg == pytest.approx(float(np.min(180 - np.abs(ph))))
        omega = np.logspace(np.log10(_frequency_grid(L)[0]), np.log10(_frequency_grid(L)[-1]), 20000)
        mag = np.abs(siso_frequency_response(L, omega))
        for k in np.nonzero(np.diff(np.sign(mag - 1.0)) != 0)[0]:
            assert any(abs(w - omega[k]) <= 0.01 * omega[k] for w in m.crossovers), (m.actuator, omega[k])
        if np.isfinite(m.phase_crossover):  # the upper gain margin is read where L is real and negative
            r = siso_frequency_response(L, np.array([m.phase_crossover]))[0]
            assert r.real < 0 and abs(r.imag) <= 1e-3 * abs(r)
            assert m.gain_margin_db == pytest.approx(-20 * np.log10(abs(r)))
    if env == "InvertedPendulum-v5":
        assert result.discrete.margins[0].phase_margin_deg == pytest.approx(59.73, abs=0.01)
    if (env, name) == ("Hopper-v5", "paper"):  # python-control misses this phase crossover
        assert result.discrete.margins[0].phase_crossover == pytest.approx(10.16, abs=0.01)


@pytest.fixture(scope="module")
def walker(models):
    """Walker2d's robust coach (six actuator loops) and its analysis."""
    loaded = models["Walker2d-v5"]
    coach = Coach(load_spec(TUNING / "Walker2d-v5.pidlab-robust.toml"), loaded)
    return analyze_coach(coach, loaded), coach


def test_loop_responses_equal_python_controls_frequency_response(walker):
    from pidlab.controller.analysis import loop_at_actuator, loop_responses, omega_grid

    analysis, coach = walker
    responses = loop_responses(analysis, coach, points=300)
    assert tuple(r.margins for r in responses) == analysis.discrete.margins
    top = np.pi / analysis.dt
    omega = omega_grid(analysis.dt, 300)
    assert omega[0] == pytest.approx(1e-4 * top) and top * (1 - 1e-5) < omega[-1] < top
    coach_d = coach.linear_model()
    plant = analysis.plant
    for r in responses:
        assert r.dt == analysis.dt and np.array_equal(r.omega, omega) and r.response.shape == (300,)
        L = loop_at_actuator(plant, coach_d, list(plant.input_labels).index(r.actuator))
        ref = np.asarray(L.frequency_response(omega).complex).ravel()
        assert np.allclose(r.response, ref, rtol=1e-9, atol=0)
        assert np.allclose(r.magnitude_db, 20 * np.log10(np.abs(ref)), rtol=0, atol=1e-9)
        assert np.allclose(np.exp(1j * np.deg2rad(r.phase_deg)), ref / np.abs(ref), rtol=0, atol=1e-9)
        assert np.all(np.abs(np.diff(r.phase_deg)) < 180)  # unwrapped


def test_closed_loop_responses_equal_python_controls_forced_and_initial_response(walker):
    import warnings

    from pidlab.controller.analysis import INITIAL_DEVIATION, closed_loop_responses

    analysis, coach = walker
    r = closed_loop_responses(analysis, coach, horizon_s=2.0)
    cl, plant = analysis.discrete.sys, analysis.plant
    n, steps = len(coach.spec.loops), round(2.0 / analysis.dt)
    assert r.loops == tuple(lp.name for lp in coach.spec.loops) and r.deviation == INITIAL_DEVIATION
    assert r.outputs == tuple(plant.output_labels) + tuple(plant.input_labels)
    assert np.array_equal(r.timepts, np.arange(steps) * analysis.dt)
    assert r.step.shape == r.initial.shape == (n, steps, cl.noutputs)
    for j, signal in enumerate(r.signals):
        sig = list(plant.output_labels).index(signal)
        x0 = np.zeros(cl.nstates)
        x0[: plant.nstates] = np.linalg.pinv(np.asarray(plant.C))[:, sig] * INITIAL_DEVIATION
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            forced = ct.forced_response(cl, T=r.timepts, U=np.outer(np.eye(n)[j], np.ones(steps)))
            initial = ct.initial_response(cl, T=r.timepts, X0=x0)
        assert np.allclose(r.step[j], np.asarray(forced.outputs).T, rtol=1e-9, atol=1e-12)
        assert np.allclose(r.initial[j], np.asarray(initial.outputs).T, rtol=1e-9, atol=1e-12)
        assert np.array_equal(r.signal_step(j), r.step[j, :, sig])
        assert r.signal_initial(j)[0] == pytest.approx(INITIAL_DEVIATION)


def test_open_loop_poles_are_the_discrete_plants(walker):
    analysis, _ = walker
    ref = np.sort_complex(np.asarray(ct.poles(analysis.linearization.sysd)))
    assert np.allclose(np.sort_complex(analysis.open_loop_poles), ref, atol=1e-9)


# ---------------------------------------------------------------- step metrics, by hand


def test_step_metrics_of_a_response_that_follows_are_measured_against_the_step():
    t = np.arange(6) * 0.5
    # a step of 2: 0, 1, 2.4 (the peak, 0.4 beyond the final 2.0), 2.1, 2.0, 2.0
    over, settle, rise = step_metrics(t, np.array([0.0, 1.0, 2.4, 2.1, 2.0, 2.0]), 2.0)
    assert over == pytest.approx(0.4 / 2.0 * 100)  # 20 %, of the setpoint change
    assert settle == 2.0  # within 2 % of 2 (0.04) of the final value from t = 2.0 on (2.1 is 0.1 away)
    assert rise == pytest.approx(1.0 - 0.5)  # 10 % of 2.0 first at t = 0.5 (1.0), 90 % at t = 1.0 (2.4)
    # a negative step mirrors it
    assert step_metrics(t, -np.array([0.0, 1.0, 2.4, 2.1, 2.0, 2.0]), -2.0) == (over, settle, rise)
    # a steady-state error within FOLLOW_FRACTION still follows: final 0.6 of a unit step, peak 0.7
    over, _, _ = step_metrics(t, np.array([0.0, 0.3, 0.7, 0.6, 0.6, 0.6]), 1.0)
    assert over == pytest.approx(10.0)


def test_step_metrics_are_not_defined_when_the_final_value_does_not_follow():
    t = np.arange(5) * 0.1
    # the signal comes back to (almost) 0: dividing by the final value gave 1e16 %
    over, settle, rise = step_metrics(t, np.array([0.0, 1.2, 0.3, 1e-16, 1e-16]), 1.0)
    assert np.isnan(over) and np.isnan(rise) and settle == pytest.approx(0.3)
    over, _, rise = step_metrics(t, np.array([0.0, -0.2, -0.3, -0.2, -0.2]), 1.0)  # the wrong way
    assert np.isnan(over) and np.isnan(rise)
    assert step_metrics(t, np.array([0.0, 1.0, np.inf, np.nan, 1.0]), 1.0)[1] == np.inf


def test_shipped_coaches_report_no_absurd_overshoot(models):
    """IDP's unit setpoint step of a pendulum angle ends back at 0: not defined, not 4e8 %."""
    for env in ("InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Hopper-v5"):
        spec = load_spec(TUNING / f"{env}.pidlab-robust.toml")
        a = analyze_coach(Coach(spec, models[env]), models[env])
        for r in a.responses:
            if r.kind == "step":
                assert np.isnan(r.overshoot_pct) or 0.0 <= r.overshoot_pct < 1000.0, (env, r)
        steps = {r.loop: r for r in a.responses if r.kind == "step"}
        if env == "InvertedDoublePendulum-v5":
            assert np.isnan(steps["lower"].overshoot_pct) and np.isnan(steps["upper"].overshoot_pct)
            assert steps["cart"].overshoot_pct == pytest.approx(0.0, abs=1e-6)
