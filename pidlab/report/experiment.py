"""Write an experiment's report: per-run and per-condition tables, figures, Markdown and HTML.

Files written into the experiment folder (each atomically)::

    metrics.csv        one row per run: every metric of pidlab.experiment.metrics.RunMetrics
    summary.csv        one row per (env, condition, metric): IQM, 95 % CI, runs that reached it
    figures/ENV-curves.png, ENV-table2.png, ENV-dependence.png
    report.md, report.html
"""

from __future__ import annotations

import csv
import functools
import html
import io
import statistics
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from pidlab.experiment import plan
from pidlab.experiment.analysis import BASELINE, METRICS, Analysis, CellResult, analyze
from pidlab.experiment.comparison import ALPHA, MEASURE, POWER, Comparison, detectable
from pidlab.experiment.reuse import reuse_sentence
from pidlab.experiment.stats import Estimate, detectable_improvement
from pidlab.experiment.sweep import Plan, check_out_folder
from pidlab.files import atomic_write_text, read_json, save_figure
from pidlab.plant.card import PaperNumbers, find_card

UNITS = {
    "episodes_to_wins": "episodes",
    "episodes_to_average": "episodes",
    "episodes_to_wins_with_coach": "episodes",
    "episodes_to_average_with_coach": "episodes",
    "env_steps_to_target": "env steps",
    "agent_steps_to_target": "agent steps",
    "first_hit_env_steps": "env steps",
    "final_score": "return",
    "final_training_score": "return",
    "final_coached_score": "return",
    "intervention_rate": "coach steps / env steps",
    "episodes": "episodes",
    "env_steps_per_episode": "env steps",
    "policy_updates": "gradient steps",
    "evaluation_env_steps": "env steps",
    "evaluation_delay": "env steps",
    "falls": "falls",
    "env_resets": "resets",
    "env_episodes_to_wins": "env episodes",
    "env_episodes_to_average": "env episodes",
    "env_steps_to_alone_target": "env steps",
    "env_episodes": "env episodes",
    "mean_run_length": "agent actions",
    "wall_s_to_alone_target": "s",
    "clone_score": "return",
    "dip_score": "return",
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
    if v != v:
        return "n/a"
    if name == "intervention_rate":
        return f"{100 * v:.1f} %"
    counts = ("policy_updates", "evaluation_delay", "falls", "env_resets")
    if "steps" in name or "episodes" in name or name in counts:
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


def saving_text(e: Estimate | None) -> str:
    """A saving ``1 - coached / baseline`` (medians) with its 95 % interval, in percent.

    A coached median that never reached the target reads "never reached"; an interval end that
    runs which never reached decide reads "unbounded".
    """
    if e is None:
        return "-"
    if e.value != e.value:
        return "not estimable (the baseline's median never reached)"

    def pct(v: float) -> str:
        return "unbounded" if abs(v) == float("inf") else f"{100 * v:+.1f} %"

    point = "never reached" if e.value == float("-inf") else pct(e.value)
    return f"{point} [{pct(e.low)}, {pct(e.high)}]"


def paper_numbers(env: str) -> PaperNumbers | None:
    """What the paper published for ``env`` (its model card's ``[paper]`` table), or None.

    Raises
    ------
    ModelCardError
        The env's model card is malformed.
    """
    card = find_card(env)
    return card.paper if card is not None else None


def recipe_budget(env: str) -> int | None:
    """The budget, env steps, of the recipe pidlab ships for ``env`` (None: it ships none)."""
    from pidlab.errors import PidlabError
    from pidlab.rl.recipe import default_recipe_path, load_recipe

    try:
        return load_recipe(default_recipe_path(env)).steps
    except PidlabError:
        return None


PAPER_ROWS = (
    ("env_episodes_to_wins", "5 wins, env episodes (training returns)"),
    ("env_episodes_to_average", "average, env episodes (training returns)"),
    ("episodes_to_wins", "5 wins, agent episodes (training returns)"),
    ("episodes_to_average", "average, agent episodes (training returns)"),
    ("episodes_to_wins_with_coach", "5 wins, agent episodes (returns with the coach's rewards)"),
    ("episodes_to_average_with_coach", "average, agent episodes (returns with the coach's rewards)"),
)
"""The paper's measures: the first two are tested (the plan's secondary family), the rest described."""


def published_numbers(env: str) -> dict[str, tuple[str, str, str]]:
    """Measure -> the paper's (with coach, without, saving as printed)."""
    paper = paper_numbers(env)
    if paper is None:
        return {}
    wins = (str(paper.wins_coached), str(paper.wins_uncoached), f"+{paper.savings_wins:g} %")
    average = (str(paper.average_coached), str(paper.average_uncoached), f"+{paper.savings_average:g} %")
    return {"env_episodes_to_wins": wins, "env_episodes_to_average": average}


def _paper_rows(a: Analysis, env: str) -> list[list[str]]:
    rows = []
    published = published_numbers(env)
    conds = [c for c in a.conditions if (env, c) in a.cells]
    for name, label in PAPER_ROWS:
        row = [label, *published.get(name, ("", "", ""))]
        for c in conds:
            text = cell_metric(a.cells[(env, c)], name)
            comp = a.comparisons.get((env, c), {}).get(name)
            if comp is not None:
                text += f"; saving {saving_text(comp.saving)}"
            row.append(text)
        rows.append(row)
    return rows


def p_text(p: float) -> str:
    """A p-value as reports print it."""
    return f"{p:.2g}" if p >= 0.001 else f"{p:.1e}"


def verdict_text(c: Comparison) -> str:
    """The verdict of a comparison with the numbers it rests on."""
    e = c.improvement
    effect = f"P = {e.value:.2f} [{e.low:.2f}, {e.high:.2f}]"
    if c.saving is not None and c.verdict not in ("not testable", "never trained"):
        effect += f", saving {saving_text(c.saving)}"
    if c.verdict in ("not testable", "never trained"):
        return f"{c.label} ({c.reason})"
    if c.verdict == "no verdict possible":
        return f"{c.label} ({c.reason}; {effect})"
    test = f"exact p = {p_text(c.test.p_value)}, Holm {p_text(c.p_holm if c.p_holm is not None else 1.0)}"
    word = {"better": "better than no coach", "worse": "worse than no coach"}.get(c.verdict, c.verdict)
    return f"{word} ({effect}, {test})"


@functools.lru_cache(maxsize=64)
def _detectable_at(n: int, m: int, alpha: float) -> float | None:
    """The smallest P(improvement) that ``n`` against ``m`` runs detect at level ``alpha`` (None: none)."""
    return detectable_improvement(n, m, alpha=alpha, power=POWER)


def _family_sizes(a: Analysis, env: str) -> dict[str, int]:
    sizes: dict[str, int] = {}
    for (e, _), cs in a.comparisons.items():
        if e == env:
            for c in cs.values():
                sizes[c.family_name] = c.family
    return sizes


def design_note(a: Analysis, env: str) -> str:
    """What the seeds can show: run counts, Holm families, smallest detectable effect, smallest p."""
    comps = [c for (e, _), cs in a.comparisons.items() if e == env for c in cs.values()]
    if not comps:
        return ""
    n, m = comps[0].test.n, comps[0].test.m
    sizes = _family_sizes(a, env)
    primary = sizes.get("primary", 1)
    d = detectable(n, m)
    if d is None:
        power = f"with {n} against {m} seeds no exact test can reach p < {ALPHA:g}"
    else:
        power = (
            f"with {n} against {m} seeds, one exact two-sided test at {ALPHA:g} (before Holm) detects "
            f"with {100 * POWER:.0f} % power only effects of P >= {d:.2f}"
        )
        strict = _detectable_at(n, m, ALPHA / primary) if primary > 1 else None
        if strict is not None:
            level = f"{ALPHA:g}/{primary}"
            power += f", and one at the primary family's strictest level, {level}, only P >= {strict:.2f}"
        power += " (normal location-shift model)"
    families = " and ".join(f"a {name} family of {size} tests" for name, size in sizes.items())
    return (
        f"Design: {power}; the smallest possible p is {p_text(comps[0].smallest_p)}. Holm runs over "
        f"{families} (fixed sizes: a test that cannot run stays in with p = 1), and a verdict says better "
        f"or worse only when its Holm-adjusted p is below {ALPHA:g}. 'No clear difference' does not mean "
        "no difference: read the interval."
    )


def reading(a: Analysis, env: str, family: str | None = None) -> list[str]:
    """Plain sentences from the numbers (the human reading goes in docs/); ``family``: only that one."""
    if (env, a.baseline) not in a.cells:
        return ["No uncoached condition in this experiment: no comparison is drawn."]
    out = []
    for cond in a.conditions:
        cell, comps = a.cells.get((env, cond)), a.comparisons.get((env, cond))
        if cell is None or cond == a.baseline or not comps:
            continue
        parts = [f"{MEASURE[n].label}: {verdict_text(c)}" for n, c in comps.items()
                 if family is None or c.family_name == family]  # fmt: skip
        facts = [f"{cell.coach_dependent}/{len(cell.runs)} agents coach-dependent"]
        if cell.never_trained:
            facts.append(f"{cell.never_trained}/{len(cell.runs)} never trained (0 policy updates)")
        rate = format_value(cell.metrics["intervention_rate"].estimate.value, "intervention_rate")
        facts.append(f"the coach ran {rate} of env steps")
        out.append(f"**{cond}** vs no coach: " + "; ".join(parts) + ". " + "; ".join(facts) + ".")
    return out


HOW_TO_READ = (
    "- Every number is the interquartile mean (IQM) over seeds with its 95 % stratified bootstrap "
    "confidence interval in brackets (rliable's method, 2000 resamples).",
    "- The analysis follows the pre-registered plan (docs/analysis-plan.md). **Primary** measures, one "
    "Holm family per env: falls during training, env steps until the agent alone reaches the agent-alone "
    "target and keeps it, and the final agent-alone score. **Secondary**, a second family: the paper's "
    "measures counted in env episodes (and, on Hopper and Walker2d, env steps to the paper's target, "
    "which standing still reaches). Everything else is descriptive.",
    "- The paper's measures read the *training* returns, episode by episode, as the paper did, and are "
    "counted in **env** episodes: under the `terminal` view every veto ends an agent episode but not the "
    "env's, so agent episodes overstate how much a coached run experienced; the agent-episode counts are "
    "shown beside them. A coach's steps count toward the env's time limit but pay the agent nothing, so a "
    "coached episode's training return is capped at the time limit minus its coach steps; the returns "
    "*with* the coach's rewards have no cap and are shown, not tested. (n/N): runs that reached the target; "
    "a run that never did ranks below all that did, and the IQM reads 'not reached' when more than a "
    "quarter of the runs never did. The paper's savings are printed as the paper printed them.",
    "- The honest measures read the agent alone: deterministic policy, coach off, fixed evaluation "
    "seeds, every `evaluation.every` env steps. Env steps count the coach's steps too. The agent "
    "*reaches* the target at the first evaluation from which it scores at least the target at every "
    "evaluation to the end of the run (a transient hit does not count; the first hit is shown apart). "
    "Runs are compared at the evaluation's grid point (a multiple of `evaluation.every`): an evaluation "
    "runs at the first env step at or after its point. A coach intervention (takeover or nudge) under "
    "way at the point, or at the budget, finishes first, so an evaluation can run late and a coached "
    "run can end over its budget, by a few steps or by hundreds; the accounts table gives the largest "
    "delay per run.",
    "- Agent-alone evaluations are not charged to the budget of any condition, and they do not cost the "
    "same in every condition (an agent that falls early evaluates cheaply): the env steps they spent are "
    "in the accounts table and per run in `metrics.csv` (`evaluation_env_steps`).",
    "- Falls during training: terminations of the real training env, whoever was acting (agent or "
    "coach). A takeover is not a fall, nor is an agent episode that a `terminal`-view takeover ended when "
    "the coach's rescue succeeded. Env resets: real resets of the training envs (a rescued env handed to "
    "a new agent episode is not reset). Runs logged before pidlab counted them: an episode that ended "
    "terminated is a fall, and every episode's end a reset.",
    "- Training return: what the agent was paid on its own steps. Return with the coach: the same "
    "episodes with the coach's steps' rewards included. Coach-dependent: a trained agent whose return "
    "with the coach over the last window reached the target while it did not alone. Never trained: "
    "the run made no policy update (PPO updates once per full rollout), so it measures the initial "
    "policy, not coaching; such a run is never called coach-dependent.",
    "- P = probability of improvement over no coach (0.5: no difference; ties count half), with its 95 % "
    "score interval (Newcombe 2006, method 5; it does not collapse when the groups separate completely), "
    "the exact two-sided Wilcoxon-Mann-Whitney p-value and its Holm adjustment within the family. "
    "Saving: 1 - median(coached) / median(no coach), with its 95 % percentile bootstrap interval (10,000 "
    "resamples); 'unbounded' where runs that never reached the target decide that end. 'Not testable "
    "at this budget': every run of both conditions has the same value (for example, none reached the "
    "target). 'No verdict possible': too few seeds for any p below 0.05 after Holm.",
)

FIGURE_TITLES = ("Learning curves", "Table II as bars", "Coach dependence and interventions")


def _wall_time(a: Analysis) -> str:
    """The finished runs' training time (a sentence with a leading space), or "" when one lacks it."""
    walls = [r.wall_s for c in a.cells.values() for r in c.runs]
    seconds = [w for w in walls if w is not None]
    if not seconds or len(seconds) < len(walls):
        return ""
    return (
        f" Training wall time: {sum(seconds) / 3600:.1f} h summed over the runs (a run: median "
        f"{statistics.median(seconds) / 60:.1f} min, longest {max(seconds) / 60:.1f} min; a session "
        "that ended without a summary, such as a SIGKILL, is not counted)."
    )


def _front_matter(a: Analysis, record: Mapping[str, Any]) -> list[str]:
    """The header, the runs counted, the conditions and how to read the numbers."""
    seeds = record["identity"]["seeds"]
    scope = f"Seeds {seeds[0]}..{seeds[-1]} ({len(seeds)}); conditions {', '.join(a.conditions)}"
    lines = report_header(f"Coaching experiment: {', '.join(a.envs)}", record, scope=scope,
                          notes=[plan.citation(seeds, a.conditions, a.algorithms, a.envs)])  # fmt: skip
    total = sum(len(c.runs) for c in a.cells.values())
    finished = f"Finished runs: {total} of {total + len(a.missing)}."
    lines.append(f"{finished}{_wall_time(a)}{reuse_sentence(record)}")
    if a.missing:
        lines.append(f" Not finished (not counted): {', '.join(a.missing)}.")
    lines += ["", "## Conditions", ""]
    descriptions = record.get("descriptions", {})
    lines += [f"- **{c}**: {descriptions.get(c, '')}" for c in a.conditions]
    return [*lines, "", "## How to read this", "", *HOW_TO_READ, ""]


def _honest_table(a: Analysis, env: str, cells: Sequence[CellResult]) -> str:
    alone = a.alone_targets[env]
    paper_target = [] if alone == a.targets[env] else [f"env steps to the paper's target {a.targets[env]:g}"]
    header = [
        "condition",
        f"env steps to the agent-alone target {alone:g}, reached and kept",
        *paper_target,
        "falls during training",
        "agent steps to " + ("the paper's target" if paper_target else "target"),
        "env steps to a first hit" + (" of the paper's target" if paper_target else ""),
        "final agent-alone score",
        f"training return, last {a.windows[env]} episodes",
        "return with the coach, same episodes",
        "coach-dependent",
        "never trained",
        "intervention rate",
    ]
    names = ("env_steps_to_alone_target", *(["env_steps_to_target"] if paper_target else []), "falls",
             "agent_steps_to_target", "first_hit_env_steps", "final_score", "final_training_score",
             "final_coached_score")  # fmt: skip
    rows = [
        [c.condition, *(cell_metric(c, n) for n in names), f"{c.coach_dependent}/{len(c.runs)}",
         f"{c.never_trained}/{len(c.runs)}", cell_metric(c, "intervention_rate")]
        for c in cells
    ]  # fmt: skip
    return markdown_table(header, rows)


def _range(cell: CellResult, name: str) -> str:
    values = [getattr(r.metrics, name) for r in cell.runs]
    known = [float(v) for v in values if v is not None]
    if not known:
        return "not recorded"
    iqm_text = format_value(cell.metrics[name].estimate.value, name)
    return f"{iqm_text} ({format_value(min(known), name)} to {format_value(max(known), name)})"


LOGGED_LATER = {
    "mean_run_length": "mean uninterrupted agent run (agent actions)",
    "wall_s_to_alone_target": "wall time to the agent-alone target (s, all included)",
    "clone_score": "agent alone right after the warm start",
    "dip_score": "lowest agent-alone score in the 5 evaluations after it",
}
"""Accounts that runs log since issue 35: a column only where some run of the env logged them."""


def _accounts_table(cells: Sequence[CellResult]) -> str:
    header = ["condition", "training (agent) episodes", "env episodes", "env steps per training episode",
              "env resets", "policy updates (gradient steps)",
              "agent-alone evaluation env steps (not charged)",
              "largest evaluation delay (env steps)"]  # fmt: skip
    names = ["episodes", "env_episodes", "env_steps_per_episode", "env_resets", "policy_updates",
             "evaluation_env_steps", "evaluation_delay"]  # fmt: skip
    for name, title in LOGGED_LATER.items():
        if any(getattr(r.metrics, name) is not None for c in cells for r in c.runs):
            names.append(name)
            header.append(title)
    rows = [[c.condition, *(_range(c, n) for n in names)] for c in cells]
    return markdown_table(header, rows)


def _comparison_rows(a: Analysis, env: str, cells: Sequence[CellResult], family: str) -> list[list[str]]:
    rows = []
    for cell in cells:
        for name, c in a.comparisons.get((env, cell.condition), {}).items():
            if c.family_name != family:
                continue
            e = c.improvement
            holm_p = "-" if c.p_holm is None else p_text(c.p_holm)
            rows.append([cell.condition, MEASURE[name].label, f"{e.value:.2f} [{e.low:.2f}, {e.high:.2f}]",
                         saving_text(c.saving), p_text(c.test.p_value), holm_p, c.label])  # fmt: skip
    return rows


def _baseline_note(a: Analysis) -> list[str]:
    """Which condition is 'no coach' when it is not plain PPO (empty when it is)."""
    if a.baseline == BASELINE:
        return []
    return [f"No coach here is `{a.baseline}` (the plain SAC learner): the sweep has no plain PPO, so its "
            "couplings are tested against plain SAC (docs/analysis-plan.md, Amendment 23).", ""]  # fmt: skip


def _improvement_section(a: Analysis, env: str, cells: Sequence[CellResult]) -> list[str]:
    header = ["condition", "measure", "P(better than no coach) [95 % CI]", "saving of the median [95 % CI]",
              "exact p", "Holm p", "verdict"]  # fmt: skip
    sizes = _family_sizes(a, env)
    lines = ["### Against no coach", "", *_baseline_note(a), design_note(a, env), ""]
    for family, title in (("primary", "Primary measures"), ("secondary", "Secondary: the paper's measures")):
        if family in sizes:
            lines += [f"#### {title} (Holm family of {sizes[family]})", "",
                      markdown_table(header, _comparison_rows(a, env, cells, family)), ""]  # fmt: skip
    words = [f"- {s}" for s in reading(a, env)]
    return [*lines, "### In words (generated from the numbers above)", "", *words, ""]


def budget_share(a: Analysis, env: str) -> str:
    """The run budget's share of the shipped recipe's full budget, in words (empty: no shipped recipe)."""
    budget, full = a.budgets[env], recipe_budget(env)
    if not full:
        return ""
    return f"{100 * budget / full:.3g} % of the recipe's full budget of {full:,}"


def budget_text(a: Analysis, env: str) -> str:
    """The run budget and its share of the shipped recipe's budget."""
    share = budget_share(a, env)
    return f"budget {a.budgets[env]:,} env steps per run" + (f", {share} (coach/{env}.toml)" if share else "")


def _alone_text(a: Analysis, env: str) -> str:
    alone = a.alone_targets[env]
    if alone == a.targets[env]:
        return "the agent-alone target is the same"
    return (
        f"the agent-alone target {alone:g} (a return that standing still cannot reach; "
        "docs/analysis-plan.md, section 3)"
    )


def _env_section(a: Analysis, env: str, figures: Sequence[str]) -> list[str]:
    """One env's tables, reading and figures (nothing when no condition of it has a run)."""
    cells = [a.cells[(env, c)] for c in a.conditions if (env, c) in a.cells]
    if not cells:
        return []
    paper_header = ["measure", "paper: with coach", "paper: without", "paper: saving (as printed)",
                    *(f"ours: {c.condition}" for c in cells)]  # fmt: skip
    lines = [
        f"## {env}",
        "",
        f"The paper's target {a.targets[env]:g}; {_alone_text(a, env)}; moving-average window "
        f"{a.windows[env]} episodes, {budget_text(a, env)}. "
        "Every conclusion below holds at this budget only.",
        "",
        "### The paper's measures, beside its Table II",
        "",
        markdown_table(paper_header, _paper_rows(a, env)),
        "",
        "### Honest measures",
        "",
        _honest_table(a, env, cells),
        "",
        "### Accounts per run (IQM, and the range over seeds)",
        "",
        _accounts_table(cells),
        "",
    ]
    if any(a.comparisons.get((env, c.condition)) for c in cells):
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
    """One row per run (the columns of :data:`LOGGED_LATER` only when some run logged them)."""
    runs = [r for cell in a.cells.values() for r in cell.runs]
    unlogged = {k for k in LOGGED_LATER if all(getattr(r.metrics, k) is None for r in runs)}
    return [
        {"env": r.env_id, "condition": r.condition, "seed": r.seed, **{
            k: ("" if v is None else v) for k, v in vars(r.metrics).items() if k not in unlogged
        }}
        for r in runs
    ]  # fmt: skip


COMPARISON_FIELDS = ("family", "family_size", "p_improvement", "p_low", "p_high", "saving", "saving_low",
                     "saving_high", "p_value", "p_holm", "verdict")  # fmt: skip


def _comparison_fields(c: Comparison | None) -> dict[str, Any]:
    if c is None:
        return dict.fromkeys(COMPARISON_FIELDS, "")
    e, sv = c.improvement, c.saving
    saving = ("", "", "") if sv is None else (sv.value, sv.low, sv.high)
    return {"family": c.family_name, "family_size": c.family, "p_improvement": e.value, "p_low": e.low,
            "p_high": e.high, "saving": saving[0], "saving_low": saving[1], "saving_high": saving[2],
            "p_value": c.test.p_value, "p_holm": "" if c.p_holm is None else c.p_holm,
            "verdict": c.label}  # fmt: skip


def summary_rows(a: Analysis) -> list[dict[str, Any]]:
    """One row per (env, condition, metric) (those of :data:`LOGGED_LATER` where some run logged them)."""
    rows = []
    for cell in a.cells.values():
        comps = a.comparisons.get((cell.env_id, cell.condition), {})
        for name, m in cell.metrics.items():
            if name in LOGGED_LATER and all(getattr(r.metrics, name) is None for r in cell.runs):
                continue
            rows.append({
                "env": cell.env_id, "condition": cell.condition, "metric": name, "unit": UNITS[name],
                "iqm": m.estimate.value, "ci_low": m.estimate.low, "ci_high": m.estimate.high,
                "reached": m.reached, "runs": m.runs, **_comparison_fields(comps.get(name)),
            })  # fmt: skip
        for name, count in (("coach_dependent", cell.coach_dependent), ("never_trained", cell.never_trained)):
            rows.append({
                "env": cell.env_id, "condition": cell.condition, "metric": name, "unit": "runs",
                "iqm": count, "ci_low": "", "ci_high": "", "reached": "", "runs": len(cell.runs),
                **_comparison_fields(None),
            })  # fmt: skip
    return rows


def figure_names(a: Analysis, env: str) -> list[str]:
    """The report's figures of ``env``, relative to the report (none when no condition of it has a run)."""
    if not any((env, c) in a.cells for c in a.conditions):
        return []
    return [f"figures/{env}-{suffix}.png" for suffix in ("curves", "table2", "dependence")]


def report_texts(
    a: Analysis, record: Mapping[str, Any], figures: Mapping[str, Sequence[str]]
) -> dict[str, str]:
    """The text files of a report, by name: ``metrics.csv``, ``summary.csv``, ``report.md``, ``report.html``.

    A pure function of the analysis and the record, so that anyone can recompute a published report
    from its runs' logs (``benchmarks/recompute.py``) and compare it byte for byte.
    """
    text = render_markdown(a, record, figures)
    return {
        "metrics.csv": _csv(metrics_rows(a)),
        "summary.csv": _csv(summary_rows(a)),
        "report.md": text,
        "report.html": render_html(text, f"pidlab experiment: {', '.join(a.envs)}"),
    }


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
            names = figure_names(a, env)
            for rel, draw in zip(names, (plot_learning_curves, plot_table2_bars, plot_coach_dependence),
                                 strict=False):  # fmt: skip
                save_figure(draw(a, env), p.out / rel)
            if names:
                figures[env] = names
            bar.update(1)
        for name, text in report_texts(a, record, figures).items():
            atomic_write_text(p.out / name, text)
        bar.update(1)
    return p.out / "report.md"
