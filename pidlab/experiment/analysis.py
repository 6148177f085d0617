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

from pidlab.errors import ExperimentError, RunDirError
from pidlab.experiment import plan
from pidlab.experiment.comparison import MEASURE, Comparison, decide, raw_comparison
from pidlab.experiment.metrics import Rule, RunLogs, RunMetrics, grid_points, moving_average, run_metrics
from pidlab.experiment.stats import Estimate, bootstrap_ci, iqm
from pidlab.files import load_json, read_file, read_toml
from pidlab.rl.rundir import csv_columns, read_csv_rows, read_csv_table

BASELINE = "none"
PLAIN_SAC = "none-sac"


def baseline_of(conditions: Sequence[str]) -> str:
    """The condition a sweep's couplings are tested against (docs/analysis-plan.md, Amendment 23).

    Plain PPO (``none``) when the sweep has it; else plain SAC (``none-sac``) when the sweep has
    that, so that a sweep of SAC couplings beside ``none-sac`` alone is judged against plain SAC;
    else ``none`` (no comparison is drawn).
    """
    if BASELINE not in conditions and PLAIN_SAC in conditions:
        return PLAIN_SAC
    return BASELINE


@dataclass(frozen=True)
class RunData:
    """One finished run's logs and metrics.

    ``wall_s`` is the training wall time over the run's sessions, seconds (None: its summary
    predates the record).
    """

    env_id: str
    condition: str
    seed: int
    returns: np.ndarray
    episode_env_steps: np.ndarray
    episode_coach_steps: np.ndarray
    eval_env_steps: np.ndarray
    eval_agent_steps: np.ndarray
    eval_means: np.ndarray
    eval_grid: np.ndarray
    budget: int
    completed: bool
    metrics: RunMetrics
    wall_s: float | None = None


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

    @property
    def never_trained(self) -> int:
        """Runs that made no policy update."""
        return sum(r.metrics.never_trained for r in self.runs)


@dataclass(frozen=True)
class Analysis:
    """An experiment's results, cell by cell, in (env, condition) order."""

    envs: tuple[str, ...]
    conditions: tuple[str, ...]
    cells: dict[tuple[str, str], CellResult]
    targets: dict[str, float]
    alone_targets: dict[str, float]
    windows: dict[str, int]
    budgets: dict[str, int]
    missing: tuple[str, ...]
    comparisons: dict[tuple[str, str], dict[str, Comparison]]
    algorithms: tuple[str, ...] = ("ppo",)
    """The algorithms the recipes trained (the analysis plan governs PPO)."""
    baseline: str = BASELINE
    """The condition every coached one is tested against (:func:`baseline_of`)."""

    def improvement(self, env: str, condition: str, measure: str) -> Estimate | None:
        """P(improvement over no coach) of one measure, or None (no such comparison)."""
        c = self.comparisons.get((env, condition), {}).get(measure)
        return None if c is None else c.improvement


# metric name -> (lower is better, "to target": may be never reached)
METRICS: dict[str, tuple[bool, bool]] = {
    "episodes_to_wins": (True, True),
    "episodes_to_average": (True, True),
    "episodes_to_wins_with_coach": (True, True),
    "episodes_to_average_with_coach": (True, True),
    "env_steps_to_target": (True, True),
    "agent_steps_to_target": (True, True),
    "first_hit_env_steps": (True, True),
    "final_score": (False, False),
    "final_training_score": (False, False),
    "final_coached_score": (False, False),
    "intervention_rate": (True, False),
    "episodes": (False, False),
    "env_steps_per_episode": (False, False),
    "policy_updates": (False, False),
    "evaluation_env_steps": (False, False),
    "evaluation_delay": (False, False),
    "falls": (True, False),
    "env_resets": (True, False),
    "env_episodes_to_wins": (True, True),
    "env_episodes_to_average": (True, True),
    "env_steps_to_alone_target": (True, True),
    "env_episodes": (False, False),
    "mean_run_length": (False, False),
    "wall_s_to_alone_target": (True, False),  # inf: not reached; None: not logged
    "clone_score": (False, False),
    "dip_score": (False, False),
}


