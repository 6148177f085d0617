"""The coaching wrapper: the PID coach takes over outside the takeover region.

:class:`CoachingWrapper` is a ``gymnasium.Wrapper``. Coach steps run *inside* ``step()``: the
agent acts at ``s_t``, and the observation it gets back is the state after the coach handed
control back. Any SB3 algorithm therefore stores only the agent's own transitions.

Intervention modes
    ``takeover`` (the paper's text): once the trigger fires, the coach acts until the state is in
    the hand-back region (or the episode ends, or ``max_coach_steps``). ``nudge`` (the paper's
    original code): exactly ``nudge_steps`` coach steps when the trigger fires (fewer only if a
    coach step ends the episode).

Triggers
    ``exit`` (default, reactive): the agent's step left the region. ``predictive``: before the
    agent's action runs, the state after it is predicted on a copy of the env's MuJoCo data; an
    action that would leave the region is vetoed (it never runs) and the coach acts from the
    current state (the spec's rescue region): under ``takeover`` until the hand-back, under
    ``nudge`` for ``nudge_steps`` steps only, so that with ``nudge_steps = 1`` the coach replaces
    just the vetoed action and the agent's next action is checked again (a minimal shield: the
    agent acts whenever its action keeps the state in the region). ``growth`` (the paper's
    code, see :class:`GrowthTrigger`, ``nudge`` only): a variable's magnitude lies in a band and
    has grown with the same sign for a number of consecutive steps.

Region
    From the spec's ``[bounds]`` table (:func:`pidlab.region.takeover.region_from_bounds`):
    ``box``, ``ellipsoid`` or ``rescue`` (the lookup grid of ``[bounds.rescue]``). A takeover
    hands back once the state is in ``region.inner(handback)`` (``handback = 1``: the region).

What the agent sees of a takeover (``view``)
    ``hidden``: nothing; its transition carries its own step's reward (predictive: the reward of
    the coach step that ran in place of its vetoed action) and the observation after the hand-back.
    ``penalty``: the same, with ``cost`` taken off the transition that triggered the takeover.
    ``terminal``: the agent's episode ends at the trigger as if it had failed (``terminated``,
    the env's failure reward, :func:`pidlab.rl.rewards.failure_reward`); the coach rescues the
    real env (inside the same ``step()``) and the next ``reset()`` returns the rescued state
    instead of resetting, unless the rescue ended the env's episode, or the reset has a seed or
    options. The look-ahead of the predictive trigger is :class:`pidlab.rl.predict.Predictor`
    (``predictor = "exact"``, a copy of the env's MuJoCo data) or
    :class:`pidlab.rl.predict.ModelPredictor` (``"model"``: the discrete linear model; the whole
    box of the forecast's measured error, ``[bounds.forecast]``, about the forecast must lie in the
    rescue region: :func:`pidlab.region.forecast.margin_region`, a lookup grid's or a classifier's).

Rewards
    By default the agent is given its own step's reward only; the coach's rewards are reported
    in ``info["coach_reward"]``. ``reward="total"`` gives the agent both (not with ``terminal``).

Episode ends
    A coach step may end the episode: ``terminated`` / ``truncated`` are passed through
    unchanged, and the env's own time limit counts coach steps (they are real env steps).

Schedules
    ``probability(progress)``: chance of intervening when the trigger fires; ``width(progress)``:
    factor on the region's size (box and ellipsoid only); ``off_after``: progress from which the
    coach never intervenes. :meth:`CoachingWrapper.set_progress` (called by the trainer) moves them.

Blend and residual
    ``blend(progress)``: the coach's weight ``w`` in the executed action. Each agent action ``a``
    runs as ``clip(w * coach(s) + (1 - w) * a)`` (a second instance of the coach acts at every
    agent step, so its filters follow the episode); ``info["executed_action"]`` and
    ``info["blend_weight"]`` report it. The agent's transition holds its own sample ``a``; the
    blend is part of the environment it learns in, which becomes its own as ``w`` fades to 0.
    With ``residual=True`` the agent's action is a correction added to the coach's:
    ``clip(w * coach(s) + a)`` (residual policy learning with a fading coach; an agent whose mean
    starts near 0, as PPO's does, starts at the coach's behaviour).

Roll-in (Jump-Start RL)
    :meth:`CoachingWrapper.set_rollin` sets ``h``: after each real reset the coach acts alone for the
    first ``h`` steps of the env's episode, and the agent's first observation is the state after them
    (a ``terminal``-view rescue, which does not reset the env, has none). Those steps belong to the
    episode (its ``coach_steps``); they are reported once, in ``info["rollin"]`` of the agent's next
    step (``steps``, and ``episodes``: the records of env episodes that ended during a roll-in, by a
    fall or the time limit; the env was then reset, and that episode starts without a roll-in).
    :meth:`CoachingWrapper.take_rollin` hands over a report that no step carried yet (the run's end).

Uninterrupted runs
    A run is a stretch of consecutive agent actions that ran with no coach step between them; an
    intervention or a veto ends it, and so does the episode's end. Each episode record gives its
    ``runs`` and ``longest_run`` (the agent's run length, which a takeover that starves it cuts short).

Value trigger (TS2C-style)
    :meth:`CoachingWrapper.set_advisor` sets a judge ``advisor(obs, agent_action, proposal)``:
    before an agent action runs that the predictive trigger let pass (the rescue region is the
    hard floor), the coach's proposal from the current state (:meth:`~CoachingWrapper.proposal`, the
    first action a takeover starting now would run) is put to it, and when it answers True the
    action is vetoed as the predictive trigger vetoes one (``info["veto_reason"] = "value"``;
    ``total_value_vetoes`` counts them). :mod:`pidlab.rl.couplings` makes the judge from the SAC
    agent's critic.

Proposer (IBRL-style)
    :meth:`CoachingWrapper.set_proposer` sets a judge of the same signature and a progress
    ``until``: while training progress is below it, the coach's proposal from the current state is
    put to the judge at every agent step, and when it answers True the proposal runs *as the agent's
    step* in place of its action (then the trigger and the view apply as to any agent step). The
    step's info gives ``proposing``, ``proposal_taken``, ``executed_action`` and ``next_proposal``
    (the coach's proposal from the observation the step returns, for the critic's target);
    ``total_proposals_taken`` counts them.

Coach transitions
    With ``record=True`` each step that ran coach steps of a takeover or a veto (not a roll-in, not
    a demonstration) reports them in ``info["coach_transitions"]``: arrays ``obs``, ``actions``
    (the action executed, inside the action space), ``rewards``, ``next_obs``, ``terminated`` and
    ``truncated``, one row per coach step in order (:mod:`pidlab.rl.replay` keeps them for an
    off-policy agent).

Demonstrations
    :meth:`CoachingWrapper.demonstrate` puts the wrapper in demonstration mode: each ``step()``
    ignores the agent's action and runs one coach step with Gaussian noise on the coach's action
    (DART); ``info["demonstration_action"]`` holds the executed action, ``info["demonstration"]``
    is True, and the step counts as a coach step (no agent step). ``demonstrate(None)`` ends it.

No coach
    ``spec=None`` gives a pass-through that only keeps the accounts (the uncoached condition
    logs exactly like the coached ones).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from pidlab.checks import instance
from pidlab.controller.pid import Coach
from pidlab.controller.spec import CoachSpec
from pidlab.errors import CoachingError
from pidlab.plant.model import LoadedModel, load_model
from pidlab.region.forecast import (
    ClassifierMarginRegion,
    MarginRegion,
    check_forecastable,
    check_network,
    learned_forecast,
    margin_region,
    margin_variables,
    spec_forecast,
)
from pidlab.region.takeover import (
    KINDS,
    ClassifierRegion,
    GridRegion,
    Region,
    observation_indices,
    region_from_bounds,
)
from pidlab.rl.predict import ModelPredictor, Predictor, forecast_of
from pidlab.rl.rewards import alive_reward, failure_function

MODES = ("takeover", "nudge")
REGIONS = KINDS
REWARDS = ("agent", "total")
TRIGGERS = ("exit", "predictive")
"""The named triggers (a table is the growth trigger): leaving the region, or a predicted exit."""
VIEWS = ("hidden", "penalty", "terminal")
"""What the agent sees of a takeover."""
COST_STEPS = 10.0
"""The default cost of a takeover (``penalty`` view), in steps of the env's alive reward."""


