"""What the tuner shows, computed: the fast linear views and the checks of the form's fields.

Nothing here knows about widgets or the browser: :func:`linear_views` takes a spec and returns
a frozen :class:`LinearViews` with every number and curve the linear plots and the margins table
need; the app only draws it. It reuses the analysis of :mod:`pidlab.controller.analysis` (the same discrete
closed loop, margins and response metrics as ``pidlab analyze``), restricted to the discrete
loop that runs, so that one update takes a few tens of milliseconds on the pendulums.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, replace
from typing import Any

import control as ct
import numpy as np

from pidlab.checks import NAME_RULE, is_name
from pidlab.controller.analysis import (
    INITIAL_DEVIATION,
    LoopMargins,
    Pole,
    ResponseMetrics,
    closed_loop_report,
    initial_response,
    loop_frequency_response,
    margin_table,
    omega_grid,
    response_metrics,
    step_response,
)
from pidlab.controller.pid import Coach
from pidlab.controller.spec import CoachSpec, Loop
from pidlab.linear.linearize import Linearization, linearize
from pidlab.linear.lti import observable_part
from pidlab.plant.model import LoadedModel

GAIN_FIELDS = ("kp", "ki", "kd", "tf")
"""The loop fields the tuner edits."""

FIELD_LIMITS = {"kp": (-1e4, 1e4), "ki": (-1e4, 1e4), "kd": (-1e4, 1e4), "tf": (0.0, 10.0)}
"""Accepted range of each field (``tf`` in s, ``ki`` in 1/s, ``kd`` in s)."""

FIELD_LABELS = {"kp": "Kp", "ki": "Ki (1/s)", "kd": "Kd (s)", "tf": "derivative filter Tf (s)"}

RESPONSE_HORIZON_S = 20.0
"""Length of the step and initial-condition responses, s."""

BODE_POINTS = 400


@dataclass(frozen=True)
class TunerContext:
    """What stays fixed while one env is tuned: the model and its linearization.

    Attributes
    ----------
    loaded : LoadedModel
    lin : Linearization
        At the model card's operating point.
    plant : control.StateSpace
        The discrete plant (observable part), as analysed by ``pidlab analyze``.
    omega : ndarray, shape (BODE_POINTS,)
        Bode grid, rad/s, up to the Nyquist frequency.
    units : dict of str to str
        Unit of each observation variable.
    """

    loaded: LoadedModel
    lin: Linearization
    plant: ct.StateSpace
    omega: np.ndarray
    units: dict[str, str]

    @property
    def dt(self) -> float:
        """Control period, s."""
        return float(self.loaded.control_dt)


def tuner_context(loaded: LoadedModel) -> TunerContext:
    """Linearize ``loaded`` at its card's operating point, once per tuning session."""
    card = loaded.require_card()
    lin = linearize(loaded)
    plant, _ = observable_part(lin.sysd)
    omega = omega_grid(loaded.control_dt, BODE_POINTS)
    units = {v.name: v.unit for v in card.observation}
    return TunerContext(loaded=loaded, lin=lin, plant=plant, omega=omega, units=units)


@dataclass(frozen=True)
class FieldCheck:
    """The verdict on one form field: the accepted value, or a message to show beside it."""

    value: float | None
    message: str = ""

    @property
    def ok(self) -> bool:
        """Whether the text was accepted."""
        return self.value is not None


def check_field(field: str, text: str) -> FieldCheck:
    """Parse and range-check the text typed into a gain field.

    Parameters
    ----------
    field : {"kp", "ki", "kd", "tf"}
    text : str

    Returns
    -------
    FieldCheck
        ``value`` None and a one-line ``message`` (what was wrong, what is expected) when the
        text is not a finite number in :data:`FIELD_LIMITS`.
    """
    lo, hi = FIELD_LIMITS[field]
    label = FIELD_LABELS[field]
    stripped = text.strip()
    if not stripped:
        return FieldCheck(None, f"{label}: empty; expected a number in [{lo:g}, {hi:g}]")
    try:
        value = float(stripped)
    except ValueError:
        return FieldCheck(None, f"{label}: {stripped[:30]!r} is not a number; expected e.g. 1.5 or 2e-3")
    if not math.isfinite(value):
        return FieldCheck(None, f"{label}: {stripped!r} is not finite; expected a number in [{lo:g}, {hi:g}]")
    if not lo <= value <= hi:
        return FieldCheck(None, f"{label}: {value:g} is out of range; expected a number in [{lo:g}, {hi:g}]")
    return FieldCheck(value)


