"""``pidlab.coach_env``: your env and your own training loop, coached as pidlab's conditions couple it."""

from __future__ import annotations

import gymnasium as gym
import pytest

import pidlab
from pidlab.errors import CoachingError, ConditionError, PidlabError
from pidlab.experiment.conditions import load_conditions, resolve
from pidlab.rl.recipe import load_recipe
from pidlab.rl.wrap import wrapper_arguments
from tests.helpers import ROOT, TUNING

IP = "InvertedPendulum-v5"
RESCUE = TUNING / f"{IP}.pidlab-rescue.toml"


class StepCounter(gym.Wrapper):
    """Counts the env steps that really ran, under the coaching wrapper."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.steps = 0

    def step(self, action):  # type: ignore[no-untyped-def]
        self.steps += 1
        return self.env.step(action)


def test_two_lines_coach_a_plain_sb3_loop_and_every_env_step_is_counted():
    from stable_baselines3 import PPO

    counter = StepCounter(gym.make(IP))
    env = pidlab.coach_env(counter, RESCUE)  # rescue-terminal: the predictive veto, a veto ends the episode
    model = PPO("MlpPolicy", env, n_steps=128, batch_size=64, n_epochs=1, seed=3, device="cpu")
    model.learn(512)
    assert env.total_vetoes > 0 and env.total_coach_steps > 0  # PPO's first actions are vetoed
    assert counter.steps == env.total_agent_steps + env.total_coach_steps
    assert env.total_falls == 0  # the rescue shield
    assert model.num_timesteps == 512


def test_the_wrapper_is_the_one_pidlabs_trainer_builds_for_the_condition():
    recipe = load_recipe(ROOT / "coach" / f"{IP}.toml")
    for name in ("rescue-terminal", "rescue-veto", "blend", "residual", "pidlab"):
        condition = load_conditions()[name]
        resolved, spec, _ = resolve(condition, recipe)
        env = pidlab.coach_env(gym.make(IP), spec, name)
        expected = wrapper_arguments(resolved.coaching, coached=True)
        got = {k: getattr(env, k) for k in ("mode", "view", "handback", "max_coach_steps", "nudge_steps")}
        assert got == {k: expected[k] for k in got}, name
        assert env.predictive == (expected["trigger"] == "predictive")
        assert (env.blend is None) == (expected["blend"] is None)
    # fields replace the condition's
    env = pidlab.coach_env(gym.make(IP), RESCUE, view="penalty", cost=3.0)
    assert env.view == "penalty" and env.cost == 3.0


@pytest.mark.parametrize(
    ("args", "kwargs", "error", "message"),
    [
        ((RESCUE, "none"), {}, CoachingError, "condition none has no coach"),
        ((RESCUE, "warm-start"), {}, CoachingError, "uses demonstrations, warm_start: pidlab's trainer runs that"),
        ((RESCUE, "telepathy"), {}, ConditionError, "unknown condition"),
        ((TUNING / "Hopper-v5.pidlab-rescue.toml",), {}, CoachingError, "the spec is for Hopper-v5"),
        ((RESCUE,), {"view": "sideways"}, PidlabError, "view"),
        ((RESCUE,), {"handback": 2.0}, PidlabError, "handback"),
    ],
)
def test_bad_couplings_are_one_line(args, kwargs, error, message):
    with pytest.raises(error, match=message) as info:
        pidlab.coach_env(gym.make(IP), *args, **kwargs)
    assert "\n" not in str(info.value)


def test_a_condition_that_needs_a_region_the_spec_lacks_says_so():
    with pytest.raises(PidlabError, match="rescue") as info:
        pidlab.coach_env(gym.make(IP), TUNING / f"{IP}.pidlab-weak.toml", "rescue-terminal")
    assert "\n" not in str(info.value)
