"""The coaching wrapper: the PID coach takes over outside the critical region, hidden from the agent.

:class:`CoachingWrapper` is a ``gymnasium.Wrapper``. Coach steps run *inside* ``step()``: the
agent acts at ``s_t``, and the observation it gets back is the state after the coach handed
control back. Any SB3 algorithm therefore stores only the agent's own transitions.

Intervention modes
    ``takeover`` (the paper's text): after an agent step that leaves the critical region, the
    coach acts until the state is back inside (or the episode ends, or ``max_coach_steps``).
    ``nudge`` (the paper's original code): exactly ``nudge_steps`` coach steps when the trigger
    fires (fewer only if a coach step ends the episode).

Triggers
    ``exit`` (default): the state left the critical region. ``growth`` (the paper's code, see
    :class:`GrowthTrigger`): a variable's magnitude lies in a band and has grown with the same
    sign for a number of consecutive steps. ``takeover`` needs the region to hand back, so it
    uses ``exit``.

Region
    From the spec's ``[bounds]`` table: ``box`` (every listed variable within its range) or
    ``ellipsoid`` (``(y - center)' shape (y - center) <= rho * level``).

Rewards
    By default the agent is given its own step's reward only; the coach's rewards are reported
    in ``info["coach_reward"]``. ``reward="total"`` gives the agent both.

Episode ends
    A coach step may end the episode: ``terminated`` / ``truncated`` are passed through
    unchanged, and the env's own time limit counts coach steps (they are real env steps).

Schedules
    ``probability(progress)``: chance of intervening when the trigger fires; ``width(progress)``:
    factor on the region's size; ``off_after``: progress from which the coach never intervenes.
    :meth:`CoachingWrapper.set_progress` (called by the trainer) moves them along.

No coach
    ``spec=None`` gives a pass-through that only keeps the accounts (the uncoached condition
    logs exactly like the coached ones).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from pidlab.controller.pid import Coach
from pidlab.controller.spec import CoachSpec
from pidlab.errors import CoachingError
from pidlab.plant.model import LoadedModel, load_model

MODES = ("takeover", "nudge")
REGIONS = ("box", "ellipsoid")
REWARDS = ("agent", "total")


def _index(name: str, observation_names: tuple[str, ...], where: str) -> int:
    if name not in observation_names:
        raise CoachingError(
            f"{where}: {name!r} is not an observation variable; valid: {', '.join(observation_names)}"
        )
    return observation_names.index(name)


class CriticalRegion:
    """Membership test of the critical region, in observation variables.

    Parameters
    ----------
    spec : CoachSpec
        With a ``[bounds]`` table.
    observation_names : tuple of str
    kind : {"box", "ellipsoid"}
    scale : float
        Shrinks (< 1) or widens (> 1) the region about its centre (a width schedule sets it).
    """

    def __init__(self, spec: CoachSpec, observation_names: tuple[str, ...], kind: str = "box",
                 scale: float = 1.0) -> None:  # fmt: skip
        if kind not in REGIONS:
            raise CoachingError(f"region {kind!r}: expected one of {', '.join(REGIONS)}")
        b = spec.bounds or {}
        self.kind = kind
        self.scale = scale
        if kind == "box":
            box = b.get("box")
            if not box:
                raise CoachingError(
                    f"{spec.name}: the spec has no [bounds.box]; run `pidlab bounds SPEC --write`"
                )
            self.index = np.array([_index(v, observation_names, "bounds.box") for v in box])
            lo = np.array([v[0] for v in box.values()])
            hi = np.array([v[1] for v in box.values()])
            self.center = 0.5 * (lo + hi)
            self.half = 0.5 * (hi - lo)
            self._indices = [int(i) for i in self.index]
            self._set_limits()
        else:
            e = b.get("ellipsoid")
            if not e:
                hint = (
                    "its bounds come from a simulated recoverable box (contacts), which has no ellipsoid; "
                    "use region = \"box\""
                    if b.get("box")
                    else "run `pidlab bounds SPEC --write`"
                )
                raise CoachingError(f"{spec.name}: the spec has no [bounds.ellipsoid]; {hint}")
            self.index = np.array([_index(v, observation_names, "bounds.ellipsoid") for v in e["variables"]])
            self.center = np.array(e["center"], dtype=float)
            self.shape = np.array(e["shape"], dtype=float)
            self.threshold = float(e["rho"]) * float(e["level"])

    @property
    def scale(self) -> float:
        """Factor on the region's size about its centre."""
        return self._scale

    @scale.setter
    def scale(self, value: float) -> None:
        self._scale = float(value)
        if self.kind == "box" and hasattr(self, "_indices"):
            self._set_limits()

    def _set_limits(self) -> None:
        # plain floats: the box test runs on every agent step, and for a handful of variables
        # Python comparisons are several times faster than numpy calls on tiny arrays
        self._limits = [
            (i, float(c - h * self._scale), float(c + h * self._scale))
            for i, c, h in zip(self._indices, self.center, self.half, strict=True)
        ]

    def inside(self, obs: np.ndarray) -> bool:
        """Whether ``obs`` lies in the region (where the agent explores freely)."""
        if self.kind == "box":
            return all(lo <= obs[i] <= hi for i, lo, hi in self._limits)
        y = np.asarray(obs, dtype=float)[self.index] - self.center
        return bool(y @ self.shape @ y <= self.threshold * self._scale**2)


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


