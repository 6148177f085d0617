"""Text and JSON presentation of results (the CLI's output layer; no computation here)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from rich.console import Console, Group
from rich.table import Table
from rich.text import Text

from pidlab.experiment.progress import RUN_STATES, RunProgress
from pidlab.linear.linearize import Linearization
from pidlab.linear.lti import LtiReport


def _fmt(x: float) -> str:
    if x == 0:
        return "0"
    return f"{x:.4g}"


MAX_TABLE_SIDE = 100
"""The most rows or columns :func:`matrix_table` shows; a larger matrix is named, not printed."""


def matrix_table(title: str, M: np.ndarray, rows: Sequence[str], cols: Sequence[str]) -> Table:
    """A named matrix as a table: one row per ``rows`` name, one column per ``cols`` name.

    A matrix with more than :data:`MAX_TABLE_SIDE` rows or columns is too wide to read on a
    terminal: the table says its size and where to get it (``--json``) instead.
    """
    table = Table(title=title, title_justify="left", min_width=len(title) + 4)
    if max(len(rows), len(cols)) > MAX_TABLE_SIDE:
        table.add_column("not shown")
        table.add_row(
            f"{len(rows)} x {len(cols)}: more than {MAX_TABLE_SIDE} rows or columns; "
            "pidlab linearize --json prints every entry"
        )
        return table
    table.add_column("", style="bold", no_wrap=True)
    for c in cols:
        table.add_column(c, justify="right", no_wrap=True)
    for name, row in zip(rows, M, strict=True):
        table.add_row(name, *(_fmt(float(v)) for v in row))
    return table


def modes_table(report: LtiReport, title: str) -> Table:
    """Eigenvalues with stability marked, damping, natural frequency and PBH results."""
    table = Table(title=title, title_justify="left", min_width=len(title) + 4)
    table.add_column("#", justify="right")
    if report.discrete:
        table.add_column("z", justify="right")
        table.add_column("|z|", justify="right")
        table.add_column("s = ln(z)/dt (rad/s)", justify="right")
    else:
        table.add_column("eigenvalue (rad/s)", justify="right")
        table.add_column("|λ| (rad/s)", justify="right")
        table.add_column("damping", justify="right")
    table.add_column("stability")
    table.add_column("controllable")
    table.add_column("observable")
    for i, m in enumerate(report.modes):
        v = m.value
        val = f"{v.real:.5g}" + (
            f" {'+' if v.imag >= 0 else '-'} {abs(v.imag):.5g}j" if abs(v.imag) > 0 else ""
        )
        if report.discrete:
            s = np.log(v + 0j) / report.dt if abs(v) > 0 else complex("-inf")
            extra = [f"{abs(v):.6g}", f"{s.real:.4g}" + (f" ± {abs(s.imag):.4g}j" if abs(s.imag) > 0 else "")]
        else:
            extra = [f"{abs(v):.5g}", "" if not np.isfinite(m.damping) else f"{m.damping:.3f}"]
        status = (
            Text("UNSTABLE", style="bold red")
            if m.unstable
            else (Text("marginal", style="yellow") if m.marginal else Text("stable", style="green"))
        )
        table.add_row(
            str(i),
            val,
            *extra,
            status,
            "yes" if m.controllable else Text(f"NO ({m.ctrb_margin:.1e})", style="red"),
            "yes" if m.observable else Text(f"NO ({m.obsv_margin:.1e})", style="red"),
        )
    return table


def _linearization_head(lin: Linearization) -> Text:
    """Where the model was linearized and how, with warnings where the linear model is fragile."""
    op = lin.op
    head = Text()
    head.append(f"{lin.source}", style="bold")
    head.append(
        f"  integrator {lin.integrator}, timestep {lin.timestep:g} s, frame_skip {lin.frame_skip}, "
        f"control period {lin.control_dt:g} s\n"
    )
    head.append(f"operating point: {op.source}; ctrl: {op.ctrl_source}\n")
    for name in ("qpos", "qvel", "ctrl"):
        head.append(f"  {name} = {np.array2string(getattr(op, name), precision=6, separator=', ')}\n")
    if op.equilibrium is not None:
        eq = op.equilibrium
        head.append(
            f"  inverse-dynamics residual (force the actuators cannot supply): {eq.residual_norm:.3g}\n"
        )
        if eq.saturated:
            head.append(f"  clamped to ctrlrange: {', '.join(eq.saturated)}\n", style="yellow")
    how = (
        "finite differences of mj_step x frame_skip"
        if lin.discretization == "step"
        else "zero-order hold of the continuous model"
    )
    head.append(f"method: {lin.method}; discrete model: {how}\n")
    eq_err = lin.equilibrium_error
    if eq_err <= 1e-6:
        head.append(f"max |f(x0, u0)| = {eq_err:.3g} (an equilibrium)\n")
    else:
        head.append(
            f"max |f(x0, u0)| = {eq_err:.3g} (NOT an equilibrium: the model drifts from this point)\n",
            style="yellow",
        )
    if lin.ncon or lin.nefc:
        head.append(
            f"active contacts {lin.ncon}, constraint rows {lin.nefc}: "
            "the model holds while the contact set does not change\n",
            style="yellow",
        )
    if lin.kink > 1e-3:
        head.append(
            f"one-sided derivatives differ by {lin.kink:.2g} (relative): "
            "the dynamics have a kink here; A is the average of both sides\n",
            style="yellow",
        )
    return head


def _lti_summary(report: LtiReport) -> Text:
    """Unstable modes, controllability and observability in three lines."""
    summary = Text()
    summary.append(
        f"unstable modes: {report.n_unstable}\n", style="bold red" if report.n_unstable else "green"
    )
    summary.append(
        f"controllability rank: {report.controllable_dim} / {report.n}"
        f" ({'controllable' if report.controllable else 'NOT controllable'};"
        f" {'stabilizable' if report.stabilizable else 'NOT stabilizable'})\n"
    )
    summary.append(
        f"observability rank:   {report.observable_dim} / {report.n} from the outputs"
        f" ({'observable' if report.observable else 'NOT observable'};"
        f" {'detectable' if report.detectable else 'NOT detectable'})\n"
    )
    return summary


def linearization_view(lin: Linearization, report: LtiReport, discrete: bool) -> Group:
    """Everything ``pidlab linearize`` prints, as a rich renderable.

    Parameters
    ----------
    lin : Linearization
    report : LtiReport
        The modal analysis of the model shown (:func:`pidlab.linear.lti.analyze_lti`).
    discrete : bool
        Show the discrete model at the control period (``sysd``) instead of the continuous one.

    Returns
    -------
    rich.console.Group
    """
    sys = lin.sysd if discrete else lin.sys
    kind = f"discrete (dt = {lin.control_dt:g} s)" if discrete else "continuous"
    a_name, b_name = ("Ad", "Bd") if discrete else ("A", "B")
    rows_are = "next state" if discrete else "time derivative of the state"
    states = lin.state_names
    parts: list[Any] = [
        _linearization_head(lin),
        matrix_table(f"{a_name}: {kind} state matrix (rows: {rows_are})", np.asarray(sys.A), states, states),
        matrix_table(f"{b_name}: {kind} input matrix", np.asarray(sys.B), states, lin.input_names),
    ]
    if lin.output_names != states:
        parts.append(
            matrix_table(
                "C: observation variables from states (Jacobian of the observation)",
                np.asarray(sys.C),
                lin.output_names,
                states,
            )
        )
    parts += [modes_table(report, f"Eigenvalues of {a_name}"), _lti_summary(report)]
    return Group(*parts)


def wide_console(stderr: bool = False) -> Console:
    """A console that does not squeeze wide matrices into the terminal width.

    Text is printed as written (``markup=False``): a path or a TOML table name such as
    ``runs/[old]/spec.toml`` is not read as rich markup (which would drop it, or stop the command
    on an unmatched ``[/...]``). Styles are given as :class:`~rich.text.Text` styles instead.
    """
    return Console(width=max(Console().width, 240), stderr=stderr, markup=False)


def progress_bar(console: Console | None = None, **options: Any) -> Any:
    """A :class:`rich.progress.Progress` whose task descriptions are shown as written (no markup).

    ``options`` go to ``Progress`` (``transient``, ``disable``).
    """
    from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeRemainingColumn

    columns = (
        TextColumn("{task.description}", markup=False, style="progress.description"),
        BarColumn(),
        TaskProgressColumn(),
        TimeRemainingColumn(),
    )
    return Progress(*columns, console=console, **options)


def _db(x: float) -> str:
    if x == float("inf"):
        return "inf"
    if x == float("-inf"):
        return "-inf"
    return _defined(x, ".2f")


def _defined(x: float, fmt: str) -> str:
    """``x`` formatted, or "-" where it is not defined (NaN: no crossover, no margin)."""
    return "-" if np.isnan(x) else format(x, fmt)


def margins_table(title: str, margins: Sequence[Any]) -> Table:
    """Per-actuator stability margins with units."""
    t = Table(title=title, title_justify="left", min_width=len(title) + 4)
    for col in (
        "loop broken at",
        "GM (dB)",
        "lower GM (dB)",
        "PM (deg)",
        "delay margin (s)",
        "disk margin",
        "disk GM (dB)",
        "disk PM (deg)",
        "Ms (dB)",
        "gain crossover (rad/s)",
        "phase crossover (rad/s)",
    ):
        t.add_column(col, justify="right" if col != "loop broken at" else "left")
    for m in margins:
        t.add_row(
            m.actuator,
            _db(m.gain_margin_db),
            _db(m.lower_gain_margin_db),
            _defined(m.phase_margin_deg, ".1f"),
            _defined(m.delay_margin_s, ".4g"),
            _defined(m.disk_margin, ".3f"),
            _defined(m.disk_gain_margin_db, ".2f"),
            _defined(m.disk_phase_margin_deg, ".1f"),
            _db(m.ms_db),
            _defined(m.gain_crossover, ".4g"),
            _defined(m.phase_crossover, ".4g"),
        )
    return t


def poles_table(title: str, poles: Sequence[Any], discrete: bool) -> Table:
    """Closed-loop poles with damping and natural frequency."""
    t = Table(title=title, title_justify="left", min_width=len(title) + 4)
    t.add_column("#", justify="right")
    if discrete:
        t.add_column("z", justify="right")
        t.add_column("|z|", justify="right")
    t.add_column("s (rad/s)", justify="right")
    t.add_column("damping", justify="right")
    t.add_column("wn (rad/s)", justify="right")
    t.add_column("")
    for i, p in enumerate(poles):
        s = p.s
        s_txt = f"{s.real:.4g}" + (f" ± {abs(s.imag):.4g}j" if abs(s.imag) > 1e-12 else "")
        row = [str(i)]
        if discrete:
            z = p.value
            row += [
                f"{z.real:.5g}"
                + (f" {'+' if z.imag >= 0 else '-'} {abs(z.imag):.4g}j" if abs(z.imag) > 1e-12 else ""),
                f"{abs(z):.6f}",
            ]
        row += [s_txt, f"{p.damping:.3f}", f"{p.natural_frequency:.4g}"]
        t.add_row(*row, Text("stable", style="green") if p.stable else Text("UNSTABLE", style="bold red"))
    return t


def responses_table(responses: Sequence[Any]) -> Table:
    """Step and initial-condition response metrics."""
    t = Table(title="Closed-loop responses (discrete, linear)", title_justify="left")
    for col in (
        "response",
        "loop",
        "signal",
        "overshoot (%)",
        "settling 2% (s)",
        "rise 10-90% (s)",
        "peak |u| / half-range",
    ):
        t.add_column(col, justify="left" if col in ("response", "loop", "signal") else "right")
    for r in responses:
        what = "unit setpoint step" if r.kind == "step" else f"initial deviation {r.size:g}"
        t.add_row(
            what,
            r.loop,
            r.signal,
            "not defined" if r.overshoot_pct != r.overshoot_pct else f"{r.overshoot_pct:.1f}",
            f"{r.settling_time_s:.3g}",
            "" if r.rise_time_s != r.rise_time_s else f"{r.rise_time_s:.3g}",
            f"{r.peak_control:.3g}",
        )
    return t


def score_table(score: Any) -> Table:
    """Coach-alone episodes summary: return statistics and failure causes."""
    t = Table(
        title=f"Coach alone on {score.env_id}: {len(score.episodes)} episodes (seeds "
        f"{score.episodes[0].seed}..{score.episodes[-1].seed})",
        title_justify="left",
    )
    t.add_column("mean return", justify="right")
    t.add_column("std", justify="right")
    t.add_column("min", justify="right")
    t.add_column("max", justify="right")
    t.add_column("mean length (steps)", justify="right")
    t.add_column("how episodes ended")
    r = score.returns
    causes = "; ".join(f"{n}x {c}" for c, n in sorted(score.causes.items(), key=lambda kv: -kv[1]))
    t.add_row(
        f"{score.mean:.1f}",
        f"{score.std:.1f}",
        f"{r.min():.1f}",
        f"{r.max():.1f}",
        f"{score.mean_length:.0f}",
        causes,
    )
    return t


def analysis_view(analysis: Any, score: Any | None) -> Group:
    """Everything ``pidlab analyze`` prints."""
    parts: list[Any] = []
    head = Text()
    head.append(f"{analysis.env_id} / {analysis.spec_name}", style="bold")
    head.append(
        f"  control period {analysis.dt:g} s; plant linearized at {analysis.linearization.op.source}\n"
    )
    if analysis.unobservable:
        head.append(f"left out (unobservable from the observation): {', '.join(analysis.unobservable)}\n")
    if analysis.linearization.kink > 1e-3:
        head.append(
            "contacts at the operating point: the linear analysis is an averaged local picture, "
            "the coach-alone score is the real test\n",
            style="yellow",
        )
    if analysis.stable:
        head.append("closed loop (discrete, linear): STABLE\n", style="bold green")
    else:
        bad = [p for p in analysis.discrete.poles if not p.stable]
        listing = ", ".join(f"|z|={abs(p.value):.5f}" for p in bad)
        head.append(
            f"closed loop (discrete, linear): UNSTABLE - {len(bad)} pole(s) on or outside the unit "
            f"circle ({listing}); the margins below do not certify anything\n",
            style="bold red",
        )
    parts.append(head)
    parts.append(
        margins_table(
            "Margins, discrete (what runs), each loop broken at its actuator", analysis.discrete.margins
        )
    )
    parts.append(
        margins_table(
            "Margins, continuous (coach by inverse Tustin, sampling ignored)", analysis.continuous.margins
        )
    )
    parts.append(poles_table("Closed-loop poles (discrete)", analysis.discrete.poles, True))
    parts.append(responses_table(analysis.responses))
    parts.append(
        Text(
            f"pole cross-check: python-control interconnect vs hand-assembled A_cl: "
            f"max difference {analysis.discrete.pole_check:.2g} (discrete), "
            f"{analysis.continuous.pole_check:.2g} (continuous)"
        )
    )
    if score is not None:
        parts.append(score_table(score))
    return Group(*parts)


def roa_view(result: Any, units: dict[str, str] | None = None) -> Group:
    """What ``pidlab roa`` prints: method, levels, samples, confidence, extents with units."""
    head = Text()
    head.append(f"{result.env_id} / {result.spec_name}: region of attraction\n", style="bold")
    head.append(f"method: {result.method}\n")
    chk = result.check
    if result.lyapunov is not None:
        opt = "not available" if result.c_optimization is None else f"{result.c_optimization:.4g}"
        head.append(
            f"level c (V = X' P X, Q = I): certified {result.level:.4g}; CasADi estimate {opt}; "
            f"simulation bisection {result.c_simulation:.4g}\n"
        )
        if result.lyapunov.tangent is not None:
            head.append(
                "centre: the posture the balance coach was designed at; V over the observation "
                "(the plant's observable part), no CasADi estimate over contacts\n"
            )
    head.append(
        f"certification: {chk.samples} simulated initial states, {chk.failures} failures "
        f"({chk.terminated} terminated, {chk.not_converged} not converged) over {chk.horizon_s:g} s; "
        f"failure probability < {chk.failure_bound_95:.2g} at 95 % (rule of three)\n"
    )
    head.append(f"computed in {result.elapsed_s:.1f} s\n")
    parts: list[Any] = [head]
    t = Table(
        title="Extent of the certified region per variable (others free within the set)", title_justify="left"
    )
    t.add_column("variable")
    t.add_column("unit")
    t.add_column("centre", justify="right")
    t.add_column("half-width", justify="right")
    if result.lyapunov is not None:
        L = result.lyapunov
        Pinv = np.linalg.inv(L.P_y)
        for i, v in enumerate(L.variables):
            t.add_row(
                v, (units or {}).get(v, ""), f"{L.center[i]:.4g}", f"{np.sqrt(result.level * Pinv[i, i]):.4g}"
            )
    else:
        for v, h in result.box.items():
            t.add_row(v, (units or {}).get(v, ""), "", f"{h:.4g}")
    parts.append(t)
    return Group(*parts)


def bounds_view(b: Any) -> Group:
    """What ``pidlab bounds`` prints."""
    head = Text()
    head.append(f"critical-state bounds ({b.method})\n", style="bold")
    frac = b.provenance.get("one_step_action_fraction", 1.0)
    if b.variables:
        head.append(
            f"ellipsoid: V <= rho c with rho = {b.rho:.4g} (c = {b.level:.4g}) over "
            f"{', '.join(b.variables)}\n"
        )
    else:
        head.append(f"box scaled to {b.rho:.4g} of the recoverable box for the one-step margin\n")
    if frac < 1.0:
        head.append(
            f"one-step margin sized for agent actions up to {frac:.0%} of the action range: "
            "from the operating point, one full-range action is more than this coach recovers from\n",
            style="yellow",
        )
    samples, escapes = b.one_step_check
    head.append(f"one-step check in MuJoCo: {samples} boundary states, {escapes} not recovered\n")
    t = Table(title="Box: the coach takes over outside", title_justify="left")
    t.add_column("variable")
    t.add_column("low", justify="right")
    t.add_column("high", justify="right")
    for v, (lo, hi) in b.box.items():
        t.add_row(v, f"{lo:.4g}", f"{hi:.4g}")
    return Group(head, t)


def rescue_view(r: Any, units: dict[str, str]) -> Group:
    """What ``pidlab rescue`` prints: the region, its validation and its coverage against the other sets."""
    s, g = r.settings, r.grid
    head = Text()
    head.append(f"rescue region of {r.spec_name} on {r.env_id} ({s.trigger} trigger)\n", style="bold")
    if s.trigger == "reactive":
        chosen = (
            " (the largest the coach handles)"
            if r.provenance.get("fraction_chosen") and s.action_fraction < 1
            else ""
        )
        head.append(f"room for one agent step of up to {s.action_fraction:.0%} of the action range{chosen}\n")
    cells = " x ".join(str(c) for c in g.cells)
    head.append(
        f"lookup grid {cells} over {', '.join(g.variables)}: {int(g.table.sum()):,} cells marked "
        f"({g.fraction_marked():.1%}); probes per cell: its vertices at each guard corner, then "
        f"{s.probes} random\n"
    )
    samples, failures = r.validation
    head.append(
        f"validation in MuJoCo: {samples:,} fresh states in the region, {failures} not rescued "
        f"(failure rate < {r.failure_bound_95:.2%} at 95 %); {r.rounds} draw(s), "
        f"{r.unmarked} cell(s) unmarked\n"
    )
    t = Table(title="Domain (rescued: brought into the certified core, no termination)", title_justify="left")
    for col in ("variable", "role", "low", "high"):
        t.add_column(col, justify="left" if col in ("variable", "role") else "right")
    for v, lo, hi in zip(g.variables, g.lower, g.upper, strict=True):
        t.add_row(f"{v} ({units.get(v, '')})", "grid", f"{lo:.4g}", f"{hi:.4g}")
    for v, (lo, hi) in g.guard.items():
        t.add_row(f"{v} ({units.get(v, '')})", "guard", f"{lo:.4g}", f"{hi:.4g}")
    c = r.coverage
    cov = Table(
        title=f"Coverage: {c.rescuable:,} of {c.samples:,} fresh states over the domain are rescuable",
        title_justify="left",
    )
    for col in ("region", "coverage (of rescuable)", "size (of domain)"):
        cov.add_column(col, justify="left" if col == "region" else "right")
    for name in c.contained:
        cov.add_row(name, f"{c.fraction(name):.1%}", f"{c.volume[name]:.1%}")
    return Group(head, t, cov)


def classifier_view(r: Any, spec_name: str, env_id: str, units: dict[str, str]) -> Group:
    """What ``pidlab rescue-classifier`` prints: the domain, the validation and the coverage."""
    s, c = r.settings, r.classifier
    head = Text()
    head.append(f"classifier rescue region of {spec_name} on {env_id} (predictive trigger)\n", style="bold")
    head.append(
        f"network {len(c.variables)}-{s.width}-{s.width}-1 (tanh) fitted on {s.samples:,} labelled states, "
        f"threshold {c.threshold:.4g} set on {s.calibration:,} more (accuracy {r.calibration_accuracy:.1%})\n"
    )
    if s.focus:
        head.append(
            f"focus: fitted again with {s.focus:,} more labelled states where a first fit scored at least "
            f"{r.provenance['focus_level']:.4g} ({r.provenance['focus_rescued']:.1%} of them rescued)\n"
        )
    if s.near:
        head.append(
            f"near: fitted with {s.near:,} more labelled states in boxes about where the coach hands back "
            f"and the operating point ({r.provenance['near_rescued']:.1%} of them rescued)\n"
        )
    if s.false_claims:
        head.append(
            f"false claims tolerated: a draw is accepted when its failures show a failure rate below "
            f"{s.false_claims:.2%} at 95 % (the failures of the accepted draw stay in the region)\n"
        )
    head.append(
        f"validation in MuJoCo: {s.validation:,} fresh states in the region, {r.validation_failures} not "
        f"rescued (failure rate < {r.failure_bound_95:.2%} at 95 %); {r.validation_rounds} draw(s), "
        f"{r.failures_removed} failure(s) found and excluded on the way\n"
    )
    if r.edge_rounds:
        head.append(
            f"at its edge (its lowest-scoring {s.edge_share:.0%}): {s.validation:,} fresh states, "
            f"{r.edge_failures} not rescued; {r.edge_rounds} draw(s), {r.edge_failures_removed} failure(s) "
            "found and excluded on the way\n"
        )
    t = Table(title="Domain: this box, states the env's termination rule ends dropped", title_justify="left")
    for col in ("variable", "low", "high"):
        t.add_column(col, justify="left" if col == "variable" else "right")
    for v, lo, hi in zip(c.variables, c.lower, c.upper, strict=True):
        t.add_row(f"{v} ({units.get(v, '')})", f"{lo:.4g}", f"{hi:.4g}")
    rescuable = r.provenance.get("coverage_rescuable", 0)
    cov = Table(
        title=f"Coverage: {rescuable:,} of {s.coverage:,} fresh states over the domain are rescuable "
        f"({r.rescued_fraction:.1%})",
        title_justify="left",
    )
    for col in ("region", "coverage (of rescuable)"):
        cov.add_column(col, justify="left" if col == "region" else "right")
    cov.add_row("classifier", f"{r.coverage:.1%}")
    if r.coverage_grid is not None:
        cov.add_row("the spec's lookup grid", f"{r.coverage_grid:.1%}")
    return Group(head, t, cov)


def _reach_cell(r: Any) -> str:
    """A perturbation's reach on each side, and where its starts leave a joint's range (none probed past)."""
    cell = f"{-r.negative or 0.0:.3g} .. {r.positive:+.3g} of {r.limit:g}"
    cut = r.past_range()
    return cell + (f" (a joint leaves its range past {' and '.join(cut)})" if cut else "")


def recovery_view(found: Sequence[Any]) -> Group:
    """What ``pidlab recovery`` prints: each coach's reach per perturbation and its falls."""
    first = found[0]
    head = Text()
    head.append(f"What the coach alone recovers from on {first.env_id}\n", style="bold")
    head.append(
        f"a start is recovered when the env's termination rule does not fire in {first.horizon_s:g} s; "
        "reach: the largest push on each side up to which every probe recovered (a start that puts a joint "
        "outside its range is not probed)\n"
    )
    t = Table(title_justify="left")
    t.add_column("coach")
    for r in first.reach:
        t.add_column(f"{r.name} ({r.unit}), reach", justify="right")
    t.add_column(f"falls / 100 episodes (95 % interval), seed {first.seed}", justify="right")
    for rec in found:
        cells = [_reach_cell(r) for r in rec.reach]
        lo, hi = rec.falls_ci
        falls = f"{rec.falls_per_100:.0f} ({lo:.0f}-{hi:.0f}) of {rec.episodes}" if rec.episodes else "-"
        t.add_row(rec.spec_name, *cells, falls)
    return Group(head, t)


