"""The tuner in a real browser: Debian's Chromium driven by Playwright, against `pidlab tune --ui`.

One server (the real CLI, in a subprocess) for the module; every test opens its own page, so
it gets its own tuner session. The server writes specs into a temporary tuning folder.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from pidlab.app.browser import CHROMIUM, CHROMIUM_ARGS, PAGE_JS, free_port, start_server, stop_server
from pidlab.controller.spec import load_spec

ROOT = Path(__file__).resolve().parents[1]
SPEC = ROOT / "tuning" / "InvertedPendulum-v5.pidlab-robust.toml"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: the test setup (scripts/browser.sh) installs Debian's chromium")
    tuning = tmp_path_factory.mktemp("tuning")
    log = tuning.parent / "server.log"
    port = free_port()
    proc = start_server("InvertedPendulum-v5", SPEC, tuning, port, extra=["--bounds-samples", "100"], log=log)
    yield f"http://localhost:{port}/", tuning, log
    assert stop_server(proc) == 130, log.read_text()[-2000:]  # SIGTERM: a clean stop, as every command


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture
def page(browser, server):
    url, _, log = server
    context = browser.new_context(viewport={"width": 1600, "height": 1300})
    context.add_init_script(PAGE_JS)
    pg = context.new_page()
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.goto(url)
    pg.wait_for_selector("#margins-table", timeout=60_000)
    pg.wait_for_function("() => window.__plotted()", timeout=60_000)
    yield pg
    context.close()
    assert not errors, f"JavaScript errors on the page: {errors}"
    text = log.read_text(errors="replace")
    assert "Traceback" not in text, (
        "the server logged a traceback:\n" + text[text.index("Traceback") - 300 :][:4000]
    )


def _text(pg, selector: str) -> str:
    return str(pg.evaluate("(sel) => window.__text(sel)", selector) or "")


def _table(pg) -> str:
    return _text(pg, "#margins-table")


def _source(pg, name: str, column: str) -> list[float]:
    return pg.evaluate(f"() => Array.from(window.__source('{name}')['{column}'])")


def _field(pg, field: str):
    return pg.locator(f".pidlab-input-{field} input")


def _message(pg, field: str) -> str:
    return _text(pg, f".pidlab-msg-{field}").strip()


def _move_slider(pg, field: str, presses: int = 5, key: str = "ArrowRight") -> None:
    handle = pg.locator(f".pidlab-slider-{field} .noUi-handle")
    handle.focus()
    for _ in range(presses):
        pg.keyboard.press(key)


def _wait_changed(pg, selector: str, before: str, timeout: float = 10_000) -> None:
    pg.wait_for_function(
        "([sel, before]) => window.__text(sel) !== null && window.__text(sel) !== before",
        arg=[selector, before],
        timeout=timeout,
    )


def _type(pg, field: str, text: str) -> None:
    box = _field(pg, field)
    box.fill(text)
    box.press("Enter")


def _click(pg, css: str) -> None:
    pg.locator(f"{css} button").click()


def test_slider_changes_margins_table_and_redraws_plots(page):
    pg = page
    table0 = _table(pg)
    bode0 = _source(pg, "bode-mag", "db")
    step0 = _source(pg, "step", "y")
    poles0 = _source(pg, "poles", "re")
    shot0 = pg.locator(".bk-Figure").first.screenshot()
    kp0 = float(_field(pg, "kp").input_value())
    _move_slider(pg, "kp", presses=8)
    _wait_changed(pg, "#margins-table", _table(pg))
    # the numeric field follows the slider, and the loop got stiffer
    kp1 = float(_field(pg, "kp").input_value())
    assert kp1 > kp0
    assert _table(pg) != table0
    pg.wait_for_function("(b) => window.__source('bode-mag').db[0] !== b", arg=bode0[0], timeout=5000)
    # the views arrive in separate websocket messages: wait for each before comparing it
    # compared number by number: a JSON text comparison can differ on formatting alone (Python
    # writes 1e-07 where JavaScript writes 1e-7) and stop the wait before the view has arrived
    changed = (
        "([n, c, b]) => { const a = Array.from(window.__source(n)[c]); "
        "return a.length !== b.length || a.some((v, i) => v !== b[i]); }"
    )
    for name, column, before in (("step", "y", step0), ("poles", "re", poles0)):
        pg.wait_for_function(changed, arg=[name, column, list(before)], timeout=5000)
    assert _source(pg, "bode-mag", "db") != bode0
    assert _source(pg, "step", "y") != step0
    assert _source(pg, "poles", "re") != poles0
    pg.wait_for_timeout(300)  # let the canvas repaint
    assert pg.locator(".bk-Figure").first.screenshot() != shot0


def test_background_views_arrive_with_progress(page):
    pg = page
    pg.wait_for_selector("#rollout-animation", timeout=120_000)
    assert pg.locator("#rollout-animation").get_attribute("data-backend") in ("mujoco", "schematic")
    pg.wait_for_function("() => /mean return/.test(window.__text('#coach-score') || '')", timeout=120_000)
    score = _text(pg, "#coach-score")
    assert "mean return 1000.0" in score  # the robust coach balances all 5 episodes
    # the status that describes the preview is written after the preview's paths (the tuner's
    # _say(after_plot=True)): once it says so, the paths are already there
    pg.wait_for_function("() => /preview/.test(window.__text('.pidlab-status-roa') || '')", timeout=120_000)
    assert pg.evaluate("() => window.__source('roa-paths').xs.length") > 0
    status = _text(pg, ".pidlab-status-roa")
    assert "preview" in status and "failures" in status
    # a change starts the slow views again: a visible waiting/progress state ...
    _move_slider(pg, "kd", presses=3)
    busy = "() => /waiting|starting|bisection|final check|level estimate/.test(window.__text('.pidlab-status-roa'))"
    pg.wait_for_function(busy, timeout=5000)
    # ... during which the page keeps answering: the linear views follow another slider move
    table = _table(pg)
    _move_slider(pg, "kp", presses=8)
    _wait_changed(pg, "#margins-table", table, timeout=5000)
    assert pg.evaluate(busy) or "preview" in _text(pg, ".pidlab-status-roa")


def test_save_then_load_back_identical(page, server):
    pg = page
    _, tuning, _ = server
    name = pg.locator(".pidlab-name input")
    name.fill("uitest")
    name.press("Enter")
    _click(pg, ".pidlab-save")
    pg.wait_for_function("() => (window.__text('.pidlab-file-msg') || '').includes('saved')", timeout=10_000)
    path = tuning / "InvertedPendulum-v5.uitest.toml"
    saved = path.read_bytes()
    # unchanged gains: the starting spec under a new name, bounds and provenance kept
    assert load_spec(path) == replace(load_spec(SPEC), name="uitest")
    kp_saved = _field(pg, "kp").input_value()
    # change a gain, then load the file back
    table = _table(pg)
    _move_slider(pg, "kp", presses=10)
    _wait_changed(pg, "#margins-table", table)
    assert _field(pg, "kp").input_value() != kp_saved
    pg.locator(".pidlab-load-select select").select_option("InvertedPendulum-v5.uitest.toml")
    _click(pg, ".pidlab-load")
    pg.wait_for_function("() => (window.__text('.pidlab-file-msg') || '').includes('loaded')", timeout=10_000)
    pg.wait_for_function("(v) => window.__input('.pidlab-input-kp').value === v", arg=kp_saved, timeout=5000)
    # saving what was loaded writes the same bytes
    _click(pg, ".pidlab-save")
    pg.wait_for_function("() => (window.__text('.pidlab-file-msg') || '').includes('saved')", timeout=10_000)
    assert path.read_bytes() == saved
    # an edited coach is saved without the bounds (not certified for it) and says it was edited
    _type(pg, "kd", "1.1")
    name.fill("uitest-edited")
    name.press("Enter")
    _click(pg, ".pidlab-save")
    edited = tuning / "InvertedPendulum-v5.uitest-edited.toml"
    pg.wait_for_function(
        "() => (window.__text('.pidlab-file-msg') || '').includes('uitest-edited')", timeout=10_000
    )
    spec = load_spec(edited)
    assert spec.loop("pole").kd == 1.1 and spec.bounds is None
    assert "--ui" in spec.provenance["tool"] and spec.provenance["edited_from"] == "uitest"


def test_bad_input_shows_a_message_and_writes_nothing(page, server):
    pg = page
    _, tuning, _ = server
    table = _table(pg)
    _type(pg, "kp", "abc")
    pg.wait_for_selector(".pidlab-msg-kp .pidlab-msg", timeout=5000)
    assert "is not a number" in _message(pg, "kp")
    _type(pg, "tf", "-0.5")
    pg.wait_for_selector(".pidlab-msg-tf .pidlab-msg", timeout=5000)
    assert "out of range" in _message(pg, "tf")
    _type(pg, "kd", "1e9")
    pg.wait_for_selector(".pidlab-msg-kd .pidlab-msg", timeout=5000)
    assert "out of range" in _message(pg, "kd")
    assert _table(pg) == table  # rejected values change nothing
    # an unstable coach is shown (that is the point of a tuner) but never saved
    _type(pg, "kp", "-1")
    pg.wait_for_function("() => (window.__text('.pidlab-msg-kp') || '').includes('unstable')", timeout=5000)
    assert "UNSTABLE" in _text(pg, "#closed-loop-summary")
    name = pg.locator(".pidlab-name input")
    name.fill("unstable")
    name.press("Enter")
    _click(pg, ".pidlab-save")
    pg.wait_for_function(
        "() => (window.__text('.pidlab-file-msg') || '').includes('not saved')", timeout=5000
    )
    assert not (tuning / "InvertedPendulum-v5.unstable.toml").exists()
    name.fill("../escape")
    name.press("Enter")
    _click(pg, ".pidlab-save")
    pg.wait_for_selector(".pidlab-msg-name .pidlab-msg", timeout=5000)
    assert not list(tuning.parent.glob("*escape*"))
    # a valid value clears the message and the page still answers
    _type(pg, "kp", "5")
    pg.wait_for_function("() => !(window.__text('.pidlab-msg-kp') || '').trim()", timeout=5000)
    # the summary is recomputed by the server after the message clears: wait for it, then check it
    pg.wait_for_function(
        "() => !(window.__text('#closed-loop-summary') || '').includes('UNSTABLE')", timeout=15000
    )
    assert ": stable" in _text(pg, "#closed-loop-summary")


def test_autotune_and_derive_bounds_buttons(page):
    pg = page
    kp0 = _field(pg, "kp").input_value()
    # ask for a slower loop, then auto-tune
    handle = pg.locator(".pidlab-response-time .noUi-handle")
    handle.focus()
    for _ in range(10):
        pg.keyboard.press("ArrowRight")
    _click(pg, ".pidlab-autotune")
    pg.wait_for_function(
        "() => (window.__text('.pidlab-status-autotune') || '').includes('achieved')", timeout=120_000
    )
    assert _field(pg, "kp").input_value() != kp0
    # the tuned coach has no bounds yet; derive them. Every frame until the status says "certified"
    # records what the box held then: the status must never arrive before its plot
    pg.evaluate(
        """() => { window.__boxAtCertified = null; const watch = () => {
             if ((window.__text('.pidlab-status-bounds') || '').includes('certified')) {
               window.__boxAtCertified = window.__source('bounds-box').x.length; return; }
             requestAnimationFrame(watch); }; requestAnimationFrame(watch); }"""
    )
    _click(pg, ".pidlab-derive")
    pg.wait_for_function("() => window.__boxAtCertified !== null", timeout=240_000)
    assert pg.evaluate("() => window.__boxAtCertified") == 5
    assert "hinge_pos" in _text(pg, "#bounds-table")
    box0 = _source(pg, "bounds-box", "x")
    assert len(box0) == 5
    handle = pg.locator(".pidlab-scale .noUi-handle")
    handle.focus()
    for _ in range(4):
        pg.keyboard.press("ArrowRight")
    pg.wait_for_function("(b) => window.__source('bounds-box').x[1] !== b", arg=box0[1], timeout=5000)
    box1 = _source(pg, "bounds-box", "x")
    assert box1[1] - box1[0] > box0[1] - box0[0]


def _raw_get(url: str, path: str, headers: dict[str, str] | None = None) -> int:
    """The status of ``GET path`` sent as written (no client-side normalization of ``..``)."""
    import http.client
    from urllib.parse import urlparse

    u = urlparse(url)
    conn = http.client.HTTPConnection(u.hostname, u.port, timeout=60)
    try:
        conn.request("GET", path, headers=headers or {})
        return conn.getresponse().status
    finally:
        conn.close()


def _log_since(log: Path, start: int) -> str:
    return log.read_text(errors="replace")[start:]


def test_paths_out_of_the_server_are_refused_without_a_traceback(server):
    url, _, log = server
    start = len(log.read_text(errors="replace"))
    paths = [
        "/components/../../../../etc/passwd",
        "/components/%2e%2e/%2e%2e/etc/passwd",
        "/components/..%2f..%2f..%2fetc/passwd",
        "/components/os/path/__css__/x",
        "/components/this/x/y/z",  # importing `this` prints; no module is imported by name
        "/components/",
        "/static/../../../etc/passwd",
        "/static/extensions/../../../etc/passwd",
    ]
    codes = {p: _raw_get(url, p) for p in paths}
    assert all(c in (403, 404) for c in codes.values()), codes
    text = _log_since(log, start)
    assert "Traceback" not in text and "500 GET" not in text, text[-3000:]


def test_a_foreign_page_is_told_about_allow_host(server):
    """Bokeh's refusal of a websocket from another origin names pidlab's flag, not Bokeh's."""
    url, _, log = server
    start = len(log.read_text(errors="replace"))
    upgrade = {
        "Connection": "Upgrade",
        "Upgrade": "websocket",
        "Sec-WebSocket-Version": "13",
        "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ==",
        "Origin": "http://evil.example:8000",
    }
    assert _raw_get(url, "/ws", upgrade) == 403
    text = _log_since(log, start)
    assert "--allow-host" in text and "evil.example" in text, text[-2000:]
    assert "--allow-websocket-origin" not in text and "BOKEH_ALLOW_WS_ORIGIN" not in text


