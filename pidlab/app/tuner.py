"""The tuner's page: widgets, layout and the callbacks that tie them to the computations.

One :class:`Tuner` per browser session (or notebook cell). The linear views are recomputed
in the widget callback itself (tens of milliseconds on the pendulums); everything slow goes to
a :class:`pidlab.app.jobs.JobRunner` and comes back through a periodic poll, so the page never
waits for it.
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import math
import time
import uuid
from dataclasses import replace
from pathlib import Path
from typing import Any

import panel as pn
from panel.io import hold

from pidlab import __version__
from pidlab.app import figures as F
from pidlab.app.jobs import JobRunner, JobUpdate, slice_variables
from pidlab.app.live import (
    FIELD_LABELS,
    FIELD_LIMITS,
    GAIN_FIELDS,
    LinearViews,
    TunerContext,
    check_field,
    check_name,
    linear_views,
    margins_rows,
    scaled_bounds,
    tuner_context,
    with_loop_value,
)
from pidlab.checks import path_under
from pidlab.controller.analysis import MARGIN_COLUMNS
from pidlab.controller.spec import (
    CoachSpec,
    dumps_spec,
    load_spec,
    loads_spec,
    validate_against,
    writing_spec,
)
from pidlab.errors import PidlabError
from pidlab.files import read_file
from pidlab.plant.model import load_model

POLL_MS = 150
"""Period of the poll that collects background results, ms."""

DEBOUNCE_S = 0.4
"""Slow jobs start this long after the last change (a slider drag is many changes)."""

SLOW_KINDS = ("roa", "rollout")

MAX_TEXT = 200
"""The longest text a form field takes from the browser."""

# inline styles: a pane's stylesheets are Bokeh models, and replacing them on every update makes
# Bokeh recompute the document's model graph (~90 ms a time on this page)
RED = "style='color:#c92a2a'"
GREEN = "style='color:#2b8a3e'"
TABLE = "style='border-collapse:collapse;font-size:0.85em'"
TH = "style='border:1px solid #ddd;padding:3px 6px;background:#f3f3f3'"
TD = "style='border:1px solid #ddd;padding:3px 6px;text-align:right'"
TD_LEFT = "style='border:1px solid #ddd;padding:3px 6px;text-align:left'"
TD_BAD = "style='border:1px solid #ddd;padding:3px 6px;text-align:right;color:#c92a2a;font-weight:bold'"


class _HTML(pn.pane.HTML):
    """An HTML pane whose updates send only its text.

    Panel resends a pane's style sheets with every update; they are Bokeh models, so Bokeh then
    recomputes the whole document's model graph (~90 ms a time on this page, measured). The
    tuner never changes a pane's styles after it is made, so updates leave them out.
    """

    def _update(self, ref: str, model: Any) -> None:
        props = self._get_properties(model.document)
        props.pop("stylesheets", None)
        model.update(**props)


def _html(object: str = "", **kw: Any) -> Any:
    """An HTML pane for text the tuner updates (styles are inline: see :data:`RED`)."""
    return _HTML(object, **kw)


def _heading(text: str, level: int = 3) -> Any:
    """A heading as plain HTML (a Markdown string would be parsed again for every tab)."""
    return pn.pane.HTML(f"<h{level}>{html.escape(text)}</h{level}>")


def _number(value: Any) -> float | None:
    """``value`` as a finite float, or None (a string, a bool, None, NaN or an infinity)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return float(value) if math.isfinite(value) else None


class _Slider(pn.widgets.FloatSlider):
    """A slider whose value the server keeps within its range, whatever a browser sends.

    A browser (or anything that speaks Bokeh's websocket protocol) may send any property of a
    widget's model, and Panel would apply it: a value past the slider's end, or a new end. This
    slider takes only its value from the browser, clamped to ``[start, end]``; anything else
    (range, step, label, a value that is not a finite number) is ignored.
    """

    def _process_property_change(self, props: dict[str, Any]) -> dict[str, Any]:
        kept = {}
        for key in ("value", "value_throttled"):
            v = _number(props.get(key))
            if v is not None:
                kept[key] = min(max(v, float(self.start)), float(self.end))
        return dict(super()._process_property_change(kept))


class _Text(pn.widgets.TextInput):
    """A text field that takes only its text from the browser (at most :data:`MAX_TEXT` characters)."""

    def _process_property_change(self, props: dict[str, Any]) -> dict[str, Any]:
        kept = {
            k: v
            for k, v in props.items()
            if k in ("value", "value_input") and isinstance(v, str) and len(v) <= MAX_TEXT
        }
        return dict(super()._process_property_change(kept))


class _Select(pn.widgets.Select):
    """A selector that takes from the browser only one of the options it offers."""

    def _process_property_change(self, props: dict[str, Any]) -> dict[str, Any]:
        value = props.get("value")
        labels = [str(label) for label in self.labels]
        kept = {"value": value} if isinstance(value, str) and value in labels else {}
        return dict(super()._process_property_change(kept))


