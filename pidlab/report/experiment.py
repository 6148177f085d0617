"""Write an experiment's report: per-run and per-condition tables, figures, Markdown and HTML.

Files written into the experiment folder (each atomically)::

    metrics.csv        one row per run: every metric of pidlab.experiment.metrics.RunMetrics
    summary.csv        one row per (env, condition, metric): IQM, 95 % CI, runs that reached it
    figures/ENV-curves.png, ENV-table2.png, ENV-dependence.png
    report.md, report.html
"""

from __future__ import annotations

import csv
import html
import io
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from pidlab.experiment.analysis import BASELINE, METRICS, Analysis, CellResult, analyze
from pidlab.experiment.stats import Estimate
from pidlab.experiment.sweep import Plan, check_out_folder
from pidlab.files import atomic_write_text, read_json, save_figure
from pidlab.plant.card import PaperNumbers, find_card

UNITS = {
    "episodes_to_wins": "episodes",
    "episodes_to_average": "episodes",
    "env_steps_to_target": "env steps",
    "agent_steps_to_target": "agent steps",
    "final_score": "return",
    "final_training_score": "return",
    "final_coached_score": "return",
    "intervention_rate": "coach steps / env steps",
}

VERSIONS = (
    "python",
    "pidlab",
    "numpy",
    "mujoco",
    "gymnasium",
    "stable-baselines3",
    "torch",
    "control",
    "ray",
)


def format_value(v: float, name: str) -> str:
    """A metric's value as the report shows it (``name``: a metric of :data:`METRICS`)."""
    if v == float("inf"):
        return "not reached"
    if name == "intervention_rate":
        return f"{100 * v:.1f} %"
    if "steps" in name:
        return f"{v:,.0f}"
    return f"{v:.0f}" if abs(v) >= 100 else f"{v:.1f}"


def estimate_text(e: Estimate, name: str) -> str:
    """An estimate as ``value [low, high]`` in the units of metric ``name``."""
    if e.value == float("inf"):
        return "not reached"
    high = format_value(e.high, name) if e.high < float("inf") else "not reached"
    return f"{format_value(e.value, name)} [{format_value(e.low, name)}, {high}]"


def cell_metric(cell: CellResult, name: str) -> str:
    """A metric of one (env, condition) with its interval and, for targets, how many runs reached it."""
    m = cell.metrics[name]
    text = estimate_text(m.estimate, name)
    if METRICS[name][1]:
        text += f" ({m.reached}/{m.runs})"
    return text


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A Markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def report_header(
    title: str,
    record: Mapping[str, Any],
    *,
    scope: str = "",
    notes: Sequence[str] = (),
    default_command: str = "",
) -> list[str]:
    """The head of every pidlab report: title, command, provenance, then versions (Markdown lines).

    Parameters
    ----------
    title : str
        The level-1 heading.
    record : mapping
        The provenance record (``experiment.json``, ``pipeline.json``): ``command``, ``created``,
        ``git`` (``sha``, ``dirty``), ``resumes``, ``versions``; a missing key shows as empty or ``?``.
    scope : str
        What the report covers (an experiment's seeds and conditions). Given, the command stands in a
        paragraph of its own and ``scope`` opens the provenance sentence; empty, the provenance follows
        the command on its line.
    notes : sequence of str
        Paragraphs between the provenance and the versions (a pipeline's settings).
    default_command : str
        Shown when the record has no command.

    Returns
    -------
    list of str
        The lines, each paragraph followed by an empty line.
    """
    git = record.get("git") or {}
    versions = record.get("versions", {})
    command = f"Command: `{' '.join(record.get('command', [])) or default_command}`"
    provenance = (
        f"created {record.get('created', '')}; git {str(git.get('sha') or '?')[:12]}"
        f"{' (dirty)' if git.get('dirty') else ''}; resumed {len(record.get('resumes', []))} time(s)."
    )
    lines = [f"# {title}", ""]
    lines += [command, "", f"{scope}; {provenance}", ""] if scope else [f"{command}; {provenance}", ""]
    for note in notes:
        lines += [note, ""]
    lines += ["Versions: " + ", ".join(f"{k} {versions[k]}" for k in VERSIONS if k in versions) + ".", ""]
    return lines


