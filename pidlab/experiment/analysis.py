"""Read an experiment's runs and compute its metrics, statistics and curves (no plotting, no writing).

:func:`analyze` returns an :class:`Analysis`: per-run metrics (:class:`pidlab.experiment.metrics.RunMetrics`),
per (env, condition) aggregates with IQM and stratified-bootstrap 95 % intervals, probabilities of
improvement over the uncoached condition, and learning curves on the episode and env-step axes.

A run that never reaches a target within its budget counts as ``+inf`` for a "steps (or episodes)
to target" metric: it ranks below every run that reached it (ties with the other such runs) in the
probability of improvement, and the IQM is ``+inf`` ("not reached") when more than a quarter of the
runs never reached it. The count of runs that reached the target is reported next to it. (Counting
such runs at their budget instead would favour a condition with fewer, longer episodes: a coach that
keeps episodes alive "needs" fewer episodes without learning anything.)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pidlab.errors import ExperimentError
from pidlab.experiment.metrics import RunMetrics, moving_average, run_metrics
from pidlab.experiment.stats import Estimate, bootstrap_ci, iqm, probability_of_improvement
from pidlab.files import load_json
from pidlab.rl.rundir import read_csv_rows

BASELINE = "none"


@dataclass(frozen=True)
class RunData:
    """One finished run's logs and metrics."""

    env_id: str
    condition: str
    seed: int
    returns: np.ndarray
    episode_env_steps: np.ndarray
    episode_coach_steps: np.ndarray
    eval_env_steps: np.ndarray
    eval_agent_steps: np.ndarray
    eval_means: np.ndarray
    budget: int
    completed: bool
    metrics: RunMetrics


@dataclass(frozen=True)
class MetricSummary:
    """A metric over the seeds of one (env, condition).

    Attributes
    ----------
    estimate : Estimate
        IQM with its 95 % stratified bootstrap interval (censored values included, see module doc).
    reached : int
        Runs that reached the target (for "to target" metrics; all runs otherwise).
    runs : int
    """

    estimate: Estimate
    reached: int
    runs: int


@dataclass(frozen=True)
class Curve:
    """IQM and 95 % band of a quantity over seeds, on a common x axis."""

    x: np.ndarray
    iqm: np.ndarray
    low: np.ndarray
    high: np.ndarray


@dataclass(frozen=True)
class CellResult:
    """Everything about one (env, condition)."""

    env_id: str
    condition: str
    runs: tuple[RunData, ...]
    metrics: dict[str, MetricSummary]
    coach_dependent: int
    eval_curve: Curve
    training_curve_episodes: Curve
    training_curve_steps: Curve
    intervention_curve: Curve
    improvement: dict[str, Estimate]


@dataclass(frozen=True)
class Analysis:
    """An experiment's results, cell by cell, in (env, condition) order."""

    envs: tuple[str, ...]
    conditions: tuple[str, ...]
    cells: dict[tuple[str, str], CellResult]
    targets: dict[str, float]
    windows: dict[str, int]
    budgets: dict[str, int]
    missing: tuple[str, ...]


# metric name -> (lower is better, "to target": may be never reached)
METRICS: dict[str, tuple[bool, bool]] = {
    "episodes_to_wins": (True, True),
    "episodes_to_average": (True, True),
    "env_steps_to_target": (True, True),
    "agent_steps_to_target": (True, True),
    "final_score": (False, False),
    "final_training_score": (False, False),
    "final_coached_score": (False, False),
    "intervention_rate": (True, False),
}

IMPROVEMENT_METRICS = ("episodes_to_wins", "episodes_to_average", "env_steps_to_target", "final_score")


def load_run(
    run_dir: Path, env_id: str, condition: str, seed: int, target: float, consecutive: int, window: int
) -> RunData | None:
    """A run's logs and metrics; None when it has no ``summary.json`` yet.

    Raises
    ------
    ExperimentError
        The run's ``summary.json`` or CSV logs are damaged (one line naming the run).
    """
    summary_path = run_dir / "summary.json"
    if not summary_path.exists():
        return None
    s = load_json(summary_path, "run summary", ExperimentError)
    try:
        return _run_data(run_dir, s, env_id, condition, seed, target, consecutive, window)
    except (KeyError, ValueError, TypeError, AttributeError) as exc:
        raise ExperimentError(
            f"{run_dir}: the run's logs are damaged ({type(exc).__name__}: {exc}); "
            "resume the run (pidlab experiment with the same command) or delete its folder"
        ) from None


