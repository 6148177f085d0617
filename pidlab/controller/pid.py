"""The coach: one discrete multi-loop PID law, used by analysis, simulation, tuner and training.

At every control period ``dt`` (the env's ``timestep * frame_skip``), for each loop in cascade
order (a loop that feeds another first)::

    e  = s * (r_eff - y)                 s = +1 (reverse action) or -1 (direct action)
    P  = kp * e
    I  = xi                              (integral state; forward-Euler update below)
    D  = kd * xd                         xd: derivative of e on measurement, filtered
         xd <- a * xd + (1 - a) * (-s * rate)             with a measured rate signal
         xd <- a * xd + (1 - a) * (-s * (y - y_prev) / dt)  otherwise
         a = tf / (tf + dt)              (backward-Euler first-order filter; tf = 0: none)
    v  = clip(P + I + D, output_limits)
    -> feeds: r_eff(fed loop) += v       -> actuators: u += weight * v

    u_cmd = offset + sum(weight * v);  u = clip(u_cmd, ctrlrange)
    xi <- xi + ki * dt * e               (clamping: skipped while the loop pushes a saturated
                                          output further; back-calculation: plus
                                          dt / tt * (u - u_cmd) projected on the loop's weights)

The first call after :meth:`Coach.reset` takes ``y_prev = y``, so there is no derivative kick.
The coach's linear model (:meth:`Coach.linear_model`) is not written separately: it is read off
this same law (with saturation switched off) by probing it, which is exact because the
unsaturated law is affine.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from pidlab.checks import instance
from pidlab.controller.spec import CoachSpec, Loop, validate_against
from pidlab.errors import SpecError
from pidlab.plant.model import LoadedModel

if TYPE_CHECKING:
    import control as ct

N_LOOP_STATES = 3  # integral, filtered derivative, previous measurement


@dataclass(frozen=True)
class CoachLayout:
    """A spec compiled against its env: indices, weights and limits as arrays.

    Attributes
    ----------
    spec : CoachSpec
    observation_names : tuple of str
    actuator_names : tuple of str
    dt : float
        Control period, s.
    ctrl_low, ctrl_high : ndarray, shape (nu,)
        Actuator limits (``-inf``/``inf`` where unlimited).
    offset : ndarray, shape (nu,)
    order : tuple of int
        Loop indices in evaluation order.
    signal_index, rate_index, feeds_index : tuple of int
        Per loop (``-1`` for none).
    weights : ndarray, shape (n_loops, nu)
    """

    spec: CoachSpec
    observation_names: tuple[str, ...]
    actuator_names: tuple[str, ...]
    dt: float
    ctrl_low: np.ndarray
    ctrl_high: np.ndarray
    offset: np.ndarray
    order: tuple[int, ...]
    signal_index: tuple[int, ...]
    rate_index: tuple[int, ...]
    feeds_index: tuple[int, ...]
    weights: np.ndarray

    @property
    def n_loops(self) -> int:
        """Number of loops."""
        return len(self.spec.loops)

    @property
    def n_states(self) -> int:
        """Length of the law's state vector (3 per loop)."""
        return N_LOOP_STATES * self.n_loops

    @property
    def setpoints(self) -> np.ndarray:
        """The loops' setpoints, shape ``(n_loops,)``."""
        return np.array([lp.setpoint for lp in self.spec.loops])

    def active_states(self) -> np.ndarray:
        """Mask of the states that influence the output (for a minimal linear model)."""
        mask = np.zeros(self.n_states, dtype=bool)
        for i, lp in enumerate(self.spec.loops):
            base = N_LOOP_STATES * i
            mask[base] = lp.ki != 0.0
            derivative = lp.kd != 0.0
            mask[base + 1] = derivative and lp.tf > 0.0
            mask[base + 2] = derivative and lp.rate_signal is None
        return mask


