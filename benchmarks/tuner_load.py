"""How many browser tabs the tuner serves at once, under a flood of page requests; and its shutdown.

One server (``pidlab tune ENV --ui``, the real command line in a subprocess), driven by
:class:`pidlab.app.browser.TunerClient`: it speaks Bokeh's websocket protocol as the page's
JavaScript does (request the page, open the websocket, pull the document, say it is ready)
but draws nothing, so the figures are the server's. Phases, all bounded:

1. **Tabs alone**: ``--tabs`` tabs open at the same moment; each is timed from its page request
   until the tuner's views (the margins table) have arrived. Then each tab moves its Kp slider
   ``--moves`` times, one move a second, timed until the new margins table arrives.
2. **Under load**: ``--clients`` HTTP clients request the page in a loop for ``--seconds`` s (as
   the flood of a load test); after 2 s, ``--tabs`` more tabs open at the same moment.
3. **Memory**: the server's resident set before, at its peak, and ``--settle`` s after the load.
4. **Kill**: the server is killed with SIGKILL while its tabs are open and its worker processes
   busy; timed until every process it started is gone.

Writes ``docs/tuner-load.md``. Takes about a minute and a half.

    .venv/bin/python benchmarks/tuner_load.py [--tabs 5] [--clients 20] [--seconds 20]
"""

from __future__ import annotations

import argparse
import asyncio
import datetime as _dt
import math
import os
import platform
import signal
import statistics
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from bench_cli import Parser, count, positive, seconds
from bench_cli import run as run_script

from pidlab.app.browser import TunerClient, free_port, start_server, stop_server
from pidlab.files import atomic_write_text
from pidlab.provenance import git_state

ROOT = Path(__file__).resolve().parents[1]
ENV = "InvertedPendulum-v5"
OPEN_TIMEOUT_S = 30.0


def pct(values: list[float], q: float) -> float:
    """The q-quantile (0..1) of ``values``, nearest rank (nan when empty)."""
    s = sorted(values)
    return s[min(len(s) - 1, max(0, round(q * (len(s) - 1))))] if s else math.nan


