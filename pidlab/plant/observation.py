"""Evaluate a model card on MuJoCo data: observations, named signals, termination.

These functions reproduce the Gymnasium env's ``_get_obs`` and termination rule from the
card alone, so a test can hold the card to the env, and later stages can map MuJoCo states
to observation variables (and back, through the linearized output matrix).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from pidlab.errors import UnknownSignalError
from pidlab.plant.card import ModelCard, ObservationVariable, TerminationLimit, parse_signal


def variable_address(model: mujoco.MjModel, var: ObservationVariable) -> int:
    """Where ``var`` sits in its source array (``qpos`` address, else the joint's dof address)."""
    jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, var.joint)
    if var.source == "qpos":
        return int(model.jnt_qposadr[jid])
    return int(model.jnt_dofadr[jid])


def observe(card: ModelCard, model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    """The Gymnasium observation, computed from ``data`` through the card's map.

    Parameters
    ----------
    card : ModelCard
    model : mujoco.MjModel
    data : mujoco.MjData
        After ``mj_forward`` or ``mj_step`` (``qfrc_constraint`` must be current).

    Returns
    -------
    obs : ndarray, shape (n_obs,)
    """
    out = np.empty(len(card.observation))
    for i, var in enumerate(card.observation):
        arr = getattr(data, var.source)
        value = float(arr[variable_address(model, var)])
        if var.transform == "sin":
            value = float(np.sin(value))
        elif var.transform == "cos":
            value = float(np.cos(value))
        if var.clip is not None:
            value = float(np.clip(value, var.clip[0], var.clip[1]))
        out[i] = value
    return out


def observe_at(card: ModelCard, model: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
    """The observation at a state ``(qpos, qvel)`` (fresh ``MjData``, ``mj_forward``)."""
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    data.qvel[:] = qvel
    mujoco.mj_forward(model, data)
    return observe(card, model, data)


def signal_value(model: mujoco.MjModel, data: mujoco.MjData, signal: str) -> float:
    """Value of a named state signal: ``<joint>_pos``, ``<joint>_vel`` or ``site:<s>:x|y|z``.

    Raises
    ------
    UnknownSignalError
    """
    ref = parse_signal(signal)
    if signal.startswith("site:"):
        sid = -1 if ref is None else mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, ref.name)
        if ref is None or sid < 0:
            raise UnknownSignalError(f"no site signal {signal!r}; expected site:<site>:x|y|z")
        return float(data.site_xpos[sid][ref.axis])
    jid = -1 if ref is None else mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, ref.name)
    if ref is None or jid < 0:
        raise UnknownSignalError(f"no state signal {signal!r}; expected <joint>_pos or <joint>_vel")
    if ref.kind == "pos":
        return float(data.qpos[model.jnt_qposadr[jid]])
    return float(data.qvel[model.jnt_dofadr[jid]])


@dataclass(frozen=True)
class TerminationCheck:
    """Which termination limits a state violates.

    Attributes
    ----------
    terminated : bool
    violated : tuple of TerminationLimit
    values : tuple of float
        The signal value of each violated limit.
    nonfinite : bool
        The observation held NaN or inf.
    """

    terminated: bool
    violated: tuple[TerminationLimit, ...]
    values: tuple[float, ...]
    nonfinite: bool


def check_termination(card: ModelCard, model: mujoco.MjModel, data: mujoco.MjData) -> TerminationCheck:
    """Apply the card's termination rule to ``data`` (as the env does after a step)."""
    violated: list[TerminationLimit] = []
    values: list[float] = []
    for limit in card.termination:
        v = signal_value(model, data, limit.signal)
        if not limit.healthy(v):
            violated.append(limit)
            values.append(v)
    nonfinite = card.terminate_on_nonfinite and not bool(np.all(np.isfinite(observe(card, model, data))))
    return TerminationCheck(
        terminated=bool(violated) or nonfinite,
        violated=tuple(violated),
        values=tuple(values),
        nonfinite=nonfinite,
    )


