"""The coaching wrapper: mechanics, not luck. Coach steps never reach the agent's training data."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from pidlab.controller.spec import load_spec
from pidlab.errors import CoachingError
from pidlab.rl.coaching import CoachingWrapper

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


def test_gymnasium_vector_envs_carry_the_accounts(ip_spec, models):
    from gymnasium.vector import AsyncVectorEnv, SyncVectorEnv

    def make():
        return CoachingWrapper(gym.make(IP), ip_spec)

    for cls in (SyncVectorEnv, AsyncVectorEnv):
        vec = cls([make, make])
        vec.reset(seed=0)
        agent = np.zeros(2, dtype=int)
        coach = np.zeros(2, dtype=int)
        finished = 0
        rng = np.random.default_rng(0)
        for _ in range(300):
            _, _, te, tr, info = vec.step(rng.uniform(-1, 1, (2, 1)))
            stepped = info.get("_coach_steps", np.zeros(2, bool))  # False: an autoreset step
            agent += stepped
            coach += np.where(stepped, info.get("coach_steps", 0), 0)
            for i in np.flatnonzero(te | tr):
                ep = info["coaching_episode"]
                assert ep["_agent_steps"][i]
                assert ep["agent_steps"][i] + ep["coach_steps"][i] == ep["env_steps"][i]
                finished += 1
        assert finished > 0 and coach.sum() > 0
        assert list(vec.get_attr("total_coach_steps")) == list(coach)
        assert list(vec.get_attr("total_agent_steps")) == list(agent)
        vec.close()


def test_sb3_subproc_vec_env(ip_spec):
    from stable_baselines3.common.vec_env import SubprocVecEnv

    def make():
        return CoachingWrapper(gym.make(IP), ip_spec)

    vec = SubprocVecEnv([make, make])
    vec.seed(0)
    vec.reset()
    coach = 0
    for _ in range(200):
        _, _, _, infos = vec.step(np.full((2, 1), 1.0))
        coach += sum(i["coach_steps"] for i in infos)
    totals = vec.get_attr("total_coach_steps")
    assert sum(totals) == coach > 0 and vec.get_attr("total_agent_steps") == [200, 200]
    vec.env_method("set_progress", 1.0)
    assert vec.get_attr("progress") == [1.0, 1.0]
    vec.close()


def test_growth_trigger_on_hand_made_histories():
    from collections import deque

    from pidlab.rl.coaching import GrowthTrigger

    t = GrowthTrigger("hinge_vel", 0.0, 0.3, 2)
    assert t.fires(deque([0.1, 0.2, 0.25]))  # grew twice, same sign, inside the band
    assert t.fires(deque([-0.1, -0.2, -0.25]))
    assert not t.fires(deque([0.2, 0.25]))  # too short a history
    assert not t.fires(deque([0.1, 0.2, 0.35]))  # outside the band
    assert not t.fires(deque([-0.1, 0.2, 0.25]))  # sign changed
    assert not t.fires(deque([0.2, 0.1, 0.25]))  # did not grow on both steps
    assert not t.fires(deque([0.0, 0.0, 0.0]))
    band = GrowthTrigger("v", 0.1, 0.4, 3)  # Hopper's: 0.1 <= |v| <= 0.4, growing for 3 steps
    assert band.fires(deque([0.01, 0.05, 0.08, 0.12]))
    assert not band.fires(deque([0.01, 0.05, 0.08, 0.09]))
    with pytest.raises(CoachingError, match="band"):
        GrowthTrigger("v", 0.5, 0.1, 1)


def test_growth_trigger_needs_nudge(ip_spec, models):
    from pidlab.rl.coaching import GrowthTrigger

    with pytest.raises(CoachingError, match="mode = nudge"):
        coached(ip_spec, models, trigger=GrowthTrigger("hinge_vel", 0, 0.3, 2))
    with pytest.raises(CoachingError, match="not an observation variable"):
        coached(ip_spec, models, mode="nudge", trigger=GrowthTrigger("pole_vel", 0, 0.3, 2))


def test_width_schedule_scales_the_region(ip_spec, models):
    from pidlab.rl.schedule import Schedule

    env, _ = coached(ip_spec, models, width=Schedule("linear", 1.0, 100.0))
    env.set_progress(0.0)
    assert env.region.scale == 1.0
    env.set_progress(1.0)
    assert env.region.scale == 100.0
    env.reset(seed=0)
    for _ in range(20):  # 100 times the box: hinge_vel +-9.9 rad/s, the agent is never coached
        _, _, te, tr, info = env.step(np.array([0.3]))
        assert info["coach_steps"] == 0
        if te or tr:
            break


def test_no_coach_is_a_pass_through_that_keeps_accounts(models):
    env = CoachingWrapper(gym.make(IP), None)
    bare = gym.make(IP)
    env.reset(seed=3)
    bare.reset(seed=3)
    for _ in range(50):
        a = np.array([0.7])
        o1, r1, te1, tr1, info = env.step(a)
        o2, r2, te2, tr2, _ = bare.step(a)
        np.testing.assert_array_equal(o1, o2)
        assert (r1, te1, tr1) == (r2, te2, tr2) and info["coach_steps"] == 0
        if te1 or tr1:
            assert info["coaching_episode"]["agent_steps"] == info["episode_agent_steps"]
            break


def test_ellipsoid_region_on_a_box_only_spec_says_why(models):
    from pidlab.region.takeover import region_from_bounds

    names = tuple(v.name for v in models["Hopper-v5"].card.observation)
    spec = load_spec(TUNING / "Hopper-v5.pidlab-robust.toml")
    with pytest.raises(CoachingError, match='recoverable box .*use region = "box"'):
        region_from_bounds(spec.bounds, names, "ellipsoid", spec.name)
    bare = dataclasses.replace(spec, bounds=None)
    with pytest.raises(CoachingError, match=r"no \[bounds.ellipsoid\]; run `pidlab bounds SPEC --write`"):
        region_from_bounds(bare.bounds, names, "ellipsoid", bare.name)


# ---------------------------------------------------------------- conditions files (issue 17, items 2, 8, 13)


def _conditions(**condition):
    return {"schema": "pidlab.conditions/1", "condition": {"c": {"coach": "none", **condition}}}


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (
            _conditions(bounds={"hinge_pos": [False, True]}),
            "bounds.hinge_pos = False: expected a finite number",
        ),
        (
            _conditions(bounds={"hinge_pos": [float("nan"), 1.0]}),
            "bounds.hinge_pos = nan: expected a finite number",
        ),
        (_conditions(bounds={"hinge_pos": [0.0, float("inf")]}), "bounds.hinge_pos = inf"),
        (
            _conditions(bounds={"hinge_pos": [0.0]}),
            "bounds.hinge_pos = [0.0]: expected [low, high] with low < high",
        ),
        (_conditions(coaching={"width": -1.0}), "coaching.width"),
        (_conditions(coaching={"probability": float("nan")}), "coaching.probability = nan"),
        (_conditions(coaching={"mode": "dance"}), "coaching.mode = 'dance': expected one of takeover, nudge"),
        (_conditions(coaching={"nudge_steps": True}), "coaching.nudge_steps = True"),
        (_conditions(coaching={"trigger": {"variable": "v", "high": 0.3, "steps": 0}}), "trigger.steps = 0"),
        (_conditions(coach="../../x"), "coach = '../../x': expected a name"),
        (_conditions(coach=3), "coach = 3: expected none, a spec file"),
        (_conditions(description=3), "description = 3: expected a string"),
        (
            {"schema": "pidlab.conditions/1", "condition": {"../../x": {"coach": "none"}}},
            "condition name = '../../x': expected a name of 1-64 letters",
        ),
        (
            {"schema": "pidlab.conditions/1", "condition": {"y" * 100_000: {"coach": "none"}}},
            "condition name = 'yyy",
        ),
        (_conditions(env={"../x": {"coach": "none"}}), "env: env id = '../x': expected a name"),
        (_conditions(env={"InvertedPendulum-v5": 3}), "expected a table"),
        ({"schema": "pidlab.conditions/1", "condition": {"c": 3}}, "condition.c: expected a table"),
    ],
)
def test_conditions_check_names_and_numbers_where_they_are_parsed(data, message):
    from pidlab.errors import ConditionError
    from pidlab.experiment.conditions import parse_conditions

    with pytest.raises(ConditionError) as err:
        parse_conditions(data, "conditions.toml")
    assert message in str(err.value) and "\n" not in str(err.value) and len(str(err.value)) < 400


@pytest.mark.parametrize("value", [None, [], "conditions", 3, {1: 2}])
def test_parse_conditions_of_no_table_is_a_condition_error(value):
    from pidlab.errors import ConditionError
    from pidlab.experiment.conditions import parse_conditions

    with pytest.raises(ConditionError, match="expected a table"):
        parse_conditions(value)


def test_a_trigger_without_mode_is_checked_as_a_nudge_and_resolved_with_the_recipe():
    from pidlab.experiment.conditions import parse_conditions

    trigger = {"variable": "hinge_vel", "high": 0.3, "steps": 2}
    conds = parse_conditions(
        _conditions(coaching={"mode": "nudge"}, env={"X-v0": {"coaching": {"trigger": trigger}}})
    )
    assert conds["c"].for_env("X-v0").coaching == {"mode": "nudge", "trigger": trigger}


def test_a_predictive_trigger_is_kept_by_a_condition_that_sets_the_mode():
    """A recipe's trigger = "predictive" is not a growth trigger: a takeover condition keeps it."""
    from pidlab.experiment.conditions import parse_conditions, resolve
    from pidlab.rl.recipe import load_recipe

    conds = parse_conditions(_conditions(coaching={"trigger": "predictive", "view": "penalty"}))
    assert conds["c"].default.coaching == {"trigger": "predictive", "view": "penalty"}  # no nudge added
    recipe = load_recipe(Path(__file__).resolve().parents[1] / "coach" / f"{IP}.toml")
    recipe = dataclasses.replace(
        recipe, coaching=dataclasses.replace(recipe.coaching, trigger="predictive", region="rescue")
    )
    takeover = parse_conditions(_conditions(coaching={"mode": "takeover", "handback": 0.5}))["c"]
    resolved, spec, _ = resolve(takeover, recipe)
    c = resolved.coaching
    assert (c.trigger, c.region, c.handback, spec) == ("predictive", "rescue", 0.5, None)


