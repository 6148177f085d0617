"""Coached training with Stable-Baselines3: logs, agent-alone evaluation, checkpoints, resume.

:func:`train` trains one agent from a recipe (``coach/``) with or without a coach spec
(``tuning/``). The coach runs inside :class:`pidlab.rl.coaching.CoachingWrapper`, so the SB3
algorithm only ever stores the agent's own transitions. The budget is counted in **env steps**
(agent steps + coach steps): a coached run is charged for every step its coach takes.

A run directory holds::

    config.toml          the resolved recipe (overrides applied) and which coach
    coach.toml           the coach spec used (absent for --coach none)
    run.json             seed, command, package versions, git SHA, start and resume times
    episodes.csv         one row per finished agent episode (whether the env's episode ended too, a fall)
    evaluations.csv      one row per agent-alone evaluation (coach off, fixed seeds)
    tb/                  TensorBoard: pidlab's scalars (x = env steps), tb/sb3: SB3's (x = agent steps)
    checkpoints/<env steps>/   the latest two: model.zip, vecnormalize.npz, replay_buffer.npz (SAC),
                               state.json (written last, with each file's SHA-256)
    final_model.zip      (and final_vecnormalize.npz) when the budget is spent
    summary.json         totals, final evaluation, wall time (this session's and the run's total)

:mod:`pidlab.rl.rundir` writes and reads these files. :func:`resume` continues from the newest
checkpoint that loads (:func:`load_checkpoint` checks every file of it): the CSV files are cut
back to the rows that checkpoint had recorded (so no episode is lost or logged twice), the model,
normalization statistics and replay buffer are reloaded without unpickling anything
(:mod:`pidlab.rl.checkpoint`), and the envs start fresh episodes.
Episodes in progress at the checkpoint are not logged (their env steps stay counted). When the
latest checkpoint is damaged, a resume says so in one warning line, falls back to the previous
one and records that in ``run.json``; when no checkpoint loads, it refuses and changes nothing.
Every resume reads and checks everything before it writes anything. SIGINT/SIGTERM stop at the
next step with a checkpoint. :func:`train` and :func:`resume` hold the run directory's lock
(:func:`pidlab.provenance.hold_lock`) from start to end: a second command on it is refused.
"""

from __future__ import annotations

import errno
import os
import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import tomli_w

from pidlab.controller.spec import CoachSpec
from pidlab.errors import CheckpointError, OutputError
from pidlab.files import atomic_write_text, check_output_folder, read_json, write_json
from pidlab.plant.envs import make_env
from pidlab.provenance import hold_lock, read_record
from pidlab.rl.checkpoint import (
    FINAL,
    check_manifest,
    expected_files,
    load_agent_files,
    save_agent,
    short_reason,
)
from pidlab.rl.coaching import CoachingWrapper, step_env_steps
from pidlab.rl.couplings import RollInCoupling, couplings_of
from pidlab.rl.evaluation import AgentEvaluation, evaluate_agent, evaluation_envs, sb3_policy
from pidlab.rl.recipe import LINEAR_SCHEDULES, Recipe, recipe_to_dict
from pidlab.rl.rundir import (
    EPISODE_COLUMNS,
    EVALUATION_COLUMNS,
    RUN_SCHEMA,
    TIMING_COLUMNS,
    CsvLog,
    RunDirError,
    check_log,
    check_new_run_dir,
    checkpoint_folders,
    evaluated_at,
    finished_summary,
    is_checkpoint_name,
    load_run_config,
    prepare_run_dir,
    read_csv_rows,
    read_state,
    record_resume,
    truncate_csv,
    truncate_timing,
)
from pidlab.rl.wrap import mix_of, wrapper_arguments

ACTIVATION_CLASSES = {
    "tanh": "Tanh",
    "relu": "ReLU",
    "elu": "ELU",
    "leaky_relu": "LeakyReLU",
    "gelu": "GELU",
    "silu": "SiLU",
}


@dataclass
class Counters:
    """Running totals of a training run (what a checkpoint records).

    ``agent_steps`` are the env steps the agent's actions ran (a vetoed action runs none);
    ``episodes`` are agent episodes, ``env_episodes`` the env's ended episodes (fewer when a
    ``terminal``-view rescue hands the running env to the next agent episode); ``env_resets``
    count every real reset of a training env (each env's first of every session included);
    ``falls`` the env's terminations, whoever was acting; ``rollin_stage`` the roll-in's stage
    (:class:`pidlab.rl.couplings.RollInCoupling`, 0 without one); ``kept_rounds`` and ``kept_at``
    the warm start's rounds on the kept demonstrations and SB3's update count at the last one;
    ``value_vetoes`` the agent actions that the value trigger vetoed (among ``interventions``);
    ``proposals_taken`` the agent steps that ran the coach's proposal (a proposer's).
    """

    env_steps: int = 0
    agent_steps: int = 0
    coach_steps: int = 0
    interventions: int = 0
    episodes: int = 0
    evaluations: int = 0
    next_evaluation: int = 0
    next_checkpoint: int = 0
    resumes: int = 0
    policy_updates: int = 0
    env_episodes: int = 0
    env_resets: int = 0
    falls: int = 0
    rollin_stage: int = 0
    kept_rounds: int = 0
    kept_at: int = 0
    value_vetoes: int = 0
    proposals_taken: int = 0

    def to_dict(self) -> dict[str, int]:
        """Plain dict for JSON."""
        return dict(self.__dict__)


