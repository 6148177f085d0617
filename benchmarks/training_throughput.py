"""Env steps per second of a whole ``pidlab train`` run against raw SB3 PPO (one env) and MuJoCo alone.

Writes docs/training-throughput.md. Run:
    .venv/bin/python benchmarks/training_throughput.py [--repeats 2] [--envs InvertedPendulum-v5,Hopper-v5]

For each env, in paired rounds (the configurations of a round run back to back, so a slow phase of a
shared machine hits all of them), every configuration trains uncoached PPO with the recipe's
hyperparameters for the same number of env steps:

- ``raw SB3, 1 env``: ``PPO("MlpPolicy", VecNormalize(DummyVecEnv([Monitor(gym.make(ENV))])))`` with
  the zoo's values of coach/ENV.toml's ``[ppo]`` source (1 env), ``learn()`` only: no evaluation, no
  logs, no checkpoints.
- ``pidlab train, recipe``: :func:`pidlab.rl.train.train` with the shipped recipe (its ``n_envs``),
  the whole call: env construction, the agent-alone evaluations (every ``evaluation.every`` env
  steps, ``evaluation.episodes`` episodes each; their env steps are extra and not counted),
  episode logs, TensorBoard, checkpoints, the final model and summary.
- ``pidlab train, 1 env``: the same with ``n_envs = 1`` and the zoo's ``n_steps``/``batch_size``.

The ceiling is MuJoCo alone: ``mj_step`` ``frame_skip`` times per env step (no Python env, no policy),
and the bare Gymnasium env with random actions. torch runs on one thread everywhere (the recipes'
``threads = 1``).
"""

from __future__ import annotations

import dataclasses
import os
import platform
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np
import torch
from bench_cli import Parser, count, names, run
from stable_baselines3 import PPO
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

from pidlab import __version__
from pidlab.files import atomic_write_text
from pidlab.provenance import git_state
from pidlab.rl.recipe import Recipe, load_recipe
from pidlab.rl.rundir import read_csv_rows
from pidlab.rl.train import sb3_arguments, train

ROOT = Path(__file__).resolve().parents[1]
STEPS = {"InvertedPendulum-v5": 30000, "Hopper-v5": 50000}
ZOO_ROLLOUT = {"InvertedPendulum-v5": (32, 32), "Hopper-v5": (512, 32)}  # the zoo's n_steps, batch_size


def single_env(recipe: Recipe) -> Recipe:
    """The recipe with one env and the zoo's rollout (what pidlab trained before issue 19)."""
    n_steps, batch = ZOO_ROLLOUT[recipe.env_id]
    ppo = {**recipe.algorithms["ppo"], "n_steps": n_steps, "batch_size": batch}
    return dataclasses.replace(recipe, n_envs=1, algorithms={**recipe.algorithms, "ppo": ppo})


def raw_sb3(recipe: Recipe, steps: int) -> float:
    """Seconds of ``learn()`` for raw SB3 PPO, one env, the zoo's values."""
    r = single_env(recipe)
    venv = DummyVecEnv([lambda: Monitor(gym.make(r.env_id))])
    gamma = float(r.hyperparameters.get("gamma", 0.99))
    venv = VecNormalize(venv, norm_obs=r.normalize_obs, norm_reward=r.normalize_reward, gamma=gamma)
    model = PPO("MlpPolicy", venv, seed=0, device="cpu", verbose=0, **sb3_arguments(r))
    start = time.perf_counter()
    model.learn(total_timesteps=steps)
    wall = time.perf_counter() - start
    venv.close()
    return wall


