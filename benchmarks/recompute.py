"""Recompute every published table from the committed per-run logs, and compare.

Each published experiment folder (docs/results/ENV/ and docs/results/pipeline-ENV/experiment/)
holds its record (experiment.json) and, under runs/ENV/CONDITION/seed-S/, every run's
episodes.csv, evaluations.csv, summary.json and config.toml (the recipe it ran). This script
analyzes those logs with pidlab's own code, without retraining, and compares the result byte for
byte with the committed metrics.csv, summary.csv, report.md and report.html; then it recomputes the
tables of docs/results/README.md (benchmarks/results_table.py) from the summaries, and
docs/rescue.md's forecast tables (benchmarks/forecast_table.py) from the shipped specs and the
published runs, and its shield-floor table (benchmarks/shield_floor.py) from its per-episode JSON
files and the published runs. For a pipeline's experiment (docs/results/pipeline-ENV/experiment/) it also
recomputes the section of the pipeline's own report (docs/results/pipeline-ENV/report.md) that
reads those runs, "The agent alone" (its table, design note and reading), and its last section,
"Why this coaching", from the published experiment it cites (the other sections come from stages
whose data is not published), and checks that the pipeline's report.html is its report.md rendered.

With --write it writes the recomputed files (and that section of a pipeline's report, with its
report.html) instead of comparing: run it after a change to the report code, then review the diff.

It also prints, per condition, the numbers behind two of the reports' explanations, straight from
the logs: the first hit against the hit that lasted (runs whose first hit did not last), and the
training episodes with their mean length (a coach that keeps episodes alive gives fewer, longer ones).

Exit status: 0 everything matches, 1 a difference (shown as a diff), 2 a folder cannot be read.
Run: .venv/bin/python benchmarks/recompute.py [--write] [FOLDER ...]
"""

from __future__ import annotations

import difflib
import re
import sys
from pathlib import Path

import numpy as np
from bench_cli import run

from pidlab.errors import PidlabError
from pidlab.experiment.analysis import Analysis, analyze, recipes_of_runs
from pidlab.files import read_json
from pidlab.pipeline import published_evidence
from pidlab.report.experiment import figure_names, render_html, report_texts
from pidlab.report.pipeline import AGENT_ALONE, EVIDENCE_HEADING, agent_alone, evidence_lines

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


def pipeline_report(folder: Path) -> Path | None:
    """The pipeline report beside a pipeline's experiment folder (None: not a pipeline's experiment)."""
    report = folder.parent / "report.md"
    return report if folder.name == "experiment" and folder.parent.name.startswith("pipeline-") else None


def pipeline_texts(a: Analysis, report: Path) -> dict[str, str]:
    """A pipeline's report.md with its section on the agent alone recomputed, and its report.html.

    The section runs from its heading to the link to the experiment report that follows it.

    Raises
    ------
    ValueError
        The report has no such section, or not for exactly one env.
    """
    if len(a.envs) != 1:
        raise ValueError(f"a pipeline's experiment has one env, not {len(a.envs)}")
    text = report.read_text()
    start = text.index(f"\n{AGENT_ALONE}\n") + 1
    end = text.index("\nThe full experiment report", start) + 1
    text = text[:start] + "\n".join(agent_alone(a, a.envs[0])) + "\n" + text[end:]
    section = text.index(f"\n{EVIDENCE_HEADING}\n") + 1
    cond = re.search(r"intervene as the condition `([^`]+)`|compares the condition `([^`]+)`", text[section:])
    if cond is None:
        raise ValueError(f"{report}: section 5 names no condition")
    name = cond.group(1) or cond.group(2)
    lines = evidence_lines(a.envs[0], name, published_evidence(a.envs[0], name))
    text = text[:section] + "\n".join(lines).rstrip() + "\n"
    return {"report.md": text, "report.html": render_html(text, f"pidlab run {a.envs[0]}")}


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
    """The README tables against benchmarks/results_table.py's (recomputed from the summaries and logs)."""
    import results_table

    text = (RESULTS / "README.md").read_text()
    problems = []
    for block in results_table.BLOCKS:
        if block.begin not in text or block.end not in text:
            problems.append(f"docs/results/README.md: no {block.begin} ... {block.end} block")
            continue
        a, b = text.index(block.begin) + len(block.begin), text.index(block.end)
        if text[a:b].strip() != results_table.tables(block).strip():
            problems.append(f"docs/results/README.md: the tables after {block.begin} differ from "
                            "benchmarks/results_table.py's; run that script")  # fmt: skip
    marked = [(results_table.TEACH_BEGIN, results_table.TEACH_END, results_table.teaching_tables),
              (results_table.BASE_BEGIN, results_table.BASE_END, results_table.baselines),
              (results_table.BEST_BEGIN, results_table.BEST_END, results_table.against_best)]  # fmt: skip
    for begin, end, body in marked:
        if begin not in text or end not in text:
            problems.append(f"docs/results/README.md: no {begin} ... {end} block")
        elif text[text.index(begin) + len(begin) : text.index(end)].strip() != body().strip():
            problems.append(f"docs/results/README.md: the tables after {begin} differ from "
                            "benchmarks/results_table.py's; run that script")  # fmt: skip
    return problems


def check_forecast() -> list[str]:
    """docs/rescue.md's forecast tables against benchmarks/forecast_table.py's (minutes: Hopper's rows)."""
    import forecast_table

    same = forecast_table.page_tables() == forecast_table.tables().strip()
    return [] if same else [forecast_table.MISMATCH]


def check_shield_floor() -> list[str]:
    """docs/rescue.md's shield-floor table against benchmarks/shield_floor.py's, from its JSON files."""
    import shield_floor

    if shield_floor.page_table() == shield_floor.table():
        return []
    return ["docs/rescue.md: the shield-floor table differs from benchmarks/shield_floor.py's; run it "
            "with --table-only"]  # fmt: skip


def main(argv: list[str]) -> int:
    """Recompute the folders given (default: every published one); print what differs, or write it."""
    write = "--write" in argv
    argv = [a for a in argv if a != "--write"]
    folders = [Path(f) for f in argv] or published_folders()
    problems: list[str] = []
    for folder in folders:
        report = pipeline_report(folder)
        try:
            a, texts = recompute(folder)
            extra = pipeline_texts(a, report) if report is not None and report.exists() else {}
        except (PidlabError, OSError, KeyError, ValueError, TypeError) as exc:
            print(f"recompute: {folder}: cannot be read ({exc})", file=sys.stderr)
            return 2
        outputs = [(folder, texts), *([(folder.parent, extra)] if extra else [])]
        runs = sum(len(c.runs) for c in a.cells.values())
        for where, files in outputs:
            shown = where.relative_to(ROOT) if where.is_relative_to(ROOT) else where
            if write:
                for name, text in files.items():
                    (where / name).write_text(text)
                print(f"{shown}: {runs} runs; wrote {', '.join(files)}")
                continue
            diffs = differences(where, files)
            print(f"{shown}: {runs} runs; "
                  f"{', '.join(files)}: {'all match' if not diffs else f'{len(diffs)} differ'}")  # fmt: skip
            problems += diffs
        print("\n".join(explanations(a)))
    if not argv and not write:
        problems += check_readme() + check_forecast() + check_shield_floor()
    for p in problems:
        print(p)
    return 1 if problems else 0


if __name__ == "__main__":
    run(lambda: main(sys.argv[1:]))
