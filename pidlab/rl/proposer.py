"""The coach as a proposer for SAC (IBRL-style): the critic picks the agent's action or the coach's.

IBRL (Hu et al. 2024) lets an imitation policy propose an action beside the RL actor's, and the
critic picks the better of the two, both for acting and in the TD target. With
``[coaching] proposer = { until }`` (:class:`pidlab.rl.recipe.Proposer`) the PID coach is that
imitation policy:

Acting
    At every agent step while training progress is below ``until``, the coach's proposal from the
    current state (:meth:`pidlab.rl.coaching.CoachingWrapper.proposal`) and the agent's sampled
    action are valued by SAC's critic (the smaller of the twin critics), and the better one runs as
    the agent's step (:class:`pidlab.rl.couplings.ProposerCoupling` sets the judge; ties go to the
    agent). From ``until`` on the agent acts alone. The critic judges only once learning has
    started.
What the buffer holds
    One transition per agent step, with the action that ran: the coach's proposal when it was
    picked (scaled as SB3 scales the agent's), the agent's own sample otherwise. Beside each, the
    coach's proposal from the transition's next observation (:attr:`ProposerSAC.next_proposals`).
The TD target
    While the coach proposes, the value of the next state is the larger of the target critics'
    values of the actor's sample and of the coach's proposal there, less the entropy term of the
    actor's sample: ``max(min Q'(s', a'), min Q'(s', a_coach(s'))) - alpha log pi(a'|s')``. From
    ``until`` on it is SAC's own. SAC's updates are otherwise SB3's, unchanged.
Gradient steps
    SB3's: one per agent step on the shipped recipes; a picked proposal is an agent step.
    ``learning_starts`` counts env steps, the coach's included (:mod:`pidlab.rl.envclock`), so the
    critic starts judging after that many env steps, not agent actions.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from pidlab.rl.envclock import CoachedSAC


class _Stash:
    """The coach's proposals at the next states of the batch being trained on (a torch tensor)."""

    proposals: Any = None


class ProposalBatches:
    """SB3's replay buffer, sampled as SB3 samples it, keeping the batch's next-state proposals."""

    def __init__(self, buffer: Any, proposals: np.ndarray, stash: _Stash) -> None:
        self.buffer, self.proposals, self.stash = buffer, proposals, stash

    def sample(self, batch_size: int, env: Any = None) -> Any:
        """``batch_size`` transitions drawn uniformly; their next-state proposals go to the stash."""
        upper = self.buffer.buffer_size if self.buffer.full else self.buffer.pos
        # numpy's global generator, as SB3 samples (SB3 seeds it with the run's seed)
        rows = np.random.randint(0, upper, size=batch_size)  # noqa: NPY002
        self.stash.proposals = torch.as_tensor(self.proposals[rows])
        return self.buffer._get_samples(rows, env=env)  # one env: its index is always 0


class ProposalTarget:
    """The target critics, answering with the better of the actor's action and the coach's proposal.

    SAC's update takes the minimum over what the target critics return, then subtracts the actor's
    entropy term; each critic's answer here is ``max(min Q'(s', a'), min Q'(s', a_coach))``.
    """

    def __init__(self, critic_target: Any, stash: _Stash) -> None:
        self.critic_target, self.stash = critic_target, stash

    def __call__(self, obs: Any, actions: Any) -> tuple[Any, ...]:
        """One answer per target critic, each the better of the two actions' (smaller-twin) values."""

        def low(a: Any) -> Any:
            return torch.min(torch.cat(self.critic_target(obs, a), dim=1), dim=1, keepdim=True).values

        best = torch.maximum(low(actions), low(self.stash.proposals))
        return (best,) * len(self.critic_target.q_networks)

    def parameters(self) -> Any:
        """The target critics' parameters (SAC's Polyak update moves them)."""
        return self.critic_target.parameters()


class ProposerSAC(CoachedSAC):
    """SAC whose buffer holds the actions that ran and whose target weighs the coach's proposals."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.proposing = False  # the last step's: the coach still proposes
        super().__init__(*args, **kwargs)

    def _setup_model(self) -> None:
        super()._setup_model()
        shape = (int(self.buffer_size), *(self.action_space.shape or ()))
        self.next_proposals = np.zeros(shape, dtype=np.float32)

    def _excluded_save_params(self) -> list[str]:
        """SB3's, and the proposals: a checkpoint keeps them in ``proposals.npz``, not in the model zip."""
        return [*super()._excluded_save_params(), "next_proposals"]

    def _store_transition(self, replay_buffer: Any, buffer_action: np.ndarray, new_obs: Any,
                          reward: np.ndarray, dones: np.ndarray,
                          infos: list[dict[str, Any]]) -> None:  # fmt: skip
        info = infos[0]
        pos = replay_buffer.pos
        if info.get("proposal_taken"):
            buffer_action = self._scaled(info["executed_action"])[None]
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)
        self.proposing = bool(info.get("proposing"))
        if "next_proposal" in info:
            self.next_proposals[pos] = self._scaled(info["next_proposal"])

    def _scaled(self, action: Any) -> np.ndarray:
        return np.clip(self.policy.scale_action(np.asarray(action, dtype=np.float64)), -1.0, 1.0)

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """SB3's updates; while the coach proposes, on a target that weighs its proposals."""
        if not self.proposing:
            super().train(gradient_steps, batch_size)
            return
        stash = _Stash()
        buffer, target = self.replay_buffer, self.critic_target
        self.replay_buffer = ProposalBatches(buffer, self.next_proposals, stash)  # type: ignore[assignment]
        self.critic_target = ProposalTarget(target, stash)  # type: ignore[assignment]
        try:
            super().train(gradient_steps, batch_size)
        finally:
            self.replay_buffer, self.critic_target = buffer, target
