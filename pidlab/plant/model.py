"""Resolve a Gymnasium MuJoCo env id or an MJCF file into a compiled MuJoCo model.

The env's own ``MjModel`` and ``frame_skip`` are used, so that the linearization describes
exactly the system the RL agent acts on. Names for states and inputs are derived here, once.
"""

from __future__ import annotations

import contextlib
import difflib
import logging
import os
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from pidlab.checks import exists, path_argument, shown
from pidlab.errors import ModelCardError, ModelCompileError, UnknownEnvError
from pidlab.files import open_regular
from pidlab.plant.card import MJCF_SUFFIXES, ModelCard, card_for_mjcf, find_card
from pidlab.provenance import digest

_LOG = logging.getLogger("pidlab.mujoco")
MAX_MODEL_BYTES = 2**30
"""The largest MJCF or compiled model file pidlab hands MuJoCo (1 GiB)."""


def _log_mujoco_warning(text: str) -> None:
    """MuJoCo's run-time warnings (an unstable simulation, a full contact buffer) go to logging.

    Without a handler, MuJoCo appends them to ``MUJOCO_LOG.TXT`` in the working directory: a file
    in the user's folder that no pidlab command asked for. pidlab detects and reports the states
    behind them itself (non-finite observations terminate an episode), so they are logged at
    DEBUG level on the ``pidlab.mujoco`` logger.
    """
    _LOG.debug("MuJoCo: %s", text)


if mujoco.get_mju_user_warning() is None:  # keep a handler the user installed
    mujoco.set_mju_user_warning(_log_mujoco_warning)

_INTEGRATORS = {
    int(mujoco.mjtIntegrator.mjINT_EULER): "Euler",
    int(mujoco.mjtIntegrator.mjINT_RK4): "RK4",
    int(mujoco.mjtIntegrator.mjINT_IMPLICIT): "implicit",
    int(mujoco.mjtIntegrator.mjINT_IMPLICITFAST): "implicitfast",
}


@dataclass(frozen=True)
class LoadedModel:
    """A compiled MuJoCo model with what pidlab needs to know about how it is stepped.

    Attributes
    ----------
    model : mujoco.MjModel
        The compiled model (for an env id: the env's own model).
    source : str
        The env id, or the absolute path of the MJCF file.
    env_id : str or None
        The Gymnasium env id, or the ``env_id`` of the card that names the MJCF file (its
        ``[model]`` table); None for an MJCF file no card names.
    frame_skip : int
        MuJoCo steps per control period (the env's ``frame_skip``; the card's for an MJCF file
        it names; else 1).
    card : ModelCard or None
        The model card from ``models/`` (observation map, operating point, termination
        limits), when one exists for this env or names this MJCF file.
    """

    model: mujoco.MjModel
    source: str
    env_id: str | None
    frame_skip: int
    card: ModelCard | None

    @property
    def timestep(self) -> float:
        """MuJoCo's physics timestep in seconds."""
        return float(self.model.opt.timestep)

    @property
    def control_dt(self) -> float:
        """Control period in seconds: ``timestep * frame_skip``."""
        return self.timestep * self.frame_skip

    @property
    def integrator(self) -> str:
        """Name of the model's numerical integrator (e.g. ``"RK4"``)."""
        return _INTEGRATORS.get(int(self.model.opt.integrator), str(self.model.opt.integrator))

    def require_card(self) -> ModelCard:
        """The model card, which every stage after linearization needs.

        Raises
        ------
        ModelCardError
            The model has no card (a bare MJCF file, or an env without ``models/ENV.toml``).
        """
        if self.card is None:
            raise ModelCardError(f"{self.name}: has no model card; this step needs one ({self.card_hint})")
        return self.card

    @property
    def card_hint(self) -> str:
        """Where this model's card would be, and how to get one (for messages)."""
        if self.env_id is not None:
            return f"models/{self.env_id}.toml with its observation map and termination limits"
        return (
            f"none names this file: pidlab init {self.name} --env-id ID writes models/ID.toml, whose "
            "[model] mjcf names it"
        )

    @property
    def name(self) -> str:
        """Short display name: the env id, or the MJCF file name."""
        return self.env_id if self.env_id is not None else Path(self.source).name

    @property
    def position_names(self) -> tuple[str, ...]:
        """Names of the ``nv`` tangent-space position coordinates."""
        return dof_names(self.model)[0]

    @property
    def velocity_names(self) -> tuple[str, ...]:
        """Names of the ``nv`` generalized velocities."""
        return dof_names(self.model)[1]

    @property
    def activation_names(self) -> tuple[str, ...]:
        """Names of the ``na`` actuator activation states."""
        acts = actuator_names(self.model)
        return tuple(f"{acts[i]}_act" for i in range(self.model.nu) if self.model.actuator_actadr[i] >= 0)

    @property
    def state_names(self) -> tuple[str, ...]:
        """Names of the ``2*nv + na`` tangent-space states: positions, velocities, activations."""
        return self.position_names + self.velocity_names + self.activation_names

    @property
    def input_names(self) -> tuple[str, ...]:
        """Names of the ``nu`` actuators (controls)."""
        return actuator_names(self.model)