def test_spec_names_cannot_leave_tuning():
    from pidlab.errors import ConditionError
    from pidlab.experiment.conditions import spec_path

    assert spec_path("InvertedPendulum-v5", "pidlab-robust").name == "InvertedPendulum-v5.pidlab-robust.toml"
    assert str(spec_path("InvertedPendulum-v5", "../mine.toml")) == "../mine.toml"  # a file the user names
    for env, coach in (("InvertedPendulum-v5", "../../x"), ("../x", "paper"), ("InvertedPendulum-v5", "a/b")):
        with pytest.raises(ConditionError) as err:
            spec_path(env, coach)
        assert err.value.param in ("coach", "env_id")


def test_default_run_dir_stays_under_runs():
    from pidlab.controller.spec import CoachSpec, Loop
    from pidlab.errors import RunDirError
    from pidlab.rl.recipe import load_recipe
    from pidlab.rl.rundir import default_run_dir
    from tests.helpers import COACH

    recipe = load_recipe(COACH / "InvertedPendulum-v5.toml")
    loop = Loop(name="p", signal="hinge_pos", actuators=(("slide", 1.0),))
    good = CoachSpec("InvertedPendulum-v5", "pidlab-robust", (loop,))
    assert default_run_dir(recipe, good) == Path("runs/InvertedPendulum-v5/pidlab-robust-ppo-seed0")
    for name in ("../../../../tmp/x", "x" * 300, "a/b"):
        with pytest.raises(RunDirError):
            default_run_dir(recipe, dataclasses.replace(good, name=name))


