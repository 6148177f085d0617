"""Automatic tuning of a coach, in the spirit of MATLAB's ``pidtune``.

The loop structure comes from a template (which signals, which actuators, which loops are
*core*). The gains are then found in two steps:

1. **A stabilizing start**, even for open-loop unstable plants: a discrete LQR design on the
   linearized plant gives a state feedback ``u = -K x``; the coach's gains are its
   least-squares projection onto the PID structure (exact when the structure measures every
   state, as for the pendulums with their rate signals).
2. **Shaping**: Nelder-Mead on the log-gains (signs fixed) minimizes the mismatch between the
   achieved and the asked gain-crossover frequency and phase margin at every actuator, with
   penalties for an unstable closed loop and a sensitivity peak above the preset's limit.

Presets: ``robust`` (all loops, phase margin >= 60 deg, Ms <= 1.6), and ``weak``, a deliberately
barely functioning coach in the spirit of the paper: core loops only (for the pendulums: the
poles but not the cart), a phase margin of 25 deg, and the lowest sensible crossover: 1.4 times
the fastest unstable open-loop pole.
"""

from __future__ import annotations

import datetime as _dt
import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import control as ct
import numpy as np
from scipy.optimize import minimize

from pidlab import __version__
from pidlab.controller.pid import Coach
from pidlab.controller.spec import CoachSpec, Loop
from pidlab.errors import PidlabError
from pidlab.linear.linearize import Linearization, linearize
from pidlab.plant.card import ModelCard, TuningLoop
from pidlab.plant.model import LoadedModel

LoopTemplate = TuningLoop
"""A loop of a tuning template (the model card's ``[[tuning.loop]]``)."""


@dataclass(frozen=True)
class Preset:
    """Targets of a tuning preset."""

    name: str
    phase_margin: float
    max_ms: float
    core_only: bool
    bandwidth_factor: float
    max_spectral_radius: float


WEAK_CROSSOVER_FACTOR = 1.4
"""Weak preset: asked crossover = this factor times the fastest unstable open-loop pole, rad/s."""

POSTURE_START = (1.0, 0.1)
"""Contact-rich envs: a joint-posture PD start (kp, kd) tried beside the linear design."""

PRESETS = {
    "robust": Preset(
        "robust",
        phase_margin=60.0,
        max_ms=1.6,
        core_only=False,
        bandwidth_factor=1.0,
        max_spectral_radius=0.999,
    ),
    "weak": Preset(
        "weak",
        phase_margin=25.0,
        max_ms=math.inf,
        core_only=True,
        bandwidth_factor=0.5,
        max_spectral_radius=1.002,
    ),
}


@dataclass(frozen=True)
class TuneResult:
    """What the tuner was asked and what it achieved.

    Attributes
    ----------
    spec : CoachSpec
    preset : str
    asked_bandwidth, asked_phase_margin : float
        rad/s and degrees.
    achieved_bandwidth, achieved_phase_margin, achieved_ms : float
        Over the actuators' loops: the highest gain crossover (rad/s), the smallest angular
        distance of ``L`` from -1 at any crossover (degrees), the largest Ms.
    spectral_radius : float
        Largest ``|z|`` of the discrete closed loop.
    evaluations : int
    refined_return : float or None
        Contact-rich envs: mean coach-alone return on the tuning seeds after refinement.
    """

    spec: CoachSpec
    preset: str
    asked_bandwidth: float
    asked_phase_margin: float
    achieved_bandwidth: float
    achieved_phase_margin: float
    achieved_ms: float
    spectral_radius: float
    evaluations: int
    refined_return: float | None = None


