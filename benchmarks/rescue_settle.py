"""Where a simulation-certified coach's "rescued" states end: docs/rescue.md.

A coach certified by simulation only (Hopper, Walker2d: contacts) "rescues" a state when it holds
the horizon (3 s) without a termination (:func:`pidlab.region.rescue._rescued`). This script asks
whether that criterion means a rescue: from states of the coverage table's domain
(``benchmarks/coverage_table.py``, the same draw as ``pidlab rescue-coverage``), the coach alone
runs for ``--long`` seconds; for the states that hold 3 s it prints how many also hold the longer
horizon, and where the torso's pitch and its rate are at 3 s (deviation from the operating point).

Run: .venv/bin/python benchmarks/rescue_settle.py Walker2d-v5 tuning/Walker2d-v5.pidlab-room.toml
     [--states 3000] [--long 10]
"""

from __future__ import annotations

import sys
from pathlib import Path

import mujoco
import numpy as np

from pidlab.controller.spec import load_spec
from pidlab.plant.model import load_model
from pidlab.region.coverage import DomainSettings, draw_states
from pidlab.region.rescue import simulations, state_domain

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_cli import Parser, count, positive, run
from coverage_table import DOMAINS

SHORT_S = 3.0
"""The rescue criterion's horizon (the region estimates' default)."""


def run_out(sim, x: np.ndarray, grounded: bool, short: int, long: int, pitch: tuple[int, int]):
    """Steps survived (up to ``long``) from ``x`` under the coach, and (pitch, rate) at step ``short``."""
    obs = sim.start(x, grounded=grounded)
    sim.coach.reset(obs)
    m, d, card, frame_skip = sim.m, sim.d, sim.fast, sim.loaded.frame_skip
    at_short = np.full(2, np.nan)
    for k in range(long):
        d.ctrl[:] = sim.coach.act(obs)
        mujoco.mj_step(m, d, nstep=frame_skip)
        obs = card.observe(d)
        if card.terminated(d, obs):
            return k, at_short
        if k == short - 1:
            at_short = obs[list(pitch)] - sim.y_op[list(pitch)]
    return long, at_short


def main() -> None:
    parser = Parser(description=__doc__.splitlines()[0])
    parser.add_argument("env", choices=("Hopper-v5", "Walker2d-v5"))
    parser.add_argument("spec", help="The coach spec (TOML).")
    parser.add_argument("--states", type=count, default=3000, help="States drawn (default 3,000).")
    parser.add_argument("--long", type=positive, default=10.0, help="The longer horizon, s (default 10).")
    args = parser.parse_args()
    box = DOMAINS[args.env]
    settings = DomainSettings(tuple(box), tuple(box.values()), states=args.states)
    spec, loaded = load_spec(args.spec), load_model(args.env)

    def domain(card, model, y_op):
        return state_domain(settings.variables, settings.half_range, card, model, y_op)

    with simulations(spec, loaded, settings, domain, 1) as (est, _, _):
        values = draw_states(est, args.states)
        sim = est.pool.sim
        names = sim.card.observation_names
        pitch = (names.index("rooty_pos"), names.index("rooty_vel"))
        short = round(SHORT_S / loaded.control_dt)
        long = round(args.long / loaded.control_dt)
        runs = [run_out(sim, est.domain.to_plant(v, sim), est.grounded, short, long, pitch) for v in values]
    steps = np.array([r[0] for r in runs])
    held = steps >= short
    end = np.abs(np.array([r[1] for r in runs])[held])
    print(f"{args.env}, {spec.name}: {args.states:,} states of the coverage domain")
    print(f"  hold {SHORT_S:g} s (rescued by the criterion): {held.sum():,}")
    kept = int((steps >= long).sum())
    print(f"  of those, also hold {args.long:g} s: {kept:,} ({kept / max(int(held.sum()), 1):.0%})")
    for q in (0.1, 0.5, 0.9):
        print(f"  at {SHORT_S:g} s, quantile {q}: |pitch| {np.quantile(end[:, 0], q):.3f} rad, "
              f"|pitch rate| {np.quantile(end[:, 1], q):.3f} rad/s")  # fmt: skip


if __name__ == "__main__":
    run(main)
