"""Linearize a MuJoCo model about an operating point.

Continuous time
    ``x = (dq, qvel, act)`` with ``dq`` in the tangent space of the configuration
    (``2*nv + na`` states, quaternion-safe: ``qpos = qpos0 (+) dq`` through
    ``mj_integratePos``), ``u = ctrl``. The vector field
    ``f(x, u) = (qvel, qacc, act_dot)`` is differentiated by finite differences of
    ``mj_forward``, so the result does not depend on the model's integrator (the four paper
    envs use RK4, for which ``mujoco.mjd_transitionFD`` refuses).

Discrete time
    At the env's control period ``timestep * frame_skip`` (what the agent experiences). By
    default the map ``x_k -> x_{k+1}`` of ``frame_skip`` calls of ``mj_step`` with the control
    held is differentiated (``discretization="step"``: integrator included); alternatively the
    continuous model is sampled with a zero-order hold (``"zoh"``).

Both are returned as python-control ``StateSpace`` objects with named states, inputs and
outputs. With a model card the outputs are the Gymnasium observation variables (``C`` and
``D`` are the observation's Jacobian); without one they are the states.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import control as ct
import mujoco
import numpy as np

from pidlab.checks import instance
from pidlab.errors import LinearizationError, NonFiniteJacobianError
from pidlab.plant.model import LoadedModel
from pidlab.plant.observation import observe
from pidlab.plant.operating_point import OperatingPoint, resolve_operating_point

Discretization = Literal["step", "zoh"]


@dataclass(frozen=True)
class Linearization:
    """A linearized MuJoCo model and how it was obtained.

    Attributes
    ----------
    sys : control.StateSpace
        Continuous-time model; ``A`` shape ``(n, n)`` with ``n = 2*nv + na``, ``B`` shape
        ``(n, nu)``. States ``<joint>_pos``/``<joint>_vel`` (and ``<actuator>_act``),
        inputs are actuator names, outputs observation variables (or the states).
    sysd : control.StateSpace
        Discrete-time model at ``control_dt``.
    op : OperatingPoint
        The point linearized about.
    eps : float
        Finite-difference step (tangent coordinates, velocities, controls).
    centered : bool
        Centered (second-order) rather than forward differences.
    method : str
        How ``A``, ``B`` were computed.
    discretization : {"step", "zoh"}
        How ``sysd`` was obtained.
    source : str
        Env id or MJCF path.
    timestep, control_dt : float
        Physics step and control period, seconds.
    frame_skip : int
    integrator : str
        The model's integrator (it affects ``sysd`` with ``"step"`` only).
    xdot0 : ndarray, shape (n,)
        ``f(x0, u0)``: zero at an equilibrium. Its norm says how far the point is from one.
    ncon, nefc : int
        Contacts and active constraint rows at the operating point. Where these are
        non-zero the dynamics are only piecewise smooth and the model holds while the
        active set does not change.
    kink : float
        ``|J_forward - J_backward| / |J|`` of the one-sided differences of ``[A, B]``
        (centered mode only). Near ``eps`` for smooth dynamics; of order 1 where the
        dynamics have a kink at the operating point (Hopper and Walker2d standing: the
        friction cones switch facets at zero slip), and the centered ``A`` is then the
        average of the two one-sided slopes.
    """

    sys: ct.StateSpace
    sysd: ct.StateSpace
    op: OperatingPoint
    eps: float
    centered: bool
    method: str
    discretization: str
    source: str
    timestep: float
    control_dt: float
    frame_skip: int
    integrator: str
    xdot0: np.ndarray
    ncon: int
    nefc: int
    kink: float

    @property
    def A(self) -> np.ndarray:
        """Continuous state matrix, shape ``(n, n)``."""
        return np.asarray(self.sys.A)

    @property
    def B(self) -> np.ndarray:
        """Continuous input matrix, shape ``(n, nu)``."""
        return np.asarray(self.sys.B)

    @property
    def C(self) -> np.ndarray:
        """Output matrix, shape ``(p, n)``."""
        return np.asarray(self.sys.C)

    @property
    def D(self) -> np.ndarray:
        """Feedthrough matrix, shape ``(p, nu)``."""
        return np.asarray(self.sys.D)

    @property
    def Ad(self) -> np.ndarray:
        """Discrete state matrix at ``control_dt``, shape ``(n, n)``."""
        return np.asarray(self.sysd.A)

    @property
    def Bd(self) -> np.ndarray:
        """Discrete input matrix at ``control_dt``, shape ``(n, nu)``."""
        return np.asarray(self.sysd.B)

    @property
    def state_names(self) -> tuple[str, ...]:
        """State names, in order."""
        return tuple(self.sys.state_labels)

    @property
    def input_names(self) -> tuple[str, ...]:
        """Input (actuator) names, in order."""
        return tuple(self.sys.input_labels)

    @property
    def output_names(self) -> tuple[str, ...]:
        """Output names, in order."""
        return tuple(self.sys.output_labels)

    @property
    def equilibrium_error(self) -> float:
        """``max |xdot0|``: how far the operating point is from an equilibrium."""
        return float(np.max(np.abs(self.xdot0))) if self.xdot0.size else 0.0


class _Evaluator:
    """Evaluates the vector field, one control period of stepping, and the observation."""

    def __init__(self, loaded: LoadedModel, op: OperatingPoint) -> None:
        self.loaded = loaded
        self.m = loaded.model
        self.d = mujoco.MjData(self.m)
        self.op = op
        self.nv, self.na, self.nu = self.m.nv, self.m.na, self.m.nu
        self._set(np.zeros(self.n), np.zeros(self.nu))
        mujoco.mj_forward(self.m, self.d)
        # Converge the constraint solver's warm start at the nominal point, then reuse it for
        # every perturbed evaluation so that all of them start the solver identically.
        for _ in range(3):
            self.d.qacc_warmstart[:] = self.d.qacc
            mujoco.mj_forward(self.m, self.d)
        self.warmstart = self.d.qacc.copy()
        self.ncon = int(self.d.ncon)
        self.nefc = int(self.d.nefc)

    @property
    def n(self) -> int:
        return 2 * self.nv + self.na

    def _set(self, x: np.ndarray, u: np.ndarray) -> None:
        m, d, nv = self.m, self.d, self.nv
        qpos = self.op.qpos.copy()
        mujoco.mj_integratePos(m, qpos, x[:nv], 1.0)
        d.qpos[:] = qpos
        d.qvel[:] = self.op.qvel + x[nv : 2 * nv]
        if self.na:
            d.act[:] = self.op.act + x[2 * nv :]
        d.ctrl[:] = self.op.ctrl + u
        d.time = 0.0
        if hasattr(self, "warmstart"):
            d.qacc_warmstart[:] = self.warmstart

    def vector_field(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``f(x, u) = (qvel, qacc, act_dot)`` at the perturbed state, shape ``(n,)``."""
        self._set(x, u)
        mujoco.mj_forward(self.m, self.d)
        parts = [self.d.qvel.copy(), self.d.qacc.copy()]
        if self.na:
            parts.append(self.d.act_dot.copy())
        return np.concatenate(parts)

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Tangent-space state after one control period, relative to the operating point."""
        self._set(x, u)
        mujoco.mj_step(self.m, self.d, nstep=self.loaded.frame_skip)
        dq = np.zeros(self.nv)
        mujoco.mj_differentiatePos(self.m, dq, 1.0, self.op.qpos, self.d.qpos)
        parts = [dq, self.d.qvel - self.op.qvel]
        if self.na:
            parts.append(self.d.act - self.op.act)
        return np.concatenate(parts)

    def observation(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Observation (card) or full state at the perturbed point."""
        if self.loaded.card is None:
            return x.copy()
        self._set(x, u)
        mujoco.mj_forward(self.m, self.d)
        return observe(self.loaded.card, self.m, self.d)


