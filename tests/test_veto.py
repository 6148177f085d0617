"""The minimal shield (rescue-veto): one coach step in place of a vetoed action, and the agent's runs."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import tomli_w
import tomllib

from pidlab.controller.pid import Coach
from pidlab.controller.spec import load_spec
from pidlab.experiment.conditions import load_conditions, resolve
from pidlab.plant.model import load_model
from pidlab.rl.coaching import CoachingWrapper
from pidlab.rl.recipe import load_recipe
from pidlab.rl.rundir import read_csv_rows
from pidlab.rl.train import train
from tests.helpers import COACH, ROOT, TUNING

IP = "InvertedPendulum-v5"


@pytest.fixture(scope="module")
def spec():
    return load_spec(TUNING / f"{IP}.pidlab-rescue.toml")


def veto_env(spec, env: gym.Env | None = None) -> CoachingWrapper:
    return CoachingWrapper(env or gym.make(IP), spec, mode="nudge", nudge_steps=1, region="rescue",
                           trigger="predictive", view="penalty")  # fmt: skip


def test_a_vetoed_action_is_replaced_by_one_coach_step_and_the_episode_goes_on(spec) -> None:
    env = veto_env(spec)
    twin_env, twin = gym.make(IP), Coach(spec, load_model(IP))
    obs, _ = env.reset(seed=1)
    twin_env.reset(seed=1)
    vetoes = 0
    for _ in range(300):
        before = twin_env.unwrapped.data.qpos.copy(), twin_env.unwrapped.data.qvel.copy()
        obs, reward, terminated, truncated, info = env.step(np.array([3.0], dtype=np.float32))  # push hard
        if info["vetoed"]:
            vetoes += 1
            # exactly one coach step ran, from the state the agent saw, in the agent's place
            twin_env.unwrapped.set_state(*before)
            twin.reset(twin_env.unwrapped._get_obs())
            expected, coach_reward, *_ = twin_env.step(twin.act(twin_env.unwrapped._get_obs()))
            np.testing.assert_allclose(obs, expected, atol=1e-12)
            assert info["coach_steps"] == 1 and info["intervened"]
            assert reward == pytest.approx(coach_reward - env.cost) and env.cost == 10.0
            assert not terminated  # the agent's episode goes on
        else:
            twin_env.unwrapped.set_state(env.unwrapped.data.qpos.copy(), env.unwrapped.data.qvel.copy())
        if terminated or truncated:
            break
    assert vetoes > 10  # full push: vetoed again and again, never a fall
    assert env.total_falls == 0 and env.total_coach_steps == vetoes == env.total_interventions


def test_runs_count_the_agents_uninterrupted_stretches(spec) -> None:
    env = veto_env(spec)
    env.reset(seed=2)
    rng = np.random.default_rng(0)
    ran, runs, longest, length = [], 0, 0, 0
    for _ in range(200):
        a = np.array([3.0 if rng.random() < 0.3 else 0.0], dtype=np.float32)
        _, _, terminated, truncated, info = env.step(a)
        if info["vetoed"]:
            length = 0
        else:
            length += 1
            runs += length == 1
            longest = max(longest, length)
        ran.append(not info["vetoed"])
        assert env.episode_runs == runs and env.episode_longest_run == longest
        if terminated or truncated:
            assert info["coaching_episode"]["runs"] == runs
            break
    assert 1 < runs < len(ran)  # vetoes split the agent's play into several runs


def test_the_rescue_veto_condition_trains_with_one_coach_step_per_intervention(tmp_path: Path) -> None:
    data = tomllib.loads((ROOT / "coach" / f"{IP}.toml").read_text())
    data.update(steps=2000, evaluation={"every": 1000, "episodes": 2, "seed": 1000000})
    path = tmp_path / "v.toml"
    path.write_text(tomli_w.dumps(data))
    condition = load_conditions(COACH / "conditions.toml")["rescue-veto"]
    recipe, spec, _ = resolve(condition, load_recipe(path))
    c = recipe.coaching
    assert (c.mode, c.nudge_steps, c.trigger, c.view) == ("nudge", 1, "predictive", "penalty")
    train(recipe, spec, tmp_path / "run", progress_bar=False)
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    eps = read_csv_rows(tmp_path / "run" / "episodes.csv")
    assert s["env_steps"] == s["agent_steps"] + s["coach_steps"] and s["coach_steps"] > 0
    assert s["coach_steps"] == s["interventions"]  # each veto: one coach step
    assert all(int(e["runs"]) >= 1 and int(e["longest_run"]) <= int(e["agent_steps"]) for e in eps)
    assert sum(int(e["interventions"]) for e in eps) <= s["interventions"]
