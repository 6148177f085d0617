"""Analysis of a coached closed loop with python-control.

The plant is the linearized env (:mod:`pidlab.linear.linearize`, outputs = observation variables);
the coach is the linear model read off its own discrete law
(:meth:`pidlab.controller.pid.Coach.linear_model`).
Analysis is done in discrete time at the control period (what runs) and, for comparison, in
continuous time with the coach mapped back by the inverse bilinear (Tustin) transform.

For each actuator the loop is broken at that actuator's input, the other actuators staying
closed, and ``L = -(u_cmd_i / u_i)`` (negative-feedback convention) gives: gain margins (upper
and, for open-loop unstable plants, lower), phase margin, delay margin, disk margin, the
sensitivity peak ``Ms = 1 / min|1 + L|``, and crossover frequencies.

The figures' data are computed here too, and drawn by :mod:`pidlab.report.plots`:
:func:`loop_responses` (each loop's frequency response with its margins) and
:func:`closed_loop_responses` (setpoint-step and initial-deviation responses).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import control as ct
import numpy as np

from pidlab.checks import instance
from pidlab.controller.pid import Coach
from pidlab.controller.spec import CoachSpec
from pidlab.errors import AnalysisError, PidlabError
from pidlab.linear.linearize import Linearization, linearize
from pidlab.linear.lti import observable_part, siso_disk_margins, siso_frequency_response
from pidlab.plant.model import LoadedModel

SETTLE_FRACTION = 0.02
"""Settling band of the response metrics, as a fraction of the step or initial deviation."""

FOLLOW_FRACTION = 0.5
"""A step response follows its setpoint when its final value is within this fraction of the step
from the new setpoint; otherwise its overshoot and rise time are not defined (nan)."""

INITIAL_DEVIATION = 0.05
"""Initial deviation of a loop's signal in the initial-condition responses, in the signal's unit."""

DIVERGED = 1e9
"""Magnitude beyond which :func:`closed_loop_responses` cuts a response (an unstable loop): the
plots draw the part before it."""

_NUMERIC_FAILURES = (np.linalg.LinAlgError, ArithmeticError, ValueError, RuntimeError)
"""What NumPy, SciPy and python-control raise on overflowing matrices (LinAlgError on NaN,
OverflowError, ``algebraic loop detected``, ...)."""


@contextmanager
def undefined_as_error(what: str) -> Iterator[None]:
    """Turn the numerical failures of an overflowing closed loop into one :class:`AnalysisError`.

    Parameters
    ----------
    what : str
        The loop, e.g. ``"the loop broken at actuator 'slide'"``; the message starts with it.

    Raises
    ------
    AnalysisError
        Instead of ``LinAlgError``, ``OverflowError``, python-control's "algebraic loop", ...
    """
    try:
        yield
    except PidlabError:
        raise
    except _NUMERIC_FAILURES as exc:
        reason = " ".join(str(exc).split())[:120] or type(exc).__name__
        raise AnalysisError(
            f"{what}: poles and margins are undefined ({reason}); the gains are too large for a linear "
            "analysis, expected gains that keep the loop's numbers finite"
        ) from None


def _require_finite(matrix: np.ndarray, what: str) -> None:
    if not np.all(np.isfinite(matrix)):
        raise AnalysisError(
            f"{what}: the closed loop's matrices overflow (inf or nan); the gains are too large for a "
            "linear analysis, expected gains that keep the loop's numbers finite"
        )


def _largest_gain(spec: CoachSpec) -> str:
    """Which loop of ``spec`` has the largest gain, e.g. ``"loop 'pole' (kp = -1e+300)"``."""
    best = max(
        ((abs(getattr(lp, key)) * max((abs(w) for _, w in lp.actuators), default=1.0), lp.name, key,
          getattr(lp, key)) for lp in spec.loops for key in ("kp", "ki", "kd")),
        key=lambda item: item[0] if np.isfinite(item[0]) else np.inf,
    )  # fmt: skip
    return f"loop {best[1]!r} ({best[2]} = {best[3]:g})"


@dataclass(frozen=True)
class LoopMargins:
    """Stability margins of the loop broken at one actuator.

    Attributes
    ----------
    actuator : str
    gain_margin_db : float
        Upper gain margin, dB (``inf``: none).
    lower_gain_margin_db : float
        Lower gain margin, dB, negative (``-inf``: none). An open-loop unstable plant has one:
        reducing the gain that much destabilizes the loop.
    phase_margin_deg : float
        Smallest phase margin over the gain crossovers: the angle between ``L`` and -1 there,
        degrees (``inf``: no crossover). Equals python-control's value for the usual
        crossover below the real axis; python-control reports a negative number for a
        crossover above it, which open-loop unstable plants normally have.
    delay_margin_s : float
        Smallest extra loop delay that rotates a crossover onto -1, seconds.
    disk_margin : float
        Balanced disk margin alpha.
    disk_gain_margin_db, disk_phase_margin_deg : float
        The gain and phase variations the disk margin guarantees simultaneously.
    ms : float
        Sensitivity peak ``max |1 / (1 + L)|``.
    gain_crossover : float
        Frequency of the smallest phase margin, rad/s (nan: none).
    phase_crossover : float
        Frequency of the upper gain margin, rad/s (nan: none).
    crossovers : tuple of float
        Every gain-crossover frequency, rad/s.
    """

    actuator: str
    gain_margin_db: float
    lower_gain_margin_db: float
    phase_margin_deg: float
    delay_margin_s: float
    disk_margin: float
    disk_gain_margin_db: float
    disk_phase_margin_deg: float
    ms: float
    gain_crossover: float
    phase_crossover: float
    crossovers: tuple[float, ...] = ()

    @property
    def bandwidth(self) -> float:
        """Highest gain-crossover frequency, rad/s (nan: none)."""
        return max(self.crossovers) if self.crossovers else float("nan")

    @property
    def ms_db(self) -> float:
        """Sensitivity peak in dB."""
        return float(20 * np.log10(self.ms))


MARGIN_COLUMNS = (
    ("actuator", "loop broken at"),
    ("gm_db", "gain margin (dB)"),
    ("lower_gm_db", "lower gain margin (dB)"),
    ("pm_deg", "phase margin (deg)"),
    ("delay_ms", "delay margin (ms)"),
    ("disk_alpha", "disk margin α"),
    ("disk_gm_db", "disk gain margin (dB)"),
    ("disk_pm_deg", "disk phase margin (deg)"),
    ("ms_db", "Ms (dB)"),
    ("wgc", "gain crossover (rad/s)"),
    ("wpc", "phase crossover (rad/s)"),
)
"""Columns of a margins table (the tuner's, the pipeline report's): key, and heading with its unit."""


def margin_table(margins: Sequence[LoopMargins]) -> list[dict[str, Any]]:
    """One row per actuator, keyed and in the units of :data:`MARGIN_COLUMNS`."""
    return [
        {
            "actuator": m.actuator,
            "gm_db": m.gain_margin_db,
            "lower_gm_db": m.lower_gain_margin_db,
            "pm_deg": m.phase_margin_deg,
            "delay_ms": 1000.0 * m.delay_margin_s,
            "disk_alpha": m.disk_margin,
            "disk_gm_db": m.disk_gain_margin_db,
            "disk_pm_deg": m.disk_phase_margin_deg,
            "ms_db": m.ms_db,
            "wgc": m.gain_crossover,
            "wpc": m.phase_crossover,
        }
        for m in margins
    ]


@dataclass(frozen=True)
class Pole:
    """A closed-loop pole with damping and natural frequency.

    For a discrete pole ``z`` the equivalent ``s = ln(z) / dt`` gives damping and frequency.
    """

    value: complex
    s: complex
    damping: float
    natural_frequency: float
    stable: bool


@dataclass(frozen=True)
class ResponseMetrics:
    """Metrics of one closed-loop response.

    Attributes
    ----------
    kind : {"step", "initial"}
    loop : str
        The loop whose setpoint is stepped, or whose signal is perturbed.
    signal : str
    overshoot_pct : float
        Step: how far the signal goes beyond its final value, in % of the setpoint change; nan
        ("not defined") when the final value does not follow the setpoint (it ends farther than
        :data:`FOLLOW_FRACTION` of the step from it) or the loop is unstable. Initial: largest
        excursion beyond the initial deviation, in % of it.
    settling_time_s : float
        Time after which the signal stays within 2 % (of the step, or of the initial deviation)
        of its final value; inf when it never does within the horizon or the loop is unstable.
    rise_time_s : float
        Step: time from 10 % to 90 % of the way to the final value (nan when the final value
        does not follow the setpoint, and for initial-condition responses).
    peak_control : float
        Largest ``|u|`` over the response, as a fraction of the actuator's range half-width
        (> 1: the linear response would saturate).
    size : float
        Step size or initial deviation, in the signal's unit.
    """

    kind: str
    loop: str
    signal: str
    overshoot_pct: float
    settling_time_s: float
    rise_time_s: float
    peak_control: float
    size: float


@dataclass(frozen=True)
class ClosedLoopReport:
    """Closed loop in one time domain.

    Attributes
    ----------
    discrete : bool
    sys : control.StateSpace
        Closed loop from the setpoints to the observation variables and actuator commands.
    poles : tuple of Pole
    stable : bool
    margins : tuple of LoopMargins
        One per actuator the coach drives.
    pole_check : float
        ``max |poles(python-control interconnect) - eig(hand-assembled A_cl)|``.
    """

    discrete: bool
    sys: ct.StateSpace
    poles: tuple[Pole, ...]
    stable: bool
    margins: tuple[LoopMargins, ...]
    pole_check: float


@dataclass(frozen=True)
class CoachAnalysis:
    """Everything :func:`analyze_coach` computes.

    Attributes
    ----------
    env_id, spec_name : str
    dt : float
    linearization : Linearization
    discrete, continuous : ClosedLoopReport
    responses : tuple of ResponseMetrics
        Discrete closed loop: a unit setpoint step per loop and an initial deviation of each
        loop's signal.
    plant : control.StateSpace
        The discrete plant analysed: the linearization restricted to its observable part.
    unobservable : tuple of str
        Plant states no output feedback can see, left out (Hopper's and Walker2d's ``rootx``).
    """

    env_id: str
    spec_name: str
    dt: float
    linearization: Linearization
    discrete: ClosedLoopReport
    continuous: ClosedLoopReport
    responses: tuple[ResponseMetrics, ...]
    plant: ct.StateSpace
    unobservable: tuple[str, ...]

    @property
    def stable(self) -> bool:
        """Whether the discrete closed loop (the one that runs) is stable."""
        return self.discrete.stable

    @property
    def open_loop_poles(self) -> np.ndarray:
        """Poles of the discrete linearized plant (eigenvalues of ``Ad``), complex, shape (2*nv,)."""
        return np.linalg.eigvals(self.linearization.Ad)


@dataclass(frozen=True)
class LoopResponse:
    """Frequency response of the discrete loop broken at one actuator, with its margins.

    Attributes
    ----------
    margins : LoopMargins
        The loop's margins (:func:`loop_margins`); ``margins.actuator`` is where it is broken.
    omega : ndarray, shape (n,)
        Frequencies, rad/s, up to the Nyquist frequency ``pi / dt``.
    response : ndarray of complex, shape (n,)
        ``L(exp(j omega dt))`` (negative-feedback convention, as :func:`loop_at_actuator`).
    dt : float
        Sampling period, s.
    """

    margins: LoopMargins
    omega: np.ndarray
    response: np.ndarray
    dt: float

    @property
    def actuator(self) -> str:
        """The actuator where the loop is broken."""
        return self.margins.actuator

    @property
    def magnitude_db(self) -> np.ndarray:
        """``20 log10 |L|``, dB, shape (n,)."""
        with np.errstate(divide="ignore"):
            return 20 * np.log10(np.abs(self.response))

    @property
    def phase_deg(self) -> np.ndarray:
        """Unwrapped phase of ``L``, degrees, shape (n,)."""
        return np.unwrap(np.angle(self.response)) * 180 / np.pi


@dataclass(frozen=True)
class ClosedLoopResponses:
    """Time responses of the discrete closed loop: per loop, a setpoint step and an initial deviation.

    Attributes
    ----------
    timepts : ndarray, shape (steps,)
        Time, s.
    loops : tuple of str, length n_loops
        Loop names, in the coach's setpoint order.
    signals : tuple of str, length n_loops
        Each loop's measured observation variable.
    outputs : tuple of str, length n_outputs
        Names of the closed loop's outputs: observation variables, then actuator commands.
    step : ndarray, shape (n_loops, steps, n_outputs)
        ``step[j]``: the outputs after a unit step of loop ``j``'s setpoint, from rest.
    initial : ndarray, shape (n_loops, steps, n_outputs)
        ``initial[j]``: the outputs from an initial deviation ``deviation`` of loop ``j``'s
        signal (:func:`initial_response`).
    deviation : float
        Size of the initial deviations, in each signal's unit.
    """

    timepts: np.ndarray
    loops: tuple[str, ...]
    signals: tuple[str, ...]
    outputs: tuple[str, ...]
    step: np.ndarray
    initial: np.ndarray
    deviation: float

    def signal_step(self, j: int) -> np.ndarray:
        """Loop ``j``'s signal after a unit step of its setpoint, shape (steps,)."""
        return self.step[j, :, self.outputs.index(self.signals[j])]

    def signal_initial(self, j: int) -> np.ndarray:
        """Loop ``j``'s signal from its initial deviation, shape (steps,)."""
        return self.initial[j, :, self.outputs.index(self.signals[j])]