def compile_spec(spec: CoachSpec, loaded: LoadedModel) -> CoachLayout:
    """Check ``spec`` against ``loaded`` and compile it.

    Raises
    ------
    SpecError
        The env differs, or a name is unknown (with the valid names).
    """
    if loaded.card is None:
        raise SpecError(f"{loaded.name} has no model card: a coach needs named observation variables")
    if loaded.env_id != spec.env_id:
        raise SpecError(f"the spec is for {spec.env_id}, not for {loaded.name}")
    obs = loaded.card.observation_names
    acts = loaded.input_names
    m = loaded.model
    lo = np.where(m.actuator_ctrllimited.astype(bool), m.actuator_ctrlrange[:, 0], -np.inf)
    hi = np.where(m.actuator_ctrllimited.astype(bool), m.actuator_ctrlrange[:, 1], np.inf)
    validate_against(spec, obs, acts, {a: (float(lo[i]), float(hi[i])) for i, a in enumerate(acts)})
    names = [lp.name for lp in spec.loops]
    weights = np.zeros((len(spec.loops), len(acts)))
    for i, lp in enumerate(spec.loops):
        for act, w in lp.actuators:
            weights[i, acts.index(act)] += w
    offset = np.zeros(len(acts))
    for act, v in spec.offset:
        offset[acts.index(act)] = v
    return CoachLayout(
        spec=spec,
        observation_names=obs,
        actuator_names=acts,
        dt=loaded.control_dt,
        ctrl_low=lo,
        ctrl_high=hi,
        offset=offset,
        order=tuple(names.index(lp.name) for lp in spec.order()),
        signal_index=tuple(obs.index(lp.signal) for lp in spec.loops),
        rate_index=tuple(obs.index(lp.rate_signal) if lp.rate_signal else -1 for lp in spec.loops),
        feeds_index=tuple(names.index(lp.feeds) if lp.feeds else -1 for lp in spec.loops),
        weights=weights,
    )


