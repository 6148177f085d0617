"""Triggers (exit, predictive), hand-back and what the agent sees of a takeover (hidden, penalty, terminal).

Real MuJoCo envs, real SB3. The regions are hand-made rescue regions (``pidlab.lookup.LookupGrid``
put into a spec's ``[bounds.rescue]``): one wider than the termination domain (the trigger never
fires) and a narrow band about the upright state (it fires often).
"""

from __future__ import annotations

import dataclasses
import sys
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

from pidlab.controller.spec import load_spec
from pidlab.errors import CoachingError
from pidlab.lookup import LookupGrid
from pidlab.plant.model import load_model
from pidlab.rl.coaching import CoachingWrapper
from pidlab.rl.predict import Predictor
from pidlab.rl.rewards import alive_reward, failure_function, failure_reward
from tests.helpers import PAPER_ENVS, TUNING

IP, HOPPER = "InvertedPendulum-v5", "Hopper-v5"
VIEWS = ("hidden", "penalty", "terminal")
TRIGGERS = ("exit", "predictive")
BAND = {IP: ("hinge_pos", "hinge_vel"), HOPPER: ("rooty_pos", "rooty_vel")}
RANGE = {IP: (0.2, 2.0), HOPPER: (0.2, 2.0)}
"""Half-ranges of the grids' variables."""


def grid(
    env_id: str, marked: float, trigger: str = "reactive", half: tuple[float, float] | None = None
) -> LookupGrid:
    """A 20 x 20 grid on the env's band variables: cells whose centre is within ``marked`` of the half-range."""
    half = half or RANGE[env_id]
    centres = [(np.arange(20) + 0.5) / 20 * 2 * h - h for h in half]
    table = (np.abs(centres[0])[:, None] < marked * half[0]) & (
        np.abs(centres[1])[None, :] < marked * half[1]
    )
    return LookupGrid(BAND[env_id], tuple(-h for h in half), half, (20, 20), table, {}, trigger, 0.0)


def with_rescue(env_id: str, g: LookupGrid):
    spec = load_spec(TUNING / f"{env_id}.pidlab-robust.toml")
    return dataclasses.replace(spec, bounds={**spec.bounds, "rescue": g.to_table(), "takeover": "rescue"})


@pytest.fixture(scope="module")
def narrow():
    return {env: with_rescue(env, grid(env, 0.25)) for env in (IP, HOPPER)}


@pytest.fixture(scope="module")
def wide():
    """Every cell marked, on a domain far beyond the termination limits: nothing ever leaves it."""
    return {env: with_rescue(env, grid(env, 2.0, half=(50.0, 1e4))) for env in (IP, HOPPER)}


class EnvLog(gym.Wrapper):
    """Under the coaching wrapper: every real env step and reset."""

    def __init__(self, env):
        super().__init__(env)
        self.steps: list[tuple[Any, float, bool, bool, dict]] = []
        self.resets = 0

    def reset(self, **kw):
        self.resets += 1
        obs, info = self.env.reset(**kw)
        self.obs = obs
        return obs, info

    def step(self, action):
        out = self.env.step(action)
        self.steps.append(out)
        self.obs = out[0]
        return out


class AgentLog(gym.Wrapper):
    """Over the coaching wrapper: what the agent is given (the wrapper's record of its transitions)."""

    def __init__(self, env):
        super().__init__(env)
        self.obs: list[np.ndarray] = []  # every observation the agent acted on, in order
        self.rewards: list[float] = []
        self.dones: list[bool] = []
        self.terminal: list[np.ndarray] = []  # the observation each step returned

    def reset(self, **kw):
        obs, info = self.env.reset(**kw)
        self.obs.append(np.array(obs))
        return obs, info

    def step(self, action):
        obs, r, te, tr, info = self.env.step(action)
        self.rewards.append(float(r))
        self.dones.append(bool(te or tr))
        self.terminal.append(np.array(obs))
        if not (te or tr):
            self.obs.append(np.array(obs))
        return obs, r, te, tr, info


