"""A user's robot: an env made from an MJCF and its card (``CardEnv``), and the analysis on it."""

from __future__ import annotations

import pickle
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import pidlab
from pidlab.controller.analysis import coach_to_continuous, loop_at_actuator
from pidlab.controller.pid import Coach
from pidlab.linear.lti import observable_part, siso_frequency_response
from pidlab.plant.card import load_card
from pidlab.plant.model import load_model
from pidlab.plant.observation import check_termination, observe

DATA = Path(__file__).resolve().parent / "data" / "cartpole"
ENV_ID = "MyCartPole-v0"


@pytest.fixture(scope="module")
def cartpole() -> str:
    """The user's cart-pole registered from its MJCF and card (no card in models/)."""
    if ENV_ID not in gym.registry:
        gym.register(
            ENV_ID,
            entry_point="pidlab.plant.card_env:CardEnv",
            kwargs={"xml_file": str(DATA / "cartpole.xml"), "card": str(DATA / f"{ENV_ID}.toml"), "frame_skip": 2},
            max_episode_steps=1000,
        )
    return ENV_ID


def test_a_card_env_observes_ends_and_pays_as_its_card_says(cartpole):
    env = gym.make(cartpole)
    card = load_card(DATA / f"{ENV_ID}.toml")
    obs, _ = env.reset(seed=0)
    assert np.all(np.abs(obs) <= 0.01)  # the operating point (all zero) with noise of at most 0.01
    u = env.unwrapped
    assert u.dt == pytest.approx(0.02) and env.observation_space.shape == (4,)
    rewards = []
    for _ in range(1000):
        obs, reward, terminated, truncated, _ = env.step(np.array([3.0]))  # push until it falls
        assert np.array_equal(obs, observe(card, u.model, u.data))
        rewards.append(reward)
        if terminated or truncated:
            break
    assert terminated and check_termination(card, u.model, u.data).violated
    assert rewards[-1] == 0.0 and set(rewards[:-1]) == {1.0}  # the card's alive reward, 0 on the fall
    again = pickle.loads(pickle.dumps(u))  # EzPickle: the env's arguments, made anew
    assert again.card.env_id == ENV_ID and again.frame_skip == 2


def test_load_model_takes_the_card_from_an_env_made_of_one(cartpole):
    loaded = load_model(cartpole)
    assert loaded.card is not None and loaded.card.env_id == ENV_ID
    assert loaded.frame_skip == 2 and loaded.card.observation_names[1] == "pole_angle_pos"


def test_a_loop_that_never_rolls_off_has_its_continuous_ms_at_infinity(cartpole):
    """Rate feedback with no filter: |S| -> 1 as w -> inf (Ms = 0 dB, never -0.00); sampled, the peak is at Nyquist."""
    loaded = load_model(cartpole)
    spec = pidlab.tune(loaded, preset="robust").spec
    coach = Coach(spec, loaded)
    a = pidlab.analyze_coach(coach, loaded)
    (cont,), (disc,) = a.continuous.margins, a.discrete.margins
    assert cont.ms == 1.0 and cont.ms_db == 0.0
    assert disc.ms > 1.05
    plant_d, _ = observable_part(a.linearization.sysd)
    plant_c, _ = observable_part(a.linearization.sys)
    loop_d = loop_at_actuator(plant_d, coach.linear_model(), 0)
    loop_c = loop_at_actuator(plant_c, coach_to_continuous(coach.linear_model()), 0)
    nyquist = np.pi / coach.dt
    w = np.array([0.5, 1.0, 5.0, 0.999 * nyquist])
    s_d = 1 / np.abs(1 + siso_frequency_response(loop_d, w))
    s_c = 1 / np.abs(1 + siso_frequency_response(loop_c, w))
    assert s_d[:3] == pytest.approx(s_c[:3], rel=0.01)  # they agree well below the Nyquist frequency
    assert s_d[3] == pytest.approx(disc.ms, rel=1e-3) and s_c[3] < 1.0  # and part near it