def load_run(run_dir: Path, env_id: str, condition: str, seed: int, rule: Rule) -> RunData | None:
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
        return _run_data(run_dir, s, env_id, condition, seed, rule)
    except LOG_DAMAGE as exc:
        again = "run the experiment's command again (without --report-only)"
        raise logs_damaged(run_dir, exc, again) from None


LOG_DAMAGE = (KeyError, ValueError, TypeError, AttributeError, OSError, RunDirError)
"""What reading a finished run's damaged logs raises (:func:`read_logs`; a log that is no regular
file, or not UTF-8 text, is a :class:`~pidlab.errors.RunDirError` of
:func:`pidlab.rl.rundir.read_csv_rows`)."""


def logs_damaged(run_dir: Path, exc: Exception, again: str) -> ExperimentError:
    """The one message for a finished run whose logs are damaged: what to remove, what to run ``again``."""
    import shlex

    return ExperimentError(
        f"{run_dir}: the finished run's logs are damaged ({type(exc).__name__}: {exc}); nothing was changed. "
        f"Remove the run's folder (rm -r {shlex.quote(str(run_dir))}), then {again}: it trains that run anew"
    )


def _run_data(run_dir: Path, s: Any, env_id: str, condition: str, seed: int, rule: Rule) -> RunData:
    logs = read_logs(run_dir, s)
    return RunData(
        env_id=env_id,
        condition=condition,
        seed=seed,
        returns=logs.returns,
        episode_env_steps=logs.episode_env_steps,
        episode_coach_steps=logs.episode_coach_steps,
        eval_env_steps=logs.eval_env_steps,
        eval_agent_steps=logs.eval_agent_steps,
        eval_means=logs.eval_means,
        eval_grid=grid_points(logs.eval_env_steps, rule.every, rule.budget).astype(float),
        budget=int(s.get("budget_env_steps", s["env_steps"])),
        completed=bool(s["completed"]),
        metrics=run_metrics(logs, rule),
        wall_s=_wall_s(s),
    )


def _wall_s(summary: Any) -> float | None:
    """The run's training wall time over its sessions (``wall_s_total``); None when not recorded."""
    value = summary.get("wall_s_total")
    if value is None:
        return None
    if type(value) not in (int, float) or not np.isfinite(value) or value < 0:
        raise ValueError(f"wall_s_total = {value!r}, expected a number of seconds >= 0")
    return float(value)


def _updates(summary: Any) -> int | None:
    value = summary.get("policy_updates")
    if value is None:
        return None
    if type(value) is not int or value < 0:
        raise ValueError(f"policy_updates = {value!r}, expected an integer >= 0")
    return value


def _count(summary: Any, key: str) -> int | None:
    value = summary.get(key)
    if value is None:
        return None
    if type(value) is not int or value < 0:
        raise ValueError(f"{key} = {value!r}, expected an integer >= 0")
    return value


Columns = dict[str, tuple[str, ...]]
"""A CSV log by column (:func:`pidlab.rl.rundir.csv_columns`)."""


def _rows(columns: Columns) -> int:
    """How many rows a log read by column holds."""
    return len(next(iter(columns.values()), ()))


def _floats(columns: Columns, name: str) -> np.ndarray:
    """Column ``name`` as numbers (a missing column is an error only when the log has rows)."""
    return np.array(columns[name] if _rows(columns) else (), dtype=float)


def _falls(summary: Any, episodes: Columns) -> int:
    """The run's falls: ``summary.json``'s, else from ``episodes.csv``.

    A run logged before pidlab counted falls had no ``terminal`` view: each of its episodes that
    ended ``terminated`` was a fall of the env.
    """
    falls = _count(summary, "falls")
    if falls is not None:
        return falls
    if not _rows(episodes):
        return 0
    ended = episodes["fell"] if "fell" in episodes else episodes["terminated"]
    return sum(int(v) for v in ended)


