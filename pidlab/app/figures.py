"""Bokeh figures of the tuner and the column data that feeds them.

Each ``*_data`` function is pure: it turns a computed result into the columns of a
``ColumnDataSource``; the app assigns them to ``source.data`` and Bokeh sends the new arrays
to the browser, which redraws without a page reload. Sources carry a ``name`` (e.g.
``"bode-mag"``) so that a test can find them in the browser's Bokeh document.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from bokeh.models import ColumnDataSource
from bokeh.models.annotations import Span
from bokeh.plotting import figure

from pidlab.app.live import LinearViews
from pidlab.region.roa import ellipse_slice

STABLE = "#2b8a3e"
UNSTABLE = "#c92a2a"
PLOT_TOOLS = "pan,wheel_zoom,reset,save,hover"
"""Every plot's tools (no box zoom: its overlay is four more models per plot, sent to every tab)."""


def _finite(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=float).copy()
    a[~np.isfinite(a)] = np.nan
    return a


@dataclass(frozen=True)
class Sources:
    """Every data source of the tuner's plots."""

    bode_mag: ColumnDataSource
    bode_phase: ColumnDataSource
    bode_markers: ColumnDataSource
    nyquist: ColumnDataSource
    nyquist_markers: ColumnDataSource
    step: ColumnDataSource
    initial: ColumnDataSource
    poles: ColumnDataSource
    zeros: ColumnDataSource
    roa_set: ColumnDataSource
    roa_paths: ColumnDataSource
    bounds_box: ColumnDataSource
    bounds_ellipse: ColumnDataSource


def make_sources() -> Sources:
    """Empty, named sources."""

    def src(name: str, *cols: str) -> ColumnDataSource:
        return ColumnDataSource({c: [] for c in cols}, name=name)

    return Sources(
        bode_mag=src("bode-mag", "w", "db"),
        bode_phase=src("bode-phase", "w", "deg"),
        bode_markers=src("bode-markers", "w", "db", "deg", "label"),
        nyquist=src("nyquist", "re", "im", "re_m", "im_m"),
        nyquist_markers=src("nyquist-markers", "re", "im", "label"),
        step=src("step", "t", "y", "u"),
        initial=src("initial", "t", "y", "u"),
        poles=src("poles", "re", "im", "color", "label"),
        zeros=src("zeros", "re", "im"),
        roa_set=src("roa-set", "x", "y"),
        roa_paths=src("roa-paths", "xs", "ys", "color"),
        bounds_box=src("bounds-box", "x", "y"),
        bounds_ellipse=src("bounds-ellipse", "x", "y"),
    )


def _fig(title: str, x_label: str, y_label: str, **kw: Any) -> Any:
    f = figure(
        title=title,
        x_axis_label=x_label,
        y_axis_label=y_label,
        tools=PLOT_TOOLS,
        sizing_mode="stretch_width",
        height=kw.pop("height", 260),
        **kw,
    )
    f.title.text_font_size = "11pt"  # type: ignore[union-attr]
    f.toolbar.logo = None
    return f


def _lean(f: Any) -> Any:
    """``f`` without the glyphs Bokeh adds for unselected and muted points (the tuner has neither).

    Every glyph method adds two copies of its glyph, drawn for points outside a selection and for
    a muted legend entry; without selection tools or muting they are never drawn, yet every tab's
    document would carry them (a third of the plots' models).
    """
    for r in f.renderers:
        r.nonselection_glyph = None
        r.muted_glyph = None
    return f


def bode_figures(s: Sources) -> tuple[Any, Any]:
    """Magnitude and phase of the loop transfer, with the margins marked."""
    mag = _fig("Bode: |L|", "frequency (rad/s)", "magnitude (dB)", x_axis_type="log", height=220)
    mag.line("w", "db", source=s.bode_mag, line_width=2)
    mag.add_layout(Span(location=0, dimension="width", line_dash="dashed", line_color="gray"))
    mag.scatter("w", "db", source=s.bode_markers, size=9, color=UNSTABLE, marker="circle")
    ph = _fig("Bode: phase of L", "frequency (rad/s)", "phase (deg)", x_axis_type="log", height=220)
    ph.x_range = mag.x_range
    ph.line("w", "deg", source=s.bode_phase, line_width=2)
    for level in (-180, 180):
        ph.add_layout(Span(location=level, dimension="width", line_dash="dashed", line_color="gray"))
    ph.scatter("w", "deg", source=s.bode_markers, size=9, color=UNSTABLE, marker="circle")
    return _lean(mag), _lean(ph)