def check_name(text: str) -> FieldCheck:
    """Check a spec name for ``tuning/ENV.NAME.toml``; ``value`` is 0.0 when it is fine.

    The rule is pidlab's one rule for names in paths, :data:`pidlab.checks.NAME_RULE`.
    """
    if is_name(text.strip()):
        return FieldCheck(0.0)
    return FieldCheck(None, f"name {text.strip()[:30]!r}: expected {NAME_RULE}")


def with_loop_value(spec: CoachSpec, loop: str, field: str, value: float) -> CoachSpec:
    """A copy of ``spec`` with ``field`` of loop ``loop`` set to ``value``."""
    if field not in GAIN_FIELDS:
        raise ValueError(f"field {field!r}; expected one of {', '.join(GAIN_FIELDS)}")
    change: dict[str, Any] = {field: float(value)}
    loops = tuple(replace(lp, **change) if lp.name == loop else lp for lp in spec.loops)
    spec.loop(loop)  # raises SpecError for an unknown loop
    return replace(spec, loops=loops)


def loop_actuator(spec: CoachSpec, loop: str) -> str:
    """The actuator a loop acts through: its heaviest weight, following cascades."""
    lp: Loop = spec.loop(loop)
    seen = set()
    while lp.feeds is not None and lp.name not in seen:
        seen.add(lp.name)
        lp = spec.loop(lp.feeds)
    return max(lp.actuators, key=lambda a: abs(a[1]))[0]


@dataclass(frozen=True)
class LinearViews:
    """Everything the linear views show for one spec and one chosen loop.

    Attributes
    ----------
    loop : str
        The loop being tuned.
    actuator : str
        Where the loop transfer ``L`` of the Bode and Nyquist plots is broken.
    omega : ndarray, shape (m,)
        rad/s.
    response : ndarray of complex, shape (m,)
        ``L(exp(j omega dt))``.
    margins : tuple of LoopMargins
        Every actuator the coach drives.
    poles : tuple of Pole
        Discrete closed-loop poles.
    zeros : ndarray of complex
        Zeros from the loop's setpoint to its signal (z-plane).
    stable : bool
    spectral_radius : float
        Largest ``|z|`` of the closed-loop poles.
    t : ndarray, shape (steps,)
        s.
    step, step_u : ndarray, shape (steps,)
        The loop's signal after a unit setpoint step, and the actuator command (deviation).
    initial, initial_u : ndarray, shape (steps,)
        The loop's signal from an initial deviation
        (:data:`pidlab.controller.analysis.INITIAL_DEVIATION`), and the command.
    metrics : tuple of ResponseMetrics
        Step and initial-condition metrics of the loop.
    elapsed_s : float
        Compute time.
    """

    loop: str
    actuator: str
    omega: np.ndarray
    response: np.ndarray
    margins: tuple[LoopMargins, ...]
    poles: tuple[Pole, ...]
    zeros: np.ndarray
    stable: bool
    spectral_radius: float
    t: np.ndarray
    step: np.ndarray
    step_u: np.ndarray
    initial: np.ndarray
    initial_u: np.ndarray
    metrics: tuple[ResponseMetrics, ...]
    elapsed_s: float

    @property
    def loop_margins(self) -> LoopMargins | None:
        """Margins at :attr:`actuator` (None when the coach does not drive it)."""
        return next((m for m in self.margins if m.actuator == self.actuator), None)

    @property
    def magnitude_db(self) -> np.ndarray:
        """``20 log10 |L|``, dB."""
        with np.errstate(divide="ignore"):
            return 20.0 * np.log10(np.abs(self.response))

    @property
    def phase_deg(self) -> np.ndarray:
        """Unwrapped phase of ``L``, degrees, shifted so that it starts in (-270, 90]."""
        ph = np.rad2deg(np.unwrap(np.angle(self.response)))
        if ph.size:
            ph = ph - 360.0 * math.ceil((ph[0] - 90.0) / 360.0)
        return ph


