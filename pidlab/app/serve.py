"""Serve the tuner on a local port (``pidlab tune ENV --ui``)."""

from __future__ import annotations

import functools
import gc
import logging
import re
import signal
import socket
import sys
import time
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

from pidlab.checks import clip
from pidlab.controller.spec import CoachSpec
from pidlab.errors import PidlabError
from pidlab.plant.envs import MODULE_NAME

MAX_SESSIONS = 8
"""Browser tabs the tuner serves at once; a further tab gets a page that says so.

The server has one event loop and the tabs share two worker processes, so every tab beyond a
handful slows all the others (see ``docs/tuner-load.md``)."""

SPARE_TUNERS = 5
"""Tuner pages built ahead, while the server is idle, so that a new tab only has to send one."""

SPARE_IDLE_S = 2.0
"""A spare tuner is built only when no tab has opened or changed for this long (building one
holds the server's loop for a few tenths of a second)."""

FLUSH_S = 0.02
"""Pause after filling a tab, so that its document is sent before the next tab is built."""

PAGE_SLOTS = 1
"""New pages (Bokeh sessions) made at once; further page requests wait their turn, at no cost.

Making a page takes the server's loop for a few hundredths of a second. A flood of page
requests served back to back would make every message of an open tab wait behind them: after
each page the next waits as long again, so that pages take at most half of the loop."""

LOADING_HTML = "<div id='pidlab-loading'><h3>pidlab tuner</h3>loading the tuner…</div>"


class _ClosedSocketNoise(logging.Filter):
    """Drop asyncio's report of a write to a browser tab that was just closed.

    When a tab closes, Bokeh keeps the session until its cleanup and a pending write to the
    closed websocket ends in ``WebSocketClosedError``; asyncio then logs "Task exception was
    never retrieved" with a traceback. Nothing is wrong, so nothing is printed.
    """

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        name = type(exc).__name__ if exc is not None else ""
        text = record.getMessage()
        return not (
            name in ("WebSocketClosedError", "StreamClosedError")
            or ("never retrieved" in text and "WebSocketClosedError" in text)
        )


class _OriginInPidlabTerms(logging.Filter):
    """Reword Bokeh's refusal of a websocket from a foreign page: name pidlab's flag, not Bokeh's.

    Bokeh's message advises ``--allow-websocket-origin`` and ``BOKEH_ALLOW_WS_ORIGIN``, which the
    tuner's command line does not have; its flag for the same thing is ``--allow-host``.
    """

    def filter(self, record: logging.LogRecord) -> bool:
        if str(record.msg).startswith("Refusing websocket connection from Origin"):
            origin = str(record.args[0]) if isinstance(record.args, tuple) and record.args else "?"
            record.msg = (
                "pidlab tuner: refused a websocket connection from a page at %s; the tuner only "
                "talks to its own pages under localhost, 127.0.0.1 and the names given with "
                "--allow-host NAME (e.g. --allow-host %s, if that page is yours)"
            )
            record.args = (origin, urlparse(origin).hostname or origin)
        return True


def check_port(port: int) -> None:
    """Raise :class:`PidlabError` unless ``port`` can be bound on 127.0.0.1."""
    if not 0 < port < 65536:
        raise PidlabError(f"port={port!r}: expected a TCP port between 1 and 65535", param="port")
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
        except OSError as exc:
            raise PidlabError(
                f"port={port!r}: cannot listen there ({exc.strerror}); pick another port", param="port"
            ) from None


def check_tuning_dir(tuning_dir: str | Path) -> Path:
    """``tuning_dir`` as a path, checked to be an existing folder (*Save* writes there, *Load* looks).

    Raises
    ------
    PidlabError
        No such folder, or not a folder.
    """
    path = Path(tuning_dir)
    try:
        ok, exists = path.is_dir(), path.exists()
    except (OSError, ValueError):
        ok, exists = False, False
    if not ok:
        what = "not a folder" if exists else "no such folder"
        raise PidlabError(
            f"tuning_dir={clip(str(path))}: {what}; expected the folder where Save writes "
            "ENV.NAME.toml and Load looks (create it first, or give another)",
            param="tuning_dir",
        )
    return path


