"""Critical-state bounds: where the agent explores freely, where the coach takes over.

From a certified region (:mod:`pidlab.region.roa`), in Gymnasium observation variables:

(a) **ellipsoid** ``(y - y0)' P_y (y - y0) <= rho * c``. ``rho`` leaves room for the one agent
    step that can happen between two checks: from any state on the boundary ``V = rho c``,
    after one control period of the agent's worst-case action (the corners of the action
    box) the coach must still recover in MuJoCo — no termination within the horizon, and ``V``
    lower at its end than just after the kick. ``rho`` is the largest value that passes (bisection), then
    checked again with more samples. The linear bound ``sqrt(V+) <= alpha sqrt(V) + beta`` is
    reported too: for the pendulums a single full-force step moves the state further than the
    certified ellipsoid is wide, so no ``rho`` could come from it; the coach recovers from well
    outside the ellipsoid, and that is what the simulation checks.
(b) **box** on chosen variables: the largest centred box inside the ellipsoid projected on
    those variables, ``{y_S : y_S' ((P_y^-1)_SS)^-1 y_S <= rho c}``.

For Hopper and Walker2d (simulation method) the box comes from the recoverable set, scaled by
the largest factor (bisection) from whose boundary the coach still recovers after one
worst-case agent step.
"""

from __future__ import annotations

import datetime as _dt
import functools
import itertools
import math
from dataclasses import dataclass, field, replace
from typing import Any

import mujoco
import numpy as np
import scipy.linalg
from scipy.optimize import minimize

from pidlab import __version__
from pidlab.checks import instance, integer
from pidlab.checks import seed as check_seed
from pidlab.controller.pid import Coach
from pidlab.controller.spec import CoachSpec
from pidlab.errors import RegionError
from pidlab.linear.linearize import Linearization
from pidlab.parallel import resolve_workers
from pidlab.plant.model import LoadedModel
from pidlab.region.roa import (
    METHOD_SIMULATION,
    Lyapunov,
    RegionOfAttraction,
    check_variables,
    region_analysis,
    region_start,
    region_value,
)
from pidlab.region.shrink import geometric_bisect, shrink_until_clean
from pidlab.region.simulate import SimulationPool, Simulator, horizon_steps, sample_ellipsoid, tangent_index

BOX_SHRINK = 0.7
"""Simulation method: factor on the box scale after a failed final one-step check."""

RHO_SHRINK = 0.6
"""Lyapunov method: factor on ``rho`` after a failed final one-step check."""

MAX_VERTICES = 8
"""At most this many corners of the action box are tried as the agent's worst-case step."""

BOX_BISECTION_SAMPLES = 12
"""Simulation method: states on the box per bisection step of the one-step margin."""

RHO_BISECTION_SAMPLES = 20
"""Lyapunov method: states on the boundary ``V = rho c`` per bisection step of the one-step margin."""


@dataclass(frozen=True)
class CriticalBounds:
    """Bounds in observation variables, with provenance.

    Attributes
    ----------
    env_id, spec_name, method : str
    variables : tuple of str
        Ellipsoid variables (empty for the simulation method).
    center : ndarray, shape (k,)
    shape : ndarray, shape (k, k)
        ``P_y``.
    level : float
        Certified ``c``.
    rho : float
        Safety factor for one agent step: the coach takes over outside ``V <= rho c``.
    box : dict of str to (float, float)
        Absolute ``(low, high)`` per chosen variable.
    one_step_check : tuple of int
        (samples, escapes): states on the boundary, one random worst-case action in MuJoCo,
        how many left the certified set.
    provenance : dict
    """

    env_id: str
    spec_name: str
    method: str
    variables: tuple[str, ...]
    center: np.ndarray
    shape: np.ndarray
    level: float
    rho: float
    box: dict[str, tuple[float, float]]
    one_step_check: tuple[int, int]
    provenance: dict[str, Any] = field(default_factory=dict)

    def to_table(self) -> dict[str, Any]:
        """The spec's ``[bounds]`` table."""
        out: dict[str, Any] = {"method": self.method}
        if self.variables:
            out["ellipsoid"] = {
                "variables": list(self.variables),
                "center": [float(v) for v in self.center],
                "shape": [[float(v) for v in row] for row in self.shape],
                "level": float(self.level),
                "rho": float(self.rho),
            }
        if self.box:
            out["box"] = {k: [float(lo), float(hi)] for k, (lo, hi) in self.box.items()}
        out["provenance"] = dict(self.provenance)
        return out


