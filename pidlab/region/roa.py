"""Regions of attraction of a coached closed loop, certified against MuJoCo.

Pendulums (smooth dynamics)
    ``V(X) = X' P X`` from the discrete closed-loop linearization (plant tangent state and the
    coach's own states), with ``A_cl' P A_cl - P = -Q`` and ``Q = I`` in those coordinates
    (SI units: m, rad, m/s, rad/s; every state direction weighted alike, so ``V`` measures the
    plain squared deviation that the closed loop removes per step). Two estimates of the
    largest level ``c`` with ``{V <= c}`` attracted:

    - **optimization** (CasADi + IPOPT, multi-start): the symbolic cart-pole model of
      :mod:`pidlab.linear.symbolic`, integrated with RK4 over one control period exactly as the env
      does, closed by the coach's law with saturation: ``c_opt = min V(X)`` subject to
      ``V(F(X)) >= V(X)``, ``V(X) >= delta``. Below ``c_opt``, ``V`` decreases every step;
    - **simulation** (MuJoCo itself, the coach's real discrete law, saturation, the env's
      termination rule): states sampled uniformly in ``{V <= c}`` (coach at reset), simulated
      for a horizon; a sample fails if the episode would terminate or ``V`` has not decreased
      by the end. Bisection on ``c`` (up to ``4 c_opt`` and the termination limits), then a final
      check with ``N`` samples.

    The certified level has zero failures among ``N`` samples: by the rule of three the
    probability of failure from a uniformly drawn state in the set is below ``3/N`` at 95 %.

Hopper and Walker2d (contacts)
    A quadratic Lyapunov argument over contacts is not sound. The recoverable set is estimated
    by simulation only, as a box over the coached variables (torso pitch and its rate) around
    the standing pose: the largest box from whose corners and interior (sampled) the coach
    recovers without termination within the horizon. A balance coach, designed about a posture
    of its own, can have the level set instead (``method="lyapunov"``): about that posture, from
    the linear model there, over every observed variable, certified by the simulation check alone
    (:func:`contact_analysis`).

Every result says which method produced it.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import casadi as cs
import mujoco
import numpy as np
import scipy.linalg

from pidlab.checks import MAX_SAMPLES, instance, integer, number, shown
from pidlab.checks import seed as check_seed
from pidlab.controller.analysis import CoachAnalysis, analyze_coach
from pidlab.controller.pid import N_LOOP_STATES, Coach, law
from pidlab.controller.spec import CoachSpec
from pidlab.errors import PidlabError, RegionError
from pidlab.linear.linearize import Linearization
from pidlab.parallel import resolve_workers, run_all
from pidlab.plant.card import ModelCard
from pidlab.plant.model import LoadedModel
from pidlab.region.shrink import geometric_bisect, halving_bisect, shrink_until_clean
from pidlab.region.simulate import SimulationPool, Simulator, horizon_steps, sample_ellipsoid, tangent_index

OPTIMIZATION_HORIZON_S = 0.5
"""Window of the finite-step decrease condition in the CasADi estimate, s."""

METHOD_LYAPUNOV = "lyapunov level set, certified by simulation"
METHOD_SIMULATION = "simulation: recoverable box over the coached variables (no Lyapunov argument)"

LEVEL_SHRINK = 0.7
"""Lyapunov method: factor on ``c`` after a failed final check."""

BOX_SHRINK = 0.8
"""Simulation method: factor on the box scale after a failed final check."""

Progress = Callable[[str, "float | None"], None]
"""``progress(stage, fraction)``: what a long estimate is doing; fraction in [0, 1] or None."""


def _no_progress(stage: str, fraction: float | None) -> None:
    return None


def _final_tick(report: Progress, samples: int) -> Callable[[int], None]:
    """``tick(done)``: reports the final check's progress every 2 % (``done`` may jump, from workers)."""
    every = max(1, samples // 50)
    shown = [-1]

    def tick(i: int) -> None:
        if i // every != shown[0]:
            shown[0] = i // every
            report(f"final check ({i}/{samples} samples)", i / samples)

    return tick


@dataclass(frozen=True)
class Lyapunov:
    """A quadratic Lyapunov function of the discrete closed loop.

    Attributes
    ----------
    P : ndarray, shape (n, n)
        Over ``X = (plant tangent deviation, coach state deviation)``.
    Q : ndarray, shape (n, n)
    A_cl : ndarray, shape (n, n)
    variables : tuple of str
        Observation variables that determine the plant state (in observation order).
    center : ndarray, shape (k,)
        Their values at the operating point.
    to_state : ndarray, shape (n, k)
        ``X = to_state @ (y - center)`` with the coach at reset.
    P_y : ndarray, shape (k, k)
        ``V`` in the observation variables: ``to_state' P to_state``.
    tangent : tuple of int, optional
        Per variable, its index in the simulator's tangent state ``(dq, dv)``, where the linear
        model is the observable part of the plant only (a robot whose observation leaves out a
        coordinate no other state depends on, such as Walker2d's forward position) and the coach
        has no states: a sample then starts from the variables themselves, and ``V`` is read from
        the observation (:func:`region_start`, :func:`region_value`). None: through ``to_state``.
    """

    P: np.ndarray
    Q: np.ndarray
    A_cl: np.ndarray
    variables: tuple[str, ...]
    center: np.ndarray
    to_state: np.ndarray
    P_y: np.ndarray
    tangent: tuple[int, ...] | None = None


@dataclass(frozen=True)
class SimulationCheck:
    """Outcome of simulating the coach from sampled initial states.

    Attributes
    ----------
    level : float
        The level (or box scale) checked.
    samples, failures, terminated, not_converged : int
    horizon_s : float
    seed : int
    """

    level: float
    samples: int
    failures: int
    terminated: int
    not_converged: int
    horizon_s: float
    seed: int

    @property
    def failure_bound_95(self) -> float:
        """Rule of three: upper 95 % bound on the failure probability with zero failures (3/N)."""
        return 3.0 / self.samples if self.samples else 1.0


@dataclass(frozen=True)
class RegionOfAttraction:
    """A certified region of attraction (or recoverable set) of a coach.

    Attributes
    ----------
    env_id, spec_name, method : str
    lyapunov : Lyapunov or None
        None for the simulation-only method.
    level : float
        Certified level ``c`` of ``{V <= c}`` (Lyapunov method).
    c_optimization : float or None
        CasADi estimate (None where no symbolic model or the coach has states).
    c_simulation : float
        Bisection result before the final check.
    box : dict of str to float
        Simulation method: half-widths of the recoverable box, per coached variable.
    check : SimulationCheck
        The final certification run.
    elapsed_s : float
    """

    env_id: str
    spec_name: str
    method: str
    lyapunov: Lyapunov | None
    level: float
    c_optimization: float | None
    c_simulation: float
    check: SimulationCheck
    elapsed_s: float
    box: dict[str, float] = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# Lyapunov function


def _select_variables(C: np.ndarray, names: tuple[str, ...]) -> list[int]:
    """Observation rows, in order, that together determine the plant state."""
    chosen: list[int] = []
    for i in range(C.shape[0]):
        rows = C[[*chosen, i]]
        if np.linalg.matrix_rank(rows, tol=1e-9) > len(chosen):
            chosen.append(i)
        if len(chosen) == C.shape[1]:
            break
    if len(chosen) < C.shape[1]:
        raise RegionError(
            f"the observation does not determine the plant state ({len(chosen)} of {C.shape[1]}); "
            "no region in observation variables can be given"
        )
    return chosen


def lyapunov_function(analysis: CoachAnalysis, coach: Coach, y_op: np.ndarray) -> Lyapunov:
    """Solve the discrete Lyapunov equation of the closed loop, ``Q = I``.

    Raises
    ------
    RegionError
        The closed loop is not (strictly) stable; or its linear model is the plant's observable
        part only and the coach has states of its own (``V`` could not be read from the
        observation), or a variable is no joint's position or rate.
    """
    if not analysis.stable:
        bad = ", ".join(f"|z|={abs(p.value):.5f}" for p in analysis.discrete.poles if not p.stable)
        raise RegionError(f"no region of attraction: closed loop is unstable; poles {bad}")
    A = np.asarray(analysis.discrete.sys.A)
    n = A.shape[0]
    Q = np.eye(n)
    P = scipy.linalg.solve_discrete_lyapunov(A.T, Q)
    P = 0.5 * (P + P.T)
    plant = analysis.plant
    Cp = np.asarray(plant.C)
    names = tuple(plant.output_labels)
    chosen = _select_variables(Cp, names)
    Csel_inv = np.linalg.inv(Cp[chosen])
    rows = [Csel_inv]
    lay = coach.layout
    keep = lay.active_states()
    for i, lp in enumerate(lay.spec.loops):
        sig = names.index(lp.signal)
        for k in range(N_LOOP_STATES):
            if keep[N_LOOP_STATES * i + k]:
                # at reset: integral 0, filter 0, previous measurement = the signal
                rows.append((Cp[sig] @ Csel_inv)[None, :] if k == 2 else np.zeros((1, len(chosen))))
    M = np.vstack(rows)
    variables = tuple(names[i] for i in chosen)
    reduced = Cp.shape[1] < analysis.linearization.sysd.nstates
    return Lyapunov(
        P=P,
        Q=Q,
        A_cl=A,
        variables=variables,
        center=y_op[chosen],
        to_state=M,
        P_y=M.T @ P @ M,
        tangent=_tangent_of(variables, coach, analysis.linearization) if reduced else None,
    )


def _tangent_of(variables: tuple[str, ...], coach: Coach, lin: Linearization) -> tuple[int, ...]:
    """Each variable's index in the tangent state, for a linear model of the observable part only.

    Raises
    ------
    RegionError
        The coach has states (``V`` would need them), or a variable is no joint's position or rate.
    """
    if np.any(coach.layout.active_states()):
        raise RegionError(
            f"{coach.spec.name}: the linear model is the plant's observable part only, and a level set "
            "over it needs a coach without states of its own (kp only); this coach has integrators, "
            "filters or derivatives"
        )
    states = lin.state_names
    missing = [v for v in variables if v not in states]
    if missing:
        raise RegionError(
            f"{coach.spec.name}: {missing[0]!r} is no joint position or rate of the model; a level set over "
            "the observable part is drawn in joint coordinates"
        )
    return tuple(states.index(v) for v in variables)


def region_start(sim: Simulator, lyap: Lyapunov, y_dev: np.ndarray) -> tuple[np.ndarray, float]:
    """Put ``sim`` at the region's centre (+) the observation deviation ``y_dev``: the obs, and ``V`` there.

    Through ``to_state`` (the coach at reset), or, with :attr:`Lyapunov.tangent`, each variable
    moved by its own deviation (the coordinates the observation leaves out at the centre's).
    """
    if lyap.tangent is None:
        X0 = lyap.to_state @ y_dev
        return sim.start(X0[: sim.lin.sysd.nstates]), float(X0 @ lyap.P @ X0)
    x = np.zeros(2 * sim.m.nv)
    x[list(lyap.tangent)] = y_dev
    return sim.start(x), float(y_dev @ lyap.P_y @ y_dev)


def region_value(sim: Simulator, lyap: Lyapunov, obs: np.ndarray) -> float:
    """``V`` where ``sim`` stands (``obs`` its observation there).

    Over the closed-loop state (:meth:`Simulator.closed_loop_state`), or, with
    :attr:`Lyapunov.tangent`, over the observation: ``(y - center)' P_y (y - center)``.
    """
    if lyap.tangent is None:
        X = sim.closed_loop_state()
        return float(X @ lyap.P @ X)
    names = sim.card.observation_names
    y = np.array([obs[names.index(v)] for v in lyap.variables]) - lyap.center
    return float(y @ lyap.P_y @ y)


# --------------------------------------------------------------------------------------------
# Simulation with MuJoCo and the coach's real law (:mod:`pidlab.region.simulate`)


def ellipse_slice(
    P: np.ndarray, center: np.ndarray, level: float, idx: tuple[int, int], points: int = 200
) -> np.ndarray:
    """Boundary of ``{y : (y - c)' P (y - c) <= level}`` cut by the plane of ``idx`` through ``c``.

    Returns
    -------
    xy : ndarray, shape (2, points)
        The two chosen coordinates along the boundary.
    """
    M = np.asarray(P)[np.ix_(idx, idx)]
    t = np.linspace(0, 2 * np.pi, points)
    pts = np.linalg.solve(np.linalg.cholesky(M / level).T, np.vstack([np.cos(t), np.sin(t)]))
    return np.asarray(center)[list(idx), None] + pts


@dataclass(frozen=True)
class Trajectory:
    """A simulated trajectory, for plots: recorded observation columns and its outcome."""

    path: np.ndarray
    recovered: bool


RECOVERED, TERMINATED, NOT_CONVERGED = 0, 1, 2
"""Outcomes of one simulation from a state in ``{V <= c}``."""


def _level_sample(
    sim: Simulator, item: tuple[np.ndarray, bool], lyap: Lyapunov, steps: int, record: list[int] | None
) -> tuple[int, np.ndarray | None]:
    """One simulation from ``item = (y_dev, keep_path)``: its outcome, and its path if kept.

    A task of :meth:`~pidlab.parallel.WorkerPool.run`.
    """
    y_dev, keep_path = item
    obs, v0 = region_start(sim, lyap, y_dev)
    term, path = sim.run(obs, steps, record)
    outcome = TERMINATED if term else RECOVERED
    if not term and region_value(sim, lyap, sim.observe()) >= v0:
        outcome = NOT_CONVERGED
    return outcome, (path if keep_path else None)


def _level_failed(result: tuple[int, np.ndarray | None]) -> bool:
    """Whether :func:`_level_sample` found a failure (stops a batch)."""
    return result[0] != RECOVERED


def _check_level(
    pool: SimulationPool,
    lyap: Lyapunov,
    c: float,
    n: int,
    steps: int,
    rng: np.random.Generator,
    record: list[int] | None = None,
    keep: int = 0,
    tick: Callable[[int], None] | None = None,
) -> tuple[int, int, list[Trajectory]]:
    """(terminated, not converged, kept trajectories) among n samples in {V <= c}.

    The n samples are drawn from ``rng`` first (always all n). The simulations stop at the
    first failure: then the counts are those found so far (only whether they are zero is
    reproducible) and no trajectory is kept.
    """
    items = [(y, i < keep) for i, y in enumerate(sample_ellipsoid(lyap.P_y, c, n, rng))]
    task = functools.partial(_level_sample, lyap=lyap, steps=steps, record=record)
    batch = pool.run(task, items, stop=_level_failed, tick=tick)
    outcomes = [code for code, _ in batch.results]
    first = [] if batch.stopped else batch.results[:keep]
    kept = [Trajectory(path, code == RECOVERED) for code, path in first if path is not None]
    return outcomes.count(TERMINATED), outcomes.count(NOT_CONVERGED), kept


def phase_portrait(
    spec: CoachSpec,
    loaded: LoadedModel,
    variables: tuple[str, str],
    extent: tuple[float, float],
    grid: int = 7,
    horizon_s: float = 3.0,
    method: str | None = None,
) -> list[np.ndarray]:
    """Coached MuJoCo trajectories, recorded in two variables, from a grid over ``+-extent``.

    About the point the region of ``method`` (default: the model card's) is drawn at: the
    operating point, where the two variables are set through the plant state (least-norm change)
    and everything else stays; or, for a level set over contacts, the balance coach's posture,
    where each of the two moves by its own offset (:func:`region_start`).

    Raises
    ------
    RegionError
        A variable unknown, or not one the level set over contacts is drawn in; ``method`` as
        :func:`region_method`.
    """
    check_variables(variables, loaded, "variables", count=2)
    chosen = region_method(loaded, method)
    coach = Coach(spec, loaded)
    analysis = region_analysis(spec, loaded, coach, chosen)
    lin = analysis.linearization
    sim = Simulator(spec, loaded, lin)
    names = loaded.require_card().observation_names
    idx = [names.index(v) for v in variables]
    start = _portrait_start(sim, analysis, coach, variables, chosen)
    steps = horizon_steps(horizon_s, loaded.control_dt)
    paths = []
    for a in np.linspace(-extent[0], extent[0], grid):
        for b in np.linspace(-extent[1], extent[1], grid):
            _, path = sim.run(start(a, b), steps, idx)
            paths.append(path)
    return paths


def check_portrait_variables(
    spec: CoachSpec,
    loaded: LoadedModel,
    variables: tuple[str, str],
    method: str | None = None,
    param: str = "variables",
) -> None:
    """Refuse, before any simulation, two variables :func:`phase_portrait` cannot draw in.

    Any two observation variables serve about the operating point; about a balance coach's
    posture (a level set over contacts), only two the level set is drawn in.

    Raises
    ------
    RegionError
        As :func:`phase_portrait`.
    """
    check_variables(variables, loaded, param, count=2)
    chosen = region_method(loaded, method)
    if not over_contacts(loaded, chosen):
        return
    coach = Coach(spec, loaded)
    analysis = region_analysis(spec, loaded, coach, chosen)
    y_op = Simulator(spec, loaded, analysis.linearization).y_op
    lyap = lyapunov_function(analysis, coach, y_op)
    if lyap.tangent is not None:
        _check_posture_pair(lyap, spec.name, variables, param)


def _check_posture_pair(
    lyap: Lyapunov, coach_name: str, variables: tuple[str, str], param: str = "variables"
) -> None:
    """Refuse a variable the level set about a posture is not drawn in."""
    missing = [v for v in variables if v not in lyap.variables]
    if missing:
        raise RegionError(
            f"{param}={','.join(variables)}: {missing[0]!r} is not among the variables the level set "
            f"about {coach_name}'s posture is drawn in; expected two of {', '.join(lyap.variables)}",
            param=param,
        )


def _portrait_start(
    sim: Simulator, analysis: CoachAnalysis, coach: Coach, variables: tuple[str, str], method: str
) -> Callable[[float, float], np.ndarray]:
    """``start(a, b)``: ``sim`` put where the two variables deviate by ``a`` and ``b``; its observation."""
    lyap = lyapunov_function(analysis, coach, sim.y_op) if over_contacts(sim.loaded, method) else None
    if lyap is not None and lyap.tangent is not None:
        _check_posture_pair(lyap, coach.spec.name, variables)
        pos = [lyap.variables.index(v) for v in variables]

        def about_posture(a: float, b: float) -> np.ndarray:
            y_dev = np.zeros(len(lyap.variables))
            y_dev[pos] = (a, b)
            return region_start(sim, lyap, y_dev)[0]

        return about_posture
    names = sim.card.observation_names
    Cinv = np.linalg.pinv(np.asarray(analysis.linearization.sysd.C))
    cols = [Cinv[:, names.index(v)] for v in variables]
    return lambda a, b: sim.start(cols[0] * a + cols[1] * b)


# --------------------------------------------------------------------------------------------
# Optimization-based estimate (CasADi, symbolic pendulum)


def optimization_level(
    spec: CoachSpec,
    loaded: LoadedModel,
    lyap: Lyapunov,
    coach: Coach,
    lin: Linearization,
    horizon_steps: int = 1,
    starts: int = 16,
    seed: int = 0,
    c_scale: float = 1.0,
    workers: int | None = None,
) -> float | None:
    """``min V(X)`` subject to ``V(F^k(X)) >= V(X)``, ``V(X) >= delta``, multi-start IPOPT.

    ``F`` is one control period of the symbolic cart-pole model (RK4 at the model's timestep,
    ``frame_skip`` times, control held), closed by the coach's law with saturation; ``k`` is
    ``horizon_steps``. With ``k = 1`` this is the classical one-step decrease; a slow
    closed-loop mode makes the one-step decrease tiny relative to ``V`` and the estimate
    needlessly small, so ``k > 1`` uses the finite-step Lyapunov condition (``V`` decreases
    over every ``k`` steps), which also implies attraction. Returns None when there is no
    symbolic model (not a cart-pole chain) or the coach has states of its own (the static map
    ``u(X)`` would not be the coach). The starts are solved over ``workers`` processes (default:
    the machine's cores, at most 4); the result does not depend on their number.
    """
    from pidlab.linear.symbolic import cart_pole_dynamics, cart_pole_parameters

    lay = coach.layout
    if np.any(lay.active_states()):
        return None
    try:
        sym = cart_pole_dynamics(cart_pole_parameters(loaded.model))
    except PidlabError:
        return None
    x = cs.SX.sym("x", 2 * loaded.model.nq)
    observe_sym = _symbolic_observation(loaded.require_card(), loaded.model, x)
    xk = _coached_steps(sym.f, observe_sym, coach, loaded, x, horizon_steps)
    x_op = np.concatenate([lin.op.qpos, lin.op.qvel])
    P = lyap.P
    V = cs.bilin(cs.DM(P), x - x_op, x - x_op)
    V_next = cs.bilin(cs.DM(P), xk - x_op, xk - x_op)
    # exclude a small ball: the symbolic model's closed-loop equilibrium sits a hair away from
    # MuJoCo's (e.g. a few micrometres of cart offset under a slow cart loop), where V cannot
    # decrease; below delta = 1e-4 c_scale that is all the optimizer would find
    delta = 1e-4 * c_scale
    solver = _ipopt({"x": x, "f": V, "g": cs.vertcat(V_next - V, V)})
    return _multistart_minimum(
        solver, x_op, P, c_scale, delta, starts, seed, resolve_workers(workers, RegionError)
    )


def _symbolic_observation(card: ModelCard, m: mujoco.MjModel, x: cs.SX) -> cs.Function:
    """The observation as a CasADi function of the state ``x = (qpos, qvel)``.

    ``qfrc_constraint`` entries are zero (away from joint limits).
    """
    nq = m.nq
    ys = []
    for var in card.observation:
        jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, var.joint)
        if var.source == "qfrc_constraint":
            ys.append(cs.SX(0.0))
            continue
        idx = int(m.jnt_qposadr[jid]) if var.source == "qpos" else nq + int(m.jnt_dofadr[jid])
        v = x[idx]
        ys.append(cs.sin(v) if var.transform == "sin" else cs.cos(v) if var.transform == "cos" else v)
    return cs.Function("observe", [x], [cs.vertcat(*ys)])