LOCAL_HOSTS = ("localhost", "127.0.0.1")
"""The names the tuner answers to by default (the HTTP ``Host`` header, without the port).

The server listens on 127.0.0.1 only, so ``[::1]`` never reaches it directly (and Panel cannot
serve a page under a bracketed IPv6 host)."""
_HOST_NAME = re.compile(r"^(\*|[A-Za-z0-9]([A-Za-z0-9.-]{0,252}[A-Za-z0-9])?)$")


def check_hosts(names: Sequence[str]) -> tuple[str, ...]:
    """The extra host names the tuner should answer to (``--allow-host``), checked.

    Raises
    ------
    PidlabError
        A name that is not a host name or an IPv4 address (letters, digits, dots and dashes)
        or ``*`` (any host).
    """
    for name in names:
        if not isinstance(name, str) or not _HOST_NAME.match(name):
            raise PidlabError(
                f"allow_host={name!r}: expected a host name such as tuner.example.org, an IPv4 "
                "address, or * (any host); without the port",
                param="allow_host",
            )
    return tuple(n.lower() for n in names)


def refuse_foreign_hosts(app: Any, hosts: Sequence[str]) -> None:
    """Answer 403 to any request whose ``Host`` header is not one of ``hosts`` (any port).

    Bokeh checks the ``Origin`` of websocket connections but serves its pages to any ``Host``; a
    page reached under a foreign name (DNS rebinding) could then drive the tuner. Tornado routes by
    host name first, so one rule in front of Bokeh's refuses every other name, for pages,
    static files and websockets alike.

    Parameters
    ----------
    app : tornado.web.Application
        The server's application (Bokeh's ``BokehTornado``).
    hosts : sequence of str
        Host names without the port; ``*`` allows any.
    """
    from tornado.web import RequestHandler

    if "*" in hosts:
        return
    allowed = "|".join(re.escape(h.lower()) for h in hosts)

    class _ForeignHost(RequestHandler):
        def prepare(self) -> None:
            self.set_status(403)
            self.finish(
                f"pidlab tuner: the host name {self.request.host_name!r} is not allowed; open "
                "http://localhost:PORT/ or start the tuner with --allow-host NAME\n"
            )

    app.add_handlers(rf"(?!(?:{allowed})$).*", [(r".*", _ForeignHost)])


def refuse_unknown_components(app: Any) -> None:
    """Answer 404, without a traceback, to a ``/components/`` path that names no loaded module.

    Panel serves a component's style sheets and scripts under ``/components/MODULE/CLASS/...``
    and imports ``MODULE`` to find them; a path such as ``/components/../../etc/passwd`` then
    ended in an uncaught ``TypeError`` (500, with a traceback in the log), and any installed
    module could be imported by name. The rule placed in front of Panel's serves only modules
    that are already loaded, and turns any other failure into a 404.
    """
    from panel.io.resources import COMPONENT_PATH
    from panel.io.server import ComponentResourceHandler
    from tornado.web import HTTPError

    class _Components(ComponentResourceHandler):  # type: ignore[misc]
        def parse_url_path(self, path: str) -> str:
            module = path.split("/", 1)[0]
            if not MODULE_NAME.fullmatch(module) or module not in sys.modules:
                raise HTTPError(404, "no such component")
            try:
                return str(super().parse_url_path(path))
            except HTTPError:
                raise
            except Exception:  # a malformed path inside a loaded module: not found, no traceback
                raise HTTPError(404, "no such component") from None

    app.add_handlers(r".*", [(rf"/{COMPONENT_PATH}(.*)", _Components, {})])


