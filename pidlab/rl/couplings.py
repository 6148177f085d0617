"""Couplings: how the coach's knowledge reaches the agent, behind the one interface the trainer calls.

The coaching wrapper (:mod:`pidlab.rl.coaching`) is the coupling that acts during training: the
coach shields the agent (takeover, veto) and what the agent sees of it is the wrapper's ``view``.
A coupling here acts at the points the trainer offers:

``before_learning(trainer)``
    Once, when a new run starts, before the agent's first action (never again on resume: the
    checkpoint it leaves holds its result). It may step the training envs (every step is charged
    to the budget and logged through the trainer's accounts) and change the agent.

:func:`couplings_of` lists a run's couplings from its recipe; adding one touches no other.

Warm start (:class:`WarmStartCoupling`)
    The coach demonstrates on the training envs with noisy actions
    (:mod:`pidlab.rl.demonstrations`, kept in the run folder as ``demonstrations.npz``); with a
    ``warm_start`` table the agent is then behaviour-cloned on them and its critic warmed up
    (:mod:`pidlab.rl.cloning`). The agent alone is evaluated at env step 0 and right after the
    warm start; learning then goes on from the envs' current states (no reset).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Protocol

from pidlab.controller.spec import CoachSpec
from pidlab.files import write_json
from pidlab.rl.recipe import DemonstrationSettings, Recipe, WarmStart

RECORD = "warm_start.json"


class Coupling(Protocol):
    """A coupling the trainer calls before learning starts."""

    def before_learning(self, trainer: Any) -> None:
        """Act once before the agent's first action of a new run."""


@dataclass(frozen=True)
class WarmStartCoupling:
    """Coach demonstrations and, optionally, behaviour cloning on them (see the module docstring)."""

    demonstrations: DemonstrationSettings
    warm_start: WarmStart | None

    def before_learning(self, trainer: Any) -> None:
        """Evaluate the initial agent, demonstrate, clone, evaluate again, checkpoint."""
        from pidlab.rl import demonstrations as demo

        recipe, venv, model, c = trainer.recipe, trainer.venv, trainer.model, trainer.counters
        if c.evaluations == 0:
            trainer.evaluate()
        c.env_resets += recipe.n_envs  # collect() resets every env
        demos, last_obs, last_dones = demo.collect(
            venv, self.demonstrations.steps, self.demonstrations.noise, 7919 * recipe.seed + 17,
            lambda infos, more: trainer.on_step(infos, evaluating=more),
        )  # fmt: skip
        demo.save(trainer.run_dir / demo.FILE, demos)
        record: dict[str, Any] = {"demonstration_steps": len(demos), "noise": self.demonstrations.noise}
        if self.warm_start is not None:
            record["clone"] = asdict(self._clone(trainer, demos))
        model._last_obs, model._last_episode_starts = last_obs, last_dones
        trainer.envs_running = True
        record["agent_alone_after"] = trainer.evaluate().mean
        record["env_steps_after"] = c.env_steps
        write_json(trainer.run_dir / RECORD, record)
        trainer.checkpoint()

    def _clone(self, trainer: Any, demos: Any) -> Any:
        from pidlab.rl.cloning import clone

        recipe, venv = trainer.recipe, trainer.venv
        ws = self.warm_start or WarmStart()
        normalize_obs = getattr(venv, "normalize_obs", None) if getattr(venv, "norm_obs", False) else None
        normalize_reward = (
            getattr(venv, "normalize_reward", None) if getattr(venv, "norm_reward", False) else None
        )
        gamma = float(recipe.hyperparameters.get("gamma", 0.99))
        return clone(
            trainer.model, demos, normalize_obs or _identity, normalize_reward or _identity, ws.epochs,
            ws.critic, gamma, recipe.seed,
        )  # fmt: skip


def _identity(x: Any) -> Any:
    return x


def couplings_of(recipe: Recipe, spec: CoachSpec | None) -> list[Coupling]:
    """The couplings a new run of ``recipe`` calls before learning (none without a coach)."""
    c = recipe.coaching
    if spec is None or c.demonstrations is None:
        return []
    return [WarmStartCoupling(c.demonstrations, c.warm_start)]


def check_couplings(recipe: Recipe, spec: CoachSpec | None) -> None:
    """Refuse couplings that cannot run with this recipe and coach.

    Raises
    ------
    CoachingError
        Demonstrations or a blend without a coach; demonstrations as long as the budget; a warm
        start with an algorithm other than PPO.
    """
    from pidlab.errors import CoachingError

    c = recipe.coaching
    if c.blend is not None and spec is None:
        raise CoachingError("coaching.blend: blending the coach's action needs a coach; this run has none")
    if c.demonstrations is None:
        return
    if spec is None:
        raise CoachingError(
            "coaching.demonstrations: demonstrations need a coach, and this run has none (--coach none)"
        )
    if c.demonstrations.steps >= recipe.steps:
        raise CoachingError(
            f"coaching.demonstrations.steps = {c.demonstrations.steps}: expected fewer env steps than the "
            f"budget ({recipe.steps}), which they are charged to"
        )
    if c.warm_start is not None and recipe.algo != "ppo":
        raise CoachingError(
            f"coaching.warm_start with algo = {recipe.algo!r}: the warm start clones a PPO agent "
            "(its policy's mean and spread, and its critic); use algo = 'ppo'"
        )
