"""Rescue coverage over each env's termination domain, and the falls while the coach acts: docs/rescue.md.

For each env, each coach below is scored with :func:`pidlab.region.coverage.measure_domain_coverage`
(the same as ``pidlab rescue-coverage``) over one domain per env, the same states for every coach:
the env's termination domain (and its joints' ranges), cut by a box on the rates. A coach that was
trained with is read from the published run folder itself (its ``coach.toml``, the same in every
seed), and the run folder's ``episodes.csv`` files give the falls while the coach acted: under the
``terminal`` view a takeover ends the agent's episode, so a fall in an episode with a takeover
happened under the coach. The figures go to docs/results/coverage/ENV.json, the table into
docs/rescue.md between ``<!-- coverage-table -->`` and ``<!-- /coverage-table -->``.

Run: .venv/bin/python benchmarks/coverage_table.py [--envs Hopper-v5] [--states 20000] [--workers 2]
[--new-only]
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, replace
from pathlib import Path

import tomllib
from bench_cli import Parser, count, names, run
from run_accounts import falls_under_coach

from pidlab.controller.spec import load_spec
from pidlab.files import atomic_write_text, write_json
from pidlab.plant.model import load_model
from pidlab.region.coverage import MODEL_KIND, DomainCoverage, DomainSettings, measure_domain_coverage

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "rescue.md"
OUT = ROOT / "docs" / "results" / "coverage"
START, END = "<!-- coverage-table -->", "<!-- /coverage-table -->"

DOMAINS = {
    # the pole to its termination limit, the cart over its rail; rates as the shipped grid's domain
    "InvertedPendulum-v5": {"hinge_pos": 0.2, "slider_pos": 1.0, "hinge_vel": 4.0, "slider_vel": 1.5},
    # the classifier's domain: the poles as far as the tip-height rule allows, the cart within 0.9 m
    "InvertedDoublePendulum-v5": {
        "slider_pos": 0.9, "hinge_sin": 0.6, "hinge2_sin": 0.9, "slider_vel": 1.0, "hinge_vel": 2.0,
        "hinge2_vel": 2.0,
    },
    # pitch to its termination limit, every leg joint over its range; rates within 2 rad/s, 1 m/s
    "Hopper-v5": {
        "rooty_pos": 0.2, "thigh_joint_pos": 2.62, "leg_joint_pos": 2.62, "foot_joint_pos": 0.79,
        "rootx_vel": 1.0, "rootz_vel": 1.0, "rooty_vel": 2.0, "thigh_joint_vel": 2.0, "leg_joint_vel": 2.0,
        "foot_joint_vel": 2.0,
    },
    "Walker2d-v5": {
        "rooty_pos": 1.0, "thigh_joint_pos": 2.62, "leg_joint_pos": 2.62, "foot_joint_pos": 0.79,
        "thigh_left_joint_pos": 2.62, "leg_left_joint_pos": 2.62, "foot_left_joint_pos": 0.79,
        "rootx_vel": 1.0, "rootz_vel": 1.0, "rooty_vel": 2.0, "thigh_joint_vel": 2.0, "leg_joint_vel": 2.0,
        "foot_joint_vel": 2.0, "thigh_left_joint_vel": 2.0, "leg_left_joint_vel": 2.0,
        "foot_left_joint_vel": 2.0,
    },
}  # fmt: skip


@dataclass(frozen=True)
class Coach:
    """A coach to score: a spec file, and the published runs (folder, condition) trained with it."""

    label: str
    spec: str | None = None
    runs: tuple[str, str] | None = None
    kind: str = "rescue region"
    """The region scored in the table: the rescue region, or it as the model predictor asks it."""
    into: str = "core"
    """Where a rescue ends (``pidlab rescue-coverage --into``): the core, or the horizon's end in the box."""


def _runs(folder: str, env: str, condition: str) -> Path:
    return ROOT / "docs" / "results" / folder / "runs" / env / condition


