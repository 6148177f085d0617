"""Recompute every published table from the committed per-run logs, and compare.

Each published experiment folder (docs/results/ENV/ and docs/results/pipeline-ENV/experiment/)
holds its record (experiment.json) and, under runs/ENV/CONDITION/seed-S/, every run's
episodes.csv, evaluations.csv, summary.json and config.toml (the recipe it ran). This script
analyzes those logs with pidlab's own code, without retraining, and compares the result byte for
byte with the committed metrics.csv, summary.csv, report.md and report.html; then it recomputes the
tables of docs/results/README.md (benchmarks/results_table.py) from the summaries.

It also prints, per condition, the numbers behind two of the reports' explanations, straight from
the logs: the first hit against the hit that lasted (runs whose first hit did not last), and the
training episodes with their mean length (a coach that keeps episodes alive gives fewer, longer ones).

Exit status: 0 everything matches, 1 a difference (shown as a diff), 2 a folder cannot be read.
Run: .venv/bin/python benchmarks/recompute.py [FOLDER ...]
"""

from __future__ import annotations

import difflib
import sys
from pathlib import Path

import numpy as np

from pidlab.errors import PidlabError
from pidlab.experiment.analysis import Analysis, analyze, recipes_of_runs
from pidlab.files import read_json
from pidlab.report.experiment import figure_names, report_texts

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results"
sys.path.insert(0, str(ROOT / "benchmarks"))


def published_folders() -> list[Path]:
    """Every published experiment folder with per-run logs."""
    found = [p.parent for p in sorted(RESULTS.glob("*/experiment.json"))]
    found += [p.parent for p in sorted(RESULTS.glob("pipeline-*/experiment/experiment.json"))]
    return [f for f in found if (f / "runs").is_dir()]


def recompute(folder: Path) -> tuple[Analysis, dict[str, str]]:
    """The analysis of a published folder and the report files it gives."""
    record = read_json(folder / "experiment.json")
    identity = record.get("identity") if isinstance(record, dict) else None
    keys = ("envs", "conditions", "seeds")
    if not isinstance(identity, dict) or not all(isinstance(identity.get(k), list) for k in keys):
        raise ValueError("experiment.json is not an experiment record (expected lists identity.envs, "
                         ".conditions and .seeds)")  # fmt: skip
    a = analyze(identity, folder, recipes_of_runs(folder, identity))
    return a, report_texts(a, record, {env: figure_names(a, env) for env in a.envs})


def differences(folder: Path, texts: dict[str, str]) -> list[str]:
    """Unified diffs (at most 20 lines each) of the committed files against the recomputed ones."""
    out = []
    for name, text in texts.items():
        committed = (folder / name).read_text() if (folder / name).exists() else ""
        if committed != text:
            diff = difflib.unified_diff(committed.splitlines(), text.splitlines(), f"committed {name}",
                                        f"recomputed {name}", lineterm="", n=0)  # fmt: skip
            out.append("\n".join(list(diff)[:20]))
    return out


def explanations(a: Analysis) -> list[str]:
    """Per condition: hits that did not last, and training episodes with their length."""
    lines = []
    for (env, cond), cell in a.cells.items():
        hits = [(r.seed, r.metrics.first_hit_env_steps, r.metrics.env_steps_to_target) for r in cell.runs]
        lost = [seed for seed, first, kept in hits if first is not None and kept is None]
        late = [seed for seed, first, kept in hits if first is not None and kept is not None and first < kept]
        episodes = np.median([r.metrics.episodes for r in cell.runs])
        length = np.median([r.metrics.env_steps_per_episode for r in cell.runs])
        lines.append(
            f"  {env}/{cond}: median {episodes:.0f} training episodes of {length:.0f} env steps; "
            f"first hit lost by the end: seeds {lost or 'none'}; first hit lost, then regained later: "
            f"seeds {late or 'none'}"
        )
    return lines


def check_readme() -> list[str]:
    """The README tables against results_table.tables() (recomputed from the summaries)."""
    import results_table

    text = (RESULTS / "README.md").read_text()
    a, b = text.index(results_table.BEGIN) + len(results_table.BEGIN), text.index(results_table.END)
    if text[a:b].strip() == results_table.tables().strip():
        return []
    return ["docs/results/README.md: its tables differ from benchmarks/results_table.py's; run that script"]


def main(argv: list[str]) -> int:
    """Recompute the folders given (default: every published one); print what differs."""
    folders = [Path(f) for f in argv] or published_folders()
    problems: list[str] = []
    for folder in folders:
        try:
            a, texts = recompute(folder)
        except (PidlabError, OSError, KeyError, ValueError, TypeError) as exc:
            print(f"recompute: {folder}: cannot be read ({exc})", file=sys.stderr)
            return 2
        diffs = differences(folder, texts)
        runs = sum(len(c.runs) for c in a.cells.values())
        print(f"{folder.relative_to(ROOT) if folder.is_relative_to(ROOT) else folder}: {runs} runs; "
              f"{', '.join(texts)}: {'all match' if not diffs else f'{len(diffs)} differ'}")  # fmt: skip
        print("\n".join(explanations(a)))
        problems += diffs
    if not argv:
        problems += check_readme()
    for p in problems:
        print(p)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
