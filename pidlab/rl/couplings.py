"""Couplings: how the coach's knowledge reaches the agent, behind the one interface the trainer calls.

The coaching wrapper (:mod:`pidlab.rl.coaching`) is the coupling that acts during training: the
coach shields the agent (takeover, veto) and what the agent sees of it is the wrapper's ``view``.
A coupling here acts at the points the trainer offers (:class:`Coupling`, each a no-op by default):

``before_learning(trainer)``
    Once, when a new run starts, before the agent's first action (never again on resume: the
    checkpoint it leaves holds its result). It may step the training envs (every step is charged
    to the budget and logged through the trainer's accounts) and change the agent.
``on_session(trainer)``
    At the start of every session (new or resumed), after ``before_learning``, before learning.
``after_evaluation(trainer, evaluation)``
    After each evaluation of the agent alone.
``before_rollout(trainer)``
    Before each of the agent's rollouts (after the update that ended the previous one), before
    the trainer's checkpoint there, so that a checkpoint holds what the coupling did.

:func:`couplings_of` lists a run's couplings from its recipe; adding one touches no other.

Warm start (:class:`WarmStartCoupling`)
    The coach demonstrates on the training envs with noisy actions
    (:mod:`pidlab.rl.demonstrations`, kept in the run folder as ``demonstrations.npz``); with a
    ``warm_start`` table the agent is then behaviour-cloned on them and its critic warmed up
    (:mod:`pidlab.rl.cloning`). The agent alone is evaluated at env step 0 and right after the
    warm start; learning then goes on from the envs' current states (no reset). With
    ``warm_start.keep`` the demonstrations stay in the updates: after each PPO update, as many
    behaviour-cloning steps as the update took gradient steps, weighted by ``keep(progress)``
    (:func:`pidlab.rl.cloning.keep_step`; DAPG's augmented gradient, Rajeswaran et al. 2018). The
    rounds are checkpointed counters (``kept_rounds``, and ``kept_at``: SB3's update count at the
    last round, so a resume does not repeat one). With SAC (which needs a ``coach_buffer``) there is
    no cloning: every demonstration step enters the coach's buffer as a transition of the coach's,
    counted as an env step; the demonstrations replace SAC's random warm-up (``learning_starts`` is
    their number, :func:`pidlab.rl.train.new_model`).
Value trigger (:class:`ValueTriggerCoupling`, TS2C-style)
    SAC's critic judges, before each agent action that the rescue region lets pass, whether the
    coach's proposal is worth more; the coach then takes over as at a veto.
Proposer (:class:`ProposerCoupling`, IBRL-style)
    The coach proposes an action at every agent step and SAC's critic picks which one runs, until
    the recipe's ``until``.
Roll-in (:class:`RollInCoupling`, Jump-Start RL)
    The coach acts alone for the first ``h`` steps of every env episode (the wrapper's
    :meth:`~pidlab.rl.coaching.CoachingWrapper.set_rollin`). The agent takes the episode over in
    ``stages`` equal shares of the env's horizon ``H`` (its time limit): at stage ``k`` the coach
    rolls in for ``h_k = H (stages - 1 - k) / stages`` steps (rounded up), so the agent plays the
    last share from the start and the whole episode from the last stage on. At an evaluation after
    env step 0 the stage advances by one when the agent alone, from the env's reset, lasts on average
    at least ``(1 - tolerance) (H - h_k)`` steps: it plays from the start the share it plays in
    training (JSRL advances when the mixed policy keeps the guide's score; the agent alone is the
    stricter test and needs no extra evaluation). The stage is a checkpointed counter
    (``rollin_stage``); ``rollin.json`` lists its changes.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

from pidlab.controller.spec import CoachSpec
from pidlab.errors import CoachingError
from pidlab.files import load_json, write_json
from pidlab.rl.recipe import DemonstrationSettings, Proposer, Recipe, RollIn, ValueTrigger, WarmStart

RECORD = "warm_start.json"
ROLLIN_RECORD = "rollin.json"


class Coupling:
    """A coupling: the trainer calls each method at its point (see the module docstring)."""

    def before_learning(self, trainer: Any) -> None:
        """Act once before the agent's first action of a new run."""

    def on_session(self, trainer: Any) -> None:
        """Act at the start of every session, new or resumed, before learning."""

    def after_evaluation(self, trainer: Any, evaluation: Any) -> None:
        """Act on an evaluation of the agent alone."""

    def before_rollout(self, trainer: Any) -> None:
        """Act before a rollout, after the update that ended the previous one."""


