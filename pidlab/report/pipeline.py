"""The report of ``pidlab run``: what each stage of the pipeline found, on one page (Markdown).

Pure functions: :func:`tune_summary` and :func:`roa_summary` turn results into the JSON the
pipeline keeps between runs; :func:`render_markdown` turns :class:`PipelineFacts` into the
report. Writing files is :mod:`pidlab.pipeline`'s job.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from pidlab.controller.analysis import MARGIN_COLUMNS, CoachAnalysis, margin_table
from pidlab.controller.rollout import CoachScore
from pidlab.controller.spec import CoachSpec
from pidlab.experiment.analysis import BASELINE, Analysis
from pidlab.experiment.stats import Estimate
from pidlab.linear.lti import LtiReport
from pidlab.report.experiment import (
    budget_share,
    cell_metric,
    design_note,
    markdown_table,
    p_text,
    reading,
    report_header,
    saving_text,
)
from pidlab.rl.recipe import PipelineSettings


@dataclass(frozen=True)
class PipelineFacts:
    """Everything the report shows (figure paths relative to the report)."""

    env_id: str
    settings: PipelineSettings
    record: dict[str, Any]
    coaching: dict[str, Any]
    lti: LtiReport
    control_dt: float
    tuning: dict[str, Any]
    spec: CoachSpec
    analysis: CoachAnalysis
    score: CoachScore | None
    roa: dict[str, Any]
    units: dict[str, str]
    results: Analysis
    figures: tuple[str, ...]
    roa_figure: str
    curves_figure: str | None
    evidence: Evidence | None = None


EVIDENCE_METRICS = ("falls", "env_steps_to_alone_target", "final_score")
"""What the choice of the coached condition rests on: falls during training, env steps until the
agent alone reaches the target, and its final score."""


@dataclass(frozen=True)
class Evidence:
    """A published experiment's rows (its ``summary.csv``) for ``none`` and the pipeline's condition.

    Attributes
    ----------
    folder : str
        The experiment's folder, as the report links it.
    rows : dict
        ``(condition, metric) -> summary.csv row`` for :data:`EVIDENCE_METRICS`.
    """

    folder: str
    rows: dict[tuple[str, str], dict[str, str]]


def tune_summary(result: Any) -> dict[str, Any]:
    """What the auto-tuner was asked and achieved, as JSON.

    ``result`` is a :class:`pidlab.controller.autotune.TuneResult`.
    """
    return {
        "preset": result.preset,
        "asked_bandwidth_rad_s": result.asked_bandwidth,
        "achieved_bandwidth_rad_s": result.achieved_bandwidth,
        "asked_phase_margin_deg": result.asked_phase_margin,
        "achieved_phase_margin_deg": result.achieved_phase_margin,
        "achieved_ms": result.achieved_ms,
        "spectral_radius": result.spectral_radius,
        "evaluations": result.evaluations,
        "refined_return": result.refined_return,
    }


def roa_summary(region: Any, bounds: Any, pair: tuple[str, str]) -> dict[str, Any]:
    """A certified region (:class:`pidlab.region.roa.RegionOfAttraction`) and its bounds, as JSON."""
    check = region.check
    return {
        "method": region.method,
        "level": region.level,
        "c_optimization": region.c_optimization,
        "c_simulation": region.c_simulation,
        "variables": list(region.lyapunov.variables) if region.lyapunov is not None else [],
        "check": {
            "samples": check.samples,
            "failures": check.failures,
            "terminated": check.terminated,
            "not_converged": check.not_converged,
            "horizon_s": check.horizon_s,
            "seed": check.seed,
            "failure_bound_95": check.failure_bound_95,
        },
        "elapsed_s": region.elapsed_s,
        "recoverable_box": {k: float(v) for k, v in region.box.items()},
        "bounds": {
            "method": bounds.method,
            "rho": bounds.rho,
            "box": {k: [float(lo), float(hi)] for k, (lo, hi) in bounds.box.items()},
            "one_step_check": list(bounds.one_step_check),
            "one_step_action_fraction": float(bounds.provenance.get("one_step_action_fraction", 1.0)),
        },
        "slice": list(pair),
    }


def rescue_summary(region: Any) -> dict[str, Any]:
    """A rescue region (:class:`pidlab.region.rescue.RescueRegion`) as JSON: its grid, checks and coverage."""
    g, cov = region.grid, region.coverage
    return {
        "variables": list(g.variables),
        "lower": [float(v) for v in g.lower],
        "upper": [float(v) for v in g.upper],
        "cells": list(g.cells),
        "guard": {k: [float(lo), float(hi)] for k, (lo, hi) in g.guard.items()},
        "trigger": g.trigger,
        "fraction_marked": g.fraction_marked(),
        "validation": {"samples": region.validation[0], "failures": region.validation[1],
                       "rounds": region.rounds, "failure_bound_95": region.failure_bound_95},
        "coverage": {"rescuable": cov.rescuable, "samples": cov.samples,
                     **{k: cov.fraction(k) for k in cov.contained}},
        "elapsed_s": region.elapsed_s,
        "horizon_s": region.settings.horizon_s,
        "reused": region.reused,
    }  # fmt: skip


def _analysed_at(analysis: Any) -> str:
    """Where the analysis linearized the plant, when not at the model card's operating point."""
    op = analysis.linearization.op
    return "" if op.source.startswith("card") else f"; the plant linearized at {op.source}"