def wrapped(spec, trigger: str, view: str, **kw) -> tuple[CoachingWrapper, EnvLog]:
    log = EnvLog(gym.make(spec.env_id))
    kw.setdefault("max_coach_steps", 100)
    return CoachingWrapper(log, spec, region="rescue", trigger=trigger, view=view, **kw), log


def test_the_prediction_is_the_env_step_bit_for_bit():
    """Predicted observations equal the env's own, bit for bit (IDP's clipped constraint force included)."""
    for env_id in PAPER_ENVS:
        env = gym.make(env_id)
        predictor = Predictor(env, load_model(env_id).require_card())
        rng = np.random.default_rng(0)
        env.reset(seed=1)
        low, high = env.action_space.low, env.action_space.high
        for _ in range(300):
            a = rng.uniform(low, high).astype(np.float32)
            predicted = predictor.predict(a)
            obs, _, te, tr, _ = env.step(a)
            np.testing.assert_array_equal(predicted, obs)
            assert predicted.dtype == obs.dtype
            if te or tr:
                env.reset()


FIELDS = ("time", "qpos", "qvel", "act", "ctrl", "qacc", "qacc_warmstart", "qfrc_constraint", "site_xpos", "cacc",
          "cfrc_int", "cfrc_ext")  # fmt: skip
"""MjData fields a step leaves behind (``cacc`` and ``cfrc_*`` from ``mj_rnePostConstraint``)."""


def assert_same_data(env: gym.Env, bare: gym.Env) -> None:
    for name in FIELDS:
        np.testing.assert_array_equal(
            getattr(env.unwrapped.data, name), getattr(bare.unwrapped.data, name), name
        )


def test_a_prediction_is_copied_into_the_env_only_for_its_own_action():
    """``execute`` copies the predicted data in (no second simulation) only for the action it was computed for."""
    env, bare = gym.make(HOPPER), gym.make(HOPPER)
    predictor = Predictor(env, load_model(HOPPER).require_card())
    env.reset(seed=0)
    bare.reset(seed=0)
    rng = np.random.default_rng(1)
    for i in range(200):
        a, b = rng.uniform(-1, 1, 3), rng.uniform(-1, 1, 3)
        predictor.predict(a)
        if i % 3 == 1:
            predictor.discard()  # a vetoed prediction is never copied in later
        act = a if i % 3 == 0 else b  # 0: its own action (copied in); 1: discarded; 2: another action
        out, ref = predictor.execute(env.step, act), bare.step(act)
        np.testing.assert_array_equal(out[0], ref[0])
        assert out[1:4] == ref[1:4]
        assert_same_data(env, bare)
        assert "_step_mujoco_simulation" not in env.unwrapped.__dict__
        if ref[2] or ref[3]:
            env.reset(seed=i)
            bare.reset(seed=i)


def test_the_failure_reward_is_what_the_env_pays_on_a_failing_step():
    for env_id in PAPER_ENVS:
        env = gym.make(env_id)
        rng = np.random.default_rng(2)
        env.reset(seed=2)
        failures = 0
        while failures < 5:
            _, r, te, tr, info = env.step(
                env.action_space.sample() if rng.random() < 0.5 else env.action_space.high
            )
            if te:
                assert failure_reward(env_id, r, info) == r  # exactly: the same terms, the same operations
                failures += 1
            if te or tr:
                env.reset()
    with pytest.raises(CoachingError, match="failure reward of Pusher-v5: add \\[reward\\] failure"):
        failure_reward("Pusher-v5", 0.0, {})


