"""Operating points: where to linearize, and the control that holds the model there.

An operating point is ``(qpos, qvel, act, ctrl)``. It comes from the model card, the model's
``qpos0``, a keyframe, or explicit vectors. The equilibrium control is found the way MuJoCo's
LQR recipe does it: inverse dynamics (``mj_inverse``) gives the generalized force that holds
the state with zero acceleration, and the actuators' moments map it to controls by least
squares. Unactuated degrees of freedom cannot be helped by the actuators; what is left on them
is reported as a residual, and :func:`settle` can move free coordinates (e.g. a floating
base's height) until contact forces carry the model.
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from dataclasses import dataclass, field

import mujoco
import numpy as np
from scipy.optimize import least_squares

from pidlab.checks import instance, number, shown
from pidlab.errors import KeyframeError, OperatingPointError
from pidlab.plant.model import LoadedModel, dof_names, finite_or_raise, joint_name


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class EquilibriumControl:
    """The control that best holds a state still, from inverse dynamics.

    Attributes
    ----------
    ctrl : ndarray, shape (nu,)
        Least-squares control (clamped to ``ctrlrange`` where the actuator is limited).
    qfrc_inverse : ndarray, shape (nv,)
        Generalized force required for zero acceleration (``mj_inverse``), N or N m.
    residual : ndarray, shape (nv,)
        Required force the actuators cannot provide at ``ctrl``; zero at a true equilibrium.
    saturated : tuple of str
        Actuators whose least-squares control fell outside ``ctrlrange`` and was clamped.
    """

    ctrl: np.ndarray
    qfrc_inverse: np.ndarray
    residual: np.ndarray
    saturated: tuple[str, ...]

    @property
    def residual_norm(self) -> float:
        """Euclidean norm of :attr:`residual`."""
        return float(np.linalg.norm(self.residual))


@dataclass(frozen=True)
class OperatingPoint:
    """A point in state and input space to linearize about.

    Attributes
    ----------
    qpos : ndarray, shape (nq,)
    qvel : ndarray, shape (nv,)
    act : ndarray, shape (na,)
    ctrl : ndarray, shape (nu,)
    source : str
        How the state was chosen: ``"qpos0"``, ``"keyframe:<name>"``, ``"card:<name>"``,
        ``"explicit"`` (possibly combined, e.g. ``"qpos0+explicit qvel"``).
    ctrl_source : str
        ``"zero"``, ``"keyframe"``, ``"card"``, ``"explicit"`` or ``"inverse dynamics"``.
    equilibrium : EquilibriumControl or None
        Present when the control came from inverse dynamics.
    """

    qpos: np.ndarray
    qvel: np.ndarray
    act: np.ndarray
    ctrl: np.ndarray
    source: str
    ctrl_source: str
    equilibrium: EquilibriumControl | None = field(default=None)

    def __post_init__(self) -> None:
        for name in ("qpos", "qvel", "act", "ctrl"):
            object.__setattr__(self, name, _frozen(getattr(self, name)))

    def to_dict(self) -> dict[str, object]:
        """Plain-Python view for JSON output."""
        out: dict[str, object] = {
            "qpos": self.qpos.tolist(),
            "qvel": self.qvel.tolist(),
            "act": self.act.tolist(),
            "ctrl": self.ctrl.tolist(),
            "source": self.source,
            "ctrl_source": self.ctrl_source,
        }
        if self.equilibrium is not None:
            out["equilibrium_residual"] = self.equilibrium.residual.tolist()
            out["equilibrium_saturated"] = list(self.equilibrium.saturated)
        return out


def _check_len(values: Sequence[float] | np.ndarray, n: int, what: str, names: Sequence[str]) -> np.ndarray:
    """``values`` as a vector of ``n`` finite floats (booleans and strings are not numbers).

    Raises
    ------
    OperatingPointError
        The wrong length, an entry that is not a number, or a non-finite entry.
    """
    try:
        arr = np.asarray(values, dtype=object).ravel()
    except (ValueError, TypeError):
        raise OperatingPointError(
            f"{what}={shown(values)}: expected {n} finite numbers", param=what
        ) from None
    if arr.size != n:
        listing = f" ({', '.join(names)})" if names else ""
        raise OperatingPointError(f"{what} has {arr.size} entries; the model expects {n}{listing}")
    out = np.empty(n)
    for i, v in enumerate(arr):
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (numbers.Real, np.floating, np.integer)):
            raise OperatingPointError(f"{what}[{i}] = {shown(v)}: expected a finite number")
        try:
            out[i] = float(v)
        except OverflowError:
            out[i] = np.inf
    return finite_or_raise(out, what)


def _qpos_names(model: mujoco.MjModel) -> list[str]:
    names = []
    for j in range(model.njnt):
        jtype = int(model.jnt_type[j])
        width = {int(mujoco.mjtJoint.mjJNT_FREE): 7, int(mujoco.mjtJoint.mjJNT_BALL): 4}.get(jtype, 1)
        name = joint_name(model, j)
        names.extend([name] if width == 1 else [f"{name}[{k}]" for k in range(width)])
    return names


def keyframe_names(model: mujoco.MjModel) -> list[str]:
    """Names of the model's keyframes (unnamed ones as ``key<i>``)."""
    return [model.key(k).name or f"key{k}" for k in range(model.nkey)]