def _rescued_meaning(r: dict[str, Any]) -> str:
    """What a rescue is for this coach: into its certified core, or (certified by simulation) held."""
    if "core" in r["coverage"]:
        return (
            "the states from which the coach brings the system into its certified core without a termination"
        )
    horizon = f" {_num(r['horizon_s'], 'g')} s" if r.get("horizon_s") is not None else ""
    return (
        f"the states from which the coach holds the system{horizon} without a termination (a coach "
        "certified by simulation has no Lyapunov core to enter)"
    )


def _held_shares(cov: dict[str, Any]) -> str:
    """``the rescue region holds 96.7 % of them, the critical box 53.3 %``: the regions measured."""
    names = {"rescue": "the rescue region", "core": "the certified core", "takeover box": "the critical box"}
    shares = [(label, f"{100 * cov[key]:.1f} %") for key, label in names.items() if key in cov]
    if not shares:
        return "no region is measured against them"
    (label, share), rest = shares[0], shares[1:]
    return ", ".join([f"{label} holds {share} of them", *(f"{lab} {sh}" for lab, sh in rest)])


def _num(x: float | None, fmt: str = ".4g") -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return format(x, fmt)


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


def _eig(value: complex) -> str:
    if abs(value.imag) < 1e-9:
        return f"{value.real:.4g}"
    return f"{value.real:.4g} {'+' if value.imag >= 0 else '-'} {abs(value.imag):.4g}j"


def _header(f: PipelineFacts) -> list[str]:
    s = f.settings
    settings = (
        f"Settings (the recipe's `[pipeline]` table and the command's overrides): {_count(s.seeds, 'seed')} "
        f"per condition, {s.steps:,} env steps per run, preset {s.preset}, {s.roa_samples} simulated states "
        f"certifying the region, {_count(s.episodes, 'coach-alone episode')}; coached runs intervene as the "
        f"condition `{s.condition}` of coach/conditions.toml."
    )
    lines = report_header(
        f"pidlab run: {f.env_id}", f.record, notes=[settings], default_command=f"pidlab run {f.env_id}"
    )
    stages = f.record.get("stages", {})
    if stages:
        rows = [[name, f"{v['seconds']:.1f}"] for name, v in stages.items()]
        lines += [markdown_table(["stage", "time of its last run (s)"], rows), ""]
    return lines


def _linear_model(f: PipelineFacts) -> list[str]:
    r = f.lti
    unstable = [m for m in r.modes if m.unstable]
    lines = [
        "## 1. The linear model",
        "",
        f"{r.n} states, linearized at the model card's operating point; the coach runs every "
        f"{1000 * f.control_dt:.4g} ms (the env's control period). "
        f"{_count(len(unstable), 'unstable open-loop eigenvalue')}"
        + (": " + ", ".join(f"{_eig(m.value)} rad/s" for m in unstable) if unstable else "")
        + f". Controllable subspace: {r.controllable_dim} of {r.n}; "
        f"{'stabilizable' if r.stabilizable else 'NOT stabilizable'}.",
        "",
        "Full tables: `linearization.json` beside this report (or `pidlab linearize " + f.env_id + "`).",
        "",
    ]
    return lines