def law(
    layout: CoachLayout, state: np.ndarray, y: np.ndarray, r: np.ndarray, saturate: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One step of the coach's discrete control law (pure: returns the new state).

    Parameters
    ----------
    layout : CoachLayout
    state : ndarray, shape (3 * n_loops,)
        Per loop: integral, filtered derivative, previous measurement.
    y : ndarray, shape (n_obs,)
        The observation.
    r : ndarray, shape (n_loops,)
        The loops' setpoints (before cascade shifts).
    saturate : bool, default True
        Apply output limits, actuator saturation and anti-windup. ``False`` gives the affine
        law the linear analysis uses.

    Returns
    -------
    new_state : ndarray, shape (3 * n_loops,)
    u_cmd : ndarray, shape (nu,)
        Command before actuator saturation.
    u : ndarray, shape (nu,)
        Command after saturation (equal to ``u_cmd`` when ``saturate`` is False).
    """
    spec = layout.spec
    dt = layout.dt
    new = np.array(state, dtype=float, copy=True)
    r_eff = np.array(r, dtype=float, copy=True)
    errors = np.zeros(layout.n_loops)
    outputs = np.zeros(layout.n_loops)
    clipped = np.zeros(layout.n_loops)  # v_clipped - v, per loop
    u_cmd = layout.offset.copy()
    for i in layout.order:
        lp = spec.loops[i]
        b = N_LOOP_STATES * i
        yi = float(y[layout.signal_index[i]])
        e = lp.sign * (r_eff[i] - yi)
        errors[i] = e
        a = lp.tf / (lp.tf + dt)
        if layout.rate_index[i] >= 0:
            raw = -lp.sign * float(y[layout.rate_index[i]])
        else:
            raw = -lp.sign * (yi - state[b + 2]) / dt
        xd = a * state[b + 1] + (1.0 - a) * raw
        new[b + 1] = xd
        new[b + 2] = yi
        v = lp.kp * e + state[b] + lp.kd * xd
        if saturate:
            vc = min(max(v, lp.output_limits[0]), lp.output_limits[1])
            clipped[i] = vc - v
            v = vc
        outputs[i] = v
        if layout.feeds_index[i] >= 0:
            r_eff[layout.feeds_index[i]] += v
        else:
            u_cmd = u_cmd + layout.weights[i] * v
    u = np.clip(u_cmd, layout.ctrl_low, layout.ctrl_high) if saturate else u_cmd.copy()
    excess = u - u_cmd  # nonzero where saturated
    for i, lp in enumerate(spec.loops):
        if lp.ki != 0.0:
            b = N_LOOP_STATES * i
            push = _saturation_push(layout, i, clipped, excess) if saturate else 0.0
            new[b] = state[b] + _integral_increment(lp, dt, errors[i], push, saturate)
    return new, u_cmd, u


def _saturation_push(layout: CoachLayout, i: int, clipped: np.ndarray, excess: np.ndarray) -> float:
    """How far saturation pushed loop ``i``'s output back: its own clip, or the actuators' share."""
    if layout.feeds_index[i] >= 0:
        return float(clipped[i])
    w = layout.weights[i]
    norm = float(w @ w)
    return float(w @ excess) / norm if norm > 0 else 0.0


def _integral_increment(lp: Loop, dt: float, error: float, push: float, saturate: bool) -> float:
    """The integral's change over one step, after anti-windup (``push``: see :func:`_saturation_push`)."""
    increment = lp.ki * dt * error
    if saturate and lp.anti_windup != "none":
        if lp.anti_windup == "clamping":
            # saturated (push != 0) and the integral would push further out: freeze it
            if push != 0.0 and np.sign(increment) == -np.sign(push):
                increment = 0.0
        else:  # back-calculation
            increment += dt / lp.tt * push
    return increment


class Coach:
    """A PID coach acting on Gymnasium observations of its env.

    Parameters
    ----------
    spec : CoachSpec
    loaded : LoadedModel
        The env the spec is for (gives observation names, actuators, limits, ``dt``).

    Examples
    --------
    >>> coach = Coach(spec, load_model("InvertedPendulum-v5"))  # doctest: +SKIP
    >>> obs, _ = env.reset(seed=0); coach.reset(obs)             # doctest: +SKIP
    >>> obs, *_ = env.step(coach.act(obs))                        # doctest: +SKIP
    """

    def __init__(self, spec: CoachSpec, loaded: LoadedModel) -> None:
        instance(spec, CoachSpec, "spec", SpecError)
        instance(loaded, LoadedModel, "loaded")
        self.layout = compile_spec(spec, loaded)
        self.spec = spec
        self.state = np.zeros(self.layout.n_states)
        self._primed = False
        self.last_command = np.zeros(len(self.layout.actuator_names))
        self._setpoints = self.layout.setpoints  # built once: act runs every control step

    @property
    def dt(self) -> float:
        """Control period, s."""
        return self.layout.dt

    def reset(self, obs: np.ndarray | None = None) -> None:
        """Clear integrators and filters; with ``obs``, prime the derivative (no kick)."""
        self.state = np.zeros(self.layout.n_states)
        self._primed = False
        if obs is not None:
            self._prime(np.asarray(obs, dtype=float))

    def _prime(self, y: np.ndarray) -> None:
        for i in range(self.layout.n_loops):
            self.state[N_LOOP_STATES * i + 2] = y[self.layout.signal_index[i]]
        self._primed = True

    def act(self, obs: np.ndarray) -> np.ndarray:
        """The coach's action for observation ``obs`` (saturated to ``ctrlrange``)."""
        y = np.asarray(obs, dtype=float)
        if not self._primed:
            self._prime(y)
        self.state, self.last_command, u = law(self.layout, self.state, y, self._setpoints)
        return u

    def linear_model(self) -> ct.StateSpace:
        """The unsaturated law as a discrete state-space model (deviation variables).

        Inputs are every observation variable, then one setpoint per loop
        (``<loop>_setpoint``); outputs are the actuator commands. States are the active
        integrators (``<loop>_integral``), derivative filters (``<loop>_dfilter``) and
        stored measurements (``<loop>_prev``).
        """
        import control as ct  # python-control takes seconds to import; training never needs it

        lay = self.layout
        n, ny, nr = lay.n_states, len(lay.observation_names), lay.n_loops
        zero_x, zero_y, zero_r = np.zeros(n), np.zeros(ny), np.zeros(nr)
        x0, u0, _ = law(lay, zero_x, zero_y, zero_r, saturate=False)
        u0 = u0 - lay.offset

        def probe(x: np.ndarray, y: np.ndarray, r: np.ndarray) -> np.ndarray:
            xn, u, _ = law(lay, x, y, r, saturate=False)
            return np.concatenate([xn - x0, u - lay.offset - u0])

        cols = [probe(np.eye(n)[j], zero_y, zero_r) for j in range(n)]
        cols += [probe(zero_x, np.eye(ny)[j], zero_r) for j in range(ny)]
        cols += [probe(zero_x, zero_y, np.eye(nr)[j]) for j in range(nr)]
        M = np.column_stack(cols)
        A, B = M[:n, :n], M[:n, n:]
        C, D = M[n:, :n], M[n:, n:]
        keep = lay.active_states()
        A, B, C = A[np.ix_(keep, keep)], B[keep], C[:, keep]
        state_names = [
            f"{lp.name}_{kind}" for lp in lay.spec.loops for kind in ("integral", "dfilter", "prev")
        ]
        return ct.ss(
            A,
            B,
            C,
            D,
            lay.dt,
            states=[s for s, k in zip(state_names, keep, strict=True) if k],
            inputs=list(lay.observation_names) + [f"{lp.name}_setpoint" for lp in lay.spec.loops],
            outputs=list(lay.actuator_names),
            name="coach",
        )


__all__ = ["Coach", "CoachLayout", "SpecError", "compile_spec", "law"]