CRAFTED = """([cls, attr, value]) => {
  const m = [...Bokeh.documents[0].all_models].find((m) => (m.css_classes || []).includes(cls));
  m[attr] = value;  // BokehJS sends the change to the server, as a slider drag would
}"""


def test_a_crafted_websocket_patch_cannot_leave_a_widgets_range(page, server):
    """Values sent past a widget's range are clamped by the server; bad options are ignored."""
    pg = page
    _, _, log = server
    start = len(log.read_text(errors="replace"))
    end = pg.evaluate(
        "() => [...Bokeh.documents[0].all_models].find((m) => (m.css_classes || []).includes('pidlab-slider-kp')).end"
    )
    table = _table(pg)
    pg.evaluate(CRAFTED, ["pidlab-slider-kp", "end", 1e12])  # a wider range is not taken either
    pg.evaluate(CRAFTED, ["pidlab-slider-kp", "value", 1e9])
    pg.wait_for_function(
        "(v) => window.__input('.pidlab-input-kp').value === v", arg=f"{end:.6g}", timeout=10_000
    )
    _wait_changed(pg, "#margins-table", table)
    for cls, attr, value in (
        ("pidlab-slider-tf", "value", -5.0),
        ("pidlab-slider-ki", "value", 1e300),
        ("pidlab-scale", "value", 1e6),
        ("pidlab-response-time", "value_throttled", 1e-9),
        ("pidlab-robustness", "value", -3.0),
        ("pidlab-loop", "value", "nope"),
        ("pidlab-load-select", "value", "../../../../etc/passwd"),
    ):
        pg.evaluate(CRAFTED, [cls, attr, value])
    pg.wait_for_timeout(1500)
    assert float(_field(pg, "tf").input_value()) >= 0.0
    assert abs(float(_field(pg, "ki").input_value())) <= 1e4
    # the page still answers
    table = _table(pg)
    _type(pg, "kp", "5")
    _wait_changed(pg, "#margins-table", table)
    text = _log_since(log, start)
    assert "Traceback" not in text and "Error" not in text, text[-3000:]


