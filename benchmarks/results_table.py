"""Write the tables of docs/results/README.md from the committed experiment reports.

Six blocks, each between its own markers: each env's best plain baseline (:func:`baselines`, Amendment
8's rule), every coupling against it (:func:`against_best`, issue 37's aim), the couplings against none
(:func:`teaching_tables`: the sweeps of the plan's Amendments 1-5, 7-17 and 19, `benchmarks/evidence.sh
--teach` to `--teach8`, `--sac`, `--full`, `--edge`, `--offpolicy`, `--edgemodel`, `--learned`, `--room`
and `--scoped`), the confirmation (:data:`CONFIRM`: the sweeps of docs/analysis-plan.md on fresh seeds,
`benchmarks/evidence.sh --confirm`), the pilot evidence at budgets where the uncoached agent
reaches the target (:data:`EVIDENCE`: the folders benchmarks/evidence.sh publishes, with `none`,
`paper` and the coached condition chosen for it) and the early-phase results (:data:`EARLY`: the
folders benchmarks/experiments.sh publishes). Reads each folder's summary.csv and experiment.json
and the paper's published numbers from the model cards (models/ENV.toml, ``[paper]``), and replaces
the text between the markers, so the numbers there are never typed by hand.
Run: .venv/bin/python benchmarks/results_table.py
"""

from __future__ import annotations

import csv
import math
import statistics
from dataclasses import dataclass
from pathlib import Path

from bench_cli import run

from pidlab.experiment.analysis import baseline_of, recipes_of_runs
from pidlab.experiment.plan import ALONE_TARGETS, AMENDMENT_LIST, PlainLearner, best_plain_baseline
from pidlab.experiment.stats import Estimate, median_saving
from pidlab.experiment.sweep import finished
from pidlab.files import atomic_write_text, read_json
from pidlab.report.experiment import (
    PAPER_ROWS,
    estimate_text,
    p_text,
    paper_numbers,
    published_numbers,
    recipe_budget,
    saving_text,
)

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results"
ENVS = ("InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Hopper-v5", "Walker2d-v5")
CONDITIONS = ("none", "paper", "pidlab", "pidlab-fading")
BEGIN = "<!-- tables: begin (benchmarks/results_table.py) -->"
END = "<!-- tables: end -->"


@dataclass(frozen=True)
class Block:
    """One marked block of tables: which published folders, which conditions, under which headings."""

    begin: str
    end: str
    folders: tuple[tuple[str, str], ...]  # (env, folder under docs/results)
    conditions: tuple[str, ...]
    headings: tuple[str, str, str]  # Table II, honest measures, how each was run
    falls: bool  # the honest table shows the falls during training and their comparison


EARLY = Block(
    BEGIN, END, tuple((env, env) for env in ENVS), CONDITIONS,
    ("The paper's Table II beside ours (training episodes; IQM [95 % CI] (runs that reached it))",
     "The honest measures", "How each was run"),
    falls=False,
)  # fmt: skip
"""The early-phase sweeps (cut budgets on three envs) with the issue-9 conditions."""
EVIDENCE = Block(
    "<!-- evidence: begin (benchmarks/results_table.py) -->", "<!-- evidence: end -->",
    (("InvertedPendulum-v5", "InvertedPendulum-v5-rescue"),
     ("InvertedDoublePendulum-v5", "InvertedDoublePendulum-v5-rescue"),
     ("Hopper-v5", "Hopper-v5-300k"), ("Walker2d-v5", "Walker2d-v5-evidence")),
    ("none", "paper", "rescue-terminal"),
    ("Table II at these budgets (training episodes; IQM [95 % CI] (runs that reached it))",
     "The honest measures at these budgets", "How the evidence was run"),
    falls=True,
)  # fmt: skip
"""The pilot evidence (seeds 0-9): budgets where the uncoached agent reaches the target; a folder not
yet published is left out."""
CONFIRM = Block(
    "<!-- confirmation: begin (benchmarks/results_table.py) -->", "<!-- confirmation: end -->",
    tuple((env, f"{env}-confirm") for env in ENVS),
    ("none", "paper", "rescue-terminal"),
    ("Table II on the confirmatory seeds (env episodes; IQM [95 % CI] (runs that reached it))",
     "The primary measures on the confirmatory seeds", "How the confirmation was run"),
    falls=True,
)  # fmt: skip
"""The confirmation (docs/analysis-plan.md): fresh seeds 100-109; a folder not yet published is left
out."""
BLOCKS = (CONFIRM, EVIDENCE, EARLY)
TABLE2_ROWS = PAPER_ROWS[:4]
"""The paper's measures in env episodes (tested) and in agent episodes (described)."""


