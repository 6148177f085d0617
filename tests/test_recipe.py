"""Recipes and schedules: the shipped recipes load, malformed ones name the field and what is allowed."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest

from pidlab.controller.autotune import PRESETS as TUNING_PRESETS
from pidlab.errors import RecipeError, ScheduleError
from pidlab.rl.recipe import PRESETS, load_recipe, parse_recipe, recipe_to_dict, with_overrides
from pidlab.rl.schedule import Schedule, parse_schedule

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
ENVS = ("InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Hopper-v5", "Walker2d-v5")


@pytest.mark.parametrize("env", ENVS)
def test_shipped_recipes_load_and_round_trip(env):
    r = load_recipe(ROOT / "coach" / f"{env}.toml")
    assert r.env_id == env and r.algo == "ppo" and {"ppo", "sac"} <= set(r.algorithms)
    assert "Zoo" in r.sources["ppo"]
    again = parse_recipe(recipe_to_dict(r))
    assert again == type(r)(**{**r.__dict__, "path": None})


def test_trigger_view_cost_and_handback_round_trip():
    data = base()
    data["coaching"] = {"trigger": "predictive", "view": "penalty", "cost": 2.5, "handback": 0.5}
    r = parse_recipe(data)
    c = r.coaching
    assert (c.trigger, c.region, c.view, c.cost, c.handback) == ("predictive", "rescue", "penalty", 2.5, 0.5)
    assert parse_recipe(recipe_to_dict(r)) == r
    # the defaults are not written (a run's settings read as before), and "exit" is the default trigger
    data["coaching"] = {"trigger": "exit"}
    plain = parse_recipe(data)
    assert plain.coaching.trigger is None and plain.coaching.region == "box" and plain.coaching.cost is None
    assert not {"trigger", "view", "cost", "handback"} & set(recipe_to_dict(plain)["coaching"])


def test_schedules():
    lin = Schedule("linear", 1.0, 0.0, 0.2, 0.6)
    assert lin(0.0) == 1.0 and lin(0.2) == 1.0 and math.isclose(lin(0.4), 0.5) and lin(0.6) == 0.0 and lin(1) == 0.0
    cos = Schedule("cosine", 1.0, 0.0)
    assert math.isclose(cos(0.5), 0.5) and cos(0.0) == 1.0 and math.isclose(cos(1.0), 0.0, abs_tol=1e-12)
    exp = Schedule("exponential", 1.0, 100.0)
    assert math.isclose(exp(0.5), 10.0)
    step = Schedule("step", 1.0, 0.0, 0.0, 0.5)
    assert step(0.49) == 1.0 and step(0.5) == 0.0
    assert parse_schedule(0.3, "x")(0.9) == 0.3
    with pytest.raises(ScheduleError, match="expected one of constant"):
        Schedule("sigmoid")
    with pytest.raises(ScheduleError, match="begin <= finish"):
        Schedule("linear", 1, 0, 0.8, 0.2)
    with pytest.raises(ScheduleError, match="unknown field"):
        parse_schedule({"shape": "linear", "stop": 1}, "coaching.probability")


def base() -> dict:
    """The shipped IP recipe on one env (its [ppo] table asks for 4; the rollout checks assume one)."""
    data = tomllib.loads((ROOT / "coach" / "InvertedPendulum-v5.toml").read_text())
    data["ppo"].pop("n_envs")
    return data


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"schema": "pidlab.recipe/9"}, "expected 'pidlab.recipe/1'"),
        ({"stepz": 10}, "unknown field(s) ['stepz']"),
        ({"steps": -5}, "steps = -5: expected an integer in [1, 1000000000000]"),
        ({"steps": "many"}, "steps = 'many': expected an integer"),
        ({"algo": "td3"}, "algo = 'td3': expected one of ppo, sac"),
        ({"vec_env": "ray"}, "vec_env = 'ray': expected one of dummy, subproc"),
        ({"ppo": {"n_stepz": 3}}, "unknown PPO argument(s) ['n_stepz']"),
        ({"ppo": {"learning_rate": "fast"}}, "learning_rate = 'fast'"),
        ({"ppo": {"clip_range": "lin_x"}}, "clip_range = 'lin_x': expected a number > 0, or 'lin_<number>'"),
        ({"ppo": {"policy_kwargs": {"activation_fn": "sigmoid"}}}, "activation_fn = 'sigmoid'"),
        ({"coaching": {"mode": "always"}}, "coaching.mode = 'always': expected one of takeover, nudge"),
        ({"coaching": {"region": "ball"}}, "coaching.region = 'ball'"),
        ({"coaching": {"probability": {"shape": "linear", "start": 2.0}}}, "probability cannot exceed 1"),
        ({"coaching": {"width": 0.0}}, "must be positive"),
        ({"coaching": {"off_after": 1.5}}, "off_after = 1.5"),
        ({"coaching": {"trigger": {"variable": "hinge_vel", "high": 0.3, "steps": 2}}}, "needs mode = 'nudge'"),
        ({"coaching": {"mode": "nudge", "trigger": {"variable": "v", "high": 0.3, "steps": 0}}}, "steps = 0"),
        ({"coaching": {"view": "peek"}}, "coaching.view = 'peek': expected one of hidden, penalty, terminal"),
        ({"coaching": {"cost": -1.0}}, "coaching.cost = -1.0: expected a finite number >= 0"),
        ({"coaching": {"handback": 0.0}}, "coaching.handback = 0.0: expected a finite number in (0, 1]"),
        ({"coaching": {"handback": 1.5}}, "coaching.handback = 1.5: expected a finite number in (0, 1]"),
        ({"coaching": {"trigger": "later"}}, "coaching.trigger = 'later': expected one of exit, predictive"),
        ({"coaching": {"trigger": 3}}, "coaching.trigger = 3: expected one of exit, predictive"),
        ({"coaching": {"trigger": "predictive", "region": "box"}}, "expected region = 'rescue'"),
        ({"coaching": {"region": "rescue", "width": {"shape": "linear", "start": 1.0, "end": 2.0}}},
         "coaching.width: a rescue region (a lookup grid) cannot be scaled"),
        ({"coaching": {"view": "terminal", "reward": "total"}}, "coaching.reward = 'total' with view = 'terminal'"),
        ({"win": {}}, "win.target: missing"),
        ({"evaluation": {"episodes": 0}}, "evaluation.episodes = 0"),
        ({"normalize": {"obs": "yes"}}, "normalize.obs = 'yes': expected true or false"),
    ],
)
def test_malformed_recipes_name_the_field(change, message):
    data = base()
    for key, value in change.items():
        if isinstance(value, dict) and isinstance(data.get(key), dict) and key != "win":
            data[key] = {**data[key], **value}
        else:
            data[key] = value
    with pytest.raises(RecipeError) as err:
        parse_recipe(data, "r.toml")
    assert message in str(err.value)


def test_overrides():
    r = load_recipe(ROOT / "coach" / "InvertedPendulum-v5.toml")
    o = with_overrides(r, algo="sac", steps=10, seed=4, n_envs=2)
    assert (o.algo, o.steps, o.seed, o.n_envs) == ("sac", 10, 4, 2)
    assert o.algorithms == r.algorithms  # identical agent settings whatever the coach
    without_sac = parse_recipe({k: v for k, v in base().items() if k != "sac"})
    with pytest.raises(RecipeError, match=r"no \[sac\] table"):
        with_overrides(without_sac, algo="sac")


@pytest.mark.parametrize(
    ("kwargs", "param", "message"),
    [
        ({"algo": "td3"}, "algo", "algo='td3': expected one of ppo, sac"),
        ({"steps": 0}, "steps", "steps=0: expected an integer in [1, 1000000000000]"),
        ({"n_envs": 0}, "n_envs", "n_envs=0: expected an integer in [1, 1024]"),
        ({"seed": -1}, "seed", "seed=-1: expected an integer in [0, 4294967295]"),
        ({"seed": 2**40}, "seed", "seed=1099511627776: expected an integer in [0, 4294967295]"),
        ({"seed": True}, "seed", "seed=True: expected an integer in [0, 4294967295]"),
        ({"n_envs": 10**9}, "n_envs", "n_envs=1000000000: expected an integer in [1, 1024]"),
    ],
)
def test_overrides_name_the_python_parameter(kwargs, param, message):
    r = load_recipe(ROOT / "coach" / "InvertedPendulum-v5.toml")
    with pytest.raises(RecipeError) as err:
        with_overrides(r, **kwargs)
    assert str(err.value) == message and err.value.param == param


def test_one_list_of_presets():
    assert PRESETS == (*TUNING_PRESETS, "room", "balance") == ("robust", "weak", "room", "balance")


# ---------------------------------------------------------------- SB3 arguments (issue 17, item 9)


@pytest.mark.parametrize("algo", ["ppo", "sac"])
def test_every_accepted_argument_is_one_of_sb3s(algo):
    import inspect

    from stable_baselines3 import PPO, SAC

    from pidlab.rl.recipe import ARGUMENTS, algorithm_arguments

    params = set(inspect.signature({"ppo": PPO, "sac": SAC}[algo]).parameters)
    assert set(ARGUMENTS[algo]) <= params
    assert algorithm_arguments(algo) == tuple(ARGUMENTS[algo])


EDGES = {
    "ppo": {"learning_rate": "lin_1e-9", "n_steps": 2, "batch_size": 2, "n_epochs": 1, "gamma": 1.0,
            "gae_lambda": 0.0, "clip_range": "lin_0.1", "clip_range_vf": 1e-6, "normalize_advantage": True,
            "ent_coef": 0.0, "vf_coef": 0.0, "max_grad_norm": 1e-9, "use_sde": True, "sde_sample_freq": -1,
            "target_kl": 1e-9, "stats_window_size": 1,
            "policy_kwargs": {"net_arch": {"pi": [1], "vf": []}, "activation_fn": "silu", "ortho_init": False,
                              "log_std_init": -20.0, "full_std": False, "use_expln": True,
                              "share_features_extractor": True, "normalize_images": False}},
    "sac": {"learning_rate": 1e-9, "buffer_size": 1, "learning_starts": 0, "batch_size": 1, "tau": 1.0,
            "gamma": 1e-9, "train_freq": [1, "episode"], "gradient_steps": -1, "n_steps": 3, "ent_coef": "auto_1e-3",
            "target_update_interval": 1, "target_entropy": -1e3, "use_sde": True, "sde_sample_freq": 0,
            "use_sde_at_warmup": True, "stats_window_size": 1,
            "policy_kwargs": {"net_arch": {"pi": [], "qf": [1, 1]}, "activation_fn": "gelu", "log_std_init": 20.0,
                              "use_expln": False, "clip_mean": 1e-3, "n_critics": 1,
                              "share_features_extractor": False, "normalize_images": True}},
}  # fmt: skip


@pytest.mark.parametrize("algo", ["ppo", "sac"])
def test_sb3_takes_every_value_the_recipe_accepts_at_its_edges(algo):
    """Values at the ends of each accepted range build the SB3 model: nothing fails after the run folder is made."""
    import gymnasium as gym

    from pidlab.rl.train import _algorithm_class, sb3_arguments

    data = base()
    data[algo] = EDGES[algo]
    data["algo"] = algo
    recipe = parse_recipe(data)
    env = gym.make("InvertedPendulum-v5")
    try:
        model = _algorithm_class(algo)("MlpPolicy", env, seed=0, **sb3_arguments(recipe))
        assert model is not None
    finally:
        env.close()


@pytest.mark.parametrize(
    ("algo", "key", "value", "message"),
    [
        ("ppo", "n_steps", "abc", "ppo.n_steps = 'abc': expected an integer in [1, 10000000]"),
        ("ppo", "n_steps", 1, "expected a PPO rollout (n_steps * n_envs) of at least 2 steps"),
        ("ppo", "n_steps", 2.0, "n_steps = 2.0: expected an integer"),
        ("ppo", "batch_size", -1, "ppo.batch_size = -1: expected an integer in [1, 10000000]"),
        ("ppo", "batch_size", 1, "ppo.batch_size = 1: expected an integer >= 2 (or normalize_advantage = false)"),
        ("ppo", "gamma", 5.0, "ppo.gamma = 5.0: expected a finite number in (0, 1]"),
        ("ppo", "gamma", 0.0, "ppo.gamma = 0.0: expected a finite number in (0, 1]"),
        ("ppo", "gamma", float("nan"), "ppo.gamma = nan"),
        ("ppo", "gae_lambda", 1.01, "gae_lambda = 1.01: expected a finite number in [0, 1]"),
        ("ppo", "learning_rate", -1.0, "learning_rate = -1.0: expected a finite number > 0"),
        ("ppo", "learning_rate", "lin_-1", "learning_rate = 'lin_-1': expected a number > 0, or 'lin_<number>'"),
        ("ppo", "learning_rate", True, "learning_rate = True"),
        ("ppo", "clip_range", 0, "clip_range = 0: expected a finite number > 0"),
        ("ppo", "ent_coef", -0.1, "ent_coef = -0.1: expected a finite number >= 0"),
        ("ppo", "max_grad_norm", 0.0, "max_grad_norm = 0.0: expected a finite number > 0"),
        ("ppo", "n_epochs", 0, "n_epochs = 0: expected an integer in [1, 10000]"),
        ("ppo", "normalize_advantage", 1, "normalize_advantage = 1: expected true or false"),
        ("ppo", "rollout_buffer_class", "x", "unknown PPO argument(s) ['rollout_buffer_class']"),
        ("ppo", "policy_kwargs", {"net_arch": [64, 0]}, "net_arch[1] = 0: expected an integer in [1, 10000]"),
        ("ppo", "policy_kwargs", {"net_arch": {"pi": [8], "qf": [8]}}, "policy_kwargs.net_arch = "),
        ("ppo", "policy_kwargs", {"net_arch": "big"}, "net_arch = 'big': expected a list of at most 100 layer"),
        ("ppo", "policy_kwargs", {"optimizer_class": "Adam"}, "unknown PPO policy argument(s) ['optimizer_class']"),
        ("ppo", "policy_kwargs", {"log_std_init": float("inf")}, "log_std_init = inf"),
        ("ppo", "policy_kwargs", [1], "policy_kwargs: expected a table of policy arguments, got [1]"),
        ("sac", "tau", 0.0, "sac.tau = 0.0: expected a finite number in (0, 1]"),
        ("sac", "buffer_size", 0, "sac.buffer_size = 0: expected an integer in [1, 100000000]"),
        ("sac", "learning_starts", -1, "sac.learning_starts = -1"),
        ("sac", "train_freq", 0, "sac.train_freq = 0: expected an integer in [1, 1000000000]"),
        ("sac", "train_freq", [4, "week"], "train_freq = [4, 'week']: expected an integer >= 1 or [n, \"step\""),
        ("sac", "gradient_steps", -2, "gradient_steps = -2: expected an integer in [-1, 1000000]"),
        ("sac", "ent_coef", "auto_0", "ent_coef = 'auto_0': expected a number >= 0, 'auto' or 'auto_<number > 0>'"),
        ("sac", "ent_coef", -1.0, "ent_coef = -1.0: expected a finite number >= 0"),
        ("sac", "target_entropy", "high", "target_entropy = 'high': expected 'auto' or a finite number"),
        ("sac", "optimize_memory_usage", True, "unknown SAC argument(s) ['optimize_memory_usage']"),
        ("sac", "policy_kwargs", {"net_arch": {"pi": [8]}}, "net_arch = {'pi': [8]}"),
        ("sac", "policy_kwargs", {"n_critics": 0}, "n_critics = 0: expected an integer in [1, 100]"),
    ],
)
def test_sb3_arguments_are_checked_for_type_and_range(algo, key, value, message):
    data = base()
    data[algo] = {**data[algo], key: value}
    with pytest.raises(RecipeError) as err:
        parse_recipe(data, "r.toml")
    assert message in str(err.value)


def test_an_n_envs_override_that_shrinks_the_rollout_is_refused():
    data = base()
    data["ppo"] = {**data["ppo"], "n_steps": 1}
    data["n_envs"] = 2
    r = parse_recipe(data)
    with pytest.raises(RecipeError) as err:
        with_overrides(r, n_envs=1)
    assert err.value.param == "n_envs" and str(err.value).startswith("n_envs=1: expected a PPO rollout")
    assert with_overrides(r, n_envs=3).n_envs == 3


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"env_id": "../../x"}, "env_id = '../../x': expected a name of 1-64 letters"),
        ({"env_id": "x" * 100_000}, "env_id = 'xxxxxxxx"),
        ({"seed": 2**32}, "seed = 4294967296: expected an integer in [0, 4294967295]"),
        ({"seed": True}, "seed = True"),
        ({"steps": 10**13}, "steps = 10000000000000: expected an integer in [1, 1000000000000]"),
        ({"n_envs": 0}, "n_envs = 0: expected an integer in [1, 1024]"),
        ({"threads": 10**6}, "threads = 1000000"),
        ({"description": ["x"]}, "description = ['x']: expected a string"),
        ({"win": {"target": float("inf")}}, "win.target = inf: expected a finite number"),
        ({"win": {"target": 1.0, "window": 0}}, "win.window = 0"),
        ({"evaluation": {"seed": 2**32 - 5}}, "evaluation.seed = 4294967291: expected an integer in [0, 4294967286]"),
        ({"evaluation": {"every": True}}, "evaluation.every = True"),
        ({"checkpoint": {"every": 0}}, "checkpoint.every = 0"),
        ({"coaching": {"probability": {"shape": "linear", "start": float("nan")}}}, "schedule start = nan"),
        ({"coaching": {"width": True}}, "coaching.width = True: expected a number >= 0 or a table"),
        ({"coaching": {"nudge_steps": 10**9}}, "nudge_steps = 1000000000"),
        ({"coaching": {"mode": "nudge", "trigger": {"variable": "v", "high": float("nan"), "steps": 2}}},
         "trigger.high = nan"),
        ({"coaching": {"mode": "nudge", "trigger": {"variable": "v", "low": 0.5, "high": 0.1, "steps": 2}}},
         "trigger.high = 0.1: expected a finite number >= 0.5"),
        ({"coaching": {"mode": "nudge", "trigger": {"variable": "v", "high": 0.3, "steps": 10**20}}},
         "trigger.steps = 100000000000000000000"),
        ({"pipeline": {"seeds": 10**12}}, "pipeline.seeds = 1000000000000: expected an integer in [1, 10000]"),
        ({"pipeline": {"episodes": -1}}, "pipeline.episodes = -1"),
    ],
)
def test_recipe_numbers_and_names_are_checked(change, message):
    data = base()
    for key, value in change.items():
        data[key] = {**data[key], **value} if isinstance(value, dict) and key in data else value
    with pytest.raises(RecipeError) as err:
        parse_recipe(data, "r.toml")
    assert message in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("value", [None, [], "recipe", 3, {1: 2}])
def test_parse_recipe_of_no_table_is_a_recipe_error(value):
    with pytest.raises(RecipeError, match="expected a table"):
        parse_recipe(value)


def test_default_recipe_path_refuses_names_that_leave_coach():
    from pidlab.rl.recipe import default_recipe_path

    for env in ("../../etc/passwd", "/abs", "", "a/b", "x" * 300):
        with pytest.raises(RecipeError) as err:
            default_recipe_path(env)
        assert err.value.param == "env_id"


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ({"shape": "linear", "start": True}, "schedule start = True: expected a finite number >= 0"),
        ({"shape": "linear", "begin": -0.1}, "schedule begin = -0.1: expected a finite number in [0, 1]"),
        ({"shape": "linear", "finish": float("inf")}, "schedule finish = inf"),
        ({"shape": 3}, "schedule shape 3: expected one of constant"),
        ({"shape": ["x"]}, "schedule shape ['x']"),
        (float("nan"), "w = nan: expected a finite number >= 0"),
        (-1, "w = -1: expected a finite number >= 0"),
        (None, "w = None: expected a number >= 0 or a table"),
        ({1: 2}, "w = {1: 2}: expected a number >= 0 or a table"),
    ],
)
def test_schedule_values_are_checked(value, message):
    with pytest.raises(ScheduleError) as err:
        parse_schedule(value, "w")
    assert message in str(err.value)


def _ip_data(**ppo) -> dict:
    data = tomllib.loads((ROOT / "coach" / "InvertedPendulum-v5.toml").read_text())
    data["n_envs"] = 1
    data["ppo"].update(ppo)
    data["sac"].pop("n_envs", None)
    return data


def test_an_algorithm_table_sets_its_own_number_of_envs():
    r = parse_recipe(_ip_data(n_envs=4, n_steps=8))
    assert (r.algo, r.n_envs, r.algorithm_envs) == ("ppo", 4, {"ppo": 4, "sac": 1})
    assert "n_envs" not in r.hyperparameters  # pidlab's key, never passed to SB3
    sac = with_overrides(r, algo="sac")  # SAC keeps its own one env (its train_freq counts vector steps)
    assert (sac.n_envs, sac.algorithm_envs) == (1, {"ppo": 4, "sac": 1})
    two = with_overrides(r, n_envs=2)
    assert (two.n_envs, two.algorithm_envs["ppo"]) == (2, 2)
    for recipe in (r, sac, two):  # what a run's config.toml holds reads back the same
        again = parse_recipe(recipe_to_dict(recipe))
        assert (again.algo, again.n_envs, again.algorithm_envs) == (recipe.algo, recipe.n_envs, recipe.algorithm_envs)


@pytest.mark.parametrize(("value", "message"), [(0, "recipe.ppo.n_envs"), ("4", "recipe.ppo.n_envs"), (2000, "1024")])
def test_a_bad_number_of_envs_in_a_table_names_it(value, message):
    with pytest.raises(RecipeError, match=message):
        parse_recipe(_ip_data(n_envs=value))


def test_the_ppo_rollout_is_checked_with_the_tables_envs():
    parse_recipe(_ip_data(n_envs=2, n_steps=1))  # a rollout of 2
    with pytest.raises(RecipeError, match="rollout"):
        parse_recipe(_ip_data(n_envs=1, n_steps=1))
