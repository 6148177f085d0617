"""The coach's one control law: linear model, anti-windup, cascades, no derivative kick."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from pidlab.controller.pid import Coach, law
from pidlab.controller.spec import CoachSpec, Loop

FULL = CoachSpec(
    env_id="InvertedPendulum-v5",
    name="every-feature",
    loops=(
        # outer loop: cart position -> pole angle setpoint, PID with a differenced, filtered derivative
        Loop(
            name="cart",
            signal="slider_pos",
            action="reverse",
            kp=0.05,
            ki=0.02,
            kd=0.03,
            tf=0.1,
            output_limits=(-0.1, 0.1),
            feeds="pole",
        ),
        # inner loop: pole angle with measured rate and a filter, integral with back-calculation
        Loop(
            name="pole",
            signal="hinge_pos",
            setpoint=-0.0016666651234593622,
            action="direct",
            kp=6.0,
            ki=0.5,
            kd=1.0,
            rate_signal="hinge_vel",
            tf=0.02,
            anti_windup="back-calculation",
            tt=0.5,
            actuators=(("slide", 1.0),),
        ),
    ),
)


def test_linear_model_reproduces_the_law_on_real_observations(models):
    """Analysis and the env run the same law: the linear model's output equals act() (unsaturated)."""
    loaded = models["InvertedPendulum-v5"]
    coach = Coach(FULL, loaded)
    K = coach.linear_model()
    assert set(K.state_labels) == {
        "cart_integral",
        "cart_dfilter",
        "cart_prev",
        "pole_integral",
        "pole_dfilter",
    }
    env = gym.make("InvertedPendulum-v5")
    obs, _ = env.reset(seed=3)
    coach.reset(obs)
    lay = coach.layout
    # the affine law's constant part: its step at zero state and observation, real setpoints
    x_const, u_const, _ = law(lay, np.zeros(lay.n_states), np.zeros(4), lay.setpoints, saturate=False)
    A, B, C, D = (np.asarray(M) for M in (K.A, K.B, K.C, K.D))
    keep = lay.active_states()
    compared = 0
    for _ in range(300):
        x = coach.state[keep].copy()
        u_linear = C @ x + D[:, :4] @ obs + u_const
        x_next = A @ x + B[:, :4] @ obs + x_const[keep]
        u = coach.act(obs)
        if np.all(np.abs(coach.last_command) < 3.0):  # not saturated: the law is affine
            np.testing.assert_allclose(coach.last_command, u_linear, rtol=0, atol=1e-10)
            np.testing.assert_allclose(coach.state[keep], x_next, rtol=0, atol=1e-10)
            compared += 1
        obs, _, terminated, truncated, _ = env.step(u)
        if terminated or truncated:
            obs, _ = env.reset(seed=4)
            coach.reset(obs)
    assert compared > 50


def test_no_derivative_kick_after_reset(models):
    spec = CoachSpec(
        "InvertedPendulum-v5",
        "d",
        (Loop(name="p", signal="hinge_pos", kd=10.0, actuators=(("slide", 1.0),)),),
    )
    coach = Coach(spec, models["InvertedPendulum-v5"])
    coach.reset(np.array([0.0, 0.15, 0.0, 0.0]))
    assert coach.act(np.array([0.0, 0.15, 0.0, 0.0]))[0] == 0.0  # derivative of a constant signal
    u = coach.act(np.array([0.0, 0.16, 0.0, 0.0]))[0]
    assert u == pytest.approx(-10.0 * 0.01 / coach.dt)  # reverse action: rising signal, negative push


def _ramp(coach: Coach, steps: int, value: float) -> list[float]:
    coach.reset()
    out = []
    for _ in range(steps):
        out.append(coach.act(np.array([value, 0.0, 0.0, 0.0]))[0])
    return out


@pytest.mark.parametrize("aw", ["none", "clamping", "back-calculation"])
def test_saturation_and_anti_windup(models, aw):
    loop = Loop(
        name="x",
        signal="slider_pos",
        kp=1.0,
        ki=5.0,
        anti_windup=aw,
        tt=0.2 if aw == "back-calculation" else 0.0,
        actuators=(("slide", 1.0),),
    )
    coach = Coach(CoachSpec("InvertedPendulum-v5", aw, (loop,)), models["InvertedPendulum-v5"])
    u = _ramp(coach, 200, -1.0)  # error +1: the command climbs to the limit 3
    assert max(u) == 3.0  # saturated to ctrlrange
    integral = coach.state[0]
    if aw == "none":
        assert integral > 30  # winds up
    elif aw == "clamping":
        assert integral == pytest.approx(2.0, abs=0.21)  # frozen near where saturation began
    else:
        assert 1.5 < integral < 3.5  # held near the limit by back-calculation
    # recovery: after the error flips, how long until the output leaves the limit
    recover = next((k for k in range(1, 400) if coach.act(np.array([1.0, 0.0, 0.0, 0.0]))[0] < 3.0), 400)
    if aw == "none":
        assert recover > 100
    else:
        assert recover <= 2


def test_cascade_shifts_the_inner_setpoint(models):
    coach = Coach(FULL, models["InvertedPendulum-v5"])
    obs = np.array([0.5, 0.0, 0.0, 0.0])  # cart far right, pole at zero
    coach.reset(obs)
    coach.act(obs)
    # outer: e = 0 - 0.5 -> 0.05 * -0.5 = -0.025 (integral starts at 0; derivative 0)
    # inner (direct): e = y - (r + v_outer) = 0 - (-0.00166667 - 0.025)
    e_inner = 0.0 - (-0.0016666651234593622 - 0.025)
    assert coach.last_command[0] == pytest.approx(6.0 * e_inner)
