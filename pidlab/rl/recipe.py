"""Coaching recipes: how to train an agent on one env, with or without its coach.

A recipe lives in ``coach/`` (``coach/InvertedPendulum-v5.toml``) and holds what stays the same
whether the agent is coached or not (algorithm hyperparameters, budget, evaluation protocol,
win target) and how the coach intervenes when there is one. Coached and uncoached runs of one
recipe use identical agent settings; only ``--coach`` differs.

Schema ``pidlab.recipe/1``::

    schema = "pidlab.recipe/1"
    env_id = "InvertedPendulum-v5"
    description = "..."
    algo = "ppo"                 # default algorithm: ppo | sac
    steps = 100000               # budget in env steps (agent + coach steps)
    n_envs = 1                   # parallel envs
    vec_env = "dummy"            # dummy (one process) | subproc (one process per env)
    seed = 0
    threads = 1                  # torch threads per training process

    [normalize]                  # VecNormalize, as the zoo does (statistics saved with the model)
    obs = true
    reward = true

    [win]                        # the paper's win: return >= target
    target = 800.0
    consecutive = 5              # "5 consecutive wins"
    window = 20                  # moving-average window

    [evaluation]                 # the agent alone: coach off, deterministic policy
    every = 5000                 # env steps between evaluations (and one at step 0)
    episodes = 10
    seed = 1000000               # episode i is reset with seed + i, every time

    [checkpoint]
    every = 20000                # env steps between checkpoints

    [coaching]                   # used when --coach is a spec; ignored with --coach none
    mode = "takeover"            # takeover | nudge
    region = "box"               # box | ellipsoid (from the spec's [bounds])
    nudge_steps = 1
    max_coach_steps = 1000
    reward = "agent"             # agent | total
    off_after = 1.0              # optional: progress from which the coach never intervenes
    probability = { shape = "linear", start = 1.0, end = 0.0, begin = 0.0, finish = 0.5 }
    width = 1.0                  # a number (constant) or a schedule table
    # trigger = { variable = "hinge_vel", low = 0.0, high = 0.3, steps = 2 }   # nudge only

    [ppo]                        # keyword arguments of stable_baselines3.PPO
    source = "where the values come from"
    n_steps = 32
    learning_rate = 0.000222425  # or "lin_0.0003" (linear decay, the zoo's notation)
    policy_kwargs = { net_arch = { pi = [64, 64], vf = [64, 64] }, activation_fn = "tanh" }

    [sac]                        # keyword arguments of stable_baselines3.SAC
    ...

    [pipeline]                   # optional: what `pidlab run ENV` does (not part of a run's settings)
    seeds = 3                    # seeds per condition (coached and uncoached)
    steps = 30000                # env steps per run (default: the recipe's steps)
    preset = "robust"            # auto-tuning preset: robust | weak
    roa_samples = 1000           # simulated states certifying the region behind the bounds
    episodes = 10                # coach-alone episodes on the real env
"""

from __future__ import annotations

import inspect
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from pidlab.controller import autotune
from pidlab.data import coach_dir
from pidlab.errors import PidlabError, RecipeError, ScheduleError
from pidlab.files import read_toml
from pidlab.rl.coaching import MODES, REGIONS, REWARDS, GrowthTrigger
from pidlab.rl.schedule import Schedule, parse_schedule, schedule_to_dict

RECIPE_SCHEMA = "pidlab.recipe/1"
ALGOS = ("ppo", "sac")
VEC_ENVS = ("dummy", "subproc")
ACTIVATIONS = ("tanh", "relu", "elu", "leaky_relu", "gelu", "silu")
LINEAR_SCHEDULES = ("learning_rate", "clip_range")  # may be "lin_<x>": x * remaining progress (the zoo's)
# SB3 constructor arguments that pidlab sets itself
_RESERVED = {"self", "policy", "env", "seed", "device", "verbose", "tensorboard_log", "_init_setup_model"}


@dataclass(frozen=True)
class Win:
    """The paper's win: an episode whose return reaches ``target``.

    Attributes
    ----------
    target : float
    consecutive : int
        Wins in a row for the "5 consecutive wins" measure.
    window : int
        Episodes in the moving average for the "average" measure.
    """

    target: float
    consecutive: int = 5
    window: int = 20


