"""Property tests (Hypothesis): every parser either returns a valid object or raises PidlabError.

Two kinds of input: random TOML-like values (strings, booleans, integers of any size, floats with
NaN and infinities, lists, nested tables), and the shipped files (coach specs, recipes, the
conditions file, model cards) with one field replaced by such a value. Nothing may escape as
AttributeError, KeyError, IndexError, TypeError or a bare ValueError.

With the environment variable ``CI`` set, each property runs 50 examples (the ``ci`` profile);
otherwise 300 (``dev``). ``HYPOTHESIS_PROFILE`` picks a profile by name.
"""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from pidlab.checks import (
    NAME_MAX_BYTES,
    SEED_MAX,
    check_name,
    exists,
    is_file,
    is_name,
    parse_vector,
    path_under,
)
from pidlab.controller.spec import CoachSpec, dumps_spec, loads_spec, parse_spec
from pidlab.errors import PidlabError
from pidlab.experiment.conditions import Condition, parse_conditions, resolve
from pidlab.experiment.sweep import parse_seeds
from pidlab.plant.card import ModelCard, parse_card
from pidlab.rl.recipe import Recipe, parse_pipeline, parse_recipe, recipe_to_dict
from pidlab.rl.schedule import Schedule, parse_schedule
from tests.helpers import COACH, MODELS, TUNING

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

_COMMON = {"deadline": None, "suppress_health_check": [HealthCheck.too_slow, HealthCheck.data_too_large]}
settings.register_profile("ci", max_examples=50, **_COMMON)
settings.register_profile("dev", max_examples=300, **_COMMON)
PROFILE = os.environ.get("HYPOTHESIS_PROFILE") or ("ci" if os.environ.get("CI") else "dev")

# ------------------------------------------------------------------------------------------ inputs

HUGE = [2**31, 2**32 - 1, 2**32, 2**40, 2**63 - 1, 2**63, 2**64, 10**30, 10**400, -(2**63), -1, 0]
FIELDS = [
    "schema", "env_id", "name", "description", "loop", "kp", "ki", "kd", "tf", "tt", "setpoint", "actuators",
    "feeds", "signal", "rate_signal", "output_limits", "bounds", "box", "ellipsoid", "level", "rho", "center",
    "shape", "variables", "method", "steps", "seed", "n_envs", "threads", "ppo", "sac", "algo", "n_steps",
    "batch_size", "gamma", "learning_rate", "policy_kwargs", "net_arch", "coaching", "probability", "width",
    "start", "end", "begin", "finish", "trigger", "condition", "coach", "env", "win", "target", "evaluation",
    "pipeline", "seeds", "qpos", "operating_point", "observation", "termination", "low", "high",
]  # fmt: skip

scalars = st.one_of(
    st.text(max_size=12),
    st.sampled_from(["", "none", "inf", "-inf", "nan", "lin_0.1", "lin_nan", "auto", "../x", "a" * 300]),
    st.booleans(),
    st.integers(),
    st.sampled_from(HUGE),
    st.floats(allow_nan=True, allow_infinity=True),
)
toml_like = st.recursive(
    scalars,
    lambda children: (
        st.lists(children, max_size=4)
        | st.dictionaries(st.text(max_size=6) | st.sampled_from(FIELDS), children, max_size=4)
    ),
    max_leaves=12,
)
python_like = st.recursive(
    scalars | st.none() | st.just(object()),
    lambda children: (
        st.lists(children, max_size=3)
        | st.tuples(children, children)
        | st.dictionaries(st.text(max_size=6) | st.sampled_from(FIELDS) | st.integers(), children, max_size=3)
    ),
    max_leaves=8,
)


def _load(path: Path) -> dict[str, Any]:
    return tomllib.loads(path.read_text(encoding="utf-8"))


SPECS = {p.name: _load(p) for p in sorted(TUNING.glob("*.toml"))}
RECIPES = {p.name: _load(p) for p in sorted(COACH.glob("*-v*.toml"))}
CONDITIONS = _load(COACH / "conditions.toml")
CARDS = {p.name: _load(p) for p in sorted(MODELS.glob("*.toml"))}