def _coached_steps(
    f: cs.Function, observe_sym: cs.Function, coach: Coach, loaded: LoadedModel, x: cs.SX, steps: int
) -> cs.SX:
    """The state after ``steps`` control periods of the static, saturated coach on ``f`` (RK4)."""
    lay = coach.layout
    n_obs = len(loaded.require_card().observation)
    _, u_const, _ = law(lay, np.zeros(lay.n_states), np.zeros(n_obs), lay.setpoints, saturate=False)
    K = np.asarray(coach.linear_model().D)[:, :n_obs]
    h = float(loaded.model.opt.timestep)
    xk = x
    for _ in range(steps):
        u = cs.fmin(
            cs.fmax(u_const[0] + cs.mtimes(cs.DM(K[0:1]), observe_sym(xk)), lay.ctrl_low[0]), lay.ctrl_high[0]
        )
        for _ in range(loaded.frame_skip):
            k1 = f(xk, u)
            k2 = f(xk + h / 2 * k1, u)
            k3 = f(xk + h / 2 * k2, u)
            k4 = f(xk + h * k3, u)
            xk = xk + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return xk


def _ipopt(nlp: dict[str, cs.SX]) -> cs.Function:
    """A quiet IPOPT solver for ``nlp``."""
    return cs.nlpsol(
        "roa",
        "ipopt",
        nlp,
        {
            "ipopt.print_level": 0,
            "ipopt.sb": "yes",
            "print_time": False,
            "show_eval_warnings": False,
            "ipopt.max_iter": 300,
            "ipopt.tol": 1e-10,
        },
    )


