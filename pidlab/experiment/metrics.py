"""Learning-speed metrics of one training run: the paper's and the honest ones.

The paper's metrics read the *training* returns, episode by episode, as the paper did: with a
coach in the loop those episodes are coach-assisted (the coach keeps them alive). A coach's steps
count toward the env's time limit but pay the agent nothing, so a coached episode's training return
is capped at the time limit minus its coach steps (InvertedPendulum: 1000 - coach steps): a light
coach makes wins easier (episodes stay alive), a heavy one makes them impossible. The same measures
are therefore also read from the returns *with* the coach's rewards, which have no such cap.

The honest metrics read the agent-alone evaluations (coach off, deterministic policy) and count the
environment steps the coach spent too. "Reached the target" means reached and kept to the end of
the run (:func:`sustained_hit`), and runs are compared at the evaluation grid point
(:func:`grid_points`), so that two runs reaching it at the same evaluation tie.

All functions are pure; :func:`run_metrics` bundles them for one run's logs (:class:`RunLogs`).
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
    """The first ``x`` whose ``y`` is ``>= target`` (a first hit, transient or not)."""
    for x, y in zip(xs, ys, strict=True):
        if y >= target:
            return float(x)
    return None


def first_hit(means: Values, target: float) -> int | None:
    """Index of the first evaluation whose mean return is ``>= target`` (it may not last).

    Examples
    --------
    >>> first_hit([10, 900, 20, 950], 800)
    1
    """
    hits = np.flatnonzero(np.asarray(means, dtype=float) >= target)
    return int(hits[0]) if hits.size else None


def sustained_hit(means: Values, target: float) -> int | None:
    """Index of the first evaluation from which every evaluation, to the last, is ``>= target``.

    This is what "reached the target" means in pidlab: the agent alone reached it and kept it
    until the end of the run. A transient hit, lost again at a later evaluation, does not count.
    A run counted as reached therefore ends with a final score ``>= target``, and a run whose
    final score is ``>= target`` has reached it (at its last evaluation at the latest).

    Examples
    --------
    >>> sustained_hit([10, 900, 20, 950, 1000], 800)
    3
    >>> sustained_hit([10, 900, 20], 800) is None
    True
    """
    below = np.flatnonzero(~(np.asarray(means, dtype=float) >= target))
    n = len(means)
    start = int(below[-1]) + 1 if below.size else 0
    return start if start < n else None


def grid_points(env_steps: Values, every: int, budget: int) -> np.ndarray:
    """The point each evaluation was due at: ``floor(env_steps / every) * every``, or the budget.

    An evaluation due at ``k * every`` env steps runs at the first step at or after it; when a coach
    step crosses the point it runs a few steps late (10,003 for 10,000). Two runs evaluated at the
    same grid point were evaluated at the same point of their budgets, and tie. The final
    evaluation, at the end of the budget, is due at the budget (50,000 with ``every`` 20,000).

    Examples
    --------
    >>> grid_points([0, 5000, 10003], 5000, 100000).tolist()
    [0, 5000, 10000]
    >>> grid_points([0, 20000, 40000, 50000], 20000, 50000).tolist()
    [0, 20000, 40000, 50000]
    """
    x = np.asarray(env_steps, dtype=np.int64)
    return np.where(x >= int(budget), int(budget), (x // int(every)) * int(every))


@dataclass(frozen=True)
class Rule:
    """What counts as reaching the target.

    Attributes
    ----------
    target : float
        The return that counts (the paper's win target).
    consecutive : int
        The paper's streak of wins.
    window : int
        The paper's moving-average window, episodes.
    every : int
        Env steps between agent-alone evaluations (the evaluation grid).
    budget : int
        The run's budget, env steps (its final evaluation is due there).
    alone_target : float or None
        The agent-alone target of the analysis plan (:mod:`pidlab.experiment.plan`) when it
        differs from ``target`` (Hopper and Walker2d: a return that standing still cannot reach);
        None: ``target``.
    """

    target: float
    consecutive: int
    window: int
    every: int
    budget: int
    alone_target: float | None = None

    @property
    def agent_target(self) -> float:
        """The return the agent alone must reach and keep (the primary target)."""
        return self.target if self.alone_target is None else self.alone_target


@dataclass(frozen=True)
class RunLogs:
    """One run's logs, as :mod:`pidlab.rl.train` writes them.

    Attributes
    ----------
    returns : ndarray
        Training return per episode: what the agent was paid on its own steps.
    coached_returns : ndarray
        The same episodes' returns with the coach's steps' rewards included.
    episode_env_steps : ndarray
        Env steps so far at the end of each episode.
    episode_coach_steps : ndarray
        The coach's steps in each episode.
    eval_env_steps, eval_agent_steps : ndarray
        Env and agent steps so far at each agent-alone evaluation.
    eval_means : ndarray
        Mean return of each evaluation.
    eval_steps : ndarray
        Env steps each evaluation spent (its episodes' lengths summed); not charged to the budget.
    env_steps, agent_steps, coach_steps : int
        The run's totals.
    policy_updates : int or None
        Gradient steps of the policy's optimizer (None: not recorded by the run).
    falls : int or None
        Terminations of the training env, whoever was acting (None: unknown).
    env_resets : int or None
        Real resets of the training envs (None: unknown).
    env_episodes_ended : ndarray or None
        Env episodes ended so far at the end of each training episode (None: every training
        episode ended its env's episode, as before the ``terminal`` view).
    episode_agent_steps : ndarray or None
        Agent steps of each training episode (None: not read).
    episode_runs : ndarray or None
        The agent's uninterrupted runs in each training episode (``nan``: not logged).
    eval_wall_s : ndarray or None
        Wall-clock seconds since the run started at each evaluation (``nan``: not logged).
    warm_start_at : int or None
        Env steps when the warm start ended (``warm_start.json``; None: no warm start).
    """

    returns: np.ndarray
    coached_returns: np.ndarray
    episode_env_steps: np.ndarray
    episode_coach_steps: np.ndarray
    eval_env_steps: np.ndarray
    eval_agent_steps: np.ndarray
    eval_means: np.ndarray
    eval_steps: np.ndarray
    env_steps: int
    agent_steps: int
    coach_steps: int
    policy_updates: int | None
    falls: int | None = None
    env_resets: int | None = None
    env_episodes_ended: np.ndarray | None = None
    episode_agent_steps: np.ndarray | None = None
    episode_runs: np.ndarray | None = None
    eval_wall_s: np.ndarray | None = None
    warm_start_at: int | None = None

    @property
    def env_episode_counts(self) -> np.ndarray:
        """Env episodes ended so far at the end of each training episode."""
        if self.env_episodes_ended is None:
            return np.arange(1, len(self.returns) + 1)
        return self.env_episodes_ended


@dataclass(frozen=True)
class RunMetrics:
    """What one run says about learning speed (None: never reached within the run).

    Attributes
    ----------
    episodes_to_wins : int or None
        The paper's: training episodes until ``consecutive`` wins in a row, on training returns
        (the agent's reward only; with a coach, capped at the time limit minus the coach's steps).
    episodes_to_average : int or None
        The paper's: training episodes until the moving average over ``window`` reaches the target,
        on training returns.
    episodes_to_wins_with_coach, episodes_to_average_with_coach : int or None
        The same two measures on the returns with the coach's rewards included (no cap).
    env_steps_to_target : float or None
        Honest: the grid point (env steps, agent + coach) of the evaluation from which the agent
        alone scores ``>= target`` to the end of the run (:func:`sustained_hit`).
    agent_steps_to_target : float or None
        Agent steps at that same evaluation.
    first_hit_env_steps : float or None
        The grid point of the first evaluation at the target, even if the hit did not last.
    final_score : float
        Honest: mean return of the last agent-alone evaluation.
    final_training_score : float
        Mean training return over the last ``window`` episodes.
    final_coached_score : float
        Mean return *with the coach* over the last ``window`` training episodes.
    coach_dependent : bool
        A trained agent (at least one policy update) that scores well with its coach
        (``final_coached_score >= target``) but not alone (final score ``< target``).
    never_trained : bool
        The run made no policy update (``policy_updates == 0``): its agent is the initial policy.
    intervention_rate : float
        Coach steps / env steps over the whole run.
    episodes, env_steps, agent_steps, coach_steps : int
        Totals of the run.
    policy_updates : int or None
        Gradient steps of the policy (None: not recorded).
    evaluation_env_steps : int
        Env steps spent by agent-alone evaluations, not charged to the budget.
    evaluation_delay : int
        The largest distance, env steps, between an evaluation and its grid point.
    env_steps_per_episode : float
        Mean training episode length, env steps (agent + coach).
    falls : int or None
        Failures during training: terminations of the real env, whoever was acting (agent or
        coach). An agent episode ended by a ``terminal``-view takeover whose rescue succeeded is
        not one. None: not recorded.
    env_resets : int or None
        Real resets of the training envs (each env's first reset of every session included; a
        ``terminal``-view rescue that hands the running env to a new agent episode is none).
        None: not recorded.
    env_episodes_to_wins, env_episodes_to_average : int or None
        The paper's two measures counted in **env** episodes: the env episodes that had ended when
        the training episodes first met the criterion (under the ``terminal`` view a veto ends an
        agent episode but not the env's).
    env_steps_to_alone_target : float or None
        As ``env_steps_to_target``, at the agent-alone target of the analysis plan
        (:attr:`Rule.agent_target`; the win target on the pendulums).
    env_episodes : int or None
        Env episodes that ended during training.
    mean_run_length : float or None
        The agent's mean uninterrupted run, agent actions: its steps over its runs, in the training
        episodes that logged runs (None: none did). A takeover or veto ends a run, and so does an
        episode's end.
    clone_score : float or None
        The agent alone right after a warm start, before any RL update (None: no warm start).
    dip_score : float or None
        The lowest agent-alone score over the :data:`DIP_EVALUATIONS` evaluations after it: the
        "unlearning dip" of RL fine-tuning from a clone (None: no warm start, or none after it).
    wall_s_to_alone_target : float or None
        Wall-clock seconds since the run started (demonstrations, cloning and evaluations included)
        at the evaluation of ``env_steps_to_alone_target`` (``inf``: not reached; None: the run did
        not log its timing).
    """

    episodes_to_wins: int | None
    episodes_to_average: int | None
    episodes_to_wins_with_coach: int | None
    episodes_to_average_with_coach: int | None
    env_steps_to_target: float | None
    agent_steps_to_target: float | None
    first_hit_env_steps: float | None
    final_score: float
    final_training_score: float
    final_coached_score: float
    coach_dependent: bool
    never_trained: bool
    intervention_rate: float
    episodes: int
    env_steps: int
    agent_steps: int
    coach_steps: int
    policy_updates: int | None
    evaluation_env_steps: int
    evaluation_delay: int
    env_steps_per_episode: float
    falls: int | None = None
    env_resets: int | None = None
    env_episodes_to_wins: int | None = None
    env_episodes_to_average: int | None = None
    env_steps_to_alone_target: float | None = None
    env_episodes: int | None = None
    mean_run_length: float | None = None
    wall_s_to_alone_target: float | None = None
    clone_score: float | None = None
    dip_score: float | None = None


DIP_EVALUATIONS = 5
"""Evaluations after a warm start over which its unlearning dip is read."""


def warm_start_scores(
    eval_env_steps: np.ndarray, eval_agent_steps: np.ndarray, eval_means: np.ndarray, at: int | None,
    after: int = DIP_EVALUATIONS,
) -> tuple[float | None, float | None]:  # fmt: skip
    """The agent-alone score right after a warm start, and the lowest of the ``after`` that follow.

    The warm start's evaluation is the last one at env step ``at`` with no agent step yet.

    Examples
    --------
    >>> warm_start_scores(np.array([0, 500, 500, 1000, 1500]), np.array([0, 0, 0, 400, 900]),
    ...                   np.array([9.0, 30.0, 1000.0, 120.0, 700.0]), at=500)
    (1000.0, 120.0)
    """
    if at is None:
        return None, None
    rows = np.flatnonzero((eval_env_steps == at) & (eval_agent_steps == 0))
    if rows.size == 0:
        return None, None
    i = int(rows[-1])
    later = eval_means[i + 1 : i + 1 + after]
    return float(eval_means[i]), (float(np.min(later)) if later.size else None)


def _tail_mean(values: np.ndarray, window: int) -> float:
    tail = np.asarray(values[-window:], dtype=float)
    return float(tail.mean()) if tail.size else float("nan")


def _at(values: np.ndarray, index: int | None) -> float | None:
    return None if index is None else float(values[index])


def _env_episodes_at(logs: RunLogs, episode: int | None) -> int | None:
    """Env episodes ended by the end of training episode ``episode`` (1-based; None stays None)."""
    return None if episode is None else int(logs.env_episode_counts[episode - 1])


def mean_run_length(agent_steps: np.ndarray | None, runs: np.ndarray | None) -> float | None:
    """Agent steps per uninterrupted run over the episodes whose runs are known (None: none are).

    Parameters
    ----------
    agent_steps, runs : ndarray, shape (n_episodes,)
        Per training episode; ``runs`` is ``nan`` where the log did not record it.

    Examples
    --------
    >>> mean_run_length(np.array([6.0, 4.0, 9.0]), np.array([2.0, 3.0, np.nan]))
    2.0
    """
    if agent_steps is None or runs is None:
        return None
    known = np.isfinite(runs)
    total = float(np.sum(runs[known]))
    return float(np.sum(agent_steps[known])) / total if total > 0 else None


def _wall_at(logs: RunLogs, index: int | None) -> float | None:
    """Wall-clock seconds at evaluation ``index`` (``inf``: never reached; None: not logged)."""
    wall = logs.eval_wall_s
    if wall is None or not np.any(np.isfinite(wall)):
        return None
    if index is None:
        return float("inf")
    return float(wall[index]) if np.isfinite(wall[index]) else None


def run_metrics(logs: RunLogs, rule: Rule) -> RunMetrics:
    """All metrics of one run from its logs.

    Parameters
    ----------
    logs : RunLogs
    rule : Rule

    Returns
    -------
    RunMetrics
    """
    final = float(logs.eval_means[-1]) if len(logs.eval_means) else float("nan")
    coached = _tail_mean(logs.coached_returns, rule.window)
    grid = grid_points(logs.eval_env_steps, rule.every, rule.budget)
    reached = sustained_hit(logs.eval_means, rule.target)
    wins = episodes_to_consecutive_wins(logs.returns, rule.target, rule.consecutive)
    average = episodes_to_average(logs.returns, rule.target, rule.window)
    trained = logs.policy_updates is None or logs.policy_updates > 0
    target, with_coach = rule.target, logs.coached_returns
    dependent = trained and logs.coach_steps > 0 and coached >= target and not final >= target
    alone = sustained_hit(logs.eval_means, rule.agent_target)
    clone, dip = warm_start_scores(
        logs.eval_env_steps, logs.eval_agent_steps, logs.eval_means, logs.warm_start_at
    )
    return RunMetrics(
        episodes_to_wins=wins,
        episodes_to_average=average,
        episodes_to_wins_with_coach=episodes_to_consecutive_wins(with_coach, target, rule.consecutive),
        episodes_to_average_with_coach=episodes_to_average(with_coach, target, rule.window),
        env_steps_to_target=_at(grid, reached),
        agent_steps_to_target=_at(logs.eval_agent_steps, reached),
        first_hit_env_steps=_at(grid, first_hit(logs.eval_means, rule.target)),
        final_score=final,
        final_training_score=_tail_mean(logs.returns, rule.window),
        final_coached_score=coached,
        coach_dependent=bool(dependent),
        never_trained=not trained,
        intervention_rate=logs.coach_steps / logs.env_steps if logs.env_steps else 0.0,
        episodes=len(logs.returns),
        env_steps=int(logs.env_steps),
        agent_steps=int(logs.agent_steps),
        coach_steps=int(logs.coach_steps),
        policy_updates=logs.policy_updates,
        evaluation_env_steps=int(np.sum(logs.eval_steps)),
        evaluation_delay=int(np.max(logs.eval_env_steps - grid)) if grid.size else 0,
        env_steps_per_episode=logs.env_steps / len(logs.returns) if len(logs.returns) else float("nan"),
        falls=logs.falls,
        env_resets=logs.env_resets,
        env_episodes_to_wins=_env_episodes_at(logs, wins),
        env_episodes_to_average=_env_episodes_at(logs, average),
        env_steps_to_alone_target=_at(grid, alone),
        env_episodes=int(logs.env_episode_counts[-1]) if len(logs.returns) else 0,
        mean_run_length=mean_run_length(logs.episode_agent_steps, logs.episode_runs),
        wall_s_to_alone_target=_wall_at(logs, alone),
        clone_score=clone,
        dip_score=dip,
    )
