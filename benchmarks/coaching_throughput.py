"""Throughput of coached vs uncoached SB3 training, and what vectorized envs gain on this machine.

Writes docs/coaching-throughput.md. Run: .venv/bin/python benchmarks/coaching_throughput.py
[--steps N] [--repeats R] [--envs InvertedPendulum-v5,Hopper-v5]

Every configuration trains PPO (the recipe's hyperparameters) for the same number of agent steps,
with the pidlab env stack the trainer uses (gym.make -> CoachingWrapper -> Monitor ->
DummyVecEnv/SubprocVecEnv -> VecNormalize), and times ``model.learn`` only. Configurations are
run interleaved (A, B, C, A, B, C, ...) and the median of the repeats is reported, so slow
drifts of the machine hit all of them alike.

1. Coaching machinery: ``bare`` (no wrapper) vs ``uncoached`` (wrapper without coach) vs
   ``coached, never triggers`` (the coach spec with bounds so wide the trigger never fires:
   the same trajectory as bare, so the difference is the pure per-step cost of coaching).
2. ``coached`` with the spec's derived bounds: env steps/s and agent steps/s, and the share of
   coach steps; coach steps skip the policy and the gradient updates, so they are cheap.
3. Vectorized envs: 1 env (SB3's default) vs 2 envs in one process (DummyVecEnv) vs 2 envs in
   two processes (SubprocVecEnv), each with the same rollout size (n_steps * n_envs).
"""

from __future__ import annotations

import dataclasses
import os
import platform
import statistics
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from bench_cli import Parser, count, run
from stable_baselines3 import PPO
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecNormalize

from pidlab import __version__
from pidlab.controller.pid import Coach
from pidlab.controller.spec import load_spec
from pidlab.files import atomic_write_text
from pidlab.plant.model import load_model
from pidlab.provenance import git_state
from pidlab.rl.coaching import CoachingWrapper
from pidlab.rl.recipe import load_recipe
from pidlab.rl.train import make_vec_env, sb3_arguments

ROOT = Path(__file__).resolve().parents[1]


def _bare(env_id: str) -> gym.Env:
    return Monitor(gym.make(env_id))


def bare_vec_env(recipe, n_envs: int, subproc: bool):
    fns = [lambda e=recipe.env_id: _bare(e)] * n_envs
    venv = SubprocVecEnv(fns) if subproc else DummyVecEnv(fns)
    gamma = float(recipe.hyperparameters.get("gamma", 0.99))
    return VecNormalize(venv, norm_obs=recipe.normalize_obs, norm_reward=recipe.normalize_reward, gamma=gamma)


def run_once(recipe, spec, kind: str, steps: int, n_envs: int = 1, subproc: bool = False) -> dict:
    kwargs = sb3_arguments(recipe)
    if n_envs > 1:
        kwargs["n_steps"] = max(kwargs.get("n_steps", 2048) // n_envs, 1)
    r = dataclasses.replace(recipe, n_envs=n_envs, vec_env="subproc" if subproc else "dummy")
    venv = bare_vec_env(r, n_envs, subproc) if kind == "bare" else make_vec_env(r, spec)
    model = PPO("MlpPolicy", venv, seed=0, device="cpu", verbose=0, **kwargs)
    t = time.perf_counter()
    model.learn(total_timesteps=steps)
    wall = time.perf_counter() - t
    agent = int(model.num_timesteps)
    coach = 0
    if kind != "bare":
        coach = sum(venv.get_attr("total_coach_steps"))
    venv.close()
    return {"wall": wall, "agent": agent, "coach": coach, "env": agent + coach}


def median_rate(runs: list[dict], key: str) -> float:
    return statistics.median(r[key] / r["wall"] for r in runs)


def spread(runs: list[dict], key: str) -> str:
    rates = [r[key] / r["wall"] for r in runs]
    return f"{min(rates):.0f}-{max(rates):.0f}"


def _time_env(env, actions: np.ndarray, seed: int) -> float:
    env.reset(seed=seed)
    t = time.perf_counter()
    for a in actions:
        _, _, te, tr, _ = env.step(a)
        if te or tr:
            env.reset()
    return (time.perf_counter() - t) / len(actions) * 1e6


def _time_coach(env, coach: Coach, steps: int, seed: int) -> float:
    obs, _ = env.reset(seed=seed)
    coach.reset(obs)
    t = time.perf_counter()
    for _ in range(steps):
        obs, _, te, tr, _ = env.step(coach.act(obs))
        if te or tr:
            obs, _ = env.reset()
            coach.reset(obs)
    return (time.perf_counter() - t) / steps * 1e6


def step_costs_us(stacks: dict, spec, loaded, steps: int = 1000, rounds: int = 60) -> dict[str, list[float]]:
    """Microseconds per step through each env stack, and per coach step, in paired rounds.

    In each round every stack runs the same ``steps`` random actions from the same reset seed,
    one after the other, so a difference to ``bare`` within a round is paired: slow phases of
    a shared machine hit both sides.
    """
    envs = {name: make() for name, make in stacks.items()}
    first = next(iter(envs.values()))
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (steps, *first.action_space.shape)) * first.action_space.high
    coach_env, coach = gym.make(spec.env_id), Coach(spec, loaded)
    out: dict[str, list[float]] = {name: [] for name in [*envs, "coach"]}
    for r in range(rounds):
        for name, env in envs.items():
            out[name].append(_time_env(env, actions, r))
        out["coach"].append(_time_coach(coach_env, coach, steps, r))
    for env in [*envs.values(), coach_env]:
        env.close()
    return out


