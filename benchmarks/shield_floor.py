"""How much of an untrained agent's run the coach must take: the shields against the exact rescue test.

For each coach, an untrained agent (actions ``N(0, 1)`` per component, clipped to the action range,
as SB3's PPO starts) acts on the env, shielded three ways, each over the same episodes:

1. **exact test, one-step veto** (:func:`pidlab.region.oracle.shield_floor`): an action runs when the
   coach alone rescues the state after it, simulated exactly from that state; otherwise the coach
   acts for that one step. No region and no hand-back rule lets the agent act more often without
   letting it where its coach cannot bring it back: the floor of the coach's share for that coach.
2. **the region, one-step veto**: the condition's own wrapper (the published runs' ``coaching``
   table), with ``mode = "nudge"`` and ``nudge_steps = 1``: the coach replaces the vetoed action only.
3. **the region and its hand-back, as trained**: the published runs' wrapper unchanged.

Between 3 and 2 lies what the hand-back costs, between 2 and 1 what the region's caution costs, and
1 is what the coach itself allows. The last column reads the published runs' share over training
(``coverage_table.training``), where the agent learns. Figures: docs/results/shield-floor/ENV.json
(per episode, so the shares are recomputed from them); the table sits in docs/rescue.md between
``<!-- shield-floor-table -->`` and ``<!-- /shield-floor-table -->``.

Run: .venv/bin/python benchmarks/shield_floor.py [--envs ENV,...] [--episodes 5] [--table-only | --check]
(about 2 minutes on the pendulums, 5 to 10 minutes per coach on Hopper and Walker2d, one core)
"""

from __future__ import annotations

import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
import tomllib
from bench_cli import Parser, count, names, run
from coverage_table import ROOT, Coach, spec_file, training
from tqdm import tqdm

from pidlab.controller.spec import load_spec
from pidlab.files import atomic_write_text
from pidlab.plant.model import load_model
from pidlab.provenance import git_state, package_versions
from pidlab.region.oracle import shield_floor
from pidlab.rl.coaching import CoachingWrapper
from pidlab.rl.recipe import parse_coaching
from pidlab.rl.wrap import wrapper_arguments

PAGE = ROOT / "docs" / "rescue.md"
OUT = ROOT / "docs" / "results" / "shield-floor"
START, END = "<!-- shield-floor-table -->", "<!-- /shield-floor-table -->"
STD = 1.0
"""The untrained agent's action noise (SB3's PPO: log std 0)."""
SEED = 0


@dataclass(frozen=True)
class Row:
    """A coach to measure: the spec (a file, or the published runs' own), and the runs trained with it."""

    coach: Coach
    condition: str | None = None
    """The published runs' condition (None: no region was trained with, the exact test only)."""


COACHES = {
    "InvertedPendulum-v5": (
        Row(Coach("room coach, classifier validated at its edge",
                  runs=("InvertedPendulum-v5-edge", "rescue-terminal-edge")), "rescue-terminal-edge"),
    ),
    "InvertedDoublePendulum-v5": (
        Row(Coach("room coach, classifier", runs=("InvertedDoublePendulum-v5-full", "rescue-terminal-full")),
            "rescue-terminal-full"),
    ),
    "Hopper-v5": (
        Row(Coach("robust coach, lookup grid over pitch", runs=("Hopper-v5-rescue", "rescue-terminal")),
            "rescue-terminal"),
        Row(Coach("room coach, classifier over pitch, legs and rates, focused fit",
                  runs=("Hopper-v5-roomfocus", "rescue-terminal-room-focus")), "rescue-terminal-room-focus"),
    ),
    "Walker2d-v5": (
        Row(Coach("robust coach, lookup grid over pitch", runs=("Walker2d-v5-evidence", "rescue-terminal")),
            "rescue-terminal"),
        Row(Coach("balance coach (full-state LQR about a bent-knee posture), no region",
                  "tuning/Walker2d-v5.pidlab-balance.toml")),
        Row(Coach("balance coach, no region; rescued only when it holds 3 s and ends in its recoverable box",
                  "tuning/Walker2d-v5.pidlab-balance.toml", into="box")),
        Row(Coach("balance coach, no region; rescued only when it enters its certified core (a level set "
                  "about its posture)", "tuning/Walker2d-v5.pidlab-balance-core.toml")),
    ),
}  # fmt: skip


def run_coaching(env: str, row: Row) -> dict:
    """The published runs' ``[recipe.coaching]`` table, the same in every seed."""
    folder, condition = row.coach.runs or ("", "")
    paths = sorted((ROOT / "docs" / "results" / folder / "runs" / env / condition).glob("seed-*/config.toml"))
    tables = [tomllib.loads(p.read_text())["recipe"]["coaching"] for p in paths]
    if not tables or any(t != tables[0] for t in tables):
        raise SystemExit(f"{folder}/{condition}: expected one coaching table shared by every seed")
    return tables[0]


def shielded(env: str, spec_path: Path, coaching: dict, env_steps: int) -> dict:
    """The untrained agent under a condition's wrapper for ``env_steps`` env steps: the accounts."""
    spec = load_spec(spec_path)
    wrapper = CoachingWrapper(gym.make(env), spec, **wrapper_arguments(parse_coaching(coaching, env), True))
    rng = np.random.default_rng(SEED)
    low, high = wrapper.action_space.low, wrapper.action_space.high
    wrapper.reset(seed=SEED)
    while wrapper.total_agent_steps + wrapper.total_coach_steps < env_steps:
        _, _, terminated, truncated, _ = wrapper.step(np.clip(rng.normal(0.0, STD, low.shape), low, high))
        if terminated or truncated:
            wrapper.reset()
    wrapper.close()
    return {
        "agent_steps": wrapper.total_agent_steps, "coach_steps": wrapper.total_coach_steps,
        "falls": wrapper.total_falls, "vetoes": wrapper.total_vetoes,
    }  # fmt: skip