def _env_resets(run_dir: Path, summary: Any, episodes: Columns) -> int | None:
    """The run's real env resets: ``summary.json``'s, else derived (None when the config is missing).

    Before pidlab counted them every episode's end was the env's: one reset per episode, plus
    each env's first reset of every session (the first and one per resume).
    """
    resets = _count(summary, "env_resets")
    if resets is not None:
        return resets
    config = run_dir / "config.toml"
    if not config.is_file():
        return None
    n_envs = read_toml(config, "run config", ExperimentError).get("recipe", {}).get("n_envs", 1)
    if type(n_envs) is not int or n_envs < 1:
        raise ValueError(f"config.toml: n_envs = {n_envs!r}, expected an integer >= 1")
    resumes = _count(summary, "resumes") or 0
    return _rows(episodes) + n_envs * (resumes + 1)


def read_logs(run_dir: Path, summary: Any) -> RunLogs:
    """A run's ``episodes.csv``, ``evaluations.csv`` and totals of ``summary.json`` (``summary``)."""
    updates = _updates(summary)
    for name in ("episodes.csv", "evaluations.csv"):
        if not (run_dir / name).is_file():
            raise ValueError(f"{name} is missing")
    header, rows = read_csv_table(run_dir / "episodes.csv")
    evals = read_csv_rows(run_dir / "evaluations.csv")
    if not evals and summary.get("completed"):
        raise ValueError("evaluations.csv holds no evaluation of the finished run")
    for name, count in (("episodes", len(rows)), ("evaluations", len(evals))):
        recorded = summary.get(name)
        if summary.get("completed") and type(recorded) is int and recorded != count:
            raise ValueError(f"{name}.csv holds {count} of the {recorded} {name} summary.json records")
    episodes = csv_columns(header, rows, "episodes.csv")
    return RunLogs(
        returns=_floats(episodes, "agent_return"),
        coached_returns=_floats(episodes, "total_return"),
        episode_env_steps=_floats(episodes, "env_steps_so_far"),
        episode_coach_steps=_floats(episodes, "coach_steps"),
        eval_env_steps=np.array([int(r["env_steps_so_far"]) for r in evals]),
        eval_agent_steps=np.array([float(r["agent_steps_so_far"]) for r in evals]),
        eval_means=np.array([float(r["mean_return"]) for r in evals]),
        eval_steps=np.array([round(float(r["mean_length"]) * len(r["returns"].split(";"))) for r in evals]),
        env_steps=int(summary["env_steps"]),
        agent_steps=int(summary["agent_steps"]),
        coach_steps=int(summary["coach_steps"]),
        policy_updates=updates,
        falls=_falls(summary, episodes),
        env_resets=_env_resets(run_dir, summary, episodes),
        env_episodes_ended=_env_episodes_ended(episodes),
        episode_agent_steps=_floats(episodes, "agent_steps"),
        episode_runs=np.array([_number(v) for v in episodes.get("runs", (None,) * _rows(episodes))]),
        eval_wall_s=_wall_clock(run_dir, evals),
        warm_start_at=_warm_start_at(run_dir),
    )


def _warm_start_at(run_dir: Path) -> int | None:
    """Env steps when the run's warm start ended (``warm_start.json``), None without one."""
    path = run_dir / "warm_start.json"
    if not path.is_file():
        return None
    record = load_json(path, "warm-start record", ExperimentError)
    at = record.get("env_steps_after") if isinstance(record, dict) else None
    if type(at) is not int or at < 0:
        raise ValueError(f"warm_start.json: env_steps_after = {at!r}, expected an integer >= 0")
    return at


def _number(text: str | None) -> float:
    """A logged number, ``nan`` when missing or not a number."""
    try:
        return float(text) if text else float("nan")
    except ValueError:
        return float("nan")


def _wall_clock(run_dir: Path, evals: list[dict[str, str]]) -> np.ndarray:
    """``timing.csv``'s wall-clock seconds at each evaluation's env step (``nan`` where not logged)."""
    at: dict[int, float] = {}
    for row in read_csv_rows(run_dir / "timing.csv"):
        step, wall = _number(row.get("env_steps_so_far")), _number(row.get("wall_s"))
        if np.isfinite(step) and np.isfinite(wall):
            at[int(step)] = wall
    return np.array([at.get(int(r["env_steps_so_far"]), float("nan")) for r in evals])