class _Checkbox(pn.widgets.Checkbox):
    """A checkbox that takes from the browser only whether it is ticked."""

    def _process_property_change(self, props: dict[str, Any]) -> dict[str, Any]:
        kept = {"active": props["active"]} if isinstance(props.get("active"), bool) else {}
        return dict(super()._process_property_change(kept))


class _Button(pn.widgets.Button):
    """A button that takes nothing from the browser but its clicks (events, not properties)."""

    def _process_property_change(self, props: dict[str, Any]) -> dict[str, Any]:
        return dict(super()._process_property_change({}))


def _value(widget: Any) -> float:
    return float(widget.value)


def _fmt(v: float, digits: int = 3) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "—"
    if math.isinf(v):
        return "∞" if v > 0 else "-∞"
    return f"{v:.{digits}g}"


def _gains_only(spec: CoachSpec) -> CoachSpec:
    return replace(spec, name="", description="", provenance={}, bounds=None)


def _slider_range(value: float, field: str) -> tuple[float, float]:
    lo, hi = FIELD_LIMITS[field]
    if field == "tf":
        return 0.0, max(0.2, 3.0 * value)
    if value == 0.0:
        return -1.0, 1.0
    a, b = sorted((0.0, 3.0 * value))
    return max(lo, a), min(hi, b)


