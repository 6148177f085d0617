"""The ``balance`` preset: full-state LQR about a balanced standing posture, for a robot on its feet.

At Walker2d's operating point (the env's reset pose) the hips and knees sit at the upper limit of
their range and the centre of mass is 0.03 m ahead of the ankles, over the heel edge of feet that
reach 0.2 m forward: a backward push tips it over, and a finite-difference linearization there
is dominated by the limits and contacts switching (eigenvalues of order 6,000). The PD structures
of the other presets, searched on the env, still fall in 75 of 100 perturbed episodes
(``pidlab recovery``).

This preset poses the robot first, then designs on the linear model of that pose:

1. **Posture** (:func:`balanced_posture`): the card's ``[balance]`` table holds its ``bend``
   joints at their angles (knees off their limits); one hip angle (every ``hips`` joint) and one
   ankle angle (every ``ankles`` joint) are solved so that the feet lie flat and the centre of mass
   is over the middle of the feet. :func:`pidlab.plant.operating_point.settle` then lowers and
   tilts the base (``height``, ``pitch``) until the floor carries the weight, within
   :data:`SETTLE_SPAN` (a wider scan finds the heel-balanced equilibrium again), and gives the
   equilibrium control ``u0``.
2. **Linear model** (:func:`pidlab.linear.linearize.linearize`, step :data:`LINEARIZE_EPS`) over
   the observed states (Walker2d: all but the forward position, which no other state depends on;
   refused when one does).
3. **Full-state LQR** (:func:`balance_gain`): the weights of :data:`DESIGN` per kind of state,
   plus one on the centre of mass's distance from the middle of the feet and one on its rate
   (their gradients by finite differences), and an input weight on every actuator.
4. **Coach law** (:func:`balance_spec`): ``u = clip(u0 - K (y - y*))`` exactly, as one loop per
   observed variable (``kp`` 1, its actuator weights a column of ``K``, its setpoint the posture's
   observation ``y*``) and ``u0`` as the offset.

The weights are round numbers chosen on the tuning starts of :mod:`pidlab.region.room_env` (seeds
1000-1001), never on seed 0, which ``pidlab recovery`` reports on; ``benchmarks/balance_ablation.py``
measures what each is worth. The margins are reported at the posture's linear model, as for the
other presets.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import mujoco
import numpy as np
from scipy.linalg import solve_discrete_are
from scipy.optimize import fsolve

from pidlab.controller.autotune import TuneResult, tune_result
from pidlab.controller.spec import CoachSpec, Loop
from pidlab.errors import PidlabError
from pidlab.linear.linearize import Linearization, linearize
from pidlab.plant.card import Balance, ModelCard
from pidlab.plant.model import LoadedModel
from pidlab.plant.observation import observe_at
from pidlab.plant.operating_point import OperatingPoint, resolve_operating_point, settle

SETTLE_SPAN = 0.01
"""Half-width (m, rad) of the settle's scan of the base's height and pitch."""

LINEARIZE_EPS = 1e-4
"""Finite-difference step of the posture's linear model (1e-6 resolves the contacts' kinks)."""


@dataclass(frozen=True)
class BalanceDesign:
    """The LQR's weights, and optionally one knee bend for every ``bend`` joint of the card.

    Attributes
    ----------
    height, pitch, position, rate : float
        State weights: the base's height, its pitch, every other position, every rate.
    com, com_rate : float
        Weights on the centre of mass's horizontal distance from the middle of the feet (per m^2)
        and on its rate.
    input : float
        Input weight on every actuator (commands in their control range).
    bend : float or None
        Replaces the angle of every joint of the card's ``bend`` (rad); None keeps the card's.
    """

    height: float = 0.0
    pitch: float = 10.0
    position: float = 1.0
    rate: float = 0.1
    com: float = 100.0
    com_rate: float = 10.0
    input: float = 10**0.5
    bend: float | None = None


DESIGN = BalanceDesign()
"""The preset's design."""

FLAT_TOLERANCE = 1e-6
"""The posture's residuals (foot slope, centre of mass offset in m) must end below this."""


@dataclass(frozen=True)
class Posture:
    """A balanced standing posture and the control that holds it.

    Attributes
    ----------
    qpos : ndarray, shape (nq,)
        Settled on the floor.
    ctrl : ndarray, shape (nu,)
        Equilibrium control.
    hip, ankle : float
        The solved angles (rad).
    com_offset : float
        Centre of mass minus the middle of the feet, along the walking direction (m), after settling.
    """

    qpos: np.ndarray
    ctrl: np.ndarray
    hip: float
    ankle: float
    com_offset: float