def test_five_tabs_at_once_and_a_limit(server):
    """Page requests get a placeholder (no tuner built); five tabs open at once; the ninth is told no.

    Mechanics only: how fast is measured by ``benchmarks/tuner_load.py`` (docs/tuner-load.md).
    """
    import asyncio

    from pidlab.app.browser import TunerClient
    from pidlab.app.serve import MAX_SESSIONS
    from pidlab.errors import PidlabError

    url, _, log = server

    async def scenario() -> tuple[list, list, str, float]:
        five = [TunerClient(url) for _ in range(5)]
        opened = await asyncio.gather(*(c.open(120) for c in five))
        more = [TunerClient(url) for _ in range(MAX_SESSIONS + 1 - 5)]
        rest = await asyncio.gather(*(c.open(120) for c in more), return_exceptions=True)
        tabs = five + more
        pulled = five[0].pulled
        for c in tabs:
            c.close()
        await asyncio.sleep(0.5)
        again = TunerClient(url)  # the closed tabs freed their places at once
        seconds = await again.open(120)
        again.close()
        return opened, rest, pulled, seconds

    import threading

    out: list = []  # in a thread of its own: this thread's event loop belongs to Playwright
    worker = threading.Thread(target=lambda: out.append(asyncio.run(scenario())))
    worker.start()
    worker.join(timeout=600)
    opened, rest, pulled, again = out[0]
    assert len(opened) == 5 and all(isinstance(t, float) for t in opened)
    busy = [r for r in rest if isinstance(r, PidlabError)]
    assert len(busy) == 1 and "busy" in str(busy[0]), rest
    assert sum(isinstance(r, float) for r in rest) == MAX_SESSIONS - 5
    assert "margins-table" not in pulled and "pidlab-loading" in pulled  # the page alone: a placeholder
    assert isinstance(again, float)
    assert "Traceback" not in log.read_text(errors="replace")