def _env_episodes_ended(episodes: Columns) -> np.ndarray | None:
    """Env episodes ended so far at each training episode's end (None: logs without ``env_end``).

    Logs written before the ``terminal`` view have no ``env_end`` column: each of their training
    episodes ended its env's episode.
    """
    if not _rows(episodes) or "env_end" not in episodes:
        return None
    ends = np.array(episodes["env_end"])
    wrong = ~np.isin(ends, ("0", "1"))
    if wrong.any():
        raise ValueError(f"episodes.csv: env_end = {str(ends[wrong][0])!r}, expected 0 or 1")
    return np.cumsum(ends == "1")


def censored_values(runs: Sequence[RunData], name: str) -> tuple[np.ndarray, int]:
    """The metric per run (``+inf``: never reached) and how many runs reached the target."""
    values = [getattr(r.metrics, name) for r in runs]
    if not METRICS[name][1]:  # not a "to target" metric: None is "not recorded"
        return np.array([np.nan if v is None else float(v) for v in values]), len(values)
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


def _summaries(runs: Sequence[RunData], reps: int) -> dict[str, MetricSummary]:
    metrics = {}
    for name in METRICS:
        values, reached = censored_values(runs, name)
        values = values[~np.isnan(values)]
        nan = float("nan")
        est = bootstrap_ci([values.tolist()], iqm, reps=reps) if values.size else Estimate(nan, nan, nan)
        metrics[name] = MetricSummary(est, reached, len(runs))
    return metrics


def analyze_cell(
    runs: Sequence[RunData], env_id: str, condition: str, window: int, budget: int, every: int,
    reps: int = 2000,
) -> CellResult:  # fmt: skip
    """Aggregates and curves of one (env, condition) over its runs."""
    grid = np.arange(0, budget + 1, every, dtype=float)
    if grid[-1] < budget:
        grid = np.append(grid, float(budget))
    # each evaluation at the grid point it was due at (it runs a few steps late when a coach step crosses it)
    evals = np.asarray([_step_curve(r.eval_grid, r.eval_means, grid) for r in runs])
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
        metrics=_summaries(runs, reps),
        coach_dependent=sum(r.metrics.coach_dependent for r in runs),
        eval_curve=band(evals, grid, 500, 1),
        training_curve_episodes=_thin_band(by_episode, episodes_x),
        training_curve_steps=band(by_steps, step_grid, 300, 2),
        intervention_curve=band(_intervention_rows(runs, edges), (edges[1:] + edges[:-1]) / 2, 300, 3),
    )


def _thin_band(rows: np.ndarray, x: np.ndarray, points: int = 150) -> Curve:
    """The band on at most ``points`` evenly spaced episodes (long episode axes cost bootstrap time)."""
    if x.size == 0:
        return Curve(x, x, x, x)
    keep = np.unique(np.linspace(0, x.size - 1, min(points, x.size)).round().astype(int))
    return band(rows[:, keep], x[keep], 300, 4)


def rule_of(recipe: Any) -> Rule:
    """The :class:`pidlab.experiment.metrics.Rule` of a recipe (its win target and evaluation grid)."""
    win = recipe.win
    alone = plan.alone_target(recipe.env_id, win.target)
    return Rule(win.target, win.consecutive, win.window, recipe.evaluation.every, recipe.steps, alone)


def _load_cells(
    envs: Sequence[str], conditions: Sequence[str], seeds: Sequence[int], root: Path, recipes: dict[str, Any]
) -> tuple[dict[tuple[str, str], list[RunData]], list[str]]:
    loaded: dict[tuple[str, str], list[RunData]] = {}
    missing = []
    for env in envs:
        rule = rule_of(recipes[env])
        for cond in conditions:
            runs = []
            for seed in seeds:
                run = load_run(root / "runs" / env / cond / f"seed-{seed}", env, cond, seed, rule)
                if run is None or not run.completed:
                    missing.append(f"{env}/{cond}/seed-{seed}")
                else:
                    runs.append(run)
            loaded[(env, cond)] = runs
    return loaded, missing


