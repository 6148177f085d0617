"""The coach alone on the real Gymnasium env: scores and how it fails.

This is the paper's Table I "PID score", measured over many seeds rather than once: each
episode starts from ``env.reset(seed=seed0 + i)`` and the coach acts until the env terminates
or its time limit truncates the episode.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from pidlab.checks import instance, shown
from pidlab.controller.pid import Coach
from pidlab.controller.spec import CoachSpec
from pidlab.errors import ArgumentError, BudgetError
from pidlab.plant.envs import make_coach_env
from pidlab.plant.model import LoadedModel
from pidlab.plant.observation import check_termination

MAX_EPISODES = 10_000
"""The most coach-alone episodes :func:`coach_alone` runs at once (about 15 minutes of 1000-step
episodes on one core); more would run for hours without adding precision to a mean return."""


def check_episodes(episodes: object, param: str = "episodes") -> int:
    """``episodes`` as an int from 1 to :data:`MAX_EPISODES`, or a :class:`BudgetError` saying so.

    Raises
    ------
    ArgumentError
        ``episodes`` is not an int (a bool is not); a ``TypeError`` too.
    BudgetError
        ``episodes`` is below 1 or above :data:`MAX_EPISODES`.
    """
    if isinstance(episodes, bool) or not isinstance(episodes, (int, np.integer)):
        raise ArgumentError(f"{param}={shown(episodes)}: expected an int", param=param)
    if not 1 <= episodes <= MAX_EPISODES:
        raise BudgetError(
            f"{param}={episodes!r}: expected 1 to {MAX_EPISODES:,} episodes (more would run for hours)",
            param=param,
        )
    return int(episodes)


@dataclass(frozen=True)
class Episode:
    """One coach-alone episode.

    Attributes
    ----------
    seed : int
    episode_return : float
    length : int
        Steps taken.
    terminated, truncated : bool
    cause : str
        ``"time limit"``, or the termination limits violated (e.g.
        ``"hinge_pos outside [-0.2, 0.2]"``), or ``"non-finite observation"``.
    saturated_fraction : float
        Fraction of steps with at least one actuator at its limit.
    """

    seed: int
    episode_return: float
    length: int
    terminated: bool
    truncated: bool
    cause: str
    saturated_fraction: float


@dataclass(frozen=True)
class CoachScore:
    """Summary of coach-alone episodes.

    Attributes
    ----------
    env_id, spec_name : str
    episodes : tuple of Episode
    """

    env_id: str
    spec_name: str
    episodes: tuple[Episode, ...]

    @property
    def returns(self) -> np.ndarray:
        """Episode returns, shape ``(n,)``."""
        return np.array([e.episode_return for e in self.episodes])

    @property
    def mean(self) -> float:
        """Mean return."""
        return float(self.returns.mean())

    @property
    def std(self) -> float:
        """Standard deviation of the return (ddof=1; 0 for one episode)."""
        return float(self.returns.std(ddof=1)) if len(self.episodes) > 1 else 0.0

    @property
    def causes(self) -> dict[str, int]:
        """How many episodes ended for each cause."""
        return dict(Counter(e.cause for e in self.episodes))

    @property
    def mean_length(self) -> float:
        """Mean episode length, steps."""
        return float(np.mean([e.length for e in self.episodes]))


def termination_cause(loaded: LoadedModel, env: gym.Env) -> str:
    """Why ``env`` terminated, in the words of :attr:`Episode.cause`.

    Call it right after a step that returned ``terminated=True``: it reads the env's current
    MuJoCo state against the model card's termination limits.

    Parameters
    ----------
    loaded : LoadedModel
        The model of ``env``, with a model card.
    env : gymnasium.Env
        A MuJoCo env (``env.unwrapped`` has ``model`` and ``data``).

    Returns
    -------
    str
        ``"non-finite observation"``; or the violated limits joined by ``"; "``, e.g.
        ``"hinge_pos outside [-0.2, 0.2]"``; or ``"terminated (no card limit violated)"``.
    """
    card = loaded.require_card()
    u = env.unwrapped
    check = check_termination(card, u.model, u.data)  # type: ignore[attr-defined]
    if check.nonfinite:
        return "non-finite observation"
    parts = []
    for limit in check.violated:
        parts.append(f"{limit.signal} outside [{limit.low:g}, {limit.high:g}]")
    return "; ".join(parts) if parts else "terminated (no card limit violated)"


def coach_alone(
    spec: CoachSpec,
    loaded: LoadedModel,
    episodes: int = 10,
    seed0: int = 0,
    max_steps: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> CoachScore:
    """Run the coach alone on the real env for ``episodes`` seeded episodes.

    Parameters
    ----------
    spec : CoachSpec
    loaded : LoadedModel
    episodes : int
        1 to :data:`MAX_EPISODES`.
    seed0 : int
        Episode ``i`` is reset with ``seed0 + i``.
    max_steps : int, optional
        Time limit (default: the env's own, 1000 for the paper envs).
    progress : callable, optional
        ``progress(done, episodes)`` after each episode (e.g. to move a progress bar).

    Returns
    -------
    CoachScore

    Raises
    ------
    BudgetError
        ``episodes`` is outside 1 to :data:`MAX_EPISODES`.
    """
    episodes = check_episodes(episodes)
    instance(spec, CoachSpec, "spec")
    instance(loaded, LoadedModel, "loaded")
    limit = {} if max_steps is None else {"max_episode_steps": max_steps}
    env = make_coach_env(spec.env_id, **limit)
    coach = Coach(spec, loaded)
    lay = coach.layout
    out = []
    try:
        for i in range(episodes):
            obs, _ = env.reset(seed=seed0 + i)
            coach.reset(obs)
            total, steps, saturated = 0.0, 0, 0
            terminated = truncated = False
            while not (terminated or truncated):
                u = coach.act(obs)
                saturated += bool(np.any((u <= lay.ctrl_low) | (u >= lay.ctrl_high)))
                obs, reward, terminated, truncated, _ = env.step(u)
                total += float(reward)
                steps += 1
            cause = termination_cause(loaded, env) if terminated else "time limit"
            out.append(
                Episode(
                    seed0 + i,
                    total,
                    steps,
                    bool(terminated),
                    bool(truncated),
                    cause,
                    saturated / max(steps, 1),
                )
            )
            if progress is not None:
                progress(i + 1, episodes)
    finally:
        env.close()
    return CoachScore(env_id=spec.env_id, spec_name=spec.name, episodes=tuple(out))
