"""The predictive trigger's look-ahead: the env's next observation, from a copy of its MuJoCo data."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np

from pidlab.errors import CoachingError
from pidlab.plant.card import ModelCard
from pidlab.plant.observation import CompiledCard


class Predictor:
    """The observation one control period ahead, stepped on a copy of the env's MuJoCo data.

    What ``env.step(action)`` would observe, bit for bit: the action goes into ``ctrl`` as
    Gymnasium's ``MujocoEnv.do_simulation`` puts it, ``frame_skip`` MuJoCo steps follow, and the
    model card's compiled observation reads the copy. (``do_simulation`` also calls
    ``mj_rnePostConstraint``, which fills ``cacc`` and ``cfrc_*`` only; no card observes them.)
    :meth:`execute` then runs the env's step with the predicted data copied in instead of
    simulating the same control period a second time.

    Parameters
    ----------
    env : gymnasium.Env
        A Gymnasium MuJoCo env (``unwrapped`` has ``model``, ``data``, ``frame_skip``).
    card : ModelCard
        The env's model card.

    Raises
    ------
    CoachingError
        ``env`` is not a MuJoCo env.
    """

    def __init__(self, env: gym.Env, card: ModelCard) -> None:
        u: Any = env.unwrapped
        model, data, skip = (getattr(u, k, None) for k in ("model", "data", "frame_skip"))
        mujoco_env = isinstance(model, mujoco.MjModel) and isinstance(data, mujoco.MjData)
        if not mujoco_env or not isinstance(skip, int):
            raise CoachingError("trigger 'predictive' needs a Gymnasium MuJoCo env (model, data, frame_skip)")
        inner: Any = env
        while isinstance(inner, gym.Wrapper):  # the prediction needs the action the env will simulate
            if isinstance(inner, gym.ActionWrapper):
                raise CoachingError(
                    f"trigger 'predictive': {type(inner).__name__} changes the agent's action on its way to "
                    "the env; put it outside the coaching wrapper"
                )
            inner = inner.env
        self._env = u
        self._model = model
        self._copy = mujoco.MjData(model)
        self._frame_skip = skip
        self._card = CompiledCard(card, model)
        # Gymnasium's MujocoEnv simulates in _step_mujoco_simulation(ctrl, n_frames); without it
        # (another env class) the action is simulated again by the env itself
        self._copy_back = hasattr(type(u), "_step_mujoco_simulation")
        self._predicted = False
        self._action: Any = None

    def predict(self, action: Any) -> np.ndarray:
        """The observation after ``action`` from the env's current state (the env is not touched)."""
        d = self._copy
        mujoco.mj_copyData(d, self._model, self._env.data)
        d.ctrl[:] = action
        mujoco.mj_step(self._model, d, nstep=self._frame_skip)
        self._predicted = True
        self._action = action
        return self._card.observe(d)

    def discard(self) -> None:
        """Forget the last prediction (its action was vetoed: the env moves on without it)."""
        self._predicted = False

    def execute(self, step: Callable[[Any], tuple], action: Any) -> tuple:
        """``step(action)`` (the env's step) on the data :meth:`predict` computed for ``action``.

        The env's simulation is replaced, for this call, by copying the predicted data in and
        completing it as ``do_simulation`` does (``mj_rnePostConstraint``): the env's data end up
        bit for bit as if it had simulated, at the cost of a copy. Anything else (another action,
        another number of frames) is simulated by the env as usual.
        """
        if not (self._copy_back and self._predicted):
            return step(action)
        self._env.__dict__["_step_mujoco_simulation"] = self._simulate
        try:
            return step(action)
        finally:
            del self._env.__dict__["_step_mujoco_simulation"]
            self._predicted = False

    def _simulate(self, ctrl: Any, n_frames: int) -> None:
        u, model, d = self._env, self._model, self._copy
        # the env passes the agent's action down unchanged (gym.make's wrappers do): the same object
        same = ctrl is self._action or np.array_equal(d.ctrl, ctrl)
        if not (self._predicted and n_frames == self._frame_skip and same):
            type(u)._step_mujoco_simulation(u, ctrl, n_frames)
            return
        self._predicted = False
        mujoco.mj_copyData(u.data, model, d)
        mujoco.mj_rnePostConstraint(model, u.data)