def coach_to_continuous(coach_d: ct.StateSpace) -> ct.StateSpace:
    """Map a discrete coach to continuous time by the inverse bilinear (Tustin) transform.

    Exact inverse of ``control.sample_system(..., method="bilinear")``.
    """
    T = float(coach_d.dt)
    Ad, Bd, Cd, Dd = (np.asarray(M, dtype=float) for M in (coach_d.A, coach_d.B, coach_d.C, coach_d.D))
    n = Ad.shape[0]
    if n == 0:
        return ct.ss(
            np.zeros((0, 0)),
            np.zeros((0, Dd.shape[1])),
            np.zeros((Dd.shape[0], 0)),
            Dd,
            inputs=coach_d.input_labels,
            outputs=coach_d.output_labels,
            name="coach_c",
        )
    eye = np.eye(n)
    A = (2.0 / T) * np.linalg.solve((eye + Ad).T, (Ad - eye).T).T
    ima = eye - A * T / 2.0
    B = ima @ Bd / T
    C = Cd @ ima
    D = Dd - 0.5 * C @ Bd
    return ct.ss(
        A,
        B,
        C,
        D,
        states=coach_d.state_labels,
        inputs=coach_d.input_labels,
        outputs=coach_d.output_labels,
        name="coach_c",
    )


