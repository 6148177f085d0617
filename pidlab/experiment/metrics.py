"""Learning-speed metrics of one training run: the paper's and the honest ones.

The paper's metrics read the *training* returns, episode by episode, as the paper did: with a
coach in the loop those episodes are coach-assisted (the coach keeps them alive). The honest
metrics read the agent-alone evaluations (coach off, deterministic policy) and count the
environment steps the coach spent too.

All functions are pure; :func:`run_metrics` bundles them for one run's logs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

Values = Sequence[float] | np.ndarray


def episodes_to_consecutive_wins(returns: Values, target: float, consecutive: int = 5) -> int | None:
    """The episode (1-based) at which ``consecutive`` episodes in a row have scored ``>= target``.

    Parameters
    ----------
    returns : sequence of float
        Training returns in episode order.
    target : float
    consecutive : int

    Returns
    -------
    int or None
        The episode number of the last win of the first such streak; None if there is none.

    Examples
    --------
    >>> episodes_to_consecutive_wins([900, 100, 900, 900, 900, 900, 900], 800, 5)
    7
    """
    streak = 0
    for i, r in enumerate(returns):
        streak = streak + 1 if r >= target else 0
        if streak >= consecutive:
            return i + 1
    return None


def moving_average(values: Values, window: int) -> np.ndarray:
    """Trailing mean over ``window`` values; the first ``window - 1`` entries average what exists."""
    x = np.asarray(values, dtype=float)
    if x.size == 0:
        return x
    c = np.cumsum(np.insert(x, 0, 0.0))
    n = np.arange(1, x.size + 1)
    lo = np.maximum(n - window, 0)
    return (c[n] - c[lo]) / (n - lo)


def episodes_to_average(returns: Values, target: float, window: int) -> int | None:
    """The first episode (1-based) at which the mean of the last ``window`` returns is ``>= target``.

    Only full windows count: the first candidate is episode ``window`` (a short first window would let
    one lucky early episode count as learning).

    Examples
    --------
    >>> episodes_to_average([0, 1000, 1000, 1000], 800, 2)
    3
    """
    x = np.asarray(returns, dtype=float)
    if x.size < window:
        return None
    avg = moving_average(x, window)[window - 1 :]
    hit = np.flatnonzero(avg >= target)
    return int(hit[0]) + window if hit.size else None


def first_reaching(xs: Values, ys: Values, target: float) -> float | None:
    """The first ``x`` whose ``y`` is ``>= target`` (e.g. env steps at which an evaluation reached it)."""
    for x, y in zip(xs, ys, strict=True):
        if y >= target:
            return float(x)
    return None


@dataclass(frozen=True)
class RunMetrics:
    """What one run says about learning speed (None: never reached within the run).

    Attributes
    ----------
    episodes_to_wins : int or None
        The paper's: training episodes until ``consecutive`` wins in a row (coach-assisted returns).
    episodes_to_average : int or None
        The paper's: training episodes until the moving average over ``window`` reaches the target.
    env_steps_to_target, agent_steps_to_target : float or None
        Honest: env steps (agent + coach) and agent steps until the agent-alone evaluation reached
        the target.
    final_score : float
        Honest: mean return of the last agent-alone evaluation.
    final_training_score : float
        Mean training return (agent reward, coach-assisted episodes) over the last ``window`` episodes.
    final_coached_score : float
        Mean return *with the coach* (every step's reward, the coach's included) over the last
        ``window`` training episodes: how the agent and its coach score together.
    coach_dependent : bool
        The agent scores well with its coach (``final_coached_score >= target``) but not alone
        (final agent-alone score ``< target``).
    intervention_rate : float
        Coach steps / env steps over the whole run.
    episodes, env_steps, agent_steps, coach_steps : int
        Totals of the run.
    """

    episodes_to_wins: int | None
    episodes_to_average: int | None
    env_steps_to_target: float | None
    agent_steps_to_target: float | None
    final_score: float
    final_training_score: float
    final_coached_score: float
    coach_dependent: bool
    intervention_rate: float
    episodes: int
    env_steps: int
    agent_steps: int
    coach_steps: int


def run_metrics(
    returns: Values,
    eval_env_steps: Values,
    eval_agent_steps: Values,
    eval_means: Values,
    env_steps: int,
    agent_steps: int,
    coach_steps: int,
    target: float,
    consecutive: int,
    window: int,
    coached_returns: Values | None = None,
) -> RunMetrics:
    """All metrics of one run from its training returns and its agent-alone evaluations.

    Parameters
    ----------
    returns : sequence of float
        Training returns per episode (what the agent was paid; the paper's score).
    eval_env_steps, eval_agent_steps, eval_means : sequence of float
        Per agent-alone evaluation: env steps and agent steps so far, mean return.
    env_steps, agent_steps, coach_steps : int
        The run's totals.
    target : float
        The win target.
    consecutive, window : int
        The paper's streak length and moving-average window.
    coached_returns : sequence of float, optional
        Per episode, the return with the coach's steps included (default: ``returns``).
    """
    final = float(eval_means[-1]) if len(eval_means) else float("nan")
    tail = np.asarray(returns[-window:], dtype=float)
    training = float(tail.mean()) if tail.size else float("nan")
    both = np.asarray((returns if coached_returns is None else coached_returns)[-window:], dtype=float)
    coached = float(both.mean()) if both.size else float("nan")
    return RunMetrics(
        episodes_to_wins=episodes_to_consecutive_wins(returns, target, consecutive),
        episodes_to_average=episodes_to_average(returns, target, window),
        env_steps_to_target=first_reaching(eval_env_steps, eval_means, target),
        agent_steps_to_target=first_reaching(eval_agent_steps, eval_means, target),
        final_score=final,
        final_training_score=training,
        final_coached_score=coached,
        coach_dependent=bool(coach_steps > 0 and coached >= target and not final >= target),
        intervention_rate=coach_steps / env_steps if env_steps else 0.0,
        episodes=len(returns),
        env_steps=int(env_steps),
        agent_steps=int(agent_steps),
        coach_steps=int(coach_steps),
    )
