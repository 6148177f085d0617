"""The coach's transitions in a replay buffer of their own, for SAC (PVP-style off-policy coaching).

A takeover's coach steps are real env steps. Under every other coupling they are hidden from an
off-policy agent and lost. With ``[coaching] coach_buffer`` (:class:`pidlab.rl.recipe.CoachBuffer`)
they are kept, and the agent learns from them (PVP, Peng et al. 2023, keeps the teacher's
transitions in a buffer of their own and draws half of each batch from it).

What enters each buffer
    *The agent's buffer* (SB3's ``replay_buffer``) holds exactly what SB3 stores for every agent
    step: ``(s, a, r, s', done)`` with the agent's own action ``a``. What ``r``, ``s'`` and
    ``done`` are at a takeover is the wrapper's ``view``: under ``terminal`` the step that
    triggered a takeover, or whose action was vetoed, ends the agent's episode with the env's
    failure reward and no bootstrap, so the critic learns that action as a failure; under
    ``penalty`` it pays the takeover's cost. That transition is the *label* of the agent's action
    that the coach overruled. ``hidden`` labels nothing (the agent's transition would carry the
    coach's steps as if its action had done them) and is refused.

    *The coach's buffer* (:attr:`CoachReplaySAC.coach_buffer`) holds one transition per coach step
    of a takeover or a veto: ``(s, a_coach, r, s', done)``, where ``a_coach`` is the action the coach
    executed (inside the action space, scaled as SB3 scales the agent's), ``r`` the env's reward,
    and ``done`` the env's own end (a fall ends it with no bootstrap; the time limit is a timeout,
    bootstrapped, as SB3 does for the agent). The coach's demonstrations before learning
    (``[coaching] demonstrations``) enter it too, one transition per demonstration step with the
    executed, noisy action (:meth:`CoachReplaySAC.keep_demonstrations`). Roll-ins do not.

Batches
    Each gradient step draws ``round(share * batch_size)`` transitions from the coach's buffer and
    the rest from the agent's (all from one buffer while the other is empty), uniformly within
    each; observations and rewards are normalized by the training envs' ``VecNormalize``
    at sampling time, as SB3 does for its own buffer.

Gradient steps per env step
    Every env step buys the same number of gradient steps, the agent's and the coach's alike:
    ``gradient_steps / (train_freq * n_envs)`` of the recipe (``gradient_steps = -1``: one). SB3
    buys them for the agent's actions; this class adds the coach's steps, less one per vetoed
    agent action (SB3 bought that action a gradient step, and it was no env step), after the
    agent's updates of the same rollout. Coach steps of the rollout that the budget ends are not
    spent, as SB3's own are not. ``learning_starts`` counts env steps, the coach's included:
    SB3's ``num_timesteps`` counts env steps here (the coach's steps are added, and a vetoed agent
    action, which never ran, is not), so it equals the run's env steps. Uncoached SAC makes the
    same number of gradient steps per env step, so a comparison of the two is at the same
    update-to-data ratio. Demonstration steps count the same way, and they take the place of SAC's
    random warm-up: ``learning_starts`` is their number (:func:`pidlab.rl.train.new_model`), so
    learning starts right after them. A coupling without a coach buffer (``rescue-terminal``) makes
    gradient steps only for the agent's steps.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.type_aliases import ReplayBufferSamples

COUNTERS = ("coach_transitions", "coach_counted", "coach_updates")
"""The coach buffer's counters that a checkpoint keeps (in ``state.json``'s ``sb3`` table)."""


def updates_per_env_step(gradient_steps: int, train_freq: int, n_envs: int) -> float:
    """Gradient steps that one env step buys: ``gradient_steps / (train_freq * n_envs)`` (-1: one)."""
    return 1.0 if gradient_steps < 0 else gradient_steps / (train_freq * n_envs)


def coach_rows(share: float, batch_size: int, agent_size: int, coach_size: int) -> int:
    """Rows of a batch drawn from the coach's buffer: ``round(share * batch_size)`` (halves up).

    All of them while the agent's buffer is empty, none while the coach's is.
    """
    if coach_size == 0:
        return 0
    if agent_size == 0:
        return batch_size
    return min(int(share * batch_size + 0.5), batch_size)


class MixedBatches:
    """Batches from the agent's and the coach's buffers, in the share :func:`coach_rows` gives.

    It stands in for SB3's replay buffer while SAC trains (only ``sample`` is called there).
    """

    def __init__(self, agent: Any, coach: Any, share: float) -> None:
        self.agent, self.coach, self.share = agent, coach, float(share)
        self.coach_rows_drawn = 0

    def sample(self, batch_size: int, env: Any = None) -> Any:
        """``batch_size`` transitions: the agent's rows first, then the coach's."""
        n = coach_rows(self.share, batch_size, self.agent.size(), self.coach.size())
        self.coach_rows_drawn += n
        parts = [b.sample(k, env=env) for b, k in ((self.agent, batch_size - n), (self.coach, n)) if k > 0]
        if len(parts) == 1:
            return parts[0]
        joined = [None if f[0] is None else torch.cat(f) for f in zip(*parts, strict=True)]
        return ReplayBufferSamples(*joined)  # type: ignore[arg-type]  # discounts may be None


class CoachReplaySAC(SAC):
    """SAC that keeps the coach's transitions and trains on both buffers (module docstring).

    Parameters
    ----------
    coach_share : float
        Fraction of each batch from the coach's buffer, in [0, 1].
    coach_buffer_size : int, optional
        Capacity of the coach's buffer (default: ``buffer_size``).
    **kwargs
        SB3's ``SAC`` arguments.
    """

    def __init__(self, *args: Any, coach_share: float = 0.5, coach_buffer_size: int | None = None,
                 **kwargs: Any) -> None:  # fmt: skip
        self.coach_share = float(coach_share)
        self._coach_size = coach_buffer_size
        self.coach_transitions = 0  # coach steps stored
        # env steps after learning_starts that SB3 does not buy gradient steps for: the coach's,
        # less one per vetoed agent action (SB3 buys it one, and it was no env step)
        self.coach_counted = 0
        self.coach_updates = 0  # gradient steps made for them
        super().__init__(*args, **kwargs)

    def _setup_model(self) -> None:
        super()._setup_model()
        self.coach_buffer = ReplayBuffer(
            int(self._coach_size or self.buffer_size), self.observation_space, self.action_space,
            device=self.device, n_envs=1, optimize_memory_usage=False, handle_timeout_termination=True,
        )  # fmt: skip

    def _excluded_save_params(self) -> list[str]:
        """SB3's, and the coach's buffer: a checkpoint keeps it in ``coach_buffer.npz``.

        SB3's ``save`` would otherwise pickle the whole buffer, at its capacity, into the model
        archive (64 MB of 69.5 in an InvertedDoublePendulum checkpoint), which pidlab never reads.
        """
        return [*super()._excluded_save_params(), "coach_buffer"]

    def _store_transition(self, replay_buffer: Any, buffer_action: np.ndarray, new_obs: Any,
                          reward: np.ndarray, dones: np.ndarray,
                          infos: list[dict[str, Any]]) -> None:  # fmt: skip
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)
        for info in infos:
            vetoed = bool(info.get("vetoed"))
            if vetoed:  # SB3 counted the agent's action, which never ran, and buys it a gradient step
                self.num_timesteps -= 1
                self.coach_counted -= int(self.num_timesteps >= self.learning_starts)
            rows = info.get("coach_transitions")
            if rows is not None:
                self._keep(rows)

    def _keep(self, rows: dict[str, np.ndarray]) -> None:
        """Add a step's coach transitions; count them as env steps that buy gradient steps."""
        actions = np.clip(self.policy.scale_action(rows["actions"]), -1.0, 1.0)
        for i in range(len(rows["rewards"])):
            terminated, truncated = bool(rows["terminated"][i]), bool(rows["truncated"][i])
            self.coach_buffer.add(
                rows["obs"][i][None], rows["next_obs"][i][None], actions[i][None],
                np.array([rows["rewards"][i]]), np.array([terminated or truncated]),
                [{"TimeLimit.truncated": truncated and not terminated}],
            )  # fmt: skip
            self.coach_transitions += 1
            self.num_timesteps += 1
            self.coach_counted += int(self.num_timesteps > self.learning_starts)

    def keep_demonstrations(self, demos: Any) -> int:
        """Keep the coach's demonstration steps (:mod:`pidlab.rl.demonstrations`) as coach transitions.

        Each is an env step of the run: it counts towards ``learning_starts`` and, past it, buys
        gradient steps as any coach step does. Returns the number kept.

        Raises
        ------
        CoachingError
            The demonstrations hold no next observations (a file written before they were kept).
        """
        from pidlab.errors import CoachingError

        if demos.next_obs is None:
            raise CoachingError("demonstrations without next observations cannot enter a replay buffer")
        fields = ("obs", "actions", "rewards", "next_obs", "terminated", "truncated")
        rows = {k: getattr(demos, k) for k in fields}
        self._keep(rows)
        return len(demos)

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """SB3's updates for the agent's steps, plus those the coach's steps bought."""
        freq = int(self.train_freq.frequency)  # type: ignore[union-attr]  # a TrainFreq by now
        rate = updates_per_env_step(int(self.gradient_steps), freq, int(self.n_envs))
        extra = max(int(self.coach_counted * rate) - self.coach_updates, 0)
        self.coach_updates += extra
        agent = self.replay_buffer
        self.replay_buffer = MixedBatches(agent, self.coach_buffer, self.coach_share)  # type: ignore[assignment]
        try:
            super().train(gradient_steps + extra, batch_size)
        finally:
            self.replay_buffer = agent

    def counters(self) -> dict[str, int]:
        """The coach buffer's counters, for a checkpoint."""
        return {k: int(getattr(self, k)) for k in COUNTERS}

    def restore_counters(self, saved: dict[str, Any]) -> None:
        """Set the counters a checkpoint kept (a missing or bad one reads 0)."""
        for k in COUNTERS:
            value = saved.get(k, 0)
            setattr(self, k, value if type(value) is int and value >= 0 else 0)
