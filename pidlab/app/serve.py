"""Serve the tuner on a local port (``pidlab tune ENV --ui``)."""

from __future__ import annotations

import logging
import signal
import socket
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


def serve_tuner(
    spec: CoachSpec,
    source: str,
    tuning_dir: Path,
    port: int,
    animation: str = "auto",
    bounds_samples: int = 1000,
    announce: Any = print,
) -> None:
    """Serve the tuner for ``spec`` until interrupted (Ctrl-C).

    Every browser session gets its own :class:`pidlab.app.tuner.Tuner`; the worker pool that
    runs the slow parts is shared and stopped on exit.
    """
    import panel as pn

    from pidlab.app.jobs import JobRunner
    from pidlab.app.tuner import Tuner

    check_port(port)
    logging.getLogger("pidlab.app").addHandler(logging.StreamHandler())
    logging.getLogger("asyncio").addFilter(_ClosedSocketNoise())
    runner = JobRunner()

    def page() -> Any:
        return Tuner(
            spec, source, tuning_dir, runner=runner, animation=animation, bounds_samples=bounds_samples
        ).panel()

    def stop(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt  # SIGTERM stops like Ctrl-C: the workers are shut down below

    signal.signal(signal.SIGTERM, stop)
    url = f"http://localhost:{port}/"
    announce(f"pidlab tuner for {spec.env_id} at {url} (Ctrl-C to stop)")
    try:
        pn.serve(
            {"/": page},
            port=port,
            address="127.0.0.1",
            websocket_origin=[f"localhost:{port}", f"127.0.0.1:{port}"],
            show=False,
            title=f"pidlab tuner: {spec.env_id}",
            threaded=False,
            print=False,
        )
    finally:
        runner.shutdown()
