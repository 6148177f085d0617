"""How fast the tuner's linear views follow a slider, measured in a real browser; and screenshots.

For each env: serve ``pidlab tune ENV --ui``, open it in headless Chromium (Playwright), wait
for the page and its first background results, then press the Kp slider's arrow key N times,
one press every ``--gap`` seconds (so the background ROA and rollout jobs restart after every
change, as when a user tunes by hand). Each press is timed in the page, from the keydown to the
moment both the Bode plot's data and the margins table have changed and a frame was painted.

Writes ``docs/tuner-latency.md`` (the table) and ``docs/images/tuner-ENV.png`` (screenshots).

    .venv/bin/python benchmarks/tuner_latency.py [--presses 30] [--gap 1.0]
"""

from __future__ import annotations

import datetime as _dt
import platform
import re
import statistics
import tempfile
from pathlib import Path

from bench_cli import Parser, count, names, run, seconds

from pidlab.app.browser import CHROMIUM, CHROMIUM_ARGS, PAGE_JS, free_port, start_server, stop_server
from pidlab.files import atomic_write_text
from pidlab.provenance import git_state

ROOT = Path(__file__).resolve().parents[1]
ENVS = ("InvertedPendulum-v5", "InvertedDoublePendulum-v5")


def measure(page, presses: int, gap: float) -> tuple[list[float], list[float], list[float]]:
    """(ms until the Bode data changed, until the table changed, until painted), per press."""
    data, table, painted = [], [], []
    handle = page.locator(".pidlab-slider-kp .noUi-handle")
    for i in range(presses):
        handle.focus()
        page.evaluate("() => { window.__p = window.__measure(); }")
        page.keyboard.press("ArrowRight" if (i // 5) % 2 == 0 else "ArrowLeft")
        r = page.evaluate("() => window.__p")
        if r["data"] is not None:
            data.append(r["data"])
            painted.append(r["painted"])
        if r["table"] is not None:
            table.append(r["table"])
        page.wait_for_timeout(int(gap * 1000))
    return data, table, painted


def server_compute_ms(page) -> float | None:
    """The page's own report of the last update's compute time (ms)."""
    text = page.evaluate("() => window.__text('#closed-loop-summary')") or ""
    m = re.search(r"computed in (\d+) ms", text)
    return float(m.group(1)) if m else None


def pct(values: list[float], q: float) -> float:
    """The q-quantile (0..1) of ``values``, nearest rank."""
    s = sorted(values)
    return s[min(len(s) - 1, max(0, round(q * (len(s) - 1))))]


def main() -> None:
    """Run the measurement and write the docs page and screenshots."""
    ap = Parser(description=__doc__.splitlines()[0])
    ap.add_argument("--presses", type=count, default=30)
    ap.add_argument("--gap", type=seconds, default=1.0, help="seconds between presses")
    ap.add_argument("--envs", type=names(ENVS), default=",".join(ENVS))
    ap.add_argument("--out", default=str(ROOT / "docs"))
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    out = Path(args.out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    rows = []
    with sync_playwright() as p, tempfile.TemporaryDirectory() as tmp:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        for env in args.envs.split(","):
            port = free_port()
            spec = ROOT / "tuning" / f"{env}.pidlab-robust.toml"
            proc = start_server(env, spec, tmp, port, log=Path(tmp) / f"{env}.log")
            try:
                ctx = browser.new_context(viewport={"width": 1600, "height": 1300})
                ctx.add_init_script(PAGE_JS)
                page = ctx.new_page()
                page.goto(f"http://localhost:{port}/")
                page.wait_for_selector("#margins-table", timeout=60_000)
                page.wait_for_function("() => window.__plotted()", timeout=60_000)
                page.wait_for_selector("#rollout-animation", timeout=300_000)
                page.wait_for_function("() => window.__source('roa-paths').xs.length > 0", timeout=300_000)
                page.wait_for_timeout(1000)
                page.screenshot(path=str(out / "images" / f"tuner-{env}.png"), full_page=True)
                data, table, painted = measure(page, args.presses, args.gap)
                compute = server_compute_ms(page)
                rows.append((env, data, table, painted, compute))
                print(
                    f"{env}: slider -> Bode data {statistics.median(data):.0f} ms median, "
                    f"{pct(data, 0.9):.0f} ms p90; -> margins table {statistics.median(table):.0f} ms median "
                    f"({len(table)}/{args.presses} presses changed it); "
                    f"painted {statistics.median(painted):.0f} ms; server compute {compute} ms"
                )
                ctx.close()
            finally:
                stop_server(proc)
        browser.close()
    git = git_state(ROOT)
    sha, dirty = str(git["sha"] or "unknown"), bool(git["dirty"])
    lines = [
        "# Tuner responsiveness",
        "",
        "Generated by `.venv/bin/python benchmarks/tuner_latency.py "
        f"--presses {args.presses} --gap {args.gap}` on {_dt.date.today().isoformat()} "
        f"(git {sha[:7]}{' + local changes' if dirty else ''}; {platform.machine()}, "
        f"{platform.python_version()}; headless Debian Chromium via Playwright).",
        "",
        "Each row: the Kp slider of the first loop moved by one arrow-key step, "
        f"{args.presses} times, one press every {args.gap} s, while the background region-of-attraction "
        "and rollout jobs restart after every change (as when tuning by hand). Times are measured in "
        "the page, from the keydown to the moment the Bode plot's data (and the margins table) changed, "
        "and to the next painted frame.",
        "",
        "| env | Bode data updated, median (ms) | p90 (ms) | max (ms) | margins table updated, median (ms) "
        "| painted, median (ms) | server compute of the last update (ms) |",
        "|---|---|---|---|---|---|---|",
    ]
    for env, data, table, painted, compute in rows:
        lines.append(
            f"| {env} | {statistics.median(data):.0f} | {pct(data, 0.9):.0f} | {max(data):.0f} | "
            f"{statistics.median(table):.0f} ({len(table)}/{args.presses} presses changed it) | "
            f"{statistics.median(painted):.0f} | {compute if compute is not None else '—'} |"
        )
    lines += [
        "",
        "The server compute is the page's own figure (closed loop, margins at every actuator, responses, "
        "Bode grid of 400 points); the rest is the websocket round trip and Bokeh's redraw.",
        "",
        *[f"![tuner on {env}](images/tuner-{env}.png)" for env, *_ in rows],
        "",
    ]
    atomic_write_text(out / "tuner-latency.md", "\n".join(lines))
    print(f"wrote {out / 'tuner-latency.md'}")


if __name__ == "__main__":
    run(main)
