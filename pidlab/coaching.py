"""The coaching wrapper: the PID coach takes over outside the critical region, hidden from the agent.

:class:`CoachingWrapper` is a ``gymnasium.Wrapper``. Coach steps run *inside* ``step()``: the
agent acts at ``s_t``, and the observation it gets back is the state after the coach handed
control back. Any SB3 algorithm therefore stores only the agent's own transitions.

Intervention modes
    ``takeover`` (the paper's text): after an agent step that leaves the critical region, the
    coach acts until the state is back inside (or the episode ends, or ``max_coach_steps``).
    ``nudge`` (the paper's original code): when the trigger fires, exactly ``nudge_steps``
    coach steps.

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
    ``schedule(progress) -> probability`` of intervening when the trigger fires; call
    :meth:`CoachingWrapper.set_progress` (e.g. from a training callback) to fade coaching out.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

from pidlab.errors import PidlabError
from pidlab.model import LoadedModel, load_model
from pidlab.pid import Coach
from pidlab.spec import CoachSpec

MODES = ("takeover", "nudge")
REGIONS = ("box", "ellipsoid")


class CoachingError(PidlabError, ValueError):
    """A coaching configuration that cannot work (no bounds, unknown mode, wrong env)."""


class CriticalRegion:
    """Membership test of the critical region, in observation variables.

    Parameters
    ----------
    spec : CoachSpec
        With a ``[bounds]`` table.
    observation_names : tuple of str
    kind : {"box", "ellipsoid"}
    scale : float
        Shrinks (< 1) or widens (> 1) the region about its centre (a schedule may use it).
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
            self.index = np.array([observation_names.index(v) for v in box])
            lo = np.array([v[0] for v in box.values()])
            hi = np.array([v[1] for v in box.values()])
            self.center = 0.5 * (lo + hi)
            self.half = 0.5 * (hi - lo)
        else:
            e = b.get("ellipsoid")
            if not e:
                raise CoachingError(
                    f"{spec.name}: the spec has no [bounds.ellipsoid]; run `pidlab bounds SPEC --write`"
                )
            self.index = np.array([observation_names.index(v) for v in e["variables"]])
            self.center = np.array(e["center"], dtype=float)
            self.shape = np.array(e["shape"], dtype=float)
            self.threshold = float(e["rho"]) * float(e["level"])

    def inside(self, obs: np.ndarray) -> bool:
        """Whether ``obs`` lies in the region (where the agent explores freely)."""
        y = np.asarray(obs, dtype=float)[self.index] - self.center
        if self.kind == "box":
            return bool(np.all(np.abs(y) <= self.half * self.scale))
        return bool(y @ self.shape @ y <= self.threshold * self.scale**2)