def _split_coach(coach: ct.StateSpace, ny: int) -> tuple[np.ndarray, ...]:
    A, B, C, D = (np.asarray(M, dtype=float) for M in (coach.A, coach.B, coach.C, coach.D))
    return A, B[:, :ny], C, D[:, :ny]


def hand_closed_loop(plant: ct.StateSpace, coach: ct.StateSpace) -> np.ndarray:
    """Closed-loop state matrix assembled by hand: ``[[A + B Dk C, B Ck], [Bk C, Ak]]``."""
    A, B, C = (np.asarray(M, dtype=float) for M in (plant.A, plant.B, plant.C))
    Ak, Bk, Ck, Dk = _split_coach(coach, C.shape[0])
    return np.block([[A + B @ Dk @ C, B @ Ck], [Bk @ C, Ak]])


def loop_at_actuator(plant: ct.StateSpace, coach: ct.StateSpace, i: int) -> ct.StateSpace:
    """Loop transfer ``L_i = -(u_cmd_i / u_i)`` broken at actuator ``i``, others closed."""
    A, B, C = (np.asarray(M, dtype=float) for M in (plant.A, plant.B, plant.C))
    Ak, Bk, Ck, Dk = _split_coach(coach, C.shape[0])
    nu = B.shape[1]
    keep = np.eye(nu)
    keep[i, i] = 0.0
    e = np.zeros((nu, 1))
    e[i] = 1.0
    Acl = np.block([[A + B @ keep @ Dk @ C, B @ keep @ Ck], [Bk @ C, Ak]])
    Bcl = np.vstack([B @ e, np.zeros((Ak.shape[0], 1))])
    Ccl = np.hstack([Dk[i : i + 1] @ C, Ck[i : i + 1]])
    return ct.ss(Acl, Bcl, -Ccl, np.zeros((1, 1)), plant.dt)


