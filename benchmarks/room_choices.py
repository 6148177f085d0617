"""How much room each coaching choice leaves the agent: coach preset and hand-back fraction.

Writes (or replaces) the section "Choices measured" of docs/rescue.md, between its markers, and
prints the table. Run:

    .venv/bin/python benchmarks/room_choices.py [--env InvertedPendulum-v5] [--seeds 3] [--steps 20000]

Two tables:

1. **Coach preset** (``robust``, the shipped ``room`` coach): the rescue region each coach gets on
   the model card's rescue domain (``estimate_rescue`` with the card's settings; its coverage and
   its validation), and the coach's falls alone: in ``--episodes`` episodes of the real env from
   its own resets, and among the validation's fresh states drawn inside the region.
2. **Hand-back fraction** (0.25, 0.5, 1.0) for the ``hidden`` and ``terminal`` views with the
   room coach's rescue region and the predictive trigger: a ``pidlab experiment`` of ``--seeds``
   seeds at ``--steps`` env steps each (results/room-choices-ENV, resumable; its report and runs'
   logs are copied to docs/results/room-choices-ENV, where benchmarks/recompute.py checks them).
   Per choice, the median over seeds, with the lowest and highest seed beside it, of: the coach's share
   of env steps, the agent's average uninterrupted run (agent steps per takeover: how long the agent
   acts before its next vetoed action), the falls during training and the agent-alone score at the end.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import re
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

from bench_cli import Parser, count, run

from pidlab.controller.rollout import coach_alone
from pidlab.controller.spec import load_spec
from pidlab.errors import RegionError
from pidlab.files import atomic_write_text
from pidlab.plant.model import load_model
from pidlab.region.rescue import default_settings, estimate_rescue
from pidlab.region.takeover import load_region

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "rescue.md"
START, END = "<!-- room-choices: start -->", "<!-- room-choices: end -->"
HANDBACKS = (0.25, 0.5, 1.0)
VIEWS = ("hidden", "terminal")


def preset_rows(env_id: str, episodes: int) -> list[str]:
    """One table row per coach preset: its rescue region and its falls alone."""
    loaded = load_model(env_id)
    rows = []
    for preset, name in (("robust", "pidlab-robust"), ("room", "pidlab-rescue")):
        spec = load_spec(ROOT / "tuning" / f"{env_id}.{name}.toml")
        alone = coach_alone(spec, loaded, episodes=episodes)
        falls = sum(e.terminated for e in alone.episodes)
        try:
            region = estimate_rescue(spec, loaded, default_settings(spec, loaded), workers=2)
        except RegionError as exc:
            rows.append(f"| {preset} | no region: {exc} | — | — | {falls} of {episodes} |")
            continue
        cov = region.coverage
        n, failures = region.validation
        rows.append(
            f"| {preset} | {cov.fraction('rescue'):.1%} of {cov.rescuable:,} rescuable | "
            f"{region.grid.fraction_marked():.1%} | {failures} of {n:,} ({region.rounds} draw(s)) | "
            f"{falls} of {episodes} |"
        )
    return rows


def conditions_file(path: Path) -> None:
    """The hand-back choices as a conditions file."""
    lines = ['schema = "pidlab.conditions/1"', ""]
    for view in VIEWS:
        for h in HANDBACKS:
            lines += [
                f"[condition.{view}-h{int(h * 100)}]",
                f'description = "Rescue region, predictive trigger, view {view}, hand-back {h}."',
                'coach = "pidlab-rescue"',
                f'coaching = {{ mode = "takeover", region = "rescue", trigger = "predictive", '
                f'handback = {h}, view = "{view}" }}',
                "",
            ]
    atomic_write_text(path, "\n".join(lines))


def run_choices(env_id: str, seeds: int, steps: int) -> Path:
    """Run (or resume) the hand-back experiment; its folder."""
    out = ROOT / "results" / f"room-choices-{env_id}"
    cond = ROOT / "benchmarks" / "room_choices.conditions.toml"  # committed: the command names it
    conditions_file(cond)
    names = ",".join(f"{v}-h{int(h * 100)}" for v in VIEWS for h in HANDBACKS)
    cmd = [str(ROOT / ".venv" / "bin" / "pidlab"), "experiment", "--envs", env_id, "--conditions", names,
           "--seeds", str(seeds), "--steps", str(steps), "--out", str(out.relative_to(ROOT)),
           "--conditions-file", str(cond.relative_to(ROOT)), "--workers", "2", "--no-progress"]  # fmt: skip
    subprocess.run(cmd, check=True, cwd=ROOT)
    return out


def publish(out: Path, env_id: str) -> Path:
    """Copy the experiment's report, tables, record and runs' logs to docs/results/room-choices-ENV."""
    dst = ROOT / "docs" / "results" / f"room-choices-{env_id}"
    dst.mkdir(parents=True, exist_ok=True)
    for name in ("report.md", "report.html", "metrics.csv", "summary.csv", "experiment.json"):
        shutil.copy2(out / name, dst / name)
    shutil.copytree(out / "figures", dst / "figures", dirs_exist_ok=True)
    subprocess.run(["bash", str(ROOT / "benchmarks" / "copy_runs.sh"), str(out), str(dst)], check=True)
    return dst


def spread(values: list[float], fmt: str) -> str:
    """The median over seeds, then the lowest and highest seed: a median alone hides a seed that fails."""
    return f"{statistics.median(values):{fmt}} ({min(values):{fmt}} to {max(values):{fmt}})"


def choice_rows(out: Path, env_id: str) -> list[str]:
    """One row per hand-back choice: medians and ranges over seeds, from the runs' summaries and metrics."""
    metrics: dict[str, list[dict[str, str]]] = {}
    with open(out / "metrics.csv", newline="") as f:
        for r in csv.DictReader(f):
            metrics.setdefault(r["condition"], []).append(r)
    rows = []
    for view in VIEWS:
        for h in HANDBACKS:
            name = f"{view}-h{int(h * 100)}"
            runs = metrics[name]
            summaries = [
                json.loads((out / "runs" / env_id / name / f"seed-{r['seed']}" / "summary.json").read_text())
                for r in runs
            ]
            share = spread([s["coach_step_fraction"] for s in summaries], ".1%")
            run_len = spread([s["agent_steps"] / max(s["interventions"], 1) for s in summaries], ".1f")
            falls = spread([float(r["falls"]) for r in runs], "g")
            score = spread([float(r["final_score"]) for r in runs], ".1f")
            rows.append(f"| {view} | {h} | {share} | {run_len} | {falls} | {score} | {len(runs)} |")
    return rows


