"""Write the tables of docs/results/README.md from the committed experiment reports.

Reads docs/results/ENV/summary.csv and experiment.json (copied there by benchmarks/experiments.sh)
and the paper's published numbers from the model cards (models/ENV.toml, ``[paper]``), and replaces
the text between the markers in docs/results/README.md, so the numbers there are never typed by
hand. Run: .venv/bin/python benchmarks/results_table.py
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

from pidlab.files import atomic_write_text, read_json
from pidlab.report.experiment import format_value, paper_numbers

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results"
ENVS = ("InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Hopper-v5", "Walker2d-v5")
CONDITIONS = ("none", "paper", "pidlab", "pidlab-fading")
BEGIN = "<!-- tables: begin (benchmarks/results_table.py) -->"
END = "<!-- tables: end -->"


def _num(text: str) -> float:
    return float(text) if text not in ("", "inf") else math.inf


def _cell(row: dict[str, str] | None, to_target: bool = True) -> str:
    if row is None:
        return "-"
    v, lo, hi = _num(row["iqm"]), _num(row["ci_low"]), _num(row["ci_high"])
    name = row["metric"]
    text = (
        "not reached"
        if math.isinf(v)
        else f"{format_value(v, name)} [{format_value(lo, name)}, {format_value(hi, name)}]"
    )
    if to_target:
        text += f" ({row['reached']}/{row['runs']})"
    return text


def _load(env: str) -> tuple[dict[tuple[str, str], dict[str, str]], dict] | None:
    folder = RESULTS / env
    if not (folder / "summary.csv").exists():
        return None
    with open(folder / "summary.csv", newline="") as fh:
        rows = {(r["condition"], r["metric"]): r for r in csv.DictReader(fh)}
    return rows, read_json(folder / "experiment.json")


def tables() -> str:
    """The Markdown tables."""
    head = ["env (target)", "measure", "paper: with coach", "paper: without", "paper: saving",
            *(f"ours: {c}" for c in CONDITIONS)]  # fmt: skip
    t2 = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    honest_head = ["env", "condition", "env steps to target, agent alone", "final agent-alone score",
                   "coach-dependent", "intervention rate",
                   "P(fewer env steps to target than none)"]  # fmt: skip
    t3 = ["| " + " | ".join(honest_head) + " |", "|" + "---|" * len(honest_head)]
    budgets = []
    for env in ENVS:
        loaded = _load(env)
        if loaded is None:
            continue
        rows, record = loaded
        ident = record["identity"]
        paper = paper_numbers(env)
        if paper is None:
            raise SystemExit(f"models/{env}.toml has no [paper] table: the paper's numbers come from there")
        target = paper.win_target
        w, wo = paper.wins_coached, paper.wins_uncoached
        aw, awo = paper.average_coached, paper.average_uncoached
        command = " ".join(record["command"])
        budgets.append(f"- **{env}**: {len(ident['seeds'])} seeds x {len(ident['conditions'])} conditions; "
                       f"`{command}`")  # fmt: skip
        for metric, label, with_, without in (("episodes_to_wins", "5 wins", w, wo),
                                              ("episodes_to_average", "average", aw, awo)):  # fmt: skip
            saving = f"{100 * (without - with_) / without:+.1f} %"
            cells = [_cell(rows.get((c, metric))) for c in CONDITIONS]
            paper = f"| {env} ({target:g}) | {label} | {with_} | {without} | {saving} | "
            t2.append(paper + " | ".join(cells) + " |")
        for c in CONDITIONS:
            if (c, "final_score") not in rows:
                continue
            dep = rows[(c, "coach_dependent")]
            p = rows[(c, "env_steps_to_target")]
            prob = "-" if not p["p_improvement"] else (
                f"{float(p['p_improvement']):.2f} [{float(p['p_low']):.2f}, {float(p['p_high']):.2f}]"
            )  # fmt: skip
            t3.append(
                f"| {env} | {c} | {_cell(rows[(c, 'env_steps_to_target')])} | "
                f"{_cell(rows[(c, 'final_score')], False)} | {dep['iqm']}/{dep['runs']} | "
                f"{_cell(rows[(c, 'intervention_rate')], False)} | {prob} |"
            )
    return "\n".join([
        "### The paper's Table II beside ours (training episodes; IQM [95 % CI] (runs that reached it))", "",
        *t2, "", "### The honest measures", "", *t3, "", "### How each was run", "", *budgets,
    ])  # fmt: skip


def main() -> None:
    """Replace the marked block of docs/results/README.md."""
    readme = RESULTS / "README.md"
    text = readme.read_text()
    a, b = text.index(BEGIN) + len(BEGIN), text.index(END)
    atomic_write_text(readme, text[:a] + "\n\n" + tables() + "\n\n" + text[b:])
    print(tables())


if __name__ == "__main__":
    main()