def _frequency_grid(L: ct.StateSpace) -> np.ndarray:
    if L.isdtime(strict=True):
        top = np.pi / float(L.dt)
        return np.logspace(np.log10(top) - 5, np.log10(top) - 1e-6, 3000)
    return np.logspace(-3, 4, 3000)


CROSSOVER_TOL = 1e-3
"""Relative tolerance for accepting a crossover: ``||L| - 1|`` (gain), ``|Im L| / |L|`` (phase)."""


def _refine(f: Callable[[float], float], a: float, b: float) -> float:
    """Root of ``f`` between log-frequencies ``a`` and ``b`` (bisection, to 1e-12 relative)."""
    fa = f(a)
    for _ in range(60):
        m = 0.5 * (a + b)
        fm = f(m)
        if (fm > 0) == (fa > 0):
            a, fa = m, fm
        else:
            b = m
    return float(np.exp(0.5 * (a + b)))


def _true_gain_crossovers(
    L: ct.StateSpace, wgc: np.ndarray, omega: np.ndarray, response: np.ndarray
) -> np.ndarray:
    """Gain crossovers where ``|L| = 1`` really holds.

    ``control.stability_margins`` finds crossovers as polynomial roots; with a pole on the unit
    circle (a cart position loop: z = 1) it can return frequencies where ``|L|`` is far from 1
    (seen: 4 dB on InvertedPendulum). Those are dropped, and crossovers seen on the dense grid
    but missing from python-control's list are added (refined by bisection).
    """
    keep: list[float] = []
    for w in sorted(float(v) for v in wgc):
        near_one = abs(abs(siso_frequency_response(L, np.array([w]))[0]) - 1.0) < CROSSOVER_TOL
        if near_one and all(abs(w - k) > 1e-4 * w for k in keep):
            keep.append(w)
    with np.errstate(divide="ignore"):
        logmag = np.log(np.abs(response))
    idx = np.nonzero(np.diff(np.sign(logmag)) != 0)[0]

    def f(x: float) -> float:
        return float(np.log(abs(siso_frequency_response(L, np.array([np.exp(x)]))[0])))

    for i in idx:
        if not (np.isfinite(logmag[i]) and np.isfinite(logmag[i + 1])):
            continue
        w = _refine(f, float(np.log(omega[i])), float(np.log(omega[i + 1])))
        if all(abs(w - k) > 1e-4 * w for k in keep):
            keep.append(w)
    return np.array(sorted(keep))