def _ctrl_steps(loaded: LoadedModel, op: OperatingPoint, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-actuator (minus, plus) perturbations that stay inside ``ctrlrange``.

    A control sitting on its limit would be clamped by MuJoCo on one side and halve the
    centered difference, so the step is taken on the inner side only.
    """
    m = loaded.model
    lo = np.full(m.nu, -eps)
    hi = np.full(m.nu, eps)
    for i in range(m.nu):
        if m.actuator_ctrllimited[i]:
            cmin, cmax = m.actuator_ctrlrange[i]
            if op.ctrl[i] + eps > cmax:
                hi[i] = 0.0
            if op.ctrl[i] - eps < cmin:
                lo[i] = 0.0
    return lo, hi


def _fd_jacobian(
    fun: Callable[[np.ndarray, np.ndarray], np.ndarray],
    n: int,
    nu: int,
    eps: float,
    centered: bool,
    ctrl_lo: np.ndarray,
    ctrl_hi: np.ndarray,
    names: tuple[str, ...],
    what: str,
    tick: Callable[[], None] = lambda: None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Finite-difference Jacobians of ``fun(x, u)`` at ``(0, 0)`` in ``x`` and ``u``.

    Returns the Jacobians in ``x`` and ``u``, ``fun(0, 0)``, and the kink measure: the
    relative mismatch ``|J_forward - J_backward| / |J|`` of the one-sided differences
    (0 where the function is smooth; large where it has a kink, e.g. at a contact).
    ``tick()`` is called after each column.
    """
    zero_x, zero_u = np.zeros(n), np.zeros(nu)
    f0 = fun(zero_x, zero_u)
    cols = []
    one_sided_gap = []
    for k in range(n + nu):
        if k < n:
            lo, hi = -eps if centered else 0.0, eps
        else:
            lo = float(ctrl_lo[k - n]) if centered else 0.0
            hi = float(ctrl_hi[k - n])
            if hi == 0.0 and lo == 0.0:
                lo = float(ctrl_lo[k - n])
        dx_hi, du_hi = zero_x.copy(), zero_u.copy()
        dx_lo, du_lo = zero_x.copy(), zero_u.copy()
        if k < n:
            dx_hi[k], dx_lo[k] = hi, lo
        else:
            du_hi[k - n], du_lo[k - n] = hi, lo
        f_hi = fun(dx_hi, du_hi) if hi != 0.0 else f0
        f_lo = fun(dx_lo, du_lo) if lo != 0.0 else f0
        with np.errstate(invalid="ignore", over="ignore"):
            col = (f_hi - f_lo) / (hi - lo)
        if not np.all(np.isfinite(col)):
            raise NonFiniteJacobianError(
                f"{what}: the derivative with respect to {names[k]!r} is not finite "
                f"(NaN or inf); the dynamics are not differentiable at this operating point "
                f"- check it (qpos, qvel, ctrl) and the model's parameters"
            )
        if hi != 0.0 and lo != 0.0:
            one_sided_gap.append((f_hi - f0) / hi - (f0 - f_lo) / -lo)
        cols.append(col)
        tick()
    jac = np.column_stack(cols) if cols else np.zeros((f0.size, 0))
    scale = float(np.linalg.norm(jac))
    gap = float(np.linalg.norm(np.column_stack(one_sided_gap))) if one_sided_gap else 0.0
    kink = gap / scale if scale > 0 and centered else 0.0
    return jac[:, :n], jac[:, n:], f0, kink


def linearize(
    loaded: LoadedModel,
    op: OperatingPoint | None = None,
    *,
    eps: float = 1e-6,
    centered: bool = True,
    discretization: Discretization = "step",
    progress: Callable[[int, int], None] | None = None,
) -> Linearization:
    """Linearize ``loaded`` about ``op`` in continuous and discrete time.

    Parameters
    ----------
    loaded : LoadedModel
        From :func:`pidlab.plant.model.load_model`.
    op : OperatingPoint, optional
        Default: :func:`pidlab.plant.operating_point.resolve_operating_point` with its defaults
        (the model card's point, else ``qpos0`` with zero control).
    eps : float, default 1e-6
        Finite-difference step.
    centered : bool, default True
        Centered differences (error O(eps^2)) rather than forward (O(eps)).
    discretization : {"step", "zoh"}, default "step"
        ``"step"``: differentiate ``frame_skip`` MuJoCo steps (the model's own integrator,
        exactly what the agent experiences). ``"zoh"``: sample the continuous model with a
        zero-order hold.
    progress : callable, optional
        ``progress(done, total)`` after each finite-difference column (of
        :func:`finite_difference_columns`).

    Returns
    -------
    Linearization

    Raises
    ------
    NonFiniteJacobianError
        A derivative came out NaN or inf.
    LinearizationError
        ``eps`` is not positive and finite, ``discretization`` is unknown, or the model has no
        state (no degrees of freedom, no activations).
    """
    instance(loaded, LoadedModel, "loaded")
    check_arguments(eps, discretization)
    check_has_state(loaded)
    if op is None:
        op = resolve_operating_point(loaded)
    instance(op, OperatingPoint, "op")
    ev = _Evaluator(loaded, op)
    lo, hi = _ctrl_steps(loaded, op, eps)
    jacobians = functools.partial(
        _fd_jacobian, n=ev.n, nu=ev.nu, eps=eps, centered=centered, ctrl_lo=lo, ctrl_hi=hi,
        names=loaded.state_names + loaded.input_names, tick=_counter(progress, loaded, discretization),
    )  # fmt: skip
    sys, sysd, xdot0, kink = _systems(loaded, ev, jacobians, discretization)
    return Linearization(
        sys=sys,
        sysd=sysd,
        op=op,
        eps=eps,
        centered=centered,
        method=(
            f"{'centered' if centered else 'forward'} finite differences of mj_forward "
            f"(qacc) in tangent space, eps={eps:g}"
        ),
        discretization=discretization,
        source=loaded.source,
        timestep=loaded.timestep,
        control_dt=loaded.control_dt,
        frame_skip=loaded.frame_skip,
        integrator=loaded.integrator,
        xdot0=xdot0,
        ncon=ev.ncon,
        nefc=ev.nefc,
        kink=kink,
    )


def check_arguments(eps: object, discretization: object) -> None:
    """Check :func:`linearize`'s ``eps`` and ``discretization`` (the CLI checks them before loading).

    Raises
    ------
    LinearizationError
        ``eps`` is not a positive finite number, or ``discretization`` is not "step" or "zoh".
    """
    if not (isinstance(eps, (int, float)) and not isinstance(eps, bool) and 0 < eps < math.inf):
        raise LinearizationError(
            f"eps={eps!r}: expected a positive step (finite differences), e.g. 1e-6", param="eps"
        )
    if discretization not in ("step", "zoh"):
        raise LinearizationError(
            f"discretization={discretization!r}: expected 'step' or 'zoh'", param="discretization"
        )


def check_has_state(loaded: LoadedModel) -> None:
    """Refuse a model without state: no degrees of freedom (``nv = 0``) and no activations.

    Raises
    ------
    LinearizationError
        There is nothing to linearize.
    """
    m = loaded.model
    if 2 * m.nv + m.na == 0:
        raise LinearizationError(
            f"{loaded.source}: the model has no degrees of freedom (no joints, nv = 0) and no "
            "actuator activations: nothing to linearize; give the bodies joints"
        )


def finite_difference_columns(loaded: LoadedModel, discretization: str = "step") -> int:
    """How many finite-difference columns :func:`linearize` computes (its ``progress`` total).

    One per state and control for the vector field, the observation (with a model card) and,
    with ``discretization="step"``, the control-period map.
    """
    m = loaded.model
    passes = 1 + (loaded.card is not None) + (discretization == "step")
    return passes * (2 * m.nv + m.na + m.nu)


def _counter(
    progress: Callable[[int, int], None] | None, loaded: LoadedModel, discretization: str
) -> Callable[[], None]:
    """A ``tick()`` that reports each finite-difference column to ``progress(done, total)``."""
    if progress is None:
        return lambda: None
    total = finite_difference_columns(loaded, discretization)
    done = [0]

    def tick() -> None:
        done[0] += 1
        progress(min(done[0], total), total)

    return tick


def _best_time(work: Callable[[], Any], repeats: int = 3) -> float:
    """The shortest of ``repeats`` timings of ``work()``, seconds (a busy machine's hiccups ignored)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        work()
        times.append(time.perf_counter() - start)
    return min(times)


def estimate_seconds(loaded: LoadedModel, discretization: str = "step", analysis: bool = True) -> float:
    """A rough wall time of :func:`linearize` (and of the modal analysis ``pidlab linearize`` adds).

    Times ``mj_forward`` and one control period of ``mj_step``; with ``analysis``, also one
    singular value decomposition of each size the PBH tests of
    :func:`pidlab.linear.lti.analyze_lti` make (controllability and observability, for every
    mode of the continuous and the discrete model). Takes a fraction of a second below a few
    hundred states.
    """
    m = loaded.model
    d = mujoco.MjData(m)
    n = 2 * m.nv + m.na
    columns = 2 * (n + m.nu)  # centered differences
    total = columns * _best_time(lambda: mujoco.mj_forward(m, d)) * (1 + (loaded.card is not None))
    if discretization == "step":
        total += columns * _best_time(lambda: mujoco.mj_step(m, d, nstep=loaded.frame_skip))
    if analysis and n:
        outputs = len(loaded.card.observation_names) if loaded.card is not None else n
        rng = np.random.default_rng(0)
        for shape in ((n, n + m.nu), (n + outputs, n)):  # the PBH tests' matrices
            probe = rng.standard_normal(shape) * (1 + 1j)
            # one SVD of each kind for every mode of both models
            total += 2 * n * _best_time(functools.partial(np.linalg.svd, probe, compute_uv=False))
    return total


def _systems(
    loaded: LoadedModel, ev: _Evaluator, jacobians: Callable[..., Any], discretization: str
) -> tuple[ct.StateSpace, ct.StateSpace, np.ndarray, float]:
    """The continuous and discrete models, ``f(x0, u0)`` and the kink measure.

    ``jacobians(fun, what=...)`` is :func:`_fd_jacobian` with the step and the perturbations set.
    """
    A, B, xdot0, kink = jacobians(ev.vector_field, what=f"linearizing {loaded.name}")
    outputs = loaded.card.observation_names if loaded.card is not None else loaded.state_names
    if loaded.card is None:  # the outputs are the states
        C, D = np.eye(ev.n), np.zeros((ev.n, ev.nu))
    else:
        C, D, _, _ = jacobians(ev.observation, what=f"observation of {loaded.name}")
    # python-control reserves "." in system names (file names such as "arm.xml").
    sysname = loaded.name.replace(".", "_")
    sys = _named_ss(loaded, (A, B, C, D), outputs, sysname)
    if discretization == "step":
        Ad, Bd, _, _ = jacobians(ev.step, what=f"stepping {loaded.name}")
        sysd = _named_ss(loaded, (Ad, Bd, C, D), outputs, f"{sysname}_discrete", loaded.control_dt)
    else:
        sysd = ct.sample_system(sys, loaded.control_dt, method="zoh", name=f"{sysname}_discrete")
    xdot0 = np.array(xdot0, dtype=float)
    xdot0.setflags(write=False)
    return sys, sysd, xdot0, kink


def _named_ss(
    loaded: LoadedModel,
    matrices: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    outputs: tuple[str, ...],
    name: str,
    *dt: float,
) -> ct.StateSpace:
    """``ss(A, B, C, D[, dt])`` with the model's state and input names and ``outputs``."""
    return ct.ss(
        *matrices,
        *dt,
        states=list(loaded.state_names),
        inputs=list(loaded.input_names),
        outputs=list(outputs),
        name=name,
    )