@dataclass(frozen=True)
class WarmStartCoupling(Coupling):
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
        keep = getattr(model, "keep_demonstrations", None)
        if keep is not None:  # an off-policy agent keeps them as the coach's transitions
            record["coach_buffer_rows"] = keep(demos)
        model._last_obs, model._last_episode_starts = last_obs, last_dones
        original = getattr(venv, "get_original_obs", None)
        if original is not None:  # what SB3's off-policy agents store as the next transition's state
            model._last_original_obs = original()
        trainer.envs_running = True
        record["agent_alone_after"] = trainer.evaluate().mean
        record["env_steps_after"] = c.env_steps
        write_json(trainer.run_dir / RECORD, record)
        trainer.checkpoint()

    def before_rollout(self, trainer: Any) -> None:
        """Behaviour-cloning steps on the kept demonstrations after a PPO update (``keep``)."""
        keep = self.warm_start.keep if self.warm_start is not None else None
        c, model = trainer.counters, trainer.model
        if keep is None or int(model._n_updates) <= c.kept_at:
            return
        c.kept_at = int(model._n_updates)
        weight = float(keep(min(c.env_steps / trainer.recipe.steps, 1.0)))
        if weight <= 0.0:
            return
        from pidlab.rl import demonstrations as demo
        from pidlab.rl.cloning import keep_step
        from pidlab.rl.train import ppo_batches_per_epoch

        demos = trainer.cache.get("demonstrations")
        if demos is None:
            demos = trainer.cache["demonstrations"] = demo.load(trainer.run_dir / demo.FILE)
        normalize = _obs_normalizer(trainer.venv)
        batches = int(model.n_epochs) * ppo_batches_per_epoch(model)
        loss = keep_step(
            model, demos, normalize or _identity, weight, batches, trainer.recipe.seed + c.kept_at
        )
        c.kept_rounds += 1
        trainer.tb.add_scalar("coaching/kept_weight", weight, c.env_steps)
        trainer.tb.add_scalar("coaching/kept_nll", loss, c.env_steps)

    def _clone(self, trainer: Any, demos: Any) -> Any:
        from pidlab.rl.cloning import clone

        recipe, venv = trainer.recipe, trainer.venv
        ws = self.warm_start or WarmStart()
        normalize_obs = _obs_normalizer(venv)
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


def _obs_normalizer(venv: Any) -> Any:
    """The run's observation normalizer (a ``VecNormalize`` that normalizes observations), or None."""
    return getattr(venv, "normalize_obs", None) if getattr(venv, "norm_obs", False) else None


def episode_horizon(env_id: str) -> int | None:
    """The env's time limit in steps (``max_episode_steps`` of its registration), or None."""
    import gymnasium as gym

    try:
        steps = gym.spec(env_id).max_episode_steps
    except gym.error.Error:
        return None
    return int(steps) if steps else None


@dataclass(frozen=True)
class RollInCoupling(Coupling):
    """The coach rolls in for the first ``h`` steps of each env episode; ``h`` shrinks by stages."""

    settings: RollIn
    horizon: int

    def steps_at(self, stage: int) -> int:
        """``h`` at ``stage``: ``H (stages - 1 - stage) / stages`` rounded up (0 from the last stage)."""
        n = self.settings.stages
        return math.ceil(self.horizon * (n - 1 - min(stage, n - 1)) / n)

    def threshold(self, stage: int) -> float:
        """The agent-alone mean episode length that moves ``stage`` to the next one."""
        return (1.0 - self.settings.tolerance) * (self.horizon - self.steps_at(stage))

    def on_session(self, trainer: Any) -> None:
        """Set every training env's roll-in; forget recorded changes after the checkpoint resumed from."""
        c = trainer.counters
        path = trainer.run_dir / ROLLIN_RECORD
        kept = [e for e in _changes(path) if e["env_steps"] <= c.env_steps and e["stage"] <= c.rollin_stage]
        if not kept:
            kept = [{"env_steps": 0, "stage": 0, "steps": self.steps_at(0)}]
        write_json(path, {"horizon": self.horizon, "stages": self.settings.stages, "changes": kept})
        trainer.venv.env_method("set_rollin", self.steps_at(c.rollin_stage))

    def after_evaluation(self, trainer: Any, evaluation: Any) -> None:
        """Advance one stage when the agent alone lasted long enough (never at env step 0)."""
        c = trainer.counters
        if c.env_steps == 0 or c.rollin_stage >= self.settings.stages - 1:
            return
        if evaluation.mean_length < self.threshold(c.rollin_stage):
            return
        c.rollin_stage += 1
        steps = self.steps_at(c.rollin_stage)
        trainer.venv.env_method("set_rollin", steps)
        path = trainer.run_dir / ROLLIN_RECORD
        changes = [*_changes(path), {"env_steps": c.env_steps, "stage": c.rollin_stage, "steps": steps}]
        write_json(path, {"horizon": self.horizon, "stages": self.settings.stages, "changes": changes})
        trainer.tb.add_scalar("coaching/rollin_steps", steps, c.env_steps)