COACHES = {
    "InvertedPendulum-v5": (
        Coach("room coach, lookup grid", runs=("InvertedPendulum-v5-rescue", "rescue-terminal")),
        Coach("room coach, classifier", runs=("InvertedPendulum-v5-full", "rescue-terminal-full")),
        Coach("room coach, classifier validated at its edge",
              runs=("InvertedPendulum-v5-edge", "rescue-terminal-edge")),
        Coach("room coach, classifier validated at its edge, asked through the linear forecast's margins "
              "(the model predictor)", runs=("InvertedPendulum-v5-edgemodel", "rescue-terminal-edge-model"),
              kind=MODEL_KIND),
        Coach("room coach, classifier validated at its edge, asked through the linear forecast's margins "
              "with the linear bound", "tuning/InvertedPendulum-v5.pidlab-rescue-edge-linear.toml",
              kind=MODEL_KIND),
        Coach("room coach, classifier validated at its edge, asked through the linear forecast's margins "
              "with the linear bound, margins measured where the forecast lies in the region's domain",
              "tuning/InvertedPendulum-v5.pidlab-rescue-edge-scoped.toml", kind=MODEL_KIND),
    ),
    "InvertedDoublePendulum-v5": (
        Coach("room coach, lookup grid + guard box",
              runs=("InvertedDoublePendulum-v5-rescue", "rescue-terminal")),
        Coach("room coach, classifier", runs=("InvertedDoublePendulum-v5-full", "rescue-terminal-full")),
        Coach("room coach, classifier, asked through the learned forecast's margins (the model predictor)",
              runs=("InvertedDoublePendulum-v5-learned", "rescue-terminal-full-learned"), kind=MODEL_KIND),
        Coach("room coach, classifier, asked through the learned forecast's margins with the linear bound",
              "tuning/InvertedDoublePendulum-v5.pidlab-rescue-full-linear.toml", kind=MODEL_KIND),
        Coach("room coach, classifier, asked through the learned forecast's margins with the linear bound, "
              "margins measured where the forecast lies in the region's domain",
              "tuning/InvertedDoublePendulum-v5.pidlab-rescue-full-scoped.toml",
              runs=("InvertedDoublePendulum-v5-scoped", "rescue-terminal-full-scoped"), kind=MODEL_KIND),
    ),
    "Hopper-v5": (
        Coach("robust coach, lookup grid over pitch", runs=("Hopper-v5-rescue", "rescue-terminal")),
        Coach("room coach (gains searched on the env), no region", "tuning/Hopper-v5.pidlab-room.toml"),
        Coach("room coach, no region; rescued only when it holds 3 s and ends in its recoverable box "
              "(pitch and its rate near upright)", "tuning/Hopper-v5.pidlab-room.toml", into="box"),
        Coach("room coach, classifier over pitch, legs and rates (thigh within 0.6 rad, knee 0.8 rad)",
              "tuning/Hopper-v5.pidlab-room-full.toml", runs=("Hopper-v5-room", "rescue-terminal-room-full")),
        Coach("room coach, classifier over pitch, legs and rates, focused fit (80,000 more labels where a "
              "first fit scored high; width 128)", "tuning/Hopper-v5.pidlab-room-focus.toml",
              runs=("Hopper-v5-roomfocus", "rescue-terminal-room-focus")),
        Coach("room coach, classifier over pitch, legs and rates, asked through the learned forecast's "
              "margins with the linear bound, margins measured where the forecast lies in the region's "
              "domain (the model predictor)", "tuning/Hopper-v5.pidlab-room-full-learned.toml",
              kind=MODEL_KIND),
        Coach("room coach, classifier over pitch, legs and rates, focused fit, asked through the learned "
              "forecast's margins with the linear bound, margins measured where the forecast lies in the "
              "region's domain (the model predictor; the published runs' measurement, whose network read the "
              "forward position)", runs=("Hopper-v5-roommodel", "rescue-terminal-room-focus-learned"),
              kind=MODEL_KIND),
        Coach("the same measured again with the forward position left out of the network's inputs",
              "tuning/Hopper-v5.pidlab-room-focus-learned-blind.toml", kind=MODEL_KIND),
        Coach("room coach, classifier over pitch, legs and rates, focused fit, asked through the learned "
              "forecast's adaptive margins (each state's own, with the operating point's control) with the "
              "linear bound (the model predictor)", "tuning/Hopper-v5.pidlab-room-focus-adaptive.toml",
              kind=MODEL_KIND),
    ),
    "Walker2d-v5": (
        Coach("robust coach, lookup grid over pitch", runs=("Walker2d-v5-evidence", "rescue-terminal")),
        Coach("room coach (gains searched on the env), no region", "tuning/Walker2d-v5.pidlab-room.toml"),
        Coach("room coach, no region; rescued only when it holds 3 s and ends in its recoverable box "
              "(pitch and its rate near upright)", "tuning/Walker2d-v5.pidlab-room.toml", into="box"),
        Coach("balance coach (full-state LQR about a bent-knee posture), no region",
              "tuning/Walker2d-v5.pidlab-balance.toml"),
        Coach("balance coach, no region; rescued only when it holds 3 s and ends in its recoverable box",
              "tuning/Walker2d-v5.pidlab-balance.toml", into="box"),
    ),
}  # fmt: skip


