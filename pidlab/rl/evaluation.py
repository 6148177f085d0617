"""The agent alone: coach off, deterministic policy, fixed evaluation seeds, episodes run together.

This is the score that says whether the agent learned. Training returns of a coached agent are
propped up by its coach; an evaluation here runs the bare Gymnasium env (its own time limit, no
coaching wrapper) and resets episode ``i`` with the same seed every time, so two evaluations
differ only because the policy did.

The episodes of one evaluation run side by side, one env each, with one batched forward pass of
the policy per step (:func:`evaluate_agent`). A matrix product's rounding depends on how many
rows it multiplies, so the policy is evaluated with a *batch-invariant* copy of its network
(:func:`batch_invariant`) whose linear layers multiply each row alone: an episode's actions, and
its return, are bit for bit those of SB3's ``predict`` on that episode's observations one by one,
the evaluation pidlab ran before episodes ran side by side.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from pidlab.plant.envs import make_env

Policy = Callable[[np.ndarray], np.ndarray]
"""``observations (n, obs_dim) -> actions (n, act_dim)``, deterministic and row by row independent."""

MAX_BATCH = 32
"""Most episodes run side by side (more seeds run in waves of this many)."""


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

    @property
    def env_steps(self) -> int:
        """Env steps the evaluation took (not charged to a training budget)."""
        return int(sum(self.lengths))


def evaluation_envs(env_id: str, episodes: int) -> list[gym.Env]:
    """The bare envs an evaluation of ``episodes`` episodes runs on side by side (at most :data:`MAX_BATCH`).

    Evaluation envs are made once per run and reset with each episode's seed.
    """
    return [make_env(env_id) for _ in range(max(1, min(episodes, MAX_BATCH)))]


def evaluate_agent(
    policy: Policy, envs: gym.Env | Sequence[gym.Env], seeds: Sequence[int]
) -> AgentEvaluation:
    """Run ``policy`` alone, one episode per seed, ``len(envs)`` episodes side by side.

    Parameters
    ----------
    policy : callable
        :data:`Policy`: a batch of observations (as the env returns them) to a batch of actions.
    envs : gymnasium.Env or sequence of them
        Bare envs of one id (no coaching wrapper), with their time limit. Episode ``i`` runs on
        ``envs[i % len(envs)]``, reset with ``seeds[i]``; one env runs the episodes one by one.
    seeds : sequence of int

    Returns
    -------
    AgentEvaluation
        The same whatever the number of envs, for a :func:`batch_invariant` policy.
    """
    pool = [envs] if isinstance(envs, gym.Env) else list(envs)
    returns: list[float] = []
    lengths: list[int] = []
    for start in range(0, len(seeds), len(pool)):
        wave = [int(s) for s in seeds[start : start + len(pool)]]
        r, n = _run_together(policy, pool[: len(wave)], wave)
        returns += r
        lengths += n
    return AgentEvaluation(tuple(int(s) for s in seeds), tuple(returns), tuple(lengths))


def _run_together(policy: Policy, envs: list[gym.Env], seeds: list[int]) -> tuple[list[float], list[int]]:
    """One episode per env, all stepped with one forward pass per step until each has ended."""
    obs = [env.reset(seed=seed)[0] for env, seed in zip(envs, seeds, strict=True)]
    totals = [0.0] * len(envs)
    steps = [0] * len(envs)
    running = list(range(len(envs)))
    while running:
        actions = policy(np.stack([obs[i] for i in running]))
        still = []
        for i, action in zip(running, actions, strict=True):
            obs[i], reward, terminated, truncated, _ = envs[i].step(action)
            totals[i] += float(reward)
            steps[i] += 1
            if not (terminated or truncated):
                still.append(i)
        running = still
    return totals, steps


def batch_invariant(policy: Any) -> Any:
    """A copy of an SB3 policy whose linear layers give every row the bits it gets alone.

    ``torch.nn.Linear`` multiplies with BLAS, whose blocking (and so the rounding of a row) varies
    with the number of rows. The copy's linear layers multiply each row on its own, as SB3's
    ``predict`` does for one observation; everything else (activations, squashing) is elementwise
    and runs on the whole batch. The weights are the policy's at the time of the copy; the copy
    is in evaluation mode and never trained.
    """
    import torch.nn as nn

    frozen = type(policy)(**policy._get_constructor_parameters())  # as SB3 rebuilds a saved policy
    frozen.load_state_dict(policy.state_dict())
    rowwise = _rowwise_linear_class()
    for module in frozen.modules():
        if type(module) is nn.Linear:
            module.__class__ = rowwise
    frozen.set_training_mode(False)
    return frozen


@functools.cache
def _rowwise_linear_class() -> type:
    """The batch-invariant ``nn.Linear`` (built on first use: importing torch takes seconds)."""
    import torch
    import torch.nn as nn
    import torch.nn.functional as F

    class RowwiseLinear(nn.Linear):
        """``nn.Linear`` applied to one row at a time (see :func:`batch_invariant`)."""

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            rows = x.reshape(-1, 1, x.shape[-1])
            out = [F.linear(row, self.weight, self.bias) for row in rows]
            return torch.cat(out).reshape(*x.shape[:-1], self.out_features)

    return RowwiseLinear


def sb3_policy(model: Any, obs_normalizer: Callable[[np.ndarray], np.ndarray] | None = None) -> Policy:
    """A deterministic, batch-invariant :data:`Policy` from an SB3 model, frozen as it is now.

    Parameters
    ----------
    model : stable_baselines3.common.base_class.BaseAlgorithm
    obs_normalizer : callable, optional
        ``VecNormalize.normalize_obs`` of the training env, when observations were normalized
        (its statistics are not updated by it).
    """
    import torch
    from gymnasium import spaces

    frozen = batch_invariant(model.policy)
    space = frozen.action_space
    box = isinstance(space, spaces.Box)

    def act(obs: np.ndarray) -> np.ndarray:
        x = obs_normalizer(obs) if obs_normalizer is not None else obs
        with torch.inference_mode():  # what SB3's predict does for a batch, without its checks
            tensor = torch.as_tensor(np.asarray(x, dtype=np.float32))
            actions = frozen._predict(tensor, deterministic=True).numpy().reshape((-1, *space.shape))
        if box and frozen.squash_output:
            return frozen.unscale_action(actions)
        return np.clip(actions, space.low, space.high) if box else actions

    return act