def _verdict(p: Estimate) -> str:
    if p.low > 0.5:
        return "better than no coach"
    if p.high < 0.5:
        return "worse than no coach"
    return "no clear difference"


def _saving(with_: float, without: float) -> str:
    finite = abs(with_) < float("inf") and abs(without) < float("inf")
    return f"{100 * (without - with_) / without:+.1f} %" if without and finite else "n/a"


def paper_numbers(env: str) -> PaperNumbers | None:
    """What the paper published for ``env`` (its model card's ``[paper]`` table), or None.

    Raises
    ------
    ModelCardError
        The env's model card is malformed.
    """
    card = find_card(env)
    return card.paper if card is not None else None


def _paper_rows(a: Analysis, env: str) -> list[list[str]]:
    rows = []
    paper = paper_numbers(env)
    published: dict[str, tuple[int, int]] = {}
    if paper is not None:
        published["episodes_to_wins"] = (paper.wins_coached, paper.wins_uncoached)
        published["episodes_to_average"] = (paper.average_coached, paper.average_uncoached)
    conds = [c for c in a.conditions if (env, c) in a.cells]
    for name, label in (("episodes_to_wins", "5 wins"), ("episodes_to_average", "average")):
        row = [label]
        pair = published.get(name)
        if pair:
            row += [str(pair[0]), str(pair[1]), _saving(pair[0], pair[1])]
        else:
            row += ["", "", ""]
        base = a.cells.get((env, BASELINE))
        for c in conds:
            cell = a.cells[(env, c)]
            text = cell_metric(cell, name)
            if base is not None and c != BASELINE:
                saving = _saving(cell.metrics[name].estimate.value, base.metrics[name].estimate.value)
                text += f"; saving {saving}"
            row.append(text)
        rows.append(row)
    return rows


def reading(a: Analysis, env: str) -> list[str]:
    """Plain sentences from the numbers (the human reading goes in docs/)."""
    out = []
    base = a.cells.get((env, BASELINE))
    if base is None:
        return ["No uncoached condition in this experiment: no comparison is drawn."]
    labels = {
        "episodes_to_wins": "episodes to 5 wins (training returns)",
        "episodes_to_average": "episodes to the moving-average target (training returns)",
        "env_steps_to_target": "env steps until the agent alone reaches the target",
        "final_score": "final agent-alone score",
    }
    for cond in a.conditions:
        cell = a.cells.get((env, cond))
        if cell is None or cond == BASELINE:
            continue
        parts = []
        for name, label in labels.items():
            p = cell.improvement[name]
            parts.append(f"{label}: {_verdict(p)} (P = {p.value:.2f} [{p.low:.2f}, {p.high:.2f}])")
        dep = f"{cell.coach_dependent}/{len(cell.runs)} agents coach-dependent"
        rate = format_value(cell.metrics["intervention_rate"].estimate.value, "intervention_rate")
        out.append(
            f"**{cond}** vs no coach: " + "; ".join(parts) + f". {dep}; the coach ran {rate} of env steps."
        )
    return out


HOW_TO_READ = (
    "- Every number is the interquartile mean (IQM) over seeds with its 95 % stratified bootstrap "
    "confidence interval in brackets (rliable's method, 2000 resamples).",
    "- The paper's metrics read the *training* returns (the reward the agent was paid on its own "
    "steps, in episodes the coach kept alive), as the paper did. (n/N): runs that reached the target; "
    "a run that never did ranks below all that did, and the IQM reads 'not reached' when more than a "
    "quarter of the runs never did. Saving: (without - with) / without, as the paper computes it.",
    "- The honest metrics read the agent alone: deterministic policy, coach off, fixed evaluation "
    "seeds, every `evaluation.every` env steps. Env steps count the coach's steps too.",
    "- Training return: what the agent was paid on its own steps. Return with the coach: the same "
    "episodes with the coach's steps' rewards included. Coach-dependent: the return with the coach "
    "over the last window reached the target, the agent alone did not. "
    "P = probability of improvement over no coach (0.5: no difference).",
)

FIGURE_TITLES = ("Learning curves", "Table II as bars", "Coach dependence and interventions")


