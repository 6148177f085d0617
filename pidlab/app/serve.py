"""Serve the tuner on a local port (``pidlab tune ENV --ui``)."""

from __future__ import annotations

import logging
import re
import signal
import socket
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from pidlab.controller.spec import CoachSpec
from pidlab.errors import PidlabError


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


def serve_tuner(
    spec: CoachSpec,
    source: str,
    tuning_dir: Path,
    port: int,
    animation: str = "auto",
    bounds_samples: int = 1000,
    announce: Any = print,
    allow_hosts: Sequence[str] = (),
) -> None:
    """Serve the tuner for ``spec`` until SIGINT (Ctrl-C) or SIGTERM, then raise KeyboardInterrupt.

    Every browser session gets its own :class:`pidlab.app.tuner.Tuner`; the worker pool that
    runs the slow parts is shared and stopped on exit. The server listens on 127.0.0.1 and
    answers only to the host names :data:`LOCAL_HOSTS` and ``allow_hosts``.

    Raises
    ------
    KeyboardInterrupt
        After a clean stop by SIGINT or SIGTERM (the command line exits with code 130).
    PidlabError
        The port cannot be used, or a name in ``allow_hosts`` is not a host name.
    """
    import panel as pn

    from pidlab.app.jobs import JobRunner
    from pidlab.app.tuner import Tuner

    check_port(port)
    hosts = (*LOCAL_HOSTS, *check_hosts(allow_hosts))
    logging.getLogger("pidlab.app").addHandler(logging.StreamHandler())
    logging.getLogger("asyncio").addFilter(_ClosedSocketNoise())
    runner = JobRunner()

    def page() -> Any:
        return Tuner(
            spec, source, tuning_dir, runner=runner, animation=animation, bounds_samples=bounds_samples
        ).panel()

    try:
        server = pn.serve(
            {"/": page},
            port=port,
            address="127.0.0.1",
            websocket_origin=_origins(hosts, port),
            show=False,
            title=f"pidlab tuner: {spec.env_id}",
            threaded=False,
            verbose=False,
            start=False,
        )
        refuse_foreign_hosts(server._tornado, hosts)  # Bokeh's application; it has no public name
        announce(f"pidlab tuner for {spec.env_id} at http://localhost:{port}/ (Ctrl-C to stop)")
        _run_until_signal(server)
    finally:
        runner.shutdown()
    raise KeyboardInterrupt  # stopped by a signal: the same exit (130) as every other command


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