def _true_phase_crossovers(
    L: ct.StateSpace, wpc: np.ndarray, omega: np.ndarray, response: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Phase crossovers (``L`` real and negative) and the gain factors ``1 / |L|`` there.

    python-control's list is checked like the gain crossovers (on Hopper it returns points
    where ``L`` is far off the real axis, and misses crossings at 10 and 13 rad/s); crossings of
    the negative real axis seen on the dense grid are added (refined by bisection on ``Im L``).
    """
    keep: list[float] = []
    for w in sorted(float(v) for v in wpc):
        r = siso_frequency_response(L, np.array([w]))[0]
        on_axis = np.isfinite(r) and r.real < 0 and abs(r.imag) <= CROSSOVER_TOL * abs(r)
        if on_axis and all(abs(w - k) > 1e-4 * max(w, 1e-12) for k in keep):
            keep.append(w)
    im = response.imag
    idx = np.nonzero(
        (np.sign(im[:-1]) * np.sign(im[1:]) < 0) & (response.real[:-1] < 0) & (response.real[1:] < 0)
    )[0]

    def f(x: float) -> float:
        return float(siso_frequency_response(L, np.array([np.exp(x)]))[0].imag)

    for i in idx:
        w = _refine(f, float(np.log(omega[i])), float(np.log(omega[i + 1])))
        if all(abs(w - k) > 1e-4 * w for k in keep):
            keep.append(w)
    w_all = np.array(sorted(keep))
    mags = np.abs(siso_frequency_response(L, w_all)) if w_all.size else np.array([])
    with np.errstate(divide="ignore"):
        return 1.0 / mags, w_all


def loop_margins(L: ct.StateSpace, actuator: str) -> LoopMargins:
    """Margins of a SISO loop transfer function (negative-feedback convention)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gm, pm, sm, wpc, wgc, _ = ct.stability_margins(L, returnall=True)
        omega = _frequency_grid(L)
        response = siso_frequency_response(L, omega)
        dm, dgm, dpm = siso_disk_margins(response)
    gm, pm, sm, wpc, wgc = (np.atleast_1d(np.asarray(v, dtype=float)) for v in (gm, pm, sm, wpc, wgc))
    gm, wpc = _true_phase_crossovers(L, wpc, omega, response)
    wgc = _true_gain_crossovers(L, wgc, omega, response)
    upper = gm[gm > 1.0]
    lower = gm[(gm < 1.0) & (gm > 0.0)]
    if upper.size:
        k = int(np.argmin(upper))
        gm_db, w_pc = 20 * np.log10(upper[k]), float(wpc[gm > 1.0][k])
    else:
        gm_db, w_pc = np.inf, np.nan
    lower_db = 20 * np.log10(lower.max()) if lower.size else -np.inf
    if wgc.size:
        # phase margin per crossover = angle between L and -1 (python-control's signed value
        # is negative at crossovers in the upper half plane, normal for unstable plants);
        # delay margin = smallest delay whose lag rotates a crossover onto -1
        ph = np.angle(siso_frequency_response(L, wgc), deg=True)
        distance = 180.0 - np.abs(ph)
        lag = np.mod(ph + 180.0, 360.0)
        k = int(np.argmin(distance))
        pm_deg, w_gc = float(distance[k]), float(wgc[k])
        delays = np.deg2rad(lag) / np.where(wgc > 0, wgc, np.nan)
        delay = float(np.nanmin(delays)) if np.any(np.isfinite(delays)) else np.inf
    else:
        pm_deg, w_gc, delay = np.inf, np.nan, np.inf
    # the sensitivity peak from a dense frequency grid (robust where the polynomial method of
    # stability_margins finds no extremum), refined by python-control's value when it has one.
    # A continuous loop's sup also covers w -> infinity, where L -> D: a strictly proper loop has
    # |S| -> 1 there, so Ms >= 1 (a loop with rate feedback that never rolls off reaches its sup
    # there; sampled, the same loop peaks at the Nyquist frequency instead)
    distance = float(np.min(np.abs(1.0 + response)))
    if sm.size:
        distance = min(distance, float(sm.min()))
    if not L.isdtime():
        distance = min(distance, float(abs(1.0 + np.asarray(L.D, dtype=float)[0, 0])))
    ms = 1.0 / distance if distance > 0 else np.inf
    return LoopMargins(
        actuator=actuator,
        gain_margin_db=float(gm_db),
        lower_gain_margin_db=float(lower_db),
        phase_margin_deg=pm_deg,
        delay_margin_s=float(delay),
        disk_margin=float(dm),
        disk_gain_margin_db=float(dgm),
        disk_phase_margin_deg=float(dpm),
        ms=ms,
        gain_crossover=w_gc,
        phase_crossover=w_pc,
        crossovers=tuple(float(w) for w in wgc),
    )


def _poles(eigs: np.ndarray, dt: float | None) -> tuple[Pole, ...]:
    out = []
    for z in eigs:
        if dt:
            s = np.log(complex(z)) / dt if abs(z) > 1e-300 else complex(-np.inf)
            stable = abs(z) < 1.0 - 1e-9
        else:
            s, stable = complex(z), z.real < -1e-9
        wn = abs(s)
        zeta = -s.real / wn if wn > 0 and np.isfinite(wn) else 1.0
        out.append(Pole(complex(z), s, float(zeta), float(wn), bool(stable)))
    out.sort(key=lambda p: -p.s.real if np.isfinite(p.s.real) else -np.inf)
    return tuple(out)


