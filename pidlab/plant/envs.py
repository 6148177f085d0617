"""Gymnasium envs by id, the user's own included: ``module:EnvId`` and the modules to import first.

pidlab makes every env through :func:`make_env`, so a user's env works wherever a shipped one
does, in every process pidlab starts:

- ``module:EnvId``, as ``gymnasium.make`` takes it: ``module`` is imported (it registers
  ``EnvId``), and the id is ``EnvId`` from then on (:func:`resolve_env_id`);
- the modules named by the environment variable ``PIDLAB_GYM_PACKAGES`` (comma-separated) are
  imported before an unknown id is refused, in this process and in every process it starts (pool
  workers, the tuner's jobs, Ray workers on this machine inherit the variable). The command
  line's ``pidlab --gym-packages MODULE[,MODULE]`` sets it, as the RL Baselines3 Zoo's
  ``--gym-packages`` does.

A MuJoCo env is recognised by what it is (:func:`is_mujoco_env`): a Gymnasium ``MujocoEnv``, or
an env whose ``model`` is a ``mujoco.MjModel``; never by the text of its entry point.
"""

from __future__ import annotations

import importlib
import os
import re
import sys
from collections.abc import Sequence
from typing import Any

from pidlab.checks import shown
from pidlab.errors import UnknownEnvError

GYM_PACKAGES_VAR = "PIDLAB_GYM_PACKAGES"
"""The environment variable naming the modules that register the user's envs (comma-separated)."""

MODULE_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$")
_IMPORTED: set[str] = set()


def gym_packages() -> tuple[str, ...]:
    """The modules named by :data:`GYM_PACKAGES_VAR`, in order (empty names dropped)."""
    return tuple(m.strip() for m in os.environ.get(GYM_PACKAGES_VAR, "").split(",") if m.strip())


def _project_on_path() -> None:
    """The project folder that started this process (``PIDLAB_PROJECT``) at the end of ``sys.path``."""
    root = os.environ.get("PIDLAB_PROJECT", "")
    if root and root not in sys.path:
        sys.path.append(root)


def import_module(name: str, named_by: str) -> None:
    """Import the module ``name`` that registers envs (once per process).

    Raises
    ------
    UnknownEnvError
        One line: ``name`` is no module name, or importing it fails (with the import's own message).
    """
    if name in _IMPORTED:
        return
    if not MODULE_NAME.fullmatch(name):
        raise UnknownEnvError(f"{named_by}: {shown(name, 80)} is not a module name (expected e.g. my_robots)")
    try:
        _project_on_path()
        importlib.import_module(name)
    except (Exception, SystemExit) as exc:  # the user's module: any failure is theirs to read, in one line
        msg = " ".join(str(exc).split()) or type(exc).__name__
        raise UnknownEnvError(f"{named_by}: cannot import {name!r}: {type(exc).__name__}: {msg}") from None
    _IMPORTED.add(name)


def add_gym_packages(modules: Sequence[str]) -> None:
    """Import ``modules`` now and add them to :data:`GYM_PACKAGES_VAR` for the processes started later.

    Raises
    ------
    UnknownEnvError
        A module that cannot be imported (nothing is added then).
    """
    for name in modules:
        import_module(name, "--gym-packages")
    known = list(gym_packages())
    os.environ[GYM_PACKAGES_VAR] = ",".join([*known, *(m for m in modules if m not in known)])


def resolve_env_id(text: str, remember: bool = False) -> str:
    """The registered id that ``text`` names, with the modules that register it imported.

    ``module:EnvId`` imports ``module`` and gives ``EnvId``; any other text is the id itself.
    With ``remember``, the module is also added to :data:`GYM_PACKAGES_VAR`, so the processes
    started later import it too (:func:`add_gym_packages`). When the id is not registered yet,
    the modules of :data:`GYM_PACKAGES_VAR` are imported first. Whether the id is then registered
    is for the caller to check.

    Raises
    ------
    UnknownEnvError
        A module that cannot be imported, or an empty id after ``module:``.
    """
    import gymnasium as gym

    module, sep, env_id = text.rpartition(":") if ":" in text else ("", "", text)
    if sep:
        if not env_id:
            raise UnknownEnvError(f"env {shown(text, 80)}: no env id after the module (expected module:Id)")
        import_module(module, f"env {shown(text, 80)}")
        if remember:
            add_gym_packages([module])
    if env_id not in gym.registry:
        for name in gym_packages():
            import_module(name, f"{GYM_PACKAGES_VAR} (from --gym-packages or pidlab.toml)")
    return env_id