def _num(text: str) -> float:
    return float(text) if text not in ("", "inf") else math.inf


def _cell(row: dict[str, str] | None, to_target: bool = True) -> str:
    if row is None:
        return "-"
    text = estimate_text(Estimate(_num(row["iqm"]), _num(row["ci_low"]), _num(row["ci_high"])), row["metric"])
    if to_target:
        text += f" ({row['reached']}/{row['runs']})"
    return text


def _load(name: str) -> tuple[dict[tuple[str, str], dict[str, str]], dict] | None:
    folder = RESULTS / name
    if not (folder / "summary.csv").exists():
        return None
    with open(folder / "summary.csv", newline="") as fh:
        rows = {(r["condition"], r["metric"]): r for r in csv.DictReader(fh)}
    return rows, read_json(folder / "experiment.json")


def _saving(row: dict[str, str]) -> str:
    """A summary row's saving of the median with its interval ("" for a measure without one)."""
    if not row.get("saving", ""):
        return ""
    saving = Estimate(_num(row["saving"]), _num(row["saving_low"]), _num(row["saving_high"]))
    return "saving " + saving_text(saving)


def _verdict(row: dict[str, str]) -> str:
    """P(improvement) [CI], saving [CI], exact p, Holm p and the verdict of one summary row."""
    if not row["p_improvement"]:
        return "-"
    p = f"{float(row['p_improvement']):.2f} [{float(row['p_low']):.2f}, {float(row['p_high']):.2f}]"
    if _saving(row):
        p += f"; {_saving(row)}"
    tests = f"p = {p_text(float(row['p_value']))}"
    if row["p_holm"]:
        tests += f", Holm {p_text(float(row['p_holm']))}"
    return f"{p}; {tests}; {row['verdict']}"


def _table2(env: str, rows: dict[tuple[str, str], dict[str, str]], conditions: tuple[str, ...]) -> list[str]:
    paper = paper_numbers(env)
    if paper is None:
        raise SystemExit(f"models/{env}.toml has no [paper] table: the paper's numbers come from there")
    published = published_numbers(env)
    out = []
    for metric, label in TABLE2_ROWS:
        ours = []
        for c in conditions:
            row = rows.get((c, metric))
            ours.append(_cell(row) + (f"; {_saving(row)}" if row is not None and _saving(row) else ""))
        cells = [*published.get(metric, ("", "", "")), *ours]
        out.append(f"| {env} ({paper.win_target:g}) | {label} | " + " | ".join(cells) + " |")
    return out


def _honest(env: str, rows: dict[tuple[str, str], dict[str, str]], share: str, block: Block) -> list[str]:
    out = []
    for c in block.conditions:
        if (c, "final_score") not in rows:
            continue
        dep, never = rows[(c, "coach_dependent")], rows[(c, "never_trained")]
        falls = [_cell(rows[(c, "falls")], False)] if block.falls else []
        steps = rows[(c, "env_steps_to_alone_target")]
        cells = [f"{env} ({_target_text(env)})", share, c, *falls,
                 _cell(steps), _cell(rows[(c, "final_score")], False), f"{dep['iqm']}/{dep['runs']}",
                 f"{never['iqm']}/{never['runs']}",
                 _cell(rows[(c, "intervention_rate")], False), _verdict(steps),
                 _verdict(rows[(c, "final_score")])]  # fmt: skip
        out.append("| " + " | ".join(cells + ([_verdict(rows[(c, "falls")])] if block.falls else [])) + " |")
    return out


