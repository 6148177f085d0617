"""Simulation helpers shared by the region estimates and the critical bounds.

The region of attraction (:mod:`pidlab.region.roa`) and the one-step margin of the bounds
(:mod:`pidlab.region.bounds`) both start MuJoCo at a chosen deviation from the operating
point, close the loop with the coach's real discrete law and watch the env's termination rule.
:class:`Simulator` does that; :class:`SimulationPool` runs many such simulations over worker
processes (:mod:`pidlab.parallel`); the functions below pick the states they start from.
"""

from __future__ import annotations

import mujoco
import numpy as np

from pidlab.controller.pid import N_LOOP_STATES, Coach
from pidlab.controller.spec import CoachSpec
from pidlab.errors import RegionError
from pidlab.linear.linearize import Linearization
from pidlab.parallel import WorkerPool, resolve_workers
from pidlab.plant.ground import ground_of, on_floor
from pidlab.plant.model import LoadedModel
from pidlab.plant.observation import CompiledCard, observe_at


class Simulator:
    """MuJoCo and the coach's real discrete law, started at a deviation from the operating point.

    Parameters
    ----------
    spec : CoachSpec
    loaded : LoadedModel
        The model of ``spec.env_id``, with a model card.
    lin : Linearization
        Supplies the operating point ``lin.op`` (``qpos``, ``qvel``, ``ctrl``).

    Attributes
    ----------
    loaded : LoadedModel
    m : mujoco.MjModel
    d : mujoco.MjData
        The simulated state (one per simulator; not thread-safe).
    coach : Coach
    lin : Linearization
    card : ModelCard
    fast : CompiledCard
        The card's observation and termination rule, compiled for ``m``.
    y_op : ndarray, shape (n_obs,)
        The observation at the operating point.
    ground : Ground or None
        How the model stands on its floor at the operating point (None: it does not).
    """

    def __init__(self, spec: CoachSpec, loaded: LoadedModel, lin: Linearization) -> None:
        self.loaded = loaded
        self.m = loaded.model
        self.d = mujoco.MjData(self.m)
        self.coach = Coach(spec, loaded)
        self.lin = lin
        card = loaded.require_card()
        self.card = card
        self.fast = CompiledCard(card, self.m)
        self.y_op = observe_at(self.card, self.m, lin.op.qpos, lin.op.qvel)
        self.ground = ground_of(self.m, lin.op.qpos)
        m = self.m
        kinds = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
        self._limits = tuple(
            (int(m.jnt_qposadr[j]), float(m.jnt_range[j][0]), float(m.jnt_range[j][1]))
            for j in range(m.njnt)
            if m.jnt_limited[j] and int(m.jnt_type[j]) in kinds
        )

    def within_limits(self) -> bool:
        """Whether every limited hinge or slide joint lies within its range (a state the model can reach)."""
        q = self.d.qpos
        return all(lo <= q[adr] <= hi for adr, lo, hi in self._limits)

    def observe(self) -> np.ndarray:
        """The observation at the current state (``fast.observe(d)``)."""
        return self.fast.observe(self.d)

    def terminated(self, obs: np.ndarray) -> bool:
        """Whether the env would terminate now; ``obs`` is :meth:`observe` (as ``fast.terminated(d)``)."""
        return self.fast.terminated(self.d, obs)

    def start(self, x_plant: np.ndarray, grounded: bool = False) -> np.ndarray:
        """Put MuJoCo at the operating point (+) ``x_plant`` and reset the coach.

        Parameters
        ----------
        x_plant : ndarray, shape (2*nv,)
            Tangent-space deviation ``(dq, dv)`` from the operating point.
        grounded : bool
            Then the root's height is moved so that the feet touch the floor as at the operating
            point (:func:`pidlab.plant.ground.on_floor`; a model with no :attr:`ground` is unchanged).

        Returns
        -------
        obs : ndarray, shape (n_obs,)
            The observation there.
        """
        m, d, op = self.m, self.d, self.lin.op
        mujoco.mj_resetData(m, d)
        q = op.qpos.copy()
        mujoco.mj_integratePos(m, q, x_plant[: m.nv], 1.0)
        d.qpos[:] = q
        d.qvel[:] = op.qvel + x_plant[m.nv : 2 * m.nv]
        if grounded and self.ground is not None:
            on_floor(m, d, self.ground)
        mujoco.mj_forward(m, d)
        obs = self.observe()
        self.coach.reset(obs)
        return obs

    def coach_deviation(self) -> np.ndarray:
        """The coach's active states minus their values at the operating point, shape ``(n_active,)``."""
        lay = self.coach.layout
        ref = np.zeros(lay.n_states)
        for i, lp in enumerate(lay.spec.loops):
            ref[N_LOOP_STATES * i + 2] = self.y_op[lay.observation_names.index(lp.signal)]
        return (self.coach.state - ref)[lay.active_states()]

    def plant_state(self) -> np.ndarray:
        """The plant's tangent-space deviation ``(dq, dv)`` from the operating point, shape ``(2*nv,)``."""
        dq = np.zeros(self.m.nv)
        mujoco.mj_differentiatePos(self.m, dq, 1.0, self.lin.op.qpos, self.d.qpos)
        return np.concatenate([dq, self.d.qvel - self.lin.op.qvel])

    def closed_loop_state(self) -> np.ndarray:
        """``X`` of the closed loop: :meth:`plant_state` then :meth:`coach_deviation`."""
        return np.concatenate([self.plant_state(), self.coach_deviation()])

    def run(self, obs: np.ndarray, steps: int, record: list[int] | None = None) -> tuple[bool, np.ndarray]:
        """Step the coached system for ``steps`` control periods, or until the env would terminate.

        Parameters
        ----------
        obs : ndarray, shape (n_obs,)
            The current observation (as :meth:`start` returns it).
        steps : int
        record : list of int, optional
            Observation columns to record along the way.

        Returns
        -------
        terminated : bool
        path : ndarray, shape (T + 1, len(record))
            The recorded columns, from ``obs`` on (empty without ``record``).
        """
        m, d, act, card = self.m, self.d, self.coach.act, self.fast
        frame_skip = self.loaded.frame_skip
        path = [obs[record]] if record is not None else []
        for _ in range(steps):
            d.ctrl[:] = act(obs)
            mujoco.mj_step(m, d, nstep=frame_skip)
            obs = card.observe(d)
            if record is not None:
                path.append(obs[record])
            if card.terminated(d, obs):
                return True, np.array(path)
        return False, np.array(path)


