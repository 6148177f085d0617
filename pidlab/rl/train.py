"""Coached training with Stable-Baselines3: logs, agent-alone evaluation, checkpoints, resume.

:func:`train` trains one agent from a recipe (``coach/``) with or without a coach spec
(``tuning/``). The coach runs inside :class:`pidlab.rl.coaching.CoachingWrapper`, so the SB3
algorithm only ever stores the agent's own transitions. The budget is counted in **env steps**
(agent steps + coach steps): a coached run is charged for every step its coach takes.

A run directory holds::

    config.toml          the resolved recipe (overrides applied) and which coach
    coach.toml           the coach spec used (absent for --coach none)
    run.json             seed, command, package versions, git SHA, start and resume times
    episodes.csv         one row per finished training episode
    evaluations.csv      one row per agent-alone evaluation (coach off, fixed seeds)
    tb/                  TensorBoard: pidlab's scalars (x = env steps), tb/sb3: SB3's (x = agent steps)
    checkpoints/<env steps>/   model.zip, vecnormalize.pkl, replay_buffer.pkl (SAC), state.json
    final_model.zip      (and final_vecnormalize.pkl) when the budget is spent
    summary.json         totals, final evaluation, wall time

:mod:`pidlab.rl.rundir` writes and reads these files. :func:`resume` continues from the newest
complete checkpoint: the CSV files are cut back to the rows that checkpoint had recorded (so no
episode is lost or logged twice), the model, normalization statistics and replay buffer are
reloaded, and the envs start fresh episodes. Episodes in progress at the checkpoint are not
logged (their env steps stay counted). SIGINT/SIGTERM stop at the next step with a checkpoint.
"""

from __future__ import annotations

import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import tomli_w

from pidlab.controller.spec import CoachSpec
from pidlab.files import atomic_write_bytes, atomic_write_text, read_json, write_json
from pidlab.rl.coaching import CoachingWrapper
from pidlab.rl.evaluation import AgentEvaluation, evaluate_agent, sb3_policy
from pidlab.rl.recipe import LINEAR_SCHEDULES, Recipe
from pidlab.rl.rundir import (
    EPISODE_COLUMNS,
    EVALUATION_COLUMNS,
    CsvLog,
    RunDirError,
    config_dict,
    evaluated_at,
    latest_checkpoint,
    load_run_config,
    prepare_run_dir,
    record_resume,
    truncate_csv,
)

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
    """Running totals of a training run (what a checkpoint records)."""

    env_steps: int = 0
    agent_steps: int = 0
    coach_steps: int = 0
    interventions: int = 0
    episodes: int = 0
    evaluations: int = 0
    next_evaluation: int = 0
    next_checkpoint: int = 0
    resumes: int = 0

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
    completed : bool
        The budget was spent (False: stopped by a signal, resumable).
    final_evaluation : AgentEvaluation or None
    wall_s : float
        Seconds spent in this call.
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


@dataclass(frozen=True)
class EnvFactory:
    """Builds one training env: ``gym.make`` -> coaching wrapper -> SB3 Monitor (picklable)."""

    env_id: str
    spec: CoachSpec | None
    recipe: Recipe

    def __call__(self) -> gym.Env:
        """A new env."""
        from stable_baselines3.common.monitor import Monitor

        c = self.recipe.coaching
        env = gym.make(self.env_id)
        wrapped = CoachingWrapper(
            env,
            self.spec,
            mode=c.mode,
            region=c.region,
            trigger=c.trigger,
            nudge_steps=c.nudge_steps,
            max_coach_steps=c.max_coach_steps,
            reward=c.reward,
            probability=c.probability,
            width=c.width,
            off_after=c.off_after,
        )
        return Monitor(wrapped)