# ----------------------------------------------------------------- env steps of a step


def step_env_steps(info: dict[str, Any]) -> tuple[int, int]:
    """The agent's and the coach's env steps of one wrapper step (a roll-in before it excluded).

    A vetoed agent action ran no env step, and a demonstration step is the coach's.
    """
    agent = 0 if info.get("vetoed", False) or info.get("demonstration", False) else 1
    return agent, int(info.get("coach_steps", 0))


def uncounted_env_steps(infos: Sequence[dict[str, Any]]) -> int:
    """Env steps of one vector-env step that SB3's count (one per env) misses, or counts wrongly.

    Per env: its agent and coach env steps (:func:`step_env_steps`) and a roll-in's coach steps
    reported with it, less the one SB3 counted.
    """
    total = 0
    for info in infos:
        agent, coach = step_env_steps(info)
        rollin = info.get("rollin")
        total += agent + coach + (int(rollin["steps"]) if rollin is not None else 0) - 1
    return total


# ----------------------------------------------------------------- triggers


@dataclass(frozen=True)
class GrowthTrigger:
    """The paper's coded trigger: ``variable`` grows in magnitude, with one sign, inside a band.

    It fires at step ``t`` when ``low <= |v_t| <= high`` and ``v_{t-steps}, ..., v_t`` all have
    the same (non-zero) sign with strictly increasing magnitude, i.e. ``|v|`` grew on ``steps``
    consecutive steps. ``v`` is read from every observation the env produced (agent's and
    coach's steps alike) since the episode's reset.

    Attributes
    ----------
    variable : str
        Observation variable (e.g. ``hinge_vel``).
    low, high : float
        Band on ``|v|``.
    steps : int
        Consecutive growing steps required (>= 1).
    """

    variable: str
    low: float
    high: float
    steps: int

    def __post_init__(self) -> None:
        if not 0.0 <= self.low <= self.high:
            raise CoachingError(f"growth trigger band [{self.low}, {self.high}]: expected 0 <= low <= high")
        if self.steps < 1:
            raise CoachingError(f"growth trigger steps = {self.steps}: expected >= 1")

    def fires(self, history: deque[float]) -> bool:
        """Whether the trigger fires on ``history`` (oldest first, newest last)."""
        if len(history) < self.steps + 1:
            return False
        v = np.array(history)[-(self.steps + 1) :]
        if not self.low <= abs(v[-1]) <= self.high:
            return False
        sign = np.sign(v)
        return bool(sign[-1] != 0 and np.all(sign == sign[-1]) and np.all(np.diff(np.abs(v)) > 0))


Advisor = Callable[[np.ndarray, np.ndarray, np.ndarray], bool]
"""The value trigger's judge: ``(observation, agent's action, coach's proposal) -> take over``."""
ProgressFn = Callable[[float], float]
"""A value as a function of training progress in [0, 1]; a :class:`pidlab.rl.schedule.Schedule` is one."""


