"""What an env pays: its reward on a failing step, and its reward per surviving step.

The coaching wrapper's ``terminal`` view pays the agent's transition what the env would have paid
had that step failed (:func:`failure_reward`); its ``penalty`` view prices a takeover in steps of
the env's alive reward (:func:`alive_reward`). Both are read off Gymnasium's v5 sources.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym

from pidlab.errors import CoachingError


def _hopper_failure(reward: float, info: dict[str, Any]) -> float:
    # hopper_v5 / walker2d_v5: reward = (forward + is_healthy * healthy_reward) - ctrl_cost
    return (float(info["reward_forward"]) + 0.0) + float(info["reward_ctrl"])


def _idp_failure(reward: float, info: dict[str, Any]) -> float:
    # inverted_double_pendulum_v5: reward = healthy_reward * int(not terminated) - dist - vel
    return float(info["distance_penalty"]) + float(info["velocity_penalty"])


_FAILURE: dict[str, Callable[[float, dict[str, Any]], float]] = {
    "InvertedPendulum-v5": lambda reward, info: 0.0,  # reward = int(not terminated)
    "InvertedDoublePendulum-v5": _idp_failure,
    "Hopper-v5": _hopper_failure,
    "Walker2d-v5": _hopper_failure,
}


def failure_reward(env_id: str, reward: float, info: dict[str, Any]) -> float:
    """What the env would have paid for a step had that step failed (terminated).

    The reward without the alive bonus, from the step's own reward terms, computed as Gymnasium's
    v5 sources compute a failing step's reward (bit for bit): InvertedPendulum 0;
    InvertedDoublePendulum ``-distance_penalty - velocity_penalty``; Hopper and Walker2d
    ``forward_reward - ctrl_cost``.

    Parameters
    ----------
    env_id : str
        One of the four v5 envs with a model card.
    reward : float
        The step's reward.
    info : dict
        The step's info (its reward terms).

    Raises
    ------
    CoachingError
        An env whose failure reward pidlab does not know.
    """
    return _failure(env_id)(reward, info)


def _failure(env_id: str) -> Callable[[float, dict[str, Any]], float]:
    """The env's failure reward function.

    Raises
    ------
    CoachingError
        An env whose failure reward pidlab does not know.
    """
    fn = _FAILURE.get(env_id)
    if fn is None:
        raise CoachingError(
            f"view = 'terminal' needs the failure reward of {env_id}; it is known for {', '.join(_FAILURE)}"
        )
    return fn


def check_failure_reward(env_id: str) -> None:
    """Raise :class:`CoachingError` when the failure reward of ``env_id`` is unknown."""
    _failure(env_id)


def alive_reward(env: gym.Env) -> float:
    """The env's reward per surviving step (its ``healthy_reward``; 1 for InvertedPendulum).

    Raises
    ------
    CoachingError
        An env without one (set ``cost`` explicitly).
    """
    u = env.unwrapped
    value = getattr(u, "_healthy_reward", None)
    if value is None and env.spec is not None and env.spec.id == "InvertedPendulum-v5":
        value = 1.0
    if value is None:
        name = env.spec.id if env.spec is not None else type(u).__name__
        raise CoachingError(f"{name} has no alive reward to price a takeover in; set cost explicitly")
    return float(value)