def _schedules_move(recipe: Recipe, spec: CoachSpec | None) -> bool:
    c = recipe.coaching
    return spec is not None and (
        c.probability.shape != "constant" or c.width.shape != "constant" or c.off_after is not None
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
        print(
            f"\npidlab: {signal.Signals(signum).name}: stopping at the next step with a checkpoint "
            "(send it again to stop at once)",
            file=sys.stderr,
            flush=True,
        )

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
    eval_env: Any = None
    moving: bool = False
    _progress_tick: int = -1

    # -- setup
    def open_logs(self, purge_env_step: int | None, purge_agent_step: int | None) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.episodes_log = CsvLog(self.run_dir / "episodes.csv", EPISODE_COLUMNS)
        self.evaluations_log = CsvLog(self.run_dir / "evaluations.csv", EVALUATION_COLUMNS)
        self.tb = SummaryWriter(str(self.run_dir / "tb"), purge_step=purge_env_step)
        from stable_baselines3.common.logger import Logger, TensorBoardOutputFormat

        class PurgingTensorBoard(TensorBoardOutputFormat):
            """SB3's TensorBoard output, hiding events past the checkpoint a run resumed from."""

            def __init__(self, folder: str, purge_step: int | None) -> None:
                self.writer = SummaryWriter(folder, purge_step=purge_step)
                self._is_closed = False

        fmt = PurgingTensorBoard(str(self.run_dir / "tb" / "sb3"), purge_agent_step)
        self.sb3_logger = Logger(folder=str(self.run_dir / "tb" / "sb3"), output_formats=[fmt])
        self.eval_env = gym.make(self.recipe.env_id)
        self.moving = _schedules_move(self.recipe, self.spec)

    def close(self) -> None:
        for closable in (self.episodes_log, self.evaluations_log, self.tb, self.sb3_logger, self.eval_env,
                         self.venv):  # fmt: skip
            if closable is not None:
                closable.close()

    # -- SB3 hooks
    def on_start(self) -> None:
        if self.counters.evaluations == 0:
            self.evaluate()
        self._set_progress(force=True)
        self._bar_update()

    def on_step(self, infos: list[dict[str, Any]]) -> bool:
        c = self.counters
        for i, info in enumerate(infos):
            coach_steps = int(info.get("coach_steps", 0))
            c.agent_steps += 1
            c.coach_steps += coach_steps
            c.env_steps += 1 + coach_steps
            c.interventions += int(bool(info.get("intervened", False)))
            episode = info.get("coaching_episode")
            if episode is not None:
                self.log_episode(i, episode)
        self._set_progress()
        if c.env_steps >= c.next_evaluation:
            self.evaluate()
        self._bar_update()
        if self.stop is not None and self.stop.requested:
            return False
        return c.env_steps < self.recipe.steps

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
            sb3_policy(self.model, normalizer), self.eval_env, self.recipe.evaluation.seeds
        )
        r = np.array(result.returns)
        self.evaluations_log.write([
            c.env_steps, c.agent_steps, c.episodes, result.mean, result.std, float(r.min()), float(r.max()),
            result.mean_length, ";".join(repr(float(v)) for v in r),
        ])  # fmt: skip
        c.evaluations += 1
        every = self.recipe.evaluation.every
        c.next_evaluation = (c.env_steps // every + 1) * every
        self.tb.add_scalar("eval/mean_return", result.mean, c.env_steps)
        self.tb.add_scalar("eval/std_return", result.std, c.env_steps)
        self.last_evaluation = result
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
        from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
        from stable_baselines3.common.vec_env import VecNormalize

        c = self.counters
        every = self.recipe.checkpoint_every
        c.next_checkpoint = (c.env_steps // every + 1) * every
        folder = self.run_dir / "checkpoints" / f"{c.env_steps:012d}"
        if folder.exists():
            shutil.rmtree(folder)
        folder.mkdir(parents=True)
        self.model.save(folder / "model.zip")
        if isinstance(self.venv, VecNormalize):
            self.venv.save(str(folder / "vecnormalize.pkl"))
        if isinstance(self.model, OffPolicyAlgorithm):
            self.model.save_replay_buffer(folder / "replay_buffer.pkl")
        self.episodes_log.sync()
        self.evaluations_log.sync()
        self.tb.flush()
        state = {**c.to_dict(), "num_timesteps": int(self.model.num_timesteps)}
        write_json(folder / "state.json", state)  # written last: marks the checkpoint complete
        for old in (self.run_dir / "checkpoints").iterdir():
            if old != folder:
                shutil.rmtree(old, ignore_errors=True)
        return folder

    def _bar_update(self) -> None:
        if self.bar is None or self.bar.disable:
            return
        c = self.counters
        post = {"episodes": c.episodes, "coach %": f"{100 * c.coach_steps / max(c.env_steps, 1):.1f}"}
        if self.last_evaluation is not None:
            post["alone"] = f"{self.last_evaluation.mean:.0f}"
        self.bar.set_postfix(post, refresh=False)
        self.bar.update(min(c.env_steps, self.recipe.steps) - self.bar.n)


def _run_summary(trainer: _Trainer, completed: bool, wall_s: float) -> dict[str, Any]:
    c = trainer.counters
    ev = trainer.last_evaluation
    return {
        "completed": completed,
        "budget_env_steps": trainer.recipe.steps,
        **c.to_dict(),
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
        ``run_dir`` exists and is not empty.
    """
    run_dir = Path(run_dir)
    EnvFactory(recipe.env_id, spec, recipe)().close()  # a coach that cannot run fails here, before any file
    prepare_run_dir(run_dir, recipe, spec, coach_source, argv)
    return _run(recipe, spec, run_dir, None, progress_bar)


def resume(
    run_dir: str | Path, *, steps: int | None = None, progress_bar: bool = True, argv: list[str] | None = None
) -> TrainResult:
    """Continue the run in ``run_dir`` from its newest complete checkpoint.

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
        Not a run directory, or ``steps`` below what the run has already done.
    """
    run_dir = Path(run_dir)
    recipe, spec, config = load_run_config(run_dir)
    if steps is not None:
        if steps < 1:
            raise RunDirError(f"--steps {steps}: expected a positive number of env steps")
        recipe = replace(recipe, steps=steps)
    summary_path = run_dir / "summary.json"
    if summary_path.exists():
        done = read_json(summary_path)
        if done.get("completed") and int(done.get("env_steps", 0)) >= recipe.steps:
            return _result_from_summary(run_dir, done)
    checkpoint = latest_checkpoint(run_dir)
    if (run_dir / "checkpoints").is_dir():
        for partial in (run_dir / "checkpoints").iterdir():
            if partial != checkpoint:  # an unfinished checkpoint from the kill
                shutil.rmtree(partial, ignore_errors=True)
    state = read_json(checkpoint / "state.json") if checkpoint else None
    if state is not None and steps is not None and steps < int(state["env_steps"]):
        raise RunDirError(f"--steps {steps}: the run has already done {state['env_steps']} env steps")
    truncate_csv(run_dir / "episodes.csv", EPISODE_COLUMNS, int(state["episodes"]) if state else 0)
    truncate_csv(run_dir / "evaluations.csv", EVALUATION_COLUMNS, int(state["evaluations"]) if state else 0)
    record_resume(run_dir, argv, int(state["env_steps"]) if state else 0, recipe.steps)
    coach = config.get("coach", {})
    atomic_write_text(run_dir / "config.toml", tomli_w.dumps(config_dict(recipe, spec, coach.get("source"))))
    summary_path.unlink(missing_ok=True)
    return _run(recipe, spec, run_dir, (checkpoint, state) if checkpoint and state else None, progress_bar)


def _run(
    recipe: Recipe,
    spec: CoachSpec | None,
    run_dir: Path,
    restart: tuple[Path, dict[str, Any]] | None,
    progress_bar: bool,
) -> TrainResult:
    import torch
    from stable_baselines3.common.vec_env import VecNormalize
    from tqdm.auto import tqdm

    started = time.perf_counter()
    torch.set_num_threads(recipe.threads)
    trainer = _Trainer(recipe, spec, run_dir, progress_bar)
    cls = _algorithm_class(recipe.algo)
    c = trainer.counters
    try:
        trainer.venv = make_vec_env(recipe, spec)
        if restart is not None:
            checkpoint, state = restart
            for key in c.to_dict():
                setattr(c, key, int(state.get(key, 0)))
            c.resumes += 1
            if isinstance(trainer.venv, VecNormalize):
                trainer.venv = VecNormalize.load(str(checkpoint / "vecnormalize.pkl"), trainer.venv.venv)
                trainer.venv.training = True
            model = cls.load(checkpoint / "model.zip", env=trainer.venv, device="cpu")
            if (checkpoint / "replay_buffer.pkl").exists():
                model.load_replay_buffer(checkpoint / "replay_buffer.pkl")
            model._last_obs = None  # the envs are new: start fresh episodes
            # a resumed run is reproducible too: its seed depends on where it resumed
            model.set_random_seed(recipe.seed + 7919 * c.resumes + c.agent_steps)
            trainer.open_logs(purge_env_step=c.env_steps, purge_agent_step=int(state["num_timesteps"]))
        else:
            model = cls(
                "MlpPolicy", trainer.venv, seed=recipe.seed, device="cpu", verbose=0, **sb3_arguments(recipe)
            )
            c.next_checkpoint = recipe.checkpoint_every
            trainer.open_logs(purge_env_step=None, purge_agent_step=None)
        model.set_logger(trainer.sb3_logger)
        trainer.model = model
        stopped = False
        if c.env_steps < recipe.steps:
            coach = spec.name if spec is not None else "uncoached"
            with (
                _Stop() as stop,
                tqdm(
                    total=recipe.steps,
                    initial=c.env_steps,
                    desc=f"{recipe.env_id} {coach} {recipe.algo} seed {recipe.seed}",
                    unit="step",
                    disable=not progress_bar,
                    dynamic_ncols=True,
                ) as bar,
            ):
                trainer.stop = stop
                trainer.bar = bar
                model.learn(
                    total_timesteps=max(recipe.steps - int(model.num_timesteps), 1),
                    callback=_make_callback(trainer),
                    reset_num_timesteps=restart is None,
                    progress_bar=False,
                )
                stopped = stop.requested
        completed = not stopped and c.env_steps >= recipe.steps
        if completed:
            if not evaluated_at(run_dir, c.env_steps):
                trainer.evaluate()
            _save_final(trainer)
        trainer.checkpoint()
        wall = time.perf_counter() - started
        write_json(run_dir / "summary.json", _run_summary(trainer, completed, wall))
        return TrainResult(
            run_dir, c.env_steps, c.agent_steps, c.coach_steps, c.interventions, c.episodes, completed,
            trainer.last_evaluation, wall,
        )  # fmt: skip
    finally:
        trainer.close()


def _save_final(trainer: _Trainer) -> None:
    import pickle

    from stable_baselines3.common.vec_env import VecNormalize

    run_dir = trainer.run_dir
    tmp = run_dir / ".final_model.tmp.zip"
    trainer.model.save(tmp)
    tmp.replace(run_dir / "final_model.zip")
    if isinstance(trainer.venv, VecNormalize):
        # what VecNormalize.save writes (the VecEnv itself is not pickled), written atomically
        atomic_write_bytes(run_dir / "final_vecnormalize.pkl", pickle.dumps(trainer.venv))


def _result_from_summary(run_dir: Path, s: dict[str, Any]) -> TrainResult:
    ev = s.get("final_evaluation")
    final = None
    if ev:
        final = AgentEvaluation(tuple(ev["seeds"]), tuple(ev["returns"]), tuple(ev["lengths"]))
    return TrainResult(
        run_dir, int(s["env_steps"]), int(s["agent_steps"]), int(s["coach_steps"]), int(s["interventions"]),
        int(s["episodes"]), bool(s["completed"]), final, 0.0,
    )  # fmt: skip