def test_the_reward_facts_are_the_cards(tmp_path, monkeypatch):
    """A user's card sets what the views pay; a card without them says where to add them."""
    folder = tmp_path / "models"
    folder.mkdir()
    monkeypatch.setenv("PIDLAB_MODELS", str(folder))
    text = (TUNING.parent / "models" / f"{HOPPER}.toml").read_text()
    (folder / f"{HOPPER}.toml").write_text(
        text.replace(
            'failure = ["reward_forward", "reward_ctrl"]', 'failure = ["reward_ctrl", "x_velocity"]'
        ).replace("alive = 1.0", "alive = 2.5")
    )
    pay = failure_function(HOPPER)
    assert pay(7.0, {"reward_ctrl": -0.25, "x_velocity": 1.5, "reward_forward": 9.0}) == 1.25
    with pytest.raises(CoachingError, match="no number 'x_velocity'"):
        pay(7.0, {"reward_ctrl": -0.25})
    assert alive_reward(gym.make(HOPPER)) == 2.5
    start = text.index("[reward]")
    (folder / f"{HOPPER}.toml").write_text(text[:start] + text[text.index("[paper]") :])  # no [reward]
    with pytest.raises(
        CoachingError, match=r"add \[reward\] failure = \.\.\. to its model card .*Hopper-v5.toml"
    ):
        failure_function(HOPPER)
    assert alive_reward(gym.make(HOPPER)) == 1.0  # the env's own healthy_reward


@pytest.mark.parametrize("trigger", TRIGGERS)
@pytest.mark.parametrize("view", VIEWS)
@pytest.mark.parametrize("env_id", [IP, HOPPER])
def test_a_trigger_that_never_fires_gives_the_bare_env(env_id, view, trigger, wide):
    """A region that holds every state: the wrapper is the bare env, step for step.

    The predictive trigger alone still vetoes the one action that the env would end (no rescue
    region holds a state its termination rule ends): there the two part.
    """
    env, _ = wrapped(wide[env_id], trigger, view)
    bare = gym.make(env_id)
    rng = np.random.default_rng(3)
    high = bare.action_space.high
    env.reset(seed=5)
    bare.reset(seed=5)
    ends = 0
    for _ in range(400):
        a = rng.uniform(-high, high)
        r2 = bare.step(a)
        if trigger == "predictive" and r2[2]:
            env.step(a)
            assert env.total_interventions == 1  # vetoed, not taken to the termination
            return
        r1 = env.step(a)
        np.testing.assert_array_equal(r1[0], r2[0])
        assert r1[1:4] == r2[1:4]
        assert_same_data(env, bare)  # the predicted data copied in are the bare env's, bit for bit
        if r1[2] or r1[3]:
            ends += 1
            env.reset()  # no rescue pending: a real reset, as the bare env's
            bare.reset()
    assert trigger == "exit" and ends > 0 and env.total_interventions == env.total_coach_steps == 0


@pytest.mark.parametrize("trigger", TRIGGERS)
@pytest.mark.parametrize("view", VIEWS)
def test_the_accounts_add_up(view, trigger, narrow):
    """Agent steps + coach steps = env steps; agent episodes, env episodes, resets and falls agree."""
    env, log = wrapped(narrow[IP], trigger, view)
    rng = np.random.default_rng(4)
    env.reset(seed=0)
    rows = []
    for _ in range(1500):
        _, _, te, tr, info = env.step(rng.uniform(-3, 3, 1))
        if te or tr:
            rows.append(info["coaching_episode"])
            env.reset()
    assert env.total_interventions > 0 and env.total_falls > 0
    assert env.total_agent_steps + env.total_coach_steps == len(log.steps)
    assert sum(r["env_steps"] for r in rows) <= len(log.steps)
    assert all(r["agent_steps"] + r["coach_steps"] == r["env_steps"] for r in rows)
    transitions = 1500
    assert env.total_agent_steps + env.total_vetoes == transitions
    assert env.total_vetoes == (env.total_interventions if trigger == "predictive" else 0)
    assert env.total_agent_episodes == len(rows)
    assert (
        env.total_env_episodes
        == sum(r["env_end"] for r in rows)
        == log.resets - 1
        == env.total_env_resets - 1
    )
    assert env.total_falls == sum(r["fell"] for r in rows) == sum(s[2] for s in log.steps)
    if view == "terminal":  # every takeover ends an agent episode; only some end the env's
        assert all(r["interventions"] <= 1 for r in rows)
        assert len(rows) == env.total_interventions + sum(not r["interventions"] for r in rows)
        assert env.total_env_episodes < env.total_agent_episodes
    else:
        assert env.total_env_episodes == env.total_agent_episodes
        assert all(r["terminated"] == r["fell"] for r in rows)