def nyquist_figure(s: Sources) -> Any:
    """Nyquist plot of the loop transfer with the critical point -1 and the unit circle."""
    f = _fig("Nyquist: L", "real", "imaginary", height=440, match_aspect=True)
    t = np.linspace(0, 2 * np.pi, 200)
    f.line(np.cos(t), np.sin(t), line_color="lightgray", line_dash="dotted")
    f.line("re", "im", source=s.nyquist, line_width=2, legend_label="ω > 0")
    f.line("re_m", "im_m", source=s.nyquist, line_width=1, line_dash="dashed", legend_label="ω < 0")
    f.scatter([-1.0], [0.0], marker="cross", size=14, color=UNSTABLE, line_width=3, legend_label="-1")
    f.scatter("re", "im", source=s.nyquist_markers, size=8, color="black")
    f.legend.location = "bottom_right"
    f.legend.label_text_font_size = "8pt"
    return _lean(f)


def response_figures(s: Sources) -> tuple[Any, Any]:
    """Step response of the loop's setpoint and the initial-condition response of its signal."""
    step = _fig("Step: setpoint -> signal", "time (s)", "signal deviation")
    step.line("t", "y", source=s.step, line_width=2, legend_label="signal")
    step.add_layout(Span(location=1.0, dimension="width", line_dash="dashed", line_color="gray"))
    init = _fig("Initial deviation of the signal", "time (s)", "signal deviation")
    init.line("t", "y", source=s.initial, line_width=2, legend_label="signal")
    init.add_layout(Span(location=0.0, dimension="width", line_dash="dashed", line_color="gray"))
    for f, src in ((step, s.step), (init, s.initial)):
        f.line("t", "u", source=src, line_width=1, color="orange", legend_label="actuator command")
        f.legend.label_text_font_size = "8pt"
    return _lean(step), _lean(init)


def pole_zero_figure(s: Sources) -> Any:
    """Discrete closed-loop poles and the loop's zeros in the z-plane, with the unit circle."""
    f = _fig("Pole-zero map (z-plane)", "real", "imaginary", height=300, match_aspect=True)
    t = np.linspace(0, 2 * np.pi, 200)
    f.line(np.cos(t), np.sin(t), line_color="gray", line_dash="dashed")
    f.scatter(
        "re", "im", source=s.poles, marker="x", size=12, line_width=2, color="color", legend_label="poles"
    )
    f.scatter(
        "re",
        "im",
        source=s.zeros,
        marker="circle",
        size=9,
        fill_color=None,
        line_width=2,
        legend_label="zeros",
    )
    f.legend.label_text_font_size = "8pt"
    return _lean(f)


def roa_figure(s: Sources, variables: tuple[str, str], units: dict[str, str]) -> Any:
    """The region-of-attraction slice with simulated trajectories and the critical bounds."""
    x, y = variables
    f = _fig(
        f"Region of attraction: slice ({x}, {y})",
        f"{x} ({units.get(x, '')})",
        f"{y} ({units.get(y, '')})",
        height=420,
    )
    f.multi_line("xs", "ys", source=s.roa_paths, line_color="color", line_alpha=0.6, line_width=1)
    f.line("x", "y", source=s.roa_set, line_width=3, color="black", legend_label="certified set (preview)")
    f.line(
        "x",
        "y",
        source=s.bounds_ellipse,
        line_width=2,
        color="purple",
        line_dash="dashed",
        legend_label="takeover ellipsoid",
    )
    f.line("x", "y", source=s.bounds_box, line_width=2, color="darkorange", legend_label="critical box")
    f.legend.label_text_font_size = "8pt"
    f.legend.location = "top_right"
    return _lean(f)


def bode_data(v: LinearViews) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    """Columns of the Bode magnitude, phase and margin markers."""
    db, deg = _finite(v.magnitude_db), _finite(v.phase_deg)
    mw, mdb, mdeg, labels = [], [], [], []
    m = v.loop_margins
    if m is not None:
        for w, label in (
            (m.gain_crossover, f"phase margin {m.phase_margin_deg:.1f} deg"),
            (m.phase_crossover, f"gain margin {m.gain_margin_db:.1f} dB"),
        ):
            if math.isfinite(w):
                k = int(np.argmin(np.abs(np.log(v.omega) - math.log(w))))
                mw.append(w)
                mdb.append(db[k])
                mdeg.append(deg[k])
                labels.append(label)
    return (
        {"w": v.omega, "db": db},
        {"w": v.omega, "deg": deg},
        {"w": mw, "db": mdb, "deg": mdeg, "label": labels},
    )