def spec_file(env: str, coach: Coach) -> Path:
    """The spec scored: the runs' own ``coach.toml`` (checked the same in every seed), else a file.

    A coach given both (a file, then runs trained with it) is scored from the file, which must be
    the runs' ``coach.toml`` to the byte.
    """
    if coach.runs is None:
        return ROOT / str(coach.spec)
    if coach.spec is not None:
        path = ROOT / coach.spec
        if spec_file(env, Coach(coach.label, None, coach.runs)).read_bytes() != path.read_bytes():
            raise SystemExit(f"{coach.spec}: not the coach.toml of {coach.runs}")
        return path
    seeds = sorted(_runs(coach.runs[0], env, coach.runs[1]).glob("seed-*/coach.toml"))
    if not seeds or len({p.read_bytes() for p in seeds}) != 1:
        raise SystemExit(f"{coach.runs}: expected one coach.toml shared by every seed ({len(seeds)} files)")
    return seeds[0]


@dataclass(frozen=True)
class Training:
    """Falls while the coach acted and the coach's share of env steps, over a condition's runs."""

    runs: int
    falls: int
    coach_falls: tuple[int, ...]
    coach_share: float


def training(env: str, folder: str, condition: str) -> Training:
    """The condition's ``episodes.csv`` files (``terminal`` view: a takeover ends the agent's episode)."""
    per_run, falls, coach_steps, env_steps = [], 0, 0, 0
    paths = sorted(_runs(folder, env, condition).glob("seed-*/episodes.csv"))
    for path in paths:
        coaching = tomllib.loads((path.parent / "config.toml").read_text())["recipe"]["coaching"]
        if coaching.get("view") != "terminal":  # elsewhere a takeover does not end the agent's episode
            raise SystemExit(f"{path.parent}: falls under the coach are counted for the terminal view only")
        with open(path, newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
        per_run.append(falls_under_coach(rows))
        falls += sum(int(r["fell"]) for r in rows)
        coach_steps += sum(int(r["coach_steps"]) for r in rows)
        env_steps += sum(int(r["coach_steps"]) + int(r["agent_steps"]) for r in rows)
    return Training(len(paths), falls, tuple(per_run), coach_steps / max(env_steps, 1))


def _pct(x: float) -> str:
    return f"{100 * x:.1f} %"


def row(env: str, coach: Coach, c: DomainCoverage) -> str:
    """One table row (printed as it is measured)."""
    r = c.score(coach.kind)
    region = "-" if r is None else f"**{_pct(r.coverage)}**"
    lo, hi = (float("nan"),) * 2 if r is None else r.false_claims_ci
    false = "-" if r is None or not r.inside else f"{_pct(r.false_claims)} [{100 * lo:.1f}, {100 * hi:.1f}]"
    rescuable = f"{c.rescuable:,} of {c.settings.states:,} ({_pct(c.rescuable_share)})"
    train = "not trained with"
    if coach.runs is not None:
        t = training(env, *coach.runs)
        runs = sorted(t.coach_falls)
        falls = (
            f"no fall in {t.runs} runs" if not t.falls
            else f"{sum(runs):,} of the {t.falls:,} falls of {t.runs} runs (per run {runs[0]:,}-{runs[-1]:,})"
        )  # fmt: skip
        train = (
            f"`{coach.runs[1]}` ({coach.runs[0]}): {falls}; the coach ran {_pct(t.coach_share)} of "
            "the env steps (all runs pooled)"
        )
    return f"| {env} | {coach.label} | {rescuable} | {region} | {false} | {train} |"


def measure(env: str, states: int, workers: int | None, new_only: bool = False) -> list[str]:
    """Score ``env``'s coaches on the same states; write their JSON; the table rows.

    ``new_only``: score only the coaches appended to :data:`COACHES` since the env's JSON was written,
    on the same states (the JSON's settings must be these), and keep the rows already measured.
    """
    loaded = load_model(env)
    box = DOMAINS[env]
    settings = DomainSettings(tuple(box), tuple(box.values()), states=states)
    found = _measured_before(env, settings) if new_only else []
    lines = []
    for coach in COACHES[env][len(found):]:
        path = spec_file(env, coach)
        mine = replace(settings, into=coach.into)
        c = measure_domain_coverage(load_spec(path), loaded, mine, workers=workers)
        found.append({"label": coach.label, "spec_file": str(path.relative_to(ROOT)), **c.to_dict()})
        lines.append(row(env, coach, c))
        print(lines[-1], f"({c.elapsed_s:.0f} s)", flush=True)
    OUT.mkdir(parents=True, exist_ok=True)
    write_json(OUT / f"{env}.json", found)
    return lines


def _measured_before(env: str, settings: DomainSettings) -> list[dict]:
    """The env's JSON rows, checked to be the first coaches of :data:`COACHES` on ``settings``' states."""
    path = OUT / f"{env}.json"
    rows = json.loads(path.read_text()) if path.exists() else []
    for d, coach in zip(rows, COACHES[env], strict=False):
        s = _coverage_of(d).settings
        same = (s.variables, s.half_range, s.states, s.seed, s.horizon_s) == (
            settings.variables, settings.half_range, settings.states, settings.seed, settings.horizon_s)
        if d["label"] != coach.label or not same:
            raise SystemExit(
                f"{path}: row {d['label']!r} is not {coach.label!r} on these states; measure all"
            )
    if len(rows) > len(COACHES[env]):
        raise SystemExit(f"{path}: more rows than coaches; measure all")
    return rows


def main() -> None:
    parser = Parser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--envs", type=names(DOMAINS), default=",".join(DOMAINS), help="Comma-separated envs (default: all)"
    )
    parser.add_argument("--states", type=count, default=20_000, help="States per env (default 20,000).")
    parser.add_argument("--workers", type=count, default=None, help="Worker processes (default: the cores).")
    parser.add_argument("--table-only", action="store_true", help="Rebuild the table from the JSON files.")
    parser.add_argument(
        "--new-only", action="store_true",
        help="Score only the coaches added since an env's JSON, on its states.",
    )
    args = parser.parse_args()
    for env in [] if args.table_only else args.envs.split(","):
        measure(env, args.states, args.workers, args.new_only)
    lines = [line for env in DOMAINS for line in _rows_from_json(env)]
    head = [
        "| env | coach and region | states the coach rescues (termination domain) | coverage: rescue region "
        "| false claims of the region [95 %] | training under the region: falls while the coach acted |",
        "|---|---|---|---|---|---|",
    ]
    text = PAGE.read_text(encoding="utf-8")
    i, j = text.index(START) + len(START), text.index(END)
    command = f"`.venv/bin/python benchmarks/coverage_table.py --states {args.states}`"
    block = f"\nMeasured with {command} (figures: docs/results/coverage/ENV.json).\n\n"
    block += "\n".join(head + lines) + "\n"
    reach = [line for env in DOMAINS for line in _reach_rows(env)]
    if reach:
        block += "\n" + "\n".join([*REACH_HEAD, *reach]) + "\n"
    atomic_write_text(PAGE, text[:i] + block + text[j:])
    print(f"wrote the table into {PAGE}")