@pytest.mark.parametrize("trigger", TRIGGERS)
@pytest.mark.parametrize("view", VIEWS)
def test_the_reward_the_agent_is_given(view, trigger, narrow):
    """Per view and trigger, the transition's reward is the documented one (Hopper: rewards vary per step)."""
    env, log = wrapped(narrow[HOPPER], trigger, view, max_coach_steps=30)
    assert env.cost == (10.0 if view == "penalty" else 0.0)  # 10 alive rewards of 1
    rng = np.random.default_rng(5)
    env.reset(seed=1)
    seen = 0
    for _ in range(600):
        before = len(log.steps)
        _, r, te, tr, info = env.step(rng.uniform(-1, 1, 3))
        ran = log.steps[before:]
        own = ran[0] if not info["vetoed"] else None  # the agent's own env step, when it ran
        first = ran[0] if info["vetoed"] else (ran[1] if len(ran) > 1 else None)  # the coach's first
        assert len(ran) == (0 if info["vetoed"] else 1) + info["coach_steps"]
        if not info["intervened"]:
            assert own is not None and r == own[1] and (te, tr) == own[2:4]
        else:
            seen += 1
            stand_in = own if own is not None else first  # the env step that ran for the agent's action
            if view == "terminal":
                assert te and not tr
                assert r == failure_reward(HOPPER, stand_in[1], stand_in[4])
                assert info["env_ended"] == (ran[-1][2] or ran[-1][3])
            else:
                paid = stand_in[1] - (10.0 if view == "penalty" else 0.0)
                assert r == paid and (te, tr) == ran[-1][2:4]
        if te or tr:
            env.reset()
    assert seen > 0


def test_hand_back_inside_the_inner_region(narrow):
    env, _ = wrapped(narrow[IP], "predictive", "hidden", handback=0.5)
    assert env._handback_region is not env.region
    rng = np.random.default_rng(6)
    env.reset(seed=0)
    handed_back = 0
    for _ in range(500):
        obs, _, te, tr, info = env.step(rng.uniform(-3, 3, 1))
        if info["intervened"] and not (te or tr) and info["coach_steps"] < env.max_coach_steps:
            assert env._handback_region.contains(obs)  # the deeper half of the band
            handed_back += 1
        if te or tr:
            env.reset()
    assert handed_back > 0
    with pytest.raises(CoachingError, match=r"handback 1.5: expected a fraction in \(0, 1\]"):
        wrapped(narrow[IP], "predictive", "hidden", handback=1.5)


def test_terminal_view_resets_to_the_rescued_state(narrow):
    env, log = wrapped(narrow[IP], "exit", "terminal")
    rng = np.random.default_rng(7)
    env.reset(seed=0)
    rescued = fell = 0
    while rescued < 3 or fell < 1:
        _, _, te, tr, info = env.step(rng.uniform(-3, 3, 1))
        if not (te or tr):
            continue
        resets = log.resets
        start, reset_info = env.reset()
        if info["env_ended"]:  # the rescue failed (or the agent fell): a real reset
            assert log.resets == resets + 1 and "rescued" not in reset_info
            fell += info["fell"]
        else:  # the env was not reset: the agent's next episode starts where the coach handed back
            assert log.resets == resets and reset_info == {"rescued": True}
            np.testing.assert_array_equal(start, log.obs)
            assert env.episode_agent_steps == env.episode_coach_steps == 0
            rescued += 1
    # a reset with a seed (or options) is always a real one, even with a rescue pending
    while True:
        _, _, te, tr, info = env.step(rng.uniform(-3, 3, 1))
        if te and not info["env_ended"]:
            break
        if te or tr:
            env.reset()
    resets = log.resets
    env.reset(seed=11)
    assert log.resets == resets + 1


