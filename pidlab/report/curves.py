"""Figures of an experiment (matplotlib; compute lives in :mod:`pidlab.experiment.analysis`).

Every function takes an :class:`~pidlab.experiment.analysis.Analysis` and one env, draws on the
axes it is given (``ax``) or on a new figure (a bare :class:`~matplotlib.figure.Figure`: no backend
is chosen or changed), and returns the figure; :func:`pidlab.files.save_figure` writes it. Bands are
95 % stratified-bootstrap intervals of the IQM over seeds.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from pidlab.experiment.analysis import Analysis, Curve
from pidlab.report.plots import figure_axes

COLORS = ("#4c4c4c", "#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#17becf")


def _color(analysis: Analysis, condition: str) -> str:
    return COLORS[analysis.conditions.index(condition) % len(COLORS)]


def _draw(ax: Axes, curve: Curve, label: str, color: str, steps: bool = False) -> None:
    ok = ~np.isnan(curve.iqm)
    style = "steps-post" if steps else "default"
    ax.plot(curve.x[ok], curve.iqm[ok], color=color, label=label, lw=1.8, drawstyle=style)
    ax.fill_between(curve.x[ok], curve.low[ok], curve.high[ok], color=color, alpha=0.18, lw=0,
                    step="post" if steps else None)  # fmt: skip


def plot_learning_curves(analysis: Analysis, env: str, ax: Any = None) -> Figure:
    """Agent-alone score vs env steps; training return vs env steps and vs episodes.

    ``ax``: three axes to draw on, in that order (default: a new figure). Returns the figure.
    """
    fig, grid, new = figure_axes(ax, 1, 3, (16, 4.6))
    axes = grid[0]
    target = analysis.targets[env]
    for cond in analysis.conditions:
        cell = analysis.cells.get((env, cond))
        if cell is None:
            continue
        label = f"{cond} (n={len(cell.runs)})"
        c = _color(analysis, cond)
        _draw(axes[0], cell.eval_curve, label, c, steps=True)
        _draw(axes[1], cell.training_curve_steps, label, c)
        _draw(axes[2], cell.training_curve_episodes, label, c)
    titles = (
        "agent alone (coach off), deterministic",
        f"training return, moving average of {analysis.windows[env]} episodes",
        "training return by episode (the paper's axis)",
    )
    xlabels = ("env steps (agent + coach)", "env steps (agent + coach)", "training episode")
    for ax, title, xl in zip(axes, titles, xlabels, strict=True):
        ax.axhline(target, color="k", ls=":", lw=1, label=f"target {target:g}")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel(xl)
        ax.set_ylabel("return")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, loc="best")
    fig.suptitle(f"{env}: IQM over seeds with 95% bootstrap bands", fontsize=11)
    if new:
        fig.tight_layout()
    return fig


_BARS = (
    ("episodes_to_wins", "episodes to 5 wins in a row\n(training returns, the paper's)", "episodes"),
    (
        "episodes_to_average",
        "episodes until the moving average\nreaches the target (the paper's)",
        "episodes",
    ),
    ("env_steps_to_target", "env steps until the agent alone\nreaches the target", "env steps"),
    ("final_score", "final agent-alone score", "return"),
)


def plot_table2_bars(analysis: Analysis, env: str, ax: Any = None) -> Figure:
    """Bar charts like the paper's Table II (and the honest metrics), IQM with 95 % CI.

    ``ax``: four axes to draw on (episodes to 5 wins, episodes to the average, env steps to the
    target, final score; default: a new figure). Returns the figure.
    """
    fig, grid, new = figure_axes(ax, 1, len(_BARS), (16, 4.2))
    axes = grid[0]
    conds = [c for c in analysis.conditions if (env, c) in analysis.cells]
    for ax, (name, title, unit) in zip(axes, _BARS, strict=True):
        for i, cond in enumerate(conds):
            m = analysis.cells[(env, cond)].metrics[name]
            e = m.estimate
            label = f"{m.reached}/{m.runs}" if name != "final_score" else ""
            if np.isfinite(e.value):
                ax.bar(i, e.value, color=_color(analysis, cond), alpha=0.85)
                high = e.high if np.isfinite(e.high) else e.value
                ax.errorbar(i, e.value, yerr=[[e.value - e.low], [high - e.value]], color="k", capsize=4)
                if not np.isfinite(e.high):
                    label += "\nCI open"
                ax.annotate(label, (i, high), ha="center", va="bottom", fontsize=8)
            else:
                ax.annotate(f"not\nreached\n{label}", (i, 0), ha="center", va="bottom", fontsize=8)
        ax.set_xticks(range(len(conds)), conds, rotation=20, fontsize=8)
        ax.set_xlim(-0.6, len(conds) - 0.4)
        ax.set_title(title, fontsize=9)
        ax.set_ylabel(unit)
        ax.grid(axis="y", alpha=0.3)
    axes[-1].axhline(analysis.targets[env], color="k", ls=":", lw=1)
    fig.suptitle(
        f"{env}: IQM over seeds, 95% bootstrap CI; n/N = runs that reached the target "
        "(a run that never did counts as not reached)",
        fontsize=10,
    )
    if new:
        fig.tight_layout()
    return fig


def plot_coach_dependence(analysis: Analysis, env: str, ax: Any = None) -> Figure:
    """Per seed: final training score (with the coach) vs agent-alone score; and intervention rate.

    ``ax``: two axes to draw on, in that order (default: a new figure). Returns the figure.
    """
    fig, grid, new = figure_axes(ax, 1, 2, (13, 4.8))
    a1, a2 = grid[0]
    target = analysis.targets[env]
    for cond in analysis.conditions:
        cell = analysis.cells.get((env, cond))
        if cell is None:
            continue
        c = _color(analysis, cond)
        xs = [r.metrics.final_coached_score for r in cell.runs]
        ys = [r.metrics.final_score for r in cell.runs]
        a1.scatter(xs, ys, color=c, label=f"{cond}: {cell.coach_dependent}/{len(cell.runs)} coach-dependent",
                   alpha=0.8, s=28)  # fmt: skip
        if cond != "none":
            _draw(a2, cell.intervention_curve, cond, c)
    a1.axvline(target, color="k", ls=":", lw=1)
    a1.axhline(target, color="k", ls=":", lw=1)
    a1.set_xlabel(f"return with the coach, last {analysis.windows[env]} training episodes")
    a1.set_ylabel("final agent-alone score (coach off)")
    a1.set_title("coach dependence: right of the line but below it = scores only with the coach", fontsize=9)
    a1.legend(fontsize=8)
    a1.grid(alpha=0.3)
    a2.set_xlabel("env steps (agent + coach)")
    a2.set_ylabel("coach steps / env steps in the interval")
    a2.set_title("intervention rate over training (IQM, 95% band)", fontsize=9)
    a2.set_ylim(-0.02, 1.02)
    a2.grid(alpha=0.3)
    if a2.lines:
        a2.legend(fontsize=8)
    fig.suptitle(env, fontsize=11)
    if new:
        fig.tight_layout()
    return fig