def closed_loop_report(plant: ct.StateSpace, coach: ct.StateSpace, loops: list[str]) -> ClosedLoopReport:
    """Close ``plant`` with ``coach`` (same time domain): poles, stability, margins per actuator.

    Parameters
    ----------
    plant : control.StateSpace
        Outputs = observation variables, inputs = actuators.
    coach : control.StateSpace
        Inputs = observation variables then one ``<loop>_setpoint`` per loop.
    loops : list of str
        Loop names, in the coach's setpoint order.
    """
    discrete = bool(plant.isdtime(strict=True))
    setpoints = [f"{name}_setpoint" for name in loops]
    what = f"the closed loop of loop(s) {', '.join(repr(n) for n in loops)}"
    with undefined_as_error(what), warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore")
        hand = hand_closed_loop(plant, coach)
        _require_finite(hand, what)
        cl = ct.interconnect(
            [plant, coach],
            inplist=setpoints,
            outlist=list(plant.output_labels) + list(plant.input_labels),
            name="closed_loop",
        )
        eig_ct = np.linalg.eigvals(np.asarray(cl.A))
        eig_hand = np.linalg.eigvals(hand)
        _require_finite(eig_hand, what)
    check = float(np.max(np.abs(np.sort_complex(eig_ct) - np.sort_complex(eig_hand)))) if eig_ct.size else 0.0
    poles = _poles(eig_hand, float(plant.dt) if discrete else None)
    driven = [
        i for i in range(plant.ninputs) if np.any(np.asarray(coach.D)[i]) or np.any(np.asarray(coach.C)[i])
    ]
    margins = []
    for i in driven:
        with undefined_as_error(f"the loop broken at actuator {plant.input_labels[i]!r}"):
            margins.append(loop_margins(loop_at_actuator(plant, coach, i), plant.input_labels[i]))
    return ClosedLoopReport(
        discrete=discrete,
        sys=cl,
        poles=poles,
        stable=all(p.stable for p in poles),
        margins=tuple(margins),
        pole_check=check,
    )


def step_metrics(t: np.ndarray, y: np.ndarray, step: float) -> tuple[float, float, float]:
    """Overshoot (%), settling time (s) and rise time (s) of a response ``y`` to a setpoint change ``step``.

    The signal starts at 0 and its setpoint moves to ``step``; its final value is ``y[-1]``.

    - **Overshoot**: ``max(0, peak beyond the final value) / |step| * 100``, the peak taken in the
      step's direction; nan (not defined) when the final value does not follow the setpoint:
      ``|y[-1] - step| > FOLLOW_FRACTION * |step|``.
    - **Settling time**: the time after which ``y`` stays within ``SETTLE_FRACTION * |step|`` of
      its final value (inf: it has not settled by the end).
    - **Rise time**: from the first sample at 10 % to the first at 90 % of the way to the final
      value; nan when the final value does not follow the setpoint.

    Parameters
    ----------
    t, y : ndarray
        Sample times (s) and the signal, same length.
    step : float
        The setpoint change (non-zero).

    Returns
    -------
    tuple of float
        ``(overshoot_pct, settling_time_s, rise_time_s)``.
    """
    final = float(y[-1])
    if not np.all(np.isfinite(y)):
        return float("nan"), float("inf"), float("nan")
    settle = _settling_time(t, y, final, SETTLE_FRACTION * abs(step))
    if abs(final - step) > FOLLOW_FRACTION * abs(step):
        return float("nan"), settle, float("nan")
    direction = float(np.sign(step))
    over = max(0.0, float(np.max(direction * y) - direction * final)) / abs(step) * 100
    toward = y / final  # the way to the final value (final has the step's sign: it follows)
    rise = float(t[np.argmax(toward >= 0.9)] - t[np.argmax(toward >= 0.1)])
    return over, settle, rise


def _settling_time(t: np.ndarray, y: np.ndarray, final: float, band: float) -> float:
    outside = np.nonzero(np.abs(y - final) > band)[0]
    if outside.size == 0:
        return 0.0
    if outside[-1] == len(y) - 1:
        return float("inf")
    return float(t[outside[-1] + 1])


def step_response(cl: ct.StateSpace, loop: int, steps: int) -> np.ndarray:
    """Outputs of the discrete closed loop after a unit step of one loop's setpoint, from rest.

    Parameters
    ----------
    cl : control.StateSpace
        Discrete closed loop from the setpoints (:attr:`ClosedLoopReport.sys`).
    loop : int
        Index of the stepped setpoint.
    steps : int

    Returns
    -------
    outputs : ndarray, shape (steps, n_outputs)
        Observation variables, then actuator commands (deviations).
    """
    A, B, C, D = (np.asarray(M, dtype=float) for M in (cl.A, cl.B, cl.C, cl.D))
    b, d = B[:, loop], D[:, loop]
    x = np.zeros(A.shape[0])
    out = np.empty((steps, C.shape[0]))
    with np.errstate(over="ignore", invalid="ignore"):  # unstable loops grow without bound
        for k in range(steps):
            out[k] = C @ x + d
            x = A @ x + b
    return out