class TunerPages:
    """The tuner's browser tabs: at most ``max_sessions`` at a time, each built once it has loaded.

    A page request only gets a small placeholder; the tuner is put in it when the browser has
    loaded the page and opened its websocket (Panel's ``onload``), so that a client that only
    requests pages costs little. Tabs that load together are filled one step after the other,
    each step sent before the next is made: first every tab's controls and numbers, then each
    tab's plots, so that no tab waits for all the others to be usable. The slow part of a tuner,
    its widgets and figures, is built ahead (:data:`SPARE_TUNERS`, while the server is idle), so
    that a new tab mostly has to be sent. A tab beyond ``max_sessions`` open ones gets a page
    that says so.

    Parameters
    ----------
    make : callable
        Builds a :class:`pidlab.app.tuner.Tuner` (outside any session).
    max_sessions : int
    spares : int
        Tuners kept built ahead.
    runner : JobRunner, optional
        The tuners' worker pool, held (no new background jobs) while tabs wait to be filled.
    """

    def __init__(
        self,
        make: Callable[[], Any],
        max_sessions: int = MAX_SESSIONS,
        spares: int = SPARE_TUNERS,
        runner: Any = None,
    ):
        self.make = make
        self.runner = runner
        self.max_sessions = max_sessions
        self.spares = spares
        self._spare: list[Any] = []
        self._live: list[Any] = []
        self._waiting: deque[tuple[Any, Any]] = deque()  # (document, placeholder) of loaded tabs
        self._plots_due: deque[tuple[Any, Any]] = deque()  # (document, tuner) whose plots are not sent
        self._draining = False
        self._slots: Any = None  # asyncio.Semaphore of PAGE_SLOTS, made in the server's loop
        self._slot_start = 0.0
        self._last_open = 0.0
        self._refill_due = False

    def prepare(self) -> None:
        """Build the spare tuners now (before the server starts), and one more to warm up with.

        The first tuner turned into a document costs about twice the next ones (caches, lazy
        imports); the warm-up one takes that cost before any tab waits for it.
        """
        from bokeh.document import Document

        doc = Document()
        doc.add_root(self.make().layout().get_root(doc))
        doc.to_json()
        del doc
        # what exists now (modules, the model, caches) lives as long as the server: kept out of
        # the garbage collector's scans, a full collection during a tab's build takes tens of
        # milliseconds instead of hundreds
        gc.collect()
        gc.freeze()
        while len(self._spare) < self.spares:
            self._spare.append(self.make())

    def live(self) -> int:
        """Tabs served now (a closed tab stops counting at once, not when Bokeh discards it)."""
        self._live = [t for t in self._live if not t.closed()]
        return len(self._live)

    def page(self) -> Any:
        """The page of a new tab: a placeholder, filled once the page has loaded."""
        import panel as pn

        from pidlab.app.tuner import _html

        holder = pn.Column(_html(LOADING_HTML), sizing_mode="stretch_width")
        doc = pn.state.curdoc
        pn.state.onload(lambda: self._enqueue(doc, holder))
        return holder

    def _enqueue(self, doc: Any, holder: Any) -> None:
        from tornado.ioloop import IOLoop

        self._waiting.append((doc, holder))
        if not self._draining:
            self._draining = True
            IOLoop.current().add_callback(self._drain)

    async def _drain(self) -> None:
        """Fill the waiting tabs one step at a time, each step sent before the next is made.

        A tab's first step is its controls and numbers, its second its plots; the first steps of
        all waiting tabs come before any second step.
        """
        self._hold(True)  # the background jobs of the tabs just opened wait: the CPU goes to opening
        try:
            while self._waiting or self._plots_due:
                if self._waiting:
                    doc, holder = self._waiting.popleft()
                    await self._in_document(doc, functools.partial(self._fill, doc, holder))
                else:
                    doc, tuner = self._plots_due.popleft()
                    if not tuner.closed():
                        await self._in_document(doc, tuner.show_plots)
        finally:
            self._draining = False
            self._hold(False)

    @staticmethod
    async def _in_document(doc: Any, step: Callable[[], None]) -> None:
        """Run ``step`` with ``doc``'s lock (changes to its models need it), then let it be sent."""
        import asyncio

        from panel.io.state import set_curdoc

        done = asyncio.Event()

        def run() -> None:
            gc.disable()  # a step makes many short-lived objects: collect them afterwards
            try:
                with set_curdoc(doc):
                    step()
            finally:
                gc.enable()
                done.set()

        try:
            doc.add_next_tick_callback(run)
            await asyncio.wait_for(done.wait(), timeout=60.0)
        except (RuntimeError, asyncio.TimeoutError):  # the tab went away before its turn
            return
        await asyncio.sleep(FLUSH_S)

    def _hold(self, held: bool) -> None:
        if self.runner is not None:
            self.runner.held = held

    async def page_slot(self) -> None:
        """Wait for a turn to make a new page (:data:`PAGE_SLOTS`), and while loaded tabs wait for theirs."""
        import asyncio

        if self._slots is None:
            self._slots = asyncio.Semaphore(PAGE_SLOTS)
        await self._slots.acquire()
        try:
            while self._waiting:  # tabs already loaded get their controls first (not their plots)
                await asyncio.sleep(FLUSH_S)
        except BaseException:
            self._slots.release()
            raise
        self._slot_start = time.monotonic()

    def free_page_slot(self) -> None:
        """Give back the turn taken by :meth:`page_slot`, after as long again as it was held."""
        from tornado.ioloop import IOLoop

        held = min(time.monotonic() - self._slot_start, 1.0)
        IOLoop.current().call_later(held, self._slots.release)

    def _fill(self, doc: Any, holder: Any) -> None:
        """A tab's first step: its tuner without the plots, or the busy page."""
        from pidlab.app.tuner import _html

        if self.live() >= self.max_sessions:
            holder.objects = [_html(_busy_html(self.max_sessions), css_classes=["pidlab-busy"])]
            return
        tuner = self._spare.pop(0) if self._spare else self.make()
        self._live.append(tuner)
        self._last_open = time.monotonic()
        holder.objects = [tuner.panel(plots=False)]
        self._plots_due.append((doc, tuner))
        self._schedule_refill()

    def _schedule_refill(self, delay: float = SPARE_IDLE_S) -> None:
        from tornado.ioloop import IOLoop

        if not self._refill_due and len(self._spare) < self.spares:
            self._refill_due = True
            IOLoop.current().call_later(delay, self._refill)

    def _refill(self) -> None:
        """Build one spare tuner if no tab opened or changed lately, then come back for the next."""
        self._refill_due = False
        busy = max([self._last_open, *(t.changed_at for t in self._live)])
        idle = time.monotonic() - busy
        if idle < SPARE_IDLE_S or self._draining:
            self._schedule_refill(max(SPARE_IDLE_S - idle, 0.2))
            return
        if len(self._spare) < self.spares:
            self._spare.append(self.make())
            self._schedule_refill(0.5)


