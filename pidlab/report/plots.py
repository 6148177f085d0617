"""Plots of a coach analysis (matplotlib; compute lives in :mod:`pidlab.controller.analysis`).

Each ``plot_*`` function draws on the axes it is given (``ax``) or on a new figure, and returns the
figure; it writes no file (:func:`pidlab.files.save_figure` does). New figures are bare
:class:`matplotlib.figure.Figure` objects, outside pyplot: nothing here chooses or changes
matplotlib's backend, and they draw without a display.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from pidlab.controller.analysis import (
    ClosedLoopResponses,
    CoachAnalysis,
    LoopResponse,
    closed_loop_responses,
    loop_responses,
)
from pidlab.controller.pid import Coach
from pidlab.files import save_figure


def figure_axes(
    ax: Any, nrows: int, ncols: int, figsize: tuple[float, float], sharex: bool = False
) -> tuple[Figure, np.ndarray, bool]:
    """The axes a ``plot_*`` function draws on: the caller's ``ax``, or those of a new figure.

    Parameters
    ----------
    ax : matplotlib.axes.Axes, array_like of Axes, or None
        The caller's axes, ``nrows * ncols`` of them (any shape), or None for a new figure.
    nrows, ncols : int
        The grid the plot draws.
    figsize : tuple of float
        Size of a new figure, inches.
    sharex : bool
        A new figure's axes share their x axis.

    Returns
    -------
    fig : matplotlib.figure.Figure
        The figure of the axes.
    axes : ndarray of Axes, shape (nrows, ncols)
    new : bool
        True when the figure was made here (its layout is then the plot's to tighten).

    Raises
    ------
    ValueError
        ``ax`` holds another number of axes.
    """
    if ax is None:
        fig = Figure(figsize=figsize)
        return fig, fig.subplots(nrows, ncols, sharex=sharex, squeeze=False), True
    axes = np.asarray(ax, dtype=object)
    if axes.size != nrows * ncols:
        raise ValueError(f"ax: expected {nrows * ncols} axes ({nrows} x {ncols}), got {axes.size}")
    return axes.flat[0].get_figure(), axes.reshape(nrows, ncols), False


def plot_bode(response: LoopResponse, title: str | None = None, ax: Any = None) -> Figure:
    """Bode plot of a loop transfer function with its gain and phase margins marked.

    Parameters
    ----------
    response : LoopResponse
        The loop's frequency response and margins
        (:func:`pidlab.controller.analysis.loop_responses`).
    title : str, optional
        Default: ``loop broken at ACTUATOR``.
    ax : sequence of 2 Axes, optional
        Magnitude and phase axes; default: a new figure.

    Returns
    -------
    matplotlib.figure.Figure
        The plot runs up to the Nyquist frequency ``pi / dt`` (rad/s), marked by a grey line.
    """
    w, mag, phase, margins = response.omega, response.magnitude_db, response.phase_deg, response.margins
    fig, axes, new = figure_axes(ax, 2, 1, (7, 6), sharex=True)
    a1, a2 = axes[:, 0]
    a1.semilogx(w, mag)
    a1.axhline(0, color="k", lw=0.8)
    a1.set_ylabel("|L| (dB)")
    a2.semilogx(w, phase)
    for k in range(-6, 6):
        level = -180 + 360 * k
        if phase.min() - 30 <= level <= phase.max() + 30:
            a2.axhline(level, color="k", lw=0.5, ls=":")
    a2.set_ylabel("phase (deg)")
    a2.set_xlabel("frequency (rad/s)")
    for wc in margins.crossovers:
        a1.axvline(wc, color="C1", ls=":", lw=0.8)
    if np.isfinite(margins.gain_crossover):
        a1.axvline(margins.gain_crossover, color="C1", ls="--")
        a2.axvline(
            margins.gain_crossover,
            color="C1",
            ls="--",
            label=f"PM {margins.phase_margin_deg:.1f} deg at {margins.gain_crossover:.3g} rad/s",
        )
    if np.isfinite(margins.phase_crossover):
        a1.axvline(
            margins.phase_crossover,
            color="C2",
            ls="--",
            label=f"GM {margins.gain_margin_db:.1f} dB at {margins.phase_crossover:.3g} rad/s",
        )
    a1.axvline(np.pi / response.dt, color="0.5", lw=0.8)
    if np.isfinite(margins.phase_crossover):
        a1.legend(loc="best", fontsize=8)
    if np.isfinite(margins.gain_crossover):
        a2.legend(loc="best", fontsize=8)
    a1.set_title(f"loop broken at {response.actuator}" if title is None else title)
    if new:
        fig.tight_layout()
    return fig


def plot_nyquist(response: LoopResponse, title: str | None = None, ax: Axes | None = None) -> Figure:
    """Nyquist curve of a loop (positive and negative frequencies) with the -1 point.

    ``response`` and ``title`` as for :func:`plot_bode`; ``ax``: the axes to draw on (default: a
    new figure). Returns the figure.
    """
    resp = response.response
    fig, axes, new = figure_axes(ax, 1, 1, (6, 6))
    ax = axes[0, 0]
    ax.plot(resp.real, resp.imag, "C0", label="L(e^{jwT}), w > 0")
    ax.plot(resp.real, -resp.imag, "C0--", lw=0.8, label="w < 0")
    ax.plot([-1], [0], "r+", ms=14, mew=2, label="-1")
    circle = np.exp(1j * np.linspace(0, 2 * np.pi, 200))
    ax.plot(circle.real, circle.imag, color="0.7", lw=0.6)
    lim = max(3.0, min(10.0, float(np.percentile(np.abs(resp), 90))))
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    ax.set_aspect("equal")
    ax.set_xlabel("Re")
    ax.set_ylabel("Im")
    ax.legend(fontsize=8)
    ax.set_title(f"loop broken at {response.actuator}" if title is None else title)
    if new:
        fig.tight_layout()
    return fig


def plot_poles(analysis: CoachAnalysis, ax: Axes | None = None) -> Figure:
    """Closed-loop poles (discrete, z-plane) with the unit circle and the plant's open-loop poles.

    ``ax``: the axes to draw on (default: a new figure). Returns the figure.
    """
    fig, axes, new = figure_axes(ax, 1, 1, (6, 6))
    ax = axes[0, 0]
    circle = np.exp(1j * np.linspace(0, 2 * np.pi, 400))
    ax.plot(circle.real, circle.imag, "k", lw=0.8)
    ol = analysis.open_loop_poles
    ax.plot(ol.real, ol.imag, "x", color="0.5", label="open loop (plant)")
    z = np.array([p.value for p in analysis.discrete.poles])
    colors = ["C0" if p.stable else "C3" for p in analysis.discrete.poles]
    ax.scatter(z.real, z.imag, edgecolors=colors, marker="o", facecolors="none", label="closed loop")
    ax.set_aspect("equal")
    ax.set_xlabel("Re z")
    ax.set_ylabel("Im z")
    ax.legend(fontsize=8)
    ax.set_title(f"{analysis.env_id} / {analysis.spec_name}: poles (dt = {analysis.dt:g} s)")
    if new:
        fig.tight_layout()
    return fig


def plot_responses(responses: ClosedLoopResponses, ax: Any = None) -> Figure:
    """Closed-loop setpoint-step and initial-deviation responses of every loop's signal.

    Parameters
    ----------
    responses : ClosedLoopResponses
        :func:`pidlab.controller.analysis.closed_loop_responses`.
    ax : array_like of Axes, shape (n_loops, 2), optional
        Per loop: setpoint step, initial deviation; default: a new figure.

    Returns
    -------
    matplotlib.figure.Figure
    """
    t = responses.timepts
    n = len(responses.loops)
    fig, axes, new = figure_axes(ax, n, 2, (10, 2.4 * n))
    for j, (name, signal) in enumerate(zip(responses.loops, responses.signals, strict=True)):
        axes[j, 0].plot(t, responses.signal_step(j))
        axes[j, 0].set_title(f"unit step of {name} setpoint -> {signal}", fontsize=9)
        axes[j, 1].plot(t, responses.signal_initial(j))
        axes[j, 1].set_title(f"initial {signal} = {responses.deviation:g} -> {signal}", fontsize=9)
    for bottom in axes[-1]:
        bottom.set_xlabel("time (s)")
    if new:
        fig.tight_layout()
    return fig


def coach_figures(analysis: CoachAnalysis, coach: Coach) -> Iterator[tuple[str, Figure]]:
    """The figures of a coach analysis, one at a time, each with its file stem.

    Bode and Nyquist plots per actuator loop (``bode_ACTUATOR``, ``nyquist_ACTUATOR``), the pole
    map (``poles``) and the responses (``responses``). The data come from
    :func:`pidlab.controller.analysis.loop_responses` and
    :func:`pidlab.controller.analysis.closed_loop_responses`.
    """
    for response in loop_responses(analysis, coach):
        title = f"{analysis.spec_name}: loop broken at {response.actuator}"
        yield f"bode_{response.actuator}", plot_bode(response, title)
        yield f"nyquist_{response.actuator}", plot_nyquist(response, title)
    yield "poles", plot_poles(analysis)
    yield "responses", plot_responses(closed_loop_responses(analysis, coach))


def write_plots(analysis: CoachAnalysis, coach: Coach, folder: str | Path) -> list[Path]:
    """Write the figures of :func:`coach_figures` into ``folder`` as ``STEM.png``; returns their paths."""
    folder = Path(folder)
    return [save_figure(fig, folder / f"{stem}.png") for stem, fig in coach_figures(analysis, coach)]


def _draw_bounds(ax: Axes, bounds: Any, variables: tuple[str, str]) -> None:
    from pidlab.region.roa import ellipse_slice

    if all(v in bounds.variables for v in variables) and bounds.rho > 0:
        idx = (bounds.variables.index(variables[0]), bounds.variables.index(variables[1]))
        pts = ellipse_slice(bounds.shape, bounds.center, bounds.rho * bounds.level, idx, points=300)
        ax.plot(pts[0], pts[1], color="C1", lw=1.5, label=f"takeover ellipsoid (rho = {bounds.rho:.3g})")
    box = bounds.box
    if any(v in box for v in variables):
        lows = [box[v][0] if v in box else -np.inf for v in variables]
        highs = [box[v][1] if v in box else np.inf for v in variables]
        xl, yl = ax.get_xlim(), ax.get_ylim()
        x0, x1 = max(lows[0], xl[0]), min(highs[0], xl[1])
        y0, y1 = max(lows[1], yl[0]), min(highs[1], yl[1])
        ax.add_patch(
            Rectangle(
                (x0, y0), x1 - x0, y1 - y0, fill=False, lw=1.5, ls="--", color="C0", label="critical box"
            )
        )


def _draw_rescue(ax: Axes, grid: Any, label: str) -> None:
    """The marked cells of a rescue grid in the plane of its first two variables.

    With more variables: the slice through the cells that hold the domain's centre (the operating
    point) in the others.
    """
    table = np.asarray(grid.table)
    plane = table[(slice(None), slice(None), *(n // 2 for n in table.shape[2:]))] if table.ndim > 2 else table
    if table.ndim == 1:
        plane = table[:, None]
    x = np.linspace(grid.lower[0], grid.upper[0], plane.shape[0] + 1)
    y = np.linspace(grid.lower[1], grid.upper[1], plane.shape[1] + 1) if table.ndim > 1 else np.array([-1, 1])
    shown = np.ma.masked_where(~plane.T, np.ones_like(plane.T, dtype=float))
    ax.pcolormesh(x, y, shown, cmap="Greens", vmin=0, vmax=1.6, alpha=0.6, shading="flat")
    ax.add_patch(Rectangle((0, 0), 0, 0, color="tab:green", alpha=0.5, label=label))


def plot_rescue_region(
    grid: Any, bounds: dict[str, Any] | None, units: dict[str, str], title: str, ax: Axes | None = None
) -> Figure:
    """A rescue region beside the certified core and the takeover box, in its first two variables' plane.

    Parameters
    ----------
    grid : pidlab.lookup.LookupGrid
        The region (with more than two variables: its slice through the operating point's cells
        of the rest).
    bounds : dict, optional
        The spec's ``[bounds]`` table: its certified core (``ellipsoid`` at ``level``), the
        ellipsoid shrunk to ``rho * level`` and the ``box`` are drawn where they span the plane.
    units : dict
        Variable name -> unit, for the axis labels.
    title : str
    ax : Axes, optional
        The axes to draw on; default: a new figure.

    Returns
    -------
    matplotlib.figure.Figure
    """
    from pidlab.region.roa import ellipse_slice

    fig, axes, _ = figure_axes(ax, 1, 1, (7, 6))
    ax = axes[0, 0]
    b = bounds or {}
    takeover = b.get("takeover", "rescue" if "rescue" in b else "box")
    variables = tuple(grid.variables[:2])
    mark = " (takeover region)"
    _draw_rescue(ax, grid, f"rescue region, {grid.trigger} trigger{mark if takeover == 'rescue' else ''}")
    e = b.get("ellipsoid")
    if e and len(variables) == 2 and all(v in e["variables"] for v in variables):
        idx = (e["variables"].index(variables[0]), e["variables"].index(variables[1]))
        P, c = np.array(e["shape"]), np.array(e["center"])
        for level, style, label in (
            (e["level"], "k", "certified core (slice of V <= c)"),
            (e["rho"] * e["level"], "C1", f"core shrunk to rho = {e['rho']:.3g}"),
        ):
            pts = ellipse_slice(P, c, level, idx, points=300)
            ax.plot(
                pts[0],
                pts[1],
                style,
                lw=1.5,
                label=label + (mark if takeover == "ellipsoid" and style == "C1" else ""),
            )
    box = b.get("box") or {}
    if len(variables) == 2 and all(v in box for v in variables):
        (x0, x1), (y0, y1) = (box[v] for v in variables)
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, lw=1.5, ls="--", color="C0",
                               label="critical box" + (mark if takeover == "box" else "")))  # fmt: skip
    ax.set_xlim(grid.lower[0], grid.upper[0])
    if len(variables) == 2:
        ax.set_ylim(grid.lower[1], grid.upper[1])
        ax.set_ylabel(f"{variables[1]} ({units.get(variables[1], '')})")
    ax.set_xlabel(f"{variables[0]} ({units.get(variables[0], '')})")
    guard = ", ".join(f"|{k}| in [{lo:.3g}, {hi:.3g}]" for k, (lo, hi) in grid.guard.items())
    ax.set_title(
        f"{title}\n{'guard: ' + guard if guard else 'other variables at the operating point'}", fontsize=9
    )
    ax.legend(fontsize=7, loc="upper right")
    return fig


def plot_roa_slice(
    result: Any,
    variables: tuple[str, str],
    trajectories: list[Any],
    units: dict[str, str],
    bounds: Any | None = None,
    ax: Axes | None = None,
) -> Figure:
    """The certified set in the plane of two variables, with simulated trajectories overlaid.

    Parameters
    ----------
    result : pidlab.region.roa.RegionOfAttraction
    variables : tuple of 2 str
        The observation variables of the plane (x, y).
    trajectories : list
        Simulated trajectories in that plane (``path``, shape (steps, 2); ``recovered``).
    units : dict
        Variable name -> unit, for the axis labels.
    bounds : pidlab.region.bounds.CriticalBounds, optional
        Also draw the takeover ellipsoid's slice and the critical box where they constrain these
        variables.
    ax : Axes, optional
        The axes to draw on; default: a new figure.

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig, axes, new = figure_axes(ax, 1, 1, (7, 6))
    ax = axes[0, 0]
    if result.lyapunov is not None:
        L = result.lyapunov
        from pidlab.region.roa import ellipse_slice

        idx = (L.variables.index(variables[0]), L.variables.index(variables[1]))
        pts = ellipse_slice(L.P_y, L.center, result.level, idx, points=300)
        ax.plot(
            pts[0],
            pts[1],
            "k",
            lw=2,
            label=f"slice of V <= c (c = {result.level:.3g})",
        )
    else:
        hx, hy = (result.box.get(v, np.nan) for v in variables)
        ax.add_patch(Rectangle((-hx, -hy), 2 * hx, 2 * hy, fill=False, lw=2, label="recoverable box"))
    for k, tr in enumerate(trajectories):
        if len(tr.path) == 0:
            continue
        color = "C2" if tr.recovered else "C3"
        label = None
        if k == 0 or (not tr.recovered and all(t.recovered for t in trajectories[:k])):
            label = "recovered" if tr.recovered else "failed"
        ax.plot(tr.path[:, 0], tr.path[:, 1], color=color, lw=0.7, alpha=0.7, label=label)
        ax.plot(tr.path[0, 0], tr.path[0, 1], ".", color=color, ms=3)
    if bounds is not None:
        _draw_bounds(ax, bounds, variables)
    ax.set_xlabel(f"{variables[0]} ({units.get(variables[0], '')})")
    ax.set_ylabel(f"{variables[1]} ({units.get(variables[1], '')})")
    ax.set_title(f"{result.env_id} / {result.spec_name}\n{result.method}", fontsize=9)
    ax.legend(fontsize=8, loc="upper right")
    if new:
        fig.tight_layout()
    return fig


def plot_phase_portrait(
    paths: list[np.ndarray],
    variables: tuple[str, str],
    units: dict[str, str],
    title: str,
    ax: Axes | None = None,
) -> Figure:
    """Coached trajectories from a grid of initial conditions in the plane of two variables.

    ``paths``: one array per trajectory, shape (steps, 2); ``ax``: the axes to draw on (default: a
    new figure). Returns the figure.
    """
    fig, axes, new = figure_axes(ax, 1, 1, (7, 6))
    ax = axes[0, 0]
    for p in paths:
        if len(p):
            ax.plot(p[:, 0], p[:, 1], color="C0", lw=0.6, alpha=0.8)
            ax.plot(p[0, 0], p[0, 1], "o", color="C0", ms=2)
            if len(p) > 2:
                ax.annotate(
                    "", xy=p[2], xytext=p[0], arrowprops={"arrowstyle": "->", "color": "C0", "lw": 0.6}
                )
    ax.set_xlabel(f"{variables[0]} ({units.get(variables[0], '')})")
    ax.set_ylabel(f"{variables[1]} ({units.get(variables[1], '')})")
    ax.set_title(title, fontsize=9)
    if new:
        fig.tight_layout()
    return fig