def _balance_of(loaded: LoadedModel) -> tuple[ModelCard, Balance]:
    card = loaded.require_card()
    if card.balance is None:
        raise PidlabError(
            f"preset balance: the model card of {loaded.name} has no [balance] table; it needs feet, bend, "
            "hips, ankles, height and pitch (see docs/linearization.md)",
            param="preset",
        )  # fmt: skip
    return card, card.balance


class _Geometry:
    """Kinematics of a configuration: the feet's slope and the centre of mass's offset from them."""

    def __init__(self, loaded: LoadedModel, balance: Balance) -> None:
        m = loaded.model
        self.m, self.d = m, mujoco.MjData(m)
        self.feet = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, g) for g in balance.feet]
        self.axes = [_long_axis(m, g) for g in self.feet]
        pitch = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, balance.pitch)
        self.body = int(m.jnt_bodyid[pitch])

    def residual(self, qpos: np.ndarray) -> np.ndarray:
        """(mean slope of the feet's long axes, centre of mass minus the feet's middle along x)."""
        d = self.d
        d.qpos[:] = qpos
        mujoco.mj_kinematics(self.m, d)
        mujoco.mj_comPos(self.m, d)
        pairs = zip(self.feet, self.axes, strict=True)
        slope = np.mean([d.geom_xmat[g].reshape(3, 3)[2, a] for g, a in pairs])
        middle = np.mean([d.geom_xpos[g][0] for g in self.feet])
        return np.array([slope, d.subtree_com[self.body][0] - middle])


def _long_axis(m: mujoco.MjModel, geom: int) -> int:
    """The axis of the geom's frame it lies along: a capsule's or cylinder's z, a box's longest side."""
    kind = int(m.geom_type[geom])
    if kind in (int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_CYLINDER)):
        return 2
    if kind == int(mujoco.mjtGeom.mjGEOM_BOX):
        return int(np.argmax(m.geom_size[geom]))
    name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, geom)
    raise PidlabError(f"preset balance: foot geom {name!r} is not a capsule, cylinder or box")


def _addresses(m: mujoco.MjModel, names: tuple[str, ...]) -> list[int]:
    return [int(m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j)]) for j in names]


def balanced_posture(loaded: LoadedModel, bend: float | None = None) -> Posture:
    """The card's ``[balance]`` posture, settled on the floor (step 1 of the module docstring).

    ``bend`` replaces the angle of every joint of the card's ``bend`` (rad; None: the card's).

    Raises
    ------
    PidlabError
        No ``[balance]`` table, or no posture with flat feet and the centre of mass over them.
    """
    card, balance = _balance_of(loaded)
    m = loaded.model
    geometry = _Geometry(loaded, balance)
    q0 = np.array(card.operating_point.qpos, dtype=float)
    angles = [(joint, angle if bend is None else bend) for joint, angle in balance.bend]
    for joint, angle in angles:
        q0[_addresses(m, (joint,))[0]] = angle
    hips, ankles = _addresses(m, balance.hips), _addresses(m, balance.ankles)

    def pose(z: np.ndarray) -> np.ndarray:
        q = q0.copy()
        q[hips], q[ankles] = z[0], z[1]
        return q

    mean_bend = float(np.mean([a for _, a in angles])) if angles else 0.0
    z, _, ok, _ = fsolve(lambda z: geometry.residual(pose(z)), [0.0, -mean_bend / 2], full_output=True)
    if ok != 1 or np.max(np.abs(geometry.residual(pose(z)))) > FLAT_TOLERANCE:
        raise PidlabError(f"preset balance: no posture of {loaded.name} with flat feet and the centre of "
                          "mass over them from the card's [balance] table")  # fmt: skip
    _check_ranges(m, pose(z), balance.hips + balance.ankles, loaded.name)
    found = settle(loaded, pose(z), free=[balance.height, balance.pitch], span=SETTLE_SPAN)
    offset = float(geometry.residual(found.qpos)[1])
    return Posture(np.asarray(found.qpos, dtype=float), np.asarray(found.equilibrium.ctrl, dtype=float),
                   float(z[0]), float(z[1]), offset)  # fmt: skip


def _check_ranges(m: mujoco.MjModel, qpos: np.ndarray, joints: tuple[str, ...], name: str) -> None:
    """Refuse a solved posture that puts a hip or an ankle outside its joint's range."""
    for joint in joints:
        jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, joint)
        lo, hi = m.jnt_range[jid]
        value = float(qpos[m.jnt_qposadr[jid]])
        if m.jnt_limited[jid] and not lo <= value <= hi:
            raise PidlabError(f"preset balance: the posture of {name} with flat feet and the centre of mass "
                              f"over them needs {joint} = {value:.4g} rad, outside its range [{lo:.4g}, "
                              f"{hi:.4g}]; change the card's [balance] bend")  # fmt: skip


