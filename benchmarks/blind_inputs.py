"""How far a learned forecast that reads a walker's forward position moves as the walker moves.

The learned one-step model of the published Hopper runs (`rescue-terminal-room-focus-learned`,
docs/results/Hopper-v5-roommodel) was fitted before its inputs left out the forward position
``rootx`` (pidlab.region.forecast.blind_inputs). This records transitions behind the exact shield
(the random agent of `pidlab forecast`, a seed of its own), moves each one's forward position on by
a few metres, as an agent that hops forward would, and prints per region variable how much the
network's correction changes, beside the margins that were measured with the walker near its start.
Nothing else in the state changes, and the dynamics do not depend on ``rootx``: any change is error.

Usage: .venv/bin/python benchmarks/blind_inputs.py [--transitions 5000] [--seed 11]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from bench_cli import Parser, count, fail, run

from pidlab.controller.spec import load_spec
from pidlab.lookup import parse_forecast
from pidlab.plant.model import load_model
from pidlab.rl.calibrate import _record

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "docs/results/Hopper-v5-roommodel/runs/Hopper-v5/rescue-terminal-room-focus-learned/seed-100"
SHIFTS = (0.5, 2.0, 5.0, 20.0)


def main(argv: list[str]) -> int:
    """Print the table (see the module docstring)."""
    ap = Parser(description=__doc__.splitlines()[0])
    ap.add_argument("--transitions", type=count, default=5000, help="transitions recorded")
    ap.add_argument("--seed", type=count, default=11, help="the recording's seed (at least 1)")
    args = ap.parse_args(argv)
    spec = load_spec(RUN / "coach.toml")
    found = parse_forecast(spec.bounds["forecast"])
    net = found.network
    if net is None:
        fail(f"{RUN}: its forecast has no network")
    loaded = load_model(spec.env_id)
    _, _, inputs = _record(spec, loaded, args.transitions, args.seed, lambda: None)
    print(f"{spec.name} (the run's own coach.toml), {args.transitions:,} transitions, seed {args.seed}; "
          f"forward position recorded within [{inputs[:, 0].min():.2f}, {inputs[:, 0].max():.2f}] m; "
          f"network blind inputs: {list(net.blind) or 'none'}")  # fmt: skip
    base = net.correction(inputs)
    print("| variable | margin | " + " | ".join(f"largest change, {s:g} m on" for s in SHIFTS) + " |")
    print("|---" * (len(SHIFTS) + 2) + "|")
    changes = []
    for shift in SHIFTS:
        moved = inputs.copy()
        moved[:, 0] += shift
        changes.append(np.abs(net.correction(moved) - base).max(axis=0))
    for k, (v, m) in enumerate(zip(found.variables, found.margins, strict=True)):
        print(f"| {v} | {m:.3g} | " + " | ".join(f"{c[k]:.3g}" for c in changes) + " |")
    return 0


if __name__ == "__main__":
    run(lambda: main(sys.argv[1:]))