def resolve_operating_point(
    loaded: LoadedModel,
    at: str | None = None,
    *,
    qpos: Sequence[float] | np.ndarray | None = None,
    qvel: Sequence[float] | np.ndarray | None = None,
    ctrl: Sequence[float] | np.ndarray | None = None,
    equilibrium_ctrl: bool = False,
) -> OperatingPoint:
    """Build an operating point from a named base point and explicit overrides.

    Parameters
    ----------
    loaded : LoadedModel
    at : str, optional
        ``"qpos0"``, ``"card"`` (the model card's point), or a keyframe name. Default: the
        card's point when the model has a card, else ``"qpos0"``.
    qpos, qvel, ctrl : array_like, optional
        Explicit vectors that replace the base point's (shapes ``(nq,)``, ``(nv,)``, ``(nu,)``).
        Quaternions of ball and free joints are normalized.
    equilibrium_ctrl : bool, default False
        Replace the control by the inverse-dynamics equilibrium control
        (:func:`equilibrium_control`); mutually exclusive with ``ctrl``.

    Returns
    -------
    OperatingPoint

    Raises
    ------
    KeyframeError
        ``at`` names no keyframe of the model.
    OperatingPointError
        A vector has the wrong length or non-finite entries.
    """
    model = instance(loaded, LoadedModel, "loaded").model
    if at is None:
        at = "card" if loaded.card is not None else "qpos0"
    if not isinstance(at, str):
        raise OperatingPointError(f"at={shown(at)}: expected qpos0, card or a keyframe name", param="at")
    base = _base_point(loaded, at)
    base_qpos, base_qvel, base_ctrl = base.qpos, base.qvel, base.ctrl
    source, ctrl_source = base.source, base.ctrl_source
    explicit = []
    if qpos is not None:
        base_qpos = _check_len(qpos, model.nq, "qpos", _qpos_names(model))
        explicit.append("qpos")
    if qvel is not None:
        base_qvel = _check_len(qvel, model.nv, "qvel", dof_names(model)[1])
        explicit.append("qvel")
    if ctrl is not None:
        if equilibrium_ctrl:
            raise OperatingPointError("give either an explicit ctrl or equilibrium_ctrl=True, not both")
        base_ctrl = _check_len(ctrl, model.nu, "ctrl", loaded.input_names)
        ctrl_source = "explicit"
    if explicit:
        source = f"{source}+explicit {'/'.join(explicit)}"
    base_qpos = finite_or_raise(base_qpos, "qpos").copy()
    mujoco.mj_normalizeQuat(model, base_qpos)
    equilibrium = None
    if equilibrium_ctrl:
        equilibrium = equilibrium_control(loaded, base_qpos, base_qvel, base.act)
        base_ctrl = equilibrium.ctrl
        ctrl_source = "inverse dynamics"
    return OperatingPoint(
        qpos=base_qpos,
        qvel=base_qvel,
        act=base.act,
        ctrl=base_ctrl,
        source=source,
        ctrl_source=ctrl_source,
        equilibrium=equilibrium,
    )


def _base_point(loaded: LoadedModel, at: str) -> OperatingPoint:
    """The named point ``at`` (``qpos0``, ``card`` or a keyframe) before explicit overrides.

    Raises
    ------
    OperatingPointError, KeyframeError
    """
    model = loaded.model
    if at == "qpos0":
        zeros = np.zeros
        return OperatingPoint(model.qpos0, zeros(model.nv), zeros(model.na), zeros(model.nu), "qpos0", "zero")
    if at == "card":
        if loaded.card is None:
            raise OperatingPointError(
                f"at={at!r}: {loaded.name} has no model card; expected qpos0 or a keyframe name", param="at"
            )
        op = loaded.card.operating_point
        return OperatingPoint(
            np.array(op.qpos),
            np.array(op.qvel),
            np.zeros(model.na),
            np.array(op.ctrl),
            f"card:{op.name}",
            "card",
        )
    names = keyframe_names(model)
    if at not in names:
        available = ", ".join(names) if names else "the model defines no keyframes"
        raise KeyframeError(
            f"no keyframe {at!r} in {loaded.name}; expected qpos0, card or one of: {available}"
        )
    key = model.key(names.index(at))
    return OperatingPoint(key.qpos, key.qvel, key.act, key.ctrl, f"keyframe:{at}", "keyframe")