def coverage_view(found: Sequence[Any], units: dict[str, str]) -> Group:
    """What ``pidlab rescue-coverage`` prints: per coach, the rescuable share and each region's scores."""
    first = found[0]
    s = first.settings
    pairs = zip(s.variables, s.half_range, strict=True)
    box = ", ".join(f"{v} +-{h:g}{' ' + units[v] if units.get(v) else ''}" for v, h in pairs)
    head = Text()
    head.append(f"Rescue coverage on {first.env_id}\n", style="bold")
    starts = "on the floor" if first.grounded else "as drawn"
    head.append(
        f"{s.states:,} states uniform over {box}, inside the termination domain and the joint ranges "
        f"(starts {starts}, seed {s.seed}); rescued: into the certified core, or held {s.horizon_s:g} s, "
        "without a termination\n"
    )
    t = Table(title_justify="left")
    for col in ("coach", "rescuable", "region", "states inside", "coverage of the rescuable",
                "false claims (95 % interval)"):  # fmt: skip
        t.add_column(col, justify="left" if col in ("coach", "region") else "right")
    for c in found:
        share = f"{c.rescuable:,} ({100 * c.rescuable_share:.1f} %)"
        if not c.scores:
            t.add_row(c.spec_name, share, "none in [bounds]", "-", "-", "-")
        for i, r in enumerate(c.scores):
            lo, hi = r.false_claims_ci
            false = "-" if not r.inside else f"{100 * r.false_claims:.1f} % ({100 * lo:.1f}-{100 * hi:.1f})"
            t.add_row(c.spec_name if i == 0 else "", share if i == 0 else "", r.kind, f"{r.inside:,}",
                      f"{100 * r.coverage:.1f} %", false)  # fmt: skip
    return Group(head, t, *(_reach_lines(c, units) for c in found if c.reach))