def _multistart_minimum(
    solver: cs.Function,
    x_op: np.ndarray,
    P: np.ndarray,
    c_scale: float,
    delta: float,
    starts: int,
    seed: int,
    workers: int = 1,
) -> float | None:
    """Smallest feasible ``V`` IPOPT finds from ``starts`` random starts; None if none is feasible.

    Start points lie on the level sets ``V = c_scale * 10^(-3..2)``, in random directions; the
    search stays within ``V <= 100 c_scale``. The starts are drawn first, then solved (over
    ``workers`` processes: each start's solve depends on nothing else).
    """
    rng = np.random.default_rng(seed)
    x0s = []
    for _ in range(starts):
        d = rng.standard_normal(len(x_op))
        d *= math.sqrt(c_scale * 10 ** rng.uniform(-3, 2) / float(d @ P @ d))
        x0s.append(x_op + d)
    task = functools.partial(_solve_from, bounds=([0.0, delta], [cs.inf, 100.0 * c_scale]), delta=delta)
    best = math.inf
    for value in run_all(_given, (solver,), task, x0s, workers):
        if value is not None:
            best = min(best, value)
    return best if math.isfinite(best) else None


def _given(value: cs.Function) -> cs.Function:
    """The state of a worker that solves from given starts: the solver itself."""
    return value