@dataclass(frozen=True)
class Evaluation:
    """Agent-alone evaluation protocol: coach off, deterministic policy, fixed seeds.

    Attributes
    ----------
    every : int
        Env steps between evaluations (there is also one at step 0 and one at the end).
    episodes : int
    seed : int
        Episode ``i`` of every evaluation is reset with ``seed + i``.
    """

    every: int
    episodes: int = 10
    seed: int = 1_000_000

    @property
    def seeds(self) -> tuple[int, ...]:
        """The evaluation episodes' reset seeds."""
        return tuple(self.seed + i for i in range(self.episodes))


@dataclass(frozen=True)
class Coaching:
    """How the coach intervenes (see :class:`pidlab.rl.coaching.CoachingWrapper`)."""

    mode: str = "takeover"
    region: str = "box"
    nudge_steps: int = 1
    max_coach_steps: int = 1000
    reward: str = "agent"
    probability: Schedule = field(default_factory=lambda: Schedule("constant", 1.0, 1.0))
    width: Schedule = field(default_factory=lambda: Schedule("constant", 1.0, 1.0))
    off_after: float | None = None
    trigger: GrowthTrigger | None = None


@dataclass(frozen=True)
class Recipe:
    """A parsed, validated recipe.

    Attributes
    ----------
    env_id, description : str
    algo : {"ppo", "sac"}
    steps : int
        Budget, env steps (agent + coach).
    n_envs : int
    vec_env : {"dummy", "subproc"}
    seed, threads : int
    normalize_obs, normalize_reward : bool
    win : Win
    evaluation : Evaluation
    checkpoint_every : int
        Env steps between checkpoints.
    coaching : Coaching
    algorithms : dict
        ``{"ppo": {...}, "sac": {...}}``: SB3 keyword arguments per algorithm, as written.
    sources : dict
        Per algorithm, where its values come from.
    path : str or None
    """

    env_id: str
    description: str
    algo: str
    steps: int
    n_envs: int
    vec_env: str
    seed: int
    threads: int
    normalize_obs: bool
    normalize_reward: bool
    win: Win
    evaluation: Evaluation
    checkpoint_every: int
    coaching: Coaching
    algorithms: dict[str, dict[str, Any]]
    sources: dict[str, str]
    path: str | None = None

    @property
    def hyperparameters(self) -> dict[str, Any]:
        """SB3 keyword arguments of the chosen algorithm."""
        return dict(self.algorithms[self.algo])


def _int(data: dict[str, Any], key: str, where: str, default: int | None = None, minimum: int = 0) -> int:
    value = data.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int):
        raise RecipeError(f"{where}.{key}: expected an integer, got {value!r}")
    if value < minimum:
        raise RecipeError(f"{where}.{key} = {value}: expected >= {minimum}")
    return value


