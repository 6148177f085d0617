"""How large a first action a shield's rescue region allows: one step from rest at the operating point.

For each action size, the env is put at its reset mean (the operating point, at rest), takes one
action of that size in each direction, and the region (the spec's takeover region, and its
hand-back region) is asked about the state after it. Prints a table; with ``--policy-std`` also the
share of an untrained Gaussian policy's actions (clipped to the action range) at least that large.

    .venv/bin/python benchmarks/one_step_room.py tuning/InvertedDoublePendulum-v5.pidlab-rescue-full.toml
"""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
from bench_cli import Parser, positive, run

from pidlab.controller.spec import load_spec
from pidlab.region.takeover import load_region

SIZES = (0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.75, 1.0)
"""Action sizes tried, as fractions of the action range's half-width."""


def one_step_inside(spec_path: str, sizes: tuple[float, ...] = SIZES, handback: float = 0.5) -> list[tuple]:
    """Per size: (size, inside after +size, inside after -size, in the hand-back region after both)."""
    spec = load_spec(spec_path)
    region = load_region(spec)
    inner = region.inner(handback)
    env = gym.make(spec.env_id)
    low, high = env.action_space.low, env.action_space.high
    centre, half = (high + low) / 2.0, (high - low) / 2.0
    out = []
    for size in sizes:
        inside = []
        for sign in (1.0, -1.0):
            env.reset(seed=0)
            u = env.unwrapped
            u.set_state(u.init_qpos.copy(), u.init_qvel.copy())
            obs, *_ = env.step((centre + sign * size * half).astype(env.action_space.dtype))
            inside.append((region.contains(obs), inner.contains(obs)))
        out.append((size, inside[0][0], inside[1][0], inside[0][1] and inside[1][1]))
    env.close()
    return out


def share_at_least(size: float, std: float) -> float:
    """P(|a| >= size) for a ~ N(0, std^2): an untrained Gaussian policy's actions (before clipping)."""
    return math.erfc(size / (std * math.sqrt(2.0)))


def main() -> None:
    """Print the table."""
    parser = Parser(description=__doc__.splitlines()[0])
    parser.add_argument("spec")
    parser.add_argument("--policy-std", type=positive, default=1.0, help="an untrained policy's std (SB3: 1)")
    args = parser.parse_args()
    print(f"{args.spec}: one action from rest at the operating point (sizes: fractions of the half-range)")
    print("| size | inside after +size | inside after -size | in the hand-back region (0.5) | "
          f"share of N(0, {args.policy_std:g}) actions at least this large |")  # fmt: skip
    print("|---:|---|---|---|---:|")
    for size, plus, minus, back in one_step_inside(args.spec):
        print(
            f"| {size:g} | {plus} | {minus} | {back} | {100 * share_at_least(size, args.policy_std):.0f} % |"
        )


if __name__ == "__main__":
    np.set_printoptions(precision=4)
    run(main)