@dataclass(frozen=True)
class ValueTriggerCoupling(Coupling):
    """The coach takes over where the agent's critic values its proposal more (TS2C-style).

    At the start of every session the training envs get a judge (:meth:`CoachingWrapper.set_advisor
    <pidlab.rl.coaching.CoachingWrapper.set_advisor>`) made from the SAC agent's critic: before an
    agent action runs that the rescue region lets pass, it compares ``Q(s, a_coach)`` with
    ``Q(s, a_agent)`` (the smaller of SAC's twin critics, on the normalized observation and the
    scaled actions) and answers take over when the coach's exceeds the agent's by more than
    ``margin`` alive rewards of the env. It says nothing until learning starts (an untrained critic
    judges nothing).
    """

    settings: ValueTrigger
    alive: float

    def on_session(self, trainer: Any) -> None:
        """Give every training env the judge of this session's agent."""
        trainer.venv.env_method("set_advisor", critic_judge(trainer.model, trainer.venv, self.threshold))

    @property
    def threshold(self) -> float:
        """The margin in the critic's units (rewards): ``margin * alive reward``."""
        return self.settings.margin * self.alive


@dataclass(frozen=True)
class ProposerCoupling(Coupling):
    """The coach proposes, SAC's critic picks (IBRL-style; :mod:`pidlab.rl.proposer`).

    At the start of every session the training envs get a judge made from the SAC agent's critic
    (:func:`critic_judge` with margin 0: the proposal is picked when its value is higher) and the
    progress ``until`` from which the coach proposes no more.
    """

    settings: Proposer

    def on_session(self, trainer: Any) -> None:
        """Give every training env this session's judge and the proposer's end."""
        judge = critic_judge(trainer.model, trainer.venv, 0.0)
        trainer.venv.env_method("set_proposer", judge, self.settings.until)


def critic_judge(model: Any, venv: Any, threshold: float) -> Any:
    """``judge(obs, agent_action, proposal)``: whether the critic prefers the proposal by ``threshold``."""
    import numpy as np
    import torch

    normalize = _obs_normalizer(venv)

    def judge(obs: Any, agent: Any, proposal: Any) -> bool:
        if model.num_timesteps <= model.learning_starts:
            return False
        x = np.asarray(obs, dtype=np.float64)[None]
        x = normalize(x) if normalize is not None else x
        actions = np.clip(model.policy.scale_action(np.stack([agent, proposal])), -1.0, 1.0)
        with torch.no_grad():
            o = torch.as_tensor(np.repeat(x, 2, axis=0), dtype=torch.float32)
            q = torch.cat(model.critic(o, torch.as_tensor(actions, dtype=torch.float32)), dim=1)
            low = torch.min(q, dim=1).values
        return bool(float(low[1] - low[0]) > threshold)

    return judge


def _changes(path: Any) -> list[dict[str, int]]:
    """The recorded roll-in changes (none if the record is missing or not pidlab's)."""
    from pidlab.errors import RunDirError

    if not path.is_file():
        return []
    try:
        data = load_json(path, "roll-in record", RunDirError)
    except RunDirError:
        return []
    changes = data.get("changes") if isinstance(data, dict) else None
    keys = ("env_steps", "stage", "steps")
    ok = isinstance(changes, list) and all(
        isinstance(e, dict) and all(type(e.get(k)) is int for k in keys) for e in changes
    )
    return list(changes) if ok and changes is not None else []