def _front_matter(a: Analysis, record: Mapping[str, Any]) -> list[str]:
    """The header, the runs counted, the conditions and how to read the numbers."""
    seeds = record["identity"]["seeds"]
    scope = f"Seeds {seeds[0]}..{seeds[-1]} ({len(seeds)}); conditions {', '.join(a.conditions)}"
    lines = report_header(f"Coaching experiment: {', '.join(a.envs)}", record, scope=scope)
    total = sum(len(c.runs) for c in a.cells.values())
    lines.append(f"Finished runs: {total} of {total + len(a.missing)}.")
    if a.missing:
        lines.append(f" Not finished (not counted): {', '.join(a.missing)}.")
    lines += ["", "## Conditions", ""]
    descriptions = record.get("descriptions", {})
    lines += [f"- **{c}**: {descriptions.get(c, '')}" for c in a.conditions]
    return [*lines, "", "## How to read this", "", *HOW_TO_READ, ""]


def _honest_table(a: Analysis, env: str, cells: Sequence[CellResult]) -> str:
    header = [
        "condition",
        "env steps to target (agent alone)",
        "agent steps to target",
        "final agent-alone score",
        f"training return, last {a.windows[env]} episodes",
        "return with the coach, same episodes",
        "coach-dependent",
        "intervention rate",
    ]
    rows = [
        [
            c.condition,
            *(cell_metric(c, name) for name in ("env_steps_to_target", "agent_steps_to_target", "final_score",
                                                "final_training_score", "final_coached_score")),
            f"{c.coach_dependent}/{len(c.runs)}",
            cell_metric(c, "intervention_rate"),
        ]
        for c in cells
    ]  # fmt: skip
    return markdown_table(header, rows)


def _improvement_section(a: Analysis, env: str, cells: Sequence[CellResult]) -> list[str]:
    header = [
        "condition",
        "P(fewer episodes to 5 wins)",
        "P(fewer episodes to average)",
        "P(fewer env steps to target, alone)",
        "P(higher final score, alone)",
    ]
    rows = [
        [c.condition, *(f"{p.value:.2f} [{p.low:.2f}, {p.high:.2f}]" for p in c.improvement.values())]
        for c in cells
        if c.improvement
    ]
    return [
        "### Probability of improvement over no coach",
        "",
        markdown_table(header, rows),
        "",
        "### In words (generated from the numbers above)",
        "",
        *(f"- {s}" for s in reading(a, env)),
        "",
    ]


def _env_section(a: Analysis, env: str, figures: Sequence[str]) -> list[str]:
    """One env's tables, reading and figures (nothing when no condition of it has a run)."""
    cells = [a.cells[(env, c)] for c in a.conditions if (env, c) in a.cells]
    if not cells:
        return []
    paper_header = ["measure", "paper: with coach", "paper: without", "paper: saving",
                    *(f"ours: {c.condition}" for c in cells)]  # fmt: skip
    lines = [
        f"## {env}",
        "",
        f"Target {a.targets[env]:g}, moving-average window {a.windows[env]} episodes, budget "
        f"{a.budgets[env]:,} env steps per run.",
        "",
        "### The paper's measures, beside its Table II",
        "",
        markdown_table(paper_header, _paper_rows(a, env)),
        "",
        "### Honest measures",
        "",
        _honest_table(a, env, cells),
        "",
    ]
    if any(c.improvement for c in cells):
        lines += _improvement_section(a, env, cells)
    for title, path in zip(FIGURE_TITLES, figures, strict=False):
        lines += [f"![{env}: {title}]({path})", ""]
    return lines


def render_markdown(a: Analysis, record: Mapping[str, Any], figures: Mapping[str, Sequence[str]]) -> str:
    """The report as Markdown.

    Parameters
    ----------
    a : Analysis
        The analyzed runs (:func:`pidlab.experiment.analysis.analyze`).
    record : mapping
        The experiment's record (``experiment.json``).
    figures : mapping
        Env -> its figure paths relative to the report, in the order of :data:`FIGURE_TITLES`.

    Returns
    -------
    str
    """
    lines = _front_matter(a, record)
    for env in a.envs:
        lines += _env_section(a, env, figures.get(env, []))
    return "\n".join(lines).rstrip() + "\n"