def _solve_from(
    solver: cs.Function, x0: np.ndarray, bounds: tuple[list[float], list[float]], delta: float
) -> float | None:
    """``V`` at IPOPT's solution from ``x0``, or None when it fails or ends infeasible."""
    try:
        sol = solver(x0=x0, lbg=bounds[0], ubg=bounds[1])
    except RuntimeError:  # pragma: no cover - IPOPT gives up on a start
        return None
    if solver.stats()["success"]:
        g = np.array(sol["g"]).ravel()
        if g[0] >= -1e-7 * g[1] and g[1] >= delta * 0.99:
            return float(sol["f"])
    return None


# --------------------------------------------------------------------------------------------
# The estimate


@dataclass(frozen=True)
class _Budget:
    """The simulation budget of one estimate (the arguments of :func:`estimate_roa`)."""

    samples: int
    seed: int
    horizon_s: float
    bisection_samples: int
    bisection_rounds: int
    keep: int
    record: tuple[str, str] | None

    def record_columns(self, card: ModelCard) -> list[int] | None:
        """Observation columns of :attr:`record` (None: record nothing)."""
        return [card.observation_names.index(v) for v in self.record] if self.record else None


def _termination_cap(lyap: Lyapunov, loaded: LoadedModel) -> float:
    """Largest c whose ellipsoid stays inside the termination limits on observed joint positions."""
    card = loaded.require_card()
    cap = math.inf
    Pinv = np.linalg.inv(lyap.P_y)
    for limit in card.termination:
        if limit.signal in lyap.variables:
            i = lyap.variables.index(limit.signal)
            room = min(abs(limit.high - lyap.center[i]), abs(lyap.center[i] - limit.low))
            cap = min(cap, room**2 / Pinv[i, i])
    return cap