def couplings_of(recipe: Recipe, spec: CoachSpec | None) -> list[Coupling]:
    """The couplings of a run of ``recipe`` (none without a coach)."""
    c = recipe.coaching
    if spec is None:
        return []
    out: list[Coupling] = []
    if c.demonstrations is not None:
        out.append(WarmStartCoupling(c.demonstrations, c.warm_start))
    if c.rollin is not None:
        out.append(RollInCoupling(c.rollin, episode_horizon(recipe.env_id) or 0))
    if c.value_trigger is not None:
        out.append(ValueTriggerCoupling(c.value_trigger, _alive(recipe.env_id)))
    if c.proposer is not None:
        out.append(ProposerCoupling(c.proposer))
    return out


def _alive(env_id: str) -> float:
    """The env's alive reward per step (:func:`pidlab.rl.rewards.alive_reward`)."""
    from pidlab.plant.envs import make_env
    from pidlab.rl.rewards import alive_reward

    env = make_env(env_id)
    try:
        return float(alive_reward(env))
    finally:
        env.close()


def _check_model_predictor(spec: CoachSpec) -> None:
    """The model predictor's region, built as a run would build it (refused as a run would be)."""
    from pidlab.plant.model import load_model
    from pidlab.region.takeover import region_from_bounds
    from pidlab.rl.coaching import model_region

    rescue = (spec.bounds or {}).get("rescue")
    if rescue is None:
        raise CoachingError(f"{spec.name}: predictor 'model' tests the spec's rescue region, and it has none")
    loaded = load_model(spec.env_id)
    model_region(spec, loaded, region_from_bounds(spec.bounds, loaded.require_card().observation_names,
                                                  "rescue", spec.name))  # fmt: skip


def check_couplings(recipe: Recipe, spec: CoachSpec | None) -> None:
    """Refuse couplings that cannot run with this recipe and coach.

    Raises
    ------
    CoachingError
        Demonstrations, a blend, a residual, a roll-in, a coach buffer or a value trigger without a
        coach; demonstrations as long as the budget; a warm start, a blend or a residual with an
        algorithm other than PPO; demonstrations for SAC without a coach buffer; a coach buffer, a
        value trigger or a proposer with PPO; a coach buffer with the ``hidden`` view while the
        coach may take over; a proposer with several envs, a coach buffer or a value trigger; a
        value trigger without the predictive trigger, or with subprocess envs; a roll-in on an env
        without a time limit; the model predictor with a spec whose region it cannot serve (see
        :func:`pidlab.rl.coaching.model_region`).
    """
    c = recipe.coaching
    if c.blend is not None and spec is None:
        raise CoachingError("coaching.blend: blending the coach's action needs a coach; this run has none")
    if c.residual is not None and spec is None:
        raise CoachingError(
            "coaching.residual: the agent's action corrects the coach's, and this run has no coach "
            "(--coach none)"
        )
    _check_mix_algorithm(recipe)
    if c.predictor == "model" and spec is not None:
        _check_model_predictor(spec)
    if c.coach_buffer is not None:
        _check_coach_buffer(recipe, spec)
    if c.value_trigger is not None:
        _check_value_trigger(recipe, spec)
    if c.proposer is not None:
        _check_proposer(recipe, spec)
    if c.rollin is not None:
        _check_rollin(recipe, spec)
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
    if recipe.algo == "sac" and c.coach_buffer is None:
        raise CoachingError(
            "coaching.demonstrations with algo = 'sac' and no coach_buffer: SAC learns from the "
            "demonstrations only through the coach's buffer; add coaching.coach_buffer = { share = S }"
        )


def _check_mix_algorithm(recipe: Recipe) -> None:
    """A fading mix needs an on-policy learner: a replay buffer would keep actions of other weights."""
    c = recipe.coaching
    key = "blend" if c.blend is not None else "residual" if c.residual is not None else None
    if key is None or recipe.algo == "ppo":
        return
    raise CoachingError(
        f"coaching.{key} with algo = {recipe.algo!r}: the coach's weight fades during the run, so the "
        "replay buffer would keep agent actions that ran under other weights (their outcome no "
        "longer follows from them); use algo = 'ppo', whose every rollout runs at one weight"
    )