def _check_options(
    mode: str, reward: str, nudge_steps: int, max_coach_steps: int, trigger: GrowthTrigger | str | None,
    view: str, cost: float | None, handback: float,
) -> None:  # fmt: skip
    """Raise :class:`CoachingError` on options that cannot work together."""
    if mode not in MODES:
        raise CoachingError(f"mode {mode!r}: expected one of {', '.join(MODES)}")
    if reward not in REWARDS:
        raise CoachingError(f"reward {reward!r}: expected one of {', '.join(REWARDS)}")
    if nudge_steps < 1 or max_coach_steps < 1:
        raise CoachingError("nudge_steps and max_coach_steps must be >= 1")
    if isinstance(trigger, GrowthTrigger) and mode == "takeover":
        raise CoachingError(
            "a growth trigger needs mode = nudge: takeover hands back once inside the critical "
            "region, so it is triggered by leaving it"
        )
    if isinstance(trigger, str) and trigger not in TRIGGERS:
        raise CoachingError(f"trigger {trigger!r}: expected one of {', '.join(TRIGGERS)} or a growth trigger")
    if view not in VIEWS:
        raise CoachingError(f"view {view!r}: expected one of {', '.join(VIEWS)}")
    if cost is not None and not (math.isfinite(cost) and cost >= 0):
        raise CoachingError(f"cost {cost!r}: expected a finite number >= 0")
    if not (math.isfinite(handback) and 0.0 < handback <= 1.0):
        raise CoachingError(f"handback {handback!r}: expected a fraction in (0, 1]")
    if view == "terminal" and reward == "total":
        raise CoachingError(
            "reward 'total' with view 'terminal': the takeover starts after the agent's episode ended, "
            "so its rewards are no agent's; use reward = 'agent'"
        )


PREDICTORS = ("exact", "model")
"""The predictive trigger's look-ahead: a copy of the MuJoCo data, or the discrete linear model."""


def _check_predictor(predictor: object, trigger: object) -> None:
    if predictor not in PREDICTORS:
        raise CoachingError(f"predictor {predictor!r}: expected one of {', '.join(PREDICTORS)}")
    if predictor == "model" and trigger != "predictive":
        raise CoachingError(
            "predictor 'model' is the predictive trigger's look-ahead; use trigger = 'predictive'"
        )


def model_region(
    spec: CoachSpec, loaded: LoadedModel, region: Region
) -> MarginRegion | ClassifierMarginRegion:
    """The rescue region the model predictor asks: of the box of the measured error about a forecast.

    A lookup grid is narrowed by the margins (:class:`MarginRegion`); a classifier's score is
    bounded over the box (:class:`ClassifierMarginRegion`).

    Raises
    ------
    CoachingError
        The region tests a variable no joint-state forecast gives; the spec has no forecast
        measurement, or one of another region, or a learned correction fitted for another model;
        the error leaves nothing of the region, or leaves out the operating point (where the coach
        hands back).
    """
    from pidlab.plant.observation import observe_at
    from pidlab.plant.operating_point import resolve_operating_point

    card = loaded.require_card()
    check_forecastable(card, margin_variables(region), f"{spec.name}: predictor 'model'")
    forecast = spec_forecast(spec.bounds, spec.name)
    try:
        shrunk = margin_region(region, forecast.margin, forecast.bound, forecast.pieces, forecast.adaptive)
        if forecast.network is not None:  # a learned correction must fit this env's linear model
            learned_forecast(forecast_of(loaded), forecast.network, card)
        if forecast.adaptive is not None:  # and so must the adaptive margins' network
            check_network(forecast_of(loaded), forecast.adaptive.network, "the adaptive margins' network")
    except CoachingError as exc:
        raise CoachingError(f"{spec.name}: {exc}") from None
    op = resolve_operating_point(loaded)
    if not shrunk.contains(observe_at(card, loaded.model, op.qpos, op.qvel)):
        raise CoachingError(
            f"{spec.name}: the forecast's error ({_margins(forecast.margin)}) is too wide for the rescue "
            "region even at the operating point, where the coach hands back; use predictor = 'exact'"
        )
    return shrunk


def _margins(margin: dict[str, float]) -> str:
    return ", ".join(f"{k} {v:.3g}" for k, v in margin.items())


def _constant_one(width: ProgressFn | None) -> bool:
    from pidlab.rl.schedule import Schedule

    return width is None or (isinstance(width, Schedule) and width.start == 1.0 and width.end == 1.0)


def takeover_region(spec: CoachSpec, observation_names: tuple[str, ...], kind: str, predictive: bool,
                    width: ProgressFn | None = None) -> Region:  # fmt: skip
    """The region the wrapper tests, checked against the trigger that tests it.

    Raises
    ------
    CoachingError
        The predictive trigger without a rescue region; a rescue region derived for the predictive
        trigger tested after the agent's step; a width schedule on a rescue region.
    """
    bounds = spec.bounds or {}
    if predictive and kind != "rescue":
        raise CoachingError(
            f"trigger 'predictive' tests the rescue region, not {kind!r}: use region = 'rescue'"
        )
    if predictive and "rescue" not in bounds:
        raise CoachingError(
            f"{spec.name}: trigger 'predictive', but the spec has no rescue region; "
            "run `pidlab rescue SPEC --write`"
        )
    region = region_from_bounds(bounds, observation_names, kind, spec.name)
    if isinstance(region, GridRegion | ClassifierRegion):
        if region.trigger == "predictive" and not predictive:
            raise CoachingError(
                f"{spec.name}: its rescue region was derived for the predictive trigger and leaves no room "
                "for the agent's step; use trigger = 'predictive', or derive a reactive one "
                "(`pidlab rescue SPEC --trigger reactive --write`)"
            )
        if not _constant_one(width):
            raise CoachingError("width: a rescue region cannot be scaled; use width = 1 with region 'rescue'")
    return region


