"""The value trigger (``value_trigger``, SAC): the critic's judge, the coach's proposal, the veto it
causes above the rescue region's floor, its accounts and its bad input.

Mechanics, not luck: nothing here asserts that an agent learned.
"""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest

from pidlab.controller.spec import load_spec
from pidlab.errors import CoachingError, RecipeError
from pidlab.files import read_json
from pidlab.rl.coaching import CoachingWrapper
from pidlab.rl.couplings import ValueTriggerCoupling, check_couplings, couplings_of, critic_judge
from pidlab.rl.recipe import ValueTrigger, parse_coaching, parse_recipe, recipe_to_dict
from pidlab.rl.train import make_vec_env, new_model, train
from tests.helpers import SHIELD, TUNING, changed_recipe, sac_recipe_data

IP = "InvertedPendulum-v5"


@pytest.fixture(scope="module")
def spec():
    return load_spec(TUNING / f"{IP}.pidlab-rescue.toml")


def tiny(**coaching):
    """SAC behind the rescue shield, with a value trigger and no coach buffer."""
    return parse_recipe(sac_recipe_data(value_trigger={"margin": 1.0}, **coaching), "tiny")


def shield(spec, **kw) -> CoachingWrapper:
    return CoachingWrapper(gym.make(IP), spec, **SHIELD, **kw)


# ----------------------------------------------------------------------------- the wrapper


def test_a_judge_that_always_prefers_the_coach_vetoes_every_action_the_region_lets_pass(spec):
    env, plain = shield(spec, record=True), shield(spec)
    seen = []

    def always(obs, agent, proposal):
        seen.append((obs.copy(), proposal.copy()))
        return True

    env.set_advisor(always)
    env.reset(seed=3)
    plain.reset(seed=3)
    for _ in range(50):
        _, _, terminated, truncated, info = env.step(np.zeros(1, dtype=np.float32))
        assert info["vetoed"] and info["veto_reason"] == "value" and info["coach_steps"] >= 1
        # the proposal put to the judge is the first action the coach's takeover ran
        np.testing.assert_allclose(info["coach_transitions"]["actions"][0], seen[-1][1])
        np.testing.assert_array_equal(info["coach_transitions"]["obs"][0], seen[-1][0])
        if terminated or truncated:
            env.reset()
    assert env.total_value_vetoes == env.total_vetoes == 50


def test_a_judge_that_never_prefers_the_coach_changes_nothing(spec):
    env, plain = shield(spec), shield(spec)
    env.set_advisor(lambda obs, agent, proposal: False)
    env.reset(seed=5)
    plain.reset(seed=5)
    rng = np.random.default_rng(0)
    for _ in range(200):
        a = rng.uniform(-3, 3, 1).astype(np.float32)
        out_a, out_b = env.step(a), plain.step(a)
        np.testing.assert_array_equal(out_a[0], out_b[0])
        assert out_a[4]["vetoed"] == out_b[4]["vetoed"]
        assert out_a[4].get("veto_reason") in (None, "region")
        if out_a[2] or out_a[3]:
            env.reset()
            plain.reset()
    assert env.total_value_vetoes == 0 and env.total_vetoes == plain.total_vetoes


def test_the_region_is_the_floor_and_the_judge_needs_it(spec):
    env = CoachingWrapper(gym.make(IP), spec, mode="takeover", region="box")  # reactive: no floor
    with pytest.raises(CoachingError, match="predictive trigger"):
        env.set_advisor(lambda *a: True)
    with pytest.raises(CoachingError, match="needs a coach"):
        CoachingWrapper(gym.make(IP), None).set_advisor(lambda *a: True)
    with pytest.raises(CoachingError, match=r"expected \(obs, action, proposal\) -> bool"):
        shield(spec).set_advisor("always")
    with pytest.raises(CoachingError, match="record='yes': expected True or False"):
        shield(spec, record="yes")


