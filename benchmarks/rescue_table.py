"""The table of docs/rescue.md, from the shipped specs' rescue regions (tuning/ENV.pidlab-rescue.toml).

Every figure is read from a spec's ``[bounds.rescue]`` table and its provenance, as
``pidlab rescue --write`` recorded it; nothing is recomputed by simulation here. The table sits in
docs/rescue.md between the markers ``<!-- rescue-table -->`` and ``<!-- /rescue-table -->``.

Run: .venv/bin/python benchmarks/rescue_table.py [--check]
(--check: exit 1 when the page's table differs from the specs'.)
"""

from __future__ import annotations

import sys
from pathlib import Path

from bench_cli import run

from pidlab.controller.spec import load_spec
from pidlab.lookup import parse_lookup

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "rescue.md"
ENVS = ("InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Hopper-v5", "Walker2d-v5")
START, END = "<!-- rescue-table -->", "<!-- /rescue-table -->"


def _pct(value: float | None) -> str:
    return "—" if value is None else f"{100 * value:.1f} %"


def row(env: str) -> str:
    """One env's row: the region, its validation and its coverage against the other sets."""
    spec = load_spec(ROOT / "tuning" / f"{env}.pidlab-rescue.toml")
    t = spec.bounds["rescue"]
    grid, p = parse_lookup(t), t["provenance"]
    coach = spec.provenance.get("preset", "?")
    cells = " x ".join(str(c) for c in grid.cells)
    guard = ", ".join(grid.guard) or "none"
    validation = (
        f"{p['validation_samples']:,} / {p['validation_failures']} ({p['validation_rounds']} draw(s))"
    )
    rescuable = f"{p['coverage_rescuable']:,} of {p['coverage_samples']:,}"
    return (
        f"| {env} | {coach} | {cells} over {', '.join(grid.variables)} | {guard} | "
        f"{_pct(grid.fraction_marked())} | {validation} | {rescuable} | **{_pct(p['coverage_rescue'])}** | "
        f"{_pct(p.get('coverage_core'))} | {_pct(p.get('coverage_takeover_box'))} | {p['elapsed_s']:.0f} |"
    )


def table() -> str:
    """The whole table, in Markdown."""
    head = (
        "| env | coach preset | lookup grid | guard variables | cells marked | validation: states / "
        "failures | rescuable states (coverage draw) | coverage: rescue region | certified core | "
        "former takeover box | estimate time (s, 2 workers) |\n|---|---|---|---|---|---|---|---|---|---|---|"
    )
    return "\n".join([head, *(row(env) for env in ENVS)])


def main(argv: list[str]) -> int:
    """Print the table; write it into the page (or, with --check, compare)."""
    text = PAGE.read_text()
    start, end = text.index(START) + len(START), text.index(END)
    new = text[:start] + "\n" + table() + "\n" + text[end:]
    print(table())
    if "--check" in argv:
        if new != text:
            print(
                f"{PAGE}: its table differs from the specs'; run benchmarks/rescue_table.py", file=sys.stderr
            )
            return 1
        return 0
    PAGE.write_text(new)
    return 0


if __name__ == "__main__":
    run(lambda: main(sys.argv[1:]))
