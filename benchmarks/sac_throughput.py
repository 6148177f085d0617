"""Env steps per second of SAC: ``pidlab train`` against raw SB3 SAC and SBX (JAX) SAC, in paired rounds.

Writes docs/sac-throughput.md. Run (the SBX arm needs ``sbx-rl`` in the interpreter's environment;
without it the arm is skipped and the page says so):

    .venv/bin/python benchmarks/sac_throughput.py [--repeats 3] [--envs Hopper-v5] [--steps 4000]

SAC makes one gradient step per env step (the recipes' ``[sac]`` tables: ``train_freq`` =
``gradient_steps``), so its rate is set by the updates. Every arm runs in a fresh process pinned to
one core (``sched_setaffinity``; torch and XLA on one thread), in rounds whose arms run back to back
so that a slow phase of a shared machine hits all of them. Each arm trains from scratch with the
recipe's ``[sac]`` values and normalization, ``learning_starts`` = 1,000, and is timed over the
``--steps`` env steps after it (the update phase; the random warm-up and SBX's compilation are
outside the timing):

- ``raw SB3``: ``SAC("MlpPolicy", VecNormalize(DummyVecEnv([Monitor(gym.make(ENV))])))``, ``learn()``
  only;
- ``pidlab train``: :func:`pidlab.rl.train.train` uncoached, the whole call from the warm-up's end
  (env step 1,000) to the budget: episode logs, TensorBoard, the agent-alone evaluations of the
  recipe (their env steps are extra and not counted), checkpoints, the final model;
- ``SBX``: ``sbx.SAC`` (its JAX implementation of the same algorithm) on the same envs;
- ``raw SB3, 2 threads``: raw SB3 with torch on two threads and both cores (one run alone on
  the machine).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench_cli import EXIT_BAD_INPUT, Parser, count, fail, run

ROOT = Path(__file__).resolve().parents[1]
WARMUP = 1000
ARMS = ("raw", "pidlab", "sbx", "raw2")
LABELS = {
    "raw": "raw SB3, 1 core",
    "pidlab": "pidlab train, 1 core",
    "sbx": "SBX (JAX), 1 core",
    "raw2": "raw SB3, 2 threads on 2 cores",
}


def _recipe(env_id: str, steps: int) -> Any:  # a Recipe; pidlab is imported late, after pinning
    from pidlab.rl.recipe import load_recipe, with_overrides

    recipe = with_overrides(load_recipe(ROOT / "coach" / f"{env_id}.toml"), algo="sac", steps=steps, seed=0)
    sac = {**recipe.algorithms["sac"], "learning_starts": WARMUP}
    return dataclasses.replace(recipe, algorithms={**recipe.algorithms, "sac": sac})


def _venv(recipe: Any) -> Any:
    import gymnasium as gym
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    venv = DummyVecEnv([lambda: Monitor(gym.make(recipe.env_id))])
    if recipe.normalize_obs or recipe.normalize_reward:
        gamma = float(recipe.hyperparameters.get("gamma", 0.99))
        venv = VecNormalize(
            venv, norm_obs=recipe.normalize_obs, norm_reward=recipe.normalize_reward, gamma=gamma
        )
    return venv


def _timed_learn(model: Any, steps: int) -> float:
    """Seconds of ``steps`` env steps of ``learn()`` after the warm-up (and one compiled update)."""
    model.learn(WARMUP + 1)
    start = time.perf_counter()
    model.learn(steps, reset_num_timesteps=False)
    return time.perf_counter() - start


def arm_raw(env_id: str, steps: int) -> float:
    from stable_baselines3 import SAC

    from pidlab.rl.train import sb3_arguments

    recipe = _recipe(env_id, steps)
    model = SAC("MlpPolicy", _venv(recipe), seed=0, device="cpu", verbose=0, **sb3_arguments(recipe))
    return _timed_learn(model, steps)


SBX_ARGUMENTS = ("learning_rate", "buffer_size", "batch_size", "ent_coef", "gamma", "tau", "train_freq",
                 "gradient_steps", "learning_starts")  # fmt: skip


def arm_sbx(env_id: str, steps: int) -> float:
    from sbx import SAC

    from pidlab.rl.train import sb3_arguments

    recipe = _recipe(env_id, steps)
    kwargs = sb3_arguments(recipe)
    if kwargs.get("use_sde"):
        raise SystemExit(f"{env_id}: its [sac] table uses gSDE, which SBX's SAC does not have")
    chosen = {k: v for k, v in kwargs.items() if k in SBX_ARGUMENTS}
    arch = kwargs.get("policy_kwargs", {}).get("net_arch")
    model = SAC("MlpPolicy", _venv(recipe), seed=0, verbose=0, **chosen,
                policy_kwargs={"net_arch": arch} if arch else None)  # fmt: skip
    return _timed_learn(model, steps)


def arm_pidlab(env_id: str, steps: int) -> float:
    """Seconds of a whole ``train`` call, less the time its warm-up took (timed on its own first)."""
    from pidlab.rl.train import train

    with tempfile.TemporaryDirectory(prefix="pidlab-sac-") as folder:
        recipe = _recipe(env_id, WARMUP + steps)
        warm = dataclasses.replace(recipe, steps=WARMUP)
        start = time.perf_counter()
        train(warm, None, Path(folder) / "warm", progress_bar=False)
        warm_s = time.perf_counter() - start
        start = time.perf_counter()
        result = train(recipe, None, Path(folder) / "run", progress_bar=False)
        wall = time.perf_counter() - start
        assert result.env_steps >= WARMUP + steps
        return wall - warm_s


def run_arm(arm: str, env_id: str, steps: int) -> float:
    """Env steps per second of one arm, in a fresh process pinned as the module docstring says."""
    env = {**os.environ, "PYTHONHASHSEED": "0"}
    if arm != "raw2":
        env["XLA_FLAGS"] = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
    out = subprocess.run(
        [sys.executable, __file__, "--arm", arm, "--envs", env_id, "--steps", str(steps)],
        env=env, capture_output=True, text=True, check=False,
    )  # fmt: skip
    if out.returncode != 0:
        last = (out.stderr.strip().splitlines() or ["no output"])[-1]
        if out.returncode == EXIT_BAD_INPUT:  # the child's one line: bad input, said once
            fail(last.split(": error: ", 1)[-1])
        raise RuntimeError(f"{arm} {env_id}: {last}")
    return steps / float(json.loads(out.stdout.strip().splitlines()[-1])["seconds"])


def _child(arm: str, env_id: str, steps: int) -> None:
    import torch

    if arm == "raw2":
        torch.set_num_threads(2)
    else:
        os.sched_setaffinity(0, {0})
        torch.set_num_threads(1)
    fn = {"raw": arm_raw, "raw2": arm_raw, "pidlab": arm_pidlab, "sbx": arm_sbx}[arm]
    print(json.dumps({"seconds": fn(env_id, steps)}))


def _have_sbx() -> bool:
    try:
        import sbx  # noqa: F401
    except ImportError:
        return False
    return True


def _summary(x: list[float]) -> str:
    return f"{statistics.median(x):,.1f} ({min(x):,.1f}-{max(x):,.1f})" if x else "not measured"


def _ratio(x: list[float], y: list[float]) -> str:
    if not x or not y:
        return "-"
    r = [a / b for a, b in zip(x, y, strict=True)]
    return f"{statistics.median(r):.2f}x ({min(r):.2f}-{max(r):.2f})"


def report(rates: dict[str, dict[str, list[float]]], steps: int, repeats: int, sbx: str | None) -> str:
    """docs/sac-throughput.md."""
    import mujoco
    import stable_baselines3
    import torch

    from pidlab import __version__
    from pidlab.provenance import git_state

    sha = (git_state(ROOT).get("sha") or "?")[:10]
    lines = [
        "# SAC throughput",
        "",
        "<!-- written by benchmarks/sac_throughput.py: do not edit -->",
        "",
        "Env steps per second of SAC in its update phase (one gradient step per env step), paired",
        f"rounds of {steps:,} env steps after a 1,000-step random warm-up, each arm in a fresh process",
        f"pinned to one core (torch and XLA on one thread). Median over {repeats} rounds, range in",
        "brackets; the ratio is taken within each round. How it is measured:",
        "`benchmarks/sac_throughput.py` (its docstring).",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"pidlab {__version__} ({sha}), SB3 {stable_baselines3.__version__}, torch {torch.__version__}, "
        f"MuJoCo {mujoco.__version__}" + (f", {sbx}." if sbx else "."),
        "",
        "| env | " + " | ".join(f"{LABELS[a]} (env steps/s)" for a in ARMS)
        + " | pidlab / raw SB3 | SBX / raw SB3 | 2 threads / 1 |",
        "|---|" + "---:|" * (len(ARMS) + 3),
    ]
    for env_id, r in rates.items():
        lines.append(
            f"| {env_id} | " + " | ".join(_summary(r[a]) for a in ARMS)
            + f" | {_ratio(r['pidlab'], r['raw'])} | {_ratio(r['sbx'], r['raw'])}"
            + f" | {_ratio(r['raw2'], r['raw'])} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = Parser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=count, default=3)
    parser.add_argument("--envs", default="Hopper-v5")
    parser.add_argument("--steps", type=count, default=4000)
    parser.add_argument("--arm", choices=ARMS, help=argparse.SUPPRESS)
    parser.add_argument("--out", default=str(ROOT / "docs" / "sac-throughput.md"))
    args = parser.parse_args()
    if args.arm:
        _child(args.arm, args.envs, args.steps)
        return
    sbx = None
    if _have_sbx():
        import jax
        import sbx as sbx_module

        sbx = f"SBX {sbx_module.__version__} on JAX {jax.__version__}"
    arms = [a for a in ARMS if a != "sbx" or sbx]
    rates: dict[str, dict[str, list[float]]] = {}
    for env_id in args.envs.split(","):
        rates[env_id] = {a: [] for a in ARMS}
        for i in range(args.repeats):
            for arm in arms:
                rates[env_id][arm].append(run_arm(arm, env_id, args.steps))
            print(f"{env_id} round {i + 1}: "
                  + ", ".join(f"{a} {rates[env_id][a][-1]:.1f}" for a in arms) + " env steps/s", flush=True)
    text = report(rates, args.steps, args.repeats, sbx)
    from pidlab.files import atomic_write_text

    atomic_write_text(Path(args.out), text)
    print(text)


if __name__ == "__main__":
    run(main)
