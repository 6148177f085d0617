"""The predictive trigger's look-ahead: the env's next observation.

:class:`Predictor` (``predictor = "exact"``) steps a copy of the env's MuJoCo data: the answer is
exact, and it is an oracle no real robot has. :class:`ModelPredictor` (``predictor = "model"``)
forecasts from the env's discrete linear model and the current joint state
(:class:`pidlab.region.forecast.LinearForecast`, or :class:`~pidlab.region.forecast.LearnedForecast`
when the spec's measurement holds a learned correction); the whole box of the forecast's measured
error about it must lie in the rescue region (:func:`pidlab.region.forecast.margin_region`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np

from pidlab.errors import CoachingError
from pidlab.lookup import ForecastError
from pidlab.plant.card import ModelCard, parse_signal
from pidlab.plant.model import LoadedModel
from pidlab.plant.observation import CompiledCard
from pidlab.region.forecast import LearnedForecast, LinearForecast, learned_forecast, linear_forecast


def _refuse_action_wrappers(env: gym.Env, what: str) -> None:
    """The prediction needs the action the env will simulate: no action wrapper may change it."""
    inner: Any = env
    while isinstance(inner, gym.Wrapper):
        if isinstance(inner, gym.ActionWrapper):
            raise CoachingError(
                f"{what}: {type(inner).__name__} changes the agent's action on its way to the env; "
                "put it outside the coaching wrapper"
            )
        inner = inner.env


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
        _refuse_action_wrappers(env, "trigger 'predictive'")
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
        self._listeners: list[Callable[[Any, Any, np.ndarray], None]] = []
        self.terminal = False
        """Whether the env's termination rule ends the last predicted state (then no region holds it)."""

    def listen(self, listener: Callable[[Any, Any, np.ndarray], None]) -> None:
        """Call ``listener(data, action, obs)`` at each prediction (``data``: the env's data before it)."""
        self._listeners.append(listener)

    def predict(self, action: Any) -> np.ndarray:
        """The observation after ``action`` from the env's current state (the env is not touched)."""
        d = self._copy
        mujoco.mj_copyData(d, self._model, self._env.data)
        d.ctrl[:] = action
        mujoco.mj_step(self._model, d, nstep=self._frame_skip)
        self._predicted = True
        self._action = action
        obs = self._card.observe(d)
        self.terminal = self._card.terminated(d, obs)
        for listener in self._listeners:
            listener(self._env.data, action, obs)
        return obs

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


_FORECASTS: dict[str, LinearForecast] = {}


def observed_limits(card: ModelCard) -> tuple[tuple[int, Any], ...]:
    """The card's termination limits on a variable the observation holds as it is: (its index, the limit).

    A forecast observation can be tested against these; a limit on a site, or on a variable observed
    through a sine or cosine, is not among them.
    """
    source = {"pos": "qpos", "vel": "qvel"}
    plain = {(v.joint, v.source): i for i, v in enumerate(card.observation) if v.transform == "identity"}
    found = []
    for limit in card.termination:
        ref = parse_signal(limit.signal)
        i = None if ref is None else plain.get((ref.name, source.get(ref.kind, "")))
        if i is not None:
            found.append((i, limit))
    return tuple(found)


def forecast_of(loaded: LoadedModel) -> LinearForecast:
    """The linear forecast of a model at its card's operating point (made once per model source)."""
    from pidlab.linear.linearize import linearize

    key = str(loaded.source)
    if key not in _FORECASTS:
        _FORECASTS[key] = linear_forecast(linearize(loaded), loaded.require_card(), loaded.model)
    return _FORECASTS[key]


class ModelPredictor:
    """The observation one control period ahead, forecast by the env's discrete linear model.

    The current joint state (``qpos``, ``qvel``, ``act``: what a state estimator gives a real
    robot; on the paper's four envs the observation holds it, less the walkers' forward position,
    which the dynamics do not depend on) and the action go through
    :class:`~pidlab.region.forecast.LinearForecast`. Nothing is simulated; the columns no joint
    state gives are NaN. :meth:`execute` is the env's own step.

    Parameters
    ----------
    env : gymnasium.Env
        A Gymnasium MuJoCo env.
    loaded : LoadedModel
        The env's model (its card and its linear model).
    measured : ForecastError, optional
        The spec's forecast measurement: with a network (``model = "learned"``) the forecast is
        :class:`~pidlab.region.forecast.LearnedForecast`, else the linear one.

    Raises
    ------
    CoachingError
        ``env`` is not a MuJoCo env, or an action wrapper sits between the wrapper and the env, or
        the learned network does not fit this env's linear model.
    """

    def __init__(self, env: gym.Env, loaded: LoadedModel, measured: ForecastError | None = None) -> None:
        u: Any = env.unwrapped
        if not isinstance(getattr(u, "data", None), mujoco.MjData):
            raise CoachingError(
                "predictor 'model' needs a Gymnasium MuJoCo env (its data hold the joint state)"
            )
        _refuse_action_wrappers(env, "predictor 'model'")
        self._env = u
        self._model = loaded.model
        self.forecast: LinearForecast | LearnedForecast = forecast_of(loaded)
        if measured is not None and measured.network is not None:
            self.forecast = learned_forecast(self.forecast, measured.network, loaded.require_card())
        self._limits = observed_limits(loaded.require_card())
        self.terminal = False
        """Whether a termination limit on an observed variable ends the last forecast state."""
        self.inputs: np.ndarray | None = None
        """The linear model's inputs of the last forecast (its adaptive margins are asked of them)."""

    def predict(self, action: Any) -> np.ndarray:
        """The forecast observation after ``action`` (NaN where no joint state gives a column)."""
        d = self._env.data
        self.inputs = self.forecast.inputs(self._model, d.qpos, d.qvel, d.act, action)
        obs = self.forecast.from_inputs(self._model, self.inputs)
        ends = (not (np.isnan(obs[i]) or limit.healthy(float(obs[i]))) for i, limit in self._limits)
        self.terminal = any(ends)
        return obs

    def discard(self) -> None:
        """Nothing to forget: the forecast holds no simulated state."""

    def execute(self, step: Callable[[Any], tuple], action: Any) -> tuple:
        """``step(action)``: the env simulates as usual."""
        return step(action)