def _observed_states(card: ModelCard, lin: Linearization) -> list[int]:
    """Per observation variable, its state's index in ``lin.sysd`` (joint positions and rates only)."""
    labels = list(lin.sysd.state_labels)
    out = []
    for v in card.observation:
        label = f"{v.joint}_{'pos' if v.source == 'qpos' else 'vel'}"
        if v.source not in ("qpos", "qvel") or v.transform != "identity" or label not in labels:
            raise PidlabError(f"preset balance: observation {v.name!r} is not a joint's position or rate; "
                              "the full-state design needs the state itself", param="preset")  # fmt: skip
        out.append(labels.index(label))
    return out


def _com_gradient(loaded: LoadedModel, balance: Balance, qpos: np.ndarray) -> np.ndarray:
    """d(centre of mass - middle of the feet)/d(tangent position), by central differences (nv,)."""
    m = loaded.model
    geometry = _Geometry(loaded, balance)
    out = np.zeros(m.nv)
    step = 1e-6
    for k in range(m.nv):
        dq = np.zeros(m.nv)
        dq[k] = step
        up, down = qpos.copy(), qpos.copy()
        mujoco.mj_integratePos(m, up, dq, 1.0)
        mujoco.mj_integratePos(m, down, -dq, 1.0)
        out[k] = (geometry.residual(up)[1] - geometry.residual(down)[1]) / (2 * step)
    return out


def balance_gain(
    loaded: LoadedModel, lin: Linearization, posture: Posture, design: BalanceDesign = DESIGN
) -> np.ndarray:
    """The full-state LQR gain over the card's observation variables, shape (nu, n_obs) (step 3).

    Raises
    ------
    PidlabError
        An observation that is not a state, an observed state that an unobserved one drives, or no
        stabilizing LQR solution.
    """
    card, balance = _balance_of(loaded)
    m = loaded.model
    rows = _observed_states(card, lin)
    A, B = np.asarray(lin.sysd.A), np.asarray(lin.sysd.B)
    hidden = [i for i in range(A.shape[0]) if i not in rows]
    if hidden and np.max(np.abs(A[np.ix_(rows, hidden)])) > 1e-6:
        raise PidlabError("preset balance: an unobserved state drives the observed ones; the full-state "
                          "design needs every state that matters observed", param="preset")  # fmt: skip
    grad = _com_gradient(loaded, balance, posture.qpos)
    weights, com, com_rate = np.zeros(len(rows)), np.zeros(len(rows)), np.zeros(len(rows))
    for j, (v, row) in enumerate(zip(card.observation, rows, strict=True)):
        rate = v.source == "qvel"
        kind = "rate" if rate else {balance.height: "height", balance.pitch: "pitch"}.get(v.joint, "position")
        weights[j] = getattr(design, kind)
        (com_rate if rate else com)[j] = grad[row - m.nv if rate else row]
    Q = np.diag(weights) + design.com * np.outer(com, com) + design.com_rate * np.outer(com_rate, com_rate)
    Ao, Bo = A[np.ix_(rows, rows)], B[rows]
    R = design.input * np.eye(Bo.shape[1])
    try:
        P = solve_discrete_are(Ao, Bo, Q, R)
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise PidlabError(f"preset balance: no LQR solution at the posture of {loaded.name} ({exc})") from exc
    return np.linalg.solve(R + Bo.T @ P @ Bo, Bo.T @ P @ Ao)


def balance_spec(
    loaded: LoadedModel, posture: Posture, K: np.ndarray, name: str = "pidlab-balance"
) -> CoachSpec:
    """``u = clip(u0 - K (y - y*))`` as a coach spec: one loop per observed variable (step 4)."""
    card = loaded.require_card()
    y_star = observe_at(card, loaded.model, posture.qpos, np.zeros(loaded.model.nv))
    loops = []
    for j, v in enumerate(card.observation):
        column = K[:, j]
        if not np.any(column):
            continue
        # reverse action: e = y* - y, and u += w * e with w = K[:, j]: u = u0 - K (y - y*)
        weights = tuple((a, float(column[i])) for i, a in enumerate(loaded.input_names))
        loops.append(Loop(name=v.name, signal=v.name, setpoint=float(y_star[j]), action="reverse", kp=1.0,
                          kd=0.0, actuators=weights))  # fmt: skip
    offset = tuple((a, float(u)) for a, u in zip(loaded.input_names, posture.ctrl, strict=True))
    return CoachSpec(env_id=str(loaded.env_id), name=name, loops=tuple(loops), offset=offset)