def _run_data(
    run_dir: Path,
    s: Any,
    env_id: str,
    condition: str,
    seed: int,
    target: float,
    consecutive: int,
    window: int,
) -> RunData:
    episodes = read_csv_rows(run_dir / "episodes.csv")
    evals = read_csv_rows(run_dir / "evaluations.csv")
    returns = np.array([float(r["agent_return"]) for r in episodes])
    ev_env = np.array([float(r["env_steps_so_far"]) for r in evals])
    ev_agent = np.array([float(r["agent_steps_so_far"]) for r in evals])
    ev_mean = np.array([float(r["mean_return"]) for r in evals])
    coached = np.array([float(r["total_return"]) for r in episodes])
    m = run_metrics(
        returns, ev_env, ev_agent, ev_mean, int(s["env_steps"]), int(s["agent_steps"]), int(s["coach_steps"]),
        target, consecutive, window, coached,
    )  # fmt: skip
    return RunData(
        env_id=env_id,
        condition=condition,
        seed=seed,
        returns=returns,
        episode_env_steps=np.array([float(r["env_steps_so_far"]) for r in episodes]),
        episode_coach_steps=np.array([float(r["coach_steps"]) for r in episodes]),
        eval_env_steps=ev_env,
        eval_agent_steps=ev_agent,
        eval_means=ev_mean,
        budget=int(s.get("budget_env_steps", s["env_steps"])),
        completed=bool(s["completed"]),
        metrics=m,
    )


def censored_values(runs: Sequence[RunData], name: str) -> tuple[np.ndarray, int]:
    """The metric per run (``+inf``: never reached) and how many runs reached the target."""
    values = [getattr(r.metrics, name) for r in runs]
    out = np.array([np.inf if v is None else float(v) for v in values])
    return out, sum(v is not None for v in values)


