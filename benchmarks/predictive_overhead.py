"""What the predictive trigger costs per env step, against a bare env step.

Writes (or replaces) the section "The predictive trigger, per env step" of
docs/coaching-throughput.md, between its markers, and prints the table.
Run: .venv/bin/python benchmarks/predictive_overhead.py [--steps N] [--rounds R] [--envs IP,Hopper]

Stacks, all stepped with the same uniformly random agent actions, interleaved action by action
(each action goes to every stack in turn, so a slow moment of the shared machine hits all of them):

- ``bare``: ``gym.make(ENV)``, no wrapper.
- ``exit trigger, never fires``: the coaching wrapper with the reactive trigger on a rescue region
  wider than the termination domain (a membership test per step, never a takeover).
- ``predictive, never fires``: the same region with the predictive trigger: every agent step first
  steps a copy of the env's MuJoCo data one control period (``mj_copyData`` + ``mj_step``) and reads
  its observation; the env's step then takes the predicted data (a second ``mj_copyData``) instead
  of simulating again. The trajectory is the bare env's, bit for bit.
- ``exit trigger, fires often`` and ``predictive, fires often``: a narrow band about the upright
  state; the coach takes over often. A vetoed action runs no env step of its own.

Only ``step`` calls are timed (resets are not). The figure compared is wall time per **env step**
(agent steps that ran plus coach steps), per round and stack, and its ratio to the bare env's in the
same round: medians over rounds (interquartile range of the ratio beside it). Vetoed actions'
predictions are charged to the coach steps that replaced them, and coach steps include the coach's
own computation, so the "fires often" rows measure coaching as a whole; the "never fires" row is the
pure cost of the predictive trigger.
"""

from __future__ import annotations

import dataclasses
import os
import platform
import re
import statistics
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
from bench_cli import Parser, count, names, run

from pidlab import __version__
from pidlab.controller.spec import load_spec
from pidlab.files import atomic_write_text
from pidlab.lookup import LookupGrid
from pidlab.plant.model import load_model
from pidlab.provenance import git_state
from pidlab.rl.coaching import CoachingWrapper

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "coaching-throughput.md"
START, END = "<!-- predictive-overhead: start -->", "<!-- predictive-overhead: end -->"
BAND = {"InvertedPendulum-v5": ("hinge_pos", "hinge_vel"), "Hopper-v5": ("rooty_pos", "rooty_vel")}
SHORT = {"IP": "InvertedPendulum-v5", "Hopper": "Hopper-v5"}


def rescue_spec(env_id: str, half: tuple[float, float], marked: float):
    """The env's pidlab-robust spec with a hand-made rescue region: a 20 x 20 grid, a centred band marked."""
    spec = load_spec(ROOT / "tuning" / f"{env_id}.pidlab-robust.toml")
    centres = [(np.arange(20) + 0.5) / 20 * 2 * h - h for h in half]
    table = (np.abs(centres[0])[:, None] < marked * half[0]) & (
        np.abs(centres[1])[None, :] < marked * half[1]
    )
    grid = LookupGrid(BAND[env_id], tuple(-h for h in half), half, (20, 20), table, {}, "reactive", 0.0)
    return dataclasses.replace(spec, bounds={**spec.bounds, "rescue": grid.to_table(), "takeover": "rescue"})


def stacks(env_id: str) -> dict:
    wide = rescue_spec(env_id, (50.0, 1e4), 2.0)
    narrow = rescue_spec(env_id, (0.2, 2.0), 0.25)
    loaded = load_model(env_id)

    def coached(spec, trigger):
        return lambda: CoachingWrapper(
            gym.make(env_id), spec, region="rescue", trigger=trigger, loaded=loaded
        )

    return {
        "bare env step": lambda: gym.make(env_id),
        "exit trigger, never fires": coached(wide, "exit"),
        "predictive, never fires": coached(wide, "predictive"),
        "exit trigger, fires often": coached(narrow, "exit"),
        "predictive, fires often": coached(narrow, "predictive"),
    }


def env_steps(env) -> tuple[int, int]:
    """Env steps taken so far and coach steps among them (a bare env: its agent steps, counted outside)."""
    if isinstance(env, CoachingWrapper):
        return env.total_agent_steps + env.total_coach_steps, env.total_coach_steps
    return 0, 0


def run_round(envs: dict, actions: np.ndarray, seed: int) -> dict[str, tuple[float, int, int]]:
    """Every stack steps each action in turn: seconds in ``step``, env steps, coach steps, per stack."""
    spent = dict.fromkeys(envs, 0.0)
    before = {name: env_steps(env) for name, env in envs.items()}
    for env in envs.values():
        env.reset(seed=seed)
    for a in actions:
        for name, env in envs.items():
            t = time.perf_counter()
            _, _, te, tr, _ = env.step(a)
            spent[name] += time.perf_counter() - t
            if te or tr:
                env.reset()
    out = {}
    for name, env in envs.items():
        after = env_steps(env)
        steps = after[0] - before[name][0] if isinstance(env, CoachingWrapper) else len(actions)
        out[name] = (spent[name], steps, after[1] - before[name][1])
    return out