def tune_balance(loaded: LoadedModel, design: BalanceDesign = DESIGN) -> TuneResult:
    """The ``balance`` preset (see the module docstring); its margins at the posture's linear model.

    ``design`` (default :data:`DESIGN`, the preset's) sets the weights and optionally the bend.

    Raises
    ------
    PidlabError
        No ``[balance]`` table in the card, no balanced posture, or no LQR solution.
    """
    posture = balanced_posture(loaded, design.bend)
    op = resolve_operating_point(loaded, qpos=posture.qpos, qvel=np.zeros(loaded.model.nv), ctrl=posture.ctrl)
    lin = linearize(loaded, op, eps=LINEARIZE_EPS)
    K = balance_gain(loaded, lin, posture, design)
    spec = balance_spec(loaded, posture, K)
    closed = np.max(np.abs(np.linalg.eigvals(_closed_loop(loaded, lin, K))))
    text = (
        f"pidlab auto-tuned coach (balance preset) for {loaded.env_id}: full-state discrete LQR about a "
        f"balanced standing posture (hip {posture.hip:.3f} rad, ankle {posture.ankle:.3f} rad, the card's "
        "[balance] bend; feet flat, centre of mass over their middle), one loop per observed variable."
    )
    extra = {
        "balance_posture_qpos": [float(v) for v in posture.qpos],
        "balance_com_offset_m": posture.com_offset,
        "balance_design": {k: v for k, v in asdict(design).items() if v is not None},
        "balance_linearize_eps": LINEARIZE_EPS,
        "balance_kink": float(lin.kink),
        "balance_lqr_spectral_radius": float(closed),
    }
    nan = float("nan")
    return tune_result(spec, loaded, lin, "balance", (nan, nan), 1, None, text, extra)


def _closed_loop(loaded: LoadedModel, lin: Linearization, K: np.ndarray) -> np.ndarray:
    """The observed states' discrete closed loop ``A - B K`` of the design."""
    rows = _observed_states(loaded.require_card(), lin)
    A, B = np.asarray(lin.sysd.A), np.asarray(lin.sysd.B)
    return A[np.ix_(rows, rows)] - B[rows] @ K


def design_point(spec: CoachSpec, loaded: LoadedModel) -> OperatingPoint | None:
    """The posture a balance coach was designed at, at rest (None: not a balance coach).

    A ``balance`` coach is designed about its posture, not about the model card's operating point
    (the env's reset pose): it regulates the robot to it, and its margins and poles mean something
    there only. The posture is the one its provenance records (``balance_posture_qpos``), at rest,
    with the coach's offset ``u0`` as the control.

    Raises
    ------
    PidlabError
        A recorded posture that is not ``nq`` finite numbers, or an offset that does not name every
        actuator.
    """
    qpos = spec.provenance.get("balance_posture_qpos")
    if qpos is None:
        return None
    offset = dict(spec.offset)
    missing = [a for a in loaded.input_names if a not in offset]
    if missing:
        raise PidlabError(
            f"{spec.name}: a balance coach's offset names every actuator (its u0); "
            f"missing {', '.join(missing)}"
        )
    ctrl = [offset[a] for a in loaded.input_names]
    try:
        op = resolve_operating_point(loaded, qpos=qpos, qvel=np.zeros(loaded.model.nv), ctrl=ctrl)
    except PidlabError as exc:
        where = f"{spec.name}: its recorded posture (provenance balance_posture_qpos)"
        raise PidlabError(f"{where}: {exc}") from None
    return replace(
        op, source="the balance posture the coach was designed at", ctrl_source="the coach's offset u0"
    )


def design_linearization(spec: CoachSpec, loaded: LoadedModel) -> Linearization | None:
    """The linear model about :func:`design_point` (None: not a balance coach), with the design's step.

    Raises
    ------
    PidlabError
        As :func:`design_point`, or a recorded step outside (0, 1).
    """
    op = design_point(spec, loaded)
    if op is None:
        return None
    eps = spec.provenance.get("balance_linearize_eps", LINEARIZE_EPS)
    if not isinstance(eps, (int, float)) or not 0 < eps < 1:
        raise PidlabError(f"{spec.name}: balance_linearize_eps {eps!r}: expected a step in (0, 1)")
    return linearize(loaded, op, eps=float(eps))


def design_observation(spec: CoachSpec, loaded: LoadedModel, variables: tuple[str, ...]) -> np.ndarray | None:
    """The observation's ``variables`` at :func:`design_point` (None: not a balance coach)."""
    op = design_point(spec, loaded)
    if op is None:
        return None
    card = loaded.require_card()
    y = observe_at(card, loaded.model, op.qpos, op.qvel)
    return np.array([y[card.observation_names.index(v)] for v in variables], dtype=float)