def _step_curve(xs: np.ndarray, ys: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """The latest y at or before each grid x (NaN before the first x)."""
    idx = np.searchsorted(xs, grid, side="right") - 1
    out = np.where(idx >= 0, ys[np.clip(idx, 0, None)] if ys.size else np.nan, np.nan)
    return out.astype(float)


def band(rows: np.ndarray, x: np.ndarray, reps: int, seed: int) -> Curve:
    """IQM and bootstrap band of each column of ``rows`` (runs x points), ignoring NaN."""
    mid, lo, hi = (np.full(x.size, np.nan) for _ in range(3))
    for j in range(x.size):
        col = rows[:, j]
        col = col[~np.isnan(col)]
        if col.size:
            e = bootstrap_ci([col.tolist()], iqm, reps=reps, seed=seed + j)
            mid[j], lo[j], hi[j] = e.value, e.low, e.high
    return Curve(x, mid, lo, hi)


def _intervention_rows(runs: Sequence[RunData], edges: np.ndarray) -> np.ndarray:
    """Coach steps / env steps between consecutive ``edges`` (env steps), per run.

    Within an episode the coach's steps are spread evenly (the logs give them per episode).
    """
    rows = []
    for r in runs:
        x = np.concatenate([[0.0], r.episode_env_steps])
        y = np.concatenate([[0.0], np.cumsum(r.episode_coach_steps)])
        at = np.interp(edges, x, y, right=np.nan)
        rows.append(np.diff(at) / np.diff(edges))
    return np.asarray(rows)


def analyze_cell(
    runs: Sequence[RunData], env_id: str, condition: str, window: int, budget: int, every: int,
    baseline: Sequence[RunData] | None, reps: int = 2000,
) -> CellResult:  # fmt: skip
    """Aggregates and curves of one (env, condition) over its runs."""
    metrics = {}
    for name in METRICS:
        values, reached = censored_values(runs, name)
        metrics[name] = MetricSummary(bootstrap_ci([values.tolist()], iqm, reps=reps), reached, len(runs))
    improvement = {}
    if baseline:
        for name in IMPROVEMENT_METRICS:
            lower_better, _ = METRICS[name]
            a, _ = censored_values(runs, name)
            b, _ = censored_values(baseline, name)
            sign = -1.0 if lower_better else 1.0
            improvement[name] = probability_of_improvement(
                [(sign * a).tolist()], [(sign * b).tolist()], reps=reps
            )
    grid = np.arange(0, budget + 1, every, dtype=float)
    if grid[-1] < budget:
        grid = np.append(grid, float(budget))
    # an evaluation due at k * every runs at the first rollout boundary after it (a few steps late)
    late = every / 2
    evals = np.asarray([_step_curve(r.eval_env_steps - late, r.eval_means, grid) for r in runs])
    smooth = [moving_average(r.returns, window) for r in runs]
    n_ep = min(len(s) for s in smooth) if smooth else 0
    episodes_x = np.arange(1, n_ep + 1, dtype=float)
    by_episode = np.asarray([s[:n_ep] for s in smooth]) if n_ep else np.zeros((len(runs), 0))
    step_grid = np.linspace(0, budget, 101)
    by_steps = np.asarray(
        [_step_curve(r.episode_env_steps, s, step_grid) for r, s in zip(runs, smooth, strict=True)]
    )
    edges = np.linspace(0, budget, 21)
    return CellResult(
        env_id=env_id,
        condition=condition,
        runs=tuple(runs),
        metrics=metrics,
        coach_dependent=sum(r.metrics.coach_dependent for r in runs),
        eval_curve=band(evals, grid, 500, 1),
        training_curve_episodes=_thin_band(by_episode, episodes_x),
        training_curve_steps=band(by_steps, step_grid, 300, 2),
        intervention_curve=band(_intervention_rows(runs, edges), (edges[1:] + edges[:-1]) / 2, 300, 3),
        improvement=improvement,
    )


def _thin_band(rows: np.ndarray, x: np.ndarray, points: int = 150) -> Curve:
    """The band on at most ``points`` evenly spaced episodes (long episode axes cost bootstrap time)."""
    if x.size == 0:
        return Curve(x, x, x, x)
    keep = np.unique(np.linspace(0, x.size - 1, min(points, x.size)).round().astype(int))
    return band(rows[:, keep], x[keep], 300, 4)


def analyze(experiment: dict[str, Any], root: Path, recipes: dict[str, Any], reps: int = 2000) -> Analysis:
    """Analyze an experiment folder.

    Parameters
    ----------
    experiment : dict
        ``identity`` of ``experiment.json`` (envs, conditions, seeds).
    root : Path
        The experiment folder.
    recipes : dict
        Env id -> :class:`pidlab.rl.recipe.Recipe` used (targets, windows, budgets, eval interval).
    reps : int
        Bootstrap resamples for the metric intervals.
    """
    envs = tuple(experiment["envs"])
    conditions = tuple(experiment["conditions"])
    seeds = tuple(experiment["seeds"])
    cells: dict[tuple[str, str], CellResult] = {}
    missing = []
    loaded: dict[tuple[str, str], list[RunData]] = {}
    for env in envs:
        r = recipes[env]
        for cond in conditions:
            runs = []
            for seed in seeds:
                d = root / "runs" / env / cond / f"seed-{seed}"
                run = load_run(d, env, cond, seed, r.win.target, r.win.consecutive, r.win.window)
                if run is None or not run.completed:
                    missing.append(f"{env}/{cond}/seed-{seed}")
                else:
                    runs.append(run)
            loaded[(env, cond)] = runs
    for env in envs:
        r = recipes[env]
        base = loaded.get((env, BASELINE)) if BASELINE in conditions else None
        for cond in conditions:
            runs = loaded[(env, cond)]
            if not runs:
                continue
            cells[(env, cond)] = analyze_cell(
                runs, env, cond, r.win.window, r.steps, r.evaluation.every,
                base if cond != BASELINE else None, reps,
            )  # fmt: skip
    return Analysis(
        envs=envs,
        conditions=conditions,
        cells=cells,
        targets={e: recipes[e].win.target for e in envs},
        windows={e: recipes[e].win.window for e in envs},
        budgets={e: recipes[e].steps for e in envs},
        missing=tuple(missing),
    )