def _reach_lines(c: Any, units: dict[str, str]) -> Text:
    """Where one coach's rescued states lie, and the classifier domain that holds them."""
    out = Text()
    if not c.rescuable:
        out.append(f"{c.spec_name}: no state rescued\n")
        return out
    reach = ", ".join(
        f"{v} {a:.3g}/{b:.3g}{' ' + units[v] if units.get(v) else ''}"
        for v, a, b in zip(c.settings.variables, c.reach, c.reach95, strict=True)
    )
    out.append(f"{c.spec_name}: the rescued states lie within (largest / 95 %, off the operating point) ")
    out.append(f"{reach}\n")
    out.append(f"  a classifier domain holding them all: --domain {c.classifier_domain()}\n")
    return out


def train_view(result: Any, win_target: float) -> Group:
    """What ``pidlab train`` prints at the end: step accounts and the agent-alone score."""
    t = Table(title=f"Training run {result.run_dir}", title_justify="left")
    t.add_column("quantity")
    t.add_column("value", justify="right")
    env = max(result.env_steps, 1)
    t.add_row("env steps (agent + coach)", f"{result.env_steps:,}")
    t.add_row("agent steps", f"{result.agent_steps:,}")
    t.add_row("coach steps", f"{result.coach_steps:,} ({100 * result.coach_steps / env:.1f} %)")
    t.add_row("interventions", f"{result.interventions:,}")
    t.add_row("training episodes", f"{result.episodes:,}")
    if result.wall_s > 0:
        t.add_row("wall time (this session)", f"{result.wall_s:.1f} s")
    ev = result.final_evaluation
    if ev is not None:
        wins = sum(r >= win_target for r in ev.returns)
        t.add_row(
            "agent alone (coach off, deterministic)",
            f"{ev.mean:.1f} +- {ev.std:.1f} over {len(ev.returns)} seeds; {wins} >= {win_target:g}",
        )
    status = Text(
        "completed" if result.completed else "stopped: resume with --resume " + str(result.run_dir),
        style="green" if result.completed else "yellow",
    )
    return Group(t, status)