def _target_text(env: str) -> str:
    """The env's agent-alone target as the honest table's env column shows it."""
    paper = paper_numbers(env)
    target = ALONE_TARGETS.get(env, paper.win_target if paper is not None else math.nan)
    return f"{target:g}"


def _budget(env: str, name: str, record: dict) -> int:
    """The run budget in env steps: the recipe its runs recorded."""
    return recipes_of_runs(RESULTS / name, record["identity"])[env].steps


def _share(env: str, steps: int) -> str:
    """The run budget and its share of the shipped recipe's budget."""
    full = recipe_budget(env)
    return f"{steps:,} ({100 * steps / full:.3g} % of {full:,})" if full else f"{steps:,}"


def _progress(name: str, record: dict, budget: int) -> str:
    """What the "how it was run" line adds while a sweep split over sessions is still under way."""
    dirs = [RESULTS / name / "runs" / env / cond / f"seed-{seed}"
            for env, cond, seed in (key.split("/") for key in record["identity"]["runs"])]  # fmt: skip
    done = sum(finished(d, budget) for d in dirs)
    return "" if done == len(dirs) else f"; **in progress: {done} of {len(dirs)} runs finished**"


def _honest_head(block: Block) -> list[str]:
    falls = ["falls during training"] if block.falls else []
    return ["env (agent-alone target)", "budget, env steps (share of the recipe's)", "condition", *falls,
            "env steps to the agent-alone target, reached and kept", "final agent-alone score",
            "coach-dependent", "never trained", "intervention rate",
            "fewer env steps to the agent-alone target than none: P [CI]; exact p; verdict",
            "higher final score than none: P [CI]; exact p; verdict",
            *(["fewer falls than none: P [CI]; exact p; verdict"] if block.falls else [])]  # fmt: skip


def tables(block: Block = EARLY) -> str:
    """The Markdown tables of ``block``."""
    head = ["env (target)", "measure", "paper: with coach", "paper: without", "paper: saving (as printed)",
            *(f"ours: {c}" for c in block.conditions)]  # fmt: skip
    t2 = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    honest_head = _honest_head(block)
    t3 = ["| " + " | ".join(honest_head) + " |", "|" + "---|" * len(honest_head)]
    budgets = []
    for env, name in block.folders:
        loaded = _load(name)
        if loaded is None:
            continue
        rows, record = loaded
        ident = record["identity"]
        budget = _budget(env, name, record)  # read once from the runs' recipes
        share, progress = _share(env, budget), _progress(name, record, budget)
        command = " ".join(record["command"])
        budgets.append(f"- **{env}**: {len(ident['seeds'])} seeds x {len(ident['conditions'])} conditions, "
                       f"{share} env steps per run; `{command}`{progress}")  # fmt: skip
        t2 += _table2(env, rows, block.conditions)
        t3 += _honest(env, rows, share, block)
    table2, honest, how = block.headings
    if not budgets:
        return f"Not published yet: {', '.join(name for _, name in block.folders)}."
    return "\n".join([
        f"### {table2}", "", *t2, "", f"### {honest}", "", *t3, "", f"### {how}", "", *budgets,
    ])  # fmt: skip


TEACH_BEGIN = "<!-- teaching: begin (benchmarks/results_table.py) -->"
TEACH_END = "<!-- teaching: end -->"
TEACH_SWEEPS = ("teach", "teach2", "teach3", "teach4", "teach5", "teach6", "teach7", "teach8", "sac", "full",
                "edge", "offpolicy", "edgemodel", "learned", "room", "roomfocus", "roommodel",
                "scoped")  # fmt: skip