@dataclass(frozen=True)
class TrainResult:
    """What a finished (or stopped) run did.

    Attributes
    ----------
    run_dir : Path
    env_steps, agent_steps, coach_steps, interventions, episodes : int
        ``episodes``: agent episodes.
    completed : bool
        The budget was spent (False: stopped by a signal, resumable).
    final_evaluation : AgentEvaluation or None
    wall_s : float
        Seconds spent in this call.
    env_episodes, env_resets, falls : int
        Ended env episodes, real env resets, terminations of the env (see :class:`Counters`).
    """

    run_dir: Path
    env_steps: int
    agent_steps: int
    coach_steps: int
    interventions: int
    episodes: int
    completed: bool
    final_evaluation: AgentEvaluation | None
    wall_s: float
    env_episodes: int = 0
    env_resets: int = 0
    falls: int = 0


@dataclass(frozen=True)
class EnvFactory:
    """Builds one training env: ``gym.make`` -> coaching wrapper -> SB3 Monitor (picklable)."""

    env_id: str
    spec: CoachSpec | None
    recipe: Recipe

    def __call__(self) -> gym.Env:
        """A new env."""
        from stable_baselines3.common.monitor import Monitor

        env = make_env(self.env_id)
        arguments = wrapper_arguments(self.recipe.coaching, coached=self.spec is not None)
        return Monitor(CoachingWrapper(env, self.spec, **arguments))


def _schedules_move(recipe: Recipe, spec: CoachSpec | None) -> bool:
    c = recipe.coaching
    return spec is not None and (
        c.probability.shape != "constant"
        or c.width.shape != "constant"
        or c.off_after is not None
        or mix_of(c) is not None
    )


def make_vec_env(recipe: Recipe, spec: CoachSpec | None) -> Any:
    """The training VecEnv of ``recipe`` (DummyVecEnv or SubprocVecEnv, then VecNormalize)."""
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecNormalize

    fns: list[Callable[[], gym.Env]] = [EnvFactory(recipe.env_id, spec, recipe) for _ in range(recipe.n_envs)]
    venv: Any = SubprocVecEnv(fns) if recipe.vec_env == "subproc" and recipe.n_envs > 1 else DummyVecEnv(fns)
    if recipe.normalize_obs or recipe.normalize_reward:
        gamma = float(recipe.hyperparameters.get("gamma", 0.99))
        venv = VecNormalize(
            venv, norm_obs=recipe.normalize_obs, norm_reward=recipe.normalize_reward, gamma=gamma
        )
    return venv


def sb3_arguments(recipe: Recipe) -> dict[str, Any]:
    """The recipe's hyperparameters as SB3 keyword arguments (schedules and classes resolved)."""
    import torch.nn as nn

    kwargs = recipe.hyperparameters
    for key in LINEAR_SCHEDULES:
        if isinstance(kwargs.get(key), str):  # "lin_<x>", checked by the recipe parser
            kwargs[key] = _Linear(float(kwargs[key][4:]))
    if isinstance(kwargs.get("train_freq"), list):
        kwargs["train_freq"] = tuple(kwargs["train_freq"])
    pk = dict(kwargs.get("policy_kwargs", {}))
    if "activation_fn" in pk:
        pk["activation_fn"] = getattr(nn, ACTIVATION_CLASSES[pk["activation_fn"]])
    if pk:
        kwargs["policy_kwargs"] = pk
    return kwargs


@dataclass(frozen=True)
class _Linear:
    """The zoo's ``lin_<x>``: ``x * progress_remaining`` (picklable, unlike a closure)."""

    start: float

    def __call__(self, progress_remaining: float) -> float:
        return self.start * progress_remaining


def _algorithm_class(algo: str) -> Any:
    from stable_baselines3 import PPO, SAC

    return {"ppo": PPO, "sac": SAC}[algo]


def new_model(recipe: Recipe, venv: Any) -> Any:
    """A new agent of ``recipe`` on ``venv``.

    SAC counts env steps (:mod:`pidlab.rl.envclock`); with a coach buffer it is
    :mod:`pidlab.rl.replay`'s, with a proposer :mod:`pidlab.rl.proposer`'s. With a coach buffer and
    demonstrations, SAC's warm-up is the demonstrations: ``learning_starts`` is their length,
    whatever the recipe's (learning starts right after them).
    """
    kwargs = {"policy": "MlpPolicy", "env": venv, "seed": recipe.seed, "device": "cpu", "verbose": 0,
              **sb3_arguments(recipe)}  # fmt: skip
    buffer = recipe.coaching.coach_buffer
    if recipe.algo == "sac" and buffer is not None:
        from pidlab.rl.replay import CoachReplaySAC

        demos = recipe.coaching.demonstrations
        if demos is not None:
            kwargs["learning_starts"] = demos.steps
        return CoachReplaySAC(coach_share=buffer.share, coach_buffer_size=buffer.size, **kwargs)
    if recipe.algo == "sac" and recipe.coaching.proposer is not None:
        from pidlab.rl.proposer import ProposerSAC

        return ProposerSAC(**kwargs)
    if recipe.algo == "sac":  # its clock is the run's env steps (pidlab.rl.envclock)
        from pidlab.rl.envclock import CoachedSAC

        return CoachedSAC(**kwargs)
    return _algorithm_class(recipe.algo)(**kwargs)


# --------------------------------------------------------------------------- checkpoints

WRITING = ".writing"
"""The folder a checkpoint is written into before it is renamed into place."""
REPLACED = ".replaced"
"""Where a checkpoint of the same env step waits while its successor is renamed into place."""