def test_an_unknown_condition_with_a_long_name_is_one_short_line():
    from pidlab.errors import ConditionError
    from pidlab.experiment.conditions import load_conditions, select

    with pytest.raises(ConditionError) as err:
        select(load_conditions(), ["none", "z" * 100_000], "coach/conditions.toml")
    assert err.value.param == "condition_names" and len(str(err.value)) < 400


@pytest.mark.parametrize(
    ("name", "kwargs"),
    [
        ("pidlab-robust", {}),
        ("pidlab-rescue", {"region": "rescue", "trigger": "predictive"}),
        ("pidlab-rescue-edge", {"region": "rescue", "trigger": "predictive"}),
        ("pidlab-rescue-model", {"region": "rescue", "trigger": "predictive", "predictor": "model"}),
    ],
    ids=["box", "grid", "classifier", "grid-model"],
)
def test_progress_moves_every_region_kind(name, kwargs):
    # coach_env's users call set_progress every step; a classifier region once had no scale and
    # raised AttributeError there (the trainer calls it only with a schedule)
    from pidlab.rl.schedule import Schedule

    spec = load_spec(TUNING / f"{IP}.{name}.toml")
    env = CoachingWrapper(gym.make(IP), spec, mode="takeover", **kwargs)
    for p in (0.0, 0.5, 1.0):
        env.set_progress(p)
        assert env.region.scale == 1.0 and env.progress == p
    ones = CoachingWrapper(gym.make(IP), spec, mode="takeover", width=Schedule("linear", 1.0, 1.0), **kwargs)
    ones.set_progress(0.7)
    assert ones.region.scale == 1.0
