"""Experimental conditions: which coach, which rule, named in a TOML file.

A condition says how an agent is coached (or not) in an experiment: the coach spec (a name in
``tuning/``, a spec file, or ``none``), changes to the recipe's ``[coaching]`` table (mode,
trigger, schedules, ...), optionally the critical-state bounds to use instead of the spec's, and
optionally the agent's algorithm (``algo``: a plain SAC learner beside PPO in one sweep).
Any of these can differ per environment (``[condition.NAME.env."ENV"]``). The file
``coach/conditions.toml`` holds pidlab's conditions; users add their own in the same form::

    schema = "pidlab.conditions/1"

    [condition.pidlab-fading]
    description = "pidlab's coach, taking over less and less often"
    coach = "pidlab-robust"
    coaching = { mode = "takeover", probability = { shape = "linear", start = 1.0, end = 0.0 } }

    [condition.paper.env."InvertedPendulum-v5"]
    coaching = { mode = "nudge", trigger = { variable = "hinge_vel", low = 0.0, high = 0.3, steps = 2 } }
    bounds = { hinge_vel = [-0.4, 0.4] }     # a box, replacing the spec's [bounds]

:func:`resolve` turns a condition and a recipe into what the trainer takes: a recipe whose
coaching table is the condition's, and the coach spec (with the condition's bounds).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from os import PathLike
from pathlib import Path
from typing import Any

from pidlab.checks import (
    as_table,
    boolean,
    check_name,
    clip,
    exists,
    fail,
    integer,
    number,
    path_argument,
    path_under,
    shown,
    strings,
    text,
)
from pidlab.controller.spec import CoachSpec, load_spec, parse_spec, spec_to_dict
from pidlab.data import find_data_file, tuning_dir
from pidlab.errors import ConditionError, ExperimentError, RecipeError, SpecError
from pidlab.files import read_toml
from pidlab.rl.recipe import ALGOS, Recipe, check_coaching, parse_recipe, recipe_to_dict, with_overrides

CONDITIONS_SCHEMA = "pidlab.conditions/1"


@dataclass(frozen=True)
class EnvCondition:
    """A condition as it applies to one environment.

    Attributes
    ----------
    coach : str
        ``none``, a spec name in ``tuning/`` or a spec file.
    coaching : dict
        Fields replacing the recipe's ``[coaching]`` fields.
    bounds : dict or None
        ``variable = [low, high]`` box replacing the spec's ``[bounds]``.
    algo : str or None
        The agent's algorithm (``ppo`` or ``sac``) replacing the recipe's and ``--algo``; None:
        the recipe's.
    """

    coach: str
    coaching: dict[str, Any]
    bounds: dict[str, list[float]] | None
    algo: str | None = None


@dataclass(frozen=True)
class Condition:
    """A named condition: a default for every env and per-env changes."""

    name: str
    description: str
    default: EnvCondition
    per_env: dict[str, EnvCondition]

    def for_env(self, env_id: str) -> EnvCondition:
        """The condition as it applies to ``env_id``."""
        return self.per_env.get(env_id, self.default)


def conditions_path() -> Path:
    """The conditions file: ``$PIDLAB_COACH/conditions.toml`` if it exists, else the shipped one."""
    return find_data_file("coach", "conditions.toml")


_FIELDS = {"description", "coach", "coaching", "bounds", "algo", "env"}


def _box(bounds: Any, where: str) -> dict[str, list[float]]:
    """A bounds box: ``variable = [low, high]``, finite numbers (not booleans), ``low < high``."""
    if not as_table(bounds, where, ConditionError, "a table of variable = [low, high]"):
        raise ConditionError(f"{where}: expected a table of variable = [low, high]")
    box = {}
    for name, lim in bounds.items():
        w = f"{where}.{name}"
        if not isinstance(lim, list) or len(lim) != 2:
            raise ConditionError(f"{w} = {shown(lim)}: expected [low, high] with low < high")
        lo, hi = (number(v, w, ConditionError) for v in lim)
        if not lo < hi:
            raise ConditionError(f"{w} = {shown(lim)}: expected [low, high] with low < high")
        box[name] = [lo, hi]
    return box


def _coach(value: Any, where: str) -> str:
    """``none``, a spec file (``*.toml``) or a spec name in ``tuning/`` (:data:`pidlab.checks.NAME_RULE`)."""
    expected = "none, a spec file (*.toml) or a spec name in tuning/"
    if not isinstance(value, str) or not value:
        raise ConditionError(f"{where} = {shown(value)}: expected {expected}")
    if value != "none" and Path(value).suffix != ".toml":
        check_name(value, where, ConditionError)
    return value


def _env_condition(table: dict[str, Any], base: EnvCondition | None, where: str) -> EnvCondition:
    unknown = set(table) - (_FIELDS - {"description", "env"} if base else _FIELDS)
    if unknown:
        allowed = ", ".join(sorted(_FIELDS - {"description", "env"} if base else _FIELDS))
        raise ConditionError(f"{where}: unknown field(s) {sorted(unknown)}; allowed: {allowed}")
    coach = _coach(table.get("coach", base.coach if base else None), f"{where}.coach")
    coaching = as_table(table.get("coaching", {}), f"{where}.coaching", ConditionError,
                        "a table of [coaching] fields of a recipe")  # fmt: skip
    merged = {**(base.coaching if base else {}), **coaching}
    try:
        check_coaching(merged, where)
    except RecipeError as exc:
        raise ConditionError(str(exc)) from None
    bounds = table.get("bounds")
    box = _box(bounds, f"{where}.bounds") if bounds is not None else base.bounds if base else None
    algo = table.get("algo", base.algo if base else None)
    if algo is not None and algo not in ALGOS:
        raise ConditionError(f"{where}.algo = {shown(algo)}: expected one of {', '.join(ALGOS)}")
    return EnvCondition(coach=coach, coaching=merged, bounds=box, algo=algo)


def parse_conditions(data: dict[str, Any], where: str = "conditions") -> dict[str, Condition]:
    """Build the conditions of a parsed conditions file.

    Condition names and env ids follow :data:`pidlab.checks.NAME_RULE` (a run folder is named
    after them); every number is checked as the recipe checks it.

    Raises
    ------
    ConditionError
        Naming the field and what is expected.
    """
    data = as_table(data, where, ConditionError, "a table (parsed TOML)")
    if data.get("schema") != CONDITIONS_SCHEMA:
        raise ConditionError(f"{where}: schema = {shown(data.get('schema'))}, expected {CONDITIONS_SCHEMA!r}")
    unknown = set(data) - {"schema", "condition"}
    if unknown:
        raise ConditionError(f"{where}: unknown field(s) {sorted(unknown)}; allowed: schema, condition")
    tables = data.get("condition")
    if not isinstance(tables, dict) or not tables:
        raise ConditionError(f"{where}: no conditions; add [condition.NAME] tables")
    out: dict[str, Condition] = {}
    for name, table in tables.items():
        check_name(name, f"{where}: condition name", ConditionError)
        w = f"{where}: condition.{name}"
        as_table(table, w, ConditionError)
        default = _env_condition(table, None, w)
        envs = as_table(table.get("env", {}), f"{w}.env", ConditionError, "tables named after env ids")
        per_env = {}
        for env_id, t in envs.items():
            check_name(env_id, f"{w}.env: env id", ConditionError)
            as_table(t, f"{w}.env.{env_id}", ConditionError)
            per_env[env_id] = _env_condition(t, default, f"{w}.env.{env_id}")
        description = text(table.get("description", ""), f"{w}.description", ConditionError)
        out[name] = Condition(name, description, default, per_env)
    return out


def load_conditions(path: str | Path | None = None) -> dict[str, Condition]:
    """Read a conditions file (default :func:`conditions_path`).

    Raises
    ------
    ConditionError
    """
    path = Path(path) if path is not None else conditions_path()
    return parse_conditions(read_toml(path, "conditions file", ConditionError), str(path))


def select(conditions: dict[str, Condition], condition_names: list[str], source: str) -> list[Condition]:
    """The conditions called ``condition_names``, in that order.

    Raises
    ------
    ConditionError
        A name that is not in the file, or none at all.
    """
    names = condition_names
    given = shown(",".join(names), 80)  # as the command line takes them
    if not names:
        raise ConditionError(
            f"condition_names={given}: empty; name at least one condition", param="condition_names"
        )
    missing = [n if len(n) <= 40 else n[:37] + "..." for n in map(str, names) if n not in conditions]
    if missing:
        raise ConditionError(
            f"condition_names={given}: unknown condition(s) {', '.join(missing[:10])}; "
            f"{source} has: {_names(list(conditions))}",
            param="condition_names",
        )
    if len(set(names)) != len(names):
        raise ConditionError(f"condition_names={given}: a condition is named twice", param="condition_names")
    return [conditions[n] for n in names]


def _names(names: list[str], width: int = 160) -> str:
    """``names`` joined, cut to about ``width`` characters with how many there are in all."""
    text = ", ".join(names)
    if len(text) <= width:
        return text
    shown_names: list[str] = []
    for name in names:
        if len(", ".join([*shown_names, name])) > width:
            break
        shown_names.append(name)
    return f"{', '.join(shown_names)}, ... ({len(names)} in all)"


def spec_path(env_id: str, coach: str) -> Path:
    """Where the spec called ``coach`` for ``env_id`` lives (a file, or ``ENV.COACH.toml`` in tuning/).

    Raises
    ------
    ConditionError
        ``coach`` is no ``*.toml`` file and not a name of :data:`pidlab.checks.NAME_RULE` (or
        ``env_id`` is not): the path would leave ``tuning/``.
    """
    path = Path(coach)
    if path.suffix == ".toml":
        return path
    check_name(env_id, "env_id", ConditionError, param="env_id")
    check_name(coach, "coach", ConditionError, param="coach")
    path_under(tuning_dir(), f"{env_id}.{coach}.toml", error=ConditionError, param="coach")  # stays inside
    return find_data_file("tuning", f"{env_id}.{coach}.toml")  # the user's spec, else the shipped one


def with_coaching(recipe: Recipe, fields: dict[str, Any], where: str) -> Recipe:
    """``recipe`` with ``fields`` replacing its ``[coaching]`` fields, as a condition applies them.

    Raises
    ------
    ConditionError
        Coaching fields a recipe rejects (the message starts with ``where``).
    """
    table = recipe_to_dict(recipe)
    coaching = {**table["coaching"], **fields}
    if (
        coaching.get("mode") != "nudge"
        and isinstance(coaching.get("trigger"), dict)
        and "trigger" not in fields
    ):
        coaching.pop("trigger", None)  # the recipe's growth trigger (nudge only) does not apply
    table["coaching"] = coaching
    try:
        return replace(parse_recipe(table, where), path=recipe.path)
    except RecipeError as exc:
        raise ConditionError(str(exc)) from None


def resolve(condition: Condition, recipe: Recipe) -> tuple[Recipe, CoachSpec | None, str | None]:
    """The recipe, coach spec and spec source that ``condition`` gives on ``recipe``'s env.

    Raises
    ------
    ConditionError
        A spec that does not exist or is for another env, coaching fields a recipe rejects,
        bounds on variables the env does not observe, an algorithm the recipe has no table for.
    """
    env_id = recipe.env_id
    c = condition.for_env(env_id)
    where = f"condition {condition.name} on {env_id}"
    if c.algo is not None:
        try:
            recipe = with_overrides(recipe, algo=c.algo)
        except RecipeError as exc:
            raise ConditionError(f"{where}: {exc}") from None
    resolved = with_coaching(recipe, c.coaching, where)
    if c.coach == "none":
        _check_couplings(resolved, None, where)
        return resolved, None, None
    path = spec_path(env_id, c.coach)
    if not exists(path):
        raise ConditionError(
            f"{where}: coach {shown(c.coach)} not found ({clip(str(path))}); "
            "expected none, a spec file or a spec name in tuning/"
        )
    spec = load_spec(path)
    if spec.env_id != env_id:
        raise ConditionError(f"{where}: the spec {path} is for {spec.env_id}")
    if c.bounds is not None:
        data = spec_to_dict(spec)
        data["bounds"] = {
            "method": f"given by the condition {condition.name!r} (not derived)",
            "box": {k: [float(v) for v in lim] for k, lim in c.bounds.items()},
        }
        try:
            spec = parse_spec(data, where)
        except SpecError as exc:
            raise ConditionError(str(exc)) from None
    _check_couplings(resolved, spec, where)
    return resolved, spec, str(path)


def _check_couplings(recipe: Recipe, spec: CoachSpec | None, where: str) -> None:
    from pidlab.errors import CoachingError
    from pidlab.rl.couplings import check_couplings

    try:
        check_couplings(recipe, spec)
    except CoachingError as exc:
        raise ConditionError(f"{where}: {exc}") from None


def check_plan_arguments(
    envs: Any,
    condition_names: Any,
    seeds: Any,
    out: Any,
    conditions_file: Any = None,
    recipe_files: Any = (),
    algo: Any = None,
    steps: Any = None,
) -> None:
    """The types of what :func:`pidlab.experiment.sweep.plan` was given, checked before anything else.

    ``plan`` checks the values (names, ranges, files); this refuses what is no value of the right
    kind, naming the parameter: one string where a list is expected (``envs="Hopper-v5"`` for
    ``["Hopper-v5"]``), a seed text (``"10"``: :func:`~pidlab.experiment.sweep.parse_seeds`
    reads it), a missing or empty folder.

    Raises
    ------
    ExperimentError
        Naming the parameter (its ``param``).
    """
    strings(envs, "envs", ExperimentError, what="env ids")
    strings(condition_names, "condition_names", ExperimentError, what="condition names")
    if isinstance(seeds, str) or not isinstance(seeds, (list, tuple, range)):
        fail(seeds, "seeds", "a list of seeds, e.g. [0, 1, 2] (parse_seeds reads a text such as '10')",
             ExperimentError, "seeds")  # fmt: skip
    path_argument(out, "out", ExperimentError, what="the experiment's folder")
    if conditions_file is not None:
        path_argument(conditions_file, "conditions_file", ExperimentError, what="a conditions file")
    strings(recipe_files, "recipe_files", ExperimentError, what="recipe files")
    if algo is not None and not isinstance(algo, str):
        fail(algo, "algo", "ppo, sac or None (each recipe's own)", ExperimentError, "algo")
    if steps is not None:
        from pidlab.rl.recipe import MAX_STEPS

        integer(steps, "steps", ExperimentError, low=1, high=MAX_STEPS, param="steps")


def check_sweep_arguments(
    p: Any, backend: Any = "process", workers: Any = None, address: Any = None, argv: Any = (),
    progress_bar: Any = True, reuse: Any = (),
) -> None:  # fmt: skip
    """The types of what :func:`pidlab.experiment.sweep.run_sweep` (and ``check_sweep``) was given.

    Raises
    ------
    ExperimentError
        ``p`` is no :class:`~pidlab.experiment.sweep.Plan` (make one with ``plan``), ``backend`` or
        ``address`` no string, ``workers`` no integer >= 1, ``argv`` no list of strings,
        ``progress_bar`` no bool or ``reuse`` no list of folders; naming the parameter.
    """
    from pidlab.experiment.sweep import Plan

    if not isinstance(p, Plan):
        expected = "a Plan (make one with pidlab.plan(envs, condition_names, seeds, out))"
        fail(p, "p", expected, ExperimentError, "p")
    if not isinstance(backend, str):
        fail(backend, "backend", "process or ray", ExperimentError, "backend")
    if workers is not None:
        integer(workers, "workers", ExperimentError, low=1, param="workers")
    if address is not None and not isinstance(address, str):
        fail(address, "address", "a Ray cluster address (a str) or None", ExperimentError, "address")
    strings(argv, "argv", ExperimentError, what="command-line words")
    boolean(progress_bar, "progress_bar", ExperimentError)
    if isinstance(reuse, (str, bytes, PathLike)) or not isinstance(reuse, (list, tuple)) or not all(
        isinstance(f, (str, PathLike)) for f in reuse
    ):
        fail(reuse, "reuse", "a list of earlier experiments' folders", ExperimentError, "reuse")
