"""Warm start: behaviour cloning of a PPO agent on coach demonstrations, and its critic's warm-up.

Behaviour cloning maximizes the likelihood of the demonstrated (executed, noisy) actions under the
agent's Gaussian policy, ``-mean log pi(a_demo | s)`` through SB3's ``policy.evaluate_actions``: it
fits the policy's mean and its spread (``log_std``), so the cloned agent explores about as much as
the demonstrations' noise. The critic is warmed up on the same states: regressed on discounted
returns of the demonstrations' rewards, as normalized by the run's reward normalizer, bootstrapped
with the critic itself where an episode was cut off (time limit, or the end of the demonstrations)
and not where it ended in a fall. Without it, PPO's first advantages come from an untrained critic
and can undo the clone (the "unlearning dip" of RL fine-tuning from a cloned policy).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pidlab.errors import CoachingError
from pidlab.rl.demonstrations import Demonstrations

BATCH = 256
LEARNING_RATE = 1e-3


@dataclass(frozen=True)
class CloneReport:
    """What the warm start did.

    Attributes
    ----------
    samples : int
        Demonstration steps cloned.
    epochs : int
    policy_loss_first, policy_loss_last : float
        Mean negative log-likelihood of the demonstrated actions over the first and last epoch.
    value_loss_first, value_loss_last : float or None
        Mean squared error of the critic over its first and last epoch (None: no critic warm-up).
    """

    samples: int
    epochs: int
    policy_loss_first: float
    policy_loss_last: float
    value_loss_first: float | None
    value_loss_last: float | None


def discounted_returns(
    rewards: np.ndarray, ends: np.ndarray, cut: np.ndarray, bootstrap: np.ndarray, gamma: float
) -> np.ndarray:
    """Returns ``G_t = r_t + gamma G_{t+1}`` of one env's steps in order.

    Parameters
    ----------
    rewards : ndarray, shape (n,)
    ends : ndarray of bool, shape (n,)
        The step ended its episode by a termination (no bootstrap).
    cut : ndarray of bool, shape (n,)
        The step ended its episode without a termination (time limit, end of the data):
        ``G_t = r_t + gamma bootstrap_t``.
    bootstrap : ndarray, shape (n,)
        The value after step ``t`` where ``cut[t]``.
    gamma : float

    Examples
    --------
    >>> discounted_returns(np.array([1.0, 1.0, 1.0]), np.array([False, False, True]),
    ...                    np.array([False, False, False]), np.zeros(3), 0.5).tolist()
    [1.75, 1.5, 1.0]
    """
    out = np.empty_like(rewards, dtype=float)
    g = 0.0
    for t in range(len(rewards) - 1, -1, -1):
        if ends[t]:
            g = 0.0
        elif cut[t]:
            g = float(bootstrap[t])
        g = float(rewards[t]) + gamma * g
        out[t] = g
    return out


def _policy(model: Any) -> Any:
    policy = getattr(model, "policy", None)
    if policy is None or not hasattr(policy, "evaluate_actions"):
        raise CoachingError(
            "a warm start clones an actor-critic policy with evaluate_actions (PPO); "
            f"{type(model).__name__} has none"
        )
    return policy


def _tensors(policy: Any, demos: Demonstrations, normalize_obs: Any, seed: int) -> tuple[Any, Any, Any]:
    """The demonstrations as tensors on the policy's device, and the minibatches' generator.

    The observations are normalized with ``normalize_obs`` (the run's normalizer as it stands).
    """
    import torch

    obs = torch.as_tensor(np.asarray(normalize_obs(demos.obs), dtype=np.float32), device=policy.device)
    actions = torch.as_tensor(demos.actions, device=policy.device)
    return obs, actions, torch.Generator().manual_seed(seed)


def clone(model: Any, demos: Demonstrations, normalize_obs: Any, normalize_reward: Any, epochs: int,
          critic: bool, gamma: float, seed: int) -> CloneReport:  # fmt: skip
    """Behaviour-clone ``model``'s policy on ``demos`` (and warm up its critic); returns what it did.

    Parameters
    ----------
    model : stable_baselines3.PPO
    demos : Demonstrations
    normalize_obs, normalize_reward : callable
        The run's normalizers (identity when the run normalizes nothing).
    epochs : int
    critic : bool
    gamma : float
        The agent's discount.
    seed : int
        Seed of the minibatch order.
    """
    import torch

    policy = _policy(model)
    obs, actions, gen = _tensors(policy, demos, normalize_obs, seed)
    policy.set_training_mode(True)
    optimizer = torch.optim.Adam(policy.parameters(), lr=LEARNING_RATE)

    def policy_loss(idx: Any) -> Any:
        _, log_prob, _ = policy.evaluate_actions(obs[idx], actions[idx])
        return -log_prob.mean()

    first, last = _fit(policy_loss, optimizer, len(demos), epochs, gen)
    value_first = value_last = None
    if critic:
        rewards = np.asarray(normalize_reward(demos.rewards), dtype=float)
        value_first, value_last = _warm_critic(policy, obs, demos, rewards, gamma, epochs, gen)
    policy.set_training_mode(False)
    return CloneReport(len(demos), epochs, first, last, value_first, value_last)


def _fit(loss_of: Any, optimizer: Any, n: int, epochs: int, gen: Any) -> tuple[float, float]:
    """Minibatch passes of ``loss_of``; the mean loss of the first and the last pass."""
    import torch

    means = []
    for _ in range(epochs):
        perm = torch.randperm(n, generator=gen)
        total = 0.0
        for start in range(0, n, BATCH):
            idx = perm[start : start + BATCH]
            loss = loss_of(idx)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            total += float(loss.detach()) * len(idx)
        means.append(total / n)
    return means[0], means[-1]


def _warm_critic(policy: Any, obs: Any, demos: Demonstrations, rewards: np.ndarray, gamma: float,
                 epochs: int, gen: Any) -> tuple[float, float]:  # fmt: skip
    """Fit the value head to bootstrapped discounted returns, in rounds (the bootstrap uses the critic)."""
    import torch

    optimizer = torch.optim.Adam(policy.parameters(), lr=LEARNING_RATE)
    rounds = 3
    first = last = float("nan")
    for r in range(rounds):
        with torch.no_grad():
            values = policy.predict_values(obs).squeeze(-1).cpu().numpy()
        target = torch.as_tensor(
            _targets(demos, rewards, values, gamma), dtype=torch.float32, device=obs.device
        )

        def value_loss(idx: Any, target: Any = target) -> Any:
            return torch.nn.functional.mse_loss(policy.predict_values(obs[idx]).squeeze(-1), target[idx])

        a, last = _fit(value_loss, optimizer, len(demos), max(1, epochs // rounds), gen)
        first = a if r == 0 else first
    return first, last


def _targets(demos: Demonstrations, rewards: np.ndarray, values: np.ndarray, gamma: float) -> np.ndarray:
    """Per env, discounted returns, bootstrapped where an episode was cut off.

    The state after a cut-off step is not recorded (the env was reset, or the data end), so its
    value is taken as the critic's value of the cut-off step's own state.
    """
    out = np.empty(len(demos))
    for i in np.unique(demos.env_index):
        rows = np.flatnonzero(demos.env_index == i)
        cut = demos.truncated[rows].copy()
        cut[-1] = not demos.terminated[rows][-1]  # the data end inside an episode: bootstrap there
        out[rows] = discounted_returns(rewards[rows], demos.terminated[rows], cut, values[rows], gamma)
    return out


def keep_step(model: Any, demos: Demonstrations, normalize_obs: Any, weight: float, batches: int,
              seed: int) -> float:  # fmt: skip
    """Behaviour-cloning steps on the demonstrations during RL (the demonstrations kept in the updates).

    ``batches`` minibatches of :data:`BATCH` demonstration steps, each a gradient step of
    ``weight * -mean log pi(a_demo | s)`` with the policy's own optimizer (DAPG's augmented
    gradient, taken after PPO's update rather than inside it). The observations are normalized with
    the run's normalizer as it stands.

    Parameters
    ----------
    model : stable_baselines3.PPO
    demos : Demonstrations
    normalize_obs : callable
    weight : float
        The term's weight, > 0.
    batches : int
        Gradient steps.
    seed : int
        Seed of the minibatches' draw.

    Returns
    -------
    float
        The mean negative log-likelihood over the steps (before weighting).
    """
    import torch

    policy = _policy(model)
    obs, actions, gen = _tensors(policy, demos, normalize_obs, seed)
    policy.set_training_mode(True)
    total = 0.0
    for _ in range(batches):
        idx = torch.randint(len(demos), (min(BATCH, len(demos)),), generator=gen)
        _, log_prob, _ = policy.evaluate_actions(obs[idx], actions[idx])
        loss = -log_prob.mean()
        policy.optimizer.zero_grad()
        (weight * loss).backward()
        policy.optimizer.step()
        total += float(loss.detach())
    policy.set_training_mode(False)
    return total / max(batches, 1)