MAX_HORIZON_S = 3600.0
"""The longest simulated time per trajectory, s."""


def check_variables(
    names: list[str] | tuple[str, ...],
    loaded: LoadedModel,
    param: str = "variables",
    count: int | None = None,
) -> None:
    """Refuse anything but distinct observation variables of ``loaded`` (``count`` of them when given).

    The one check of the variables a box, a plot slice or a recording is asked for: a variable
    named twice makes every matrix built on them singular.

    Raises
    ------
    UnknownSignalError
        A name the observation does not have (the message lists the valid names).
    RegionError
        Not a list of names, the wrong number of them, or a name given twice; ``param`` names
        the Python parameter.
    """
    if isinstance(names, str) or not isinstance(names, (list, tuple)):
        raise RegionError(f"{param}={shown(names)}: expected a list of observation variables", param=param)
    given = shown(",".join(map(str, names)), 80)
    if count is not None and len(names) != count:
        raise RegionError(f"{param}={given}: expected {count} observation variables", param=param)
    if not names:
        raise RegionError(f"{param}=[]: expected at least one observation variable", param=param)
    card = loaded.require_card()
    for n in names:
        card.variable(n)
    twice = [n for i, n in enumerate(names) if n in names[:i]]
    if twice:
        raise RegionError(
            f"{param}={given}: {twice[0]!r} is named twice; expected distinct observation variables",
            param=param,
        )