class Tuner:
    """The interactive tuner for one env.

    Parameters
    ----------
    spec : CoachSpec
        The coach to start from (its ``[bounds]`` are taken as valid for its gains).
    source : str
        Where the spec came from (shown on the page).
    tuning_dir : Path
        Where *Save* writes ``ENV.NAME.toml`` and *Load* looks for specs.
    runner : JobRunner, optional
        Shared worker pool; default: a new one.
    animation : {"auto", "mujoco", "schematic"}
        How rollout frames are drawn.
    bounds_samples : int
        Simulated initial states that certify the region behind *Derive bounds* (as
        ``pidlab bounds --samples``).
    context : TunerContext, optional
        The env's model and linearization, shared by the tabs of one server; default: made here.
    """

    def __init__(
        self,
        spec: CoachSpec,
        source: str,
        tuning_dir: Path,
        runner: JobRunner | None = None,
        animation: str = "auto",
        bounds_samples: int = 1000,
        context: TunerContext | None = None,
    ) -> None:
        self.ctx = context if context is not None else tuner_context(load_model(spec.env_id))
        self.loaded = self.ctx.loaded
        self.env_id = spec.env_id
        self.tuning_dir = Path(tuning_dir)
        self.runner = runner or JobRunner()
        self.animation = animation
        self.bounds_samples = bounds_samples
        self.source = source
        self.variables = slice_variables(spec)
        self.sources = F.make_sources()
        self.owner = uuid.uuid4().hex
        self._guard = False
        self._attached = False  # True once the page is live (the first poll)
        self._said: dict[int, int] = {}  # a status pane's id -> the version of its latest text (_say)
        self.changed_at = time.monotonic()  # when the user last changed something
        self._doc: Any = None  # the served document, once the page is made in one
        self._invalid: set[str] = set()
        self._slow_due: float | None = None
        self._views: LinearViews | None = None
        self._roa_preview: Any = None
        self._bounds_job_spec: CoachSpec | None = None
        self._build_widgets()
        self._adopt(spec, source)

    # ------------------------------------------------------------------ widgets and layout

    def _build_widgets(self) -> None:
        self._build_gain_widgets()
        self._build_tuning_widgets()
        self._build_file_widgets()
        self._build_views()

    def _build_gain_widgets(self) -> None:
        """The loop selector, and a slider, a text field and a message per gain."""
        self.title = _html(sizing_mode="stretch_width")
        self.loop_select = _Select(label="Loop", options=[], css_classes=["pidlab-loop"])
        self.loop_select.param.watch(self._on_loop, "value")
        self.sliders: dict[str, Any] = {}
        self.inputs: dict[str, Any] = {}
        self.messages: dict[str, Any] = {}
        for f in GAIN_FIELDS:
            s = _Slider(
                label=FIELD_LABELS[f],
                start=0.0,
                end=1.0,
                step=0.01,
                value=0.0,
                css_classes=[f"pidlab-slider-{f}"],
                sizing_mode="stretch_width",
            )
            s.param.watch(lambda ev, f=f: self._on_slider(f, ev.new), "value")
            t = _Text(label=f"{FIELD_LABELS[f]} value", width=130, css_classes=[f"pidlab-input-{f}"])
            t.param.watch(lambda ev, f=f: self._on_text(f, ev.new), "value")
            self.sliders[f], self.inputs[f] = s, t
            self.messages[f] = _html("", css_classes=[f"pidlab-msg-{f}"], sizing_mode="stretch_width")

    def _build_tuning_widgets(self) -> None:
        """Automatic tuning (response time, robustness) and the critical bounds' scale and button."""
        self.response_time = _Slider(
            label="Response time (s)",
            start=0.01,
            end=1.0,
            step=0.01,
            value=0.1,
            css_classes=["pidlab-response-time"],
        )
        self.robustness = _Slider(
            label="Robustness", start=0.0, end=1.0, step=0.05, value=0.67, css_classes=["pidlab-robustness"]
        )
        self.targets = _html("")
        self.response_time.param.watch(lambda ev: self._autotune(), "value_throttled")
        self.robustness.param.watch(lambda ev: self._autotune(), "value_throttled")
        self.robustness.param.watch(lambda ev: self._show_targets(), "value")
        self.response_time.param.watch(lambda ev: self._show_targets(), "value")
        self.scale = _Slider(
            label="Critical-bound scale",
            start=0.25,
            end=3.0,
            step=0.05,
            value=1.0,
            css_classes=["pidlab-scale"],
        )
        self.scale.param.watch(lambda ev: self._draw_bounds(), "value")
        self.autotune_button = _Button(label="Auto-tune", color="primary", css_classes=["pidlab-autotune"])
        self.autotune_button.on_click(lambda ev: self._autotune())
        self.bounds_button = _Button(label="Derive bounds", color="primary", css_classes=["pidlab-derive"])
        self.bounds_button.on_click(lambda ev: self._derive_bounds())

    def _build_file_widgets(self) -> None:
        """Save and Load, with their messages."""
        self.name_input = _Text(label="Spec name", width=200, css_classes=["pidlab-name"])
        self.name_msg = _html("", css_classes=["pidlab-msg-name"])
        self.overwrite = _Checkbox(label="overwrite an existing file", value=False)
        self.save_button = _Button(label="Save to tuning/", color="success", css_classes=["pidlab-save"])
        self.save_button.on_click(lambda ev: self._save())
        self.load_select = _Select(label="Spec file", options=[], css_classes=["pidlab-load-select"])
        self.load_button = _Button(label="Load", css_classes=["pidlab-load"])
        self.load_button.on_click(lambda ev: self._load())
        self.file_msg = _html("", css_classes=["pidlab-file-msg"], sizing_mode="stretch_width")

    def _build_views(self) -> None:
        """The text panes, the slow jobs' status and progress, and the figures."""
        self.margins = _html("", css_classes=["pidlab-margins"], sizing_mode="stretch_width")
        self.summary = _html("", css_classes=["pidlab-summary"], sizing_mode="stretch_width")
        self.bounds_info = _html("", css_classes=["pidlab-bounds"], sizing_mode="stretch_width")
        self.status: dict[str, Any] = {}  # a slow job's stage, with its progress bar while it runs
        for kind in ("roa", "rollout", "autotune", "bounds"):
            self.status[kind] = _html("", css_classes=[f"pidlab-status-{kind}"], sizing_mode="stretch_width")
        self.score = _html("", css_classes=["pidlab-score"], sizing_mode="stretch_width")
        self.animation_pane = _html("", css_classes=["pidlab-animation"], min_height=250)
        src = self.sources
        self.bode_mag, self.bode_phase = F.bode_figures(src)
        self.nyquist = F.nyquist_figure(src)
        self.step_fig, self.initial_fig = F.response_figures(src)
        self.pz = F.pole_zero_figure(src)
        self.roa_fig = F.roa_figure(src, self.variables, self.ctx.units)

    def panel(self, plots: bool = True) -> Any:
        """The page, and the periodic poll that feeds it background results (see :meth:`layout`)."""
        pn.state.add_periodic_callback(self._poll, period=POLL_MS)
        if pn.state.curdoc is not None and getattr(pn.state.curdoc, "session_context", None) is not None:
            self._doc = pn.state.curdoc
            pn.state.on_session_destroyed(lambda ctx: self.runner.cancel(self.owner))
        self._refresh_files()  # the tuner may have been built a while before it is shown
        return self.layout(plots)

    def layout(self, plots: bool = True) -> Any:
        """The page's widgets and views, without the poll (:meth:`panel` is the live page).

        Without ``plots`` the plots' places stay empty until :meth:`show_plots`.
        """
        page = pn.Row(self._controls(), self._views_column(), sizing_mode="stretch_width")
        if plots:
            self.show_plots()
        return page

    def _controls(self) -> Any:
        """The left column: gains, automatic tuning, critical bounds, spec file."""
        gains = []
        for f in GAIN_FIELDS:
            gains.append(pn.Row(self.sliders[f], self.inputs[f], sizing_mode="stretch_width"))
            gains.append(self.messages[f])
        return pn.Column(
            _heading("Coach"),
            self.loop_select,
            *gains,
            _heading("Automatic tuning"),
            self.response_time,
            self.robustness,
            self.targets,
            self.autotune_button,
            self.status["autotune"],
            _heading("Critical bounds"),
            self.scale,
            self.bounds_button,
            self.status["bounds"],
            self.bounds_info,
            _heading("Spec file"),
            self.name_input,
            self.name_msg,
            self.overwrite,
            self.save_button,
            pn.Row(self.load_select, self.load_button),
            self.file_msg,
            width=400,
        )

    def _views_column(self) -> Any:
        """The right column: linear views, margins, region of attraction, the coach alone.

        The plots go into two slots that :meth:`show_plots` fills (the plots are most of a page).
        """
        self._plot_slots = (pn.Column(sizing_mode="stretch_width"), pn.Column(sizing_mode="stretch_width"))
        return pn.Column(
            self.title,
            self._plot_slots[0],
            _heading("Stability margins (discrete loop, broken at each actuator)", 4),
            self.margins,
            self.summary,
            pn.Row(
                pn.Column(self.status["roa"], self._plot_slots[1], sizing_mode="stretch_width"),
                pn.Column(
                    _heading("The coach alone on the real env", 4),
                    self.status["rollout"],
                    self.score,
                    self.animation_pane,
                    sizing_mode="stretch_width",
                ),
                sizing_mode="stretch_width",
            ),
            sizing_mode="stretch_width",
        )

    def show_plots(self) -> None:
        """Put the plots in the page made by :meth:`layout` (once; later calls do nothing).

        A server sends a new tab its controls and numbers first and the plots right after, so
        that when several tabs open at once each is usable before the last one's plots are sent.
        """
        linear, roa = self._plot_slots
        if linear.objects:
            return

        wide = {"sizing_mode": "stretch_width"}
        bode = pn.Column(pn.pane.Bokeh(self.bode_mag), pn.pane.Bokeh(self.bode_phase), **wide)
        step, initial, pz = (pn.pane.Bokeh(f, **wide) for f in (self.step_fig, self.initial_fig, self.pz))
        with hold():
            linear.objects = [
                pn.Row(bode, pn.pane.Bokeh(self.nyquist, **wide), **wide),
                pn.Row(step, initial, pz, **wide),
            ]
            roa.objects = [pn.pane.Bokeh(self.roa_fig, **wide)]

    # ------------------------------------------------------------------ state

    def _push(self, draw: Any) -> None:
        """Run ``draw``, which writes to plain Bokeh models (the plots' data sources).

        In a served page, plain Bokeh models may only change while the server holds the
        document's lock. Slider callbacks run under it, and then ``draw`` runs at once;
        otherwise (e.g. a text field's Enter event, which Panel processes unlocked) it runs as
        the next tick, which takes the lock. Outside a server (a notebook) it simply runs.
        """
        doc = pn.state.curdoc
        context = getattr(doc, "session_context", None) if doc is not None else None
        if not self._attached or doc is None or context is None:
            draw()
            return
        session = getattr(context, "_session", None)
        if session is not None and getattr(session, "_pending_writes", None) is not None:
            draw()  # the lock is held
        else:
            doc.add_next_tick_callback(draw)

    def _say(self, pane: Any, text: str, after_plot: bool = True) -> None:
        """Set ``pane``'s text; with ``after_plot``, only once the drawings pushed so far are sent.

        In a served page Panel sends a pane's new text at once, while the plots' data sources
        leave when the callback that changed them ends: a status such as "certified" could
        reach the browser before its plot. A text that describes drawings is therefore written
        in the next tick. Every write to a status pane goes through here and carries a version,
        so a deferred text never overwrites a newer one.
        """
        version = self._said.get(id(pane), 0) + 1
        self._said[id(pane)] = version

        def write() -> None:
            if self._said.get(id(pane)) == version:
                pane.object = text

        doc = pn.state.curdoc
        if after_plot and self._attached and doc is not None and getattr(doc, "session_context", None):
            doc.add_next_tick_callback(write)
        else:
            write()

    def closed(self) -> bool:
        """Whether this page's browser tab has gone (Bokeh keeps the session a while longer)."""
        doc = self._doc if self._doc is not None else pn.state.curdoc
        session = getattr(getattr(doc, "session_context", None), "_session", None)
        return session is not None and getattr(session, "connection_count", 1) == 0

    def _adopt(self, spec: CoachSpec, source: str) -> None:
        """Make ``spec`` the current coach (after start, load or auto-tune)."""
        self.spec = spec
        self.source = source
        self.origin = spec
        self.base_bounds = spec.bounds
        self._bounds_gains = _gains_only(spec) if spec.bounds else None
        self._guard = True
        try:
            names = [lp.name for lp in spec.loops]
            self.loop_select.options = names
            if self.loop_select.value not in names:
                self.loop_select.value = names[0]
            self.scale.value = 1.0
            self.name_input.value = spec.name
            bw = spec.provenance.get("asked_bandwidth_rad_s")
            pm = spec.provenance.get("asked_phase_margin_deg")
            self._set_targets(bw, pm)
        finally:
            self._guard = False
        self._sync_fields()
        self._refresh_files()
        self._refresh_linear()
        if self._views is not None and (bw is None or pm is None):
            m = self._views.loop_margins
            if m is not None:
                self._guard = True
                try:
                    self._set_targets(m.bandwidth if math.isfinite(m.bandwidth) else None, m.phase_margin_deg)
                finally:
                    self._guard = False
        self._show_targets()
        self.title.object = (
            f"<h2>{html.escape(self.env_id)} — coach <code>{html.escape(spec.name)}</code></h2>"
            f"<div>from {html.escape(source)}</div>"
        )
        self._draw_bounds()
        self._schedule_slow()

    def _set_targets(self, bandwidth: float | None, phase_margin: float | None) -> None:
        if bandwidth and math.isfinite(bandwidth) and bandwidth > 0:
            tau = 1.0 / bandwidth
            self.response_time.start = round(tau / 5.0, 4)
            self.response_time.end = round(tau * 5.0, 4)
            self.response_time.step = round(tau / 50.0, 5)
            self.response_time.value = round(tau, 4)
        if phase_margin is not None and math.isfinite(phase_margin):
            self.robustness.value = round(min(max((phase_margin - 30.0) / 45.0, 0.0), 1.0), 2)

    def _asked(self) -> tuple[float, float]:
        """(crossover rad/s, phase margin deg) asked by the pidtune-style sliders."""
        return 1.0 / _value(self.response_time), 30.0 + 45.0 * _value(self.robustness)

    def _show_targets(self) -> None:
        bw, pm = self._asked()
        self.targets.object = f"asks: gain crossover {bw:.3g} rad/s, phase margin {pm:.0f} deg"

    @property
    def loop(self) -> str:
        """The loop being tuned."""
        return str(self.loop_select.value)

    def _sync_fields(self) -> None:
        """Sliders and inputs show the current loop's values; messages cleared."""
        lp = self.spec.loop(self.loop)
        self._guard = True
        try:
            for f in GAIN_FIELDS:
                v = float(getattr(lp, f))
                lo, hi = _slider_range(v, f)
                s = self.sliders[f]
                s.start, s.end = lo, hi
                s.step = (hi - lo) / 500.0
                s.value = v
                self.inputs[f].value = f"{v:.6g}"
                self._say(self.messages[f], "", after_plot=False)
            self._invalid.clear()
        finally:
            self._guard = False

    def _bounds_valid(self) -> bool:
        return self._bounds_gains is not None and self._bounds_gains == _gains_only(self.spec)

    # ------------------------------------------------------------------ callbacks

    def _on_loop(self, event: Any) -> None:
        if self._guard:
            return
        self._sync_fields()
        self._refresh_linear()

    def _on_slider(self, field: str, value: float) -> None:
        if self._guard:
            return
        self._guard = True
        try:
            self.inputs[field].value = f"{value:.6g}"
        finally:
            self._guard = False
        self._say(self.messages[field], "", after_plot=False)
        self._invalid.discard(field)
        self._apply(field, float(value))

    def _on_text(self, field: str, text: str) -> None:
        if self._guard:
            return
        check = check_field(field, text)
        if not check.ok:
            self._invalid.add(field)
            text = f"<span class='pidlab-msg' {RED}>{html.escape(check.message)}</span>"
            self._say(self.messages[field], text, after_plot=False)
            return
        self._invalid.discard(field)
        value = float(check.value)  # type: ignore[arg-type]
        self._say(self.messages[field], "", after_plot=False)
        s = self.sliders[field]
        self._guard = True
        try:
            if not s.start <= value <= s.end:
                lo, hi = _slider_range(value, field)
                s.start, s.end = min(lo, s.start, value), max(hi, s.end, value)
                s.step = (s.end - s.start) / 500.0
            s.value = value
        finally:
            self._guard = False
        self._apply(field, value)

    def _apply(self, field: str, value: float) -> None:
        previous = self.spec
        self.spec = with_loop_value(self.spec, self.loop, field, value)
        if not self._refresh_linear(field):
            self.spec = previous  # the views could not be computed: keep the last coach that could
            return
        self._draw_bounds()
        self._schedule_slow()

    # ------------------------------------------------------------------ linear views

    def _refresh_linear(self, field: str | None = None) -> bool:
        """Recompute and redraw the linear views; False (and a message) when they cannot be computed."""
        self.changed_at = time.monotonic()
        try:
            v = linear_views(self.ctx, self.spec, self.loop)
        except PidlabError as exc:  # e.g. gains so large that the closed loop overflows
            text = f"<span class='pidlab-msg' {RED}>{html.escape(str(exc))}</span>"
            if field is not None:
                self._say(self.messages[field], text, after_plot=False)
            else:
                self._views = None
                self._say(self.summary, text, after_plot=False)
            return False
        self._views = v
        s = self.sources
        mag, ph, marks = F.bode_data(v)
        nyq, nyq_marks = F.nyquist_data(v)
        step, initial = F.response_data(v)
        poles, zeros = F.pole_zero_data(v)
        title = f"Bode: |L| at actuator {v.actuator} (loop {v.loop})"

        def draw() -> None:
            s.bode_mag.data, s.bode_phase.data, s.bode_markers.data = mag, ph, marks
            s.nyquist.data, s.nyquist_markers.data = nyq, nyq_marks
            s.step.data, s.initial.data = step, initial
            s.poles.data, s.zeros.data = poles, zeros
            self.bode_mag.title.text = title

        self._push(draw)
        self._say(self.margins, self._margins_html(v))
        self._say(self.summary, self._summary_html(v))
        if field is not None:  # the field's verdict on the views just drawn: after them, like the summary
            unstable = (
                f"<span class='pidlab-msg' {RED}>"
                f"{html.escape(FIELD_LABELS[field])}: closed loop unstable with this value "
                "(spectral radius "
                f"{v.spectral_radius:.4f} &gt; 1); saving is disabled until it is stable</span>"
            )
            self._say(self.messages[field], "" if v.stable else unstable)
        return True

    @staticmethod
    def _margins_html(v: LinearViews) -> str:
        head = "".join(f"<th {TH}>{html.escape(label)}</th>" for _, label in MARGIN_COLUMNS)
        body = []
        for row in margins_rows(v):
            cells = []
            for key, _ in MARGIN_COLUMNS:
                val = row[key]
                if key == "actuator":
                    cells.append(f"<td {TD_LEFT}>{html.escape(val)}</td>")
                    continue
                bad = (
                    (key == "pm_deg" and val < 30)
                    or (key == "gm_db" and val < 6)
                    or (key == "ms_db" and val > 6)
                )
                digits = 2 if key == "disk_alpha" else 3
                cells.append(f"<td {TD_BAD if bad else TD}>{_fmt(val, digits)}</td>")
            body.append(f"<tr>{''.join(cells)}</tr>")
        return (
            f"<table {TABLE} id='margins-table'><thead><tr>{head}</tr></thead>"
            f"<tbody>{''.join(body)}</tbody></table>"
        )

    def _summary_html(self, v: LinearViews) -> str:
        state = (
            f"<span class='pidlab-ok' {GREEN}>stable</span>"
            if v.stable
            else f"<span class='pidlab-msg' {RED}>UNSTABLE</span>"
        )
        parts = [
            f"Closed loop (discrete, dt = {self.ctx.dt * 1000:.0f} ms): {state}, spectral radius "
            f"{v.spectral_radius:.5f}; update computed in {v.elapsed_s * 1000:.0f} ms."
        ]
        for m in v.metrics:
            if m.kind == "step":
                over = "not defined" if math.isnan(m.overshoot_pct) else f"{_fmt(m.overshoot_pct)} %"
                parts.append(
                    f"Step ({html.escape(m.loop)}): overshoot {over}, rise "
                    f"{_fmt(m.rise_time_s)} s, "
                    f"settling (2 %) {_fmt(m.settling_time_s)} s, peak command {_fmt(m.peak_control)} "
                    "of the range."
                )
            else:
                parts.append(
                    f"Initial deviation {m.size:g} of {html.escape(m.signal)}: excursion "
                    f"{_fmt(m.overshoot_pct)} %, "
                    f"settling (2 %) {_fmt(m.settling_time_s)} s, peak command {_fmt(m.peak_control)} "
                    "of the range."
                )
        return "<div id='closed-loop-summary'>" + "<br>".join(parts) + "</div>"

    # ------------------------------------------------------------------ bounds

    def _current_bounds(self) -> dict[str, Any] | None:
        if not self._bounds_valid():
            return None
        return scaled_bounds(self.base_bounds, _value(self.scale))

    def _draw_bounds(self) -> None:
        b = self._current_bounds()
        box, ellipse = F.bounds_data(b, self.variables)

        def draw() -> None:
            self.sources.bounds_box.data, self.sources.bounds_ellipse.data = box, ellipse

        self._push(draw)
        if self.base_bounds and not self._bounds_valid():
            self._say(
                self.bounds_info,
                f"<span class='pidlab-msg' {RED}>The gains changed since the bounds were derived: they are "
                "not certified for these gains and will not be saved. Press <b>Derive bounds</b>.</span>",
            )
            return
        if not b:
            self._say(self.bounds_info, "No critical bounds yet: press <b>Derive bounds</b>.")
            return
        rows = []
        for name, (lo, hi) in b.get("box", {}).items():
            unit = self.ctx.units.get(name, "")
            rows.append(
                f"<tr><td {TD_LEFT}>{html.escape(name)}</td><td {TD}>{lo:.4g}</td><td {TD}>{hi:.4g}</td>"
                f"<td {TD_LEFT}>{html.escape(unit)}</td></tr>"
            )
        note = ""
        if _value(self.scale) > 1.0:
            note = (
                f"<br><span class='pidlab-msg' {RED}>scale &gt; 1: the region extends beyond the certified "
                "set</span>"
            )
        e = b.get("ellipsoid")
        ell = f"ellipsoid V &le; rho c with c = {e['level']:.4g}, rho = {e['rho']:.4g}; " if e else ""
        self._say(
            self.bounds_info,
            f"<div id='bounds-table'>{ell}method: {html.escape(str(b.get('method', '')))}"
            f"<table {TABLE}><tr><th {TH}>variable</th><th {TH}>low</th><th {TH}>high</th>"
            f"<th {TH}>unit</th></tr>"
            f"{''.join(rows)}</table>{note}</div>",
        )

    def _derive_bounds(self) -> None:
        if self._views is not None and not self._views.stable:
            text = f"<span class='pidlab-msg' {RED}>closed loop unstable: no region to certify</span>"
            self._say(self.status["bounds"], text, after_plot=False)
            return
        self._bounds_job_spec = self.spec
        self.runner.submit(self.owner, "bounds", self.spec, samples=self.bounds_samples)
        self._running("bounds", "starting", 0.0)

    # ------------------------------------------------------------------ slow jobs

    def _schedule_slow(self) -> None:
        for kind in SLOW_KINDS:
            self.runner.cancel(self.owner, kind)
            self._say(self.status[kind], "<i>waiting for the gains to settle…</i>", after_plot=False)
        self._slow_due = time.monotonic() + DEBOUNCE_S

    def _start_slow(self) -> None:
        self._slow_due = None
        if self._views is not None and not self._views.stable:
            for kind in SLOW_KINDS:
                text = f"<span class='pidlab-msg' {RED}>closed loop unstable: not simulated</span>"
                self._say(self.status[kind], text, after_plot=False)
            return
        self.runner.submit(self.owner, "roa", self.spec)
        self._running("roa", "starting", 0.0)
        self.runner.submit(self.owner, "rollout", self.spec, backend=self.animation)
        self._running("rollout", "starting", 0.0)

    def _autotune(self) -> None:
        if self._guard:
            return
        bw, pm = self._asked()
        self.runner.submit(self.owner, "autotune", self.env_id, bw, pm)
        self._running("autotune", "starting", 0.0)

    def _running(self, kind: str, stage: str, fraction: float | None) -> None:
        # the bar is part of the status pane: one model per job instead of three, in every tab
        value = "" if fraction is None else f" value='{min(max(fraction, 0.0), 1.0):.3f}'"
        self._say(
            self.status[kind],
            f"<progress class='pidlab-progress' max='1'{value} style='width:220px'></progress> "
            f"<i>{html.escape(stage)}…</i>",
            after_plot=False,
        )

    def _poll(self) -> None:
        self._attached = True
        if self.closed():
            self.runner.cancel(self.owner)  # the tab is gone: its background work is not wanted
            return
        if self._slow_due is not None and time.monotonic() >= self._slow_due and not self.runner.held:
            self._start_slow()
        for u in self.runner.poll(self.owner):
            self._update(u)

    def _update(self, u: JobUpdate) -> None:
        kind = u.kind
        if u.state == "running":
            self._running(kind, u.stage, u.fraction)
            return
        if u.state == "cancelled":  # a newer job, or "waiting for the gains to settle", has the status
            return
        if u.state == "error":
            text = f"<span class='pidlab-msg' {RED}>{html.escape(u.stage)}</span>"
            self._say(self.status[kind], text, after_plot=False)
            return
        show = {"roa": self._show_roa, "rollout": self._show_rollout, "autotune": self._show_autotune,
                "bounds": self._show_bounds}  # fmt: skip
        if kind in show:
            show[kind](u.result)

    def _show_roa(self, r: Any) -> None:
        self._roa_preview = r
        boundary, paths = F.roa_data(r)

        def draw() -> None:
            self.sources.roa_set.data, self.sources.roa_paths.data = boundary, paths

        self._push(draw)
        ok = sum(r.recovered)
        self._say(
            self.status["roa"],
            f"preview: {html.escape(r.roa.method)}; level {r.roa.level:.4g}, {r.roa.check.samples} "
            "samples, "
            f"{r.roa.check.failures} failures; {ok}/{len(r.recovered)} trajectories shown recovered "
            f"({r.roa.elapsed_s:.1f} s)",
        )

    def _show_rollout(self, r: Any) -> None:
        causes = ", ".join(f"{n} × {html.escape(c)}" for c, n in r.causes.items())
        self.score.object = (
            f"<div id='coach-score'>mean return <b>{r.mean:.1f}</b> ± {r.std:.1f} over {r.episodes} "
            "episodes "
            f"(seeds 0-{r.episodes - 1}); mean length {r.mean_length:.0f} steps; ended by: {causes}</div>"
        )
        data = base64.b64encode(r.gif).decode("ascii")
        self.animation_pane.object = (
            f"<img id='rollout-animation' data-backend='{r.backend}' src='data:image/gif;base64,{data}' "
            "style='max-width:100%'><div style='font-size:0.8em'>episode seed 0 · "
            f"{html.escape(r.note)}</div>"
        )
        self._say(self.status["rollout"], "", after_plot=False)

    def _show_autotune(self, r: Any) -> None:
        tuned = r.spec
        self._adopt(tuned, f"auto-tune (asked {r.asked_bandwidth:.3g} rad/s, {r.asked_phase_margin:.0f} deg)")
        self._say(
            self.status["autotune"],
            f"achieved: crossover {r.achieved_bandwidth:.3g} rad/s, phase margin "
            f"{r.achieved_phase_margin:.1f} "
            f"deg, Ms {r.achieved_ms:.3g} ({r.evaluations} evaluations)",
        )

    def _show_bounds(self, r: Any) -> None:
        job_spec = self._bounds_job_spec
        if job_spec is None or _gains_only(job_spec) != _gains_only(self.spec):
            self._say(
                self.status["bounds"],
                f"<span class='pidlab-msg' {RED}>bounds were derived for gains that have changed since; "
                "press Derive bounds again</span>",
                after_plot=False,
            )
            return
        self.base_bounds = r.bounds.to_table()
        self._bounds_gains = _gains_only(self.spec)
        self._guard = True
        try:
            self.scale.value = 1.0
        finally:
            self._guard = False
        self._draw_bounds()
        chk = r.roa.check
        self._say(
            self.status["bounds"],
            f"certified: level {r.roa.level:.4g}, {chk.samples} samples, {chk.failures} failures "
            f"(failure probability &lt; {chk.failure_bound_95:.3g} at 95 %)",
        )

    # ------------------------------------------------------------------ files

    def _spec_files(self) -> list[str]:
        if not self.tuning_dir.is_dir():
            return []
        return sorted(p.name for p in self.tuning_dir.glob(f"{self.env_id}.*.toml"))

    def _refresh_files(self) -> None:
        files = self._spec_files()
        self.load_select.options = files
        if files and self.load_select.value not in files:
            self.load_select.value = files[0]

    def spec_to_save(self, name: str) -> CoachSpec:
        """The spec *Save* writes: current gains, valid (scaled) bounds, honest provenance."""
        spec = replace(self.spec, name=name, bounds=self._current_bounds())
        if _gains_only(self.spec) != _gains_only(self.origin):
            v = self._views if self._views is not None else linear_views(self.ctx, self.spec, self.loop)
            prov: dict[str, Any] = {
                "tool": f"pidlab {__version__} tune --ui",
                "date": _dt.date.today().isoformat(),
                "edited_from": self.origin.name,
            }
            crossovers = [m.bandwidth for m in v.margins if m.crossovers]
            if crossovers:
                prov["achieved_bandwidth_rad_s"] = float(max(crossovers))
            prov["achieved_phase_margin_deg"] = float(min(m.phase_margin_deg for m in v.margins))
            prov["achieved_ms"] = float(max(m.ms for m in v.margins))
            prov["closed_loop_spectral_radius"] = float(v.spectral_radius)
            spec = replace(
                spec, provenance=prov, description=f"{self.origin.description} Edited in the tuner.".strip()
            )
        return spec

    def _save(self) -> None:
        name = str(self.name_input.value or "").strip()
        check = check_name(name)
        if not check.ok:
            self.name_msg.object = f"<span class='pidlab-msg' {RED}>{html.escape(check.message)}</span>"
            return
        self.name_msg.object = ""
        bad = sorted(self._invalid)
        if self._views is None or not self._views.stable:
            self.file_msg.object = (
                f"<span class='pidlab-msg' {RED}>not saved: the closed loop is unstable</span>"
            )
            return
        spec = self.spec_to_save(name)
        text = dumps_spec(spec)
        try:
            again = loads_spec(text, "tuner")
            validate_against(again, self.loaded.require_card().observation_names, self.loaded.input_names)
            path = path_under(self.tuning_dir, f"{self.env_id}.{name}.toml")
        except PidlabError as exc:
            self.file_msg.object = f"<span class='pidlab-msg' {RED}>not saved: {html.escape(str(exc))}</span>"
            return
        if path.is_file() and not self.overwrite.value and _text_or_none(path) != text:
            self.file_msg.object = (
                f"<span class='pidlab-msg' {RED}>{html.escape(str(path))} exists; tick "
                "'overwrite an existing file' to replace it</span>"
            )
            return
        try:  # the one rule of spec writers: the file's lock while replacing it, never a silent overwrite
            with writing_spec(path, force=path.is_file(), param="name") as write:
                write(spec)  # refuses a read-only file or folder, or one another command holds, in one line
        except PidlabError as exc:
            self.file_msg.object = f"<span class='pidlab-msg' {RED}>not saved: {html.escape(str(exc))}</span>"
            return
        note = " (without bounds: none valid for these gains)" if spec.bounds is None else ""
        ignored = f"; fields with errors kept their last valid value: {', '.join(bad)}" if bad else ""
        self.file_msg.object = (
            f"<span class='pidlab-ok' {GREEN}>saved {html.escape(str(path))}{note}{ignored}</span>"
        )
        self.origin = spec
        self._refresh_files()
        self.load_select.value = path.name

    def _load(self) -> None:
        name = self.load_select.value
        if not name:
            self.file_msg.object = (
                f"<span class='pidlab-msg' {RED}>no spec files for {self.env_id} in {self.tuning_dir}</span>"
            )
            return
        path = self.tuning_dir / name
        try:
            spec = load_spec(path)
            if spec.env_id != self.env_id:
                raise PidlabError(f"{path} is a coach for {spec.env_id}, not {self.env_id}")
            validate_against(spec, self.loaded.require_card().observation_names, self.loaded.input_names)
        except PidlabError as exc:
            self.file_msg.object = (
                f"<span class='pidlab-msg' {RED}>not loaded: {html.escape(str(exc))}</span>"
            )
            return
        self._adopt(spec, str(path))
        self.file_msg.object = f"<span class='pidlab-ok' {GREEN}>loaded {html.escape(str(path))}</span>"


def _text_or_none(path: Path) -> str | None:
    """The UTF-8 text of ``path``, or None when it cannot be read as such."""
    try:
        return read_file(path).decode("utf-8")
    except (OSError, UnicodeDecodeError):
        return None