def _coach(f: PipelineFacts) -> list[str]:
    t = f.tuning
    rows = []
    for lp in f.spec.loops:
        acts = ", ".join(f"{a} ({w:+g})" for a, w in lp.actuators)
        rows.append(
            [lp.name, lp.signal, lp.rate_signal or "-", acts, _num(lp.kp), _num(lp.ki), _num(lp.kd),
             _num(lp.setpoint)]
        )  # fmt: skip
    lines = [
        f"## 2. The coach (auto-tuned, preset {t['preset']})",
        "",
        markdown_table(
            ["loop", "signal", "rate signal", "actuator (weight)", "Kp", "Ki (1/s)", "Kd (s)", "setpoint"],
            rows,
        ),
        "",
        f"Asked: gain crossover {_num(t['asked_bandwidth_rad_s'])} rad/s, phase margin "
        f"{_num(t['asked_phase_margin_deg'], '.1f')} deg. The tuner's own figures: crossover "
        f"{_num(t['achieved_bandwidth_rad_s'])} rad/s, phase margin "
        f"{_num(t['achieved_phase_margin_deg'], '.1f')} deg, Ms {_num(t['achieved_ms'], '.3g')}, "
        "closed-loop spectral radius "
        f"{_num(t['spectral_radius'], '.5f')}, {t['evaluations']} evaluations"
        + (
            f", mean return {t['refined_return']:.1f} on the real env after refinement"
            if t.get("refined_return") is not None
            else ""
        )
        + ".",
        "",
        "### Stability margins",
        "",
        "The discrete loop (what runs), broken at each actuator in turn, the other loops closed"
        + _analysed_at(f.analysis)
        + ".",
        "",
    ]
    formats = {"gm_db": ".2f", "lower_gm_db": ".2f", "pm_deg": ".1f", "delay_ms": ".1f", "disk_alpha": ".3f",
               "disk_gm_db": ".2f", "disk_pm_deg": ".1f", "ms_db": ".2f"}  # fmt: skip
    mrows = [
        [row["actuator"], *(_num(row[key], formats.get(key, ".4g")) for key, _ in MARGIN_COLUMNS[1:])]
        for row in margin_table(f.analysis.discrete.margins)
    ]
    lines += [markdown_table([label for _, label in MARGIN_COLUMNS], mrows)]
    poles = f.analysis.discrete.poles
    radius = max(abs(p.value) for p in poles) if poles else float("nan")
    damp = [p.damping for p in poles if not np.isnan(p.damping)]
    lines += [
        "",
        f"Closed loop: {'stable' if f.analysis.stable else 'UNSTABLE'}, {len(poles)} poles, largest |z| "
        f"{radius:.5f}, smallest damping ratio {min(damp):.3f}."
        if damp
        else "",
        "",
    ]
    for fig in f.figures:
        kind, _, actuator = fig.rsplit("/", 1)[-1].removesuffix(".png").partition("_")
        lines += [f"![{kind}{f', loop broken at {actuator}' if actuator else ''}]({fig})", ""]
    if f.score is not None:
        sc = f.score
        causes = ", ".join(f"{n} {c}" for c, n in sorted(sc.causes.items()))
        n = len(sc.episodes)
        episodes = f"{_count(n, 'seeded episode')}, " + (f"seeds 0-{n - 1}" if n > 1 else "seed 0")
        lines += [
            "### The coach alone on the real env",
            "",
            f"Return {sc.mean:.1f} +- {sc.std:.1f} (mean +- std over {episodes}); "
            f"mean length {sc.mean_length:.0f} steps; how they ended: {causes}.",
            "",
        ]
    return lines