def _check_budget(
    samples: int, seed: int, horizon_s: float, bisection_samples: int, bisection_rounds: int, keep: int
) -> None:
    """Check :func:`estimate_roa`'s budget arguments (each error names its Python parameter).

    Raises
    ------
    RegionError
    """
    counts = {"samples": (samples, 1), "bisection_samples": (bisection_samples, 1),
              "bisection_rounds": (bisection_rounds, 0), "keep_trajectories": (keep, 0)}  # fmt: skip
    for name, (value, low) in counts.items():
        integer(value, name, RegionError, low=low, high=MAX_SAMPLES if low else 10**6, param=name)
    check_seed(seed, "seed", RegionError, param="seed")
    number(horizon_s, "horizon_s", RegionError, low=0.0, high=MAX_HORIZON_S, low_open=True, unit="s",
           param="horizon_s")  # fmt: skip


def estimate_roa(
    spec: CoachSpec,
    loaded: LoadedModel,
    samples: int = 1000,
    seed: int = 0,
    horizon_s: float = 3.0,
    bisection_samples: int = 50,
    bisection_rounds: int = 8,
    keep_trajectories: int = 0,
    record: tuple[str, str] | None = None,
    progress: Progress | None = None,
    workers: int | None = None,
    method: str | None = None,
) -> tuple[RegionOfAttraction, list[Trajectory]]:
    """Estimate and certify the region of attraction of ``spec`` on its env.

    ``method`` (default: the model card's ``[region] method``) picks it: a Lyapunov level set, or
    (over contacts) a recoverable box found by simulation only. On a robot with contacts a level
    set is drawn about the posture a balance coach was designed at
    (:func:`pidlab.controller.balance.design_point`) from the linear model there, and certified by
    simulation alone (:func:`contact_analysis`).

    Parameters
    ----------
    spec : CoachSpec
    loaded : LoadedModel
    samples : int
        Final certification: number of simulated initial states (N).
    seed : int
    horizon_s : float
        Simulated time per trajectory, s.
    bisection_samples, bisection_rounds : int
        Budget of the bisection on the level.
    keep_trajectories : int
        How many final-check trajectories to return (for plots).
    record : (str, str), optional
        Two distinct observation variables to record along those trajectories.
    progress : callable, optional
        Called as ``progress(stage, fraction)`` while the estimate runs (``fraction`` in [0, 1],
        or None where the stage's length is unknown). It may raise to abandon the estimate.
    workers : int, optional
        Worker processes for the simulations (default: the machine's cores, at most 4; 1: all
        in this process). The result is the same for any number of workers.
    method : {"lyapunov", "simulation"}, optional
        The region's kind; default the model card's.

    Returns
    -------
    RegionOfAttraction, list of Trajectory

    Raises
    ------
    RegionError
        Unstable closed loop, or nothing certified; a level set asked on a robot with contacts of
        a coach not designed about a posture of its own, or a box on a model card without region
        variables; or an argument out of its range (``samples`` in [1, 1e7], ``seed`` in
        [0, 2**32 - 1], ``horizon_s`` in (0, 3600] s, ``workers`` in [1, 256], ``method`` one of
        :data:`METHODS`, ...).
    """
    instance(spec, CoachSpec, "spec")
    instance(loaded, LoadedModel, "loaded")
    _check_budget(samples, seed, horizon_s, bisection_samples, bisection_rounds, keep_trajectories)
    if record is not None:
        check_variables(record, loaded, "record", count=2)
    chosen = region_method(loaded, method)
    n_workers = resolve_workers(workers, RegionError)
    t0 = time.perf_counter()
    report = progress if progress is not None else _no_progress
    coach = Coach(spec, loaded)
    analysis = region_analysis(spec, loaded, coach, chosen)
    budget = _Budget(samples, seed, horizon_s, bisection_samples, bisection_rounds, keep_trajectories, record)
    with SimulationPool(spec, loaded, analysis.linearization, n_workers) as pool:
        if chosen == "simulation":
            return _recoverable_box(pool, spec, budget, t0, report)
        return _lyapunov_region(pool, spec, coach, analysis, budget, t0, report)


METHODS = ("lyapunov", "simulation")
"""The kinds of region :func:`estimate_roa` certifies (a model card's ``[region] method``)."""


def region_method(loaded: LoadedModel, method: str | None) -> str:
    """``method``, checked, or the model card's ``[region] method`` (None).

    Raises
    ------
    RegionError
        Not one of :data:`METHODS`, or ``"simulation"`` on a card without ``[region] variables``.
    """
    card = loaded.require_card()
    if method is None:
        return card.region_method
    if method not in METHODS:
        raise RegionError(
            f"method={shown(method)}: expected one of {', '.join(METHODS)}", param="method"
        )
    if method == "simulation" and not card.region_variables:
        raise RegionError(
            f"method='simulation': {loaded.name}'s model card names no [region] variables for the box; "
            "expected method='lyapunov'",
            param="method",
        )
    return method