def _paths(doc: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every place in a parsed document (tables and lists, to their leaves)."""
    out = [prefix] if prefix else []
    if isinstance(doc, dict):
        for k, v in doc.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            out += _paths(v, (*prefix, i))
    return out


def _replaced(doc: Any, path: tuple[Any, ...], value: Any) -> Any:
    """A copy of ``doc`` with the value at ``path`` replaced."""
    if not path:
        return value
    head, rest = path[0], path[1:]
    if isinstance(doc, dict):
        return {**doc, head: _replaced(doc[head], rest, value)}
    out = list(doc)
    out[head] = _replaced(doc[head], rest, value)
    return out


field_values = st.one_of(toml_like, st.integers(0, 10_000), st.floats(0.0, 1.0), st.booleans())
"""What a mutation writes: anything TOML-like, often a plausible number (so valid files come out too)."""


def mutated(doc: dict[str, Any], values: st.SearchStrategy[Any] = field_values) -> st.SearchStrategy[Any]:
    """``doc`` with one field (or one list entry, or one table) replaced by a generated value."""
    paths = _paths(doc)
    return st.tuples(st.sampled_from(paths), values).map(lambda pv: _replaced(doc, pv[0], pv[1]))


def _expect(parse: Any, *args: Any) -> Any:
    """``parse(*args)``, or None when it raised a PidlabError (anything else fails the test)."""
    try:
        return parse(*args)
    except PidlabError as exc:
        message = str(exc)
        assert message and "\n" not in message and len(message) < 2000, message
        return None


def given_with(*strategies: st.SearchStrategy[Any]) -> Any:
    """``@given`` with the module's settings profile."""

    def wrap(test: Any) -> Any:
        return settings(settings.get_profile(PROFILE))(given(*strategies)(test))

    return wrap


# ------------------------------------------------------------------------------------------ specs


def _check_spec(data: Any) -> None:
    spec = _expect(parse_spec, data, "spec")
    if spec is not None:
        assert isinstance(spec, CoachSpec)
        assert is_name(spec.name) and is_name(spec.env_id)
        for lp in spec.loops:
            assert all(math.isfinite(v) for v in (lp.kp, lp.ki, lp.kd, lp.setpoint, lp.tf, lp.tt))
            assert all(math.isfinite(w) for _, w in lp.actuators)
        again = loads_spec(dumps_spec(spec))  # a valid spec saves and loads again
        assert again.name == spec.name and len(again.loops) == len(spec.loops)


@given_with(python_like)
def test_spec_parser_on_random_values(data: Any) -> None:
    _check_spec(data)


@given_with(st.sampled_from(sorted(SPECS)).flatmap(lambda name: mutated(SPECS[name])))
def test_spec_parser_on_mutated_shipped_specs(data: Any) -> None:
    _check_spec(data)


# ------------------------------------------------------------------------------------------ recipes


def _check_recipe(data: Any) -> None:
    recipe = _expect(parse_recipe, data, "recipe")
    if recipe is not None:
        assert isinstance(recipe, Recipe)
        assert is_name(recipe.env_id) and 0 <= recipe.seed <= SEED_MAX
        assert recipe.evaluation.seeds[-1] <= SEED_MAX
        assert parse_recipe(recipe_to_dict(recipe)) == recipe  # what a run's config.toml holds
        assert parse_pipeline(data, "recipe").seeds >= 1


@given_with(python_like)
def test_recipe_parser_on_random_values(data: Any) -> None:
    _check_recipe(data)


@given_with(st.sampled_from(sorted(RECIPES)).flatmap(lambda name: mutated(RECIPES[name])))
def test_recipe_parser_on_mutated_shipped_recipes(data: Any) -> None:
    _check_recipe(data)


# ------------------------------------------------------------------------------------------ conditions

IP_RECIPE = parse_recipe(RECIPES["InvertedPendulum-v5.toml"])


def _check_conditions(data: Any, resolve_them: bool) -> None:
    conditions = _expect(parse_conditions, data, "conditions")
    if conditions is not None:
        for name, cond in conditions.items():
            assert isinstance(cond, Condition) and is_name(name)
            assert all(is_name(env) for env in cond.per_env)
            if resolve_them:
                _expect(resolve, cond, IP_RECIPE)


@given_with(python_like)
def test_conditions_parser_on_random_values(data: Any) -> None:
    _check_conditions(data, resolve_them=False)


@given_with(mutated(CONDITIONS))
def test_conditions_parser_on_mutated_shipped_conditions(data: Any) -> None:
    _check_conditions(data, resolve_them=True)


# ------------------------------------------------------------------------------------------ cards


def _check_card(data: Any) -> None:
    card = _expect(parse_card, data, "card.toml")
    if card is not None:
        assert isinstance(card, ModelCard)
        assert all(math.isfinite(v) for v in card.operating_point.qpos)


@given_with(st.sampled_from(sorted(CARDS)).flatmap(lambda name: mutated(CARDS[name])))
def test_card_parser_on_mutated_shipped_cards(data: Any) -> None:
    _check_card(data)


# ------------------------------------------------------------------------------------------ schedules


@given_with(
    python_like | st.dictionaries(st.sampled_from(["shape", "start", "end", "begin", "finish"]), toml_like)
)
def test_schedule_parser(data: Any) -> None:
    schedule = _expect(parse_schedule, data, "coaching.width")
    if schedule is not None:
        assert isinstance(schedule, Schedule)
        for progress in (0.0, 0.25, 0.5, 1.0):
            value = schedule(progress)
            assert math.isfinite(value) and value >= 0


# ------------------------------------------------------------------------------------------ seeds

seed_texts = st.one_of(
    st.text(max_size=20),
    st.integers(min_value=-5, max_value=10**15).map(str),
    st.tuples(st.integers(-3, 2**33), st.integers(-3, 2**33)).map(lambda ab: f"{ab[0]}-{ab[1]}"),
    st.lists(st.integers(-3, 2**33), max_size=6).map(lambda xs: ",".join(map(str, xs))),
)


@given_with(seed_texts)
def test_seed_parser(text: str) -> None:
    seeds = _expect(parse_seeds, text)
    if seeds is not None:
        assert 1 <= len(seeds) <= 10_000 and len(set(seeds)) == len(seeds)
        assert all(isinstance(s, int) and 0 <= s <= SEED_MAX for s in seeds)


def test_seed_parser_refuses_other_types() -> None:
    for value in (None, 3, ["1"], b"1"):
        with pytest.raises(PidlabError):
            parse_seeds(value)  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------------ vectors

vector_texts = st.one_of(
    st.text(max_size=30),
    st.lists(st.floats(allow_nan=True, allow_infinity=True) | st.integers(), max_size=6).map(
        lambda xs: ",".join(map(str, xs))
    ),
)


@given_with(vector_texts)
def test_vector_parser(text: str) -> None:
    values = _expect(parse_vector, text, "qpos")
    if values is not None:
        assert all(isinstance(v, float) and math.isfinite(v) for v in values)


# ------------------------------------------------------------------------------------------ names

name_like = st.one_of(
    st.text(max_size=80),
    st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,70}", fullmatch=True),
    st.sampled_from(["..", ".", "../x", "a/b", "/abs", "a\0b", "x" * 100_000, "ok-name_1.v2"]),
    python_like,
)