class CoachingWrapper(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Hide PID-coach interventions inside ``step()``.

    Parameters
    ----------
    env : gymnasium.Env
        A Gymnasium MuJoCo env (usually from ``gymnasium.make``, with its time limit).
    spec : CoachSpec
        The coach, with bounds.
    mode : {"takeover", "nudge"}
    region : {"box", "ellipsoid"}
    nudge_steps : int
        Coach steps per intervention in ``nudge`` mode.
    max_coach_steps : int
        Longest takeover (a coach that cannot bring the state back does not loop forever).
    reward : {"agent", "total"}
    schedule : callable, optional
        ``progress in [0, 1] -> probability`` of intervening; default always 1.
    loaded : LoadedModel, optional
        The env's model (default: loaded from the spec's env id).
    seed : int, optional
        Seed of the schedule's coin (default: the first ``reset`` seed).
    """

    def __init__(
        self,
        env: gym.Env,
        spec: CoachSpec,
        mode: str = "takeover",
        region: str = "box",
        nudge_steps: int = 1,
        max_coach_steps: int = 1000,
        reward: str = "agent",
        schedule: Callable[[float], float] | None = None,
        loaded: LoadedModel | None = None,
        seed: int | None = None,
    ) -> None:
        gym.utils.RecordConstructorArgs.__init__(
            self,
            spec=spec,
            mode=mode,
            region=region,
            nudge_steps=nudge_steps,
            max_coach_steps=max_coach_steps,
            reward=reward,
            schedule=schedule,
            loaded=loaded,
            seed=seed,
        )
        gym.Wrapper.__init__(self, env)
        if mode not in MODES:
            raise CoachingError(f"mode {mode!r}: expected one of {', '.join(MODES)}")
        if reward not in ("agent", "total"):
            raise CoachingError(f"reward {reward!r}: expected agent or total")
        if nudge_steps < 1 or max_coach_steps < 1:
            raise CoachingError("nudge_steps and max_coach_steps must be >= 1")
        env_id = env.spec.id if env.spec is not None else None
        if env_id is not None and env_id != spec.env_id:
            raise CoachingError(f"the spec is for {spec.env_id}, the env is {env_id}")
        self.loaded = loaded if loaded is not None else load_model(spec.env_id)
        assert self.loaded.card is not None
        self.coach = Coach(spec, self.loaded)
        self.region = CriticalRegion(spec, self.loaded.card.observation_names, region)
        self.mode = mode
        self.nudge_steps = nudge_steps
        self.max_coach_steps = max_coach_steps
        self.reward_mode = reward
        self.schedule = schedule
        self.progress = 0.0
        self._rng = np.random.default_rng(seed)
        self._seeded = seed is not None
        self._reset_counters()
        self.total_agent_steps = 0
        self.total_coach_steps = 0
        self.total_interventions = 0

    def _reset_counters(self) -> None:
        self.episode_agent_steps = 0
        self.episode_coach_steps = 0
        self.episode_interventions = 0
        self.episode_agent_return = 0.0
        self.episode_coach_return = 0.0

    def set_progress(self, progress: float) -> None:
        """Training progress in [0, 1], read by the schedule."""
        self.progress = float(min(max(progress, 0.0), 1.0))

    def intervention_probability(self) -> float:
        """Probability of intervening when the trigger fires, now."""
        return 1.0 if self.schedule is None else float(self.schedule(self.progress))

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict]:
        """Reset the env and the episode's counters."""
        if seed is not None and not self._seeded:
            self._rng = np.random.default_rng(seed)
            self._seeded = True
        obs, info = self.env.reset(seed=seed, options=options)
        self._reset_counters()
        self._last_obs = obs
        return obs, info

    def _triggered(self, obs: np.ndarray) -> bool:
        if self.region.inside(obs):
            return False
        p = self.intervention_probability()
        return p >= 1.0 or (p > 0.0 and self._rng.random() < p)

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        """One agent step, then the coach's steps if the state left the critical region."""
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.episode_agent_steps += 1
        self.total_agent_steps += 1
        self.episode_agent_return += float(reward)
        coach_steps = 0
        coach_reward = 0.0
        if not (terminated or truncated) and self._triggered(obs):
            self.episode_interventions += 1
            self.total_interventions += 1
            self.coach.reset(obs)
            limit = self.nudge_steps if self.mode == "nudge" else self.max_coach_steps
            while coach_steps < limit:
                obs, r, terminated, truncated, _ = self.env.step(self.coach.act(obs))
                coach_steps += 1
                coach_reward += float(r)
                if terminated or truncated or (self.mode == "takeover" and self.region.inside(obs)):
                    break
        self.episode_coach_steps += coach_steps
        self.total_coach_steps += coach_steps
        self.episode_coach_return += coach_reward
        info = dict(info)
        # per step, and the episode so far (deterministic given the reset; lifetime totals are
        # attributes: total_agent_steps, total_coach_steps, total_interventions)
        info.update({
            "agent_reward": float(reward),
            "coach_reward": coach_reward,
            "coach_steps": coach_steps,
            "episode_agent_steps": self.episode_agent_steps,
            "episode_coach_steps": self.episode_coach_steps,
            "episode_env_steps": self.episode_agent_steps + self.episode_coach_steps,
            "episode_interventions": self.episode_interventions,
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
            }
        out_reward = float(reward) + (coach_reward if self.reward_mode == "total" else 0.0)
        self._last_obs = obs
        return obs, out_reward, terminated, truncated, info