def joint_name(model: mujoco.MjModel, j: int) -> str:
    """Name of joint ``j``, or ``joint<j>`` when the MJCF leaves it unnamed."""
    return model.joint(j).name or f"joint{j}"


_FREE_SUFFIX = ("x", "y", "z", "rx", "ry", "rz")
_BALL_SUFFIX = ("rx", "ry", "rz")


def dof_names(model: mujoco.MjModel) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Names of the tangent position coordinates and of the velocities, one per dof.

    Hinge and slide joints give ``<joint>_pos`` / ``<joint>_vel``. Ball joints give
    ``<joint>_pos_rx`` ... (rotation vector in the joint frame), free joints
    ``<joint>_pos_x, _pos_y, _pos_z`` (world frame) and ``_pos_rx, _pos_ry, _pos_rz``
    (body frame), matching ``mj_differentiatePos``. The separator is ``_`` because
    python-control reserves ``.`` in signal names for ``system.signal``.

    Returns
    -------
    positions, velocities : tuple of str, each of length ``nv``
    """
    pos: list[str] = []
    vel: list[str] = []
    for j in range(model.njnt):
        name = joint_name(model, j)
        jtype = int(model.jnt_type[j])
        if jtype == int(mujoco.mjtJoint.mjJNT_FREE):
            suffixes: tuple[str, ...] = _FREE_SUFFIX
        elif jtype == int(mujoco.mjtJoint.mjJNT_BALL):
            suffixes = _BALL_SUFFIX
        else:
            pos.append(f"{name}_pos")
            vel.append(f"{name}_vel")
            continue
        pos.extend(f"{name}_pos_{s}" for s in suffixes)
        vel.extend(f"{name}_vel_{s}" for s in suffixes)
    return tuple(pos), tuple(vel)


def actuator_names(model: mujoco.MjModel) -> tuple[str, ...]:
    """Names of the actuators; an unnamed actuator is named after what it drives.

    Hopper's and Walker2d's actuators are unnamed in their MJCF, so they become
    ``thigh_joint``, ``leg_joint``, ... (the joint each one drives).
    """
    names: list[str] = []
    for i in range(model.nu):
        name = model.actuator(i).name
        if not name:
            target = int(model.actuator_trnid[i, 0])
            trn = int(model.actuator_trntype[i])
            obj = {
                int(mujoco.mjtTrn.mjTRN_JOINT): mujoco.mjtObj.mjOBJ_JOINT,
                int(mujoco.mjtTrn.mjTRN_JOINTINPARENT): mujoco.mjtObj.mjOBJ_JOINT,
                int(mujoco.mjtTrn.mjTRN_TENDON): mujoco.mjtObj.mjOBJ_TENDON,
                int(mujoco.mjtTrn.mjTRN_SITE): mujoco.mjtObj.mjOBJ_SITE,
                int(mujoco.mjtTrn.mjTRN_BODY): mujoco.mjtObj.mjOBJ_BODY,
            }.get(trn)
            name = (mujoco.mj_id2name(model, obj, target) if obj is not None else None) or ""
            if not name or name in names:
                name = f"actuator{i}"
        elif name in names:
            name = f"{name}#{i}"
        names.append(name)
    return tuple(names)


def _is_mjcf_path(target: str) -> bool:
    return target.lower().endswith(MJCF_SUFFIXES) or exists(target)



def model_digest(loaded: LoadedModel) -> str:
    """A digest of the compiled model (MuJoCo's binary form), its frame skip and its card."""
    m = loaded.model
    buf = np.zeros(mujoco.mj_sizeModel(m), dtype=np.uint8)
    mujoco.mj_saveModel(m, None, buf)
    return digest(buf.tobytes() + f"|{loaded.frame_skip}|{loaded.card!r}".encode(), 16)

def load_model(target: str | Path) -> LoadedModel:
    """Load a Gymnasium MuJoCo env id or an MJCF file.

    Parameters
    ----------
    target : str or Path
        A registered Gymnasium env id such as ``"InvertedPendulum-v5"``, or the path of an
        MJCF (``.xml``) or compiled (``.mjb``) model.

    Returns
    -------
    LoadedModel

    Raises
    ------
    UnknownEnvError
        ``target`` is neither an existing file nor a registered env id.
    ModelCompileError
        MuJoCo cannot load the file; the message carries MuJoCo's own text.
    """
    target = str(path_argument(target, "target", UnknownEnvError, what="an env id or an MJCF file's path"))
    if _is_mjcf_path(target):
        return _load_mjcf(Path(target))
    return _load_env(target)


def _check_model_file(path: Path) -> None:
    """Refuse a path MuJoCo should not see.

    Missing, a folder, unreadable (MuJoCo would warn), a named pipe or a device (MuJoCo would wait
    or read forever), or over :data:`MAX_MODEL_BYTES`.
    """
    if not path.exists():
        raise ModelCompileError(f"MJCF file {str(path)!r} does not exist; give an existing path")
    if path.is_dir():
        raise ModelCompileError(
            f"{str(path)!r} is a folder; give an MJCF file (.xml) or a compiled model (.mjb)"
        )
    try:
        os.close(open_regular(path, MAX_MODEL_BYTES))
    except OSError as exc:
        raise ModelCompileError(f"cannot read MJCF file {str(path)!r}: {exc.strerror or exc}") from None


@contextlib.contextmanager
def _mujoco_warnings() -> Iterator[list[str]]:
    """Collect MuJoCo's warnings instead of letting MuJoCo print them (its handler is restored)."""
    caught: list[str] = []
    old = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(caught.append)
    try:
        yield caught
    finally:
        mujoco.set_mju_user_warning(old)


def compile_mjcf(path: str | Path) -> mujoco.MjModel:
    """MuJoCo's compiled model of the MJCF (``.xml``, ``.mjcf``) or binary (``.mjb``) file ``path``.

    MuJoCo's warnings about a model that compiled are passed on as ``UserWarning``.

    Raises
    ------
    ModelCompileError
        A missing or unreadable file, or one MuJoCo cannot compile (with MuJoCo's message).
    """
    path = Path(path)
    _check_model_file(path)
    with _mujoco_warnings() as caught:
        try:
            if path.suffix.lower() == ".mjb":
                model = mujoco.MjModel.from_binary_path(str(path))
            else:
                model = mujoco.MjModel.from_xml_path(str(path))
        except Exception as exc:  # MuJoCo raises ValueError with its compiler message
            msg = " ".join(str(exc).split())
            raise ModelCompileError(f"MuJoCo could not compile {str(path)!r}: {msg}") from exc
    for text in caught:  # the model loaded: MuJoCo's warnings about it are worth passing on
        warnings.warn(f"MuJoCo: {text}", UserWarning, stacklevel=4)
    return model


def _load_mjcf(path: Path, card: ModelCard | None = None) -> LoadedModel:
    """The MJCF file ``path`` with its card: ``card``, else the card whose ``[model]`` names it."""
    model = compile_mjcf(path)
    card = card_for_mjcf(path) if card is None else card
    if card is None:
        return LoadedModel(model=model, source=str(path.resolve()), env_id=None, frame_skip=1, card=None)
    frame_skip = card.model.frame_skip if card.model is not None else 1  # a card found for a file names it
    card.check_against(model, frame_skip)
    return LoadedModel(
        model=model, source=str(path.resolve()), env_id=card.env_id, frame_skip=frame_skip, card=card
    )


def _load_env(text: str) -> LoadedModel:
    import gymnasium as gym

    from pidlab.plant.envs import GYM_PACKAGES_VAR, is_mujoco_env, resolve_env_id

    env_id = resolve_env_id(text)
    if env_id not in gym.registry:
        card = find_card(env_id)
        if card is not None and card.model is not None:  # a robot with a card and no env: its MJCF
            return _load_mjcf(Path(card.model.mjcf), card)
        close = difflib.get_close_matches(env_id, list(gym.registry), n=3, cutoff=0.5)
        hint = f"; did you mean {', '.join(close)}?" if close else ""
        raise UnknownEnvError(
            f"unknown env id or missing file {shown(text, 80)}: expected a registered MuJoCo env id "
            f"(e.g. InvertedPendulum-v5; your own: module:EnvId, or pidlab --gym-packages MODULE, or "
            f"{GYM_PACKAGES_VAR}) or the path of an MJCF file{hint}"
        )
    try:
        env = gym.make(env_id)
    except Exception as exc:  # e.g. deprecated versions that need mujoco-py
        msg = " ".join(str(exc).split())
        raise UnknownEnvError(f"cannot create env {env_id!r}: {msg}") from exc
    try:
        if not is_mujoco_env(env):
            raise UnknownEnvError(
                f"env {env_id!r} is not a MuJoCo env (its unwrapped env is a {type(env.unwrapped).__name__}, "
                "neither a gymnasium MujocoEnv nor an env with a mujoco.MjModel as its model); expected a "
                "MuJoCo env (e.g. InvertedPendulum-v5) or an MJCF file"
            )
        unwrapped = env.unwrapped
        model = unwrapped.model  # type: ignore[attr-defined]
        frame_skip = int(getattr(unwrapped, "frame_skip", 1))
    finally:
        env.close()
    card = find_card(env_id)
    own = getattr(unwrapped, "card", None)
    if card is None and isinstance(own, ModelCard):  # an env made from its card (pidlab.plant.card_env)
        if own.env_id != env_id:
            raise ModelCardError(f"{own.path}: env_id = {own.env_id!r}, the env is registered as {env_id}")
        card = own
    if card is not None:
        card.check_against(model, frame_skip)
    return LoadedModel(model=model, source=env_id, env_id=env_id, frame_skip=frame_skip, card=card)


def finite_or_raise(x: np.ndarray, what: str) -> np.ndarray:
    """Return ``x`` as float array, raising OperatingPointError if any entry is not finite."""
    from pidlab.errors import OperatingPointError

    arr = np.asarray(x, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise OperatingPointError(f"{what} has non-finite entries {arr.tolist()}; expected finite numbers")
    return arr