def _largest_box(M: np.ndarray, r: float) -> np.ndarray:
    """Half-widths of the largest-volume centred box inside ``{y : y' M y <= r}``."""
    k = M.shape[0]
    if k == 1:
        return np.array([math.sqrt(r / M[0, 0])])
    corners = [np.array((1.0, *s)) for s in itertools.product((1.0, -1.0), repeat=k - 1)]
    start = np.log(np.sqrt(r / (k * np.diag(M))))

    def cons(z: np.ndarray) -> np.ndarray:
        h = np.exp(z)
        return np.array([r - (h * c) @ M @ (h * c) for c in corners])

    res = minimize(lambda z: -np.sum(z), start, constraints=[{"type": "ineq", "fun": cons}], method="SLSQP")
    h = np.exp(res.x if res.success else start)
    worst = max((h * c) @ M @ (h * c) for c in corners)
    return h * min(1.0, math.sqrt(r / worst))


@dataclass(frozen=True)
class _OneStep:
    """The one-step check's setting: the simulator, worst-case actions, horizon and random draws.

    Attributes
    ----------
    pool : SimulationPool
        Runs the simulations (its ``sim`` serves this process).
    vertices : ndarray, shape (n_vertices, nu)
        Worst-case action deviations from ``lin.op.ctrl`` (corners of the action box).
    steps : int
        Control periods the coach gets to recover.
    rng : numpy.random.Generator
        The one stream every draw of :func:`derive_bounds` comes from, in order.
    """

    pool: SimulationPool
    vertices: np.ndarray
    steps: int
    rng: np.random.Generator

    @property
    def sim(self) -> Simulator:
        """The simulator of this process."""
        return self.pool.sim


def derive_bounds(
    roa: RegionOfAttraction,
    spec: CoachSpec,
    loaded: LoadedModel,
    variables: list[str] | None = None,
    check_samples: int = 100,
    seed: int = 0,
    workers: int | None = None,
) -> CriticalBounds:
    """Turn a certified region into critical-state bounds.

    Parameters
    ----------
    roa : RegionOfAttraction
    spec : CoachSpec
    loaded : LoadedModel
    variables : list of str, optional
        Variables for the box. Default: the first loop's signal and its rate signal
        (the region's own variables for the simulation method).
    check_samples : int
        States on the ellipsoid's boundary checked against one worst-case agent step.
    seed : int
    workers : int, optional
        Worker processes for the simulations (default: the machine's cores, at most 4; 1: all
        in this process). The bounds are the same for any number of workers.

    Raises
    ------
    UnknownSignalError
        A variable is not in the observation (the message lists the valid names).
    RegionError
        ``variables`` empty or naming a variable twice; one worst-case agent step can leave the
        certified set from anywhere: no useful bound; or
        ``check_samples`` outside [1, 1e6], ``seed`` outside [0, 2**32 - 1] or ``workers`` outside
        [1, 256].
    """
    instance(roa, RegionOfAttraction, "roa")
    instance(spec, CoachSpec, "spec")
    instance(loaded, LoadedModel, "loaded")
    integer(check_samples, "check_samples", RegionError, low=1, high=10**6, param="check_samples")
    check_seed(seed, "seed", RegionError, param="seed")
    n_workers = resolve_workers(workers, RegionError)
    lp0 = spec.loops[0]
    if variables is None:
        variables = list(roa.box) if roa.box else [v for v in (lp0.signal, lp0.rate_signal) if v]
    check_variables(variables, loaded)
    coach = Coach(spec, loaded)
    drawn_as = "simulation" if roa.lyapunov is None else "lyapunov"
    lin = region_analysis(spec, loaded, coach, drawn_as).linearization
    vertices = _action_vertices(coach, lin)
    provenance = _region_provenance(roa)
    rng = np.random.default_rng(seed)
    if len(vertices) > MAX_VERTICES:
        vertices = vertices[rng.choice(len(vertices), MAX_VERTICES, replace=False)]
    with SimulationPool(spec, loaded, lin, n_workers) as pool:
        step = _OneStep(pool, vertices, horizon_steps(roa.check.horizon_s, loaded.control_dt), rng)
        if roa.method == METHOD_SIMULATION:
            return _box_bounds(roa, spec, step, check_samples, provenance)
        return _ellipsoid_bounds(roa, spec, lin, step, variables, check_samples, provenance)