def measure_row(env: str, row: Row, episodes: int) -> dict:
    """One coach's three shields (the two region ones when it has a condition)."""
    path = spec_file(env, row.coach)
    spec, loaded = load_spec(path), load_model(env)
    bar = tqdm(total=episodes, desc=f"{env}: {row.coach.label[:40]}", unit="episode", leave=False)
    floor = shield_floor(spec, loaded, episodes=episodes, std=STD, seed=SEED, into=row.coach.into,
                         progress=lambda n: bar.update(n - bar.n))  # fmt: skip
    bar.close()
    out = {"label": row.coach.label, "spec": str(path.relative_to(ROOT)), "condition": row.condition,
           "floor": asdict(floor)}  # fmt: skip
    if row.condition is not None:
        coaching = run_coaching(env, row)
        steps = floor.steps
        out["coaching"] = coaching
        out["veto"] = shielded(env, path, {**coaching, "mode": "nudge", "nudge_steps": 1}, steps)
        out["trained"] = shielded(env, path, coaching, steps)
    return out


def _share(d: dict) -> float:
    return d["coach_steps"] / max(d["agent_steps"] + d["coach_steps"], 1)


def _pct(x: float) -> str:
    return f"{100 * x:.1f} %"


def row_text(env: str, row: Row, d: dict) -> str:
    """The table row of one coach, from its JSON record."""
    eps = d["floor"]["episodes"]
    steps, coach = sum(e["steps"] for e in eps), sum(e["coach_steps"] for e in eps)
    per = [e["coach_steps"] / e["steps"] for e in eps]
    falls = sum(e["fell"] for e in eps)
    spread = f"{_pct(min(per))} to {_pct(max(per))}"
    floor = f"**{_pct(coach / steps)}** ({spread}); {falls} fall(s) in {len(eps)} episodes"
    has_core = "ellipsoid" in (load_spec(ROOT / d["spec"]).bounds or {})
    criterion = (
        "holds 3 s, ends in its recoverable box"
        if row.coach.into == "box"
        else ("enters its certified core within 3 s" if has_core else "holds 3 s")
    )
    cells = ["-", "-", "-"]
    if row.condition is not None:
        veto, trained = d["veto"], d["trained"]
        t = training(env, *row.coach.runs)
        cells = [
            f"{_pct(_share(veto))}; {veto['falls']} fall(s)",
            f"{_pct(_share(trained))}; {trained['falls']} fall(s)",
            f"{_pct(t.coach_share)} (`{row.condition}`, {t.runs} runs)",
        ]
    return f"| {env} | {row.coach.label} | {criterion} | {steps:,} | {floor} | " + " | ".join(cells) + " |"


HEAD = (
    "| env | coach | rescued when the coach alone | env steps per shield | exact test, one-step veto: "
    "coach share (per episode) | the region, one-step veto: coach share | the region and its hand-back (as "
    "trained): coach share | published runs: coach share over training |\n|---|---|---|---:|---|---|---|---|"
)


def table() -> str:
    """The whole table from the JSON files (rows or envs not measured yet are left out)."""
    lines = []
    for env, rows in COACHES.items():
        path = OUT / f"{env}.json"
        if path.exists():
            records = {d["label"]: d for d in json.loads(path.read_text())["coaches"]}
            lines += [row_text(env, r, records[r.coach.label]) for r in rows if r.coach.label in records]
    return "\n".join([HEAD, *lines])


def page_table() -> str:
    """The table as docs/rescue.md has it."""
    text = PAGE.read_text(encoding="utf-8")
    return text[text.index(START) + len(START) : text.index(END)].strip()


def main() -> int:
    parser = Parser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", type=names(COACHES), default=",".join(COACHES), help="Comma-separated envs")
    parser.add_argument("--episodes", type=count, default=5, help="Episodes per coach (default 5).")
    parser.add_argument("--table-only", action="store_true", help="Rebuild the table from the JSON files.")
    parser.add_argument("--check", action="store_true", help="Exit 1 if the page's table is not the JSONs'.")
    args = parser.parse_args()
    if args.check:
        same = page_table() == table()
        print("docs/rescue.md's shield-floor table " + ("matches" if same else "differs from") + " the JSON")
        return 0 if same else 1
    # the tree as it was when the measurement started (the JSON files it writes change it)
    state = {"std": STD, "seed": SEED, "episodes": args.episodes, "versions": package_versions(),
             "git": git_state(ROOT)}  # fmt: skip
    for env in [] if args.table_only else args.envs.split(","):
        records = [measure_row(env, row, args.episodes) for row in COACHES[env]]
        OUT.mkdir(parents=True, exist_ok=True)
        record = {**state, "coaches": records}
        atomic_write_text(OUT / f"{env}.json", json.dumps(record, indent=1) + "\n")
        print(f"wrote {OUT / f'{env}.json'}")
    text = PAGE.read_text(encoding="utf-8")
    i, j = text.index(START) + len(START), text.index(END)
    atomic_write_text(PAGE, text[:i] + "\n" + table() + "\n" + text[j:])
    print(f"wrote the table into {PAGE}")
    return 0


if __name__ == "__main__":
    run(lambda: sys.exit(main()))