def rss_mb(pid: int) -> float:
    """Resident set of process ``pid``, MB (nan when it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return math.nan


def descendants(pid: int) -> dict[int, str]:
    """The processes started by ``pid`` (children, grandchildren...), with their command lines."""
    parents: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
                parents[int(entry.name)] = int(stat.rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
    found: dict[int, str] = {}
    frontier = [pid]
    while frontier:
        p = frontier.pop()
        for child, parent in parents.items():
            if parent == p and child not in found:
                cmd = Path(f"/proc/{child}/cmdline").read_bytes().replace(b"\0", b" ")
                found[child] = cmd.decode(errors="replace")
                frontier.append(child)
    return found


def alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, waiting to be reaped, has ended)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


@dataclass
class Tabs:
    """Opening times (s) of the tabs that opened, and how many did not within the timeout.

    ``usable``: until a tab's controls and numbers (the margins table) arrived; ``opened``: until
    its plots had arrived too.
    """

    opened: list[float] = field(default_factory=list)
    usable: list[float] = field(default_factory=list)
    failed: int = 0
    clients: list[TunerClient] = field(default_factory=list)


async def open_tabs(url: str, n: int) -> Tabs:
    """Open ``n`` tabs at the same moment."""
    clients = [TunerClient(url) for _ in range(n)]
    results = await asyncio.gather(*(c.open(OPEN_TIMEOUT_S) for c in clients), return_exceptions=True)
    tabs = Tabs()
    for c, r in zip(clients, results, strict=True):
        if isinstance(r, float):
            tabs.opened.append(r)
            tabs.usable.append(c.usable_s)
            tabs.clients.append(c)
        else:
            tabs.failed += 1
            c.close()
    return tabs


async def move_sliders(clients: list[TunerClient], moves: int) -> list[float]:
    """Each tab moves its Kp slider ``moves`` times, one move a second; seconds until the new table."""

    async def one(c: TunerClient) -> list[float]:
        kp = c.models["pidlab-slider-kp"]
        out = []
        for i in range(moves):
            t0 = time.perf_counter()
            await c.set_value("pidlab-slider-kp", kp["value"] + (1 + i % 5) * kp["step"])
            await asyncio.wait_for(c.wait_for("margins-table"), OPEN_TIMEOUT_S)
            out.append(time.perf_counter() - t0)
            await asyncio.sleep(1.0)
        return out

    per_tab = await asyncio.gather(*(one(c) for c in clients))
    return [t for ts in per_tab for t in ts]


async def flood(url: str, clients: int, seconds: float) -> tuple[list[float], dict[int, int]]:
    """``clients`` HTTP clients request the page in a loop for ``seconds``: latencies (s), status counts."""
    from tornado.httpclient import AsyncHTTPClient

    http = AsyncHTTPClient(force_instance=True, max_clients=clients)
    latencies: list[float] = []
    codes: dict[int, int] = {}
    deadline = time.monotonic() + seconds

    async def client() -> None:
        while time.monotonic() < deadline:
            t0 = time.perf_counter()
            r = await http.fetch(url, raise_error=False, request_timeout=60)
            latencies.append(time.perf_counter() - t0)
            codes[r.code] = codes.get(r.code, 0) + 1

    await asyncio.gather(*(client() for _ in range(clients)))
    http.close()
    return latencies, codes


async def sample_rss(pid: int, peak: list[float], stop: asyncio.Event) -> None:
    """Keep the largest resident set of ``pid`` in ``peak[0]`` until ``stop``."""
    while not stop.is_set():
        peak[0] = max(peak[0], rss_mb(pid))
        await asyncio.sleep(0.25)


def kill_and_time(pid: int) -> dict[str, float]:
    """SIGKILL ``pid``; seconds until each kind of process it started is gone (``nan``: still there)."""
    kids = descendants(pid)
    kinds = {
        k: "resource tracker" if "resource_tracker" in cmd else "worker or manager" for k, cmd in kids.items()
    }
    t0 = time.perf_counter()
    os.kill(pid, signal.SIGKILL)
    gone: dict[int, float] = {}
    while len(gone) < len(kids) and time.perf_counter() - t0 < 15.0:
        for k in kids:
            if k not in gone and not alive(k):
                gone[k] = time.perf_counter() - t0
        time.sleep(0.01)
    out: dict[str, float] = {}
    for k, kind in kinds.items():
        out[kind] = max(out.get(kind, 0.0), gone.get(k, math.nan))
    out["processes"] = float(len(kids))
    return out


@dataclass
class Results:
    """Everything the page reports."""

    alone: Tabs
    moves: list[float]
    loaded: Tabs
    latencies: list[float]
    codes: dict[int, int]
    rss: tuple[float, float, float]
    kill: dict[str, float]
    load_avg: tuple[float, float, float]


async def run(url: str, pid: int, args: argparse.Namespace) -> Results:
    """Phases 1-3 against a running server; closes the tabs of phase 2 and keeps phase 1's open."""
    before = rss_mb(pid)
    peak, stop = [before], asyncio.Event()
    sampler = asyncio.ensure_future(sample_rss(pid, peak, stop))
    alone = await open_tabs(url, args.tabs)
    moves = await move_sliders(alone.clients, args.moves)

    async def late_tabs() -> Tabs:
        await asyncio.sleep(2.0)
        return await open_tabs(url, args.tabs)

    for c in alone.clients:  # a closed tab frees its place at once (the server serves 8 at most)
        c.close()
    (latencies, codes), loaded = await asyncio.gather(flood(url, args.clients, args.seconds), late_tabs())
    await asyncio.sleep(args.settle)
    stop.set()
    await sampler
    # the tabs opened under load stay open: a slider move keeps their background jobs busy
    for c in loaded.clients:
        await c.set_value("pidlab-slider-kp", c.models["pidlab-slider-kp"]["value"] * 1.01)
    await asyncio.sleep(1.0)
    after = rss_mb(pid)
    kill = kill_and_time(pid)  # with the tabs open
    return Results(alone, moves, loaded, latencies, codes, (before, peak[0], after), kill, os.getloadavg())


def summary(r: Results, args: argparse.Namespace) -> list[str]:
    """The page's table rows and the console lines."""

    def tabs(t: Tabs) -> str:
        ok = f"{len(t.opened)}/{len(t.opened) + t.failed}"
        if not t.opened:
            return f"{ok} | — | — |"
        usable = f"{statistics.median(t.usable):.2f} / {max(t.usable):.2f}"
        return f"{ok} | {usable} | {statistics.median(t.opened):.2f} / {max(t.opened):.2f} |"

    pages = len(r.latencies)
    codes = ", ".join(f"{n} × {c}" for c, n in sorted(r.codes.items()))
    moves = "—"
    if r.moves:
        moves = f"{statistics.median(r.moves) * 1000:.0f} ms / {pct(r.moves, 0.9) * 1000:.0f} ms"
    workers, tracker = r.kill.get("worker or manager", math.nan), r.kill.get("resource tracker", math.nan)
    return [
        "| phase | tabs opened | controls and numbers arrived, median / slowest (s) "
        "| plots too, median / slowest (s) |",
        "|---|---|---|---|",
        f"| {args.tabs} tabs at once, alone | {tabs(r.alone)}",
        f"| {args.tabs} tabs at once, under {args.clients} HTTP clients | {tabs(r.loaded)}",
        "",
        "| measure | value |",
        "|---|---|",
        f"| Kp slider move -> new margins table, median / p90 over {len(r.moves)} moves "
        f"({args.tabs} tabs open) | {moves} |",
        f"| page requests by {args.clients} HTTP clients in {args.seconds:g} s | {pages} "
        f"({pages / args.seconds:.1f} per s; {codes}) |",
        f"| page request latency under that load, median / p90 | {pct(r.latencies, 0.5):.2f} s / "
        f"{pct(r.latencies, 0.9):.2f} s |",
        f"| server memory (RSS): before / peak / {args.settle:g} s after the load | {r.rss[0]:.0f} / "
        f"{r.rss[1]:.0f} / {r.rss[2]:.0f} MB |",
        f"| SIGKILL of the server -> its workers and manager gone | {workers:.2f} s "
        f"({r.kill.get('processes', 0):.0f} processes) |",
        f"| SIGKILL of the server -> multiprocessing's resource tracker gone | {tracker:.2f} s |",
    ]