def over_contacts(loaded: LoadedModel, method: str) -> bool:
    """Whether a region of ``method`` on ``loaded`` is a level set over contacts (about a posture)."""
    return method == "lyapunov" and loaded.require_card().region_method == "simulation"


def region_analysis(spec: CoachSpec, loaded: LoadedModel, coach: Coach, method: str) -> CoachAnalysis:
    """The closed loop a region of ``method`` (one of :data:`METHODS`) is drawn on.

    A level set on a robot with contacts (:func:`over_contacts`): at the balance coach's posture
    (:func:`contact_analysis`); anything else: at the model card's operating point.

    Raises
    ------
    RegionError
        As :func:`contact_analysis`.
    """
    if over_contacts(loaded, method):
        return contact_analysis(spec, loaded, coach)
    return analyze_coach(coach, loaded)


def contact_analysis(spec: CoachSpec, loaded: LoadedModel, coach: Coach) -> CoachAnalysis:
    """The closed loop a level set over contacts is drawn from: at the coach's design posture.

    At a robot's reset pose the contacts and joint limits switch under any push, and the linear
    model there means little; a balance coach regulates the robot to a posture of its own, at rest
    on its feet, and was designed on the linear model there
    (:func:`pidlab.controller.balance.design_linearization`). The level set is centred there and
    certified by simulation alone (no symbolic model covers the contacts).

    Raises
    ------
    RegionError
        The coach was not designed about a posture of its own.
    """
    from pidlab.controller.balance import design_linearization

    lin = design_linearization(spec, loaded)
    if lin is None:
        raise RegionError(
            f"{spec.name}: a level set on {spec.env_id} (contacts) is drawn about the posture a balance "
            "coach was designed at, and this coach records none; expected a balance coach (`pidlab tune ENV "
            "--auto --preset balance`), or method='simulation'",
            param="method",
        )
    return analyze_coach(coach, loaded, lin)


def _lyapunov_region(
    pool: SimulationPool,
    spec: CoachSpec,
    coach: Coach,
    analysis: CoachAnalysis,
    budget: _Budget,
    t0: float,
    report: Progress,
) -> tuple[RegionOfAttraction, list[Trajectory]]:
    """The Lyapunov method: bisection on ``c``, then the final check with ``N`` samples."""
    lin = analysis.linearization
    loaded = pool.sim.loaded
    lyap = lyapunov_function(analysis, coach, pool.sim.y_op)
    steps = horizon_steps(budget.horizon_s, loaded.control_dt)
    c_opt, hi = _level_ceiling(pool, spec, lyap, coach, lin, budget.seed, report)
    lo = hi * _bisect_level(pool, lyap, hi, steps, budget, report)
    if lo == 0.0:
        smallest = hi * 0.25 ** max(budget.bisection_rounds - 1, 0)
        raise RegionError(
            f"no region of attraction certified for {spec.name}: every level down to {smallest:.3g} had "
            "failures in simulation (c -> 0); no useful bound can be written"
        )
    # final certification with N samples, on the same draws (rescaled) after a shrink
    rec = budget.record_columns(loaded.require_card())
    final = shrink_until_clean(
        lambda level: _check_level(
            pool,
            lyap,
            level,
            budget.samples,
            steps,
            np.random.default_rng(budget.seed + 1),
            rec,
            budget.keep,
            _final_tick(report, budget.samples),
        ),
        lambda outcome: outcome[0] + outcome[1] == 0,
        lo,
        LEVEL_SHRINK,
    )
    if final is None:
        raise RegionError(f"no region of attraction certified for {spec.name}: failures persist as c -> 0")
    term, nonconv, kept = final.outcome
    level = final.value
    roa = RegionOfAttraction(
        env_id=spec.env_id,
        spec_name=spec.name,
        method=METHOD_LYAPUNOV,
        lyapunov=lyap,
        level=level,
        c_optimization=c_opt,
        c_simulation=lo,
        check=SimulationCheck(
            level, budget.samples, term + nonconv, term, nonconv, budget.horizon_s, budget.seed
        ),
        elapsed_s=time.perf_counter() - t0,
    )
    return roa, kept


def _level_ceiling(
    pool: SimulationPool,
    spec: CoachSpec,
    lyap: Lyapunov,
    coach: Coach,
    lin: Linearization,
    seed: int,
    report: Progress,
) -> tuple[float | None, float]:
    """``(c_opt, hi)``: the CasADi estimate and the top of the bisection on ``c``.

    ``hi`` is the smaller of the termination cap and ``4 c_opt`` (the simulation may certify
    somewhat beyond the estimate); with neither, ``1e3 (max center^2 + 1)``. The CasADi starts
    run on as many processes as ``pool`` has workers.
    """
    loaded = pool.sim.loaded
    hi = _termination_cap(lyap, loaded)
    report("level estimate (CasADi)", None)
    c_opt = optimization_level(
        spec,
        loaded,
        lyap,
        coach,
        lin,
        horizon_steps=horizon_steps(OPTIMIZATION_HORIZON_S, loaded.control_dt),
        seed=seed,
        c_scale=hi if math.isfinite(hi) else 1.0,
        workers=pool.workers,
    )
    if c_opt is not None:
        hi = min(hi, 4.0 * c_opt)
    if not math.isfinite(hi):
        hi = 1e3 * float(np.max(lyap.center**2) + 1.0)
    return c_opt, hi