def initial_response(
    cl: ct.StateSpace, plant: ct.StateSpace, signal: int, size: float, steps: int
) -> np.ndarray:
    """Outputs of the discrete closed loop from an initial deviation of one observation variable.

    The plant starts at the least-norm state whose observation ``signal`` equals ``size`` (the
    others zero), the coach at rest.

    Returns
    -------
    outputs : ndarray, shape (steps, n_outputs)
        Observation variables, then actuator commands (deviations).
    """
    A, C = np.asarray(cl.A), np.asarray(cl.C)
    x = np.concatenate(
        [np.linalg.pinv(np.asarray(plant.C))[:, signal] * size, np.zeros(A.shape[0] - plant.nstates)]
    )
    out = np.empty((steps, C.shape[0]))
    with np.errstate(over="ignore", invalid="ignore"):  # unstable loops grow without bound
        for k in range(steps):
            out[k] = C @ x
            x = A @ x
    return out


def response_metrics(
    report: ClosedLoopReport,
    coach: Coach,
    plant: ct.StateSpace,
    horizon_s: float,
    loops: tuple[str, ...] | None = None,
) -> tuple[ResponseMetrics, ...]:
    """Step and initial-condition metrics of the discrete closed loop ``report``.

    ``loops``: the loops to report (default: every loop).
    """
    cl = report.sys
    dt = coach.dt
    steps = max(round(horizon_s / dt), 10)
    t = np.arange(steps) * dt
    lay = coach.layout
    halfwidth = (lay.ctrl_high - lay.ctrl_low) / 2.0
    halfwidth = np.where(np.isfinite(halfwidth), halfwidth, 1.0)
    nobs = len(lay.observation_names)
    out = []
    for j, lp in enumerate(lay.spec.loops):
        if loops is not None and lp.name not in loops:
            continue
        sig = lay.observation_names.index(lp.signal)
        outputs = step_response(cl, j, steps)
        y = outputs[:, sig]
        u = outputs[:, nobs:].T
        peak_u = float(np.max(np.abs(u).T / halfwidth)) if u.size else 0.0
        unstable = (float("nan"), float("inf"), float("nan"))
        over, settle, rise = step_metrics(t, y, 1.0) if report.stable else unstable
        out.append(ResponseMetrics("step", lp.name, lp.signal, over, settle, rise, peak_u, 1.0))
    # initial deviation of each loop's signal, everything else at the operating point
    for lp in lay.spec.loops:
        if loops is not None and lp.name not in loops:
            continue
        sig = lay.observation_names.index(lp.signal)
        size = INITIAL_DEVIATION
        outputs = initial_response(cl, plant, sig, size, steps)
        ys, us = outputs[:, sig], outputs[:, nobs:]
        y = np.array(ys)
        peak_u = float(np.max(np.abs(us).T / halfwidth[:, None])) if us.size else 0.0
        over = max(0.0, float(np.max(-np.sign(size) * y)) / abs(size) * 100)
        settle = _settling_time(t, y, 0.0, SETTLE_FRACTION * abs(size)) if report.stable else float("inf")
        out.append(ResponseMetrics("initial", lp.name, lp.signal, over, settle, float("nan"), peak_u, size))
    return tuple(out)


def omega_grid(dt: float, points: int = 1500) -> np.ndarray:
    """Frequencies for a loop's Bode and Nyquist views: four decades up to the Nyquist frequency.

    Parameters
    ----------
    dt : float
        Sampling period, s.
    points : int
        Number of frequencies.

    Returns
    -------
    omega : ndarray, shape (points,)
        Log-spaced, rad/s, from ``1e-4 pi / dt`` to just below ``pi / dt``.
    """
    top = np.pi / dt
    return np.logspace(np.log10(top) - 4, np.log10(top) - 1e-6, points)


def loop_frequency_response(
    plant: ct.StateSpace, coach: ct.StateSpace, actuator: str, omega: np.ndarray
) -> np.ndarray:
    """Frequency response of the loop broken at one actuator (:func:`loop_at_actuator`).

    Parameters
    ----------
    plant : control.StateSpace
        Discrete plant, outputs = observation variables, inputs = actuators.
    coach : control.StateSpace
        Discrete coach (:meth:`pidlab.controller.pid.Coach.linear_model`).
    actuator : str
        One of ``plant.input_labels``.
    omega : ndarray, shape (n,)
        Frequencies, rad/s.

    Returns
    -------
    response : ndarray of complex, shape (n,)
        ``L(exp(j omega dt))``.
    """
    L = loop_at_actuator(plant, coach, list(plant.input_labels).index(actuator))
    return siso_frequency_response(L, omega)