def _action_vertices(coach: Coach, lin: Linearization) -> np.ndarray:
    """Corners of the action box as deviations from ``lin.op.ctrl``, shape ``(2**nu, nu)``.

    An unbounded actuator counts as ``[-1, 1]``.
    """
    lay = coach.layout
    du_lo = np.where(np.isfinite(lay.ctrl_low), lay.ctrl_low, -1.0) - lin.op.ctrl
    du_hi = np.where(np.isfinite(lay.ctrl_high), lay.ctrl_high, 1.0) - lin.op.ctrl
    return np.array(list(itertools.product(*zip(du_lo, du_hi, strict=True))))


def _region_provenance(roa: RegionOfAttraction) -> dict[str, Any]:
    """The region's part of the bounds' provenance."""
    provenance: dict[str, Any] = {
        "method": roa.method,
        "level_c": float(roa.level),
        "samples": int(roa.check.samples),
        "failures": int(roa.check.failures),
        "failure_probability_95": float(roa.check.failure_bound_95),
        "horizon_s": float(roa.check.horizon_s),
        "seed": int(roa.check.seed),
        "date": _dt.date.today().isoformat(),
        "pidlab_version": __version__,
    }
    if roa.c_optimization is not None:
        provenance["c_optimization"] = float(roa.c_optimization)
    if roa.lyapunov is not None and roa.lyapunov.tangent is not None:
        provenance["centre"] = "the posture the balance coach was designed at"
    return provenance


# --------------------------------------------------------------------------------------------
# Simulation method: the recoverable box, scaled for one agent step


def _box_points(roa: RegionOfAttraction, step: _OneStep, scale: float, n: int) -> list[np.ndarray]:
    """``n`` plant states on the scaled box: its corners first, then points on its faces."""
    m = step.sim.m
    keys = list(roa.box)
    addr = [tangent_index(m, v) for v in keys]
    rng = step.rng
    pts = [np.array(p) for p in itertools.product((1.0, -1.0), repeat=len(keys))]
    while len(pts) < n:  # points on the box's faces
        p = rng.uniform(-1, 1, len(keys))
        p[rng.integers(len(p))] = rng.choice((-1.0, 1.0))
        pts.append(p)
    out = []
    for p in pts[:n]:
        x = np.zeros(2 * m.nv)
        for a, key, pv in zip(addr, keys, p, strict=True):
            x[a] = pv * roa.box[key] * scale
        out.append(x)
    return out


def _box_escapes(roa: RegionOfAttraction, step: _OneStep, scale: float, n: int, acts: np.ndarray) -> int:
    """Failed recoveries after one step of ``acts`` from ``n`` states on the box scaled by ``scale``."""
    return _escapes(step, _box_points(roa, step, scale, n), acts, None, 0.0)


def _box_margin(roa: RegionOfAttraction, step: _OneStep) -> tuple[float, float]:
    """``(kappa, fraction)``: the largest box scale clean after one step of ``fraction`` of the action range.

    ``fraction`` is 1 unless one full-range step from the standing pose is already
    unrecoverable: then it is half the largest recoverable fraction (0 if none).
    """
    n = BOX_BISECTION_SAMPLES
    vertices = step.vertices
    fraction = 1.0
    kappa = geometric_bisect(lambda k: _box_escapes(roa, step, k, n, vertices) == 0)
    if kappa == 0.0:
        zero = np.zeros(2 * step.sim.m.nv)
        fraction = 0.5 * geometric_bisect(lambda f: _escapes(step, [zero], f * vertices, None, 0.0) == 0)
        if fraction > 0.0:
            kappa = geometric_bisect(lambda k: _box_escapes(roa, step, k, n, fraction * vertices) == 0)
    return kappa, fraction


