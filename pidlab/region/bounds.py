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
import itertools
import math
from dataclasses import dataclass, field, replace
from typing import Any

import mujoco
import numpy as np
import scipy.linalg
from scipy.optimize import minimize

from pidlab import __version__
from pidlab.controller.spec import CoachSpec
from pidlab.plant.model import LoadedModel
from pidlab.region.roa import (
    METHOD_SIMULATION,
    RegionError,
    RegionOfAttraction,
    _sample_ellipsoid,
    _Simulator,
    geometric_bisect,
)


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


def check_variables(names: list[str], loaded: LoadedModel) -> None:
    """Raise :class:`~pidlab.errors.UnknownSignalError` (listing the valid names) for an unknown name."""
    card = loaded.require_card()
    for n in names:
        card.variable(n)


def derive_bounds(
    roa: RegionOfAttraction,
    spec: CoachSpec,
    loaded: LoadedModel,
    variables: list[str] | None = None,
    check_samples: int = 100,
    seed: int = 0,
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

    Raises
    ------
    UnknownSignalError
        A variable is not in the observation (the message lists the valid names).
    RegionError
        One worst-case agent step can leave the certified set from anywhere: no useful bound.
    """
    card = loaded.require_card()
    lp0 = spec.loops[0]
    if variables is None:
        variables = list(roa.box) if roa.box else [v for v in (lp0.signal, lp0.rate_signal) if v]
    check_variables(variables, loaded)
    from pidlab.controller.analysis import analyze_coach
    from pidlab.controller.pid import Coach

    coach = Coach(spec, loaded)
    lin = analyze_coach(coach, loaded).linearization
    sim = _Simulator(spec, loaded, lin)
    lay = coach.layout
    du_lo = np.where(np.isfinite(lay.ctrl_low), lay.ctrl_low, -1.0) - lin.op.ctrl
    du_hi = np.where(np.isfinite(lay.ctrl_high), lay.ctrl_high, 1.0) - lin.op.ctrl
    vertices = np.array(list(itertools.product(*zip(du_lo, du_hi, strict=True))))
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
    steps = max(1, round(roa.check.horizon_s / loaded.control_dt))
    rng = np.random.default_rng(seed)
    if len(vertices) > 8:
        vertices = vertices[rng.choice(len(vertices), 8, replace=False)]
    names = card.observation_names
    if roa.method == METHOD_SIMULATION:
        m = loaded.model
        keys = list(roa.box)
        addr = []
        for v in keys:
            jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, v.rsplit("_", 1)[0])
            addr.append(int(m.jnt_dofadr[jid]) + (m.nv if v.endswith("_vel") else 0))

        def box_points(scale: float, n: int) -> list[np.ndarray]:
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

        def box_escapes(scale: float, n: int, acts: np.ndarray) -> int:
            return sum(_escapes(sim, x, acts, steps, None, 0.0) for x in box_points(scale, n))

        fraction = 1.0
        kappa = geometric_bisect(lambda k: box_escapes(k, 12, vertices) == 0)
        if kappa == 0.0:
            # one full-range step from the standing pose is already unrecoverable: size the margin
            # for the largest recoverable fraction of the action range, halved, and say so
            zero = np.zeros(2 * m.nv)
            fraction = 0.5 * geometric_bisect(
                lambda f: _escapes(sim, zero, f * vertices, steps, None, 0.0) == 0
            )
            if fraction > 0.0:
                kappa = geometric_bisect(lambda k: box_escapes(k, 12, fraction * vertices) == 0)
        if kappa == 0.0:
            raise RegionError(
                "no useful bound: one agent step from the smallest box tried already leads to a fall"
            )
        n_check = max(check_samples // 10, 4)
        escapes = box_escapes(kappa, n_check, fraction * vertices)
        for _ in range(6):
            if escapes == 0:
                break
            kappa *= 0.7
            escapes = box_escapes(kappa, n_check, fraction * vertices)
        else:
            raise RegionError(f"no useful bound for {spec.name}: one-step falls persist as the box shrinks")
        box = {}
        for var in keys:
            center = float(sim.y_op[names.index(var)])
            box[var] = (center - kappa * roa.box[var], center + kappa * roa.box[var])
        provenance.update(
            {
                "rho": float(kappa),
                "one_step_samples": int(n_check),
                "one_step_escapes": int(escapes),
                "one_step_action_fraction": float(fraction),
                "one_step_margin": "recoverable box scaled so the coach recovers after one worst-case step",
            }
        )
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
    lyap = roa.lyapunov
    assert lyap is not None
    C = np.asarray(lin.sysd.C)
    sel = [names.index(v) for v in lyap.variables]
    P_x = C[sel].T @ lyap.P_y @ C[sel]
    root = np.real(scipy.linalg.sqrtm(P_x))
    alpha = float(np.linalg.norm(root @ lin.Ad @ np.linalg.inv(root), 2))
    beta = float(max(np.linalg.norm(root @ lin.Bd @ v) for v in vertices))
    c = roa.level
    plant_n = lin.sysd.nstates

    def boundary(r: float, n: int) -> np.ndarray:
        pts = _sample_ellipsoid(lyap.P_y, r * c, n, rng)
        return pts / np.sqrt(np.einsum("ij,jk,ik->i", pts, lyap.P_y, pts) / (r * c))[:, None]

    def escapes_at(r: float, n: int, acts: np.ndarray) -> int:
        return sum(_escapes(sim, (lyap.to_state @ y)[:plant_n], acts, steps, lyap, c) for y in boundary(r, n))

    rho = geometric_bisect(lambda r: escapes_at(r, 20, vertices) == 0)
    fraction = 1.0
    if rho == 0.0:
        # not even a worst-case step from (near) the equilibrium is recoverable: find the largest
        # fraction of the action range that is, and size the margin for that, saying so
        fraction = 0.5 * geometric_bisect(lambda f: escapes_at(1e-4, 4, f * vertices) == 0)
        if fraction == 0.0:
            raise RegionError(
                f"no useful bound: from the smallest ellipsoid tried (c = {c:.3g}), one agent step of even "
                "a small fraction of the action range takes the state where the coach cannot recover"
            )
        rho = geometric_bisect(lambda r: escapes_at(r, 20, fraction * vertices) == 0)
        if rho == 0.0:
            raise RegionError(
                f"no useful bound for {spec.name}: the one-step margin leaves nothing (c = {c:.3g})"
            )
    escapes = escapes_at(rho, check_samples, fraction * vertices)
    for _ in range(6):  # the final, larger check must pass too
        if escapes == 0:
            break
        rho *= 0.6
        escapes = escapes_at(rho, check_samples, fraction * vertices)
    else:
        raise RegionError(f"no useful bound for {spec.name}: one-step escapes persist as rho shrinks")
    # box on the chosen variables, inside the projected ellipsoid
    for v in variables:
        if v not in lyap.variables:
            raise RegionError(f"{v!r} is not one of the region's variables ({', '.join(lyap.variables)})")
    idx = [lyap.variables.index(v) for v in variables]
    M = np.linalg.inv(np.linalg.inv(lyap.P_y)[np.ix_(idx, idx)])
    halves = _largest_box(M, rho * c)
    box = {
        v: (float(lyap.center[i] - h), float(lyap.center[i] + h))
        for v, i, h in zip(variables, idx, halves, strict=True)
    }
    provenance.update(
        {
            "rho": float(rho),
            "linear_one_step_alpha": alpha,
            "linear_one_step_beta": beta,
            "one_step_samples": int(check_samples),
            "one_step_escapes": int(escapes),
            "one_step_action_fraction": float(fraction),
        }
    )
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
    sim: _Simulator, x_plant: np.ndarray, vertices: np.ndarray, steps: int, lyap: Any, c: float
) -> int:
    """How many worst-case actions (``vertices``) leave the coach unable to recover from ``x_plant``."""
    failures = 0
    for v in vertices:
        sim.start(x_plant)
        sim.d.ctrl[:] = sim.lin.op.ctrl + v
        mujoco.mj_step(sim.m, sim.d, nstep=sim.loaded.frame_skip)
        if sim.fast.terminated(sim.d):
            failures += 1
            continue
        obs = sim.fast.observe(sim.d)
        sim.coach.reset(obs)
        v_kicked = 0.0
        if lyap is not None:
            X = np.concatenate([sim.plant_state(), sim.coach_deviation()])
            v_kicked = float(X @ lyap.P @ X)
        term, _ = sim.run(obs, steps)
        if term:
            failures += 1
        elif lyap is not None:
            X = np.concatenate([sim.plant_state(), sim.coach_deviation()])
            failures += int(float(X @ lyap.P @ X) >= v_kicked)
    return failures


def with_bounds(spec: CoachSpec, bounds: CriticalBounds) -> CoachSpec:
    """A copy of ``spec`` carrying ``bounds`` in its ``[bounds]`` table."""
    return replace(spec, bounds=bounds.to_table())
