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
    return tomllib.loads((ROOT / "coach" / "InvertedPendulum-v5.toml").read_text())


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"schema": "pidlab.recipe/9"}, "expected 'pidlab.recipe/1'"),
        ({"stepz": 10}, "unknown field(s) ['stepz']"),
        ({"steps": -5}, "steps = -5: expected >= 1"),
        ({"steps": "many"}, "steps: expected an integer"),
        ({"algo": "td3"}, "algo = 'td3': expected one of ppo, sac"),
        ({"vec_env": "ray"}, "vec_env = 'ray': expected one of dummy, subproc"),
        ({"ppo": {"n_stepz": 3}}, "unknown PPO argument(s) ['n_stepz']"),
        ({"ppo": {"learning_rate": "fast"}}, "learning_rate = 'fast'"),
        ({"ppo": {"clip_range": "lin_x"}}, "clip_range = 'lin_x': expected a number or 'lin_<number>'"),
        ({"ppo": {"policy_kwargs": {"activation_fn": "sigmoid"}}}, "activation_fn = 'sigmoid'"),
        ({"coaching": {"mode": "always"}}, "coaching.mode = 'always': expected one of takeover, nudge"),
        ({"coaching": {"region": "ball"}}, "coaching.region = 'ball'"),
        ({"coaching": {"probability": {"shape": "linear", "start": 2.0}}}, "probability cannot exceed 1"),
        ({"coaching": {"width": 0.0}}, "must be positive"),
        ({"coaching": {"off_after": 1.5}}, "off_after = 1.5"),
        ({"coaching": {"trigger": {"variable": "hinge_vel", "high": 0.3, "steps": 2}}}, "needs mode = 'nudge'"),
        ({"coaching": {"mode": "nudge", "trigger": {"variable": "v", "high": 0.3, "steps": 0}}}, "steps = 0"),
        ({"win": {}}, "win.target: missing"),
        ({"evaluation": {"episodes": 0}}, "evaluation.episodes = 0"),
        ({"normalize": {"obs": "yes"}}, "normalize.obs: expected true or false"),
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
        ({"steps": 0}, "steps", "steps=0: expected a positive number of env steps"),
        ({"n_envs": 0}, "n_envs", "n_envs=0: expected 1 or more"),
        ({"seed": -1}, "seed", "seed=-1: expected a non-negative integer"),
    ],
)
def test_overrides_name_the_python_parameter(kwargs, param, message):
    r = load_recipe(ROOT / "coach" / "InvertedPendulum-v5.toml")
    with pytest.raises(RecipeError) as err:
        with_overrides(r, **kwargs)
    assert str(err.value) == message and err.value.param == param


def test_one_list_of_presets():
    assert PRESETS == tuple(TUNING_PRESETS) == ("robust", "weak")
