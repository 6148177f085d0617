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
    n_envs = 1                   # parallel envs (default for every algorithm)
    vec_env = "dummy"            # dummy (one process) | subproc (one process per env)
    seed = 0
    threads = 1                  # torch and BLAS threads per training process

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
    region = "box"               # box | ellipsoid | rescue (from the spec's [bounds]); default
                                 # rescue with trigger = "predictive", else box
    trigger = "exit"             # exit (leaving the region after the agent's step) | predictive
                                 # (the agent's action is vetoed when its predicted state leaves
                                 # the rescue region; takeover only) | a growth-trigger table:
    # trigger = { variable = "hinge_vel", low = 0.0, high = 0.3, steps = 2 }   # nudge only
    predictor = "exact"          # the predictive trigger's look-ahead: exact (a copy of the MuJoCo
                                 # data) | model (the linear model; the box of the spec's measured
                                 # error, [bounds.forecast] from `pidlab forecast`, must lie in the region)
    handback = 1.0               # the coach hands back inside region.inner(handback), in (0, 1]
    view = "hidden"              # what the agent sees of a takeover: hidden | penalty | terminal
    cost = 10.0                  # penalty view: a takeover's cost (>= 0; default 10 alive rewards)
    nudge_steps = 1
    max_coach_steps = 1000
    reward = "agent"             # agent | total (not with view = "terminal")
    off_after = 1.0              # optional: progress from which the coach never intervenes
    probability = { shape = "linear", start = 1.0, end = 0.0, begin = 0.0, finish = 0.5 }
    width = 1.0                  # a number (constant) or a schedule table (not with region rescue)
    coach_buffer = { share = 0.5 }   # optional, SAC: the coach's transitions in a replay buffer of
                                     # their own, this share of every batch
    value_trigger = { margin = 1.0 } # optional, SAC: take over where the critic values the coach's
                                     # action more (in alive rewards); needs trigger = "predictive"
    proposer = { until = 0.5 }       # optional, SAC: the coach proposes, the critic picks, until then

    [ppo]                        # keyword arguments of stable_baselines3.PPO
    source = "where the values come from"
    n_envs = 4                   # optional: this algorithm's parallel envs (overrides the top level)
    n_steps = 8                  # per env: the rollout is n_steps * n_envs
    learning_rate = 0.000222425  # or "lin_0.0003" (linear decay, the zoo's notation)
    policy_kwargs = { net_arch = { pi = [64, 64], vf = [64, 64] }, activation_fn = "tanh" }

    [sac]                        # keyword arguments of stable_baselines3.SAC
    normalize = { obs = false, reward = false }   # optional: this algorithm's [normalize]
    ...

    [pipeline]                   # optional: what `pidlab run ENV` does (not part of a run's settings)
    seeds = 3                    # seeds per condition (coached and uncoached)
    steps = 30000                # env steps per run (default: the recipe's steps)
    preset = "robust"            # auto-tuning preset: robust | weak
    roa_samples = 1000           # simulated states certifying the region behind the bounds
    episodes = 10                # coach-alone episodes on the real env
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from pidlab.checks import (
    MAX_SAMPLES,
    MAX_SEEDS,
    SEED_MAX,
    as_table,
    check_name,
    fail,
    flag,
    float_text,
    integer,
    number,
    path_under,
    shown,
    text,
)
from pidlab.checks import seed as check_seed
from pidlab.controller.rollout import MAX_EPISODES
from pidlab.data import coach_dir, data_files, find_data_file
from pidlab.errors import PidlabError, RecipeError, ScheduleError
from pidlab.files import read_toml
from pidlab.rl.coaching import MODES, PREDICTORS, REGIONS, REWARDS, TRIGGERS, VIEWS, GrowthTrigger
from pidlab.rl.schedule import Schedule, parse_schedule, schedule_to_dict

RECIPE_SCHEMA = "pidlab.recipe/1"
ALGOS = ("ppo", "sac")
VEC_ENVS = ("dummy", "subproc")
ACTIVATIONS = ("tanh", "relu", "elu", "leaky_relu", "gelu", "silu")
LINEAR_SCHEDULES = ("learning_rate", "clip_range", "clip_range_vf")
"""SB3 arguments that may be ``"lin_<x>"``: ``x`` times the remaining progress (the zoo's notation)."""


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
class DemonstrationSettings:
    """Coach demonstrations at the start of a run (:mod:`pidlab.rl.demonstrations`).

    Attributes
    ----------
    steps : int
        Env steps the coach acts alone before the agent's first action (charged to the budget).
    noise : float
        Standard deviation of the Gaussian noise added to each coach action (DART), as a fraction
        of half the actuator's range; the noisy action is the one executed and recorded.
    """

    steps: int
    noise: float = 0.1


@dataclass(frozen=True)
class WarmStart:
    """Behaviour cloning of the agent on the demonstrations before RL (:mod:`pidlab.rl.cloning`).

    Attributes
    ----------
    epochs : int
        Passes over the demonstrations for the policy (and for the critic).
    critic : bool
        Also fit the value function to the demonstrations' discounted returns (PPO).
    keep : Schedule or None
        Keep the demonstrations in the updates: after each PPO update, behaviour-cloning steps on
        them with this weight (a schedule of training progress that ends at 0; DAPG-style), so that
        RL fine-tuning does not unlearn the clone. None: the demonstrations are used once.
    """

    epochs: int = 30
    critic: bool = True
    keep: Schedule | None = None


@dataclass(frozen=True)
class RollIn:
    """Roll-ins (Jump-Start RL): the coach acts first in each episode (:mod:`pidlab.rl.couplings`).

    Attributes
    ----------
    stages : int
        The agent takes each episode over in this many equal shares of the horizon, the last
        share first; from the last stage on the coach does not roll in.
    tolerance : float
        The agent alone must last ``1 - tolerance`` of its current share for the next stage.
    """

    stages: int = 10
    tolerance: float = 0.1


@dataclass(frozen=True)
class CoachBuffer:
    """The coach's transitions in a replay buffer of their own (off-policy agents; :mod:`pidlab.rl.replay`).

    Attributes
    ----------
    share : float
        Fraction of each training batch drawn from the coach's buffer, in [0, 1] (PVP: 0.5).
    size : int or None
        Capacity of the coach's buffer, transitions; None: the agent's ``buffer_size``.
    """

    share: float = 0.5
    size: int | None = None


@dataclass(frozen=True)
class ValueTrigger:
    """The coach takes over where its action is worth more than the agent's (SAC; TS2C-style).

    Attributes
    ----------
    margin : float
        The agent's critic must value the coach's proposal above the agent's action by more than
        ``margin`` alive rewards of the env (``>= 0``).
    """

    margin: float = 1.0