def _spec(
    env_id: str,
    loops: tuple[LoopTemplate, ...],
    gains: np.ndarray,
    setpoints: dict[str, float],
    offset: tuple[tuple[str, float], ...],
    name: str,
) -> CoachSpec:
    out = []
    for i, lt in enumerate(loops):
        kp, kd = float(gains[2 * i]), float(gains[2 * i + 1])
        out.append(
            Loop(
                name=lt.name,
                signal=lt.signal,
                setpoint=setpoints[lt.signal],
                action="direct",
                kp=kp,
                kd=kd,
                rate_signal=lt.rate_signal,
                actuators=lt.actuators,
            )
        )
    return CoachSpec(env_id=env_id, name=name, loops=tuple(out), offset=offset)


def lqr_projection(
    lin: Linearization, loops: tuple[LoopTemplate, ...], input_weight: float = 0.5
) -> tuple[np.ndarray, tuple[LoopTemplate, ...]]:
    """Least-squares PD gains reproducing a discrete LQR state feedback through the structure.

    The LQR weighs what the coach measures (``Q = C'C``, unmeasured directions weakly) against
    ``input_weight`` times the identity on the actuators. Loops without fixed actuators get their
    weights from the LQR gain's column of their signal (normalized to a largest weight of 1).
    Returns the gains (``kp, kd`` per loop) and the loops with weights set.
    """
    Ad, Bd, C = lin.Ad, lin.Bd, lin.C
    obs = list(lin.output_names)
    acts = list(lin.input_names)
    n = Ad.shape[0]
    # weight what the coach measures; keep unmeasured directions weakly penalized
    Q = C.T @ C + 1e-3 * np.eye(n)
    R = np.eye(Bd.shape[1]) * input_weight
    K, _, _ = ct.dlqr(Ad, Bd, Q, R)
    pinv_c = np.linalg.pinv(C)
    resolved = []
    for lt in loops:
        if lt.auto_weights:
            w = -K @ pinv_c[:, obs.index(lt.signal)]
            w = w / np.max(np.abs(w))
            lt = replace(
                lt, actuators=tuple((a, float(v)) for a, v in zip(acts, w, strict=True) if abs(v) > 1e-3)
            )
        resolved.append(lt)
    loops = tuple(resolved)
    # structure: u = sum_l w_l (kp_l y_l + kd_l rate_l) (direct action, deviation variables)
    columns = []
    for lt in loops:
        w = np.zeros(len(acts))
        for a, v in lt.actuators:
            w[acts.index(a)] = v
        for sig in (lt.signal, lt.rate_signal):
            row = C[obs.index(sig)] if sig is not None else np.zeros(n)
            columns.append(np.outer(w, row).ravel())
    M = np.column_stack(columns)
    gains, *_ = np.linalg.lstsq(M, (-K).ravel(), rcond=None)
    return gains, loops


def _fast_loop_figures(
    plant: ct.StateSpace, coach: ct.StateSpace, omega: np.ndarray
) -> tuple[float, float, float, float]:
    """(bandwidth, phase distance, largest Ms, spectral radius) over the actuators' loops.

    The bandwidth is the highest gain crossover; the phase distance is the smallest angle
    between ``L`` and ``-1`` over all crossovers (for open-loop unstable plants python-control's
    signed phase margin can be negative at a crossover of a stable loop; the distance cannot).
    """
    from pidlab.controller.analysis import hand_closed_loop, loop_at_actuator
    from pidlab.linear.lti import siso_frequency_response

    Acl = hand_closed_loop(plant, coach)
    rho = float(np.max(np.abs(np.linalg.eigvals(Acl)))) if Acl.size else 0.0
    wc_max, pm_min, ms_max = -math.inf, math.inf, 0.0
    D = np.asarray(coach.D)
    for i in range(plant.ninputs):
        if not np.any(D[i]) and not np.any(np.asarray(coach.C)[i]):
            continue
        resp = siso_frequency_response(loop_at_actuator(plant, coach, i), omega)
        ms_max = max(ms_max, float(np.max(1.0 / np.abs(1.0 + resp))))
        mag = np.abs(resp)
        cross = np.nonzero((mag[:-1] - 1.0) * (mag[1:] - 1.0) < 0)[0]
        for k in cross:
            f = (1.0 - mag[k]) / (mag[k + 1] - mag[k])
            w = omega[k] + f * (omega[k + 1] - omega[k])
            ph = np.angle(resp[k] + f * (resp[k + 1] - resp[k]), deg=True)
            wc_max = max(wc_max, w)
            pm_min = min(pm_min, 180.0 - abs(ph))
    return (wc_max if wc_max > 0 else math.inf), pm_min, ms_max, rho


