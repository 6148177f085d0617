"""The model predictor's tables in docs/rescue.md, from the shipped model specs and the published runs.

The forecast's error, the vetoes it agrees on and the share of the region left are read from each
spec of :data:`SPECS` (``tuning/ENV.pidlab-rescue-model.toml``, and InvertedPendulum's
``pidlab-rescue-edge-model``, a classifier region; its ``[bounds.forecast]``, as ``pidlab forecast`` wrote it;
the share is :func:`pidlab.region.forecast.kept_share`, a seeded sample). Whether a run can use the
model predictor is asked of :func:`pidlab.rl.coaching.model_region`, as a run asks it. The falls in
training are read from the per-run ``summary.json`` files of the published folders of :data:`TRAINED`.
The tables sit in docs/rescue.md between ``<!-- forecast-table -->`` and ``<!-- /forecast-table -->``.

Run: .venv/bin/python benchmarks/forecast_table.py [--check]
(--check: exit 1 when the page's tables differ from the files'.) ``benchmarks/recompute.py`` runs the
same check with every published folder (some three minutes on one core: Hopper's classifier rows draw
their margin boxes); the test suite checks the rows that take seconds (:func:`quick_specs`).
"""

from __future__ import annotations

import json
import statistics
import sys
from pathlib import Path

from bench_cli import run

from pidlab.controller.spec import load_spec
from pidlab.errors import CoachingError
from pidlab.files import atomic_write_text
from pidlab.plant.model import load_model
from pidlab.region.forecast import kept_inputs, kept_share, spec_forecast
from pidlab.region.takeover import ClassifierRegion, region_from_bounds
from pidlab.rl.coaching import model_region

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "rescue.md"
SPECS = (
    ("InvertedPendulum-v5", "pidlab-rescue-model", "lookup grid"),
    ("InvertedPendulum-v5", "pidlab-rescue-edge-model", "classifier validated at its edge"),
    ("InvertedPendulum-v5", "pidlab-rescue-edge-linear", "classifier validated at its edge"),
    ("InvertedPendulum-v5", "pidlab-rescue-edge-scoped", "classifier validated at its edge"),
    ("InvertedDoublePendulum-v5", "pidlab-rescue-model", "lookup grid + guard box"),
    ("InvertedDoublePendulum-v5", "pidlab-rescue-full-learned", "classifier over the full state"),
    ("InvertedDoublePendulum-v5", "pidlab-rescue-full-linear", "classifier over the full state"),
    ("InvertedDoublePendulum-v5", "pidlab-rescue-full-scoped", "classifier over the full state"),
    ("Hopper-v5", "pidlab-rescue-model", "lookup grid over pitch"),
    ("Hopper-v5", "pidlab-room-full-learned",
     "room coach's classifier over pitch, legs and rates (its network reads the forward position)", 2000),
    ("Hopper-v5", "pidlab-room-focus-learned",
     "room coach's classifier over pitch, legs and rates, focused fit (the published runs' network, which "
     "reads the forward position)", 2000),
    ("Hopper-v5", "pidlab-room-focus-learned-blind",
     "room coach's classifier over pitch, legs and rates, focused fit (the forward position blind)", 2000),
    ("Hopper-v5", "pidlab-room-focus-adaptive",
     "room coach's classifier over pitch, legs and rates, focused fit (the forward position blind)", 2000),
    ("Walker2d-v5", "pidlab-rescue-model", "lookup grid over pitch"),
)  # fmt: skip
"""(env, the spec with its measurement in tuning/, its rescue region[, states sampled for the share of
the region kept, default :data:`KEPT_SAMPLES`]) per row of the error table. Hopper's region over the
legs draws 2,000: most of its margin boxes are halved 8 times before they fail, 20,000 take minutes."""
KEPT_SAMPLES = 20_000
TRAINED = (
    ("InvertedPendulum-v5-model", ("none", "rescue-terminal", "rescue-terminal-model")),
    ("InvertedPendulum-v5-edgemodel", ("rescue-terminal-edge", "rescue-terminal-edge-model")),
    ("InvertedDoublePendulum-v5-learned", ("rescue-terminal-full", "rescue-terminal-full-learned")),
    ("InvertedDoublePendulum-v5-scoped", ("rescue-terminal-full-scoped",)),
    ("Hopper-v5-roommodel", ("rescue-terminal-room-focus", "rescue-terminal-room-focus-learned")),
)
"""(published folder, its conditions) per block of the training table (unpublished: skipped)."""
START, END = "<!-- forecast-table -->", "<!-- /forecast-table -->"
MISMATCH = "docs/rescue.md: its forecast tables differ from the files'; run benchmarks/forecast_table.py"


def _unit(unit: str) -> str:
    return "" if unit in ("", "1") else f" {unit}"


def _model_cell(f, region) -> str:
    """The forecast model, how a classifier's score is bounded over a margin box, the margins' scope."""
    cell = f"{f.model}, {f.bound} bound" if isinstance(region, ClassifierRegion) else f.model
    if f.pieces is not None:
        cell += f", at most {f.pieces} boxes per halving"
    if f.scope == "domain":
        cell += f"; margins from the {f.in_scope:,} of {f.transitions:,} forecasts in the region's domain"
    if f.adaptive is not None:
        cell += f"; adaptive margins (scale fitted on {f.adaptive.transitions:,} more)"
    return cell