# ----------------------------------------------------------------------------- the critic's judge


@pytest.mark.parametrize("normalized", [False, True], ids=["raw-obs", "normalized-obs"])
def test_the_judge_compares_the_smaller_twin_critic_by_the_margin(spec, normalized):
    import torch

    data = sac_recipe_data(value_trigger={"margin": 1.0})
    data["sac"]["normalize"] = {"obs": normalized, "reward": False}
    recipe = parse_recipe(data, "tiny")
    venv = make_vec_env(recipe, spec)
    assert hasattr(venv, "normalize_obs") == normalized
    model = new_model(recipe, venv)
    rng = np.random.default_rng(1)
    model.num_timesteps = 0
    assert not critic_judge(model, venv, -1e9)(np.zeros(4), np.zeros(1), np.zeros(1))  # before learning
    model.num_timesteps = model.learning_starts + 1
    for _ in range(20):
        obs, a, p = rng.normal(size=4), rng.uniform(-3, 3, 1), rng.uniform(-3, 3, 1)
        x = venv.normalize_obs(obs[None]) if normalized else obs[None]
        acts = model.policy.scale_action(np.stack([a, p]))
        with torch.no_grad():
            q = torch.cat(model.critic(torch.as_tensor(np.repeat(x, 2, 0), dtype=torch.float32),
                                       torch.as_tensor(acts, dtype=torch.float32)), dim=1).min(dim=1).values  # fmt: skip
        gap = float(q[1] - q[0])
        assert critic_judge(model, venv, gap - 1e-4)(obs, a, p)
        assert not critic_judge(model, venv, gap + 1e-4)(obs, a, p)
    venv.close()


def test_the_coupling_scales_the_margin_by_the_alive_reward(spec):
    (coupling,) = [c for c in couplings_of(tiny(), spec) if isinstance(c, ValueTriggerCoupling)]
    assert coupling.alive == 1.0 and coupling.threshold == 1.0  # InvertedPendulum: 1 per step
    assert ValueTriggerCoupling(ValueTrigger(2.5), 10.0).threshold == 25.0


# ----------------------------------------------------------------------------- a run, and bad input


def test_a_run_counts_its_value_vetoes_among_its_interventions(spec, tmp_path):
    recipe = dataclasses.replace(tiny(), steps=300)
    result = train(recipe, spec, tmp_path / "run", progress_bar=False)
    summary = read_json(tmp_path / "run" / "summary.json")
    assert result.completed
    assert 0 <= summary["value_vetoes"] <= summary["interventions"]
    assert summary["env_steps"] == summary["agent_steps"] + summary["coach_steps"]


def test_the_field_reads_and_writes():
    assert parse_coaching({"value_trigger": {}}).value_trigger == ValueTrigger(1.0)
    again = parse_recipe(recipe_to_dict(tiny()), "again")
    assert again.coaching.value_trigger == ValueTrigger(1.0)
    with pytest.raises(RecipeError, match="coaching.value_trigger.margin"):
        parse_coaching({"value_trigger": {"margin": -1}})
    with pytest.raises(RecipeError, match=r"unknown field\(s\) \['gap'\]"):
        parse_coaching({"value_trigger": {"gap": 1}})


@pytest.mark.parametrize(
    ("change", "coach", "message"),
    [
        ({"algo": "ppo"}, True, "PPO's critic values states only; use algo = 'sac'"),
        ({}, False, "this run has no coach"),
        ({"coaching": {"trigger": "exit", "region": "rescue"}}, True, "expected trigger = 'predictive'"),
        ({"n_envs": 2, "vec_env": "subproc"}, True, "use vec_env = 'dummy'"),
    ],
)
def test_it_is_refused_where_it_cannot_judge(spec, change, coach, message):
    with pytest.raises(CoachingError) as info:
        check_couplings(changed_recipe(tiny(), change), spec if coach else None)
    assert message in str(info.value)