class SimulationPool(WorkerPool[Simulator]):
    """Simulations of one coach on one env: a :class:`~pidlab.parallel.WorkerPool` of :class:`Simulator`.

    Parameters
    ----------
    spec : CoachSpec
    loaded : LoadedModel
    lin : Linearization
        As for :class:`~pidlab.region.simulate.Simulator`.
    workers : int, optional
        As for :class:`~pidlab.parallel.WorkerPool`.

    Attributes
    ----------
    sim : Simulator
        This process's simulator (for single simulations and the set-up of checks).
    workers : int
    """

    def __init__(
        self, spec: CoachSpec, loaded: LoadedModel, lin: Linearization, workers: int | None = None
    ) -> None:
        super().__init__(Simulator, (spec, loaded, lin), resolve_workers(workers, RegionError))
        self.sim = self.state

    def __enter__(self) -> SimulationPool:
        return self


def horizon_steps(horizon_s: float, control_dt: float) -> int:
    """Control periods in a horizon of ``horizon_s`` seconds (at least one)."""
    return max(1, round(horizon_s / control_dt))


def tangent_index(model: mujoco.MjModel, variable: str) -> int:
    """Index of a ``<joint>_pos`` or ``<joint>_vel`` variable in the tangent state ``(dq, dv)``.

    Parameters
    ----------
    model : mujoco.MjModel
    variable : str
        e.g. ``"rooty_pos"`` (the joint's first dof in ``dq``) or ``"rooty_vel"`` (in ``dv``).

    Returns
    -------
    int
        In ``range(2 * model.nv)``.
    """
    jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, variable.rsplit("_", 1)[0])
    return int(model.jnt_dofadr[jid]) + (model.nv if variable.endswith("_vel") else 0)


def sample_ellipsoid(P_y: np.ndarray, c: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """Uniform samples in the ellipsoid ``{y : y' P_y y <= c}``.

    Parameters
    ----------
    P_y : ndarray, shape (k, k)
        Symmetric positive definite.
    c : float
        Level, > 0.
    n : int
    rng : numpy.random.Generator

    Returns
    -------
    ndarray, shape (n, k)
    """
    k = P_y.shape[0]
    L = np.linalg.cholesky(P_y / c)  # y' P_y y / c = |L' y|^2
    g = rng.standard_normal((n, k))
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    r = rng.random(n) ** (1.0 / k)
    u = g * r[:, None]
    return np.linalg.solve(L.T, u.T).T