def main() -> None:
    parser = Parser()
    parser.add_argument("--steps", type=count, default=20000, help="agent steps per training run")
    parser.add_argument("--repeats", type=count, default=3)
    parser.add_argument("--envs", default="InvertedPendulum-v5,Hopper-v5")
    parser.add_argument("--out", default=str(ROOT / "docs" / "coaching-throughput.md"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    envs = [e.strip() for e in args.envs.split(",") if e.strip()]

    lines_m, lines_a, lines_v = [], [], []
    for env_id in envs:
        recipe = load_recipe(ROOT / "coach" / f"{env_id}.toml")
        spec = load_spec(ROOT / "tuning" / f"{env_id}.pidlab-robust.toml")
        wide_box = {v: [-1e9, 1e9] for v in (spec.bounds or {}).get("box", {})}
        never = dataclasses.replace(spec, bounds={"method": "benchmark: never triggers", "box": wide_box})
        loaded = load_model(env_id)
        us = step_costs_us(
            {
                "bare": lambda e=env_id: _bare(e),
                "none": lambda e=env_id: Monitor(CoachingWrapper(gym.make(e), None)),
                "never": lambda e=env_id, s=never, m=loaded: Monitor(
                    CoachingWrapper(gym.make(e), s, loaded=m)
                ),
            },
            spec,
            loaded,
        )
        configs = {
            "bare": (None, "bare"),
            "uncoached": (None, "wrapper"),
            "coached, never triggers": (never, "wrapper"),
            "coached": (spec, "wrapper"),
        }
        runs: dict[str, list[dict]] = {k: [] for k in configs}
        for rep in range(args.repeats):
            for name, (s, kind) in configs.items():
                out = run_once(recipe, s, kind, args.steps)
                runs[name].append(out)
                rate = out["env"] / out["wall"]
                print(f"{env_id} rep {rep} {name}: {rate:.0f} env steps/s ({out['agent']} agent, "
                      f"{out['coach']} coach steps, {out['wall']:.1f} s)", flush=True)  # fmt: skip
        base = median_rate(runs["bare"], "env")
        for name, rs in runs.items():
            env_rate, agent_rate = median_rate(rs, "env"), median_rate(rs, "agent")
            share = statistics.median(r["coach"] / r["env"] for r in rs)
            lines_a.append(
                f"| {env_id} | {name} | {env_rate:.0f} | {spread(rs, 'env')} | {agent_rate:.0f} | "
                f"{100 * share:.1f} | {env_rate / base:.3f} |"
            )
        train_us = 1e6 / base  # one bare PPO training step (env step + policy + amortized updates)
        bare_us = statistics.median(us["bare"])
        lines_m.append(f"| {env_id} | bare env step | {bare_us:.1f} | | |")
        for key, name in (("none", "uncoached (wrapper, no coach)"),
                          ("never", "coached, never triggers (trigger test every step)")):  # fmt: skip
            diff = [a - b for a, b in zip(us[key], us["bare"], strict=True)]
            med = statistics.median(diff)
            q1, q3 = np.percentile(diff, [25, 75])
            lines_m.append(
                f"| {env_id} | {name} | {statistics.median(us[key]):.1f} | "
                f"{med:+.1f} ({q1:+.1f} to {q3:+.1f}) | {100 * med / train_us:+.2f} % |"
            )
        lines_m.append(
            f"| {env_id} | one coach step (coach.act + env.step) | {statistics.median(us['coach']):.1f} | | |"
        )
        lines_m.append(
            f"| {env_id} | one PPO training step, bare (1 / median env steps/s below) | {train_us:.0f} | | |"
        )
        vec_configs = {
            "1 env": (1, False),
            "2 envs, DummyVecEnv": (2, False),
            "2 envs, SubprocVecEnv": (2, True),
        }
        vruns: dict[str, list[dict]] = {k: [] for k in vec_configs}
        for rep in range(args.repeats):
            for name, (n, sub) in vec_configs.items():
                out = run_once(recipe, None, "wrapper", args.steps, n_envs=n, subproc=sub)
                vruns[name].append(out)
                print(f"{env_id} rep {rep} {name}: {out['env'] / out['wall']:.0f} env steps/s", flush=True)
        one = median_rate(vruns["1 env"], "env")
        for name, rs in vruns.items():
            rate = median_rate(rs, "env")
            lines_v.append(f"| {env_id} | {name} | {rate:.0f} | {rate / one:.2f} |")

    git = git_state()
    sha = (git["sha"] or "?")[:10] + (" + local changes" if git["dirty"] else "")
    machine = f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores"
    command = (
        f".venv/bin/python benchmarks/coaching_throughput.py --steps {args.steps} --repeats {args.repeats} "
        f"--envs {','.join(envs)}"
    )
    text = f"""# Coaching throughput

Measured by `{command}`
(pidlab {__version__}, git {sha}, {machine}, torch threads 1, Python {platform.python_version()}).
PPO with each env's recipe hyperparameters trains for {args.steps:,} agent steps per run; only
`model.learn` is timed; configurations run interleaved, {args.repeats} repeats, medians shown.

## The cost of the coaching machinery, per step

Wall time of one `env.step` through each env stack: 60 rounds, in each of which every stack runs
the same 1,000 uniformly random actions (with resets) from the same seed, one after the other.
"extra" is the median over rounds of the paired difference to the bare env (interquartile range
in brackets), and its share of one bare PPO training step is the cost the 5 % goal is about.
Single timings on this shared machine wander by tens of percent; paired medians are far steadier.

| env | what | us per step (median) | extra us per step | share of a PPO training step |
|---|---|---:|---:|---:|
{chr(10).join(lines_m)}

## Coached vs uncoached training (PPO, 1 env)

- **bare**: `gym.make` + SB3 Monitor, no pidlab wrapper.
- **uncoached**: what `pidlab train --coach none` runs (the wrapper keeps the accounts, no coach).
- **coached, never triggers**: the pidlab-robust coach with bounds so wide that it never intervenes: the
  same trajectory as bare, so the difference is the pure cost of the coaching machinery (trigger test,
  bookkeeping).
- **coached**: the pidlab-robust coach with its derived bounds (takeover). Coach steps skip the policy and
  the gradient updates, so they cost less than agent steps; env steps/s rises with the coach's share.

Medians and the range over the repeats: whole training runs on this shared 2-core machine vary by
several percent from run to run, more than the machinery costs (previous section).

| env | configuration | env steps/s | range | agent steps/s | coach steps (%) | ratio to bare |
|---|---|---:|---:|---:|---:|---:|
{chr(10).join(lines_a)}

## Vectorized envs on this machine (uncoached, PPO)

Same rollout size per update (`n_steps * n_envs` equal), so the learning updates are the same size.

| env | configuration | env steps/s | speed-up vs 1 env |
|---|---|---:|---:|
{chr(10).join(lines_v)}
"""
    atomic_write_text(args.out, text + _kept_section(Path(args.out)))
    print(f"wrote {args.out}")


def _kept_section(page: Path) -> str:
    """The page's predictive-trigger section (benchmarks/predictive_overhead.py writes it), kept as it is."""
    start, end = "<!-- predictive-overhead: start -->", "<!-- predictive-overhead: end -->"
    old = page.read_text() if page.exists() else ""
    if start not in old or end not in old:
        return ""
    return "\n" + old[old.index(start) : old.index(end) + len(end)] + "\n"


if __name__ == "__main__":
    run(main)