@dataclass(frozen=True)
class _Run:
    """A coach's run of steps: where it ended, its first step, and its totals."""

    obs: Any
    steps: int
    reward: float
    terminated: bool
    truncated: bool
    first_obs: Any
    first_reward: float
    first_info: dict[str, Any]

    @property
    def ended(self) -> bool:
        return self.terminated or self.truncated


class CoachingWrapper(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Hide PID-coach interventions inside ``step()``.

    Parameters
    ----------
    env : gymnasium.Env
        A Gymnasium MuJoCo env (usually from ``gymnasium.make``, with its time limit).
    spec : CoachSpec or None
        The coach, with bounds (the region); ``None``: no coach, accounts only.
    mode : {"takeover", "nudge"}
    region : {"box", "ellipsoid", "rescue"}
    trigger : GrowthTrigger or {"exit", "predictive"}, optional
        Default ``exit``: leaving the region after the agent's step. ``predictive``: an action
        whose predicted next state leaves the (rescue) region is vetoed. A growth trigger is the
        paper's coded one (``nudge`` only).
    nudge_steps : int
        Coach steps per intervention in ``nudge`` mode.
    max_coach_steps : int
        Longest takeover (a coach that cannot bring the state back does not loop forever).
    reward : {"agent", "total"}
    probability : callable, optional
        ``progress -> probability`` of intervening when the trigger fires (default 1).
    width : callable, optional
        ``progress -> factor`` on the region's size (default 1; box and ellipsoid only).
    off_after : float, optional
        Progress from which the coach never intervenes.
    loaded : LoadedModel, optional
        The env's model (default: loaded from the spec's env id).
    seed : int, optional
        Seed of the probability schedule's coin (default: the first ``reset`` seed).
    view : {"hidden", "penalty", "terminal"}
        What the agent sees of a takeover (see the module's docstring).
    cost : float, optional
        What a takeover costs the agent under ``penalty`` (>= 0; default :data:`COST_STEPS` times
        the env's alive reward).
    handback : float
        The coach hands back once the state is in ``region.inner(handback)``, in (0, 1].
    blend : callable, optional
        ``progress -> w``: the coach's weight in the executed action (see the module docstring).
    residual : bool
        The agent's action is added to the weighted coach's (needs ``blend``).
    record : bool
        Report the coach's transitions of takeovers and vetoes in ``info["coach_transitions"]``.
    predictor : {"exact", "model"}
        The predictive trigger's look-ahead: a copy of the env's MuJoCo data, or the linear model
        with the spec's ``[bounds.forecast]`` margins about its forecast.
    """

    def __init__(
        self,
        env: gym.Env,
        spec: CoachSpec | None,
        mode: str = "takeover",
        region: str = "box",
        trigger: GrowthTrigger | str | None = None,
        nudge_steps: int = 1,
        max_coach_steps: int = 1000,
        reward: str = "agent",
        probability: ProgressFn | None = None,
        width: ProgressFn | None = None,
        off_after: float | None = None,
        loaded: LoadedModel | None = None,
        seed: int | None = None,
        view: str = "hidden",
        cost: float | None = None,
        handback: float = 1.0,
        blend: ProgressFn | None = None,
        residual: bool = False,
        record: bool = False,
        predictor: str = "exact",
    ) -> None:
        instance(env, gym.Env, "env", CoachingError)
        if spec is not None:
            instance(spec, CoachSpec, "spec", CoachingError)
        gym.utils.RecordConstructorArgs.__init__(
            self, spec=spec, mode=mode, region=region, trigger=trigger, nudge_steps=nudge_steps,
            max_coach_steps=max_coach_steps, reward=reward, probability=probability, width=width,
            off_after=off_after, loaded=loaded, seed=seed, view=view, cost=cost, handback=handback,
            blend=blend, residual=residual, record=record, predictor=predictor,
        )  # fmt: skip
        gym.Wrapper.__init__(self, env)
        _check_options(mode, reward, nudge_steps, max_coach_steps, trigger, view, cost, handback)
        _check_predictor(predictor, trigger)
        self.predictor_kind = predictor
        self.coach_spec = spec
        self.mode = mode
        self.nudge_steps = nudge_steps
        self.max_coach_steps = max_coach_steps
        self.reward_mode = reward
        self.probability = probability
        self.width = width
        self.off_after = off_after
        self.view = view
        self.handback = float(handback)
        self.predictive = trigger == "predictive"
        self.trigger = trigger if isinstance(trigger, GrowthTrigger) else None
        self.cost = 0.0
        self.coach: Coach | None = None
        self.region: Any = None  # a Region (box, ellipsoid or rescue) with a settable scale
        self._handback_region: Region | None = None
        self._predictor: Predictor | ModelPredictor | None = None
        if spec is not None:
            self._set_coach(env, spec, region, loaded, cost)
        self._history: deque[float] = deque(maxlen=(self.trigger.steps + 1) if self.trigger else 1)
        self.progress = 0.0
        self._rng = np.random.default_rng(seed)
        self._seeded = seed is not None
        self._rescued: tuple[Any, dict[str, Any]] | None = None
        self._last_obs: Any = None
        self._demo: tuple[float, np.random.Generator] | None = None
        self._demo_started = False
        self.rollin_steps = 0
        self._pending_rollin: dict[str, Any] | None = None
        self._set_mix(spec, blend, residual)
        if not isinstance(record, bool):
            raise CoachingError(f"record={record!r}: expected True or False")
        self.record = record
        self._transitions: list[tuple[Any, ...]] = []
        self._advisor: Advisor | None = None
        self._picker: Advisor | None = None
        self._until = 1.0
        self._proposer: Coach | None = None
        self._reset_counters()
        self._zero_totals()

    def _zero_totals(self) -> None:
        """The lifetime totals, all zero (they are never reset after)."""
        self.total_value_vetoes = 0
        self.total_proposals_taken = 0
        self.total_agent_steps = 0
        self.total_coach_steps = 0
        self.total_interventions = 0
        self.total_vetoes = 0
        self.total_agent_episodes = 0
        self.total_env_episodes = 0
        self.total_env_resets = 0
        self.total_falls = 0

    def _set_coach(self, env: gym.Env, spec: CoachSpec, region: str, loaded: LoadedModel | None,
                   cost: float | None) -> None:  # fmt: skip
        env_id = env.spec.id if env.spec is not None else None
        if env_id is not None and env_id != spec.env_id:
            raise CoachingError(f"the spec is for {spec.env_id}, the env is {env_id}")
        self.loaded = loaded if loaded is not None else load_model(spec.env_id)
        card = self.loaded.require_card()
        names = card.observation_names
        self.coach = Coach(spec, self.loaded)
        if self.trigger is None:
            self.region = takeover_region(spec, names, region, self.predictive, self.width)
            if self.predictor_kind == "model":
                self.region = model_region(spec, self.loaded, self.region)
            self._update_handback()
        else:
            self._trigger_index = observation_indices([self.trigger.variable], names, "growth trigger")[0]
        if self.predictive:
            exact = self.predictor_kind == "exact"
            self._predictor = (
                Predictor(env, card) if exact
                else ModelPredictor(env, self.loaded, spec_forecast(spec.bounds, spec.name))
            )  # fmt: skip
        if self.view == "terminal":
            self._failure = failure_function(spec.env_id)
        if self.view == "penalty":
            self.cost = float(cost) if cost is not None else COST_STEPS * alive_reward(env)

    def _update_handback(self) -> None:
        if self.region is not None:
            self._handback_region = self.region if self.handback == 1.0 else self.region.inner(self.handback)

    @property
    def lookahead(self) -> Predictor | ModelPredictor | None:
        """The predictive trigger's look-ahead (None with another trigger)."""
        return self._predictor

    @property
    def coached(self) -> bool:
        """Whether there is a coach at all."""
        return self.coach is not None

    def _reset_counters(self) -> None:
        self.episode_agent_steps = 0
        self.episode_coach_steps = 0
        self.episode_interventions = 0
        self.episode_vetoes = 0
        self.episode_agent_return = 0.0
        self.episode_coach_return = 0.0
        self.episode_paid_return = 0.0
        self.episode_runs = 0
        self.episode_longest_run = 0
        self._run_length = 0

    def demonstrate(self, noise: float | None, seed: int = 0) -> None:
        """Start (``noise`` >= 0, a fraction of half the action range) or end (None) demonstration mode.

        Raises
        ------
        CoachingError
            No coach, or a negative noise.
        """
        if noise is None:
            self._demo = None
            return
        if self.coach is None:
            raise CoachingError("demonstrations need a coach; this env has none (--coach none)")
        if not (math.isfinite(noise) and noise >= 0):
            raise CoachingError(f"demonstration noise {noise!r}: expected a finite number >= 0")
        self._demo = (float(noise), np.random.default_rng(seed))
        self._demo_started = False

    def _demonstration_step(self) -> tuple[Any, float, bool, bool, dict]:
        """One coach step with noise on its action, in the agent's place (demonstration mode)."""
        coach, (noise, rng) = self.coach, self._demo or (0.0, self._rng)
        if coach is None:  # pragma: no cover - demonstrate() refuses a wrapper without a coach
            raise CoachingError("no coach to demonstrate")
        if not self._demo_started or self.episode_agent_steps + self.episode_coach_steps == 0:
            coach.reset(self._last_obs)
            self._demo_started = True
        space: Any = self.env.action_space
        low, high = np.asarray(space.low, dtype=np.float64), np.asarray(space.high, dtype=np.float64)
        action = np.asarray(coach.act(self._last_obs), dtype=float)
        action = np.clip(action + noise * (high - low) / 2 * rng.standard_normal(action.shape), low, high)
        executed = action.astype(space.dtype)
        obs, reward, terminated, truncated, info = self.env.step(executed)
        self._observe(obs)
        run = _Run(obs, 1, float(reward), terminated, truncated, obs, float(reward), info)
        info = {**info, "demonstration": True, "demonstration_action": executed}
        return self._finish(obs, float(reward), terminated, truncated, info, 0.0, run, demonstration=True)

    def set_progress(self, progress: float) -> None:
        """Training progress in [0, 1] (fraction of the budget spent), read by the schedules."""
        self.progress = float(min(max(progress, 0.0), 1.0))
        if self.region is not None:
            scale = 1.0 if self.width is None else float(self.width(self.progress))
            if scale != self.region.scale:
                self.region.scale = scale
                self._update_handback()

    def intervention_probability(self) -> float:
        """Probability of intervening when the trigger fires, now."""
        if self.coach is None or (self.off_after is not None and self.progress >= self.off_after):
            return 0.0
        return 1.0 if self.probability is None else float(self.probability(self.progress))

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict]:
        """Reset the env and the episode's counters.

        After a ``terminal``-view takeover whose rescue left the env's episode running, the env is
        not reset: the rescued state starts the agent's next episode (``info["rescued"]``). A
        reset with a seed or options always resets the env.
        """
        if seed is not None and not self._seeded:
            self._rng = np.random.default_rng(seed)
            self._seeded = True
        rescued, self._rescued = self._rescued, None
        if rescued is not None and seed is None and options is None:
            obs, info = rescued
            self._start_episode(obs)
        else:
            obs, info = self._real_reset(seed, options)
        if self._blend_coach is not None:
            self._blend_coach.reset(obs)
        return obs, info

    def _start_episode(self, obs: Any) -> None:
        self._reset_counters()
        self._history.clear()
        self._observe(obs)

    def _real_reset(self, seed: int | None, options: dict[str, Any] | None) -> tuple[Any, dict]:
        """Reset the env, then the roll-in (if any); a roll-in that ends the episode resets it again."""
        obs, info = self.env.reset(seed=seed, options=options)
        self.total_env_resets += 1
        self._start_episode(obs)
        if self.rollin_steps <= 0 or self._demo is not None or self.coach is None:
            return obs, info
        run = self._coach_run(obs, limit=self.rollin_steps)
        self.total_coach_steps += run.steps
        self.episode_coach_steps += run.steps
        self.episode_coach_return += run.reward
        report = self._pending_rollin or {"steps": 0, "episodes": []}  # joins a report no step carried
        report["steps"] += run.steps
        self._pending_rollin = report
        if not run.ended:
            return run.obs, {**info, "rollin_steps": run.steps}
        self.total_falls += int(run.terminated)
        report["episodes"].append(self._episode_record(run.terminated, True, run.terminated))
        obs, info = self.env.reset()
        self.total_env_resets += 1
        self._start_episode(obs)
        return obs, info

    def set_rollin(self, steps: int) -> None:
        """The roll-in: the coach's steps at the start of each env episode (0: none).

        Raises
        ------
        CoachingError
            A negative count, or a roll-in (> 0) without a coach.
        """
        if isinstance(steps, bool) or not isinstance(steps, int | np.integer) or steps < 0:
            raise CoachingError(f"roll-in steps {steps!r}: expected an integer >= 0")
        if steps > 0 and self.coach is None:
            raise CoachingError("a roll-in needs a coach; this env has none (--coach none)")
        self.rollin_steps = int(steps)

    def take_rollin(self) -> dict[str, Any] | None:
        """The roll-in report no step has carried yet (then forgotten), or None."""
        report, self._pending_rollin = self._pending_rollin, None
        return report

    def _observe(self, obs: np.ndarray) -> None:
        self._last_obs = obs
        if self.trigger is not None:
            self._history.append(float(np.asarray(obs)[self._trigger_index]))

    def _coin(self) -> bool:
        """Whether a trigger that fired leads to an intervention (the probability schedule)."""
        p = self.intervention_probability()
        return p >= 1.0 or (p > 0.0 and self._rng.random() < p)

    def _triggered(self, obs: np.ndarray) -> bool:
        if self.coach is None:
            return False
        if self.trigger is not None:
            fired = self.trigger.fires(self._history)
        elif self.region is not None:
            fired = not self.region.contains(obs)
        else:  # a coach always has a trigger or a region (see __init__)
            return False
        return fired and self._coin()

    def _vetoed(self, action: Any) -> bool:
        """The predictive trigger: whether ``action`` would leave the region (and the coin says act)."""
        if self._predictor is None or self.region is None or self.intervention_probability() <= 0.0:
            return False
        obs = self._predictor.predict(action)
        # a state the env's termination rule ends lies in no rescue region, whatever a region's
        # membership test says of it (a classifier's box may reach past a limit)
        if isinstance(self.region, ClassifierMarginRegion) and isinstance(self._predictor, ModelPredictor):
            inside = self.region.contains(obs, self._predictor.inputs)  # adaptive margins need its inputs
        else:
            inside = self.region.contains(obs)
        return (self._predictor.terminal or not inside) and self._coin()

    def _coach_run(self, obs: Any, limit: int | None = None) -> _Run:
        """The coach acts from ``obs``: until hand-back (takeover) or ``nudge_steps``, or the episode ends.

        With ``limit`` (a roll-in) it acts for exactly that many steps, fewer only if the episode ends.
        """
        coach = self.coach
        if coach is None:  # pragma: no cover - only called once a coach intervened
            raise CoachingError("no coach to take over")
        coach.reset(obs)
        handback = self._handback_region if self.mode == "takeover" and limit is None else None
        record = self.record and limit is None  # a roll-in's steps are not a rescue's
        if limit is None:
            limit = self.nudge_steps if self.mode == "nudge" else self.max_coach_steps
        steps, total, terminated, truncated = 0, 0.0, False, False
        first: tuple[Any, float, dict[str, Any]] = (obs, 0.0, {})
        while steps < limit:
            action = coach.act(obs)
            before = obs
            obs, r, terminated, truncated, info = self.env.step(action)
            if record:
                self._transitions.append((before, action, float(r), obs, bool(terminated), bool(truncated)))
            self._observe(obs)
            steps += 1
            total += float(r)
            if steps == 1:
                first = (obs, float(r), info)
            if terminated or truncated:
                break
            if handback is not None and handback.contains(obs):
                break
        return _Run(obs, steps, total, terminated, truncated, *first)

    def _set_mix(self, spec: CoachSpec | None, blend: ProgressFn | None, residual: bool) -> None:
        """The blend's (or residual's) weight schedule and the coach instance that mixes in."""
        self.blend = blend
        self.residual = bool(residual)
        self._blend_coach: Coach | None = None
        if residual and blend is None:
            raise CoachingError("residual: the agent corrects a weighted coach; expected a weight (blend)")
        if blend is not None:
            if spec is None:
                what = "adding the agent's correction to" if residual else "blending"
                raise CoachingError(f"blend: {what} the coach's action needs a coach; this env has none")
            self._blend_coach = Coach(spec, self.loaded)

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        """One agent step, then the coach's steps if the trigger fired (or the coach's, if vetoed)."""
        self._rescued = None  # a step after a terminal-view takeover without a reset: the env went on
        if self._demo is not None:
            return self._demonstration_step()
        if self._picker is not None and self.proposing:
            return self._proposed_step(action)
        blended = self._blended(action)
        if blended is not None:
            return self._with_blend(self._agent_step(blended[0]), blended)
        return self._agent_step(action)

    def set_proposer(self, picker: Advisor | None, until: float = 1.0) -> None:
        """The proposer's judge (None: no proposer) and the progress from which it proposes no more.

        Raises
        ------
        CoachingError
            A proposer without a coach, or ``until`` outside (0, 1].
        """
        if picker is not None and not callable(picker):
            raise CoachingError(f"picker {picker!r}: expected (obs, action, proposal) -> bool, or None")
        if picker is not None and self.coach is None:
            raise CoachingError("a proposer needs a coach; this env has none (--coach none)")
        if isinstance(until, bool) or not (isinstance(until, int | float) and 0.0 < until <= 1.0):
            raise CoachingError(f"proposer until = {until!r}: expected a fraction of the budget in (0, 1]")
        self._picker, self._until = picker, float(until)
        if picker is not None and self._proposer is None and self.coach_spec is not None:
            self._proposer = Coach(self.coach_spec, self.loaded)

    @property
    def proposing(self) -> bool:
        """Whether the coach proposes now (a proposer is set and training progress is below ``until``)."""
        return self._picker is not None and self.progress < self._until

    def _proposed_step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        """The judge picks the agent's action or the coach's proposal; the pick runs as the agent's step."""
        space: Any = self.env.action_space
        picker = self._picker
        if picker is None:  # pragma: no cover - step() calls this only with a proposer set
            raise CoachingError("no proposer")
        proposal = self.proposal()
        taken = bool(picker(np.asarray(self._last_obs), np.asarray(action, dtype=np.float64), proposal))
        executed = proposal.astype(space.dtype) if taken else action
        self.total_proposals_taken += int(taken)
        obs, reward, terminated, truncated, info = self._agent_step(executed)
        info["proposing"] = True
        info["proposal_taken"] = taken
        info["executed_action"] = np.asarray(executed)
        info["next_proposal"] = self.proposal(obs)
        return obs, reward, terminated, truncated, info

    def _blended(self, action: Any) -> tuple[Any, float] | None:
        """The executed action and ``w`` (None: no blend).

        ``clip(w coach + (1 - w) action)``; with a residual, ``clip(w coach + action)``.
        """
        if self._blend_coach is None or self.blend is None:
            return None
        coach_action = np.asarray(self._blend_coach.act(self._last_obs), dtype=np.float64)
        w = float(min(max(self.blend(self.progress), 0.0), 1.0))
        space: Any = self.env.action_space
        agent = np.asarray(action, dtype=np.float64)
        mixed = w * coach_action + (agent if self.residual else (1.0 - w) * agent)
        return np.clip(mixed, space.low, space.high).astype(space.dtype), w

    @staticmethod
    def _with_blend(out: tuple[Any, float, bool, bool, dict], blended: tuple[Any, float]) -> tuple:
        obs, reward, terminated, truncated, info = out
        info["executed_action"], info["blend_weight"] = blended
        return obs, reward, terminated, truncated, info

    def _agent_step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        """The agent's (possibly blended) action, then the coach's steps if the trigger fired."""
        if self._predictor is not None:
            if self._vetoed(action):
                self._predictor.discard()
                return self._veto()
            if self._advised_against(action):
                self._predictor.discard()
                self.total_value_vetoes += 1
                out = self._veto()
                out[4]["veto_reason"] = "value"
                return out
            # the action runs on the data its prediction computed (when it was predicted)
            obs, reward, terminated, truncated, info = self._predictor.execute(self.env.step, action)
        else:
            obs, reward, terminated, truncated, info = self.env.step(action)
        self._observe(obs)
        self.episode_agent_steps += 1
        self.total_agent_steps += 1
        self.episode_agent_return += float(reward)
        self._count_run()
        if self.predictive or terminated or truncated or not self._triggered(obs):
            return self._finish(obs, float(reward), terminated, truncated, info, float(reward), None)
        run = self._coach_run(obs)
        if self.view == "terminal":
            paid = self._failure(float(reward), info)
            return self._terminal(obs, paid, info, float(reward), run, vetoed=False)
        paid = float(reward) + (run.reward if self.reward_mode == "total" else 0.0)
        if self.view == "penalty":
            paid -= self.cost
        return self._finish(run.obs, paid, run.terminated, run.truncated, info, float(reward), run)

    def set_advisor(self, advisor: Advisor | None) -> None:
        """The value trigger's judge (None: no value trigger); see the module docstring.

        Raises
        ------
        CoachingError
            An advisor without a coach, or without the predictive trigger (its hard floor).
        """
        if advisor is not None and not callable(advisor):
            raise CoachingError(f"advisor {advisor!r}: expected (obs, action, proposal) -> bool, or None")
        if advisor is not None and (self.coach is None or self._predictor is None):
            raise CoachingError(
                "a value trigger needs a coach and the predictive trigger (the rescue region is its floor)"
            )
        self._advisor = advisor
        if advisor is not None and self._proposer is None and self.coach_spec is not None:
            self._proposer = Coach(self.coach_spec, self.loaded)

    def proposal(self, obs: Any = None) -> np.ndarray:
        """The coach's action from ``obs`` (default: the current state): a takeover's first there."""
        proposer = self._proposer
        if proposer is None:
            raise CoachingError("no coach proposes: set an advisor or a proposer first")
        obs = self._last_obs if obs is None else obs
        proposer.reset(obs)
        space: Any = self.env.action_space
        return np.clip(np.asarray(proposer.act(obs), dtype=np.float64), space.low, space.high)

    def _advised_against(self, action: Any) -> bool:
        """The value trigger: whether the advisor prefers the coach's proposal (and the coin says act)."""
        if self._advisor is None or self.intervention_probability() <= 0.0:
            return False
        agent = np.asarray(action, dtype=np.float64)
        return bool(self._advisor(np.asarray(self._last_obs), agent, self.proposal())) and self._coin()

    def _veto(self) -> tuple[Any, float, bool, bool, dict]:
        """The agent's action is not executed: the coach takes over from the current state."""
        run = self._coach_run(self._last_obs)
        self.episode_vetoes += 1
        self.total_vetoes += 1
        if self.view == "terminal":
            paid = self._failure(run.first_reward, run.first_info)
            return self._terminal(run.first_obs, paid, run.first_info, 0.0, run, vetoed=True)
        paid = run.reward if self.reward_mode == "total" else run.first_reward
        if self.view == "penalty":
            paid -= self.cost
        ended = (run.terminated, run.truncated)
        return self._finish(run.obs, paid, *ended, run.first_info, 0.0, run, vetoed=True)

    def _terminal(self, obs: Any, paid: float, info: dict[str, Any], agent_reward: float, run: _Run,
                  vetoed: bool) -> tuple[Any, float, bool, bool, dict]:  # fmt: skip
        """End the agent's episode as failed; the rescued state (if the env goes on) starts the next one."""
        self._rescued = None if run.ended else (run.obs, {"rescued": True})
        return self._finish(obs, paid, True, False, info, agent_reward, run, vetoed=vetoed,
                            env_end=run.ended, fell=run.terminated)  # fmt: skip

    def _finish(
        self, obs: Any, paid: float, terminated: bool, truncated: bool, info: dict[str, Any],
        agent_reward: float, run: _Run | None, vetoed: bool = False, env_end: bool | None = None,
        fell: bool | None = None, demonstration: bool = False,
    ) -> tuple[Any, float, bool, bool, dict]:  # fmt: skip
        """Keep the accounts of one agent step (or demonstration step) and report them in ``info``."""
        coach_steps, coach_reward = (run.steps, run.reward) if run is not None else (0, 0.0)
        if run is not None:
            self._run_length = 0  # a coach step ends the agent's uninterrupted run
        if run is not None and not demonstration:
            self.episode_interventions += 1
            self.total_interventions += 1
        self.episode_coach_steps += coach_steps
        self.total_coach_steps += coach_steps
        self.episode_coach_return += coach_reward
        self.episode_paid_return += paid
        env_end = bool(terminated or truncated) if env_end is None else env_end
        fell = bool(terminated) if fell is None else fell
        self.total_falls += int(fell)
        info = dict(info)
        # per step, and the episode so far (deterministic given the reset); lifetime totals are
        # attributes: total_agent_steps, total_coach_steps, total_interventions, ...
        info.update({
            "agent_reward": agent_reward,
            "coach_reward": coach_reward,
            "coach_steps": coach_steps,
            "intervened": run is not None and not demonstration,
            "vetoed": vetoed,
            "env_ended": env_end,
            "fell": fell,
            "episode_agent_steps": self.episode_agent_steps,
            "episode_coach_steps": self.episode_coach_steps,
            "episode_env_steps": self.episode_agent_steps + self.episode_coach_steps,
            "episode_interventions": self.episode_interventions,
            "episode_agent_return": self.episode_agent_return,
            "episode_total_return": self.episode_agent_return + self.episode_coach_return,
        })  # fmt: skip
        if vetoed:
            info["veto_reason"] = "region"  # the value trigger's say "value" (set by the caller)
        if terminated or truncated:
            info["coaching_episode"] = self._episode_record(terminated, env_end, fell)
        rollin, self._pending_rollin = self._pending_rollin, None
        if rollin is not None:
            info["rollin"] = rollin
        if self._transitions:
            info["coach_transitions"] = self._take_transitions()
        return obs, paid, terminated, truncated, info

    def _take_transitions(self) -> dict[str, np.ndarray]:
        """The recorded coach steps as arrays, one row each (then forgotten)."""
        rows, self._transitions = self._transitions, []
        space: Any = self.env.action_space
        obs, actions, rewards, next_obs, terminated, truncated = zip(*rows, strict=True)
        return {
            "obs": np.array(obs, dtype=np.float64),
            "actions": np.clip(np.array(actions, dtype=np.float64), space.low, space.high),
            "rewards": np.array(rewards, dtype=np.float64),
            "next_obs": np.array(next_obs, dtype=np.float64),
            "terminated": np.array(terminated, dtype=bool),
            "truncated": np.array(truncated, dtype=bool),
        }

    def _count_run(self) -> None:
        """One more agent action in the current uninterrupted run (a new run starts at 1)."""
        self._run_length += 1
        self.episode_runs += int(self._run_length == 1)
        self.episode_longest_run = max(self.episode_longest_run, self._run_length)

    def _episode_record(self, terminated: bool, env_end: bool, fell: bool) -> dict[str, Any]:
        """The ended agent episode's summary (``info["coaching_episode"]``)."""
        self.total_agent_episodes += 1
        self.total_env_episodes += int(env_end)
        return {
            "agent_steps": self.episode_agent_steps,
            "coach_steps": self.episode_coach_steps,
            "env_steps": self.episode_agent_steps + self.episode_coach_steps,
            "interventions": self.episode_interventions,
            "vetoes": self.episode_vetoes,
            "agent_return": self.episode_agent_return,
            "coach_return": self.episode_coach_return,
            "total_return": self.episode_agent_return + self.episode_coach_return,
            "paid_return": self.episode_paid_return,
            "terminated": bool(terminated),
            "env_end": bool(env_end),
            "fell": bool(fell),
            "runs": self.episode_runs,
            "longest_run": self.episode_longest_run,
        }