def test_refusals(narrow, wide):
    spec = load_spec(TUNING / f"{IP}.pidlab-robust.toml")
    with pytest.raises(CoachingError, match=r"no rescue region; run `pidlab rescue SPEC --write`"):
        CoachingWrapper(gym.make(IP), spec, region="rescue", trigger="predictive")
    predictive_grid = with_rescue(IP, grid(IP, 0.25, trigger="predictive"))
    with pytest.raises(CoachingError, match="derived for the predictive trigger"):
        CoachingWrapper(gym.make(IP), predictive_grid, region="rescue")
    CoachingWrapper(gym.make(IP), predictive_grid, region="rescue", trigger="predictive")  # its own trigger
    CoachingWrapper(gym.make(IP), narrow[IP], region="rescue", trigger="predictive")  # reactive: both
    with pytest.raises(CoachingError, match="ClipAction changes the agent's action"):
        CoachingWrapper(
            gym.wrappers.ClipAction(gym.make(IP)), narrow[IP], region="rescue", trigger="predictive"
        )
    from pidlab.rl.schedule import Schedule

    with pytest.raises(CoachingError, match="a rescue region cannot be scaled"):
        CoachingWrapper(gym.make(IP), narrow[IP], region="rescue", width=Schedule("linear", 1.0, 2.0))
    CoachingWrapper(gym.make(IP), narrow[IP], region="rescue", width=Schedule("constant", 1.0, 1.0))
    for kw, message in [
        ({"trigger": "predictive", "region": "box"}, "tests the rescue region"),
        ({"view": "peek"}, "view 'peek': expected one of hidden, penalty, terminal"),
        ({"view": "penalty", "cost": -1.0}, "cost -1.0: expected a finite number >= 0"),
        ({"view": "terminal", "reward": "total"}, "reward 'total' with view 'terminal'"),
        ({"trigger": "sometimes"}, "trigger 'sometimes'"),
    ]:
        with pytest.raises(CoachingError, match=message):
            CoachingWrapper(gym.make(IP), narrow[IP], **{"region": "rescue", **kw})


def test_env_checkers_pass_with_the_predictive_trigger_and_the_terminal_view(narrow):
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check

    def make():
        return CoachingWrapper(
            gym.make(IP), narrow[IP], region="rescue", trigger="predictive", view="terminal"
        )

    check_env(make(), skip_render_check=True)
    sb3_check(make(), warn=False)


# ------------------------------------------------------------------ what SB3 stores


def _sb3_env(spec, trigger, view, holder):
    def make():
        env, _ = wrapped(spec, trigger, view)
        holder["log"] = AgentLog(env)
        return holder["log"]

    return make


@pytest.mark.parametrize("trigger", TRIGGERS)
@pytest.mark.parametrize("view", VIEWS)
def test_the_ppo_rollout_buffer_holds_what_the_wrapper_gave(view, trigger, narrow):
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    holder: dict[str, AgentLog] = {}
    vec = DummyVecEnv([_sb3_env(narrow[IP], trigger, view, holder)])
    model = PPO("MlpPolicy", vec, n_steps=128, batch_size=64, n_epochs=1, seed=0, device="cpu")
    model.learn(total_timesteps=128)
    log, buf, n = holder["log"], model.rollout_buffer, 128
    coaching = log.env
    assert coaching.total_agent_steps + coaching.total_vetoes == n and coaching.total_interventions > 0
    np.testing.assert_array_equal(buf.rewards.reshape(n), np.array(log.rewards[:n], dtype=np.float32))
    # an episode starts at the first step and after every done (terminal view: the rescued state)
    starts = np.array([True, *log.dones[: n - 1]])
    np.testing.assert_array_equal(buf.episode_starts.reshape(n), starts.astype(np.float32))
    np.testing.assert_allclose(buf.observations.reshape(n, -1), np.array(log.obs[:n]), rtol=1e-6, atol=1e-6)
    if view == "terminal":
        assert sum(log.dones) > coaching.total_env_episodes  # agent episodes ended where the env went on
        assert max(log.rewards) == 1.0 and min(log.rewards) == 0.0  # IP: 1 per step, 0 at a trigger
    if view == "penalty":
        assert min(log.rewards) <= 1.0 - 10.0