"""The folders ENV-teach, ... ENV-teach8 (the plan's Amendments 1-5, 7, 10 and 19), ENV-sac (Amendment 8:
plain SAC beside plain PPO), ENV-full (Amendments 9 and 11: the rescue region over the full state), ENV-edge
(Amendment 12: that region validated at its edge), ENV-offpolicy (Amendment 13: SAC that learns from
the coach), ENV-edgemodel (Amendment 14: the model predictor on that region), ENV-learned (Amendment 15:
a learned one-step model on the full-state region), ENV-room (Amendment 16: Hopper's room coach and
its region over the legs), ENV-roomfocus (Amendment 20: that region fitted again with focus), ENV-roommodel
(Amendment 21: that region asked through a learned one-step model) and
ENV-scoped (Amendment 17: that learned model's margins where they decide a veto, and the linear bound)
of each env."""
AIM = {"falls": 0.9, "env_steps_to_alone_target": 0.5}
"""Issue 35's aim as savings of the median against none: at least 90 % fewer falls, half the env steps."""


def aim_word(low: float, high: float, threshold: float) -> str:
    """The aim read from a saving's interval: met (above the threshold), missed (below), undecided."""
    return "met" if low >= threshold else "missed" if high < threshold else "undecided"


def _aim(e: Estimate, threshold: float) -> tuple[str, str]:
    """A saving with its interval and the aim read from it, and the aim's word."""
    word = aim_word(e.low, e.high, threshold)
    return f"saving {saving_text(e)}: **{word}** (aim {100 * threshold:.0f} %)", word


def aim_text(row: dict[str, str], threshold: float) -> str:
    """A summary row's saving against none and the aim read from its interval."""
    if not row.get("saving", ""):
        return "no saving (no coach never reached it)"
    saving = Estimate(_num(row["saving"]), _num(row["saving_low"]), _num(row["saving_high"]))
    return _aim(saving, threshold)[0]


def _teach_row(env: str, sweep: str, c: str, rows: dict[tuple[str, str], dict[str, str]], base: str) -> str:
    def cell(metric: str, to_target: bool = False) -> str:
        row = rows.get((c, metric))
        return _cell(row, to_target) if row is not None else "-"

    aims = [aim_text(rows[(c, m)], t) if c != base else "-" for m, t in AIM.items()]
    verdicts = [rows[(c, m)]["verdict"] or "-" for m in ("falls", "env_steps_to_alone_target", "final_score")]
    clone = f"{cell('clone_score')} / {cell('dip_score')}" if (c, "clone_score") in rows else "-"
    cells = [env, sweep, c, cell("falls"), aims[0], cell("env_steps_to_alone_target", True), aims[1],
             cell("final_score"), cell("wall_s_to_alone_target"), cell("mean_run_length"), clone,
             cell("intervention_rate"), " / ".join(verdicts)]  # fmt: skip
    return "| " + " | ".join(cells) + " |"


def teaching_tables() -> str:
    """The teaching couplings against none: the primary measures, the aim, cost and the dip."""
    head = ["env", "sweep", "condition", "falls during training", "fewer falls (aim)",
            "env steps to the agent-alone target, reached and kept", "fewer env steps (aim)",
            "final agent-alone score", "wall time to the target (s)", "mean uninterrupted agent run",
            "agent alone after the warm start / lowest in the next 5 evaluations", "intervention rate",
            "verdicts: falls / env steps / final score (Holm)"]  # fmt: skip
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    how = []
    for env in ENVS:
        for sweep in TEACH_SWEEPS:
            name = f"{env}-{sweep}"
            loaded = _load(name)
            if loaded is None:
                continue
            rows, record = loaded
            budget = _budget(env, name, record)
            conds = record["identity"]["conditions"]
            base = baseline_of(conds)  # the sweep's no coach: plain PPO, or plain SAC without it
            out += [_teach_row(env, sweep, c, rows, base) for c in conds if (c, "final_score") in rows]
            ident = record["identity"]
            how.append(f"- **{env}, {sweep}**: {len(ident['seeds'])} seeds x {len(ident['conditions'])} "
                       f"conditions, {_share(env, budget)} env steps per run; "
                       f"`{' '.join(record['command'])}`{_progress(name, record, budget)}")  # fmt: skip
    if not how:
        names = ", ".join(f"{env}-{s}" for env in ENVS for s in TEACH_SWEEPS)
        return f"Not published yet: {names}."
    return "\n".join(["### The couplings against none", "", *out, "", "### How they were run", "", *how])