def _pieces(pieces: int | None) -> str:
    """How a query's boxes are capped, for a header line."""
    return "" if pieces is None else f", at most {pieces} boxes per halving"


def forecast_view(f: Any, units: dict[str, str], kept: float | None = None) -> Group:
    """What ``pidlab forecast`` prints: the forecast's error per region variable, and the vetoes."""
    head = Text()
    head.append(f"{f.model} forecast, measured behind the exact shield with a random agent (seed {f.seed}); "
                f"{f.bound} bound{_pieces(f.pieces)}\n", style="bold")  # fmt: skip
    if f.network is not None:
        head.append(f"its correction fitted on {f.network.fitted:,} earlier actions\n")
    if f.in_scope is None:
        head.append(
            f"margins from {f.transitions:,} actions; {f.held_out:,} held-out actions: {f.escapes} outside "
            "the margins of their forecast\n"
        )
    else:
        head.append(
            f"margins from the {f.in_scope:,} of {f.transitions:,} actions whose forecast lies in the "
            f"region's domain box; of the {f.held_out_in_scope:,} such of {f.held_out:,} held-out actions, "
            f"{f.escapes} outside the margins of their forecast\n"
        )
    if f.adaptive is not None:
        head.append(
            f"adaptive margins: a network fitted on {f.adaptive.network.fitted:,} in-scope of "
            f"{f.adaptive.transitions:,} earlier actions gives the error's scale at each state and action; "
            "a margin is that scale times the variable's factor, at most its largest margin\n"
        )
    if kept is not None:
        head.append(f"{kept:.1%} of the rescue region has its margin box inside it (sampled)\n")
    t = Table(title="Forecast error, |true - forecast| one control period ahead", title_justify="left")
    cols = ("variable", "median", "99th percentile", "margin (largest)")
    for col in (*cols, "factor (adaptive)") if f.adaptive is not None else cols:
        t.add_column(col, justify="left" if col == "variable" else "right")
    factors = f.adaptive.factors if f.adaptive is not None else (None,) * len(f.variables)
    for v, med, p99, m, k in zip(f.variables, f.median, f.p99, f.margins, factors, strict=True):
        unit = units.get(v, "")
        extra = () if k is None else (f"{k:.3g}",)
        t.add_row(f"{v} ({unit})", f"{med:.3g}", f"{p99:.3g}", f"{m:.3g}", *extra)
    a = f.agreement
    v = Table(title=f"Vetoes on the held-out actions: agreement {f.veto_agreement:.1%}",
              title_justify="left")  # fmt: skip
    for col in ("exact vetoes", "model vetoes", "actions"):
        v.add_column(col, justify="left" if col != "actions" else "right")
    rows = [("both", "yes", "yes"), ("exact_only", "yes", "no"), ("model_only", "no", "yes")]
    rows.append(("neither", "no", "no"))
    for key, exact, model in rows:
        v.add_row(exact, model, f"{a[key]:,}")
    return Group(head, t, v)