@dataclass(frozen=True, eq=False)
class _Problem:
    """What every evaluation of a candidate needs: the loops, the fixed parts, the plant."""

    loaded: LoadedModel
    loops: tuple[LoopTemplate, ...]
    setpoints: dict[str, float]
    offset: tuple[tuple[str, float], ...]
    plant: ct.StateSpace
    omega: np.ndarray

    def spec(self, gains: np.ndarray, name: str = "candidate") -> CoachSpec:
        """The coach spec with ``gains`` (``kp, kd`` per loop)."""
        return _spec(str(self.loaded.env_id), self.loops, gains, self.setpoints, self.offset, name)

    def figures(self, gains: np.ndarray) -> tuple[float, float, float, float]:
        """(bandwidth, phase distance, largest Ms, spectral radius) of the coach with ``gains``."""
        coach = Coach(self.spec(gains), self.loaded).linear_model()
        ny = self.plant.noutputs
        coach_y = ct.ss(coach.A, np.asarray(coach.B)[:, :ny], coach.C, np.asarray(coach.D)[:, :ny], coach.dt)
        return _fast_loop_figures(self.plant, coach_y, self.omega)


class _Evaluations:
    """Counts the evaluations of both optimizers and reports them to ``progress``."""

    def __init__(self, progress: Callable[[int], None] | None) -> None:
        self.count = 0
        self.progress = progress

    def tick(self) -> None:
        self.add(1)

    def add(self, n: int) -> None:
        """Count ``n`` more evaluations."""
        self.count += n
        if self.progress is not None:
            self.progress(self.count)


def check_request(
    loaded: LoadedModel, bandwidth: float | None, phase_margin: float | None, preset: str
) -> ModelCard:
    """The model card with its tuning template; raises on a request that cannot be tuned."""
    from pidlab.checks import instance

    instance(loaded, LoadedModel, "loaded")
    if preset not in PRESETS:
        raise PidlabError(
            f"preset={preset!r}: unknown preset; expected one of {', '.join(PRESETS)}", param="preset"
        )
    card = loaded.card
    if card is None or not card.tuning:
        raise PidlabError(
            f"no tuning template for {loaded.name}: its model card needs [[tuning.loop]] tables"
            if card is not None
            else f"no tuning template for {loaded.name}: it has no model card ({loaded.card_hint})"
        )
    if bandwidth is not None and not (math.isfinite(bandwidth) and bandwidth > 0):
        raise PidlabError(
            f"bandwidth={bandwidth!r}: expected a positive frequency in rad/s (finite)", param="bandwidth"
        )
    nyquist = math.pi / loaded.control_dt
    if bandwidth is not None and bandwidth >= nyquist:
        raise PidlabError(
            f"bandwidth={bandwidth!r}: at or above the Nyquist frequency of the coach's control period "
            f"(pi / {loaded.control_dt:g} s = {nyquist:.4g} rad/s); expected a crossover below it",
            param="bandwidth",
        )  # fmt: skip
    if phase_margin is not None and not 0 < phase_margin < 90:
        raise PidlabError(
            f"phase_margin={phase_margin!r}: expected degrees between 0 and 90", param="phase_margin"
        )
    return card


