"""The agent alone: coach off, deterministic policy, fixed evaluation seeds.

This is the score that says whether the agent learned. Training returns of a coached agent are
propped up by its coach; an evaluation here runs the bare Gymnasium env (its own time limit, no
coaching wrapper) and resets episode ``i`` with the same seed every time, so two evaluations
differ only because the policy did.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import gymnasium as gym
import numpy as np

Policy = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class AgentEvaluation:
    """Returns of the agent alone on fixed seeds.

    Attributes
    ----------
    seeds : tuple of int
    returns : tuple of float
    lengths : tuple of int
        Env steps per episode.
    """

    seeds: tuple[int, ...]
    returns: tuple[float, ...]
    lengths: tuple[int, ...]

    @property
    def mean(self) -> float:
        """Mean return."""
        return float(np.mean(self.returns))

    @property
    def std(self) -> float:
        """Standard deviation of the return (ddof=0)."""
        return float(np.std(self.returns))

    @property
    def mean_length(self) -> float:
        """Mean episode length, steps."""
        return float(np.mean(self.lengths))


def evaluate_agent(policy: Policy, env: gym.Env, seeds: Sequence[int]) -> AgentEvaluation:
    """Run ``policy`` alone on ``env``, one episode per seed.

    Parameters
    ----------
    policy : callable
        ``observation -> action`` (deterministic; observation as the env returns it).
    env : gymnasium.Env
        The bare env (no coaching wrapper), with its time limit.
    seeds : sequence of int

    Returns
    -------
    AgentEvaluation
    """
    returns, lengths = [], []
    for seed in seeds:
        obs, _ = env.reset(seed=int(seed))
        total, steps, done = 0.0, 0, False
        while not done:
            obs, reward, terminated, truncated, _ = env.step(policy(obs))
            total += float(reward)
            steps += 1
            done = bool(terminated or truncated)
        returns.append(total)
        lengths.append(steps)
    return AgentEvaluation(tuple(int(s) for s in seeds), tuple(returns), tuple(lengths))


def sb3_policy(model: object, obs_normalizer: Callable[[np.ndarray], np.ndarray] | None = None) -> Policy:
    """A deterministic :data:`Policy` from an SB3 model (and its frozen VecNormalize statistics).

    Parameters
    ----------
    model : stable_baselines3.common.base_class.BaseAlgorithm
    obs_normalizer : callable, optional
        ``VecNormalize.normalize_obs`` of the training env, when observations were normalized.
    """

    def act(obs: np.ndarray) -> np.ndarray:
        x = obs_normalizer(obs) if obs_normalizer is not None else obs
        action, _ = model.predict(x, deterministic=True)  # type: ignore[attr-defined]
        return np.asarray(action)

    return act