def linear_views(ctx: TunerContext, spec: CoachSpec, loop: str) -> LinearViews:
    """The linear views of ``spec`` on ``ctx``'s plant, centred on loop ``loop``.

    Parameters
    ----------
    ctx : TunerContext
    spec : CoachSpec
    loop : str
        One of the spec's loop names.

    Returns
    -------
    LinearViews
    """
    t0 = time.perf_counter()
    loaded = ctx.loaded
    coach = Coach(spec, loaded)
    coach_d = coach.linear_model()
    plant = ctx.plant
    names = [lp.name for lp in spec.loops]
    report = closed_loop_report(plant, coach_d, names)
    actuator = loop_actuator(spec, loop)
    i = list(plant.input_labels).index(actuator)
    response = loop_frequency_response(plant, coach_d, actuator, ctx.omega)
    j = names.index(loop)
    lp = spec.loop(loop)
    lay = coach.layout
    sig = lay.observation_names.index(lp.signal)
    nobs = len(lay.observation_names)
    steps = max(round(RESPONSE_HORIZON_S / coach.dt), 10)
    stepped = step_response(report.sys, j, steps)
    initial = initial_response(report.sys, plant, sig, INITIAL_DEVIATION, steps)
    cl = report.sys
    sub = ct.ss(cl.A, np.asarray(cl.B)[:, j : j + 1], np.asarray(cl.C)[sig : sig + 1], 0.0, cl.dt)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        zeros = np.asarray(ct.zeros(sub), dtype=complex)
    metrics = response_metrics(report, coach, plant, RESPONSE_HORIZON_S, loops=(loop,))
    return LinearViews(
        loop=loop,
        actuator=actuator,
        omega=ctx.omega,
        response=response,
        margins=report.margins,
        poles=report.poles,
        zeros=zeros,
        stable=report.stable,
        spectral_radius=float(max((abs(p.value) for p in report.poles), default=0.0)),
        t=np.arange(steps) * coach.dt,
        step=stepped[:, sig],
        step_u=stepped[:, nobs + i],
        initial=initial[:, sig],
        initial_u=initial[:, nobs + i],
        metrics=metrics,
        elapsed_s=time.perf_counter() - t0,
    )


def margins_rows(views: LinearViews) -> list[dict[str, Any]]:
    """The margins table, one row per actuator, values in the units of :data:`MARGIN_COLUMNS`."""
    return margin_table(views.margins)


def scaled_bounds(bounds: dict[str, Any] | None, scale: float) -> dict[str, Any] | None:
    """A spec's ``[bounds]`` table with the critical region scaled by ``scale`` about its centre.

    The box's half-widths are multiplied by ``scale`` about the box's middle; the ellipsoid's
    safety factor ``rho`` (the coach takes over outside ``V <= rho c``) by ``scale**2``, which
    scales the takeover ellipsoid's size by ``scale``. ``scale`` 1 returns the table unchanged;
    any other value is recorded in the provenance as ``scale``. Beyond 1 the region leaves the
    certified set.
    """
    if bounds is None or scale == 1.0:
        return bounds
    out = {k: v for k, v in bounds.items() if k not in ("box", "ellipsoid", "provenance")}
    if "ellipsoid" in bounds:
        e = dict(bounds["ellipsoid"])
        e["rho"] = float(e["rho"]) * scale**2
        out["ellipsoid"] = e
    if "box" in bounds:
        box = {}
        for name, (lo, hi) in bounds["box"].items():
            mid, half = (lo + hi) / 2.0, (hi - lo) / 2.0
            box[name] = [mid - scale * half, mid + scale * half]
        out["box"] = box
    prov = dict(bounds.get("provenance", {}))
    prov["scale"] = float(scale) * float(prov.get("scale", 1.0))
    out["provenance"] = prov
    return out