def tuning_problem(
    loaded: LoadedModel, card: ModelCard, lin: Linearization, p: Preset
) -> tuple[_Problem, np.ndarray]:
    """The tuning problem (loops with weights resolved) and its LQR-projected start gains."""
    from pidlab.linear.lti import observable_part
    from pidlab.plant.observation import observe_at

    loops = tuple(lt for lt in card.tuning if lt.core or not p.core_only)
    y_abs = observe_at(card, loaded.model, lin.op.qpos, lin.op.qvel)
    plant, _ = observable_part(lin.sysd)
    start, loops = lqr_projection(lin, loops)
    problem = _Problem(
        loaded=loaded,
        loops=loops,
        setpoints={name: float(v) for name, v in zip(card.observation_names, y_abs, strict=True)},
        offset=tuple((a, float(u)) for a, u in zip(loaded.input_names, lin.op.ctrl, strict=True)),
        plant=plant,
        omega=np.logspace(-2, math.log10(math.pi / lin.control_dt) - 1e-6, 400),
    )
    return problem, start


def _target_bandwidth(lin: Linearization, wc0: float, bandwidth: float | None, p: Preset) -> float:
    """The asked gain crossover, rad/s: given, or from the preset (see the module docstring)."""
    unstable = [ev.real for ev in np.linalg.eigvals(lin.A) if ev.real > 1e-9]
    if bandwidth is not None:
        return bandwidth
    if p.name == "weak" and unstable:
        # the slowest loop that can still catch the fastest unstable pole
        return WEAK_CROSSOVER_FACTOR * max(unstable)
    return (wc0 if math.isfinite(wc0) else 1.0) * p.bandwidth_factor


def _shaping_cost(
    z: np.ndarray,
    problem: _Problem,
    signs: np.ndarray,
    targets: tuple[float, float],
    p: Preset,
    evaluations: _Evaluations,
) -> float:
    """Mismatch of crossover and phase margin to ``targets``, with stability and Ms penalties."""
    evaluations.tick()
    target_wc, target_pm = targets
    wc, pm, ms, rho = problem.figures(signs * np.exp(z))
    j = 0.0
    if rho > p.max_spectral_radius:
        j += 100.0 + 1000.0 * (rho - p.max_spectral_radius)
    if not math.isfinite(wc):
        return j + 50.0
    j += math.log(wc / target_wc) ** 2
    j += (
        4.0 * ((target_pm - pm) / target_pm) ** 2
        if p.name == "weak"
        else 4.0 * max(0.0, (target_pm - pm) / target_pm) ** 2
    )
    if ms > p.max_ms:
        j += 4.0 * (ms - p.max_ms) ** 2
    return j


def _shape(
    problem: _Problem,
    start: np.ndarray,
    signs: np.ndarray,
    targets: tuple[float, float],
    p: Preset,
    max_evaluations: int,
    evaluations: _Evaluations,
) -> np.ndarray:
    """Nelder-Mead on the log-gains from ``start``; returns the best log-gains."""
    z0 = np.log(np.maximum(np.abs(start), 1e-6))
    best = minimize(
        _shaping_cost,
        z0,
        args=(problem, signs, targets, p, evaluations),
        method="Nelder-Mead",
        options={"maxfev": max_evaluations, "xatol": 1e-4, "fatol": 1e-8, "adaptive": True},
    )
    return np.asarray(best.x)


@dataclass(frozen=True)
class _Refined:
    """One refinement on the env: the best negative mean return, its start's signs, its log-gains."""

    fun: float
    signs: np.ndarray
    z: np.ndarray
    evaluations: int