def _kept_cell(share: float, samples: int) -> str:
    """The share of the region whose margin box fits, and the draw when it is not the default's."""
    return f"{100 * share:.1f} %" + (f" ({samples:,} states)" if samples != KEPT_SAMPLES else "")


def _escapes_cell(f) -> str:
    """Held-out transitions outside the margins of their forecast, of those the margins speak for."""
    if f.scope == "domain":
        return f"{f.escapes} of {f.held_out_in_scope:,} in the domain ({f.held_out:,} in all)"
    return f"{f.escapes} of {f.held_out:,}"


def _error_cell(f, units: dict[str, str]) -> str:
    return "; ".join(
        f"{v} {med:.2g} / {p99:.2g} / {m:.2g}{_unit(units.get(v, ''))}"
        for v, med, p99, m in zip(f.variables, f.median, f.p99, f.margins, strict=True)
    )


def row(env: str, name: str, shape: str, samples: int = KEPT_SAMPLES) -> str:
    """One spec's row: the error per variable, the escapes, the vetoes, the region left, usable or not."""
    spec = load_spec(ROOT / "tuning" / f"{env}.{name}.toml")
    loaded = load_model(env)
    card = loaded.require_card()
    f = spec_forecast(spec.bounds, spec.name)
    region = region_from_bounds(spec.bounds, card.observation_names, "rescue", spec.name)
    try:
        model_region(spec, loaded, region)
        usable = "yes"
    except CoachingError:
        usable = "no"
    a = f.agreement
    units = {v.name: v.unit for v in card.observation}
    kept = kept_share(region, f.margin, samples=samples, bound=f.bound, pieces=f.pieces, adaptive=f.adaptive,
                      inputs_of=kept_inputs(region, loaded) if f.adaptive is not None else None)  # fmt: skip
    return (
        f"| {env} | {shape} | {_model_cell(f, region)} | {_error_cell(f, units)} | "
        f"{_escapes_cell(f)} | "
        f"{a['both']:,} | "
        f"{a['exact_only']:,} | {a['model_only']:,} | {a['neither']:,} | "
        f"**{100 * f.veto_agreement:.1f} %** | "
        f"{_kept_cell(kept, samples)} | {usable} |"
    )


def quick_specs() -> list[tuple]:
    """The rows of :data:`SPECS` that take seconds: those drawing the default sample for the share kept."""
    return [spec for spec in SPECS if len(spec) < 4 or spec[3] == KEPT_SAMPLES]


def page_tables() -> str:
    """The tables as they stand in docs/rescue.md, between the markers."""
    text = PAGE.read_text()
    return text[text.index(START) + len(START) : text.index(END)].strip()


def error_table() -> str:
    """The forecast's error and vetoes, one row per spec."""
    head = (
        "| env | rescue region | forecast | error per variable: median / 99th percentile / margin "
        "(largest) | held-out states outside the margins | both veto | exact only | model only | neither | "
        "veto agreement | region whose margin box fits | model predictor usable |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|"
    )
    return "\n".join([head, *(row(*spec) for spec in SPECS)])


def _summaries(folder: str, condition: str) -> list[dict]:
    env = folder.rsplit("-", 1)[0]
    runs = ROOT / "docs" / "results" / folder / "runs" / env / condition
    return [json.loads(p.read_text()) for p in sorted(runs.glob("seed-*/summary.json"))]


def training_table() -> str:
    """Falls, coach share and the agent-alone score per condition, from the published runs."""
    head = (
        "| sweep | condition | runs | falls per run: median [min, max] | "
        "coach's share of env steps (median) | agent-alone final score (median) |\n|---|---|---|---|---|---|"
    )
    rows = []
    for folder, conditions in TRAINED:
        if not (ROOT / "docs" / "results" / folder / "experiment.json").exists():
            continue
        for cond in conditions:
            s = [x for x in _summaries(folder, cond) if x.get("completed")]
            if not s:
                rows.append(f"| {folder} | {cond} | 0 | — | — | — |")
                continue
            falls = [x["falls"] for x in s]
            share = statistics.median(x.get("coach_step_fraction", 0.0) for x in s)
            score = statistics.median(x["final_evaluation"]["mean"] for x in s)
            spread = f"{statistics.median(falls):g} [{min(falls)}, {max(falls)}]"
            rows.append(f"| {folder} | {cond} | {len(s)} | {spread} | {100 * share:.1f} % | {score:.0f} |")
    return "\n".join([head, *rows])


def tables() -> str:
    """Both tables, in Markdown."""
    return error_table() + "\n\n" + training_table()


def main(argv: list[str]) -> int:
    """Print the tables; write them into the page (or, with --check, compare)."""
    body = tables()  # minutes of work: the page is read after it, so edits made meanwhile are kept
    text = PAGE.read_text()
    start, end = text.index(START) + len(START), text.index(END)
    new = text[:start] + "\n" + body + "\n" + text[end:]
    print(body)
    if "--check" in argv:
        if new != text:
            print(MISMATCH, file=sys.stderr)
            return 1
        return 0
    atomic_write_text(PAGE, new)
    return 0


if __name__ == "__main__":
    run(lambda: main(sys.argv[1:]))