class CompiledCard:
    """A model card's observation map and termination rule, compiled to index arrays.

    Same results as :func:`observe` and :func:`check_termination`, without name lookups per
    call: the form used in simulation loops (regions of attraction, rollouts).
    """

    def __init__(self, card: ModelCard, model: mujoco.MjModel) -> None:
        self.card = card
        n = len(card.observation)
        self._plain = _gather_index(card, model)
        self._source = [v.source for v in card.observation]
        self._addr = np.array([variable_address(model, v) for v in card.observation])
        self._sin = np.array([v.transform == "sin" for v in card.observation])
        self._cos = np.array([v.transform == "cos" for v in card.observation])
        self._lo = np.array([v.clip[0] if v.clip else -np.inf for v in card.observation])
        self._hi = np.array([v.clip[1] if v.clip else np.inf for v in card.observation])
        self._groups = {s: np.array([i for i in range(n) if self._source[i] == s]) for s in set(self._source)}
        limits = []
        for limit in card.termination:
            ref = parse_signal(limit.signal)
            if ref is None:  # a parsed card's limits parse (pidlab.plant.card._check_signal)
                raise UnknownSignalError(f"no state signal {limit.signal!r}")
            if ref.kind == "site":
                sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, ref.name)
                limits.append(("site", sid, ref.axis, limit))
            else:
                jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, ref.name)
                adr = int(model.jnt_qposadr[jid]) if ref.kind == "pos" else int(model.jnt_dofadr[jid])
                limits.append((ref.kind, adr, 0, limit))
        self._limits = limits

    def observe(self, data: mujoco.MjData) -> np.ndarray:
        """The observation (as :func:`observe`): one gather when no variable is a sine or cosine."""
        if self._plain is not None:
            sources, flat, clipped = self._plain
            parts = [getattr(data, k) for k in sources]
            raw = parts[0] if len(parts) == 1 else np.concatenate(parts)
            return np.clip(raw[flat], self._lo, self._hi) if clipped else raw[flat]
        out = np.empty(len(self._addr))
        for source, idx in self._groups.items():
            out[idx] = getattr(data, source)[self._addr[idx]]
        out = np.where(self._sin, np.sin(out), np.where(self._cos, np.cos(out), out))
        return np.clip(out, self._lo, self._hi)

    def terminated(self, data: mujoco.MjData, obs: np.ndarray | None = None) -> bool:
        """Whether the env would terminate (as :func:`check_termination`).

        ``obs``: :meth:`observe` of ``data`` when the caller has it (not computed again).
        """
        for kind, a, b, limit in self._limits:
            if kind == "site":
                v = float(data.site_xpos[a, b])
            elif kind == "pos":
                v = float(data.qpos[a])
            else:
                v = float(data.qvel[a])
            if not limit.healthy(v):
                return True
        if not self.card.terminate_on_nonfinite:
            return False
        return not bool(np.all(np.isfinite(self.observe(data) if obs is None else obs)))


_SOURCE_SIZE = {"qpos": "nq", "qvel": "nv", "qfrc_constraint": "nv"}


def _gather_index(card: ModelCard, model: mujoco.MjModel) -> tuple[tuple[str, ...], np.ndarray, bool] | None:
    """``(sources, flat, clipped)``: the observation as one index into the sources laid end to end.

    None when a variable is a sine or cosine (the general path applies the transforms).
    """
    if any(v.transform in ("sin", "cos") for v in card.observation):
        return None
    sources = tuple(dict.fromkeys(v.source for v in card.observation))
    sizes = [int(getattr(model, _SOURCE_SIZE[k])) for k in sources]
    base = dict(zip(sources, np.cumsum([0, *sizes]), strict=False))
    flat = np.array([int(base[v.source]) + variable_address(model, v) for v in card.observation])
    return sources, flat, any(v.clip for v in card.observation)