@given_with(name_like)
def test_name_rule(value: Any) -> None:
    name = _expect(check_name, value, "name")
    if name is not None:
        assert isinstance(name, str) and 1 <= len(name) <= 64
        assert "/" not in name and name not in (".", "..") and not name.startswith(".")
        path = path_under("runs", name, "seed-0")
        assert path.parts[:2] == ("runs", name) and len(name.encode()) <= NAME_MAX_BYTES


@given_with(name_like)
def test_path_under_stays_under_its_root(value: Any) -> None:
    assume(isinstance(value, str))
    assert exists(value) in (True, False) and is_file(value) in (True, False)  # never OSError
    path = _expect(path_under, "/srv/runs", value)
    if path is not None:
        assert os.path.abspath(path).startswith("/srv/runs/")


# ------------------------------------------------------------------------------------------ operating points


@pytest.fixture(scope="module")
def pendulum() -> Any:
    from pidlab.plant.model import load_model

    return load_model("InvertedPendulum-v5")


@pytest.mark.parametrize("field", ["qpos", "qvel", "ctrl"])
def test_operating_point_vectors(pendulum: Any, field: str) -> None:
    from pidlab.plant.operating_point import resolve_operating_point

    @given_with(
        python_like | st.lists(st.floats(allow_nan=True, allow_infinity=True) | st.integers(), max_size=3)
    )
    def check(value: Any) -> None:
        op = _expect(lambda v: resolve_operating_point(pendulum, **{field: v}), value)
        if op is not None:
            assert all(math.isfinite(x) for x in getattr(op, field))

    check()
