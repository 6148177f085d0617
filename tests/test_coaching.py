"""The coaching wrapper: mechanics, not luck. Coach steps never reach the agent's training data."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from pidlab.coaching import CoachingError, CoachingWrapper
from pidlab.spec import load_spec

TUNING = Path(__file__).resolve().parents[1] / "tuning"
IP = "InvertedPendulum-v5"


@pytest.fixture(scope="module")
def ip_spec():
    return load_spec(TUNING / f"{IP}.pidlab-robust.toml")


class Counter(gym.Wrapper):
    """Counts real env steps (agent's and coach's alike) under the coaching wrapper."""

    def __init__(self, env):
        super().__init__(env)
        self.steps = 0

    def step(self, action):
        self.steps += 1
        return self.env.step(action)


class Recorder(gym.Wrapper):
    """What the agent sees and does: observations returned to it, actions it sends."""

    def __init__(self, env):
        super().__init__(env)
        self.obs: list[np.ndarray] = []
        self.actions: list[np.ndarray] = []

    def reset(self, **kw):
        obs, info = self.env.reset(**kw)
        self.obs.append(np.array(obs))
        return obs, info

    def step(self, action):
        self.actions.append(np.array(action))
        obs, r, te, tr, info = self.env.step(action)
        if not (te or tr):  # after a terminal step the agent next sees the reset observation
            self.obs.append(np.array(obs))
        return obs, r, te, tr, info


def coached(spec, models, **kw):
    counter = Counter(gym.make(spec.env_id))
    return CoachingWrapper(counter, spec, loaded=models[spec.env_id], **kw), counter


def test_bounds_that_never_trigger_give_the_bare_env(ip_spec, models):
    wide = dataclasses.replace(ip_spec, bounds={"method": "test", "box": {"hinge_pos": [-10.0, 10.0]}})
    env, _ = coached(wide, models)
    bare = gym.make(IP)
    rng = np.random.default_rng(0)
    env.reset(seed=5)
    bare.reset(seed=5)
    for _ in range(300):
        a = rng.uniform(-3, 3, 1)
        r1, r2 = env.step(a), bare.step(a)
        np.testing.assert_array_equal(r1[0], r2[0])
        assert r1[1:4] == r2[1:4]
        if r1[2] or r1[3]:
            env.reset(seed=6)
            bare.reset(seed=6)
    assert env.total_coach_steps == 0


def test_agent_plus_coach_steps_equal_env_steps(ip_spec, models):
    env, counter = coached(ip_spec, models)
    rng = np.random.default_rng(1)
    env.reset(seed=0)
    episodes = 0
    start = 0
    while episodes < 5:
        _, _, te, tr, info = env.step(rng.uniform(-1, 1, 1))
        if te or tr:
            ep = info["coaching_episode"]
            assert ep["agent_steps"] + ep["coach_steps"] == ep["env_steps"] == counter.steps - start
            assert ep["env_steps"] <= 1000  # the time limit counts coach steps
            if tr:
                assert ep["env_steps"] == 1000
            episodes += 1
            start = counter.steps
            env.reset()
    assert env.total_agent_steps + env.total_coach_steps == counter.steps
    assert env.total_coach_steps > 0 and env.total_interventions > 0


def test_agent_reward_only_by_default(ip_spec, models):
    env, _ = coached(ip_spec, models)
    env.reset(seed=0)
    for _ in range(50):
        _, r, te, tr, info = env.step(np.array([0.5]))
        assert r == info["agent_reward"]
        if info["coach_steps"]:
            assert info["coach_reward"] > 0  # IP pays 1 per surviving step, coach steps included
        if te or tr:
            break


def test_nudge_mode_takes_exactly_n_steps(ip_spec, models):
    env, _ = coached(ip_spec, models, mode="nudge", nudge_steps=2)
    env.reset(seed=0)
    seen = set()
    for _ in range(100):
        _, _, te, tr, info = env.step(np.array([1.0]))
        seen.add(info["coach_steps"])
        if te or tr:
            break
    assert seen <= {0, 1, 2} and 2 in seen  # 1 only when a coach step ends the episode


def test_schedule_zero_means_no_coaching(ip_spec, models):
    env, _ = coached(ip_spec, models, probability=lambda p: 1.0 - p)
    env.set_progress(1.0)
    env.reset(seed=0)
    for _ in range(100):
        _, _, te, tr, info = env.step(np.array([1.0]))
        assert info["coach_steps"] == 0
        if te or tr:
            env.reset()


def test_env_checkers_pass(ip_spec, models):
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check

    def plain():
        return CoachingWrapper(gym.make(IP), ip_spec, loaded=models[IP])

    check_env(plain(), skip_render_check=True)
    sb3_check(plain(), warn=False)


def test_no_coach_step_enters_the_ppo_rollout_buffer(ip_spec, models):
    from stable_baselines3 import PPO

    rec_holder = {}

    def make():
        env, _ = coached(ip_spec, models)
        rec_holder["rec"] = Recorder(env)
        return rec_holder["rec"]

    from stable_baselines3.common.vec_env import DummyVecEnv

    vec = DummyVecEnv([make])
    model = PPO("MlpPolicy", vec, n_steps=256, batch_size=64, n_epochs=1, seed=0, device="cpu")
    model.learn(total_timesteps=256)
    rec = rec_holder["rec"]
    coaching = rec.env
    buf = model.rollout_buffer
    n = buf.buffer_size
    assert coaching.total_agent_steps == n and coaching.total_coach_steps > 0
    # every stored observation is one the agent was given, in order (episode starts included)
    stored_obs = buf.observations.reshape(n, -1)  # SB3 flattens (n_steps, n_envs) after training
    np.testing.assert_allclose(stored_obs, np.array(rec.obs[:n]), rtol=0, atol=1e-6)
    # and every stored action is the agent's own (the env received its clipped version)
    stored_act = buf.actions.reshape(n, -1)
    np.testing.assert_allclose(np.clip(stored_act, -3, 3), np.array(rec.actions[:n]), atol=1e-6)


def test_no_coach_step_enters_the_sac_replay_buffer(ip_spec, models):
    from stable_baselines3 import SAC

    env, _ = coached(ip_spec, models)
    rec = Recorder(env)
    model = SAC("MlpPolicy", rec, learning_starts=100, buffer_size=1000, seed=0, device="cpu")
    model.learn(total_timesteps=200)
    rb = model.replay_buffer
    assert rb.pos == 200 == env.total_agent_steps and env.total_coach_steps > 0
    obs = np.array(rec.obs)
    stored = rb.observations[:200, 0]
    # each stored observation is one the agent saw (coach-produced states never appear alone)
    seen = {tuple(np.round(o, 6)) for o in obs}
    assert all(tuple(np.round(o, 6)) in seen for o in stored)
    scaled = rb.actions[:200, 0]
    np.testing.assert_allclose(scaled * 3.0, np.array(rec.actions[:200]), atol=1e-5)


def test_bad_configuration(ip_spec, models):
    with pytest.raises(CoachingError, match="mode 'sometimes'"):
        coached(ip_spec, models, mode="sometimes")
    bare = dataclasses.replace(ip_spec, bounds=None)
    with pytest.raises(CoachingError, match="pidlab bounds SPEC --write"):
        coached(bare, models)
    with pytest.raises(CoachingError, match="the spec is for InvertedPendulum-v5"):
        CoachingWrapper(gym.make("Hopper-v5"), ip_spec, loaded=models[IP])