def pace_page_requests(app: Any, pages: TunerPages) -> None:
    """Make the server's new pages one at a time (:meth:`TunerPages.page_slot`), not all at once.

    Every handler that makes a Bokeh session for a request (the page, ``autoload.js``) first
    waits for its turn; the websocket of an open tab never waits. The handlers are Bokeh's and
    Panel's, replaced in the application's routing table by subclasses that take the turn.
    """
    from bokeh.server.views.session_handler import SessionHandler

    for rule in app.wildcard_router.rules:
        target = rule.target
        if isinstance(target, type) and issubclass(target, SessionHandler):
            rule.target = _paced(target, pages)


def _paced(handler: type, pages: TunerPages) -> type:
    """``handler`` with a turn from ``pages`` taken before it makes a session, given back when it is done."""

    class Paced(handler):  # type: ignore[valid-type,misc]
        _turn = False

        async def prepare(self) -> None:
            await pages.page_slot()
            self._turn = True
            await super().prepare()

        def on_finish(self) -> None:
            self._give_back()
            super().on_finish()

        def on_connection_close(self) -> None:
            self._give_back()
            super().on_connection_close()

        def _give_back(self) -> None:
            if self._turn:
                self._turn = False
                pages.free_page_slot()

    Paced.__name__ = Paced.__qualname__ = f"Paced{handler.__name__}"
    return Paced


