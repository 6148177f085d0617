"""Plots of a coach analysis (matplotlib; compute lives in :mod:`pidlab.controller.analysis`).

Each ``plot_*`` function draws on a given ``ax`` (or a new figure) and returns the figure.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import control as ct
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from pidlab.controller.analysis import CoachAnalysis, LoopMargins, initial_response, loop_at_actuator
from pidlab.controller.pid import Coach


def _omega(dt: float) -> np.ndarray:
    top = np.pi / dt
    return np.logspace(np.log10(top) - 4, np.log10(top) - 1e-6, 1500)


def plot_bode(L: ct.StateSpace, margins: LoopMargins, dt: float, title: str) -> plt.Figure:
    """Bode plot of a loop transfer function with gain and phase margins marked."""
    w = _omega(dt)
    resp = np.asarray(L.frequency_response(w).complex).ravel()
    mag = 20 * np.log10(np.abs(resp))
    phase = np.unwrap(np.angle(resp)) * 180 / np.pi
    fig, (a1, a2) = plt.subplots(2, 1, sharex=True, figsize=(7, 6))
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
    a1.axvline(np.pi / dt, color="0.5", lw=0.8)
    a1.legend(loc="best", fontsize=8) if np.isfinite(margins.phase_crossover) else None
    a2.legend(loc="best", fontsize=8) if np.isfinite(margins.gain_crossover) else None
    a1.set_title(title)
    fig.tight_layout()
    return fig


def plot_nyquist(L: ct.StateSpace, dt: float, title: str) -> plt.Figure:
    """Nyquist curve of a loop (positive and negative frequencies) with the -1 point."""
    w = _omega(dt)
    resp = np.asarray(L.frequency_response(w).complex).ravel()
    fig, ax = plt.subplots(figsize=(6, 6))
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
    ax.set_title(title)
    fig.tight_layout()
    return fig


def plot_poles(analysis: CoachAnalysis) -> plt.Figure:
    """Closed-loop poles (discrete, z-plane) with the unit circle."""
    fig, ax = plt.subplots(figsize=(6, 6))
    circle = np.exp(1j * np.linspace(0, 2 * np.pi, 400))
    ax.plot(circle.real, circle.imag, "k", lw=0.8)
    ol = np.linalg.eigvals(analysis.linearization.Ad)
    ax.plot(ol.real, ol.imag, "x", color="0.5", label="open loop (plant)")
    z = np.array([p.value for p in analysis.discrete.poles])
    colors = ["C0" if p.stable else "C3" for p in analysis.discrete.poles]
    ax.scatter(z.real, z.imag, edgecolors=colors, marker="o", facecolors="none", label="closed loop")
    ax.set_aspect("equal")
    ax.set_xlabel("Re z")
    ax.set_ylabel("Im z")
    ax.legend(fontsize=8)
    ax.set_title(f"{analysis.env_id} / {analysis.spec_name}: poles (dt = {analysis.dt:g} s)")
    fig.tight_layout()
    return fig


def plot_responses(analysis: CoachAnalysis, coach: Coach, horizon_s: float = 20.0) -> plt.Figure:
    """Closed-loop setpoint-step and initial-deviation responses of every loop's signal."""
    cl = analysis.discrete.sys
    dt = analysis.dt
    steps = round(horizon_s / dt)
    t = np.arange(steps) * dt
    lay = coach.layout
    n = lay.n_loops
    fig, axes = plt.subplots(n, 2, figsize=(10, 2.4 * n), squeeze=False)
    for j, lp in enumerate(lay.spec.loops):
        sig = lay.observation_names.index(lp.signal)
        resp = ct.forced_response(cl, T=t, U=np.tile(np.eye(n)[j][:, None], (1, steps)))
        axes[j, 0].plot(t, np.asarray(resp.outputs)[sig])
        axes[j, 0].set_title(f"unit step of {lp.name} setpoint -> {lp.signal}", fontsize=9)
        ys = initial_response(cl, analysis.plant, sig, 0.05, steps)[:, sig]
        axes[j, 1].plot(t, ys)
        axes[j, 1].set_title(f"initial {lp.signal} = 0.05 -> {lp.signal}", fontsize=9)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    fig.tight_layout()
    return fig


def write_plots(analysis: CoachAnalysis, coach: Coach, folder: str | Path) -> list[Path]:
    """Write Bode and Nyquist plots per actuator loop, the pole map and the responses as PNG."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    plant = analysis.plant
    coach_d = coach.linear_model()
    ny = plant.noutputs
    coach_y = ct.ss(
        coach_d.A, np.asarray(coach_d.B)[:, :ny], coach_d.C, np.asarray(coach_d.D)[:, :ny], coach_d.dt
    )
    written = []
    for margins in analysis.discrete.margins:
        i = list(plant.input_labels).index(margins.actuator)
        L = loop_at_actuator(plant, coach_y, i)
        title = f"{analysis.spec_name}: loop broken at {margins.actuator}"
        for kind, fig in (
            ("bode", plot_bode(L, margins, analysis.dt, title)),
            ("nyquist", plot_nyquist(L, analysis.dt, title)),
        ):
            path = folder / f"{kind}_{margins.actuator}.png"
            fig.savefig(path, dpi=110)
            plt.close(fig)
            written.append(path)
    for name, fig in (("poles", plot_poles(analysis)), ("responses", plot_responses(analysis, coach))):
        path = folder / f"{name}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    return written


def _draw_bounds(ax: plt.Axes, bounds: Any, variables: tuple[str, str]) -> None:
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
            plt.Rectangle(
                (x0, y0), x1 - x0, y1 - y0, fill=False, lw=1.5, ls="--", color="C0", label="critical box"
            )
        )


def plot_roa_slice(
    result: Any,
    variables: tuple[str, str],
    trajectories: list[Any],
    units: dict[str, str],
    bounds: Any | None = None,
) -> plt.Figure:
    """The certified set in the plane of two variables, with simulated trajectories overlaid.

    ``bounds`` (:class:`pidlab.region.bounds.CriticalBounds`): also draw the takeover ellipsoid's slice and
    the critical box where they constrain these variables.
    """
    fig, ax = plt.subplots(figsize=(7, 6))
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
        ax.add_patch(plt.Rectangle((-hx, -hy), 2 * hx, 2 * hy, fill=False, lw=2, label="recoverable box"))
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
    fig.tight_layout()
    return fig


def plot_phase_portrait(
    paths: list[np.ndarray], variables: tuple[str, str], units: dict[str, str], title: str
) -> plt.Figure:
    """Coached trajectories from a grid of initial conditions in the plane of two variables."""
    fig, ax = plt.subplots(figsize=(7, 6))
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
    fig.tight_layout()
    return fig
