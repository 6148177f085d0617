"""What a coupling did in its runs, per condition, from the published logs: docs/results/README.md readings.

For each env and condition of a published experiment folder, from every run's ``summary.json``
and ``episodes.csv``: the falls, the falls in agent episodes in which the coach took over (a fall
while the coach acted: under the ``terminal`` view a takeover ends the agent's episode, so such a
fall came under the coach; demonstration steps are not takeovers), the coach's share of the env
steps, the value trigger's vetoes, the proposals the critic picked, the gradient steps per env
step, and the training wall time. The experiment reports do not tabulate the last four; the
readings of the off-policy couplings (Amendment 13) cite this table. Under another view a takeover
does not end the agent's episode, so the falls while the coach acted cannot be told apart: a run
with takeovers under another view shows "-" there.

Run: .venv/bin/python benchmarks/run_accounts.py docs/results/InvertedPendulum-v5-offpolicy [...]
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import tomllib
from bench_cli import Parser, fail, run


@dataclass(frozen=True)
class RunAccounts:
    """One run's accounts (see the module docstring)."""

    falls: int
    falls_under_coach: int | None
    env_steps: int
    coach_steps: int
    value_vetoes: int
    proposals_taken: int
    policy_updates: int
    wall_s: float | None


def falls_under_coach(rows: list[dict[str, str]]) -> int:
    """Falls in the agent episodes (rows of ``episodes.csv``) in which the coach took over.

    Under the ``terminal`` view a takeover ends the agent's episode, so such a fall came while the
    coach acted; under another view it may have come later, from the agent.
    """
    return sum(int(r["fell"]) and int(r["interventions"]) > 0 for r in rows)


def _view(run_dir: Path) -> str | None:
    """The run's takeover view (its ``config.toml``), or None when it does not say."""
    config = run_dir / "config.toml"
    if not config.is_file():
        return None
    return tomllib.loads(config.read_text()).get("recipe", {}).get("coaching", {}).get("view")


def run_accounts(run_dir: Path) -> RunAccounts:
    """The accounts of one finished run folder."""
    s = json.loads((run_dir / "summary.json").read_text())
    with open(run_dir / "episodes.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    takeovers = any(int(r["interventions"]) > 0 for r in rows)
    under = falls_under_coach(rows) if _view(run_dir) == "terminal" or not takeovers else None
    return RunAccounts(int(s["falls"]), under, int(s["env_steps"]), int(s["coach_steps"]),
                       int(s.get("value_vetoes", 0)), int(s.get("proposals_taken", 0)),
                       int(s["policy_updates"]), s.get("wall_s_total"))  # fmt: skip


def folder_accounts(folder: Path) -> dict[tuple[str, str], list[RunAccounts]]:
    """(env, condition) -> the accounts of its finished runs (``summary.json`` says ``completed``).

    A run that a signal stopped also writes a summary, with ``completed`` false: it is left out.
    """
    out: dict[tuple[str, str], list[RunAccounts]] = {}
    for summary in sorted((folder / "runs").glob("*/*/seed-*/summary.json")):
        if not json.loads(summary.read_text()).get("completed", False):
            continue
        run_dir = summary.parent
        key = (run_dir.parent.parent.name, run_dir.parent.name)
        out.setdefault(key, []).append(run_accounts(run_dir))
    return out


def _span(values: list[float], fmt: str = "{:,.0f}") -> str:
    lo, hi = fmt.format(min(values)), fmt.format(max(values))
    return lo if lo == hi else f"{lo} to {hi}"


def _known(values: list[float | None]) -> str:
    """The range, or "-" when a run does not say (a view that hides it, a log without the figure)."""
    known = [v for v in values if v is not None]
    return _span(known) if known and len(known) == len(values) else "-"


def table(accounts: dict[tuple[str, str], list[RunAccounts]]) -> list[str]:
    """A Markdown table: one row per env and condition, each cell the range over its runs."""
    head = ["env", "condition", "runs", "falls", "falls while the coach acted",
            "coach's share of env steps", "value vetoes", "proposals picked", "gradient steps per env step",
            "training wall time (s)"]  # fmt: skip
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for (env, condition), runs in accounts.items():
        cells = [env, condition, str(len(runs)), _span([r.falls for r in runs]),
                 _known([r.falls_under_coach for r in runs]),
                 _span([100 * r.coach_steps / r.env_steps for r in runs], "{:.1f} %"),
                 _span([r.value_vetoes for r in runs]), _span([r.proposals_taken for r in runs]),
                 _span([r.policy_updates / r.env_steps for r in runs], "{:.2f}"),
                 _known([r.wall_s for r in runs])]  # fmt: skip
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def main() -> None:
    parser = Parser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="+", help="Published experiment folders (docs/results/NAME).")
    args = parser.parse_args()
    for name in args.folders:
        folder = Path(name)
        accounts = folder_accounts(folder)
        if not accounts:
            fail(f"{name}: no finished run (expected runs/ENV/CONDITION/seed-N/summary.json)")
        print(f"{name}:\n")
        print("\n".join(table(accounts)) + "\n")


if __name__ == "__main__":
    run(main)