def status_lines(rows: Sequence[tuple[str, str, int, int, RunProgress]]) -> list[str]:
    """A sweep's status as text: each (env, condition)'s runs by state, the unfinished runs, the totals.

    Parameters
    ----------
    rows : sequence of (env_id, condition, seed, budget, RunProgress)
        Every run of the sweep, in its order (:func:`pidlab.experiment.progress.run_progress`).

    Returns
    -------
    list of str
    """
    lines: list[str] = []
    cells: dict[tuple[str, str], list[RunProgress]] = {}
    for env_id, condition, _seed, _budget, rp in rows:
        cells.setdefault((env_id, condition), []).append(rp)
    width = max((len(f"{e} {c}") for e, c in cells), default=0)
    for (env_id, condition), found in cells.items():
        counts = ", ".join(f"{n} {s}" for s in RUN_STATES if (n := sum(r.state == s for r in found)))
        lines.append(f"{f'{env_id} {condition}':<{width}}  {len(found)} runs: {counts}")
    for env_id, condition, seed, budget, rp in rows:
        if rp.state in ("under way", "damaged"):
            now = "; training now" if rp.training else ""
            why = f"; damaged: {rp.problem}" if rp.state == "damaged" else ""
            lines.append(f"  {env_id}/{condition}/seed-{seed}: checkpoint at {rp.checkpointed:,} of "
                         f"{budget:,} env steps, log at {rp.logged:,}{now}{why}")  # fmt: skip
    total = sum(r[3] for r in rows)
    kept = sum(r[4].checkpointed for r in rows)
    counts = ", ".join(f"{sum(r[4].state == s for r in rows)} {s}" for s in RUN_STATES)
    share = f" ({100 * kept / total:.1f} %)" if total else ""
    lines.append(f"runs: {counts} (of {len(rows)}); {kept:,} of {total:,} env steps checkpointed{share}")
    return lines