def _box_bounds(
    roa: RegionOfAttraction, spec: CoachSpec, step: _OneStep, check_samples: int, provenance: dict[str, Any]
) -> CriticalBounds:
    """Bounds for the simulation method: the recoverable box scaled for one worst-case agent step."""
    kappa, fraction = _box_margin(roa, step)
    if kappa == 0.0:
        raise RegionError(
            "no useful bound: one agent step from the smallest box tried already leads to a fall"
        )
    n_check = max(check_samples // 10, 4)
    final = shrink_until_clean(
        lambda k: _box_escapes(roa, step, k, n_check, fraction * step.vertices),
        lambda escapes: escapes == 0,
        kappa,
        BOX_SHRINK,
    )
    if final is None:
        raise RegionError(f"no useful bound for {spec.name}: one-step falls persist as the box shrinks")
    kappa, escapes = final.value, final.outcome
    names = step.sim.card.observation_names
    box = {}
    for var in roa.box:
        center = float(step.sim.y_op[names.index(var)])
        box[var] = (center - kappa * roa.box[var], center + kappa * roa.box[var])
    provenance = {
        **provenance,
        "rho": float(kappa),
        "one_step_samples": int(n_check),
        "one_step_escapes": int(escapes),
        "one_step_action_fraction": float(fraction),
        "one_step_margin": "recoverable box scaled so the coach recovers after one worst-case step",
    }
    return CriticalBounds(
        spec.env_id,
        spec.name,
        roa.method,
        (),
        np.zeros(0),
        np.zeros((0, 0)),
        roa.level,
        kappa,
        box,
        (n_check, escapes),
        provenance,
    )


# --------------------------------------------------------------------------------------------
# Lyapunov method: the ellipsoid V <= rho c and a box inside it


def _linear_one_step(
    lin: Linearization, lyap: Lyapunov, names: tuple[str, ...], vertices: np.ndarray
) -> tuple[float, float]:
    """``(alpha, beta)`` of the linear bound ``sqrt(V+) <= alpha sqrt(V) + beta`` for one agent step."""
    C = np.asarray(lin.sysd.C)
    sel = np.array([names.index(v) for v in lyap.variables])
    # the states the variables see (all of them, unless the observation leaves one out that no
    # other state depends on: Walker2d's forward position)
    seen = np.flatnonzero(np.any(C[sel] != 0.0, axis=0))
    P_x = C[np.ix_(sel, seen)].T @ lyap.P_y @ C[np.ix_(sel, seen)]
    root = np.real(scipy.linalg.sqrtm(P_x))
    Ad, Bd = lin.Ad[np.ix_(seen, seen)], lin.Bd[seen]
    alpha = float(np.linalg.norm(root @ Ad @ np.linalg.inv(root), 2))
    beta = float(max(np.linalg.norm(root @ Bd @ v) for v in vertices))
    return alpha, beta


def _ellipsoid_escapes(lyap: Lyapunov, c: float, step: _OneStep, r: float, n: int, acts: np.ndarray) -> int:
    """Failed recoveries after one step of ``acts`` from ``n`` random states on ``V = r c``."""
    pts = sample_ellipsoid(lyap.P_y, r * c, n, step.rng)
    boundary = pts / np.sqrt(np.einsum("ij,jk,ik->i", pts, lyap.P_y, pts) / (r * c))[:, None]
    return _escapes(step, list(boundary), acts, lyap, c)


def _rho_margin(lyap: Lyapunov, c: float, step: _OneStep, name: str) -> tuple[float, float]:
    """``(rho, fraction)``: the largest ``rho`` clean after one step of ``fraction`` of the action range.

    ``fraction`` is 1 unless a full-range step from (near) the equilibrium is already
    unrecoverable: then it is half the largest recoverable fraction, and the margin is sized for it.
    """
    n = RHO_BISECTION_SAMPLES
    vertices = step.vertices
    rho = geometric_bisect(lambda r: _ellipsoid_escapes(lyap, c, step, r, n, vertices) == 0)
    if rho > 0.0:
        return rho, 1.0
    fraction = 0.5 * geometric_bisect(lambda f: _ellipsoid_escapes(lyap, c, step, 1e-4, 4, f * vertices) == 0)
    if fraction == 0.0:
        raise RegionError(
            f"no useful bound: from the smallest ellipsoid tried (c = {c:.3g}), one agent step of even "
            "a small fraction of the action range takes the state where the coach cannot recover"
        )
    rho = geometric_bisect(lambda r: _ellipsoid_escapes(lyap, c, step, r, n, fraction * vertices) == 0)
    if rho == 0.0:
        raise RegionError(f"no useful bound for {name}: the one-step margin leaves nothing (c = {c:.3g})")
    return rho, fraction


def _box_in_ellipsoid(lyap: Lyapunov, variables: list[str], level: float) -> dict[str, tuple[float, float]]:
    """Absolute ``(low, high)`` per variable: the largest centred box in the projected ``{V <= level}``."""
    for v in variables:
        if v not in lyap.variables:
            raise RegionError(f"{v!r} is not one of the region's variables ({', '.join(lyap.variables)})")
    idx = [lyap.variables.index(v) for v in variables]
    M = np.linalg.inv(np.linalg.inv(lyap.P_y)[np.ix_(idx, idx)])
    halves = _largest_box(M, level)
    return {
        v: (float(lyap.center[i] - h), float(lyap.center[i] + h))
        for v, i, h in zip(variables, idx, halves, strict=True)
    }


def _ellipsoid_bounds(
    roa: RegionOfAttraction,
    spec: CoachSpec,
    lin: Linearization,
    step: _OneStep,
    variables: list[str],
    check_samples: int,
    provenance: dict[str, Any],
) -> CriticalBounds:
    """Bounds for the Lyapunov method: the ellipsoid ``V <= rho c`` and a box inside it."""
    lyap = roa.lyapunov
    if lyap is None:
        raise RegionError(
            f"roa={roa.spec_name!r}: a {roa.method!r} region carries no Lyapunov function", param="roa"
        )
    alpha, beta = _linear_one_step(lin, lyap, step.sim.card.observation_names, step.vertices)
    c = roa.level
    rho, fraction = _rho_margin(lyap, c, step, spec.name)
    final = shrink_until_clean(  # the final, larger check must pass too
        lambda r: _ellipsoid_escapes(lyap, c, step, r, check_samples, fraction * step.vertices),
        lambda escapes: escapes == 0,
        rho,
        RHO_SHRINK,
    )
    if final is None:
        raise RegionError(f"no useful bound for {spec.name}: one-step escapes persist as rho shrinks")
    rho, escapes = final.value, final.outcome
    box = _box_in_ellipsoid(lyap, variables, rho * c)
    provenance = {
        **provenance,
        "rho": float(rho),
        "linear_one_step_alpha": alpha,
        "linear_one_step_beta": beta,
        "one_step_samples": int(check_samples),
        "one_step_escapes": int(escapes),
        "one_step_action_fraction": float(fraction),
    }
    return CriticalBounds(
        spec.env_id,
        spec.name,
        roa.method,
        lyap.variables,
        lyap.center,
        lyap.P_y,
        c,
        rho,
        box,
        (check_samples, escapes),
        provenance,
    )


def _escapes(
    step: _OneStep, states: list[np.ndarray], vertices: np.ndarray, lyap: Lyapunov | None, c: float
) -> int:
    """Failed recoveries after one worst-case action (each of ``vertices``) from each of ``states``.

    The simulations stop at the first failure: a nonzero count is then only a lower bound (only
    whether it is zero is reproducible).
    """
    items = [(x, v) for x in states for v in vertices]
    task = functools.partial(_kicked_recovery, steps=step.steps, lyap=lyap)
    return sum(step.pool.run(task, items, stop=bool).results)


def _kicked_recovery(
    sim: Simulator, item: tuple[np.ndarray, np.ndarray], steps: int, lyap: Lyapunov | None
) -> int:
    """1 if the coach cannot recover from a state after one agent action ``v``, else 0.

    ``item = (state, v)``, ``v`` a deviation from the operating point's control; ``state`` is a
    tangent deviation ``x_plant`` (no ``lyap``) or an observation deviation from ``lyap``'s centre
    (:func:`~pidlab.region.roa.region_start`). A recovery fails when the env would terminate
    right after the action or within ``steps``, or (with ``lyap``) when ``V`` at the end is not
    below ``V`` just after the action. A task of :meth:`~pidlab.parallel.WorkerPool.run`.
    """
    state, v = item
    if lyap is None:
        sim.start(state)
    else:
        region_start(sim, lyap, state)
    sim.d.ctrl[:] = sim.lin.op.ctrl + v
    mujoco.mj_step(sim.m, sim.d, nstep=sim.loaded.frame_skip)
    obs = sim.observe()
    if sim.terminated(obs):
        return 1
    sim.coach.reset(obs)
    v_kicked = 0.0 if lyap is None else region_value(sim, lyap, obs)
    term, _ = sim.run(obs, steps)
    if term:
        return 1
    if lyap is not None:
        return int(region_value(sim, lyap, sim.observe()) >= v_kicked)
    return 0


BOUNDS_KEYS = ("method", "ellipsoid", "box", "provenance")
"""The keys of a spec's ``[bounds]`` table that :func:`with_bounds` owns (``rescue`` and
``takeover`` are :func:`pidlab.region.rescue.with_rescue`'s)."""


def with_bounds(spec: CoachSpec, bounds: CriticalBounds) -> CoachSpec:
    """A copy of ``spec`` carrying ``bounds`` in its ``[bounds]`` table.

    Every key the bounds do not own is kept: the rescue region and the ``takeover`` choice stay
    (a ``takeover`` that named a region the new bounds no longer have falls back to the default).
    """
    instance(spec, CoachSpec, "spec")
    instance(bounds, CriticalBounds, "bounds")
    kept = {k: v for k, v in (spec.bounds or {}).items() if k not in BOUNDS_KEYS}
    table = {**bounds.to_table(), **kept}
    if table.get("takeover") in ("box", "ellipsoid") and table["takeover"] not in table:
        del table["takeover"]
    return replace(spec, bounds=table)