BASE_BEGIN = "<!-- baselines: begin (benchmarks/results_table.py) -->"
BASE_END = "<!-- baselines: end -->"
PLAIN = ("none", "none-sac")
"""The plain learners of Amendment 8: PPO and SAC alone."""


def _per_run(name: str, metric: str) -> dict[str, tuple[float, ...]]:
    """One measure of a published sweep per run, per condition, from its ``metrics.csv``.

    An empty cell (a target never reached) reads +inf.
    """
    runs: dict[str, list[float]] = {}
    with open(RESULTS / name / "metrics.csv", newline="") as fh:
        for r in csv.DictReader(fh):
            text = r[metric]
            runs.setdefault(r["condition"], []).append(float(text) if text not in ("", "nan") else math.inf)
    return {c: tuple(v) for c, v in runs.items()}


def _learners(name: str) -> list[PlainLearner]:
    """The plain learners of a published sweep, per run from its ``metrics.csv``."""
    steps, scores = _per_run(name, "env_steps_to_alone_target"), _per_run(name, "final_score")
    return [PlainLearner(c, steps[c], scores[c]) for c in PLAIN if c in steps]


def _median_text(values: tuple[float, ...]) -> str:
    m = statistics.median(values)
    return "not reached" if math.isinf(m) else f"{m:,.0f}"


def _plain_row(
    env: str, x: PlainLearner, rows: dict[tuple[str, str], dict[str, str]], best: bool, verdict: str,
    progress: str = "",
) -> str:
    def cell(metric: str, to_target: bool = False) -> str:
        return _cell(rows.get((x.condition, metric)), to_target)

    sac = x.condition == "none-sac"
    cells = [env, "none-sac (SAC)" if sac else "none (PPO)", _median_text(x.steps_to_target),
             cell("env_steps_to_alone_target", True), cell("falls"), cell("final_score"),
             cell("wall_s_to_alone_target"), progress or ("**yes**" if best else ""),
             verdict if sac and not progress else "-"]  # fmt: skip
    return "| " + " | ".join(cells) + " |"


def _sac_missing(env: str) -> str:
    """Why ``env`` has no plain SAC sweep: the amendment that governs it, or none."""
    governs = [a.number for a in AMENDMENT_LIST if "none-sac" in a.conditions and env in a.envs]
    return f"not run yet (Amendment {governs[0]})" if governs else "not run (no amendment governs it)"


def _unfinished(env: str, name: str, record: dict) -> str:
    """A published sweep's "in progress: k of n runs finished", or "" once all its runs are in."""
    return _progress(name, record, _budget(env, name, record)).strip("; *")


def baselines() -> str:
    """Each env's best plain baseline by Amendment 8's rule, with the numbers it was read from."""
    head = ["env", "plain learner", "median env steps to the agent-alone target (rule)",
            "env steps to the target, IQM (reached)", "falls during training", "final agent-alone score",
            "wall time to the target (s)", "best plain baseline",
            "SAC against PPO on env steps (Holm)"]  # fmt: skip
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for env in ENVS:
        loaded = _load(f"{env}-sac")
        if loaded is None:
            why = _sac_missing(env)
            out.append(f"| {env} | none (PPO) | - | - | - | - | - | none (PPO): plain SAC {why} | - |")
            continue
        rows, record = loaded
        learners = _learners(f"{env}-sac")
        # a sweep split over sessions names no baseline until all its runs are in
        progress = _unfinished(env, f"{env}-sac", record)
        best = None if progress else best_plain_baseline(learners)
        test = rows.get(("none-sac", "env_steps_to_alone_target"))
        verdict = "-" if test is None else f"{test['verdict']} (Holm {p_text(float(test['p_holm']))})"
        out += [_plain_row(env, x, rows, x is best, verdict, progress) for x in learners]
    return "\n".join(out)


BEST_BEGIN = "<!-- against the best: begin (benchmarks/results_table.py) -->"
BEST_END = "<!-- against the best: end -->"
BEST_REPS = 10000
"""Bootstrap resamples of each saving against the best plain baseline (seed 0, as the sweeps' own)."""