def _refine_from(
    problem: _Problem,
    start: tuple[np.ndarray, np.ndarray],
    budget: int,
    tick: Callable[[], None] | None = None,
) -> _Refined:
    """Nelder-Mead on the mean coach-alone return on the tuning seeds from ``start = (signs, z)``.

    Depends on nothing but its arguments (a task of :func:`pidlab.parallel.run_all`).
    """
    from pidlab.controller.rollout import coach_alone

    signs, z_start = start

    def neg_return(z: np.ndarray) -> float:
        if tick is not None:
            tick()
        return -coach_alone(problem.spec(signs * np.exp(z)), problem.loaded, episodes=3, seed0=1000).mean

    res = minimize(neg_return, z_start, method="Nelder-Mead", options={"maxfev": budget, "adaptive": True})
    return _Refined(float(res.fun), signs, np.asarray(res.x), int(res.nfev))


def _problem_state(problem: _Problem) -> _Problem:
    """The state of a refinement worker: the tuning problem itself."""
    return problem


def _refine_on_env(
    problem: _Problem,
    signs: np.ndarray,
    z: np.ndarray,
    budget: int,
    evaluations: _Evaluations,
    workers: int = 1,
) -> tuple[np.ndarray, float]:
    """Maximize the mean coach-alone return on the tuning seeds from two starts; keep the better.

    The two refinements are independent: with ``workers`` > 1 they run side by side in worker
    processes (the same result; ``evaluations`` then advances as each one finishes).
    Returns the refined gains and their mean return.
    """
    from pidlab.parallel import run_all

    # two starts: the linear design, and plain posture PD on every joint loop (the torso-pitch
    # loop nearly off); both are refined and the better result is kept
    posture = np.array(
        [-v if lt.signal.endswith("joint_pos") else -1e-3 for lt in problem.loops for v in POSTURE_START]
    )
    candidates = [(signs, z), (np.where(posture >= 0, 1.0, -1.0), np.log(np.abs(posture)))]
    if workers > 1:
        task = functools.partial(_refine_from, budget=budget)
        results = run_all(_problem_state, (problem,), task, candidates, min(workers, len(candidates)))
        for r in results:
            evaluations.add(r.evaluations)
    else:
        results = [_refine_from(problem, c, budget, evaluations.tick) for c in candidates]
    best = min(results, key=lambda r: r.fun)
    return best.signs * np.exp(best.z), float(-best.fun)


def _achieved(spec: CoachSpec, loaded: LoadedModel, lin: Linearization) -> tuple[float, float, float, float]:
    """(bandwidth, phase margin, Ms, spectral radius) from the analysis' own margins.

    The optimizer's fast grid is not what is reported: the analysis is.
    """
    from pidlab.controller.analysis import analyze_coach

    final = analyze_coach(Coach(spec, loaded), loaded, lin)
    wc = max((m.bandwidth for m in final.discrete.margins if m.crossovers), default=math.nan)
    pm = min((m.phase_margin_deg for m in final.discrete.margins), default=math.inf)
    ms = max((m.ms for m in final.discrete.margins), default=math.nan)
    rho = max(abs(p_.value) for p_ in final.discrete.poles)
    return float(wc), float(pm), float(ms), float(rho)


def tune_result(
    spec: CoachSpec,
    loaded: LoadedModel,
    lin: Linearization,
    preset: str,
    targets: tuple[float, float],
    evaluations: int,
    refined: float | None,
    description: str | None = None,
    extra: dict[str, Any] | None = None,
) -> TuneResult:
    """The tuned spec with its description and provenance, and what it achieved."""
    wc, pm, ms, rho = _achieved(spec, loaded, lin)
    target_wc, target_pm = (float(t) for t in targets)
    spec = replace(
        spec,
        description=description
        or (
            f"pidlab auto-tuned coach ({preset} preset) for {loaded.env_id}: LQR-projected start, then "
            f"Nelder-Mead on crossover and phase margin at every actuator."
        ),
        provenance={
            "tool": f"pidlab {__version__} tune --auto",
            "date": _dt.date.today().isoformat(),
            "preset": preset,
            **({"asked_bandwidth_rad_s": target_wc} if math.isfinite(target_wc) else {}),
            **({"asked_phase_margin_deg": target_pm} if math.isfinite(target_pm) else {}),
            "achieved_bandwidth_rad_s": wc,
            "achieved_phase_margin_deg": pm,
            "achieved_ms": ms,
            "closed_loop_spectral_radius": rho,
            "operating_point": lin.op.source,
            **({"refined_mean_return_tuning_seeds": refined} if refined is not None else {}),
            **(extra or {}),
        },
    )
    return TuneResult(
        spec=spec,
        preset=preset,
        asked_bandwidth=target_wc,
        asked_phase_margin=target_pm,
        achieved_bandwidth=wc,
        achieved_phase_margin=pm,
        achieved_ms=ms,
        spectral_radius=rho,
        evaluations=evaluations,
        refined_return=refined,
    )