def pidlab_run(recipe: Recipe, steps: int) -> tuple[float, int]:
    """Seconds of a whole :func:`train` call, and the env steps its evaluations took."""
    folder = Path(tempfile.mkdtemp(prefix="pidlab-throughput-"))
    try:
        start = time.perf_counter()
        result = train(
            dataclasses.replace(recipe, steps=steps, seed=0), None, folder / "run", progress_bar=False
        )
        wall = time.perf_counter() - start
        rows = read_csv_rows(folder / "run" / "evaluations.csv")
        eval_steps = round(sum(float(r["mean_length"]) * recipe.evaluation.episodes for r in rows))
        assert result.env_steps >= steps
        return wall, eval_steps
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def mujoco_rate(env_id: str, steps: int = 20000) -> tuple[float, float]:
    """Env steps/s of MuJoCo alone (``mj_step`` x frame_skip) and of the bare Gymnasium env."""
    env = gym.make(env_id)
    env.reset(seed=0)
    inner = env.unwrapped
    m, d, skip = inner.model, inner.data, inner.frame_skip
    start = time.perf_counter()
    for i in range(steps):
        if i % 500 == 0:
            mujoco.mj_resetData(m, d)
        for _ in range(skip):
            mujoco.mj_step(m, d)
    raw = steps / (time.perf_counter() - start)
    actions = np.random.default_rng(0).uniform(
        env.action_space.low, env.action_space.high, (steps, *env.action_space.shape)
    )
    env.reset(seed=0)
    start = time.perf_counter()
    for a in actions:
        _, _, te, tr, _ = env.step(a)
        if te or tr:
            env.reset()
    bare = steps / (time.perf_counter() - start)
    return raw, bare


@dataclasses.dataclass(frozen=True)
class EnvFigures:
    """Paired figures of one env (env steps per second)."""

    env_id: str
    steps: int
    recipe: Recipe
    raw: tuple[float, ...]
    vec: tuple[float, ...]
    one: tuple[float, ...]
    eval_steps: int
    mujoco: float
    gym_env: float
    shares: dict[str, float]


def measure(env_id: str, steps: int, repeats: int) -> EnvFigures:
    """``repeats`` paired rounds of raw SB3, pidlab (recipe) and pidlab (1 env)."""
    recipe = load_recipe(ROOT / "coach" / f"{env_id}.toml")
    raw, vec, one = [], [], []
    eval_steps = 0
    for i in range(repeats):
        raw.append(steps / raw_sb3(recipe, steps))
        wall, eval_steps = pidlab_run(recipe, steps)
        vec.append(steps / wall)
        one.append(steps / pidlab_run(single_env(recipe), steps)[0])
        print(f"{env_id} round {i + 1}: raw {raw[-1]:.0f}, pidlab {vec[-1]:.0f}, "
              f"pidlab 1 env {one[-1]:.0f} env steps/s",
              flush=True)  # fmt: skip
    mj, bare = mujoco_rate(env_id)
    shares = where_time_goes(recipe, steps)
    return EnvFigures(env_id, steps, recipe, tuple(raw), tuple(vec), tuple(one), eval_steps, mj, bare, shares)


PARTS = {  # (file suffix, function): what the share measures
    "rollout collection (policy forward, env steps, wrappers; evaluations excluded)": (
        "on_policy_algorithm.py", "collect_rollouts"),
    "PPO updates": ("ppo.py", "train"),
    "agent-alone evaluations": ("pidlab/rl/evaluation.py", "evaluate_agent"),
    "episode logs (CSV + TensorBoard)": ("pidlab/rl/train.py", "log_episode"),
    "checkpoints and the final model": ("pidlab/rl/train.py", "checkpoint"),
    "MuJoCo (mj_step, training and evaluation)": ("~", "<built-in method mujoco._functions.mj_step>"),
}


def where_time_goes(recipe: Recipe, steps: int) -> dict[str, float]:
    """Shares of a whole :func:`train` call per part (cProfile: indicative, its overhead inflates Python)."""
    import cProfile
    import pstats

    profiler = cProfile.Profile()
    profiler.runcall(pidlab_run, recipe, steps)
    stats = pstats.Stats(profiler).stats  # type: ignore[attr-defined]
    total = max(ct for (f, _, name), (_, _, _, ct, _) in stats.items() if name == "pidlab_run")
    shares = {}
    for label, (suffix, func) in PARTS.items():
        cum = sum(
            ct for (f, _, name), (_, _, _, ct, _) in stats.items() if name == func and f.endswith(suffix)
        )
        shares[label] = cum / total
    shares["rollout collection (policy forward, env steps, wrappers; evaluations excluded)"] -= shares[
        "agent-alone evaluations"
    ]  # evaluations run from the callback inside the rollout loop
    return shares