def _rows_from_json(env: str) -> list[str]:
    """The rows of an env already measured (its JSON), so that one env can be re-measured alone."""
    path = OUT / f"{env}.json"
    if not path.exists():
        return []
    out = []
    for d, coach in zip(json.loads(path.read_text()), COACHES[env], strict=True):
        out.append(row(env, coach, _coverage_of(d)))
    return out


REACH_HEAD = (
    "Where each coach's rescued states lie: per domain variable, the largest distance of a rescued "
    "state from the operating point, and the 95th percentile, in the variable's units (hinges rad, "
    "their rates rad/s; slides and the root's x and z m, their rates m/s; a sine none). A coach "
    "measured before this was recorded is left out; one coach scored with several regions is listed "
    "once. The last column is the `pidlab rescue-classifier --domain` that holds every rescued state.",
    "",
    "| env | coach | rescued states | largest / 95th percentile distance from the operating point | "
    "classifier domain holding them all |",
    "|---|---|---|---|---|",
)


def _reach_rows(env: str) -> list[str]:
    """One row per distinct coach of ``env`` whose JSON records where its rescued states lie."""
    path = OUT / f"{env}.json"
    if not path.exists():
        return []
    rows, seen = [], set()
    for d, coach in zip(json.loads(path.read_text()), COACHES[env], strict=True):
        c = _coverage_of(d)
        key = (c.rescuable, c.reach)
        if not c.reach or not c.rescuable or key in seen:
            continue
        seen.add(key)
        far = "; ".join(
            f"{v} {a:.2g} / {b:.2g}" for v, a, b in zip(c.settings.variables, c.reach, c.reach95, strict=True)
        )
        rows.append(f"| {env} | {coach.label} | {c.rescuable:,} | {far} | `{c.classifier_domain()}` |")
    return rows


def _coverage_of(d: dict) -> DomainCoverage:
    """A :class:`DomainCoverage` back from its JSON."""
    from pidlab.region.coverage import RegionScore

    s = d["settings"]
    settings = DomainSettings(
        tuple(s["variables"]), tuple(s["half_range"]), s["states"], s["horizon_s"], s["seed"],
        s.get("into", "core"),
    )
    scores = tuple(
        RegionScore(
            x["kind"], x["inside"], x["held"], x["coverage"], x["false_claims"], tuple(x["false_claims_ci"])
        )
        for x in d["scores"]
    )
    return DomainCoverage(d["env_id"], d["spec_name"], settings, d["grounded"], d["rescuable"], scores,
                          d["simulations"], d["elapsed_s"], tuple(d.get("reach", ())),
                          tuple(d.get("reach95", ())))  # fmt: skip


if __name__ == "__main__":
    run(main)
