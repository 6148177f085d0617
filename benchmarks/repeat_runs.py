"""Whether one condition's runs repeat the same seeds' runs of another experiment over their shared env steps.

Amendment 22 (docs/analysis-plan.md) trains plain PPO on Walker2d again at 300,000 env steps and
promises to say whether those runs repeat the first 300,000 env steps of the confirmatory
1,000,000-step runs of the same seeds. For each seed both folders hold, this compares the two
runs' ``evaluations.csv`` row by row over the evaluations both made (the shorter run's), and
names the first evaluation (its env step) where they differ. Beside it: the env step of every
resume of each run (a resumed run does not reproduce the uninterrupted one past its checkpoint,
docs/coaching.md#reproducibility) and the git SHA that trained it. Training is byte-reproducible
for a seed on the same machine; two machines may part after many updates.

Run: .venv/bin/python benchmarks/repeat_runs.py SHORT LONG ENV CONDITION
e.g. .venv/bin/python benchmarks/repeat_runs.py docs/results/Walker2d-v5-sac \
     docs/results/Walker2d-v5-confirm Walker2d-v5 none
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

from bench_cli import Parser, fail, run

from pidlab.errors import ExperimentError
from pidlab.files import load_json, read_text
from pidlab.provenance import read_record
from pidlab.rl.rundir import RUN_SCHEMA


@dataclass(frozen=True)
class Repeat:
    """One seed's two runs compared (see the module docstring)."""

    seed: int
    shared: int
    first_difference: int | None
    resumes: tuple[tuple[int, ...], tuple[int, ...]]
    shas: tuple[str, str]


def _bad(path: Path, why: str) -> ExperimentError:
    return ExperimentError(f"{path}: {why}")


def _rows(run_dir: Path) -> list[list[str]]:
    """The data rows of a run's ``evaluations.csv``; each must start with its env step."""
    path = run_dir / "evaluations.csv"
    rows = list(csv.reader(read_text(path, "evaluations log", ExperimentError).splitlines()))[1:]
    for i, row in enumerate(rows):
        if not row or not row[0].isdigit():
            raise _bad(path, f"row {i + 1} does not start with an env step (a whole number)")
    return rows


def _record(run_dir: Path) -> tuple[tuple[int, ...], str]:
    """The env steps at which the run was resumed, and the git SHA that started it (``run.json``)."""
    path = run_dir / "run.json"
    record = read_record(path, RUN_SCHEMA, ExperimentError)
    steps = [r.extra.get("from_env_steps") for r in record.resumes]
    if not all(isinstance(x, int) for x in steps):
        raise _bad(path, "a resume without its env step (from_env_steps)")
    return tuple(steps), str(record.git.get("sha", "?"))[:12]


def compare(short: Path, long: Path, seed: int) -> Repeat:
    """The runs of ``seed`` in two condition folders (``.../runs/ENV/COND``), compared."""
    a, b = short / f"seed-{seed}", long / f"seed-{seed}"
    ra, rb = _rows(a), _rows(b)
    shared = min(len(ra), len(rb))
    first = next((int(ra[i][0]) for i in range(shared) if ra[i] != rb[i]), None)
    (resumes_a, sha_a), (resumes_b, sha_b) = _record(a), _record(b)
    return Repeat(seed, shared, first, (resumes_a, resumes_b), (sha_a, sha_b))


def _finished(run_dir: Path) -> bool:
    summary = run_dir / "summary.json"
    if not summary.is_file():
        return False
    data = load_json(summary, "run summary", ExperimentError)
    return isinstance(data, dict) and data.get("completed") is True


def _seeds(folder: Path) -> set[int]:
    """The seeds of the finished runs of a condition folder (folders ``seed-N``; others are ignored)."""
    runs = (p for p in folder.glob("seed-*") if p.name.removeprefix("seed-").isdigit())
    return {int(p.name.removeprefix("seed-")) for p in runs if _finished(p)}


def table(repeats: list[Repeat]) -> str:
    """A markdown table of the comparisons."""
    head = ["seed", "evaluations compared", "first differing evaluation (env steps)",
            "resumed at (env steps): this run / the other", "git: this run / the other"]  # fmt: skip
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in repeats:
        diff = "none: identical" if r.first_difference is None else f"{r.first_difference:,}"
        resumed = " / ".join(", ".join(f"{s:,}" for s in x) or "-" for x in r.resumes)
        lines.append(f"| {r.seed} | {r.shared} | {diff} | {resumed} | {' / '.join(r.shas)} |")
    return "\n".join(lines)


def main() -> int:
    p = Parser(description=__doc__.splitlines()[0])
    p.add_argument("short", type=Path, help="the experiment folder of the shorter runs")
    p.add_argument("long", type=Path, help="the experiment folder of the runs to compare against")
    p.add_argument("env", help="the env id (a folder under runs/)")
    p.add_argument("condition", help="the condition (a folder under runs/ENV/)")
    args = p.parse_args()
    folders = [root / "runs" / args.env / args.condition for root in (args.short, args.long)]
    for folder in folders:
        if not folder.is_dir():
            fail(f"{folder}: no such run folder (expected EXPERIMENT/runs/ENV/CONDITION)")
    seeds = sorted(_seeds(folders[0]) & _seeds(folders[1]))
    if not seeds:
        fail(f"{folders[0]} and {folders[1]}: no finished seed in both")
    print(table([compare(*folders, s) for s in seeds]))
    return 0


if __name__ == "__main__":
    run(main)