def render_html(markdown_text: str, title: str) -> str:
    """A standalone HTML page of the Markdown report."""
    import markdown

    body = markdown.markdown(markdown_text, extensions=["tables"])
    style = (
        "body{font-family:system-ui,sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;"
        "line-height:1.45}"
        "table{border-collapse:collapse;font-size:0.9em;margin:1em 0}"
        "th,td{border:1px solid #ccc;padding:4px 8px;text-align:left}th{background:#f0f0f0}"
        "img{max-width:100%}code{background:#f4f4f4;padding:1px 4px}"
    )
    return (
        f"<!doctype html>\n<html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
        f"<style>{style}</style></head><body>\n{body}\n</body></html>\n"
    )


def _csv(rows: list[dict[str, Any]]) -> str:
    buf = io.StringIO()
    if rows:
        w = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
        w.writeheader()
        w.writerows(rows)
    return buf.getvalue()


def metrics_rows(a: Analysis) -> list[dict[str, Any]]:
    """One row per run."""
    rows = []
    for cell in a.cells.values():
        for r in cell.runs:
            m = r.metrics
            rows.append({"env": r.env_id, "condition": r.condition, "seed": r.seed, **{
                k: ("" if v is None else v) for k, v in vars(m).items()
            }})  # fmt: skip
    return rows


def summary_rows(a: Analysis) -> list[dict[str, Any]]:
    """One row per (env, condition, metric)."""
    rows = []
    for cell in a.cells.values():
        for name, m in cell.metrics.items():
            p = cell.improvement.get(name)
            rows.append({
                "env": cell.env_id, "condition": cell.condition, "metric": name, "unit": UNITS[name],
                "iqm": m.estimate.value, "ci_low": m.estimate.low, "ci_high": m.estimate.high,
                "reached": m.reached, "runs": m.runs,
                "p_improvement": "" if p is None else p.value,
                "p_low": "" if p is None else p.low, "p_high": "" if p is None else p.high,
            })  # fmt: skip
        rows.append({
            "env": cell.env_id, "condition": cell.condition, "metric": "coach_dependent", "unit": "runs",
            "iqm": cell.coach_dependent, "ci_low": "", "ci_high": "", "reached": "", "runs": len(cell.runs),
            "p_improvement": "", "p_low": "", "p_high": "",
        })  # fmt: skip
    return rows


def write_report(p: Plan, progress_bar: bool = True, analysis: Analysis | None = None) -> Path:
    """Analyze the runs of ``p`` and write the report files; returns the path of ``report.md``.

    ``analysis``: the runs of ``p`` already analyzed (:func:`pidlab.experiment.analysis.analyze`).

    Raises
    ------
    ExperimentError
        The folder holds another experiment.
    """
    from tqdm.auto import tqdm

    from pidlab.report.curves import plot_coach_dependence, plot_learning_curves, plot_table2_bars

    check_out_folder(p)
    record = read_json(p.out / "experiment.json")
    steps = ["analysis", *(f"figures {env}" for env in p.envs), "report"]
    with tqdm(total=len(steps), desc="report", unit="step", disable=not progress_bar) as bar:
        a = analysis if analysis is not None else analyze(record["identity"], p.out, p.recipes)
        bar.update(1)
        figures: dict[str, list[str]] = {}
        for env in p.envs:
            if not any((env, c) in a.cells for c in a.conditions):
                bar.update(1)
                continue
            names = []
            for suffix, draw in (("curves", plot_learning_curves), ("table2", plot_table2_bars),
                                 ("dependence", plot_coach_dependence)):  # fmt: skip
                rel = f"figures/{env}-{suffix}.png"
                save_figure(draw(a, env), p.out / rel)
                names.append(rel)
            figures[env] = names
            bar.update(1)
        text = render_markdown(a, record, figures)
        atomic_write_text(p.out / "metrics.csv", _csv(metrics_rows(a)))
        atomic_write_text(p.out / "summary.csv", _csv(summary_rows(a)))
        atomic_write_text(p.out / "report.md", text)
        atomic_write_text(p.out / "report.html", render_html(text, f"pidlab experiment: {', '.join(a.envs)}"))
        bar.update(1)
    return p.out / "report.md"