def depth_note(env_id: str) -> str:
    """How the hand-back fractions map to the shipped region's cell depths."""
    region = load_region(load_spec(ROOT / "tuning" / f"{env_id}.pidlab-rescue.toml"))
    d = region.max_depth
    picks = ", ".join(f"{h}: depth > {math.floor((1 - h) * d)}" for h in HANDBACKS)
    return (
        f"The shipped region's deepest cell lies {d} cells from its edge (chessboard distance), and a "
        f"hand-back fraction f hands back in the cells deeper than floor((1 - f) {d}) ({picks}); "
        "fractions that give the same depth are the same rule."
    )


def section(env_id: str, args: argparse.Namespace, presets: list[str], choices: list[str]) -> str:
    """The markdown section."""
    cmd = (f".venv/bin/python benchmarks/room_choices.py --env {env_id} --seeds {args.seeds} "
           f"--steps {args.steps} --episodes {args.episodes}")  # fmt: skip
    return "\n".join([
        START,
        f"Measured with `{cmd}` ({env_id}).",
        "",
        "| coach preset | rescue region: coverage | grid cells marked | "
        "validation: failures of fresh states | coach-alone falls (env resets) |",
        "|---|---|---|---|---|",
        *presets,
        "",
        f"Hand-back choices, room coach, predictive trigger: medians over {args.seeds} seeds of "
        f"{args.steps:,} env steps, the lowest and highest seed in parentheses (the experiment's report "
        f"and runs: docs/results/room-choices-{env_id}).",
        "",
        "| view | hand-back fraction | coach share of env steps | agent steps per takeover | "
        "falls during training | agent-alone score at the end | runs |",
        "|---|---|---|---|---|---|---|",
        *choices,
        "",
        depth_note(env_id),
        END,
    ])  # fmt: skip


def main() -> None:
    p = Parser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="InvertedPendulum-v5")
    p.add_argument("--seeds", type=count, default=3)
    p.add_argument("--steps", type=count, default=20000)
    p.add_argument("--episodes", type=count, default=10)
    args = p.parse_args()
    presets = preset_rows(args.env, args.episodes)
    out = run_choices(args.env, args.seeds, args.steps)
    choices = choice_rows(out, args.env)
    publish(out, args.env)
    text = section(args.env, args, presets, choices)
    print(text)
    doc = DOC.read_text()
    if START not in doc:
        sys.exit(f"{DOC}: no {START} marker")
    new = re.sub(re.escape(START) + ".*?" + re.escape(END), lambda _: text, doc, flags=re.S)
    atomic_write_text(DOC, new)


if __name__ == "__main__":
    run(main)