def tune(
    loaded: LoadedModel,
    *,
    bandwidth: float | None = None,
    phase_margin: float | None = None,
    preset: str = "robust",
    lin: Linearization | None = None,
    max_evaluations: int = 400,
    refine_evaluations: int = 120,
    progress: Callable[[int], None] | None = None,
    workers: int | None = None,
) -> TuneResult:
    """Tune a coach for ``loaded`` from its template.

    Parameters
    ----------
    loaded : LoadedModel
        An env with a model card that holds a ``[tuning]`` template.
    bandwidth : float, optional
        Target gain-crossover frequency, rad/s. Default: the LQR start's crossover times the
        preset's factor.
    phase_margin : float, optional
        Target phase margin, degrees. Default: the preset's.
    preset : {"robust", "weak"}
    lin : Linearization, optional
        Default: linearized at the model card's operating point.
    max_evaluations : int
        Budget of the shaping step.
    refine_evaluations : int
        Contact-rich envs (Hopper, Walker2d) with the robust preset: budget of each of the two
        refinements (from the linear design and from a posture-PD start) that maximize the mean
        coach-alone return over three tuning seeds (1000-1002, disjoint from the evaluation
        seeds 0..N-1); the better is kept. 0 disables it.
    progress : callable, optional
        Called with the number of evaluations so far.
    workers : int, optional
        Worker processes for the refinement on the env (default: the machine's cores; at most
        two are used, one per start; 1: all in this process). The result is the same for any
        number; with more than one, ``progress`` advances as each refinement finishes.

    Returns
    -------
    TuneResult

    Raises
    ------
    PidlabError
        No template for the env, unknown preset, or no stabilizing gains found; or ``workers``
        outside [1, 256].
    """
    from pidlab.parallel import resolve_workers

    card = check_request(loaded, bandwidth, phase_margin, preset)
    n_workers = resolve_workers(workers)
    p = PRESETS[preset]
    if lin is None:
        lin = linearize(loaded)
    problem, start = tuning_problem(loaded, card, lin, p)
    wc0 = problem.figures(start)[0]
    targets = (
        _target_bandwidth(lin, wc0, bandwidth, p),
        phase_margin if phase_margin is not None else p.phase_margin,
    )
    signs = np.where(start >= 0, 1.0, -1.0)
    evaluations = _Evaluations(progress)
    z = _shape(problem, start, signs, targets, p, max_evaluations, evaluations)
    gains = signs * np.exp(z)
    refined = None
    if card.refine_on_env and preset == "robust" and refine_evaluations > 0:
        gains, refined = _refine_on_env(problem, signs, z, refine_evaluations, evaluations, n_workers)
    elif not card.refine_on_env:
        rho = problem.figures(gains)[3]
        if rho > p.max_spectral_radius:
            raise PidlabError(
                f"no stabilizing gains found for {loaded.name} with the {preset} preset "
                f"(closed-loop spectral radius {rho:.4f}); try another target bandwidth (rad/s) "
                "or phase margin (degrees)"
            )
    spec = problem.spec(gains, f"pidlab-{preset}")
    return tune_result(spec, loaded, lin, preset, targets, evaluations.count, refined)