def load_checkpoint(checkpoint: Path, recipe: Recipe, venv: Any) -> tuple[Any, Any, dict[str, int]]:
    """Load a checkpoint of a run: the one place that recognizes a damaged one.

    Nothing is unpickled (see :mod:`pidlab.rl.checkpoint`): the agent is rebuilt from ``recipe``
    and its weights, normalizer statistics and replay buffer are read from plain files, each
    checked first against the SHA-256 that ``state.json`` records.

    Parameters
    ----------
    checkpoint : Path
        ``RUN/checkpoints/<env steps>``.
    recipe : Recipe
        The run's recipe (which algorithm, whether observations are normalized).
    venv : VecEnv
        New training envs of the run (:func:`make_vec_env`); their normalizer statistics are set.

    Returns
    -------
    model, venv, state
        The agent (its replay buffer loaded, for SAC), the envs with the checkpoint's
        normalization statistics, and the counters of ``state.json``.

    Raises
    ------
    CheckpointError
        One line naming the file that is missing or damaged: ``state.json`` (cut short, not JSON,
        counters that disagree, no file digests), or an agent file whose digest does not match,
        that does not read, or that is not for this run's agent and envs.
    """
    from stable_baselines3.common.vec_env import VecNormalize

    state = read_state(checkpoint)
    record = checkpoint / "state.json"
    data = read_json(record)
    sac = recipe.algo == "sac"
    coach, proposals = recipe.coaching.coach_buffer is not None, recipe.coaching.proposer is not None
    files = check_manifest(
        data, record, expected_files(sac, isinstance(venv, VecNormalize), sac and coach, sac and proposals)
    )
    agent = load_agent_files(checkpoint, files, record, lambda v: new_model(recipe, v), venv)
    model = agent.model
    model.num_timesteps = state["num_timesteps"]
    sb3 = data.get("sb3") if isinstance(data.get("sb3"), dict) else {}
    for key in ("n_updates", "episode_num"):
        value = sb3.get(key, 0)
        setattr(model, f"_{key}", value if type(value) is int and value >= 0 else 0)
    if hasattr(model, "restore_counters"):  # a coach buffer's (pidlab.rl.replay)
        model.restore_counters(sb3)
    return model, agent.venv, state


@dataclass(frozen=True)
class _Restored:
    """Where a resume continues: the checkpoint that loaded (None: from scratch) and those skipped."""

    model: Any
    venv: Any
    checkpoint: Path | None
    state: dict[str, int] | None
    damaged: tuple[tuple[Path, str], ...]


def _restore(run_dir: Path, recipe: Recipe, venv: Any) -> _Restored:
    """The newest checkpoint that loads and agrees with the CSV logs; nothing is written.

    Raises
    ------
    RunDirError
        Checkpoints exist and none of them loads.
    """
    damaged: list[tuple[Path, str]] = []
    for checkpoint in reversed(checkpoint_folders(run_dir, complete=False)):
        try:
            state = read_state(checkpoint)
            check_log(run_dir / "episodes.csv", EPISODE_COLUMNS, state["episodes"])
            check_log(run_dir / "evaluations.csv", EVALUATION_COLUMNS, state["evaluations"])
            model, loaded, state = load_checkpoint(checkpoint, recipe, venv)
        except CheckpointError as exc:
            damaged.append((checkpoint, str(exc)))
            continue
        return _Restored(model, loaded, checkpoint, state, tuple(damaged))
    if len(damaged) == 1:
        raise RunDirError(
            f"{run_dir}: cannot resume: {damaged[0][1]}; there is no earlier checkpoint to fall back to. "
            "Nothing was changed"
        )
    if damaged:
        reasons = "; ".join(reason for _, reason in damaged)
        raise RunDirError(f"{run_dir}: cannot resume: no checkpoint loads ({reasons}). Nothing was changed")
    return _Restored(new_model(recipe, venv), venv, None, None, ())