def measure(env_id: str, steps: int, rounds: int) -> list[dict]:
    envs = {name: make() for name, make in stacks(env_id).items()}
    space = next(iter(envs.values())).action_space
    rng = np.random.default_rng(0)
    per_step: dict[str, list[float]] = {name: [] for name in envs}
    ratio: dict[str, list[float]] = {name: [] for name in envs}
    coach_share: dict[str, list[float]] = {name: [] for name in envs}
    for r in range(rounds):
        actions = rng.uniform(space.low, space.high, (steps, *space.shape))
        done = run_round(envs, actions, r)
        bare = done["bare env step"][0] / done["bare env step"][1]
        for name, (spent, env_steps_, coach) in done.items():
            per_step[name].append(spent / env_steps_ * 1e6)
            ratio[name].append(spent / env_steps_ / bare)
            coach_share[name].append(coach / env_steps_)
    rows = []
    for name in envs:
        q = np.percentile(ratio[name], [25, 75])
        rows.append({"env": env_id, "stack": name, "us": statistics.median(per_step[name]),
                     "ratio": statistics.median(ratio[name]), "iqr": (float(q[0]), float(q[1])),
                     "coach": statistics.median(coach_share[name])})  # fmt: skip
    for env in envs.values():
        env.close()
    return rows


def section(rows: list[dict], command: str) -> str:
    git = git_state()
    sha = (git.get("sha") or "unknown")[:10] if isinstance(git, dict) else "unknown"
    lines = [
        f"| {r['env']} | {r['stack']} | {r['us']:.1f} | {r['ratio']:.2f}x | "
        f"{r['iqr'][0]:.2f}-{r['iqr'][1]:.2f} | {100 * r['coach']:.0f} |"
        for r in rows
    ]
    return f"""{START}
## The predictive trigger, per env step

Measured by `{command}` (pidlab {__version__}, git {sha}, {platform.machine()}, {os.cpu_count()} cores,
Python {platform.python_version()}). Uniformly random agent actions, each stepped on every stack in
turn; wall time of `step` per env step (agent steps that ran plus coach steps) and its ratio to the
bare env step in the same round, medians over the rounds (IQR of the ratio).

| env | stack | us per env step | vs bare | IQR | coach steps (%) |
|---|---|---:|---:|---:|---:|
{chr(10).join(lines)}

The "never fires" row is the whole overhead of the predictive trigger (the target: at most 2x a bare
env step): per agent step, one copy of the env's MuJoCo data, one control period of MuJoCo on it and
the card's observation, then a second copy that takes the place of the env's own simulation (the
action is simulated once, not twice). The "fires often" rows include the coach's own steps (its law
and the env step) and, for the predictive trigger, the predictions of vetoed actions, which run no
env step of their own; their difference is what the prediction adds to a coached run.
{END}"""


def write_section(text: str) -> None:
    doc = DOC.read_text() if DOC.exists() else "# Coaching throughput\n"
    if START in doc and END in doc:
        doc = re.sub(re.escape(START) + r".*?" + re.escape(END), lambda _: text, doc, flags=re.S)
    else:
        doc = doc.rstrip("\n") + "\n\n" + text + "\n"
    atomic_write_text(DOC, doc)


def main() -> None:
    parser = Parser()
    parser.add_argument("--steps", type=count, default=2000, help="agent actions per round and stack")
    parser.add_argument("--rounds", type=count, default=20)
    parser.add_argument(
        "--envs", type=names(SHORT), default="IP,Hopper", help="IP and/or Hopper, comma-separated"
    )
    parser.add_argument("--no-write", action="store_true", help="print only")
    args = parser.parse_args()
    envs = [SHORT.get(e, e) for e in args.envs.split(",")]
    rows = []
    for env_id in envs:
        rows += measure(env_id, args.steps, args.rounds)
    for r in rows:
        us, ratio, coach = f"{r['us']:8.1f} us/env step", f"{r['ratio']:5.2f}x", f"coach {r['coach']:.0%}"
        print(f"{r['env']:<22} {r['stack']:<28} {us}  {ratio}  {coach}")
    command = (f".venv/bin/python benchmarks/predictive_overhead.py --steps {args.steps} "
               f"--rounds {args.rounds} --envs {args.envs}")  # fmt: skip
    if not args.no_write:
        write_section(section(rows, command))
        print(f"wrote a section of {DOC}")


if __name__ == "__main__":
    run(main)