def _actuator_force_map(model: mujoco.MjModel, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
    """``qfrc_actuator`` at zero control and its (exact, affine) derivative in the controls.

    For the affine actuators MuJoCo provides, ``d qfrc_actuator / d ctrl`` is the actuator
    moment matrix transposed, scaled by each actuator's force gain.
    """
    nu = model.nu
    saved = data.ctrl.copy()
    data.ctrl[:] = 0.0
    mujoco.mj_forward(model, data)
    f0 = data.qfrc_actuator.copy()
    gain = np.zeros((model.nv, nu))
    for i in range(nu):
        data.ctrl[:] = 0.0
        data.ctrl[i] = 1.0
        mujoco.mj_forward(model, data)
        gain[:, i] = data.qfrc_actuator - f0
    data.ctrl[:] = saved
    return f0, gain


def equilibrium_control(
    loaded: LoadedModel,
    qpos: np.ndarray,
    qvel: np.ndarray | None = None,
    act: np.ndarray | None = None,
) -> EquilibriumControl:
    """The control that holds ``(qpos, qvel)`` with zero acceleration, by inverse dynamics.

    Parameters
    ----------
    loaded : LoadedModel
    qpos : ndarray, shape (nq,)
    qvel : ndarray, shape (nv,), optional
        Default zero.
    act : ndarray, shape (na,), optional
        Default zero.

    Returns
    -------
    EquilibriumControl
        The least-squares control and the residual force the actuators cannot supply.
    """
    model = loaded.model
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    data.qvel[:] = 0.0 if qvel is None else qvel
    if model.na:
        data.act[:] = 0.0 if act is None else act
    mujoco.mj_forward(model, data)
    data.qacc[:] = 0.0
    mujoco.mj_inverse(model, data)
    # qfrc_inverse = M qacc + bias - passive - constraint: the generalized force that the
    # actuators (plus applied forces, zero here) must supply for zero acceleration.
    qfrc_inverse = data.qfrc_inverse.copy()
    f0, gain = _actuator_force_map(model, data)
    target = qfrc_inverse - f0
    if model.nu:
        ctrl, *_ = np.linalg.lstsq(gain, target, rcond=None)
    else:
        ctrl = np.zeros(0)
    names = loaded.input_names
    saturated = []
    for i in range(model.nu):
        if model.actuator_ctrllimited[i]:
            lo, hi = model.actuator_ctrlrange[i]
            if not lo <= ctrl[i] <= hi:
                saturated.append(names[i])
                ctrl[i] = float(np.clip(ctrl[i], lo, hi))
    residual = target - gain @ ctrl
    return EquilibriumControl(
        ctrl=_frozen(ctrl),
        qfrc_inverse=_frozen(qfrc_inverse),
        residual=_frozen(residual),
        saturated=tuple(saturated),
    )


@dataclass(frozen=True)
class SettledPoint:
    """Result of :func:`settle`: a state where contacts and actuators hold the model still.

    Attributes
    ----------
    qpos : ndarray, shape (nq,)
    equilibrium : EquilibriumControl
        Control and residual at ``qpos``.
    adjusted : dict of str to float
        The free coordinates and the values they were moved to.
    """

    qpos: np.ndarray
    equilibrium: EquilibriumControl
    adjusted: dict[str, float]


def settle(loaded: LoadedModel, qpos: np.ndarray, free: Sequence[str], span: float = 0.25) -> SettledPoint:
    """Move the named scalar joints until inverse dynamics needs no unactuated force.

    This generalizes the height search of MuJoCo's LQR recipe: a floating or planar base
    (Hopper's ``rootz``, ``rooty``) is lowered or tilted until the soft contacts carry the
    weight, while the actuators hold the remaining joints.

    Parameters
    ----------
    loaded : LoadedModel
    qpos : ndarray, shape (nq,)
        Starting configuration.
    free : sequence of str
        Names of hinge or slide joints whose coordinate may move.
    span : float, default 0.25
        Half-width of the initial coarse scan of each coordinate (m or rad).

    Returns
    -------
    SettledPoint
    """
    model = loaded.model
    number(span, "span", OperatingPointError, low=0.0, low_open=True, param="span")
    if isinstance(free, str) or not all(isinstance(name, str) for name in free):
        raise OperatingPointError(f"free={shown(free)}: expected a list of joint names", param="free")
    addrs = []
    for name in free:
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid < 0:
            raise OperatingPointError(f"no joint {name!r} to settle; joints: {', '.join(_qpos_names(model))}")
        addrs.append(int(model.jnt_qposadr[jid]))
    q0 = np.asarray(qpos, dtype=float).copy()

    def residual(z: np.ndarray) -> np.ndarray:
        q = q0.copy()
        q[addrs] = z
        return equilibrium_control(loaded, q).residual

    # Contacts give no gradient until they touch, so first scan each coordinate coarsely
    # (the sweep of MuJoCo's LQR recipe), then polish with least squares.
    z = q0[addrs].copy()
    offsets = np.linspace(-span, span, 201)
    for _ in range(3):
        for k in range(len(addrs)):
            trials = [z.copy() for _ in offsets]
            for t, off in zip(trials, offsets, strict=True):
                t[k] += off
            norms = [float(np.linalg.norm(residual(t))) for t in trials]
            z = trials[int(np.argmin(norms))]
    sol = least_squares(residual, z, xtol=1e-12, ftol=1e-12, gtol=1e-12)
    q = q0.copy()
    q[addrs] = sol.x
    return SettledPoint(
        qpos=_frozen(q),
        equilibrium=equilibrium_control(loaded, q),
        adjusted={name: float(v) for name, v in zip(free, sol.x, strict=True)},
    )