def named_baseline(env: str) -> tuple[str, str] | str:
    """``(sweep folder, condition)`` of ``env``'s best plain baseline, or why none is named yet.

    Amendment 8's rule reads it from the env's ``ENV-sac`` sweep once all its runs are in.
    """
    name = f"{env}-sac"
    loaded = _load(name)
    if loaded is None:
        return f"not named: plain SAC {_sac_missing(env)}"
    progress = _unfinished(env, name, loaded[1])
    if progress:
        return f"not named: its sweep is {progress}"
    return name, best_plain_baseline(_learners(name)).condition


def _against(x: tuple[float, ...], y: tuple[float, ...], threshold: float) -> tuple[str, str]:
    """The saving of the median of ``x`` against ``y`` with its interval, and the aim's word."""
    e = median_saving(x, y, reps=BEST_REPS)
    return (f"saving {saving_text(e)}", "undecided") if e.value != e.value else _aim(e, threshold)


def _best_rows(env: str, base: tuple[str, str]) -> list[str]:
    """Every published coupling of ``env`` against its best plain baseline's runs."""
    folder, learner = base
    y = {m: _per_run(folder, m)[learner] for m in AIM}
    label = f"{learner} ({'SAC' if learner == 'none-sac' else 'PPO'}, {len(y['falls'])} runs)"
    loaded_base = _load(folder)
    if loaded_base is None:  # named_baseline read it; nothing to read against once it is gone
        return []
    budget = _budget(env, folder, loaded_base[1])
    out, seen = [], set()
    for sweep in TEACH_SWEEPS:
        name = f"{env}-{sweep}"
        loaded = _load(name)
        if loaded is None or _unfinished(env, name, loaded[1]):
            continue
        other = _budget(env, name, loaded[1])
        if other != budget:  # falls and env steps to a kept target depend on the budget
            why = f"not compared: its runs' budget is {other:,} env steps, the baseline's {budget:,}"
            out.append(f"| {env} | {label} | {sweep} | all | {why} | - | - |")
            continue
        x = {m: _per_run(name, m) for m in AIM}
        seeds = tuple(loaded[1]["identity"]["seeds"])
        for c in loaded[1]["identity"]["conditions"]:
            # a condition's runs copied into a later sweep (Amendment 6) are shown once, where first run
            if c in PLAIN or c not in x["falls"] or (c, seeds) in seen:
                continue
            seen.add((c, seeds))
            cells = [_against(x[m][c], y[m], t) for m, t in AIM.items()]
            words = [w for _, w in cells]
            both = "missed" if "missed" in words else "met" if set(words) == {"met"} else "undecided"
            out.append(f"| {env} | {label} | {sweep} | {c} | {cells[0][0]} | {cells[1][0]} | **{both}** |")
    return out


def against_best() -> str:
    """Every published coupling against its env's best plain baseline: the savings and issue 37's aim."""
    head = ["env", "best plain baseline (runs)", "sweep", "condition",
            "fewer falls than the best plain baseline (aim)",
            "fewer env steps to the agent-alone target (aim)", "both aims"]  # fmt: skip
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for env in ENVS:
        base = named_baseline(env)
        if isinstance(base, str):
            out.append(f"| {env} | {base} | - | - | - | - | - |")
            continue
        out += _best_rows(env, base)
    return "\n".join(out)


def main() -> None:
    """Replace the marked blocks of docs/results/README.md."""
    readme = RESULTS / "README.md"
    text = readme.read_text()
    for begin, end, body in [(b.begin, b.end, tables(b)) for b in BLOCKS] + [
        (TEACH_BEGIN, TEACH_END, teaching_tables()),
        (BASE_BEGIN, BASE_END, baselines()),
        (BEST_BEGIN, BEST_END, against_best()),
    ]:
        a, b = text.index(begin) + len(begin), text.index(end)
        text = text[:a] + "\n\n" + body + "\n\n" + text[b:]
        print(body, end="\n\n")
    atomic_write_text(readme, text)


if __name__ == "__main__":
    run(main)