def _bisect_level(
    pool: SimulationPool, lyap: Lyapunov, hi: float, steps: int, budget: _Budget, report: Progress
) -> float:
    """Largest fraction of ``hi`` whose level passes the bisection's check (0 if none)."""
    rng = np.random.default_rng(budget.seed)
    rounds = budget.bisection_rounds
    tried = [0]

    def passes(fraction: float) -> bool:
        tried[0] += 1
        report(f"bisection on the level ({tried[0]}/{rounds})", tried[0] / rounds)
        term, nonconv, _ = _check_level(pool, lyap, fraction * hi, budget.bisection_samples, steps, rng)
        return term + nonconv == 0

    return geometric_bisect(passes, rounds - 1)


@dataclass(frozen=True)
class _BoxCheck:
    """Simulations from a box over (torso pitch, pitch rate) around the standing pose.

    ``addr`` are the two variables' indices in the tangent state; ``shape`` the box's
    half-widths at scale 1.
    """

    pool: SimulationPool
    addr: tuple[int, int]
    shape: np.ndarray
    steps: int
    record: list[int] | None

    def __call__(
        self,
        scale: float,
        n: int,
        rng: np.random.Generator,
        keep: int = 0,
        tick: Callable[[int], None] | None = None,
    ) -> tuple[int, list[Trajectory]]:
        """(failures, kept trajectories) from the box's 4 corners, then uniform interior points.

        The points are drawn from ``rng`` first (always all of them). The simulations stop at
        the first failure: then ``failures`` counts those found so far (only whether it is zero
        is reproducible) and no trajectory is kept.
        """
        corners = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1]], dtype=float)
        points = np.vstack([corners, rng.uniform(-1, 1, (max(n - 4, 0), 2))])[:n]
        items = []
        for i, p in enumerate(points):
            x = np.zeros(2 * self.pool.sim.m.nv)
            x[self.addr[0]], x[self.addr[1]] = p * self.shape * scale
            items.append((x, i < keep))
        task = functools.partial(_box_sample, steps=self.steps, record=self.record)
        batch = self.pool.run(task, items, stop=_box_failed, tick=tick)
        failures = sum(term for term, _ in batch.results)
        first = [] if batch.stopped else batch.results[:keep]
        kept = [Trajectory(path, not term) for term, path in first if path is not None]
        return failures, kept


def _box_sample(
    sim: Simulator, item: tuple[np.ndarray, bool], steps: int, record: list[int] | None
) -> tuple[bool, np.ndarray | None]:
    """One simulation from ``item = (x_plant, keep_path)``: whether it terminated, and its path if kept.

    A task of :meth:`~pidlab.parallel.WorkerPool.run`.
    """
    x, keep_path = item
    term, path = sim.run(sim.start(x), steps, record)
    return term, (path if keep_path else None)


def _box_failed(result: tuple[bool, np.ndarray | None]) -> bool:
    """Whether :func:`_box_sample` found a failure (stops a batch)."""
    return bool(result[0])


def _box_check(pool: SimulationPool, budget: _Budget) -> _BoxCheck:
    """The box's simulations: pitch up to the termination limit, pitch rate up to 10x that per second."""
    loaded = pool.sim.loaded
    card = loaded.require_card()
    m = loaded.model
    pos, rate = card.region_variables  # the card's [region] variables, e.g. torso pitch and its rate
    pitch_limit = min(abs(t.high) for t in card.termination if t.signal == pos)
    addr = (tangent_index(m, pos), tangent_index(m, rate))
    shape = np.array([pitch_limit, 10.0 * pitch_limit])
    steps = horizon_steps(budget.horizon_s, loaded.control_dt)
    return _BoxCheck(pool, addr, shape, steps, budget.record_columns(card))


def _recoverable_box(
    pool: SimulationPool,
    spec: CoachSpec,
    budget: _Budget,
    t0: float,
    report: Progress,
) -> tuple[RegionOfAttraction, list[Trajectory]]:
    """Largest box over (torso pitch, pitch rate) from which the coach recovers (simulation)."""
    check = _box_check(pool, budget)
    rng = np.random.default_rng(budget.seed)
    rounds = budget.bisection_rounds
    tried = [0]

    def passes(scale: float) -> bool:
        tried[0] += 1
        report(f"bisection on the box ({tried[0]}/{rounds})", tried[0] / rounds)
        return check(scale, budget.bisection_samples, rng)[0] == 0

    lo = halving_bisect(passes, rounds)
    if lo == 0.0:
        raise RegionError(f"no recoverable set found for {spec.name}: the coach fails from every box tried")
    final = shrink_until_clean(
        lambda scale: check(
            scale,
            budget.samples,
            np.random.default_rng(budget.seed + 1),
            budget.keep,
            _final_tick(report, budget.samples),
        ),
        lambda outcome: outcome[0] == 0,
        lo,
        BOX_SHRINK,
    )
    if final is None:
        raise RegionError(
            f"no recoverable set certified for {spec.name}: failures persist as the box shrinks"
        )
    level = final.value
    variables = pool.sim.loaded.require_card().region_variables
    box = {v: float(h * level) for v, h in zip(variables, check.shape, strict=True)}
    result = RegionOfAttraction(
        env_id=spec.env_id,
        spec_name=spec.name,
        method=METHOD_SIMULATION,
        lyapunov=None,
        level=level,
        c_optimization=None,
        c_simulation=lo,
        check=SimulationCheck(level, budget.samples, 0, 0, 0, budget.horizon_s, budget.seed),
        elapsed_s=time.perf_counter() - t0,
        box=box,
    )
    return result, final.outcome[1]