def compare_env(
    loaded: dict[tuple[str, str], list[RunData]],
    env: str,
    conditions: Sequence[str],
    win_target: float,
    reps: int = 10000,
) -> dict[tuple[str, str], dict[str, Comparison]]:
    """Every coached condition of ``env`` against no coach, in the plan's two families, with verdicts.

    ``win_target``: the env's paper target (it decides whether the paper's target in env steps is
    in the secondary family); ``reps``: bootstrap resamples of the savings. No coach is the sweep's
    baseline (:func:`baseline_of`): plain PPO, or plain SAC in a sweep without plain PPO.
    """
    baseline = baseline_of(conditions)
    base = loaded.get((env, baseline), [])
    coached = [c for c in conditions if c != baseline and loaded.get((env, c)) and base]
    never = {c: all(r.metrics.never_trained for r in loaded[(env, c)]) for c in coached}
    out: dict[tuple[str, str], dict[str, Comparison]] = {}
    for family, names in (("primary", plan.PRIMARY), ("secondary", plan.secondary_measures(env, win_target))):
        raw, values = {}, {}
        for cond in coached:
            for name in names:
                x, _ = censored_values(loaded[(env, cond)], name)
                y, _ = censored_values(base, name)
                raw[(cond, name)] = raw_comparison(x, y, MEASURE[name], reps)
                values[(cond, name)] = (x, y)
        for (cond, name), c in decide(raw, values, never, family).items():
            out.setdefault((env, cond), {})[name] = c
    return out


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
    loaded, missing = _load_cells(envs, conditions, tuple(experiment["seeds"]), root, recipes)
    cells: dict[tuple[str, str], CellResult] = {}
    comparisons: dict[tuple[str, str], dict[str, Comparison]] = {}
    for env in envs:
        r = recipes[env]
        for cond in conditions:
            if loaded[(env, cond)]:
                cells[(env, cond)] = analyze_cell(
                    loaded[(env, cond)], env, cond, r.win.window, r.steps, r.evaluation.every, reps
                )
        comparisons.update(compare_env(loaded, env, conditions, r.win.target))
    return Analysis(
        envs=envs,
        conditions=conditions,
        cells=cells,
        targets={e: recipes[e].win.target for e in envs},
        alone_targets={e: rule_of(recipes[e]).agent_target for e in envs},
        windows={e: recipes[e].win.window for e in envs},
        budgets={e: recipes[e].steps for e in envs},
        missing=tuple(missing),
        comparisons=comparisons,
        algorithms=run_algorithms(root, envs, conditions) or tuple(sorted({recipes[e].algo for e in envs})),
        baseline=baseline_of(conditions),
    )


def run_algorithms(root: Path, envs: Sequence[str], conditions: Sequence[str]) -> tuple[str, ...]:
    """The algorithms the runs of an experiment folder recorded (``[recipe] algo`` of each config.toml).

    A condition may name its own algorithm (``algo``), so the runs, not the env's recipe, say which
    agents a sweep trained. Empty when no run records one.
    """
    import tomllib

    found = set()
    for env in envs:
        for condition in conditions:
            for path in sorted((root / "runs" / env / condition).glob("seed-*/config.toml")):
                try:
                    algo = tomllib.loads(read_file(path).decode("utf-8")).get("recipe", {}).get("algo")
                except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
                    continue  # a damaged config is reported where the run is read
                if isinstance(algo, str):
                    found.add(algo)
    return tuple(sorted(found))


def recipes_of_runs(root: Path, experiment: dict[str, Any]) -> dict[str, Any]:
    """Env id -> the recipe its runs recorded (``config.toml`` of the first run found).

    This analyzes a copied or published experiment folder without the recipe files it was run
    from: every run directory records the recipe it ran (its budget included).

    Raises
    ------
    ExperimentError
        No run of an env records its recipe.
    """
    from pidlab.rl.rundir import load_run_config

    recipes = {}
    for env in experiment["envs"]:
        configs = sorted((root / "runs" / env).glob("*/seed-*/config.toml"))
        if not configs:
            raise ExperimentError(f"{root / 'runs' / env}: no run records its recipe (config.toml)")
        recipes[env], _, _ = load_run_config(configs[0].parent)
    return recipes