def make_env(env_id: str, **kwargs: Any) -> Any:
    """``gymnasium.make(env_id, **kwargs)`` once the modules that register ``env_id`` are imported.

    Raises
    ------
    UnknownEnvError
        ``env_id`` is not registered but a model card names an MJCF file for it: training needs a
        registered env, and the line says how to scaffold one.
    """
    import gymnasium as gym

    return gym.make(check_trainable(resolve_env_id(env_id)), **kwargs)


def check_trainable(env_id: str) -> str:
    """``env_id`` unless it names a robot with no registered env (training needs one): one line then.

    An MJCF file's path, or an unregistered id whose model card names an MJCF file, is refused
    with the scaffold command that writes the env; any other id is left to the caller's checks.

    Raises
    ------
    UnknownEnvError
    """
    import gymnasium as gym

    if env_id in gym.registry:
        return env_id
    from pidlab.plant.card import MJCF_SUFFIXES

    if env_id.lower().endswith(MJCF_SUFFIXES):
        raise UnknownEnvError(
            f"{shown(env_id, 80)}: an MJCF file is no env; training needs a Gymnasium env: "
            f"pidlab init {shown(env_id, 80)} --env-id ID writes the module that registers one"
        )
    card = _card_with_model(env_id)
    if card is not None:
        raise UnknownEnvError(_needs_env(env_id, card))
    return env_id


def _needs_env(env_id: str, card: Any) -> str:
    return (
        f"{env_id}: no env is registered under this id (its model card {card.path} names only an "
        f"MJCF file); training needs a Gymnasium env: pidlab init {card.model.mjcf} --env-id "
        f"{env_id} writes the module that registers one"
    )


def make_coach_env(env_id: str, **kwargs: Any) -> Any:
    """The env the coach alone runs on: the registered ``env_id``, else its card's MJCF as a CardEnv.

    For a robot with a model card and no registered env (the card's ``[model]`` table names its
    MJCF file), a :class:`pidlab.plant.card_env.CardEnv` in a time limit of the card's
    ``max_episode_steps`` (or ``max_episode_steps=`` here); other ``kwargs`` go to the env.
    """
    import gymnasium as gym

    resolved = resolve_env_id(env_id)
    card = _card_with_model(resolved) if resolved not in gym.registry else None
    if card is None:
        return make_env(resolved, **kwargs)
    from gymnasium.wrappers import OrderEnforcing, TimeLimit

    from pidlab.plant.card_env import CardEnv

    steps = kwargs.pop("max_episode_steps", None) or card.model.max_episode_steps
    return TimeLimit(OrderEnforcing(CardEnv(card=card, **kwargs)), max_episode_steps=int(steps))


def _card_with_model(env_id: str) -> Any:
    """The model card of ``env_id`` when it names an MJCF file (its ``[model]`` table), else None."""
    from pidlab.plant.card import find_card

    card = find_card(env_id)
    return card if card is not None and card.model is not None else None


def is_mujoco_env(env: Any) -> bool:
    """Whether ``env`` (wrapped or not) runs MuJoCo: a ``MujocoEnv``, or its ``model`` is an ``MjModel``."""
    import mujoco
    from gymnasium.envs.mujoco.mujoco_env import MujocoEnv

    base = getattr(env, "unwrapped", env)
    return isinstance(base, MujocoEnv) or isinstance(getattr(base, "model", None), mujoco.MjModel)
