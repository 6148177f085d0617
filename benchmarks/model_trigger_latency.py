"""What the model predictor's veto costs per agent step, against the env's control period.

A trigger a real system could run must answer within one control period. The model predictor asks,
for the forecast of each agent action, whether the whole box of the forecast's margins lies in the
rescue region: a lookup grid answers cell by cell, a classifier region bounds its network's score
over the box and halves a box it cannot prove, up to 8 times (pidlab.region.forecast). That bound is
the cost measured here, on one thread (torch's and the BLAS library's), one query at a time as the
trigger asks it.

For each shipped spec with a classifier region and a forecast measurement, ``--queries`` forecasts
are drawn uniformly in the rescue region (where every query needs the bound; a forecast outside it
is refused by one score) and asked one at a time, after ``--warm`` unmeasured queries, once with
the spec's own settings (no cap on a query's boxes) and once per cap in ``--pieces`` (the same
forecasts: at most that many boxes bounded at one halving, a box that needs more counts as
unproven, so a query bounds fewer than twice that many). The table gives the share proven (the
margin box inside), and the wall time per query: median, 99th percentile and largest (ms), and the
env's control period (ms). A spec with adaptive margins asks each forecast with the margins of one
made from that point with the operating point's control (the scale network's time is counted). The
section "What the model predictor's veto costs" of docs/rescue.md is written between its markers.

Run: .venv/bin/python benchmarks/model_trigger_latency.py [--queries 400] [--warm 20] [--pieces 64,16]
"""

from __future__ import annotations

import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
from bench_cli import Parser, count, counts, run
from threadpoolctl import threadpool_limits

from pidlab import __version__
from pidlab.controller.spec import load_spec
from pidlab.files import atomic_write_text
from pidlab.plant.model import load_model
from pidlab.provenance import git_state
from pidlab.region.forecast import ClassifierMarginRegion, classifier_points, kept_inputs, spec_forecast
from pidlab.region.takeover import region_from_bounds
from pidlab.rl.coaching import model_region

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "rescue.md"
START, END = "<!-- trigger-latency -->", "<!-- /trigger-latency -->"
SPECS = (
    ("InvertedPendulum-v5", "pidlab-rescue-edge-model"),
    ("InvertedPendulum-v5", "pidlab-rescue-edge-scoped"),
    ("InvertedDoublePendulum-v5", "pidlab-rescue-full-learned"),
    ("InvertedDoublePendulum-v5", "pidlab-rescue-full-scoped"),
    ("Hopper-v5", "pidlab-room-focus-learned-blind"),
    ("Hopper-v5", "pidlab-room-focus-adaptive"),
)
"""(env, spec in tuning/) per row: the classifier regions with a forecast measurement."""


def measure(env: str, name: str, queries: int, warm: int, pieces: int | None) -> dict[str, float]:
    """Proven share and per-query times (ms) of one spec's model predictor, on one thread.

    ``pieces``: the cap on a query's boxes at one halving (None: the spec's own, no cap).
    """
    spec = load_spec(ROOT / "tuning" / f"{env}.{name}.toml")
    loaded = load_model(env)
    region = region_from_bounds(spec.bounds, loaded.require_card().observation_names, "rescue", spec.name)
    shrunk = model_region(spec, loaded, region)
    if not isinstance(shrunk, ClassifierMarginRegion):
        raise TypeError(f"{name}: not a classifier region")
    if pieces is not None:
        full = spec_forecast(spec.bounds, spec.name).margin  # adaptive margins index the forecast's order
        shrunk = ClassifierMarginRegion(shrunk.region, full, shrunk.bound, pieces, shrunk.adaptive)
    points = classifier_points(shrunk.classifier, shrunk.threshold, queries + warm, np.random.default_rng(0))
    inputs_of = kept_inputs(region, loaded) if shrunk.adaptive is not None else None
    z = inputs_of(points) if inputs_of is not None else [None] * len(points)  # a forecast made there
    times, proven = [], []
    for i, (y, zi) in enumerate(zip(points, z, strict=True)):
        start = time.perf_counter()
        inside = bool(shrunk.hold(y, None if zi is None else zi[None, :])[0])
        if i >= warm:
            times.append(1e3 * (time.perf_counter() - start))
            proven.append(inside)
    t = np.array(times)
    return {
        "queries": len(t), "proven": float(np.mean(proven)), "median": float(np.median(t)),
        "p99": float(np.percentile(t, 99)), "max": float(t.max()), "period": 1e3 * loaded.control_dt,
    }  # fmt: skip


def table(queries: int, warm: int, caps: list[int]) -> str:
    """The Markdown table, one row per spec and cap."""
    head = (
        "| env | spec | boxes per halving at most | queries | margin box proven inside | "
        "per query: median (ms) | 99th percentile (ms) | largest (ms) | control period (ms) |\n"
        "|---|---|---|---|---|---|---|---|---|"
    )
    rows = []
    with threadpool_limits(limits=1):
        for env, name in SPECS:
            for pieces in (None, *caps):
                m = measure(env, name, queries, warm, pieces)
                cap = "no cap (the spec's)" if pieces is None else f"{pieces}"
                rows.append(
                    f"| {env} | {name} | {cap} | {m['queries']:,} | {100 * m['proven']:.1f} % | "
                    f"{m['median']:.2f} | {m['p99']:.2f} | {m['max']:.2f} | {m['period']:g} |"
                )
                print(rows[-1], flush=True)
    return "\n".join([head, *rows])


def main(argv: list[str]) -> int:
    """Measure, print and write the section."""
    p = Parser(description=__doc__.splitlines()[0])
    p.add_argument("--queries", type=count, default=400, help="measured queries per spec")
    p.add_argument("--warm", type=count, default=20, help="unmeasured queries first")
    p.add_argument(
        "--pieces", type=counts, default=[64, 16], help="caps on a query's boxes per halving, e.g. 64,16"
    )
    args = p.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    load = os.getloadavg()[0]  # what else ran: the times are only as clean as the machine
    body = table(args.queries, args.warm, args.pieces)
    git = git_state()
    sha = (git.get("sha") or "unknown")[:10] if isinstance(git, dict) else "unknown"
    how = (
        f"Measured by `.venv/bin/python benchmarks/model_trigger_latency.py --queries {args.queries} "
        f"--warm {args.warm} --pieces {','.join(map(str, args.pieces))}` "
        f"(pidlab {__version__}, git {sha}, {platform.machine()}, "
        f"{os.cpu_count()} cores, one thread; load average {load:.2f} when it started)."
    )
    text = PAGE.read_text()
    start, end = text.index(START) + len(START), text.index(END)
    atomic_write_text(PAGE, text[:start] + "\n" + how + "\n\n" + body + "\n" + text[end:])
    return 0


if __name__ == "__main__":
    run(lambda: main(sys.argv[1:]))