def _busy_html(limit: int) -> str:
    return (
        "<div id='pidlab-busy'><h3>pidlab tuner: busy</h3>"
        f"The tuner already serves {limit} browser tabs, the most it serves at once (they share "
        "one server and two worker processes). Close a tuner tab you no longer use, then reload "
        "this page.</div>"
    )


def serve_tuner(
    spec: CoachSpec,
    source: str,
    tuning_dir: Path,
    port: int,
    animation: str = "auto",
    bounds_samples: int = 1000,
    announce: Any = print,
    allow_hosts: Sequence[str] = (),
    max_sessions: int = MAX_SESSIONS,
) -> None:
    """Serve the tuner for ``spec`` until SIGINT (Ctrl-C) or SIGTERM, then raise KeyboardInterrupt.

    Every browser tab gets its own :class:`pidlab.app.tuner.Tuner` (see :class:`TunerPages`);
    the model, its linearization and the worker pool that runs the slow parts are shared, and
    the pool is stopped on exit. The server listens on 127.0.0.1 and answers only to the host
    names :data:`LOCAL_HOSTS` and ``allow_hosts``.

    Raises
    ------
    KeyboardInterrupt
        After a clean stop by SIGINT or SIGTERM (the command line exits with code 130).
    PidlabError
        ``tuning_dir`` is not an existing folder, the port cannot be used, or a name in
        ``allow_hosts`` is not a host name.
    """
    folder = check_tuning_dir(tuning_dir)
    check_port(port)
    hosts = (*LOCAL_HOSTS, *check_hosts(allow_hosts))
    import panel as pn

    from pidlab.app.jobs import JobRunner
    from pidlab.app.live import tuner_context
    from pidlab.app.tuner import Tuner
    from pidlab.plant.model import load_model

    _quiet_logs()
    pn.config.browser_info = False  # one model less in every page; the tuner does not ask the browser
    runner = JobRunner()
    ctx = tuner_context(load_model(spec.env_id))  # shared by every tab

    def make() -> Tuner:
        return Tuner(spec, source, folder, runner, animation, bounds_samples, context=ctx)

    pages = TunerPages(make, max_sessions=max_sessions, runner=runner)
    try:
        runner.start()  # the workers start now, not in the first tab's callback
        pages.prepare()
        server = pn.serve(
            {"/": pages.page},
            port=port,
            address="127.0.0.1",
            location=False,  # the tuner does not read the page's URL: one model less per page
            websocket_origin=_origins(hosts, port),
            show=False,
            title=f"pidlab tuner: {spec.env_id}",
            threaded=False,
            verbose=False,
            start=False,
        )
        app = server._tornado  # Bokeh's application; it has no public name
        refuse_foreign_hosts(app, hosts)
        refuse_unknown_components(app)
        pace_page_requests(app, pages)
        announce(f"pidlab tuner for {spec.env_id} at http://localhost:{port}/ (Ctrl-C to stop)")
        _run_until_signal(server)
    finally:
        runner.shutdown()
    raise KeyboardInterrupt  # stopped by a signal: the same exit (130) as every other command


def _quiet_logs() -> None:
    """The server's log: pidlab's own lines, no tracebacks for closed tabs, pidlab's flag names."""
    logging.getLogger("pidlab.app").addHandler(logging.StreamHandler())
    logging.getLogger("asyncio").addFilter(_ClosedSocketNoise())
    logging.getLogger("bokeh.server.views.ws").addFilter(_OriginInPidlabTerms())


def _origins(hosts: Sequence[str], port: int) -> list[str]:
    """Bokeh's websocket origin allowlist for ``hosts`` (``*:PORT`` for any)."""
    return [f"{h}:{port}" for h in hosts]


def _run_until_signal(server: Any) -> None:
    """Run the server's loop until SIGINT or SIGTERM; both stop it the same way."""
    loop = server.io_loop

    def stop(signum: int, frame: Any) -> None:
        loop.asyncio_loop.call_soon_threadsafe(loop.stop)

    old = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        server.start()
        loop.start()
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
        server.stop()