def _region(f: PipelineFacts) -> list[str]:
    r = f.roa
    c = r["check"]
    b = r["bounds"]
    check = (
        f"Simulation check in MuJoCo: {c['samples']} sampled initial states, {c['horizon_s']:g} s each, "
        f"{c['failures']} failed ({c['terminated']} terminated, {c['not_converged']} did not converge); "
        f"with no failure, the failure probability over the set is below {100 * c['failure_bound_95']:.2g} % "
        "at 95 % confidence (rule of three). A statistical statement about sampled states, not a proof."
    )
    one_step = (
        f"one-step check in MuJoCo: {b['one_step_check'][0]} boundary states, "
        f"{b['one_step_check'][1]} not recovered"
    )
    fraction = float(b.get("one_step_action_fraction", 1.0))
    step = "one agent step from its edge is still recovered"
    if fraction < 1.0:
        step += (
            f" for agent actions up to {100 * fraction:.0f} % of the action range (a full-range step "
            "is more than this coach recovers from)"
        )
    lines = ["## 3. Region of attraction and critical-state bounds", "", f"Method: {r['method']}.", ""]
    if r["variables"]:
        lines += [
            f"Certified level c = {_num(r['level'])} of V = x' P x"
            + (
                f" (CasADi's estimate {_num(r['c_optimization'])})"
                if r.get("c_optimization") is not None
                else ""
            )
            + f". {check}",
            "",
            f"Critical-state bounds: the takeover ellipsoid is V <= rho c with rho = {_num(b['rho'])}, "
            + f"sized so that {step} ({one_step}).",
        ]
    else:
        half = ", ".join(
            f"{k} +-{_num(v)} {f.units.get(k, '')}".rstrip() for k, v in r.get("recoverable_box", {}).items()
        )
        lines += [
            "Recoverable box about the operating point (contacts: no Lyapunov argument)"
            + (f": {half}" if half else "")
            + f". {check}",
            "",
            f"Critical-state bounds: that box scaled by {_num(b['rho'])}, so that {step} ({one_step}).",
        ]
    lines += [
        "",
        f"The critical box (this run's coaching rule: mode {f.coaching.get('mode')}, region "
        f"{f.coaching.get('region')}; "
        + (
            "the coach takes over when the state leaves this box). "
            if f.coaching.get("region") == "box"
            else "not the takeover region of this run). "
        )
        + "It is the largest box inside the projection of the takeover set on these variables; it does "
        "not constrain the others, so in the slice below it can reach beyond the drawn ellipse:",
        "",
    ]
    rows = [[k, f.units.get(k, ""), _num(lo), _num(hi)] for k, (lo, hi) in b["box"].items()]
    lines += [markdown_table(["variable", "unit", "low", "high"], rows), ""]
    lines += [f"![Region of attraction, the slice through {' and '.join(r['slice'])}]({f.roa_figure})", ""]
    if "rescue" in r:
        lines += _rescue(f, r["rescue"])
    return lines


def _rescue(f: PipelineFacts, r: dict[str, Any]) -> list[str]:
    """The rescue region's paragraph and figure (section 3)."""
    cov, val = r["coverage"], r["validation"]
    grid = (
        " x ".join(str(c) for c in r["cells"])
        + " cells over "
        + ", ".join(
            f"{v} {_num(lo)}..{_num(hi)} {f.units.get(v, '')}".rstrip()
            for v, lo, hi in zip(r["variables"], r["lower"], r["upper"], strict=True)
        )
    )
    guard = "; guard " + ", ".join(f"{k} {_num(lo)}..{_num(hi)}" for k, (lo, hi) in r["guard"].items())
    return [
        "### Rescue region: the takeover region",
        "",
        "This run's coach takes over outside its **rescue region** "
        f"(`pidlab rescue`, {r['trigger']} trigger): {_rescued_meaning(r)}, "
        f"found by simulation in MuJoCo on a lookup grid ({grid}{guard if r['guard'] else ''}); "
        f"{100 * r['fraction_marked']:.1f} % of the cells are marked. Validation: {val['samples']:,} fresh "
        f"states drawn inside it, {val['failures']} failed (after {_count(val['rounds'], 'draw')}; failure "
        f"rate below {100 * val['failure_bound_95']:.2g} % at 95 % confidence). Coverage: of "
        f"{cov['samples']:,} fresh states over the grid's domain, {cov['rescuable']:,} are rescuable; "
        + _held_shares(cov)
        + ".",
        "",
        "![The rescue region, the certified core and the box](figures/rescue.png)",
        "",
    ]


def _teaching_text(c: dict[str, Any]) -> str:
    """What the coach teaches before and during the coached runs (empty when it only shields)."""
    demos, warm = c.get("demonstrations"), c.get("warm_start")
    if not isinstance(demos, dict):
        return ""
    text = (f" First the coach demonstrates for {int(demos.get('steps', 0)):,} env steps of the budget, with "
            f"noise of {float(demos.get('noise', 0.1)):g} of half the actuator range")  # fmt: skip
    if isinstance(warm, dict):
        text += ", and the agent is behaviour-cloned on its demonstrations"
        keep = warm.get("keep")
        if isinstance(keep, dict):
            text += f", which stay in its updates {_keep_text(keep)}"
    return text + "."


def _keep_text(keep: dict[str, Any]) -> str:
    """The weight of the demonstrations in the agent's updates, as the schedule says."""
    start = float(keep.get("start", 1.0))
    end = float(keep.get("end", start))
    if keep.get("shape") == "constant" or start == end:
        return f"at a weight held at {start:g} for the whole budget (the demonstrations held)"
    if end == 0.0:
        return f"with a weight that fades from {start:g} to 0 (the demonstrations kept)"
    return f"with a weight that goes from {start:g} to {end:g} (the demonstrations kept)"