def _rate(x: tuple[float, ...]) -> str:
    return f"{statistics.median(x):,.0f} ({min(x):,.0f}-{max(x):,.0f})"


def _ratio(x: tuple[float, ...], y: tuple[float, ...]) -> str:
    ratios = [a / b for a, b in zip(x, y, strict=True)]
    return f"{statistics.median(ratios):.2f}x ({min(ratios):.2f}-{max(ratios):.2f})"


def report(figs: list[EnvFigures], repeats: int) -> str:
    """docs/training-throughput.md."""
    git = git_state(ROOT)
    lines = [
        "# Training throughput",
        "",
        "<!-- written by benchmarks/training_throughput.py: do not edit -->",
        "",
        "Env steps per second of a whole `pidlab train` run (evaluations, logs, checkpoints included),",
        "paired with raw SB3 PPO on one env with the same hyperparameters and no evaluation. Median over",
        f"{repeats} paired rounds (range in brackets); torch on one thread. The evaluations' own env steps",
        "are extra work that the rates do not count (they are not charged to the budget either).",
        "",
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch on "
        f"{torch.get_num_threads()} thread, Python {platform.python_version()}, "
        f"pidlab {__version__} ({(git.get('sha') or '?')[:10]}), "
        f"MuJoCo {mujoco.__version__}, torch {torch.__version__}.",
        "",
        "| env | budget, env steps | raw SB3, 1 env (steps/s) | pidlab train, recipe (steps/s) | "
        "ratio to raw SB3 | "
        "pidlab train, 1 env (steps/s) | ratio to raw SB3 | evaluation env steps (extra) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for f in figs:
        lines.append(
            f"| {f.env_id} | {f.steps:,} | {_rate(f.raw)} | {_rate(f.vec)} | **{_ratio(f.vec, f.raw)}** | "
            f"{_rate(f.one)} | {_ratio(f.one, f.raw)} | {f.eval_steps:,} |"
        )
    lines += [
        "",
        "The recipe's settings: "
        + "; ".join(
            f"{f.env_id} `n_envs = {f.recipe.n_envs}`, "
            f"`n_steps = {f.recipe.hyperparameters['n_steps']}` per env, "
            f"`batch_size = {f.recipe.hyperparameters['batch_size']}`"
            for f in figs
        )
        + " (why: [vectorized training](vectorization.md)).",
        "",
        "## The physical ceiling",
        "",
        "| env | MuJoCo alone (env steps/s) | bare Gymnasium env, random actions (env steps/s) | "
        "pidlab train / MuJoCo alone | raw SB3 / MuJoCo alone |",
        "|---|---|---|---|---|",
    ]
    for f in figs:
        lines.append(
            f"| {f.env_id} | {f.mujoco:,.0f} | {f.gym_env:,.0f} | "
            f"{statistics.median(f.vec) / f.mujoco:.1%} | "
            f"{statistics.median(f.raw) / f.mujoco:.1%} |"
        )
    lines += [
        "",
        "## Where a pidlab run's time goes now",
        "",
        "Shares of one whole `pidlab train` call with the recipe (cProfile; its overhead inflates the",
        "Python-heavy parts, so read the shares as indicative). Parts overlap where one calls another:",
        "MuJoCo's share is inside rollouts and evaluations.",
        "",
        "| part | " + " | ".join(f.env_id for f in figs) + " |",
        "|---|" + "---:|" * len(figs),
    ]
    for label in PARTS:
        lines.append(f"| {label} | " + " | ".join(f"{f.shares[label]:.1%}" for f in figs) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = Parser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=count, default=2)
    parser.add_argument("--envs", type=names(STEPS), default=",".join(STEPS))
    args = parser.parse_args()
    torch.set_num_threads(1)
    figs = [measure(env_id, STEPS[env_id], args.repeats) for env_id in args.envs.split(",")]
    text = report(figs, args.repeats)
    atomic_write_text(ROOT / "docs" / "training-throughput.md", text)
    print(text)


if __name__ == "__main__":
    run(main)