def _check_coach_buffer(recipe: Recipe, spec: CoachSpec | None) -> None:
    """Refuse a coach buffer that cannot work with this recipe and coach.

    Raises
    ------
    CoachingError
        No coach, an algorithm other than SAC, the ``hidden`` view while the coach may take over
        (``off_after`` not 0), or an episodic ``train_freq``.
    """
    if spec is None:
        raise CoachingError(
            "coaching.coach_buffer: it keeps the coach's transitions, and this run has no coach "
            "(--coach none)"
        )
    if recipe.algo != "sac":
        raise CoachingError(
            f"coaching.coach_buffer with algo = {recipe.algo!r}: the coach's transitions feed an "
            "off-policy agent's replay; use algo = 'sac'"
        )
    if recipe.coaching.view == "hidden" and recipe.coaching.off_after != 0.0:
        raise CoachingError(
            "coaching.coach_buffer with view = 'hidden': the agent's transition at a takeover would "
            "carry the coach's steps as its own, and nothing would mark its action as worse than the "
            "coach's; use view = 'terminal' or 'penalty'"
        )
    freq = recipe.hyperparameters.get("train_freq", 1)
    if isinstance(freq, list | tuple) and len(freq) == 2 and freq[1] == "episode":
        raise CoachingError(
            "coaching.coach_buffer with an episodic train_freq: the coach's steps buy gradient steps at "
            "the recipe's rate per env step, which train_freq = [n, 'episode'] does not set; use "
            "train_freq = n (steps)"
        )


def _check_proposer(recipe: Recipe, spec: CoachSpec | None) -> None:
    """Refuse a proposer that cannot work with this recipe and coach.

    Raises
    ------
    CoachingError
        No coach, an algorithm other than SAC, more than one env, or a coach buffer or a value
        trigger beside it.
    """
    c = recipe.coaching
    if spec is None:
        raise CoachingError("coaching.proposer: the coach proposes the actions, and this run has no coach "
                            "(--coach none)")  # fmt: skip
    if recipe.algo != "sac":
        raise CoachingError(
            f"coaching.proposer with algo = {recipe.algo!r}: the critic picks between two actions by their "
            "values, and PPO's critic values states only; use algo = 'sac'"
        )
    if recipe.n_envs != 1:
        raise CoachingError(
            f"coaching.proposer with n_envs = {recipe.n_envs}: the coach's proposals at the next states "
            "are kept per transition of one env; use n_envs = 1"
        )
    if c.coach_buffer is not None or c.value_trigger is not None:
        other = "coach_buffer" if c.coach_buffer is not None else "value_trigger"
        raise CoachingError(
            f"coaching.proposer and coaching.{other}: the proposer already runs the coach's actions as "
            "the agent's and asks the critic at every step; expected one of them"
        )


def _check_value_trigger(recipe: Recipe, spec: CoachSpec | None) -> None:

    c = recipe.coaching
    if spec is None:
        raise CoachingError(
            "coaching.value_trigger: the coach's proposal is judged against the agent's action, and "
            "this run has no coach (--coach none)"
        )
    if recipe.algo != "sac":
        raise CoachingError(
            f"coaching.value_trigger with algo = {recipe.algo!r}: it compares the critic's values of two "
            "actions, and PPO's critic values states only; use algo = 'sac'"
        )
    if c.trigger != "predictive":
        raise CoachingError(
            "coaching.value_trigger: the rescue region is its hard floor, tested before each action; "
            "expected trigger = 'predictive'"
        )
    if recipe.vec_env == "subproc" and recipe.n_envs > 1:
        raise CoachingError(
            "coaching.value_trigger with vec_env = 'subproc': the critic judges every action in the "
            "trainer's process; use vec_env = 'dummy'"
        )


def _check_rollin(recipe: Recipe, spec: CoachSpec | None) -> None:

    if spec is None:
        raise CoachingError("coaching.rollin: a roll-in is the coach acting first, and this run has no coach")
    horizon = episode_horizon(recipe.env_id)
    if horizon is None or horizon < 2:
        raise CoachingError(
            f"coaching.rollin: {recipe.env_id} has no time limit of at least 2 steps (max_episode_steps), "
            "and a roll-in's length is a share of it; register the env with one"
        )