@pytest.mark.parametrize("trigger", TRIGGERS)
@pytest.mark.parametrize("view", VIEWS)
def test_the_sac_replay_buffer_holds_what_the_wrapper_gave(view, trigger, narrow):
    from stable_baselines3 import SAC
    from stable_baselines3.common.vec_env import DummyVecEnv

    holder: dict[str, AgentLog] = {}
    vec = DummyVecEnv([_sb3_env(narrow[IP], trigger, view, holder)])
    model = SAC("MlpPolicy", vec, learning_starts=150, buffer_size=1000, seed=0, device="cpu")
    model.learn(total_timesteps=150)
    log, rb, n = holder["log"], model.replay_buffer, 150
    assert rb.pos == n and log.env.total_interventions > 0
    assert sum(log.dones) > 0 or (trigger == "predictive" and view != "terminal")  # kept alive by the coach
    np.testing.assert_array_equal(rb.rewards[:n, 0], np.array(log.rewards[:n], dtype=np.float32))
    np.testing.assert_array_equal(rb.dones[:n, 0], np.array(log.dones[:n], dtype=np.float32))
    assert not rb.timeouts[:n].any()  # no time limit within 150 steps: every done is a termination
    # the next observation of a done is the observation its step returned (SB3's terminal_observation)
    np.testing.assert_allclose(rb.next_observations[:n, 0], np.array(log.terminal[:n]), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(rb.observations[:n, 0], np.array(log.obs[:n]), rtol=1e-6, atol=1e-6)


# ------------------------------------------------------------------ training logs


def test_training_logs_agent_episodes_env_episodes_resets_and_falls(tmp_path, narrow):
    import tomli_w

    from pidlab.experiment.analysis import read_logs
    from pidlab.files import read_json
    from pidlab.rl.recipe import load_recipe
    from pidlab.rl.rundir import read_csv_rows
    from pidlab.rl.train import train
    from tests.helpers import COACH

    if sys.version_info >= (3, 11):
        import tomllib
    else:  # pragma: no cover
        import tomli as tomllib

    data = tomllib.loads((COACH / f"{IP}.toml").read_text())
    data |= {"steps": 800, "evaluation": {"every": 800, "episodes": 1}, "checkpoint": {"every": 400}}
    data["ppo"] |= {"n_envs": 2, "n_steps": 16}
    data["coaching"] |= {
        "trigger": "predictive",
        "region": "rescue",
        "view": "terminal",
        "max_coach_steps": 100,
    }
    path = tmp_path / "recipe.toml"
    path.write_text(tomli_w.dumps(data))
    recipe = load_recipe(path)
    assert recipe.coaching.region == "rescue" and recipe.n_envs == 2
    run = tmp_path / "run"
    result = train(recipe, narrow[IP], run, progress_bar=False)
    s = read_json(run / "summary.json")
    rows = read_csv_rows(run / "episodes.csv")
    assert result.env_steps == s["agent_steps"] + s["coach_steps"] >= 800
    assert s["agent_episodes"] == s["episodes"] == len(rows) > s["env_episodes"]  # rescued agent episodes
    assert s["env_episodes"] == sum(int(r["env_end"]) for r in rows) == result.env_episodes
    assert s["falls"] == sum(int(r["fell"]) for r in rows) == result.falls
    assert s["env_resets"] == 2 + s["env_episodes"] == result.env_resets  # each env's first, then one per end
    assert all(r["terminated"] == "1" for r in rows if r["env_end"] == "0")  # a takeover ended the agent's
    previous = 0
    for r in sorted(rows, key=lambda r: int(r["env_steps_so_far"])):  # env steps are never lost or doubled
        assert int(r["env_steps_so_far"]) >= previous
        previous = int(r["env_steps_so_far"])
    logs = read_logs(run, s)
    assert (logs.falls, logs.env_resets) == (s["falls"], s["env_resets"])