def main() -> None:
    """Run the phases and write the docs page."""
    ap = Parser(description=__doc__.splitlines()[0])
    ap.add_argument("--tabs", type=count, default=5, help="tabs opened at the same moment, in each phase")
    ap.add_argument("--moves", type=count, default=5, help="slider moves per tab")
    ap.add_argument("--clients", type=count, default=20, help="HTTP clients of the flood")
    ap.add_argument("--seconds", type=positive, default=20.0, help="length of the flood")
    ap.add_argument(
        "--settle", type=seconds, default=20.0, help="seconds after the flood before memory is read"
    )
    ap.add_argument("--out", default=str(ROOT / "docs"))
    ap.add_argument(
        "--server-path",
        help="run the server from this checkout instead (to compare before and after a change)",
    )
    args = ap.parse_args()
    if args.server_path:  # `python -m pidlab` imports from the working folder first
        os.environ["PYTHONPATH"] = str(Path(args.server_path).resolve())
        os.chdir(args.server_path)
    with tempfile.TemporaryDirectory() as tmp:
        port = free_port()
        spec = ROOT / "tuning" / f"{ENV}.pidlab-robust.toml"
        proc = start_server(ENV, spec, tmp, port, log=Path(tmp) / "server.log")
        try:
            results = asyncio.run(run(f"http://localhost:{port}/", proc.pid, args))
            proc.wait(timeout=30)
        finally:
            if proc.poll() is None:
                stop_server(proc)
        log = (Path(tmp) / "server.log").read_text(errors="replace")
    rows = summary(results, args)
    print("\n".join(rows))
    print(f"tracebacks in the server log: {log.count('Traceback')}; load average {results.load_avg}")
    write_page(Path(args.out), rows, results, args, log.count("Traceback"))


def write_page(out: Path, rows: list[str], r: Results, args: argparse.Namespace, tracebacks: int) -> None:
    """``docs/tuner-load.md``."""
    git = git_state(ROOT)
    sha, dirty = str(git["sha"] or "unknown"), bool(git["dirty"])
    cmd = (
        f"benchmarks/tuner_load.py --tabs {args.tabs} --moves {args.moves} --clients {args.clients} "
        f"--seconds {args.seconds:g} --settle {args.settle:g}"
    )
    lines = [
        "# Tuner under load",
        "",
        f"Generated by `.venv/bin/python {cmd}` on {_dt.date.today().isoformat()} (git {sha[:7]}"
        f"{' + local changes' if dirty else ''}; {platform.machine()}, {os.cpu_count()} cores, Python "
        f"{platform.python_version()}; load average {r.load_avg[0]:.1f} at the end: the machine was shared).",
        "",
        f"One server, `pidlab tune {ENV} --ui`. A *tab* is a client that does what a browser's page does "
        "(request the page, open its websocket, pull the document, say it has loaded) without drawing, "
        "timed from its page request: until the tuner's controls and numbers (the margins table) have "
        "arrived, and until its plots have arrived too. The HTTP clients only request the page, in a "
        "loop, as a load test does.",
        "",
        *rows,
        "",
        f"Tracebacks in the server's log during the run: {tracebacks}.",
        "",
        "How the server copes: a page request only gets a placeholder; the tuner is put in it once the "
        "page has loaded and opened its websocket, so that requests that never open one cost little, and "
        "new pages are made one at a time, leaving the open tabs half of the server's loop. The model and "
        "its linearization are shared by every tab, and five tuners are built ahead while the server is "
        "idle; what remains for each tab is turning its widgets and plots into Bokeh's document and "
        "sending it (about 0.4 s of one core here): tabs that open together get their controls first, "
        "one after the other, then their plots. At most 8 tabs are served at once; a further tab gets "
        "a page that says so. See [tuner.md](tuner.md).",
        "",
    ]
    atomic_write_text(out / "tuner-load.md", "\n".join(lines))
    print(f"wrote {out / 'tuner-load.md'}")


if __name__ == "__main__":
    run_script(main)