def _training(f: PipelineFacts) -> list[str]:
    a = f.results
    env = f.env_id
    budget = a.budgets.get(env, f.settings.steps)
    c = f.coaching
    rule = f"mode {c.get('mode')}, region {c.get('region')}"
    if c.get("region") == "rescue":
        rule += f", trigger {c.get('trigger', 'exit')}, hand-back {c.get('handback', 1.0)}"
    view = c.get("view", "hidden")
    seen = {
        "hidden": "its steps are hidden from the agent",
        "penalty": "its steps are hidden from the agent, and the agent's transition that triggered it pays "
        f"a cost of {c.get('cost', 'ten alive rewards')}",
        "terminal": "a takeover ends the agent's episode as a failure; the env runs on under the coach "
        "and the agent's next episode starts from the rescued state",
    }.get(view, view)
    recipe = f.record.get("recipe", f"coach/{env}.toml")
    how = (f"intervenes as the condition `{f.settings.condition}` of coach/conditions.toml says ({rule}, "
           f"view {view}): {seen}.")  # fmt: skip
    if c.get("off_after") == 0.0:  # the coach teaches only: no intervention in the agent's steps
        how = (f"coaches as the condition `{f.settings.condition}` of coach/conditions.toml says: it never "
               "intervenes in the agent's steps.")  # fmt: skip
    lines = [
        "## 4. Training with and without the coach",
        "",
        f"The recipe's agent ({recipe}), {_count(f.settings.seeds, 'seed')} per condition, "
        f"{budget:,} env steps per run (agent and coach steps both count; "
        f"{budget_share(a, env) or 'no shipped recipe'}). "
        f"`coached`: the coach above {how}{_teaching_text(c)} "
        f"Target {a.targets.get(env, 0):g}.",
        "",
    ]
    if a.missing:
        lines += [f"Not finished (not counted): {', '.join(a.missing)}.", ""]
    if f.curves_figure:
        lines += [f"![Learning curves]({f.curves_figure})", ""]
    lines += agent_alone(a, env)
    lines += [
        "The full experiment report, with the paper's measures beside its Table II: "
        "[experiment/report.html](experiment/report.html) ([Markdown](experiment/report.md)).",
        "",
    ]
    return lines


AGENT_ALONE = "### The agent alone"


def agent_alone(a: Analysis, env: str) -> list[str]:
    """Section 4's table of the agent alone, its design note and reading (Markdown lines).

    A pure function of the experiment's analysis, so that ``benchmarks/recompute.py`` can recompute
    it from the published runs' logs and compare it with the committed report.
    """
    lines = [
        AGENT_ALONE,
        "",
        "Deterministic policy, coach off, fixed evaluation seeds. IQM over seeds with its 95 % "
        "stratified bootstrap interval; P: probability of improvement over no coach (0.5: no difference), "
        "with its 95 % score interval, the exact two-sided Wilcoxon-Mann-Whitney p-value and its Holm "
        "adjustment over the primary family (docs/analysis-plan.md).",
        "",
    ]
    rows = []
    for cond in a.conditions:
        cell = a.cells.get((env, cond))
        if cell is None:
            continue
        per_seed = ", ".join(f"{r.metrics.final_score:.0f}" for r in cell.runs)
        c = a.comparisons.get((env, cond), {}).get("final_score")
        if cond == a.baseline or c is None:
            p, exact, holm = "-", "-", "-"
        else:
            e = c.improvement
            p, exact = f"{e.value:.2f} [{e.low:.2f}, {e.high:.2f}]", p_text(c.test.p_value)
            holm = "-" if c.p_holm is None else p_text(c.p_holm)
        rows.append(
            [cond, cell_metric(cell, "final_score"), per_seed, cell_metric(cell, "env_steps_to_alone_target"),
             cell_metric(cell, "intervention_rate"), cell_metric(cell, "falls"),
             f"{cell.coach_dependent}/{len(cell.runs)}", p, exact, holm]
        )  # fmt: skip
    lines += [
        markdown_table(
            [
                "condition",
                "final agent-alone score",
                "per seed",
                "env steps to target, reached and kept (agent alone)",
                "coach's share of env steps",
                "falls during training",
                "coach-dependent",
                "P(higher final score)",
                "exact p",
                "Holm p",
            ],
            rows,
        ),
        "",
        design_note(a, env),
        "",
        *(f"- {s}" for s in reading(a, env, "primary")),
        "",
    ]
    return lines