@dataclass(frozen=True)
class Proposer:
    """The coach proposes an action at every agent step; SAC's critic picks (IBRL-style).

    Attributes
    ----------
    until : float
        Training progress (fraction of the budget) from which the coach proposes no more, in
        (0, 1]: the agent acts alone from then on, and its critic's target is SAC's own.
    """

    until: float = 0.5


@dataclass(frozen=True)
class Coaching:
    """How the coach intervenes (see :class:`pidlab.rl.coaching.CoachingWrapper`).

    ``trigger``: ``None`` is the ``exit`` trigger, ``"predictive"`` the predictive one, a
    :class:`GrowthTrigger` the paper's. ``predictor``: the predictive trigger's look-ahead,
    ``"exact"`` (a copy of the MuJoCo data) or ``"model"`` (the discrete linear model).
    ``cost``: ``None`` is the default (10 alive rewards).
    ``blend`` and ``residual`` (at most one) are the coach's weight ``w`` in the executed action,
    ``w coach + (1 - w) agent`` and ``w coach + agent`` respectively, fading to 0.
    ``coach_buffer``: the coach's transitions kept for an off-policy agent's updates;
    ``value_trigger``: a takeover where the agent's critic values the coach's action higher;
    ``proposer``: the critic picks the agent's action or the coach's at every step, until ``until``.
    """

    mode: str = "takeover"
    region: str = "box"
    nudge_steps: int = 1
    max_coach_steps: int = 1000
    reward: str = "agent"
    probability: Schedule = field(default_factory=lambda: Schedule("constant", 1.0, 1.0))
    width: Schedule = field(default_factory=lambda: Schedule("constant", 1.0, 1.0))
    off_after: float | None = None
    trigger: GrowthTrigger | str | None = None
    predictor: str = "exact"
    view: str = "hidden"
    cost: float | None = None
    handback: float = 1.0
    demonstrations: DemonstrationSettings | None = None
    warm_start: WarmStart | None = None
    blend: Schedule | None = None
    rollin: RollIn | None = None
    residual: Schedule | None = None
    coach_buffer: CoachBuffer | None = None
    value_trigger: ValueTrigger | None = None
    proposer: Proposer | None = None


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
        Parallel envs of ``algo`` (its table's ``n_envs``, else the top-level one).
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
    algorithm_envs : dict
        Per algorithm, its parallel envs (``n_envs`` is ``algorithm_envs[algo]``).
    algorithm_normalize : dict
        Per algorithm, ``(obs, reward)``: what ``VecNormalize`` normalizes for it (its table's
        ``normalize``, else the top-level ``[normalize]``); ``normalize_obs`` and
        ``normalize_reward`` are the chosen algorithm's.
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
    algorithm_envs: dict[str, int] = field(default_factory=dict)
    algorithm_normalize: dict[str, tuple[bool, bool]] = field(default_factory=dict)
    path: str | None = None

    def __post_init__(self) -> None:
        """Refuse a recipe changed out of range (``dataclasses.replace(recipe, steps=-5)``).

        :func:`parse_recipe` checks every field of a file; this holds the fields a caller may
        change with ``replace`` to the same rules, so that no path reaches SB3 unchecked.
        """
        _check_recipe(self)

    @property
    def hyperparameters(self) -> dict[str, Any]:
        """SB3 keyword arguments of the chosen algorithm."""
        return dict(self.algorithms[self.algo])


MAX_STEPS = 10**12
"""The largest budget (env steps) a recipe or a command may ask for."""
MAX_PARALLEL = 1024
"""The most parallel envs (``n_envs``) and torch threads a recipe may ask for."""


def _check_recipe(r: Recipe) -> None:
    """The fields of a :class:`Recipe` in range; :class:`RecipeError` names the field (its ``param``).

    Raises
    ------
    RecipeError
    """
    check_name(r.env_id, "env_id", RecipeError, param="env_id")
    if not isinstance(r.algorithms, dict) or not r.algorithms or not set(r.algorithms) <= set(ALGOS):
        fail(r.algorithms, "algorithms", "a table of SB3 arguments per algorithm (ppo, sac)", RecipeError,
             "algorithms")  # fmt: skip
    if r.algo not in ALGOS:
        fail(r.algo, "algo", f"one of {', '.join(ALGOS)}", RecipeError, "algo")
    if r.algo not in r.algorithms:
        fail(r.algo, "algo", f"an algorithm the recipe has a table for ({', '.join(r.algorithms)})",
             RecipeError, "algo")  # fmt: skip
    for name, high in (("steps", MAX_STEPS), ("n_envs", MAX_PARALLEL), ("threads", MAX_PARALLEL),
                       ("checkpoint_every", MAX_STEPS)):  # fmt: skip
        integer(getattr(r, name), name, RecipeError, low=1, high=high, param=name)
    check_seed(r.seed, "seed", RecipeError, param="seed")
    if r.vec_env not in VEC_ENVS:
        fail(r.vec_env, "vec_env", f"one of {', '.join(VEC_ENVS)}", RecipeError, "vec_env")
    for name in ("normalize_obs", "normalize_reward"):
        if not isinstance(getattr(r, name), bool):
            fail(getattr(r, name), name, "true or false", RecipeError, name)
    for name, kind in (("win", Win), ("evaluation", Evaluation), ("coaching", Coaching)):
        if not isinstance(getattr(r, name), kind):
            fail(getattr(r, name), name, f"a {kind.__name__}", RecipeError, name)
    if r.algo == "ppo":
        check_rollout(r.algorithms["ppo"], r.n_envs, "ppo", param="n_envs")


def _int(
    data: dict[str, Any],
    key: str,
    where: str,
    default: int | None = None,
    low: int = 0,
    high: int | None = None,
) -> int:
    return integer(data.get(key, default), f"{where}.{key}", RecipeError, low=low, high=high)


def _num(data: dict[str, Any], key: str, where: str, default: float | None = None, **kw: Any) -> float:
    return number(data.get(key, default), f"{where}.{key}", RecipeError, **kw)


def _choice(data: dict[str, Any], key: str, where: str, allowed: tuple[str, ...], default: str) -> str:
    value = data.get(key, default)
    if not isinstance(value, str) or value not in allowed:
        raise RecipeError(f"{where}.{key} = {shown(value)}: expected one of {', '.join(allowed)}")
    return value


def _table(data: dict[str, Any], key: str, where: str, allowed: set[str]) -> dict[str, Any]:
    value = as_table(data.get(key, {}), f"{where}.{key}", RecipeError)
    unknown = set(value) - allowed
    if unknown:
        raise RecipeError(
            f"{where}.{key}: unknown field(s) {sorted(unknown)}; allowed: {', '.join(sorted(allowed))}"
        )
    return value


# ----------------------------------------------------------------- SB3 arguments: type and range

Check = Callable[[Any, str], Any]
"""Checks one SB3 argument's value (``where`` names it) and raises :class:`RecipeError`."""


def _integer(low: int, high: int) -> Check:
    return lambda v, w: integer(v, w, RecipeError, low=low, high=high)


def _real(low: float | None = None, high: float | None = None, low_open: bool = False) -> Check:
    return lambda v, w: number(v, w, RecipeError, low=low, high=high, low_open=low_open)


def _bool(value: Any, where: str) -> bool:
    return flag(value, where, RecipeError)


def _rate(value: Any, where: str) -> Any:
    """A positive number, or ``"lin_<x>"`` (the zoo's linear decay from ``x > 0``)."""
    expected = "a number > 0, or 'lin_<number>' (a linear decay from a number > 0)"
    if isinstance(value, str):
        start = _float_or_nan(value[4:]) if value.startswith("lin_") else math.nan
        if not (math.isfinite(start) and start > 0):
            fail(value, where, expected, RecipeError)
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        fail(value, where, expected, RecipeError)
    return number(value, where, RecipeError, low=0.0, low_open=True)


def _float_or_nan(text: str) -> float:
    return float_text(text)  # ASCII digits only, as every number given as text


def _sac_ent_coef(value: Any, where: str) -> Any:
    """SAC's entropy coefficient: a number >= 0, ``"auto"`` or ``"auto_<x>"`` (learned from ``x > 0``)."""
    if isinstance(value, str):
        start = (
            1.0 if value == "auto" else _float_or_nan(value[5:]) if value.startswith("auto_") else math.nan
        )
        if not (math.isfinite(start) and start > 0):
            fail(value, where, "a number >= 0, 'auto' or 'auto_<number > 0>'", RecipeError)
        return value
    return number(value, where, RecipeError, low=0.0)


def _target_entropy(value: Any, where: str) -> Any:
    if value == "auto":
        return value
    if isinstance(value, str):
        fail(value, where, "'auto' or a finite number", RecipeError)
    return number(value, where, RecipeError)


def _train_freq(value: Any, where: str) -> Any:
    """SAC's ``train_freq``: an integer >= 1, or ``[n, "step" | "episode"]``."""
    if isinstance(value, list):
        if len(value) != 2 or value[1] not in ("step", "episode"):
            fail(value, where, 'an integer >= 1 or [n, "step" | "episode"]', RecipeError)
        integer(value[0], f"{where}[0]", RecipeError, low=1, high=10**9)
        return value
    return integer(value, where, RecipeError, low=1, high=10**9)


_NET_UNITS = 10_000
_NET_LAYERS = 100


def _layers(value: Any, where: str) -> None:
    if not isinstance(value, list) or len(value) > _NET_LAYERS:
        fail(value, where, f"a list of at most {_NET_LAYERS} layer sizes, e.g. [64, 64]", RecipeError)
    for i, units in enumerate(value):
        integer(units, f"{where}[{i}]", RecipeError, low=1, high=_NET_UNITS)


def _net_arch(algo: str) -> Check:
    heads = {"ppo": ("pi", "vf"), "sac": ("pi", "qf")}[algo]

    def check(value: Any, where: str) -> Any:
        if isinstance(value, dict):
            as_table(value, where, RecipeError, "a table of layer lists")
            unknown = set(value) - set(heads)
            missing = [] if algo == "ppo" else [h for h in heads if h not in value]
            if unknown or missing:
                tables = " = [...], ".join(heads)
                fail(value, where, f"a list of layer sizes or a table {{ {tables} = [...] }}", RecipeError)
            for head, layers in value.items():
                _layers(layers, f"{where}.{head}")
            return value
        _layers(value, where)
        return value

    return check


def _activation(value: Any, where: str) -> Any:
    if not isinstance(value, str) or value not in ACTIVATIONS:
        fail(value, where, f"one of {', '.join(ACTIVATIONS)}", RecipeError)
    return value


_POLICY: dict[str, dict[str, Check]] = {
    "ppo": {"net_arch": _net_arch("ppo"), "activation_fn": _activation, "ortho_init": _bool,
            "log_std_init": _real(-20.0, 20.0), "full_std": _bool, "use_expln": _bool,
            "share_features_extractor": _bool, "normalize_images": _bool},
    "sac": {"net_arch": _net_arch("sac"), "activation_fn": _activation, "log_std_init": _real(-20.0, 20.0),
            "use_expln": _bool, "clip_mean": _real(0.0, low_open=True), "n_critics": _integer(1, 100),
            "share_features_extractor": _bool, "normalize_images": _bool},
}  # fmt: skip
"""The ``policy_kwargs`` a recipe may set, per algorithm, and their checks."""


def _policy_kwargs(algo: str) -> Check:
    def check(value: Any, where: str) -> Any:
        as_table(value, where, RecipeError, "a table of policy arguments")
        allowed = _POLICY[algo]
        unknown = set(value) - set(allowed)
        if unknown:
            raise RecipeError(
                f"{where}: unknown {algo.upper()} policy argument(s) {sorted(unknown)}; "
                f"allowed: {', '.join(sorted(allowed))}"
            )
        for key, item in value.items():
            allowed[key](item, f"{where}.{key}")
        return value

    return check


_SHARED: dict[str, Check] = {
    "learning_rate": _rate, "batch_size": _integer(1, 10**7), "gamma": _real(0.0, 1.0, low_open=True),
    "use_sde": _bool, "sde_sample_freq": _integer(-1, 10**9), "stats_window_size": _integer(1, 10**6),
}  # fmt: skip
ARGUMENTS: dict[str, dict[str, Check]] = {
    "ppo": {**_SHARED, "n_steps": _integer(1, 10**7), "n_epochs": _integer(1, 10**4),
            "gae_lambda": _real(0.0, 1.0), "clip_range": _rate, "clip_range_vf": _rate,
            "normalize_advantage": _bool, "ent_coef": _real(0.0), "vf_coef": _real(0.0),
            "max_grad_norm": _real(0.0, low_open=True), "target_kl": _real(0.0, low_open=True),
            "policy_kwargs": _policy_kwargs("ppo")},
    "sac": {**_SHARED, "buffer_size": _integer(1, 10**8), "learning_starts": _integer(0, MAX_STEPS),
            "tau": _real(0.0, 1.0, low_open=True), "train_freq": _train_freq,
            "gradient_steps": _integer(-1, 10**6), "n_steps": _integer(1, 10**4), "ent_coef": _sac_ent_coef,
            "target_update_interval": _integer(1, 10**9), "target_entropy": _target_entropy,
            "use_sde_at_warmup": _bool, "policy_kwargs": _policy_kwargs("sac")},
}  # fmt: skip
"""The SB3 keyword arguments a recipe may set, per algorithm, each with its check of type and range.

PPO: ``learning_rate`` > 0 or ``"lin_<x>"``, ``n_steps`` in [1, 1e7] (and ``n_steps * n_envs >= 2``
and ``batch_size >= 2`` unless ``normalize_advantage = false``), ``batch_size`` in [1, 1e7],
``n_epochs`` in [1, 1e4], ``gamma`` in (0, 1], ``gae_lambda`` in [0, 1], ``clip_range`` and
``clip_range_vf`` > 0 or ``"lin_<x>"``, ``ent_coef`` and ``vf_coef`` >= 0, ``max_grad_norm`` and
``target_kl`` > 0, ``sde_sample_freq`` >= -1, ``stats_window_size`` >= 1, booleans
``normalize_advantage`` and ``use_sde``. SAC: ``buffer_size`` in [1, 1e8], ``learning_starts`` >= 0,
``tau`` in (0, 1], ``train_freq`` >= 1 or ``[n, "step" | "episode"]``, ``gradient_steps`` >= -1,
``n_steps`` in [1, 1e4], ``ent_coef`` >= 0 or ``"auto"``/``"auto_<x>"``, ``target_update_interval``
>= 1, ``target_entropy`` a number or ``"auto"``, booleans ``use_sde`` and ``use_sde_at_warmup``.
``policy_kwargs``: ``net_arch`` (lists of 1 to 10,000 units, or ``{pi, vf}`` / ``{pi, qf}``),
``activation_fn`` (:data:`ACTIVATIONS`), ``log_std_init`` in [-20, 20], ``ortho_init``,
``full_std`` (PPO), ``clip_mean`` > 0, ``n_critics`` in [1, 100] (SAC), ``use_expln``,
``share_features_extractor``, ``normalize_images``.
"""


def algorithm_arguments(algo: str) -> tuple[str, ...]:
    """Keyword arguments of the SB3 class that a recipe may set (:data:`ARGUMENTS`)."""
    return tuple(ARGUMENTS[algo])


PIDLAB_KEYS = ("source", "n_envs", "normalize")
"""Keys of an algorithm table that are pidlab's, not SB3 arguments."""


def _check_algorithm(algo: str, table: dict[str, Any], where: str) -> tuple[dict[str, Any], str]:
    checks = ARGUMENTS[algo]
    kwargs = {k: v for k, v in table.items() if k not in PIDLAB_KEYS}
    unknown = set(kwargs) - set(checks)
    if unknown:
        raise RecipeError(
            f"{where}: unknown {algo.upper()} argument(s) {sorted(unknown)}; "
            f"allowed: {', '.join(sorted([*checks, *PIDLAB_KEYS]))}"
        )
    for key, value in kwargs.items():
        checks[key](value, f"{where}.{key}")
    source = table.get("source", "")
    if not isinstance(source, str):
        raise RecipeError(f"{where}.source: expected a string")
    return kwargs, source


def check_rollout(kwargs: dict[str, Any], n_envs: int, where: str, param: str | None = None) -> None:
    """PPO's rollout: ``n_steps * n_envs >= 2`` and ``batch_size >= 2`` (SB3 normalizes advantages).

    Raises
    ------
    RecipeError
        Naming ``where`` (or ``param``, the overridden ``n_envs``).
    """
    if not kwargs.get("normalize_advantage", True):
        return
    n_steps, batch = kwargs.get("n_steps", 2048), kwargs.get("batch_size", 64)
    if n_steps * n_envs < 2:
        expected = "a PPO rollout (n_steps * n_envs) of at least 2 steps, or normalize_advantage = false"
        if param is not None:
            fail(n_envs, param, f"{expected} (n_steps = {n_steps})", RecipeError, param)
        fail(n_steps, f"{where}.n_steps", f"{expected} (n_envs = {n_envs})", RecipeError)
    if batch < 2:
        fail(batch, f"{where}.batch_size", "an integer >= 2 (or normalize_advantage = false)", RecipeError)


_COACHING = {"mode", "region", "nudge_steps", "max_coach_steps", "reward", "probability", "width",
             "off_after", "trigger", "predictor", "view", "cost", "handback", "demonstrations", "warm_start",
             "blend", "rollin", "residual", "coach_buffer", "value_trigger", "proposer"}  # fmt: skip


def _coaching(data: dict[str, Any], where: str) -> Coaching:
    c = _table(data, "coaching", where, _COACHING)
    w = f"{where}.coaching"
    try:
        probability = parse_schedule(c.get("probability", 1.0), f"{w}.probability")
        width = parse_schedule(c.get("width", 1.0), f"{w}.width")
    except ScheduleError as exc:
        raise RecipeError(str(exc)) from None
    if probability.start > 1 or probability.end > 1:
        raise RecipeError(f"{w}.probability: a probability cannot exceed 1; expected start and end in [0, 1]")
    if width.start <= 0 or width.end <= 0:
        raise RecipeError(
            f"{w}.width: the factor on the region's size must be positive; expected start, end > 0"
        )
    off_after = None
    if "off_after" in c:
        off_after = _num(c, "off_after", w, low=0.0, high=1.0)
    trigger = _trigger(c, w) if "trigger" in c else None
    mode = _choice(c, "mode", w, MODES, "takeover")
    if isinstance(trigger, GrowthTrigger) and mode != "nudge":
        raise RecipeError(
            f"{w}.trigger: a growth trigger needs mode = 'nudge' (takeover is triggered by the region)"
        )
    region = _region(c, w, trigger, width)
    predictor = _choice(c, "predictor", w, PREDICTORS, "exact")
    if predictor == "model" and trigger != "predictive":
        raise RecipeError(
            f"{w}.predictor = 'model' is the predictive trigger's look-ahead; expected trigger = 'predictive'"
        )
    reward = _choice(c, "reward", w, REWARDS, "agent")
    view = _choice(c, "view", w, VIEWS, "hidden")
    if view == "terminal" and reward == "total":
        raise RecipeError(
            f"{w}.reward = 'total' with view = 'terminal': the takeover starts after the agent's episode "
            "ended, so its rewards are no agent's; use reward = 'agent'"
        )
    return Coaching(
        mode=mode,
        region=region,
        nudge_steps=_int(c, "nudge_steps", w, 1, low=1, high=10**6),
        max_coach_steps=_int(c, "max_coach_steps", w, 1000, low=1, high=10**9),
        reward=reward,
        probability=probability,
        width=width,
        off_after=off_after,
        trigger=trigger,
        predictor=predictor,
        view=view,
        cost=_num(c, "cost", w, low=0.0) if "cost" in c else None,
        handback=_num(c, "handback", w, 1.0, low=0.0, low_open=True, high=1.0),
        **_teaching(c, w),
    )


def parse_coaching(fields: dict[str, Any], where: str = "coaching") -> Coaching:
    """A recipe's ``[coaching]`` table on its own (the fields a condition gives).

    Raises
    ------
    RecipeError
        Naming the field (``where.coaching.FIELD``).
    """
    return _coaching({"coaching": fields}, where)


def _blend(c: dict[str, Any], w: str) -> Schedule | None:
    """``[coaching] blend``: the coach's weight in the executed action, fading to 0 by the end."""
    return _fading(c, "blend", w, "the coach's weight", high=1.0)


def _residual(c: dict[str, Any], w: str) -> Schedule | None:
    """``[coaching] residual``: the coach's weight under the agent's correction, fading to 0."""
    if "residual" in c and "blend" in c:
        raise RecipeError(
            f"{w}.residual and blend: both mix the coach's action into the agent's; expected one of them"
        )
    return _fading(c, "residual", w, "the coach's weight", high=1.0)


def _schedule(c: dict[str, Any], key: str, w: str) -> Schedule | None:
    """A schedule field (None when absent); a bad one is a :class:`RecipeError` naming it."""
    if key not in c:
        return None
    try:
        return parse_schedule(c[key], f"{w}.{key}")
    except ScheduleError as exc:
        raise RecipeError(str(exc)) from None


def _fading(c: dict[str, Any], key: str, w: str, what: str, high: float | None) -> Schedule | None:
    """A schedule field that must reach 0 by the end of the budget (None when absent)."""
    value = _schedule(c, key, w)
    if value is None:
        return None
    if high is not None and (value.start > high or value.end > high):
        raise RecipeError(
            f"{w}.{key}: {what} cannot exceed {high:g}; expected start and end in [0, {high:g}]"
        )
    if value(1.0) != 0.0:
        raise RecipeError(
            f"{w}.{key}: {what} must fade to 0 by the end of the budget, so that the agent ends "
            "up acting alone; expected end = 0 (and finish <= 1)"
        )
    return value


def _rollin(c: dict[str, Any], w: str) -> RollIn | None:
    """``[coaching] rollin = { stages, tolerance }`` (an empty table takes the defaults)."""
    if "rollin" not in c:
        return None
    t = _table(c, "rollin", w, {"stages", "tolerance"})
    where = f"{w}.rollin"
    stages = _int(t, "stages", where, 10, low=2, high=1000)
    return RollIn(stages=stages, tolerance=_num(t, "tolerance", where, 0.1, low=0.0, high=1.0))


def _coach_buffer(c: dict[str, Any], w: str) -> CoachBuffer | None:
    """``[coaching] coach_buffer = { share, size }`` (an empty table takes the defaults)."""
    if "coach_buffer" not in c:
        return None
    t = _table(c, "coach_buffer", w, {"share", "size"})
    where = f"{w}.coach_buffer"
    size = _int(t, "size", where, low=1, high=10**8) if "size" in t else None
    return CoachBuffer(share=_num(t, "share", where, 0.5, low=0.0, high=1.0), size=size)


def _value_trigger(c: dict[str, Any], w: str) -> ValueTrigger | None:
    """``[coaching] value_trigger = { margin }`` (an empty table takes the default)."""
    if "value_trigger" not in c:
        return None
    t = _table(c, "value_trigger", w, {"margin"})
    return ValueTrigger(margin=_num(t, "margin", f"{w}.value_trigger", 1.0, low=0.0))


def _proposer(c: dict[str, Any], w: str) -> Proposer | None:
    """``[coaching] proposer = { until }`` (an empty table takes the default)."""
    if "proposer" not in c:
        return None
    t = _table(c, "proposer", w, {"until"})
    return Proposer(until=_num(t, "until", f"{w}.proposer", 0.5, low=0.0, low_open=True, high=1.0))


def _teaching(c: dict[str, Any], w: str) -> dict[str, Any]:
    """``[coaching] demonstrations`` and ``warm_start`` (a warm start needs demonstrations)."""
    out: dict[str, Any] = {"demonstrations": None, "warm_start": None, "blend": _blend(c, w),
                           "rollin": _rollin(c, w), "residual": _residual(c, w),
                           "coach_buffer": _coach_buffer(c, w),
                           "value_trigger": _value_trigger(c, w), "proposer": _proposer(c, w)}  # fmt: skip
    if "demonstrations" in c:
        d = _table(c, "demonstrations", w, {"steps", "noise"})
        where = f"{w}.demonstrations"
        if "steps" not in d:
            raise RecipeError(f"{where}.steps: missing; the env steps the coach demonstrates, e.g. 5000")
        steps = _int(d, "steps", where, low=1, high=10**9)
        noise = _num(d, "noise", where, 0.1, low=0.0, high=10.0)
        out["demonstrations"] = DemonstrationSettings(steps=steps, noise=noise)
    if "warm_start" in c:
        t = _table(c, "warm_start", w, {"epochs", "critic", "keep"})
        if out["demonstrations"] is None:
            raise RecipeError(
                f"{w}.warm_start: a warm start clones the coach's demonstrations, and there are none; "
                f"add {w}.demonstrations = {{ steps = N }}"
            )
        critic = _bool(t["critic"], f"{w}.warm_start.critic") if "critic" in t else True
        epochs = _int(t, "epochs", f"{w}.warm_start", 30, low=1, high=10**5)
        # unlike blend and residual, keep need not fade to 0: it weighs a loss on the demonstrations
        # in the agent's own updates, and the coach acts in no step of the agent's
        keep = _schedule(t, "keep", f"{w}.warm_start")
        out["warm_start"] = WarmStart(epochs=epochs, critic=critic, keep=keep)
    return out


def _region(c: dict[str, Any], w: str, trigger: GrowthTrigger | str | None, width: Schedule) -> str:
    """``[coaching] region``, checked against the trigger (predictive: rescue) and the width schedule."""
    predictive = trigger == "predictive"
    region = _choice(c, "region", w, REGIONS, "rescue" if predictive else "box")
    if predictive and region != "rescue":
        raise RecipeError(
            f"{w}.trigger = 'predictive' tests the spec's rescue region; expected region = 'rescue'"
        )
    if region == "rescue" and not (width.start == 1.0 and width.end == 1.0):
        raise RecipeError(
            f"{w}.width: a rescue region (a lookup grid) cannot be scaled; "
            "expected width = 1 with region = 'rescue'"
        )
    return region


def _trigger(c: dict[str, Any], w: str) -> GrowthTrigger | str | None:
    """``[coaching] trigger``: ``exit`` (None), ``predictive``, or a growth-trigger table.

    A growth trigger has a variable, a band ``0 <= low <= high`` and ``steps`` in [1, 10000].
    """
    value = c["trigger"]
    if isinstance(value, str):
        if value not in TRIGGERS:
            raise RecipeError(
                f"{w}.trigger = {shown(value)}: expected one of {', '.join(TRIGGERS)}, or a growth-trigger "
                "table { variable, low, high, steps }"
            )
        return None if value == "exit" else value
    if not isinstance(value, dict):
        raise RecipeError(
            f"{w}.trigger = {shown(value)}: expected one of {', '.join(TRIGGERS)}, or a growth-trigger table"
        )
    t = _table(c, "trigger", w, {"variable", "low", "high", "steps"})
    if not isinstance(t.get("variable"), str) or not t["variable"]:
        raise RecipeError(f"{w}.trigger.variable: expected an observation variable name")
    low = _num(t, "low", f"{w}.trigger", 0.0, low=0.0)
    high = _num(t, "high", f"{w}.trigger", low=low)
    steps = _int(t, "steps", f"{w}.trigger", low=1, high=10_000)
    try:
        return GrowthTrigger(t["variable"], low, high, steps)
    except PidlabError as exc:
        raise RecipeError(f"{w}.trigger: {exc}") from None


_TOP = {"schema", "env_id", "description", "algo", "steps", "n_envs", "vec_env", "seed", "threads",
        "normalize", "win", "evaluation", "checkpoint", "coaching", "pipeline", *ALGOS}  # fmt: skip
PRESETS = ("robust", "weak", "room", "balance")
"""Auto-tuning presets a ``[pipeline]`` table may name: those of :mod:`pidlab.controller.autotune`,
``room`` (:mod:`pidlab.region.room`, pendulums only) and ``balance`` (:mod:`pidlab.controller.balance`,
robots whose model card has a ``[balance]`` table). Named here so that training does not import
the tuner and python-control; a test checks they agree."""


@dataclass(frozen=True)
class PipelineSettings:
    """What ``pidlab run ENV`` does on the recipe's env (the recipe's ``[pipeline]`` table).

    Attributes
    ----------
    seeds : int
        Seeds per condition; the pipeline trains the recipe's agent with and without the coach.
    steps : int
        Budget of each run, env steps (agent + coach).
    preset : {"robust", "weak", "room", "balance"}
        Auto-tuning preset.
    roa_samples : int
        Simulated initial states in the final certification of the region of attraction.
    episodes : int
        Coach-alone episodes on the real env.
    condition : str
        The condition of ``coach/conditions.toml`` whose ``coaching`` fields the coached runs use
        (with the pipeline's own coach): how the coach intervenes and what the agent sees of it.
        When its region is ``rescue``, the bounds stage also estimates the coach's rescue region.
    """

    seeds: int
    steps: int
    preset: str
    roa_samples: int
    episodes: int
    condition: str = "pidlab"


_PIPELINE = {"seeds", "steps", "preset", "roa_samples", "episodes", "condition"}


def parse_pipeline(data: dict[str, Any], where: str = "recipe") -> PipelineSettings:
    """The ``[pipeline]`` table of parsed recipe TOML, with defaults for what it leaves out.

    ``seeds`` in [1, 10000], ``steps`` in [1, 1e12], ``roa_samples`` in [1, 1e7], ``episodes``
    in [0, 10000] (:data:`pidlab.controller.rollout.MAX_EPISODES`).

    Raises
    ------
    RecipeError
        Naming the field and what is allowed.
    """
    data = _top(data, where)
    table = _table(data, "pipeline", where, _PIPELINE)
    w = f"{where}.pipeline"
    return PipelineSettings(
        seeds=_int(table, "seeds", w, 3, low=1, high=MAX_SEEDS),
        steps=_int(table, "steps", w, _int(data, "steps", where, 100_000, low=1, high=MAX_STEPS), low=1,
                   high=MAX_STEPS),
        preset=_choice(table, "preset", w, PRESETS, "robust"),
        roa_samples=_int(table, "roa_samples", w, 1000, low=1, high=MAX_SAMPLES),
        episodes=_int(table, "episodes", w, 10, low=0, high=MAX_EPISODES),
        condition=check_name(table.get("condition", "pidlab"), f"{w}.condition", RecipeError),
    )  # fmt: skip


def load_pipeline_settings(path: str | Path) -> PipelineSettings:
    """Read and validate the ``[pipeline]`` table of a recipe file (and the rest of the recipe).

    Raises
    ------
    RecipeError
    """
    data = read_toml(path, "recipe", RecipeError)
    parse_recipe(data, str(path))
    settings = parse_pipeline(data, str(path))
    check_pipeline_condition(data, settings.condition, str(path))
    return settings


def check_pipeline_condition(data: dict[str, Any], condition: str, where: str) -> None:
    """The ``[pipeline] condition`` a recipe file names is a coached condition of ``coach/conditions.toml``.

    Checked wherever a recipe file is read (``pidlab train --recipe``, ``pidlab experiment``), not
    only by ``pidlab run``, which trains with it. Without a readable conditions file there is
    nothing to check against; the commands that read that file report it.

    Raises
    ------
    RecipeError
        Naming the field, and the conditions the file has.
    """
    file = find_data_file("coach", "conditions.toml")
    try:
        conditions = read_toml(file, "conditions file", RecipeError)
    except PidlabError:
        return
    tables = conditions.get("condition")
    if not isinstance(tables, dict) or not all(isinstance(t, dict) for t in tables.values()):
        return
    w = f"{where}.pipeline.condition"
    if condition not in tables:
        fail(condition, w, f"a condition of {file}: {', '.join(tables)}",
             RecipeError)  # fmt: skip
    table = tables[condition]
    envs = table.get("env")
    env = envs.get(data.get("env_id"), {}) if isinstance(envs, dict) else {}
    coach = env.get("coach", table.get("coach")) if isinstance(env, dict) else table.get("coach")
    if coach == "none":
        fail(condition, w, "a condition that trains a coach (this one has coach = 'none')", RecipeError)


def _top(data: Any, where: str) -> dict[str, Any]:
    """The recipe's top level: a table with the schema and known fields."""
    data = as_table(data, where, RecipeError, "a table (parsed TOML)")
    if data.get("schema") != RECIPE_SCHEMA:
        raise RecipeError(f"{where}: schema = {shown(data.get('schema'))}, expected {RECIPE_SCHEMA!r}")
    unknown = set(data) - _TOP
    if unknown:
        raise RecipeError(f"{where}: unknown field(s) {sorted(unknown)}; allowed: {', '.join(sorted(_TOP))}")
    return data


def _algorithms(data: dict[str, Any], where: str) -> tuple[dict[str, dict[str, Any]], dict[str, str], str]:
    """The ``[ppo]``/``[sac]`` tables (checked against :data:`ARGUMENTS`), their sources, and ``algo``."""
    algorithms: dict[str, dict[str, Any]] = {}
    sources: dict[str, str] = {}
    for algo in ALGOS:
        if algo in data:
            as_table(data[algo], f"{where}.{algo}", RecipeError, f"a table of {algo.upper()} arguments")
            algorithms[algo], sources[algo] = _check_algorithm(algo, data[algo], f"{where}.{algo}")
    if not algorithms:
        raise RecipeError(f"{where}: no algorithm table; add [ppo] and/or [sac]")
    algo = _choice(data, "algo", where, ALGOS, next(iter(algorithms)))
    if algo not in algorithms:
        raise RecipeError(f"{where}.algo = {algo!r}, but the recipe has no [{algo}] table")
    return algorithms, sources, algo


def _win(data: dict[str, Any], where: str) -> Win:
    win = _table(data, "win", where, {"target", "consecutive", "window"})
    if "target" not in win:
        raise RecipeError(f"{where}.win.target: missing; the return that counts as a win, e.g. 800")
    return Win(
        target=_num(win, "target", f"{where}.win"),
        consecutive=_int(win, "consecutive", f"{where}.win", 5, low=1, high=10**6),
        window=_int(win, "window", f"{where}.win", 20, low=1, high=10**6),
    )


def _evaluation(data: dict[str, Any], where: str, steps: int) -> Evaluation:
    """``[evaluation]``: ``every`` >= 1, ``episodes`` in [1, 10000], seeds ``seed + i`` below 2**32."""
    ev = _table(data, "evaluation", where, {"every", "episodes", "seed"})
    w = f"{where}.evaluation"
    episodes = _int(ev, "episodes", w, 10, low=1, high=10_000)
    return Evaluation(
        every=_int(ev, "every", w, max(steps // 20, 1), low=1, high=MAX_STEPS),
        episodes=episodes,
        seed=_int(ev, "seed", w, 1_000_000, low=0, high=SEED_MAX - (episodes - 1)),
    )


def parse_recipe(data: dict[str, Any], where: str = "recipe") -> Recipe:
    """Build a :class:`Recipe` from parsed TOML, checking every field's type and range.

    ``env_id`` follows :data:`pidlab.checks.NAME_RULE`; ``steps`` in [1, 1e12]; ``n_envs`` and
    ``threads`` in [1, 1024]; ``seed`` in [0, 2**32 - 1]; the ``[ppo]`` and ``[sac]`` tables as
    :data:`ARGUMENTS` says. Nothing reaches SB3 unchecked.

    Raises
    ------
    RecipeError
        Naming the field and what is allowed.
    """
    data = _top(data, where)
    env_id = check_name(data.get("env_id"), f"{where}.env_id", RecipeError)
    algorithms, sources, algo = _algorithms(data, where)
    normalize = _algorithm_normalize(data, algorithms, where)
    obs, reward = normalize[algo]
    steps = _int(data, "steps", where, low=1, high=MAX_STEPS)
    envs = _algorithm_envs(data, algorithms, where)
    if "ppo" in algorithms:
        check_rollout(algorithms["ppo"], envs["ppo"], f"{where}.ppo")
    ck = _table(data, "checkpoint", where, {"every"})
    parse_pipeline(data, where)  # checked here so a bad [pipeline] fails wherever the recipe loads
    return Recipe(
        env_id=env_id,
        description=text(data.get("description", ""), f"{where}.description", RecipeError),
        algo=algo,
        steps=steps,
        n_envs=envs[algo],
        vec_env=_choice(data, "vec_env", where, VEC_ENVS, "dummy"),
        seed=check_seed(data.get("seed", 0), f"{where}.seed", RecipeError),
        threads=_int(data, "threads", where, 1, low=1, high=MAX_PARALLEL),
        normalize_obs=obs,
        normalize_reward=reward,
        win=_win(data, where),
        evaluation=_evaluation(data, where, steps),
        checkpoint_every=_int(ck, "every", f"{where}.checkpoint", max(steps // 10, 1), low=1, high=MAX_STEPS),
        coaching=_coaching(data, where),
        algorithms=algorithms,
        sources=sources,
        algorithm_envs=envs,
        algorithm_normalize=normalize,
        path=None,
    )


def _normalize(table: dict[str, Any], where: str, default: tuple[bool, bool]) -> tuple[bool, bool]:
    """A ``normalize = { obs, reward }`` table (each flag defaults to ``default``'s)."""
    norm = _table(table, "normalize", where, {"obs", "reward"})
    obs, reward = (
        flag(norm.get(key, d), f"{where}.normalize.{key}", RecipeError)
        for key, d in zip(("obs", "reward"), default, strict=True)
    )
    return obs, reward


def _algorithm_normalize(
    data: dict[str, Any], algorithms: dict[str, Any], where: str
) -> dict[str, tuple[bool, bool]]:
    """What ``VecNormalize`` normalizes per algorithm: its table's ``normalize``, else ``[normalize]``."""
    default = _normalize(data, where, (False, False))
    return {algo: _normalize(data[algo], f"{where}.{algo}", default) for algo in algorithms}


def _algorithm_envs(data: dict[str, Any], algorithms: dict[str, Any], where: str) -> dict[str, int]:
    """Parallel envs per algorithm: its table's ``n_envs``, else the top-level ``n_envs`` (default 1)."""
    default = _int(data, "n_envs", where, 1, low=1, high=MAX_PARALLEL)
    return {
        algo: _int(data[algo], "n_envs", f"{where}.{algo}", default, low=1, high=MAX_PARALLEL)
        for algo in algorithms
    }


def load_recipe(path: str | Path) -> Recipe:
    """Read and validate a recipe file (its ``[pipeline] condition`` too: :func:`check_pipeline_condition`).

    Raises
    ------
    RecipeError
    """
    data = read_toml(path, "recipe", RecipeError)
    recipe = parse_recipe(data, str(path))
    if "pipeline" in data:
        check_pipeline_condition(data, parse_pipeline(data, str(path)).condition, str(path))
    return replace(recipe, path=str(path))


def recipes_dir() -> Path:
    """The folder of recipes (:func:`pidlab.data.coach_dir`)."""
    return coach_dir()


def default_recipe_path(env_id: str) -> Path:
    """``coach/<env_id>.toml``: the user's folder's (``$PIDLAB_COACH``) when it has one, else the shipped one.

    Raises
    ------
    RecipeError
        ``env_id`` does not follow :data:`pidlab.checks.NAME_RULE` (it would leave ``coach/``).
    """
    check_name(env_id, "env_id", RecipeError, param="env_id")
    path_under(recipes_dir(), f"{env_id}.toml", error=RecipeError, param="env_id")  # stays inside coach/
    return find_data_file("coach", f"{env_id}.toml")  # the user's recipe, else the shipped one


def recipe_envs() -> list[str]:
    """The env ids that have a recipe in the user's or the shipped ``coach/`` folder, sorted."""
    return [p.stem for p in data_files("coach", "*-v*.toml")]


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
        An algorithm the recipe has no table for, or a number out of range: ``steps`` in
        [1, 1e12], ``seed`` in [0, 2**32 - 1], ``n_envs`` in [1, 1024] (and PPO's rollout).
    """
    if algo is not None:
        if algo not in ALGOS:
            raise RecipeError(f"algo={shown(algo)}: expected one of {', '.join(ALGOS)}", param="algo")
        if algo not in recipe.algorithms:
            raise RecipeError(
                f"algo={algo!r}: the recipe {recipe.path or ''} has no [{algo}] table", param="algo"
            )
    if steps is not None:
        integer(steps, "steps", RecipeError, low=1, high=MAX_STEPS, param="steps")
    chosen = algo or recipe.algo
    if n_envs is not None:
        integer(n_envs, "n_envs", RecipeError, low=1, high=MAX_PARALLEL, param="n_envs")
        if chosen == "ppo":
            check_rollout(recipe.algorithms["ppo"], n_envs, "ppo", param="n_envs")
    elif chosen != recipe.algo:  # another algorithm: its own number of envs
        n_envs = recipe.algorithm_envs.get(chosen, recipe.n_envs)
    if seed is not None:
        check_seed(seed, "seed", RecipeError, param="seed")
    obs, reward = recipe.algorithm_normalize.get(chosen, (recipe.normalize_obs, recipe.normalize_reward))
    return replace(
        recipe,
        algo=algo or recipe.algo,
        normalize_obs=obs,
        normalize_reward=reward,
        steps=steps or recipe.steps,
        seed=recipe.seed if seed is None else seed,
        n_envs=n_envs or recipe.n_envs,
        algorithm_envs={**recipe.algorithm_envs, chosen: n_envs or recipe.n_envs},
    )


def _teaching_to_dict(c: Coaching) -> dict[str, Any]:
    """The teaching couplings' fields of ``c`` that are set (none: the recipe reads as before)."""
    coaching: dict[str, Any] = {}
    if c.demonstrations is not None:
        coaching["demonstrations"] = {"steps": c.demonstrations.steps, "noise": c.demonstrations.noise}
    if c.warm_start is not None:
        coaching["warm_start"] = {"epochs": c.warm_start.epochs, "critic": c.warm_start.critic}
        if c.warm_start.keep is not None:
            coaching["warm_start"]["keep"] = schedule_to_dict(c.warm_start.keep)
    if c.blend is not None:
        coaching["blend"] = schedule_to_dict(c.blend)
    if c.residual is not None:
        coaching["residual"] = schedule_to_dict(c.residual)
    if c.rollin is not None:
        coaching["rollin"] = {"stages": c.rollin.stages, "tolerance": c.rollin.tolerance}
    if c.coach_buffer is not None:
        buffer: dict[str, Any] = {"share": c.coach_buffer.share}
        if c.coach_buffer.size is not None:
            buffer["size"] = c.coach_buffer.size
        coaching["coach_buffer"] = buffer
    if c.value_trigger is not None:
        coaching["value_trigger"] = {"margin": c.value_trigger.margin}
    if c.proposer is not None:
        coaching["proposer"] = {"until": c.proposer.until}
    return coaching


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
    if isinstance(c.trigger, GrowthTrigger):
        t = c.trigger
        coaching["trigger"] = {"variable": t.variable, "low": t.low, "high": t.high, "steps": t.steps}
    elif c.trigger is not None:
        coaching["trigger"] = c.trigger
    if c.predictor != "exact":
        coaching["predictor"] = c.predictor
    # written only when they differ from the defaults, so a run's settings (and their digest) read
    # as before for the recipes that do not use them
    if c.handback != 1.0:
        coaching["handback"] = c.handback
    if c.view != "hidden":
        coaching["view"] = c.view
    if c.cost is not None:
        coaching["cost"] = c.cost
    coaching |= _teaching_to_dict(c)
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
        # the top level holds the chosen algorithm's envs (what the run uses); another algorithm's
        # table says its own only where it differs, so recipes without per-algorithm envs read as before
        envs = recipe.algorithm_envs.get(algo, recipe.n_envs)
        own: dict[str, Any] = {"n_envs": envs} if algo != recipe.algo and envs != recipe.n_envs else {}
        chosen = (recipe.normalize_obs, recipe.normalize_reward)
        norm = recipe.algorithm_normalize.get(algo, chosen)
        if algo != recipe.algo and norm != chosen:
            own["normalize"] = {"obs": norm[0], "reward": norm[1]}
        out[algo] = {"source": recipe.sources.get(algo, ""), **own, **kwargs}
    return out


def check_coaching(value: Any, where: str) -> None:
    """Check fields meant to replace a recipe's ``[coaching]`` fields (a condition's ``coaching``).

    Each field is checked for its type and range as :func:`parse_recipe` checks it; a growth
    ``trigger`` (a table) without a ``mode`` is checked as for ``mode = "nudge"`` (the recipe may set it).

    Raises
    ------
    RecipeError
        Naming ``where.coaching.FIELD``.
    """
    fields = as_table(value, f"{where}.coaching", RecipeError, "a table of [coaching] fields of a recipe")
    if isinstance(fields.get("trigger"), dict) and "mode" not in fields:
        fields = {**fields, "mode": "nudge"}
    _coaching({"coaching": fields}, where)
