"""What the balance preset's choices are worth: falls per 100 perturbed episodes with one changed.

For each legged env, the ``balance`` preset's coach (:data:`pidlab.controller.balance.DESIGN`) and
variants that change one choice: no centre-of-mass terms in the LQR, the input weight 1 or 31.6
(the preset's is 3.16), the knees bent 0.05 or 0.25 rad (the cards' 0.15). Each coach is built
with :func:`pidlab.controller.balance.tune_balance` and measured as ``pidlab recovery`` measures it
(:func:`pidlab.region.recovery.measure_recovery`: the card's perturbations, 20 magnitudes per
side, 100 random-start episodes of seed 0, 5 s each). The preset's weights were chosen on other
starts (the room search's seeds 1000-1001); these variants were measured after the choice. The
table sits in docs/coach.md between ``<!-- balance-ablation -->`` and ``<!-- /balance-ablation -->``.

Run: .venv/bin/python benchmarks/balance_ablation.py [--envs Hopper-v5,Walker2d-v5]
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

from bench_cli import Parser, names, run
from recovery_table import _reach

from pidlab.controller.balance import DESIGN, tune_balance
from pidlab.errors import PidlabError
from pidlab.linear.linearize import linearize
from pidlab.plant.model import load_model
from pidlab.region.recovery import measure_recovery

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "coach.md"
ENVS = ("Hopper-v5", "Walker2d-v5")
START, END = "<!-- balance-ablation -->", "<!-- /balance-ablation -->"
VARIANTS = (
    ("the preset", DESIGN),
    ("no centre-of-mass terms", dataclasses.replace(DESIGN, com=0.0, com_rate=0.0)),
    ("input weight 1", dataclasses.replace(DESIGN, input=1.0)),
    ("input weight 31.6", dataclasses.replace(DESIGN, input=10**1.5)),
    ("knees bent 0.05 rad", dataclasses.replace(DESIGN, bend=-0.05)),
    ("knees bent 0.25 rad", dataclasses.replace(DESIGN, bend=-0.25)),
)


def rows(env: str) -> list[str]:
    """One row per variant of ``env``'s balance coach (printed as it is measured)."""
    loaded = load_model(env)
    lin = linearize(loaded)
    out = []
    for label, design in VARIANTS:
        t = time.perf_counter()
        try:
            spec = tune_balance(loaded, design).spec
        except PidlabError as exc:  # a variant whose posture cannot be (a joint past its stop)
            line = f"| {env} | {label} | no such coach: {str(exc).removeprefix('preset balance: ')} | - | - |"
            print(line, flush=True)
            out.append(line)
            continue
        found = measure_recovery(spec, loaded, lin=lin)
        lo, hi = found.falls_ci
        reach = _reach(found)
        seconds = time.perf_counter() - t
        falls = f"{found.falls_per_100:.0f} [{lo:.0f}, {hi:.0f}]"
        line = f"| {env} | {label} | {reach} | {falls} | {seconds:.0f} |"
        print(line, flush=True)
        out.append(line)
    return out


def main() -> None:
    parser = Parser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--envs", type=names(ENVS), default=",".join(ENVS), help="Comma-separated envs (default: both)."
    )
    args = parser.parse_args()
    head = [
        "| env | balance coach | reach on each side (every probe up to it recovered) "
        "| falls / 100 episodes [95 %] | s |",
        "|---|---|---|---|---|",
    ]
    body = [line for env in args.envs.split(",") for line in rows(env)]
    text = PAGE.read_text(encoding="utf-8")
    i, j = text.index(START) + len(START), text.index(END)
    command = f"`.venv/bin/python benchmarks/balance_ablation.py --envs {args.envs}`"
    block = f"\nMeasured with {command}.\n\n" + "\n".join(head + body) + "\n"
    PAGE.write_text(text[:i] + block + text[j:], encoding="utf-8")
    print(f"wrote the table into {PAGE}")


if __name__ == "__main__":
    run(main)