def _estimate(row: dict[str, str] | None) -> str:
    """A summary.csv row as ``IQM [low, high] (reached/runs)``."""
    if row is None:
        return "-"
    if not row["iqm"]:
        return f"not reached ({row['reached']}/{row['runs']})"
    text = f"{float(row['iqm']):,.1f} [{float(row['ci_low']):,.1f}, {float(row['ci_high']):,.1f}]"
    counted = row["metric"] == "env_steps_to_alone_target"
    return text + (f" ({row['reached']}/{row['runs']})" if counted else "")


EVIDENCE_HEADING = "## 5. Why this coaching"


def evidence_section(f: PipelineFacts) -> list[str]:
    """Why the coached runs intervene as they do: the published experiment behind the choice."""
    return evidence_lines(f.env_id, f.settings.condition, f.evidence)


def evidence_lines(env_id: str, cond: str, ev: Evidence | None) -> list[str]:
    """Section 5 of a pipeline report from the published experiment ``ev`` (Markdown lines).

    A pure function of the published summary, so that ``benchmarks/recompute.py`` can check it.
    """
    head = [EVIDENCE_HEADING, ""]
    if ev is None:
        return [
            *head,
            f"No published experiment in docs/results compares the condition `{cond}` with `none` on "
            f"{env_id}: the choice is the recipe's, not the evidence's.",
            "",
        ]
    rows = [[c] + [_estimate(ev.rows.get((c, m))) for m in EVIDENCE_METRICS] for c in (BASELINE, cond)]
    header = ["condition", "falls during training", "env steps to target (agent alone)",
              "final agent-alone score"]  # fmt: skip
    return [
        *head,
        f"The coached runs intervene as the condition `{cond}` (the recipe's `[pipeline]` table). The "
        f"published experiment `{ev.folder}` (in pidlab's source tree) measured it against `none` on "
        f"{env_id} (IQM over its seeds with 95 % intervals):",
        "",
        markdown_table(header, rows),
        "",
        evidence_reading(ev, cond),
        "",
    ]


def evidence_reading(ev: Evidence, cond: str) -> str:
    """One plain sentence: what ``cond`` beat ``none`` on there, and what the coach bought."""
    names = {"falls": "falls during training", "env_steps_to_alone_target": "env steps until the agent alone "
             "keeps the target", "final_score": "the final agent-alone score"}  # fmt: skip

    def verdict(m: str) -> str:
        return ev.rows.get((cond, m), {}).get("verdict", "") or "not tested"

    alone = ("env_steps_to_alone_target", "final_score")
    better = [names[m] for m in alone if verdict(m) == "better"]
    worse = [names[m] for m in alone if verdict(m) == "worse"]
    if better:
        text = f"It beats `none` on {' and '.join(better)}"
    else:
        text = "Nothing beats `none` on the agent-alone measures there"
    text += " (" + "; ".join(f"{names[m]}: {verdict(m)}" for m in alone) + ")"
    if worse:
        text += f", and it is worse on {' and '.join(worse)}"
    falls = ev.rows.get((cond, "falls"))
    base = ev.rows.get((BASELINE, "falls"))
    if falls is not None and base is not None and verdict("falls") == "better":
        text += (
            f". What the coach buys: fewer falls during training, IQM {float(falls['iqm']):,.1f} against "
            f"{float(base['iqm']):,.1f} without a coach (Holm p = {p_text(float(falls['p_holm']))})"
        )
    else:
        text += f". Falls during training: {verdict('falls')}"
    savings = [f"{label} {saving_text(s)}" for label, s in _savings(ev, cond)]
    if savings:
        text += ". Savings of the median against `none` (95 % intervals): " + "; ".join(savings)
    return text + "."


def _savings(ev: Evidence, cond: str) -> list[tuple[str, Estimate]]:
    """The published savings of ``cond`` on falls and on env steps to the target, where recorded."""
    out = []
    for metric, label in (("falls", "falls"), ("env_steps_to_alone_target", "env steps to the target")):
        row = ev.rows.get((cond, metric), {})
        if row.get("saving", ""):
            values = [float(row[k]) if row[k] not in ("", "inf") else math.inf
                      for k in ("saving", "saving_low", "saving_high")]  # fmt: skip
            out.append((label, Estimate(*values)))
    return out


def render_markdown(f: PipelineFacts) -> str:
    """The pipeline's report as Markdown."""
    lines = _header(f) + _linear_model(f) + _coach(f) + _region(f) + _training(f) + evidence_section(f)
    return "\n".join(lines).rstrip() + "\n"
