"""The tuner's computations without a browser: live views, form checks, bounds scaling, jobs, CLI."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from pidlab.app.jobs import JobRunner, roa_preview, rollout_preview
from pidlab.app.live import (
    check_field,
    check_name,
    linear_views,
    loop_actuator,
    scaled_bounds,
    tuner_context,
    with_loop_value,
)
from pidlab.controller.analysis import analyze_coach
from pidlab.controller.pid import Coach
from pidlab.controller.spec import load_spec
from tests.helpers import cli_in_process

ROOT = Path(__file__).resolve().parents[1]
TUNING = ROOT / "tuning"


@pytest.fixture(scope="module")
def ip(models):
    loaded = models["InvertedPendulum-v5"]
    return loaded, tuner_context(loaded), load_spec(TUNING / "InvertedPendulum-v5.pidlab-robust.toml")


def test_live_views_agree_with_pidlab_analyze(ip):
    loaded, ctx, spec = ip
    v = linear_views(ctx, spec, "pole")
    ref = analyze_coach(Coach(spec, loaded), loaded)
    assert v.margins == ref.discrete.margins
    assert v.stable == ref.discrete.stable
    assert np.allclose(
        sorted(abs(p.value) for p in v.poles), sorted(abs(p.value) for p in ref.discrete.poles)
    )
    assert {m.kind for m in v.metrics} == {"step", "initial"}
    assert all(m.loop == "pole" for m in v.metrics)
    assert v.actuator == "slide" and v.loop_margins is not None
    # the phase margin marked on the Bode plot is where |L| crosses 0 dB
    m = v.loop_margins
    k = int(np.argmin(np.abs(v.omega - m.gain_crossover)))
    assert abs(v.magnitude_db[k]) < 0.5
    assert v.initial[0] == pytest.approx(0.05)  # the initial deviation of the loop's signal
    assert v.step.shape == v.t.shape == v.step_u.shape


def test_live_views_follow_the_gains(ip):
    _, ctx, spec = ip
    stiff = with_loop_value(spec, "pole", "kp", 2 * spec.loop("pole").kp)
    assert stiff.loop("pole").kp == 2 * spec.loop("pole").kp and stiff.loop("cart") == spec.loop("cart")
    a, b = linear_views(ctx, spec, "pole"), linear_views(ctx, stiff, "pole")
    assert a.margins != b.margins and not np.allclose(a.response, b.response)
    unstable = with_loop_value(spec, "pole", "kp", -1.0)
    u = linear_views(ctx, unstable, "pole")
    assert not u.stable and u.spectral_radius > 1
    # the cart loop drives the same actuator: same loop transfer, centred on another signal
    c = linear_views(ctx, spec, "cart")
    assert c.actuator == "slide" and np.allclose(c.response, a.response)
    assert c.metrics[0].signal == "slider_pos"


def test_live_views_are_fast_enough_to_follow_a_slider(ip):
    """Not a timing assertion: the compute time is reported on the page; here only its order."""
    _, ctx, spec = ip
    v = min((linear_views(ctx, spec, "pole") for _ in range(3)), key=lambda x: x.elapsed_s)
    assert v.elapsed_s < 2.0  # loose: CI machines are shared; docs/tuner.md has the measured figure


@pytest.mark.parametrize(
    ("field", "text", "ok", "words"),
    [
        ("kp", "4.5", True, ""),
        ("kp", " -2e-3 ", True, ""),
        ("kp", "abc", False, "is not a number"),
        ("kp", "", False, "empty"),
        ("kp", "nan", False, "not finite"),
        ("kd", "inf", False, "not finite"),
        ("ki", "1e9", False, "out of range"),
        ("tf", "-0.1", False, "out of range"),
        ("tf", "0", True, ""),
    ],
)
def test_check_field(field, text, ok, words):
    c = check_field(field, text)
    assert c.ok is ok
    assert words in c.message
    if not ok:
        assert "expected" in c.message and "\n" not in c.message


def test_check_name():
    assert check_name("my-coach_2.v1").ok
    for bad in ("", "../x", "a/b", "-x", "x" * 65, "a b"):
        assert not check_name(bad).ok


def test_scaled_bounds(ip):
    _, _, spec = ip
    b = spec.bounds
    assert scaled_bounds(b, 1.0) is b
    s2 = scaled_bounds(b, 2.0)
    assert s2 is not None
    for name, (lo, hi) in b["box"].items():
        lo2, hi2 = s2["box"][name]
        assert hi2 - lo2 == pytest.approx(2 * (hi - lo)) and lo2 + hi2 == pytest.approx(lo + hi)
    assert s2["ellipsoid"]["rho"] == pytest.approx(4 * b["ellipsoid"]["rho"])
    assert s2["provenance"]["scale"] == 2.0
    assert b["ellipsoid"]["rho"] == spec.bounds["ellipsoid"]["rho"]  # the input is not changed
    assert scaled_bounds(s2, 0.5)["provenance"]["scale"] == 1.0


def test_loop_actuator_follows_weights(models):
    spec = load_spec(TUNING / "Walker2d-v5.pidlab-robust.toml")
    for lp in spec.loops:
        act = loop_actuator(spec, lp.name)
        assert act in dict(lp.actuators)
        assert abs(dict(lp.actuators)[act]) == max(abs(w) for _, w in lp.actuators)


def test_preview_jobs_called_directly(ip):
    _, _, spec = ip
    stages: list[str] = []
    r = roa_preview(spec, samples=40, progress=lambda s, f: stages.append(s))
    assert r.roa.check.samples == 40 and r.roa.check.failures == 0
    assert r.variables == ("hinge_pos", "hinge_vel") and len(r.paths) == len(r.recovered) > 0
    assert all(p.shape[1] == 2 for p in r.paths)
    assert any("bisection" in s for s in stages) and any("final check" in s for s in stages)
    roll = rollout_preview(spec, episodes=2, backend="schematic")
    assert roll.mean == pytest.approx(1000.0) and roll.episodes == 2 and roll.causes == {"time limit": 2}
    assert roll.gif[:6] == b"GIF89a" and roll.backend == "schematic"


def test_job_runner_progress_results_cancellation_and_owners(ip):
    _, _, spec = ip
    runner = JobRunner(workers=2)
    try:
        first = runner.submit("a", "roa", spec, samples=400)
        # a second roa job of the same owner abandons the first; another owner's job is independent
        time.sleep(1.0)
        second = runner.submit("a", "roa", spec, samples=30)
        other = runner.submit("b", "rollout", spec, episodes=1, backend="schematic")
        assert first != second != other
        seen: dict[str, list] = {"a": [], "b": []}
        deadline = time.monotonic() + 180
        while (runner.running("a", "roa") or runner.running("b", "rollout")) and time.monotonic() < deadline:
            for owner in ("a", "b"):
                seen[owner] += runner.poll(owner)
            time.sleep(0.1)
        for owner in ("a", "b"):
            seen[owner] += runner.poll(owner)
        done_a = [u for u in seen["a"] if u.state == "done"]
        assert [u.job_id for u in done_a] == [second]  # the abandoned job never reports a result
        assert done_a[0].result.roa.check.samples == 30
        assert all(u.job_id != first for u in seen["a"] if u.state == "done")
        assert any(u.state == "running" and u.fraction is not None for u in seen["a"])
        done_b = [u for u in seen["b"] if u.state == "done"]
        assert [u.job_id for u in done_b] == [other] and done_b[0].result.episodes == 1
        # a bad-input error comes back as one line, not a crash
        unstable = with_loop_value(spec, "pole", "kp", -1.0)
        runner.submit("a", "roa", unstable, samples=10)
        updates = []
        deadline = time.monotonic() + 60
        while runner.running("a", "roa") and time.monotonic() < deadline:
            updates += runner.poll("a")
            time.sleep(0.1)
        updates += runner.poll("a")
        errors = [u for u in updates if u.state == "error"]
        assert len(errors) == 1 and "\n" not in errors[0].stage
    finally:
        runner.shutdown()


def _cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "pidlab", *args], capture_output=True, text=True, timeout=120, cwd=cwd
    )


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--ui", "--auto"], "exactly one of --auto"),
        (["--ui", "--spec", "nope.toml"], "no such file"),
        (["--ui", "--spec", str(TUNING / "Hopper-v5.paper.toml")], "a coach for Hopper-v5"),
        (["--ui", "--port", "0"], "--port 0"),
        (["--ui", "--animation", "vr"], "--animation"),
        (["--ui", "--bounds-samples", "0"], "--bounds-samples"),
        (["--ui", "--bandwidth", "3"], "--bandwidth: a setting of --auto"),
        (["--ui", "-o", "x.toml"], "--output: a setting of --auto"),
    ],
)
def test_tune_ui_bad_input(args, words):
    code, stderr = cli_in_process("tune", "InvertedPendulum-v5", *args)
    assert code == 2, stderr
    assert words in stderr
    assert len(stderr.strip().splitlines()) == 1 and "Traceback" not in stderr


def test_tune_ui_refuses_a_busy_port():
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        r = _cli("tune", "InvertedPendulum-v5", "--ui", "--port", str(port))
    assert r.returncode == 2 and f"--port {port}" in r.stderr and "Traceback" not in r.stderr


def test_with_loop_value_rejects_unknown_names(ip):
    _, _, spec = ip
    with pytest.raises(ValueError):
        with_loop_value(spec, "pole", "setpoint", 1.0)
    with pytest.raises(ValueError):
        with_loop_value(spec, "nope", "kp", 1.0)
    assert replace(spec) == spec


def test_tuner_works_outside_a_server_as_in_a_notebook(ip, tmp_path):
    """The same page object a notebook displays: widgets drive the views without a server."""
    from bokeh.document import Document

    from pidlab.app.tuner import Tuner

    _, _, spec = ip
    tuner = Tuner(spec, "notebook", tmp_path, runner=JobRunner(workers=1))
    try:
        doc = Document()
        doc.add_root(tuner.panel().get_root(doc))
        table = tuner.margins.object
        bode = list(tuner.sources.bode_mag.data["db"])
        tuner.sliders["kp"].value = 1.5 * tuner.sliders["kp"].value
        assert tuner.margins.object != table
        assert list(tuner.sources.bode_mag.data["db"]) != bode
        assert tuner.inputs["kp"].value == f"{tuner.sliders['kp'].value:.6g}"
        tuner.inputs["kd"].value = "garbage"
        assert "is not a number" in tuner.messages["kd"].object
        assert tuner.spec.loop("pole").kd == spec.loop("pole").kd
    finally:
        tuner.runner.shutdown()


def _status(port: int, host: str, path: str = "/static/js/bokeh.min.js") -> int:
    """The HTTP status of ``GET path`` on the tuner with ``Host: host:port`` (a static file: no session)."""
    import http.client

    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=60)
    try:
        conn.request("GET", path, headers={"Host": f"{host}:{port}"})
        return conn.getresponse().status
    finally:
        conn.close()


def test_tuner_answers_only_local_host_names_and_sigint_exits_130(tmp_path):
    """A page asked for under a foreign name (DNS rebinding) is refused; Ctrl-C exits 130."""
    import signal

    from pidlab.app.browser import free_port, start_server

    port = free_port()
    log = tmp_path / "server.log"
    extra = ["--allow-host", "tuner.example"]
    (tmp_path / "tuning").mkdir()
    proc = start_server("InvertedPendulum-v5", TUNING / "InvertedPendulum-v5.pidlab-robust.toml",
                        tmp_path / "tuning", port, extra=extra, log=log)  # fmt: skip
    try:
        hosts = (
            "localhost",
            "127.0.0.1",
            "LocalHost",
            "tuner.example",
            "evil.example",
            "localhost.evil.example",
        )
        codes = {host: _status(port, host) for host in hosts}
        codes["evil.example /"] = _status(port, "evil.example", "/")  # the page itself
    finally:
        proc.send_signal(signal.SIGINT)
        code = proc.wait(timeout=30)
    assert codes == {"localhost": 200, "127.0.0.1": 200, "LocalHost": 200, "tuner.example": 200,
                     "evil.example": 403, "localhost.evil.example": 403, "evil.example /": 403}, log.read_text()  # fmt: skip
    assert code == 130, log.read_text()
    assert "pidlab: interrupted" in log.read_text() and "Traceback" not in log.read_text()


@pytest.mark.parametrize("name", ["evil.example/x", "host:5006", "[::1]", "", "-x"])
def test_allow_host_takes_host_names_only(name):
    from pidlab.app.serve import check_hosts
    from pidlab.errors import PidlabError

    with pytest.raises(PidlabError, match="allow_host="):
        check_hosts([name])
    assert check_hosts(["Tuner.Example", "10.0.0.2", "*"]) == ("tuner.example", "10.0.0.2", "*")


def test_tune_ui_refuses_a_missing_tuning_dir(tmp_path):
    """A --tuning-dir that does not exist is refused in one line before anything is served."""
    from pidlab.app.browser import free_port

    missing = tmp_path / "no-such-folder"
    r = subprocess.run(
        [sys.executable, "-m", "pidlab", "tune", "InvertedPendulum-v5", "--ui", "--tuning-dir", str(missing),
         "--port", str(free_port())],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert r.returncode == 2, r.stderr
    assert (
        r.stderr.startswith("pidlab: error: --tuning-dir ") and ": no such folder;" in r.stderr
    )  # long paths are clipped
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr
    assert "pidlab tuner for" not in r.stdout  # never served


def test_check_tuning_dir(tmp_path):
    from pidlab.app.serve import check_tuning_dir
    from pidlab.errors import PidlabError

    assert check_tuning_dir(tmp_path) == tmp_path
    (tmp_path / "file").write_text("x")
    for bad, words in ((tmp_path / "nope", "no such folder"), (tmp_path / "file", "not a folder")):
        with pytest.raises(PidlabError, match=f"tuning_dir=.*{words}") as err:
            check_tuning_dir(bad)
        assert err.value.param == "tuning_dir"


def test_every_widget_keeps_what_a_browser_sends_in_range(ip, tmp_path):
    """A crafted websocket patch (any value, any property) cannot push a widget past its range.

    ``_process_events`` is where Panel applies what the browser sent; the tuner's widgets check it
    there, on the server, for every numeric widget, and refuse options that are not offered.
    """
    from pidlab.app.tuner import Tuner

    _, _, spec = ip
    tuner = Tuner(spec, "notebook", tmp_path, runner=JobRunner(workers=1))
    try:
        numeric = {**{f"gain {f}": s for f, s in tuner.sliders.items()}, "response time": tuner.response_time,
                   "robustness": tuner.robustness, "scale": tuner.scale}  # fmt: skip
        for name, w in numeric.items():
            start, end = w.start, w.end
            for sent in (1e9, -1e9, 1e300):
                w._process_events({"value": sent, "value_throttled": sent})  # no exception either
                assert start <= w.value <= end, (name, sent, w.value)
            w._process_events({"value": (start + end) / 2})
            before = w.value
            for sent in (float("nan"), float("inf"), "12", None, True):
                w._process_events({"value": sent})
                assert w.value == before, (name, sent)
            w._process_events({"start": -1e12, "end": 1e12, "step": 1e9})  # the range is the server's
            assert (w.start, w.end) == (start, end), name
        gains = {f: getattr(tuner.spec.loop(tuner.loop), f) for f in ("kp", "ki", "kd", "tf")}
        assert gains["kp"] == tuner.sliders["kp"].value and all(abs(v) <= 1e4 for v in gains.values())
        # a selector takes only the options it offers; a text field, text of a sane length
        loop = tuner.loop_select.value
        tuner.loop_select._process_events({"value": "nope"})
        tuner.load_select._process_events({"value": "../../../etc/passwd"})
        assert tuner.loop_select.value == loop and tuner.load_select.value != "../../../etc/passwd"
        kd = tuner.inputs["kd"].value
        tuner.inputs["kd"]._process_events({"value": "1" * 100_000})
        assert tuner.inputs["kd"].value == kd
        tuner.overwrite._process_events({"active": "yes"})
        assert tuner.overwrite.value is False
        # and a value the views cannot be computed for is refused with a message, not a traceback
        table = tuner.margins.object
        tuner._apply("kp", 1e300)
        assert "undefined" in tuner.messages["kp"].object and tuner.margins.object == table
        assert tuner.spec.loop(tuner.loop).kp == gains["kp"]
    finally:
        tuner.runner.shutdown()


def _parent_death_signal() -> int:
    """The signal this process gets when its parent dies (Linux ``prctl(PR_GET_PDEATHSIG)``)."""
    import ctypes

    sig = ctypes.c_int(0)
    ctypes.CDLL(None).prctl(2, ctypes.byref(sig), 0, 0, 0)  # PR_GET_PDEATHSIG
    return sig.value


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl is Linux's")
def test_a_job_whose_worker_dies_is_one_line_and_the_next_job_runs(ip):
    """The tuner's pool after a worker is killed (SIGKILL, the out-of-memory killer): the job reports
    one line that says so, and the next job gets a new pool instead of an error on every click."""
    import signal

    _, _, spec = ip
    runner = JobRunner(workers=1)
    try:
        runner.start()
        worker = next(iter(runner._pool._processes.values()))
        runner.submit("a", "roa", spec, samples=5000)
        time.sleep(1.0)
        os.kill(worker.pid, signal.SIGKILL)
        updates, deadline = [], time.monotonic() + 60
        while runner.running("a", "roa") and time.monotonic() < deadline:
            updates += runner.poll("a")
            time.sleep(0.1)
        updates += runner.poll("a")
        errors = [u for u in updates if u.state == "error"]
        assert len(errors) == 1 and errors[0].stage == (
            "the roa job's worker process died (killed by a signal, or by the system out of memory); "
            "start it again"
        )
        again = runner.submit("a", "rollout", spec, episodes=1, backend="schematic")
        done, deadline = [], time.monotonic() + 120
        while not done and time.monotonic() < deadline:
            done = [u for u in runner.poll("a") if u.state == "done"]
            time.sleep(0.1)
        assert [u.job_id for u in done] == [again] and done[0].result.episodes == 1
    finally:
        runner.shutdown()


def test_workers_die_with_their_server():
    """The kernel kills a worker the moment its server dies (SIGKILL), instead of a 1 s poll."""
    import signal

    runner = JobRunner(workers=1)
    try:
        runner.start()
        assert runner._pool is not None
        assert runner._pool.submit(_parent_death_signal).result(timeout=60) == signal.SIGKILL
    finally:
        runner.shutdown()


def _descendants(pid: int) -> set[int]:
    """The processes ``pid`` started, and theirs (from each process's parent in /proc)."""
    parent: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        try:
            parent[int(entry.name)] = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (ValueError, OSError, IndexError):
            continue
    out: set[int] = set()
    frontier = [pid]
    while frontier:
        p = frontier.pop()
        for child in [c for c, pp in parent.items() if pp == p and c not in out]:
            out.add(child)
            frontier.append(child)
    return out


def _running(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_killed_server_leaves_no_workers(tmp_path):
    """SIGKILL of the server (no cleanup at all): its workers and their manager end too.

    How soon is measured by ``benchmarks/tuner_load.py`` (docs/tuner-load.md), not asserted here.
    """
    from pidlab.app.browser import free_port, start_server

    port = free_port()
    proc = start_server("InvertedPendulum-v5", TUNING / "InvertedPendulum-v5.pidlab-robust.toml", tmp_path,
                        port, log=tmp_path / "server.log")  # fmt: skip
    kids = _descendants(proc.pid)
    proc.kill()
    proc.wait(timeout=30)
    deadline = time.monotonic() + 30
    while any(_running(k) for k in kids) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert len(kids) >= 3 and not [k for k in kids if _running(k)]  # 2 workers, their manager, ...


def test_tuner_pages_serve_at_most_max_sessions(tmp_path):
    """Tabs beyond the limit get a page that says so; a closed tab frees its place at once."""
    import panel as pn
    from bokeh.document import Document

    from pidlab.app.serve import TunerPages

    class FakeTuner:
        def __init__(self) -> None:
            self.gone, self.changed_at = False, 0.0

        def closed(self) -> bool:
            return self.gone

        def panel(self, plots: bool = True) -> object:
            return pn.pane.HTML("<div id='margins-table'></div>")

    made: list[FakeTuner] = []

    def make() -> FakeTuner:
        made.append(FakeTuner())
        return made[-1]

    pages = TunerPages(make, max_sessions=2, spares=0)
    holders = [pn.Column() for _ in range(3)]
    for h in holders:
        pages._fill(Document(), h)
    assert ["margins-table" in h.objects[0].object for h in holders] == [True, True, False]
    assert "busy" in holders[2].objects[0].object and len(made) == 2
    made[0].gone = True  # its tab was closed
    again = pn.Column()
    pages._fill(Document(), again)
    assert "margins-table" in again.objects[0].object and pages.live() == 2