def loop_responses(analysis: CoachAnalysis, coach: Coach, points: int = 1500) -> tuple[LoopResponse, ...]:
    """Frequency responses of the discrete loops of an analysis, one per actuator the coach drives.

    Parameters
    ----------
    analysis : CoachAnalysis
        :func:`analyze_coach` of ``coach``.
    coach : Coach
    points : int
        Frequencies per loop, on :func:`omega_grid`.

    Returns
    -------
    tuple of LoopResponse
        In the order of ``analysis.discrete.margins``.
    """
    coach_d = coach.linear_model()
    omega = omega_grid(analysis.dt, points)
    plant = analysis.plant
    return tuple(
        LoopResponse(m, omega, loop_frequency_response(plant, coach_d, m.actuator, omega), analysis.dt)
        for m in analysis.discrete.margins
    )


def _cut_diverged(responses: np.ndarray) -> np.ndarray:
    """``responses`` with NaN from where each output first exceeds :data:`DIVERGED` (or overflows).

    Parameters
    ----------
    responses : ndarray, shape (n_loops, steps, n_outputs)

    Returns
    -------
    ndarray, shape (n_loops, steps, n_outputs)
        Plots draw the finite part; an unstable loop's growth would reach inf.
    """
    with np.errstate(invalid="ignore"):
        gone = ~(np.abs(responses) <= DIVERGED)
    return np.where(np.maximum.accumulate(gone, axis=1), np.nan, responses)


def closed_loop_responses(
    analysis: CoachAnalysis, coach: Coach, horizon_s: float = 20.0, deviation: float = INITIAL_DEVIATION
) -> ClosedLoopResponses:
    """Setpoint-step and initial-deviation responses of every loop of the discrete closed loop.

    Parameters
    ----------
    analysis : CoachAnalysis
        :func:`analyze_coach` of ``coach``.
    coach : Coach
        The coach analysed (its loops name the setpoints and signals).
    horizon_s : float
        Simulated time, s.
    deviation : float
        Initial deviation of each loop's signal, in its unit.

    Returns
    -------
    ClosedLoopResponses
    """
    cl, plant = analysis.discrete.sys, analysis.plant
    steps = round(horizon_s / analysis.dt)
    lay = coach.layout
    loops = lay.spec.loops
    signals = tuple(lp.signal for lp in loops)
    index = [lay.observation_names.index(sig) for sig in signals]
    shape = (len(loops), steps, cl.noutputs)
    stepped = _cut_diverged(np.array([step_response(cl, j, steps) for j in range(len(loops))]).reshape(shape))
    initial = _cut_diverged(
        np.array([initial_response(cl, plant, sig, deviation, steps) for sig in index]).reshape(shape)
    )
    return ClosedLoopResponses(
        timepts=np.arange(steps) * analysis.dt,
        loops=tuple(lp.name for lp in loops),
        signals=signals,
        outputs=tuple(lay.observation_names) + tuple(plant.input_labels),
        step=stepped,
        initial=initial,
        deviation=deviation,
    )


def analyze_coach(
    coach: Coach, loaded: LoadedModel, lin: Linearization | None = None, horizon_s: float = 20.0
) -> CoachAnalysis:
    """Closed-loop analysis of ``coach`` on ``loaded``, linearized at its model card's point.

    Parameters
    ----------
    coach : Coach
    loaded : LoadedModel
    lin : Linearization, optional
        Default: :func:`pidlab.linear.linearize.linearize` at the card's operating point.
    horizon_s : float
        Length of the simulated responses, s.

    Returns
    -------
    CoachAnalysis

    Raises
    ------
    AnalysisError
        Gains so large that the poles or margins are undefined; names the loop with the largest gain.
    """
    instance(coach, Coach, "coach")
    instance(loaded, LoadedModel, "loaded")
    if lin is None:
        lin = linearize(loaded)
    loops = [lp.name for lp in coach.spec.loops]
    try:
        with undefined_as_error(f"the closed loop of loop(s) {', '.join(repr(n) for n in loops)}"):
            coach_d = coach.linear_model()
            plant_d, removed = observable_part(lin.sysd)
            plant_c, _ = observable_part(lin.sys)
            discrete = closed_loop_report(plant_d, coach_d, loops)
            continuous = closed_loop_report(plant_c, coach_to_continuous(coach_d), loops)
    except AnalysisError as exc:
        raise AnalysisError(
            f"coach {coach.spec.name!r}: {exc}; largest gain: {_largest_gain(coach.spec)}"
        ) from None
    return CoachAnalysis(
        env_id=coach.spec.env_id,
        spec_name=coach.spec.name,
        dt=coach.dt,
        linearization=lin,
        discrete=discrete,
        continuous=continuous,
        responses=response_metrics(discrete, coach, plant_d, horizon_s),
        plant=plant_d,
        unobservable=removed,
    )