def _num(data: dict[str, Any], key: str, where: str, default: float | None = None) -> float:
    value = data.get(key, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise RecipeError(f"{where}.{key}: expected a finite number, got {value!r}")
    return float(value)


def _choice(data: dict[str, Any], key: str, where: str, allowed: tuple[str, ...], default: str) -> str:
    value = data.get(key, default)
    if value not in allowed:
        raise RecipeError(f"{where}.{key} = {value!r}: expected one of {', '.join(allowed)}")
    return str(value)


def _table(data: dict[str, Any], key: str, where: str, allowed: set[str]) -> dict[str, Any]:
    value = data.get(key, {})
    if not isinstance(value, dict):
        raise RecipeError(f"{where}.{key}: expected a table")
    unknown = set(value) - allowed
    if unknown:
        raise RecipeError(
            f"{where}.{key}: unknown field(s) {sorted(unknown)}; allowed: {', '.join(sorted(allowed))}"
        )
    return value


def algorithm_arguments(algo: str) -> tuple[str, ...]:
    """Keyword arguments of the SB3 class that a recipe may set."""
    from stable_baselines3 import PPO, SAC

    cls = {"ppo": PPO, "sac": SAC}[algo]
    return tuple(p for p in inspect.signature(cls).parameters if p not in _RESERVED)


def _check_algorithm(algo: str, table: dict[str, Any], where: str) -> tuple[dict[str, Any], str]:
    allowed = set(algorithm_arguments(algo))
    kwargs = {k: v for k, v in table.items() if k != "source"}
    unknown = set(kwargs) - allowed
    if unknown:
        raise RecipeError(
            f"{where}: unknown {algo.upper()} argument(s) {sorted(unknown)}; "
            f"allowed: {', '.join(sorted(allowed))}"
        )
    for key in LINEAR_SCHEDULES:
        value = kwargs.get(key)
        if isinstance(value, str) and not (value.startswith("lin_") and _is_number(value[4:])):
            raise RecipeError(f"{where}.{key} = {value!r}: expected a number or 'lin_<number>'")
    pk = kwargs.get("policy_kwargs", {})
    if not isinstance(pk, dict):
        raise RecipeError(f"{where}.policy_kwargs: expected a table")
    act = pk.get("activation_fn")
    if act is not None and act not in ACTIVATIONS:
        raise RecipeError(
            f"{where}.policy_kwargs.activation_fn = {act!r}: expected one of {', '.join(ACTIVATIONS)}"
        )
    source = table.get("source", "")
    if not isinstance(source, str):
        raise RecipeError(f"{where}.source: expected a string")
    return kwargs, source


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _coaching(data: dict[str, Any], where: str) -> Coaching:
    c = _table(
        data,
        "coaching",
        where,
        {"mode", "region", "nudge_steps", "max_coach_steps", "reward", "probability", "width", "off_after",
         "trigger"},
    )  # fmt: skip
    w = f"{where}.coaching"
    try:
        probability = parse_schedule(c.get("probability", 1.0), f"{w}.probability")
        width = parse_schedule(c.get("width", 1.0), f"{w}.width")
    except ScheduleError as exc:
        raise RecipeError(str(exc)) from None
    if probability.start > 1 or probability.end > 1:
        raise RecipeError(f"{w}.probability: a probability cannot exceed 1")
    if width.start <= 0 or width.end <= 0:
        raise RecipeError(f"{w}.width: the factor on the region's size must be positive")
    off_after = None
    if "off_after" in c:
        off_after = _num(c, "off_after", w)
        if not 0.0 <= off_after <= 1.0:
            raise RecipeError(f"{w}.off_after = {off_after}: expected a progress in [0, 1]")
    trigger = None
    if "trigger" in c:
        t = _table(c, "trigger", w, {"variable", "low", "high", "steps"})
        if not isinstance(t.get("variable"), str):
            raise RecipeError(f"{w}.trigger.variable: expected an observation variable name")
        try:
            trigger = GrowthTrigger(
                t["variable"], _num(t, "low", f"{w}.trigger", 0.0), _num(t, "high", f"{w}.trigger"),
                _int(t, "steps", f"{w}.trigger", minimum=1),
            )  # fmt: skip
        except PidlabError as exc:
            raise RecipeError(f"{w}.trigger: {exc}") from None
    mode = _choice(c, "mode", w, MODES, "takeover")
    if trigger is not None and mode != "nudge":
        raise RecipeError(
            f"{w}.trigger: a growth trigger needs mode = 'nudge' (takeover is triggered by the region)"
        )
    return Coaching(
        mode=mode,
        region=_choice(c, "region", w, REGIONS, "box"),
        nudge_steps=_int(c, "nudge_steps", w, 1, minimum=1),
        max_coach_steps=_int(c, "max_coach_steps", w, 1000, minimum=1),
        reward=_choice(c, "reward", w, REWARDS, "agent"),
        probability=probability,
        width=width,
        off_after=off_after,
        trigger=trigger,
    )


_TOP = {"schema", "env_id", "description", "algo", "steps", "n_envs", "vec_env", "seed", "threads",
        "normalize", "win", "evaluation", "checkpoint", "coaching", "pipeline", *ALGOS}  # fmt: skip
PRESETS = tuple(autotune.PRESETS)
"""Auto-tuning presets a ``[pipeline]`` table may name (those of :mod:`pidlab.controller.autotune`)."""


@dataclass(frozen=True)
class PipelineSettings:
    """What ``pidlab run ENV`` does on the recipe's env (the recipe's ``[pipeline]`` table).

    Attributes
    ----------
    seeds : int
        Seeds per condition; the pipeline trains the recipe's agent with and without the coach.
    steps : int
        Budget of each run, env steps (agent + coach).
    preset : {"robust", "weak"}
        Auto-tuning preset.
    roa_samples : int
        Simulated initial states in the final certification of the region of attraction.
    episodes : int
        Coach-alone episodes on the real env.
    """

    seeds: int
    steps: int
    preset: str
    roa_samples: int
    episodes: int


_PIPELINE = {"seeds", "steps", "preset", "roa_samples", "episodes"}


def parse_pipeline(data: dict[str, Any], where: str = "recipe") -> PipelineSettings:
    """The ``[pipeline]`` table of parsed recipe TOML, with defaults for what it leaves out.

    Raises
    ------
    RecipeError
        Naming the field and what is allowed.
    """
    table = _table(data, "pipeline", where, _PIPELINE)
    w = f"{where}.pipeline"
    return PipelineSettings(
        seeds=_int(table, "seeds", w, 3, minimum=1),
        steps=_int(table, "steps", w, _int(data, "steps", where, 100_000, minimum=1), minimum=1),
        preset=_choice(table, "preset", w, PRESETS, "robust"),
        roa_samples=_int(table, "roa_samples", w, 1000, minimum=1),
        episodes=_int(table, "episodes", w, 10, minimum=0),
    )


def load_pipeline_settings(path: str | Path) -> PipelineSettings:
    """Read and validate the ``[pipeline]`` table of a recipe file (and the rest of the recipe).

    Raises
    ------
    RecipeError
    """
    data = read_toml(path, "recipe", RecipeError)
    parse_recipe(data, str(path))
    return parse_pipeline(data, str(path))


def parse_recipe(data: dict[str, Any], where: str = "recipe") -> Recipe:
    """Build a :class:`Recipe` from parsed TOML.

    Raises
    ------
    RecipeError
        Naming the field and what is allowed.
    """
    if data.get("schema") != RECIPE_SCHEMA:
        raise RecipeError(f"{where}: schema = {data.get('schema')!r}, expected {RECIPE_SCHEMA!r}")
    unknown = set(data) - _TOP
    if unknown:
        raise RecipeError(f"{where}: unknown field(s) {sorted(unknown)}; allowed: {', '.join(sorted(_TOP))}")
    env_id = data.get("env_id")
    if not isinstance(env_id, str) or not env_id:
        raise RecipeError(f"{where}.env_id: expected a Gymnasium env id, e.g. InvertedPendulum-v5")
    algorithms: dict[str, dict[str, Any]] = {}
    sources: dict[str, str] = {}
    for algo in ALGOS:
        if algo in data:
            if not isinstance(data[algo], dict):
                raise RecipeError(f"{where}.{algo}: expected a table of {algo.upper()} arguments")
            algorithms[algo], sources[algo] = _check_algorithm(algo, data[algo], f"{where}.{algo}")
    if not algorithms:
        raise RecipeError(f"{where}: no algorithm table; add [ppo] and/or [sac]")
    algo = _choice(data, "algo", where, ALGOS, next(iter(algorithms)))
    if algo not in algorithms:
        raise RecipeError(f"{where}.algo = {algo!r}, but the recipe has no [{algo}] table")
    norm = _table(data, "normalize", where, {"obs", "reward"})
    for key in ("obs", "reward"):
        if not isinstance(norm.get(key, False), bool):
            raise RecipeError(f"{where}.normalize.{key}: expected true or false")
    win = _table(data, "win", where, {"target", "consecutive", "window"})
    if "target" not in win:
        raise RecipeError(f"{where}.win.target: missing; the return that counts as a win, e.g. 800")
    ev = _table(data, "evaluation", where, {"every", "episodes", "seed"})
    steps = _int(data, "steps", where, minimum=1)
    ck = _table(data, "checkpoint", where, {"every"})
    parse_pipeline(data, where)  # checked here so a bad [pipeline] fails wherever the recipe loads
    return Recipe(
        env_id=env_id,
        description=str(data.get("description", "")),
        algo=algo,
        steps=steps,
        n_envs=_int(data, "n_envs", where, 1, minimum=1),
        vec_env=_choice(data, "vec_env", where, VEC_ENVS, "dummy"),
        seed=_int(data, "seed", where, 0),
        threads=_int(data, "threads", where, 1, minimum=1),
        normalize_obs=bool(norm.get("obs", False)),
        normalize_reward=bool(norm.get("reward", False)),
        win=Win(
            target=_num(win, "target", f"{where}.win"),
            consecutive=_int(win, "consecutive", f"{where}.win", 5, minimum=1),
            window=_int(win, "window", f"{where}.win", 20, minimum=1),
        ),
        evaluation=Evaluation(
            every=_int(ev, "every", f"{where}.evaluation", max(steps // 20, 1), minimum=1),
            episodes=_int(ev, "episodes", f"{where}.evaluation", 10, minimum=1),
            seed=_int(ev, "seed", f"{where}.evaluation", 1_000_000),
        ),
        checkpoint_every=_int(ck, "every", f"{where}.checkpoint", max(steps // 10, 1), minimum=1),
        coaching=_coaching(data, where),
        algorithms=algorithms,
        sources=sources,
        path=None,
    )


def load_recipe(path: str | Path) -> Recipe:
    """Read and validate a recipe file.

    Raises
    ------
    RecipeError
    """
    data = read_toml(path, "recipe", RecipeError)
    return replace(parse_recipe(data, str(path)), path=str(path))


def recipes_dir() -> Path:
    """The folder of recipes (:func:`pidlab.data.coach_dir`)."""
    return coach_dir()


def default_recipe_path(env_id: str) -> Path:
    """``coach/<env_id>.toml``."""
    return recipes_dir() / f"{env_id}.toml"


def recipe_envs() -> list[str]:
    """The env ids that have a recipe in :func:`recipes_dir`, sorted."""
    return sorted(p.stem for p in recipes_dir().glob("*-v*.toml"))


def with_overrides(
    recipe: Recipe,
    algo: str | None = None,
    steps: int | None = None,
    seed: int | None = None,
    n_envs: int | None = None,
) -> Recipe:
    """The recipe with command-line overrides applied (``None``: keep the recipe's value).

    Raises
    ------
    RecipeError
        An algorithm the recipe has no table for, or a non-positive number.
    """
    if algo is not None:
        if algo not in ALGOS:
            raise RecipeError(f"algo={algo!r}: expected one of {', '.join(ALGOS)}", param="algo")
        if algo not in recipe.algorithms:
            raise RecipeError(
                f"algo={algo!r}: the recipe {recipe.path or ''} has no [{algo}] table", param="algo"
            )
    if steps is not None and steps < 1:
        raise RecipeError(f"steps={steps!r}: expected a positive number of env steps", param="steps")
    if n_envs is not None and n_envs < 1:
        raise RecipeError(f"n_envs={n_envs!r}: expected 1 or more", param="n_envs")
    if seed is not None and seed < 0:
        raise RecipeError(f"seed={seed!r}: expected a non-negative integer", param="seed")
    return replace(
        recipe,
        algo=algo or recipe.algo,
        steps=steps or recipe.steps,
        seed=recipe.seed if seed is None else seed,
        n_envs=n_envs or recipe.n_envs,
    )


def recipe_to_dict(recipe: Recipe) -> dict[str, Any]:
    """The TOML tables of ``recipe`` (what :func:`parse_recipe` reads back)."""
    c = recipe.coaching
    coaching: dict[str, Any] = {
        "mode": c.mode,
        "region": c.region,
        "nudge_steps": c.nudge_steps,
        "max_coach_steps": c.max_coach_steps,
        "reward": c.reward,
        "probability": schedule_to_dict(c.probability),
        "width": schedule_to_dict(c.width),
    }
    if c.off_after is not None:
        coaching["off_after"] = c.off_after
    if c.trigger is not None:
        t = c.trigger
        coaching["trigger"] = {"variable": t.variable, "low": t.low, "high": t.high, "steps": t.steps}
    out: dict[str, Any] = {
        "schema": RECIPE_SCHEMA,
        "env_id": recipe.env_id,
        "description": recipe.description,
        "algo": recipe.algo,
        "steps": recipe.steps,
        "n_envs": recipe.n_envs,
        "vec_env": recipe.vec_env,
        "seed": recipe.seed,
        "threads": recipe.threads,
        "normalize": {"obs": recipe.normalize_obs, "reward": recipe.normalize_reward},
        "win": {
            "target": recipe.win.target,
            "consecutive": recipe.win.consecutive,
            "window": recipe.win.window,
        },
        "evaluation": {
            "every": recipe.evaluation.every,
            "episodes": recipe.evaluation.episodes,
            "seed": recipe.evaluation.seed,
        },
        "checkpoint": {"every": recipe.checkpoint_every},
        "coaching": coaching,
    }
    for algo, kwargs in recipe.algorithms.items():
        out[algo] = {"source": recipe.sources.get(algo, ""), **kwargs}
    return out