ProgressFn = Callable[[float], float]
"""A value as a function of training progress in [0, 1]; a :class:`pidlab.rl.schedule.Schedule` is one."""


def _check_options(
    mode: str, reward: str, nudge_steps: int, max_coach_steps: int, trigger: GrowthTrigger | None
) -> None:
    """Raise :class:`CoachingError` on options that cannot work together."""
    if mode not in MODES:
        raise CoachingError(f"mode {mode!r}: expected one of {', '.join(MODES)}")
    if reward not in REWARDS:
        raise CoachingError(f"reward {reward!r}: expected one of {', '.join(REWARDS)}")
    if nudge_steps < 1 or max_coach_steps < 1:
        raise CoachingError("nudge_steps and max_coach_steps must be >= 1")
    if trigger is not None and mode == "takeover":
        raise CoachingError(
            "a growth trigger needs mode = nudge: takeover hands back once inside the critical "
            "region, so it is triggered by leaving it"
        )


class CoachingWrapper(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Hide PID-coach interventions inside ``step()``.

    Parameters
    ----------
    env : gymnasium.Env
        A Gymnasium MuJoCo env (usually from ``gymnasium.make``, with its time limit).
    spec : CoachSpec or None
        The coach, with bounds (for the ``exit`` trigger); ``None``: no coach, accounts only.
    mode : {"takeover", "nudge"}
    region : {"box", "ellipsoid"}
    trigger : GrowthTrigger, optional
        The paper's coded trigger (``nudge`` only); default: leaving the critical region.
    nudge_steps : int
        Coach steps per intervention in ``nudge`` mode.
    max_coach_steps : int
        Longest takeover (a coach that cannot bring the state back does not loop forever).
    reward : {"agent", "total"}
    probability : callable, optional
        ``progress -> probability`` of intervening when the trigger fires (default 1).
    width : callable, optional
        ``progress -> factor`` on the region's size (default 1).
    off_after : float, optional
        Progress from which the coach never intervenes.
    loaded : LoadedModel, optional
        The env's model (default: loaded from the spec's env id).
    seed : int, optional
        Seed of the probability schedule's coin (default: the first ``reset`` seed).
    """

    def __init__(
        self,
        env: gym.Env,
        spec: CoachSpec | None,
        mode: str = "takeover",
        region: str = "box",
        trigger: GrowthTrigger | None = None,
        nudge_steps: int = 1,
        max_coach_steps: int = 1000,
        reward: str = "agent",
        probability: ProgressFn | None = None,
        width: ProgressFn | None = None,
        off_after: float | None = None,
        loaded: LoadedModel | None = None,
        seed: int | None = None,
    ) -> None:
        gym.utils.RecordConstructorArgs.__init__(
            self,
            spec=spec,
            mode=mode,
            region=region,
            trigger=trigger,
            nudge_steps=nudge_steps,
            max_coach_steps=max_coach_steps,
            reward=reward,
            probability=probability,
            width=width,
            off_after=off_after,
            loaded=loaded,
            seed=seed,
        )
        gym.Wrapper.__init__(self, env)
        _check_options(mode, reward, nudge_steps, max_coach_steps, trigger)
        self.coach_spec = spec
        self.mode = mode
        self.nudge_steps = nudge_steps
        self.max_coach_steps = max_coach_steps
        self.reward_mode = reward
        self.probability = probability
        self.width = width
        self.off_after = off_after
        self.trigger = trigger
        self.coach: Coach | None = None
        self.region: CriticalRegion | None = None
        if spec is not None:
            env_id = env.spec.id if env.spec is not None else None
            if env_id is not None and env_id != spec.env_id:
                raise CoachingError(f"the spec is for {spec.env_id}, the env is {env_id}")
            self.loaded = loaded if loaded is not None else load_model(spec.env_id)
            card = self.loaded.require_card()
            names = card.observation_names
            self.coach = Coach(spec, self.loaded)
            if trigger is None:
                self.region = CriticalRegion(spec, names, region)
            else:
                self._trigger_index = _index(trigger.variable, names, "growth trigger")
        self._history: deque[float] = deque(maxlen=(trigger.steps + 1) if trigger else 1)
        self.progress = 0.0
        self._rng = np.random.default_rng(seed)
        self._seeded = seed is not None
        self._reset_counters()
        self.total_agent_steps = 0
        self.total_coach_steps = 0
        self.total_interventions = 0

    @property
    def coached(self) -> bool:
        """Whether there is a coach at all."""
        return self.coach is not None

    def _reset_counters(self) -> None:
        self.episode_agent_steps = 0
        self.episode_coach_steps = 0
        self.episode_interventions = 0
        self.episode_agent_return = 0.0
        self.episode_coach_return = 0.0

    def set_progress(self, progress: float) -> None:
        """Training progress in [0, 1] (fraction of the budget spent), read by the schedules."""
        self.progress = float(min(max(progress, 0.0), 1.0))
        if self.region is not None:
            self.region.scale = 1.0 if self.width is None else float(self.width(self.progress))

    def intervention_probability(self) -> float:
        """Probability of intervening when the trigger fires, now."""
        if self.coach is None or (self.off_after is not None and self.progress >= self.off_after):
            return 0.0
        return 1.0 if self.probability is None else float(self.probability(self.progress))

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict]:
        """Reset the env and the episode's counters."""
        if seed is not None and not self._seeded:
            self._rng = np.random.default_rng(seed)
            self._seeded = True
        obs, info = self.env.reset(seed=seed, options=options)
        self._reset_counters()
        self._history.clear()
        self._observe(obs)
        return obs, info

    def _observe(self, obs: np.ndarray) -> None:
        if self.trigger is not None:
            self._history.append(float(np.asarray(obs)[self._trigger_index]))

    def _triggered(self, obs: np.ndarray) -> bool:
        if self.coach is None:
            return False
        if self.trigger is not None:
            fired = self.trigger.fires(self._history)
        elif self.region is not None:
            fired = not self.region.inside(obs)
        else:  # a coach always has a trigger or a region (see __init__)
            return False
        if not fired:
            return False
        p = self.intervention_probability()
        return p >= 1.0 or (p > 0.0 and self._rng.random() < p)

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        """One agent step, then the coach's steps if the trigger fired."""
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._observe(obs)
        self.episode_agent_steps += 1
        self.total_agent_steps += 1
        self.episode_agent_return += float(reward)
        coach_steps = 0
        coach_reward = 0.0
        coach = self.coach
        intervened = not (terminated or truncated) and self._triggered(obs)
        if intervened and coach is not None:  # _triggered is False without a coach
            self.episode_interventions += 1
            self.total_interventions += 1
            coach.reset(obs)
            limit = self.nudge_steps if self.mode == "nudge" else self.max_coach_steps
            while coach_steps < limit:
                obs, r, terminated, truncated, _ = self.env.step(coach.act(obs))
                self._observe(obs)
                coach_steps += 1
                coach_reward += float(r)
                if terminated or truncated:
                    break
                if self.mode == "takeover" and self.region is not None and self.region.inside(obs):
                    break
        self.episode_coach_steps += coach_steps
        self.total_coach_steps += coach_steps
        self.episode_coach_return += coach_reward
        info = dict(info)
        # per step, and the episode so far (deterministic given the reset); lifetime totals are
        # attributes: total_agent_steps, total_coach_steps, total_interventions
        info.update({
            "agent_reward": float(reward),
            "coach_reward": coach_reward,
            "coach_steps": coach_steps,
            "intervened": bool(intervened),
            "episode_agent_steps": self.episode_agent_steps,
            "episode_coach_steps": self.episode_coach_steps,
            "episode_env_steps": self.episode_agent_steps + self.episode_coach_steps,
            "episode_interventions": self.episode_interventions,
            "episode_agent_return": self.episode_agent_return,
            "episode_total_return": self.episode_agent_return + self.episode_coach_return,
        })  # fmt: skip
        if terminated or truncated:
            info["coaching_episode"] = {
                "agent_steps": self.episode_agent_steps,
                "coach_steps": self.episode_coach_steps,
                "env_steps": self.episode_agent_steps + self.episode_coach_steps,
                "interventions": self.episode_interventions,
                "agent_return": self.episode_agent_return,
                "coach_return": self.episode_coach_return,
                "total_return": self.episode_agent_return + self.episode_coach_return,
                "terminated": bool(terminated),
            }
        out_reward = float(reward) + (coach_reward if self.reward_mode == "total" else 0.0)
        return obs, out_reward, terminated, truncated, info
