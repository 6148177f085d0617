"""How hard a push each shipped coach alone recovers from: the table of docs/coach.md.

For each env, every shipped coach in tuning/ENV.{COACHES}.toml that exists is measured with
:func:`pidlab.region.recovery.measure_recovery` (the model card's perturbations, 20 magnitudes per
side, 100 random-start episodes of seed 0, 5 s each; the same as ``pidlab recovery``). The table
sits in docs/coach.md between ``<!-- recovery-table -->`` and ``<!-- /recovery-table -->``.

Run: .venv/bin/python benchmarks/recovery_table.py [--envs Hopper-v5,Walker2d-v5]
"""

from __future__ import annotations

import time
from pathlib import Path

from bench_cli import Parser, names, run

from pidlab.controller.spec import load_spec
from pidlab.plant.model import load_model
from pidlab.region.recovery import Recovery, measure_recovery

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "coach.md"
ENVS = ("InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Hopper-v5", "Walker2d-v5")
COACHES = ("paper", "pidlab-weak", "pidlab-robust", "pidlab-rescue", "pidlab-room", "pidlab-balance")
START, END = "<!-- recovery-table -->", "<!-- /recovery-table -->"


def _reach(r: Recovery) -> str:
    """Per perturbation its reach, and where its starts leave a joint's range (nothing probed past)."""
    out = []
    for x in r.reach:
        cut = x.past_range()
        note = f" (starts leave a joint's range past {' and '.join(cut)})" if cut else ""
        out.append(f"{x.name} {-x.negative or 0.0:.3g} .. {x.positive:+.3g} {x.unit}{note}")
    return "; ".join(out)


def rows(env: str) -> list[str]:
    """One row per shipped coach of ``env`` (printed as it is measured)."""
    loaded = load_model(env)
    out = []
    for name in COACHES:
        path = ROOT / "tuning" / f"{env}.{name}.toml"
        if not path.exists():
            continue
        t = time.perf_counter()
        r = measure_recovery(load_spec(path), loaded)
        lo, hi = r.falls_ci
        line = (
            f"| {env} | {name} | {_reach(r)} | {r.falls_per_100:.0f} [{lo:.0f}, {hi:.0f}] | "
            f"{time.perf_counter() - t:.0f} |"
        )
        print(line, flush=True)
        out.append(line)
    return out


def main() -> None:
    parser = Parser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--envs", type=names(ENVS), default=",".join(ENVS), help="Comma-separated envs (default: all four)."
    )
    args = parser.parse_args()
    head = [
        "| env | coach | reach on each side (every probe up to it recovered) "
        "| falls / 100 episodes [95 %] | s |",
        "|---|---|---|---|---|",
    ]
    body = [line for env in args.envs.split(",") for line in rows(env)]
    text = PAGE.read_text(encoding="utf-8")
    i, j = text.index(START) + len(START), text.index(END)
    command = f"`.venv/bin/python benchmarks/recovery_table.py --envs {args.envs}`"
    block = f"\nMeasured with {command}.\n\n" + "\n".join(head + body) + "\n"
    PAGE.write_text(text[:i] + block + text[j:], encoding="utf-8")
    print(f"wrote the table into {PAGE}")


if __name__ == "__main__":
    run(main)