NYQUIST_CLIP = 10.0
"""Nyquist points are drawn up to this modulus (the region around -1 is what matters)."""


def nyquist_data(v: LinearViews) -> tuple[dict[str, Any], dict[str, Any]]:
    """Columns of the Nyquist curve (clipped to :data:`NYQUIST_CLIP`) and its crossover markers."""
    r = v.response.copy()
    big = np.abs(r) > NYQUIST_CLIP
    r[big] = r[big] / np.abs(r[big]) * NYQUIST_CLIP
    curve = {"re": r.real, "im": r.imag, "re_m": r.real, "im_m": -r.imag}
    markers: dict[str, list[Any]] = {"re": [], "im": [], "label": []}
    m = v.loop_margins
    if m is not None and math.isfinite(m.gain_crossover):
        k = int(np.argmin(np.abs(v.omega - m.gain_crossover)))
        markers = {"re": [r[k].real], "im": [r[k].imag], "label": ["gain crossover"]}
    return curve, markers


def response_data(v: LinearViews) -> tuple[dict[str, Any], dict[str, Any]]:
    """Columns of the step and initial-condition responses."""
    return (
        {"t": v.t, "y": _finite(v.step), "u": _finite(v.step_u)},
        {"t": v.t, "y": _finite(v.initial), "u": _finite(v.initial_u)},
    )


def pole_zero_data(v: LinearViews) -> tuple[dict[str, Any], dict[str, Any]]:
    """Columns of the closed-loop poles (coloured by stability) and the loop's zeros."""
    z = np.array([p.value for p in v.poles], dtype=complex)
    colors = [STABLE if p.stable else UNSTABLE for p in v.poles]
    labels = [f"|z| = {abs(p.value):.4f}, damping {p.damping:.2f}" for p in v.poles]
    zeros = v.zeros[np.isfinite(v.zeros)]
    return (
        {"re": z.real, "im": z.imag, "color": colors, "label": labels},
        {"re": zeros.real, "im": zeros.imag},
    )


def _slice(P: np.ndarray, center: np.ndarray, level: float, idx: tuple[int, int]) -> dict[str, Any]:
    xy = ellipse_slice(P, center, level, idx)
    return {"x": xy[0], "y": xy[1]}


def roa_data(preview: Any) -> tuple[dict[str, Any], dict[str, Any]]:
    """Columns of the certified set's slice and of the simulated trajectories."""
    roa = preview.roa
    x, y = preview.variables
    if roa.lyapunov is not None:
        L = roa.lyapunov
        idx = (L.variables.index(x), L.variables.index(y))
        boundary = _slice(L.P_y, L.center, roa.level, idx)
    else:
        hx, hy = roa.box.get(x, math.nan), roa.box.get(y, math.nan)
        boundary = {"x": [-hx, hx, hx, -hx, -hx], "y": [-hy, -hy, hy, hy, -hy]}
    paths = {
        "xs": [p[:, 0] for p in preview.paths],
        "ys": [p[:, 1] for p in preview.paths],
        "color": [STABLE if ok else UNSTABLE for ok in preview.recovered],
    }
    return boundary, paths


def bounds_data(
    bounds: dict[str, Any] | None, variables: tuple[str, str]
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Columns of the critical box and the takeover ellipsoid (``V <= rho c``) in the slice."""
    empty: dict[str, Any] = {"x": [], "y": []}
    if not bounds:
        return empty, empty
    x, y = variables
    box = empty
    if "box" in bounds and x in bounds["box"]:
        (x0, x1) = bounds["box"][x]
        (y0, y1) = bounds["box"].get(y, [math.nan, math.nan])
        if not math.isfinite(y0):
            y0, y1 = -1e3, 1e3
        box = {"x": [x0, x1, x1, x0, x0], "y": [y0, y0, y1, y1, y0]}
    ellipse = empty
    e = bounds.get("ellipsoid")
    if e and x in e["variables"] and y in e["variables"]:
        idx = (e["variables"].index(x), e["variables"].index(y))
        ellipse = _slice(np.asarray(e["shape"]), np.asarray(e["center"]), e["level"] * e["rho"], idx)
    return box, ellipse