def _warn(message: str) -> None:
    """One warning line on stderr (the command goes on)."""
    print(f"pidlab: warning: {message}", file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- the callback


class _Stop:
    """Turns SIGINT/SIGTERM into a polite stop at the next step (a second signal interrupts)."""

    def __init__(self) -> None:
        self.requested = False
        self._old: dict[int, Any] = {}

    def __enter__(self) -> _Stop:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._old[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        try:
            print(
                f"\npidlab: {signal.Signals(signum).name}: stopping at the next step with a checkpoint "
                "(send it again to stop at once)",
                file=sys.stderr,
                flush=True,
            )
        except (OSError, RuntimeError, ValueError):
            # stderr gone (a pipe whose reader died with the sweep, a closed stream) or in the middle
            # of a write the signal interrupted: the stop is what matters, not its notice
            pass

    def __exit__(self, *exc: Any) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)


def _make_callback(trainer: _Trainer) -> Any:
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

    class TrainingMonitor(BaseCallback):
        """Counts env steps, logs episodes, evaluates, checkpoints, stops at the budget."""

        def _on_training_start(self) -> None:
            trainer.on_start()

        def _on_rollout_start(self) -> None:
            for coupling in trainer.couplings:
                coupling.before_rollout(trainer)
            trainer.maybe_checkpoint()

        def _on_step(self) -> bool:
            go_on = trainer.on_step(self.locals["infos"])
            if not go_on and isinstance(self.model, OffPolicyAlgorithm):
                # SB3 returns before storing this step's transition when a callback stops it;
                # store it as SB3 would have, so the replay buffer holds every agent step taken
                loc = self.locals
                self.model._update_info_buffer(loc["infos"], loc["dones"])
                self.model._store_transition(
                    loc["replay_buffer"], loc["buffer_actions"], loc["new_obs"], loc["rewards"], loc["dones"],
                    loc["infos"],
                )  # fmt: skip
            return go_on

    return TrainingMonitor()


# --------------------------------------------------------------------------- the trainer


@dataclass
class _Trainer:
    recipe: Recipe
    spec: CoachSpec | None
    run_dir: Path
    progress_bar: bool
    counters: Counters = field(default_factory=Counters)
    model: Any = None
    venv: Any = None
    stop: _Stop | None = None
    last_evaluation: AgentEvaluation | None = None
    bar: Any = None
    episodes_log: Any = None  # set by open_logs, like the four below
    evaluations_log: Any = None
    tb: Any = None
    sb3_logger: Any = None
    eval_envs: list[Any] = field(default_factory=list)
    moving: bool = False
    envs_running: bool = False  # a coupling stepped the envs: learning goes on without resetting them
    couplings: list[Any] = field(default_factory=list)
    cache: dict[str, Any] = field(default_factory=dict)  # what couplings keep between calls
    timing_log: Any = None
    clock: Callable[[], float] = time.perf_counter  # wall-clock seconds since the run started
    _progress_tick: int = -1

    # -- setup
    def open_logs(self, purge_env_step: int | None, purge_agent_step: int | None) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.episodes_log = CsvLog(self.run_dir / "episodes.csv", EPISODE_COLUMNS)
        self.evaluations_log = CsvLog(self.run_dir / "evaluations.csv", EVALUATION_COLUMNS)
        self.timing_log = CsvLog(self.run_dir / "timing.csv", TIMING_COLUMNS)
        self.tb = SummaryWriter(str(self.run_dir / "tb"), purge_step=purge_env_step)
        from stable_baselines3.common.logger import Logger, TensorBoardOutputFormat

        class PurgingTensorBoard(TensorBoardOutputFormat):
            """SB3's TensorBoard output, hiding events past the checkpoint a run resumed from."""

            def __init__(self, folder: str, purge_step: int | None) -> None:
                self.writer = SummaryWriter(folder, purge_step=purge_step)
                self._is_closed = False

        fmt = PurgingTensorBoard(str(self.run_dir / "tb" / "sb3"), purge_agent_step)
        self.sb3_logger = Logger(folder=str(self.run_dir / "tb" / "sb3"), output_formats=[fmt])
        self.eval_envs = evaluation_envs(self.recipe.env_id, self.recipe.evaluation.episodes)
        self.moving = _schedules_move(self.recipe, self.spec)

    def close(self) -> None:
        for closable in (self.episodes_log, self.evaluations_log, self.timing_log, self.tb, self.sb3_logger,
                         *self.eval_envs, self.venv):  # fmt: skip
            if closable is not None:
                closable.close()

    # -- SB3 hooks
    def on_start(self) -> None:
        # SB3 resets every training env when learning starts (a new run, or new envs on resume),
        # unless a coupling left them running
        if not self.envs_running:
            self.counters.env_resets += self.recipe.n_envs
        if self.counters.evaluations == 0:
            self.evaluate()
        self._set_progress(force=True)
        self._bar_update()

    def on_step(self, infos: list[dict[str, Any]], evaluating: bool = True) -> bool:
        """Count one step of every env; evaluate when a grid point is due (and ``evaluating``)."""
        c = self.counters
        for i, info in enumerate(infos):
            if "rollin" in info:
                self.count_rollin(i, info["rollin"])
            agent, coach_steps = step_env_steps(info)
            c.agent_steps += agent
            c.coach_steps += coach_steps
            c.env_steps += agent + coach_steps
            c.interventions += int(bool(info.get("intervened", False)))
            c.value_vetoes += int(info.get("veto_reason") == "value")
            c.proposals_taken += int(bool(info.get("proposal_taken", False)))
            c.falls += int(bool(info.get("fell", False)))
            if info.get("env_ended", False):  # the VecEnv resets this env at once, for real
                c.env_episodes += 1
                c.env_resets += 1
            episode = info.get("coaching_episode")
            if episode is not None:
                self.log_episode(i, episode)
        self._set_progress()
        if evaluating and c.env_steps >= c.next_evaluation:
            self.evaluate()
        self._bar_update()
        if self.stop is not None and self.stop.requested:
            return False
        return c.env_steps < self.recipe.steps

    def count_rollin(self, env_index: int, report: dict[str, Any]) -> None:
        """Charge a roll-in's coach steps, and log the env episodes that ended in it (falls included)."""
        c = self.counters
        c.coach_steps += int(report["steps"])
        c.env_steps += int(report["steps"])
        for episode in report["episodes"]:
            c.falls += int(bool(episode["fell"]))
            c.env_episodes += 1
            c.env_resets += 1  # the wrapper reset the env again
            self.log_episode(env_index, episode)

    def settle_rollins(self) -> None:
        """Charge the roll-ins that ran after the last step (the envs' resets at the budget's end)."""
        if not any(isinstance(k, RollInCoupling) for k in self.couplings):
            return
        for i, report in enumerate(self.venv.env_method("take_rollin")):
            if report is not None:
                self.count_rollin(i, report)

    # -- pieces
    def log_episode(self, env_index: int, ep: dict[str, Any]) -> None:
        c = self.counters
        row = [
            c.episodes,
            c.env_steps,
            c.agent_steps,
            ep["agent_steps"],
            ep["coach_steps"],
            ep["interventions"],
            float(ep["agent_return"]),
            float(ep["total_return"]),
            bool(ep["terminated"]),
            env_index,
            bool(ep.get("env_end", True)),
            bool(ep.get("fell", ep["terminated"])),
            int(ep.get("runs", 0)),
            int(ep.get("longest_run", 0)),
        ]
        self.episodes_log.write(row)
        c.episodes += 1
        step = c.env_steps
        self.tb.add_scalar("episode/agent_return", ep["agent_return"], step)
        self.tb.add_scalar("episode/total_return", ep["total_return"], step)
        self.tb.add_scalar("episode/coach_steps", ep["coach_steps"], step)
        self.tb.add_scalar("episode/interventions", ep["interventions"], step)
        self.tb.add_scalar(
            "coaching/coach_step_fraction",
            ep["coach_steps"] / max(ep["agent_steps"] + ep["coach_steps"], 1),
            step,
        )

    def evaluate(self) -> AgentEvaluation:
        c = self.counters
        normalizer: Any = None
        from stable_baselines3.common.vec_env import VecNormalize

        if isinstance(self.venv, VecNormalize) and self.venv.norm_obs:
            normalizer = self.venv.normalize_obs
        result = evaluate_agent(
            sb3_policy(self.model, normalizer), self.eval_envs, self.recipe.evaluation.seeds
        )
        r = np.array(result.returns)
        self.evaluations_log.write([
            c.env_steps, c.agent_steps, c.episodes, result.mean, result.std, float(r.min()), float(r.max()),
            result.mean_length, ";".join(repr(float(v)) for v in r),
        ])  # fmt: skip
        self.timing_log.write([c.env_steps, self.clock()])
        c.evaluations += 1
        every = self.recipe.evaluation.every
        c.next_evaluation = (c.env_steps // every + 1) * every
        self.tb.add_scalar("eval/mean_return", result.mean, c.env_steps)
        self.tb.add_scalar("eval/std_return", result.std, c.env_steps)
        self.last_evaluation = result
        for coupling in self.couplings:
            coupling.after_evaluation(self, result)
        return result

    def _set_progress(self, force: bool = False) -> None:
        if not self.moving:
            return
        p = min(self.counters.env_steps / self.recipe.steps, 1.0)
        tick = int(p * 1000)
        if force or tick != self._progress_tick:
            self._progress_tick = tick
            self.venv.env_method("set_progress", tick / 1000)

    def maybe_checkpoint(self) -> Path | None:
        c = self.counters
        if c.env_steps < c.next_checkpoint or c.env_steps == 0:
            return None
        return self.checkpoint()

    def checkpoint(self) -> Path:
        """Write a checkpoint at the current env step; keep it and the one before, remove older ones.

        It is written into ``checkpoints/.writing`` and renamed into place once complete, so a
        kill leaves the checkpoints that were there (and at worst a partial folder, ignored).
        """
        c = self.counters
        every = self.recipe.checkpoint_every
        c.next_checkpoint = (c.env_steps // every + 1) * every
        root = self.run_dir / "checkpoints"
        folder = root / f"{c.env_steps:012d}"
        writing = root / WRITING
        shutil.rmtree(writing, ignore_errors=True)
        writing.mkdir(parents=True)
        self._save(writing)
        if folder.exists():  # a checkpoint of this very step (a resume that took no step): replaced
            replaced = root / REPLACED
            shutil.rmtree(replaced, ignore_errors=True)
            folder.rename(replaced)
        writing.rename(folder)
        earlier = [p for p in checkpoint_folders(self.run_dir) if p.name < folder.name]
        keep = {folder, *earlier[-1:]}
        for old in root.iterdir():
            if old not in keep and old.is_dir():
                shutil.rmtree(old, ignore_errors=True)
        return folder

    def _save(self, folder: Path) -> None:
        """The agent's files, the logs and the counters into ``folder`` (``state.json`` last).

        ``state.json`` records each agent file's SHA-256 (see :mod:`pidlab.rl.checkpoint`).
        """
        files = save_agent(folder, self.model, self.venv)
        self.episodes_log.sync()
        self.evaluations_log.sync()
        self.timing_log.sync()
        self.tb.flush()
        sb3 = {"n_updates": int(self.model._n_updates), "episode_num": int(self.model._episode_num)}
        if hasattr(self.model, "counters"):  # a coach buffer's (pidlab.rl.replay)
            sb3 |= self.model.counters()
        state = {**self.counters.to_dict(), "num_timesteps": int(self.model.num_timesteps), "files": files,
                 "sb3": sb3}  # fmt: skip
        write_json(folder / "state.json", state)  # written last: marks the checkpoint complete

    def _bar_update(self) -> None:
        if self.bar is None or self.bar.disable:
            return
        c = self.counters
        post = {"episodes": c.episodes, "coach %": f"{100 * c.coach_steps / max(c.env_steps, 1):.1f}"}
        if self.last_evaluation is not None:
            post["alone"] = f"{self.last_evaluation.mean:.0f}"
        self.bar.set_postfix(post, refresh=False)
        self.bar.update(min(c.env_steps, self.recipe.steps) - self.bar.n)


def _earlier_wall_s(run_dir: Path) -> float:
    """Seconds the run's earlier sessions spent, by the ``summary.json`` the last of them wrote.

    0 for a new run. A session that ended without writing one (SIGKILL, power loss) is not counted,
    and neither are sessions before the one whose summary predates ``wall_s_total``.
    """
    try:
        earlier = read_json(run_dir / "summary.json")
        value = float(earlier.get("wall_s_total", earlier.get("wall_s_last_session", 0.0)))
    except (OSError, ValueError, TypeError, AttributeError):
        return 0.0
    return value if np.isfinite(value) and value > 0 else 0.0


def _run_summary(trainer: _Trainer, completed: bool, wall_s: float, earlier_s: float) -> dict[str, Any]:
    c = trainer.counters
    ev = trainer.last_evaluation
    return {
        "completed": completed,
        "budget_env_steps": trainer.recipe.steps,
        **c.to_dict(),
        "agent_episodes": c.episodes,
        "coach_step_fraction": c.coach_steps / max(c.env_steps, 1),
        "final_evaluation": None
        if ev is None
        else {
            "mean": ev.mean,
            "std": ev.std,
            "returns": list(ev.returns),
            "lengths": list(ev.lengths),
            "seeds": list(ev.seeds),
        },
        "wall_s_last_session": wall_s,
        "wall_s_total": earlier_s + wall_s,
    }


def train(
    recipe: Recipe,
    spec: CoachSpec | None,
    run_dir: str | Path,
    *,
    coach_source: str | None = None,
    progress_bar: bool = True,
    argv: list[str] | None = None,
) -> TrainResult:
    """Train one agent from scratch, coached by ``spec`` (or not), into a new ``run_dir``.

    Parameters
    ----------
    recipe : Recipe
        Resolved (command-line overrides applied).
    spec : CoachSpec or None
        The coach; ``None`` trains without one.
    run_dir : path
        Must not exist, or be empty.
    coach_source : str, optional
        Where the spec came from (recorded in config.toml).
    progress_bar : bool
    argv : list of str, optional
        The command line to record (default ``sys.argv``).

    Returns
    -------
    TrainResult

    Raises
    ------
    RunDirError
        ``run_dir`` exists and is not empty, or another command is working in it. Every input
        is checked (the coach runs on the env, SB3 accepts the agent's settings) before the
        first file is written.
    """
    from pidlab.rl.arguments import check_train_arguments

    check_train_arguments(recipe, spec, run_dir, coach_source, progress_bar, argv)
    run_dir = Path(run_dir)
    EnvFactory(recipe.env_id, spec, recipe)().close()  # a coach that cannot run fails here, before any file
    check_new_run_dir(run_dir)

    def start(venv: Any) -> tuple[Any, Any, dict[str, int] | None]:
        model = new_model(recipe, venv)  # bad agent settings fail here, before any file
        prepare_run_dir(run_dir, recipe, spec, coach_source, argv)
        return model, venv, None

    with hold_lock(run_dir, RunDirError), _disk_full(run_dir, recipe.env_id):
        return _run(recipe, spec, run_dir, progress_bar, start)


def resume(
    run_dir: str | Path, *, steps: int | None = None, progress_bar: bool = True, argv: list[str] | None = None
) -> TrainResult:
    """Continue the run in ``run_dir`` from its newest checkpoint that loads.

    Everything is read and checked first (the run's config, spec and record, the checkpoint and
    the CSV logs); only then is anything written. A damaged latest checkpoint is reported in one
    warning line and the previous one is used (the fallback is recorded in ``run.json``).

    Parameters
    ----------
    run_dir : path
    steps : int, optional
        A new, larger budget in env steps (default: the run's own).
    progress_bar : bool
    argv : list of str, optional

    Returns
    -------
    TrainResult
        At once, when the run has already spent its budget.

    Raises
    ------
    RunDirError
        Not a run directory, a damaged file in it (named), no checkpoint that loads, ``steps``
        below what the run has already done, or another command working in it. Nothing is
        changed then.
    """
    from pidlab.rl.arguments import check_resume_arguments

    check_resume_arguments(run_dir, steps, progress_bar, argv)
    run_dir = Path(run_dir)
    if steps is not None and (type(steps) is not int or steps < 1):
        raise RunDirError(f"steps={steps!r}: expected a positive number of env steps", param="steps")
    env_id = load_run_config(run_dir)[0].env_id  # not a run: refused before its lock is taken
    check_output_folder(run_dir)  # a read-only run: refused before the first write, not during
    with hold_lock(run_dir, RunDirError), _disk_full(run_dir, env_id):
        return _resume(run_dir, steps, progress_bar, argv)


@contextmanager
def _disk_full(run_dir: Path, env_id: str) -> Iterator[None]:
    """A full disk (or quota) while a run writes becomes one line that says how to go on.

    What the run wrote up to its last complete checkpoint stays usable (checkpoints are renamed
    into place once complete); the resume cuts the logs back to it.
    """
    try:
        yield
    except OSError as exc:
        if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise
        where = f" ({exc.filename})" if exc.filename else ""
        raise OutputError(
            f"{run_dir}: {os.strerror(exc.errno).lower()}{where}; the run keeps its last checkpoint. "
            f"Free some space, then resume: pidlab train {env_id} --resume {run_dir}"
        ) from None


def _finished(run_dir: Path, budget: int) -> TrainResult | None:
    """The result in ``summary.json`` when it says the run spent ``budget``; a damaged one is ignored."""
    try:
        done = finished_summary(run_dir, budget)
        return None if done is None else _result_from_summary(run_dir, done)
    except RunDirError as exc:  # its message names the file
        _warn(f"{short_reason(exc)}; ignored, it is written again at the end")
        return None
    except (KeyError, TypeError, ValueError) as exc:
        path = run_dir / "summary.json"
        _warn(f"{path}: damaged ({short_reason(exc)}); ignored, it is written again at the end")
        return None


def _resume(run_dir: Path, steps: int | None, progress_bar: bool, argv: list[str] | None) -> TrainResult:
    """:func:`resume`, holding the lock."""
    recipe, spec, config = load_run_config(run_dir)
    read_record(run_dir / "run.json", RUN_SCHEMA, RunDirError)
    asked = recipe if steps is None else replace(recipe, steps=steps)
    done = _finished(run_dir, asked.steps)
    if done is not None:
        return done

    def start(venv: Any) -> tuple[Any, Any, dict[str, int] | None]:
        r = _restore(run_dir, recipe, venv)
        if r.state is not None and steps is not None and steps < r.state["env_steps"]:
            raise RunDirError(
                f"steps={steps}: the run has already done {r.state['env_steps']} env steps", param="steps"
            )
        _commit_resume(run_dir, config, asked, r, argv)
        return r.model, r.venv, r.state

    return _run(asked, spec, run_dir, progress_bar, start)


def _commit_resume(run_dir: Path, config: dict[str, Any], recipe: Recipe, r: _Restored,
                   argv: list[str] | None) -> None:  # fmt: skip
    """The writes of a resume, once everything was checked: cut back to ``r``'s checkpoint, record it."""
    at = r.state["env_steps"] if r.state is not None else 0
    for checkpoint, reason in r.damaged:
        _warn(f"{reason}; resuming from the checkpoint at {at} env steps instead of {int(checkpoint.name)}")
    root = run_dir / "checkpoints"
    if root.is_dir():  # damaged checkpoints and partial ones (a kill while writing) go
        for entry in root.iterdir():
            kept = (
                r.checkpoint is not None
                and is_checkpoint_name(entry.name)
                and entry.name <= r.checkpoint.name
            )
            if entry.is_dir() and not kept:
                shutil.rmtree(entry, ignore_errors=True)
    truncate_csv(run_dir / "episodes.csv", EPISODE_COLUMNS, r.state["episodes"] if r.state else 0)
    truncate_csv(run_dir / "evaluations.csv", EVALUATION_COLUMNS, r.state["evaluations"] if r.state else 0)
    truncate_timing(run_dir / "timing.csv", at)
    if config["recipe"].get("steps") != recipe.steps:  # a new budget: the config says so
        atomic_write_text(
            run_dir / "config.toml", tomli_w.dumps({**config, "recipe": recipe_to_dict(recipe)})
        )
    (run_dir / "summary.json").unlink(missing_ok=True)
    damaged = [{"env_steps": int(p.name), "reason": reason} for p, reason in r.damaged]
    extra = {"damaged_checkpoints": damaged} if damaged else {}
    record_resume(run_dir, argv, at, recipe.steps, **extra)


Start = Callable[[Any], tuple[Any, Any, dict[str, int] | None]]
"""Given new training envs: the agent, the envs to train on and the checkpoint's counters (None:
a new start). Everything is checked before it writes the run's first files of this session."""


def _run(
    recipe: Recipe, spec: CoachSpec | None, run_dir: Path, progress_bar: bool, start: Start
) -> TrainResult:
    """One training session, on ``recipe.threads`` threads: torch's, and the BLAS numpy calls.

    The coach's own numerics (a classifier region's scores, the model predictor's bounds) are numpy
    matrix products; left at the BLAS library's default they spread over every core, and in a sweep
    whose workers already fill the cores they wait on each other (the model predictor on Hopper ran
    several times slower so).
    """
    import torch
    from threadpoolctl import threadpool_limits

    torch.set_num_threads(recipe.threads)
    with threadpool_limits(limits=recipe.threads, user_api="blas"):
        return _session(recipe, spec, run_dir, progress_bar, start)


def _session(
    recipe: Recipe, spec: CoachSpec | None, run_dir: Path, progress_bar: bool, start: Start
) -> TrainResult:
    started = time.perf_counter()
    earlier_s = _earlier_wall_s(Path(run_dir))
    trainer = _Trainer(recipe, spec, run_dir, progress_bar)
    trainer.clock = lambda: earlier_s + time.perf_counter() - started
    trainer.couplings = couplings_of(recipe, spec)
    c = trainer.counters
    try:
        trainer.venv = make_vec_env(recipe, spec)
        model, trainer.venv, state = start(trainer.venv)
        trainer.model = model
        _set_counters(trainer, state)
        _count_policy_updates(model, c)
        model.set_logger(trainer.sb3_logger)
        stopped = _learn(trainer, resumed=state is not None) if c.env_steps < recipe.steps else False
        trainer.settle_rollins()
        completed = not stopped and c.env_steps >= recipe.steps
        final: dict[str, str] = {}
        if completed:
            if not evaluated_at(run_dir, c.env_steps):
                trainer.evaluate()
            final = _save_final(trainer)
        trainer.checkpoint()
        wall = time.perf_counter() - started
        summary = _run_summary(trainer, completed, wall, earlier_s)
        write_json(run_dir / "summary.json", {**summary, "files": final} if final else summary)
        return TrainResult(
            run_dir, c.env_steps, c.agent_steps, c.coach_steps, c.interventions, c.episodes, completed,
            trainer.last_evaluation, wall, c.env_episodes, c.env_resets, c.falls,
        )  # fmt: skip
    finally:
        trainer.close()


def sb3_update_count(model: Any) -> int:
    """Gradient steps of the policy by SB3's own count (for checkpoints written before pidlab counted them).

    SAC's ``_n_updates`` counts gradient steps; PPO's counts epochs, each of
    ``ceil(n_steps * n_envs / batch_size)`` gradient steps (exact unless ``target_kl`` cut an epoch short).
    """
    n = int(model._n_updates)
    return n * ppo_batches_per_epoch(model) if hasattr(model, "n_epochs") else n


def ppo_batches_per_epoch(model: Any) -> int:
    """PPO's gradient steps per epoch: ``ceil(n_steps * n_envs / batch_size)``."""
    return -(-int(model.n_steps) * int(model.n_envs) // int(model.batch_size))


def _count_policy_updates(model: Any, counters: Counters) -> None:
    """Count the gradient steps of the policy's optimizer into ``counters.policy_updates``.

    PPO's one optimizer updates actor and critic together; SAC's actor has its own. A post-step
    hook counts each step exactly (PPO's ``target_kl`` early stop included), which SB3's own
    ``_n_updates`` does not (it counts PPO epochs).
    """
    policy = model.policy
    optimizer = policy.actor.optimizer if hasattr(policy, "actor") else policy.optimizer

    def count(*_: Any) -> None:
        counters.policy_updates += 1

    optimizer.register_step_post_hook(count)


def _set_counters(trainer: _Trainer, state: dict[str, int] | None) -> None:
    """Counters, seed and logs of a new start (``state`` None) or of a resume from a checkpoint."""
    c, recipe = trainer.counters, trainer.recipe
    if state is None:
        c.next_checkpoint = recipe.checkpoint_every
        trainer.open_logs(purge_env_step=None, purge_agent_step=None)
        return
    for key in c.to_dict():
        setattr(c, key, int(state.get(key, 0)))
    if "policy_updates" not in state:
        c.policy_updates = sb3_update_count(trainer.model)
    if "env_episodes" not in state:
        _derive_env_counters(trainer, state)
    c.resumes += 1
    trainer.model._last_obs = None  # the envs are new: start fresh episodes
    # a resumed run is reproducible too: its seed depends on where it resumed
    trainer.model.set_random_seed(recipe.seed + 7919 * c.resumes + c.agent_steps)
    trainer.open_logs(purge_env_step=c.env_steps, purge_agent_step=int(state["num_timesteps"]))


def _derive_env_counters(trainer: _Trainer, state: dict[str, int]) -> None:
    """The env counters of a checkpoint written before pidlab kept them, from its ``episodes.csv``.

    Such a run had no ``terminal`` view: every episode ended the env's too, and a terminated one
    was a fall. Each of its sessions (the first and one per resume) reset every env once.
    """
    c = trainer.counters
    kept = read_csv_rows(trainer.run_dir / "episodes.csv")[: state["episodes"]]
    c.env_episodes = sum(int(r["env_end"]) for r in kept)
    c.falls = sum(int(r["fell"]) for r in kept)
    c.env_resets = c.env_episodes + trainer.recipe.n_envs * (int(state.get("resumes", 0)) + 1)


def _learn(trainer: _Trainer, resumed: bool) -> bool:
    """Train until the budget is spent or a signal stops it; True when stopped by a signal.

    A new run first calls its couplings (:func:`pidlab.rl.couplings.couplings_of`) under the same
    signal handler and progress bar; a stop asked for meanwhile takes effect once they are done
    (they end with a checkpoint).
    """
    from tqdm.auto import tqdm

    recipe, spec, c, model = trainer.recipe, trainer.spec, trainer.counters, trainer.model
    coach = spec.name if spec is not None else "uncoached"
    with (
        _Stop() as stop,
        tqdm(
            total=recipe.steps,
            initial=c.env_steps,
            desc=f"{recipe.env_id} {coach} {recipe.algo} seed {recipe.seed}",
            unit="step",
            disable=not trainer.progress_bar,
            dynamic_ncols=True,
        ) as bar,
    ):
        trainer.stop = stop
        trainer.bar = bar
        if not resumed:
            for coupling in trainer.couplings:
                coupling.before_learning(trainer)
        if stop.requested:
            return True
        for coupling in trainer.couplings:
            coupling.on_session(trainer)
        model.learn(
            total_timesteps=max(recipe.steps - int(model.num_timesteps), 1),
            callback=_make_callback(trainer),
            reset_num_timesteps=not (resumed or trainer.envs_running),
            progress_bar=False,
        )
        return stop.requested


def _save_final(trainer: _Trainer) -> dict[str, str]:
    """The final agent (model and normalizer, no replay buffer) into the run folder; their digests.

    Each file is written under a temporary name and renamed into place.
    """
    run_dir = trainer.run_dir
    tmp = run_dir / ".final.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        files = save_agent(tmp, trainer.model, trainer.venv, buffer=False)
        for name in files:
            (tmp / name).replace(run_dir / FINAL[name])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return files


def _result_from_summary(run_dir: Path, s: dict[str, Any]) -> TrainResult:
    ev = s.get("final_evaluation")
    final = None
    if ev:
        final = AgentEvaluation(tuple(ev["seeds"]), tuple(ev["returns"]), tuple(ev["lengths"]))
    return TrainResult(
        run_dir, int(s["env_steps"]), int(s["agent_steps"]), int(s["coach_steps"]), int(s["interventions"]),
        int(s["episodes"]), bool(s["completed"]), final, 0.0, int(s.get("env_episodes", s["episodes"])),
        int(s.get("env_resets", 0)), int(s.get("falls", 0)),
    )  # fmt: skip
