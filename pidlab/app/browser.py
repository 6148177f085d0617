"""Driving the tuner from outside: start a server, the JavaScript that reads the page, a light client.

Used by the browser tests and by ``benchmarks/tuner_latency.py`` and ``benchmarks/tuner_load.py``.
The page is read through Bokeh's own document (``Bokeh.documents[0]``: the plots' data sources
by name) and through the DOM; Bokeh and Panel render every widget and pane inside a shadow root,
so the helpers search through shadow roots. :class:`TunerClient` opens a tab without a browser:
it speaks Bokeh's websocket protocol as the page's JavaScript does, but draws nothing.
"""

from __future__ import annotations

import json
import math
import os
import re
import socket
import subprocess
import sys
import time
import urllib.request
import uuid
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from pidlab.errors import PidlabError

CHROMIUM = "/usr/bin/chromium"
"""Debian's chromium, driven by Playwright with ``executable_path``."""

CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking"]

PAGE_JS = """
window.__deep = (sel, root = document) => {
  const hit = root.querySelector(sel);
  if (hit) return hit;
  for (const el of root.querySelectorAll('*')) {
    if (el.shadowRoot) { const f = window.__deep(sel, el.shadowRoot); if (f) return f; }
  }
  return null;
};
// visible text of an element, including its own shadow root (Panel panes render there)
window.__text = (sel) => {
  const e = window.__deep(sel);
  if (!e) return null;
  const parts = [e.innerText || ''];
  if (e.shadowRoot) {
    for (const c of e.shadowRoot.children) {
      if (c.tagName !== 'STYLE' && c.tagName !== 'LINK') parts.push(c.innerText || c.textContent || '');
    }
  }
  return parts.join(' ');
};
window.__input = (host) => {
  const h = window.__deep(host);
  return h && h.shadowRoot ? h.shadowRoot.querySelector('input') : null;
};
window.__source = (name) => Bokeh.documents[0].get_model_by_name(name).data;
// whether the plots have arrived (a server sends a new tab its controls first, its plots next)
window.__plotted = () => Boolean(window.Bokeh && Bokeh.documents.length
  && Bokeh.documents[0].get_model_by_name('bode-mag') && window.__deep('.bk-Figure'));
// resolves with the ms from the next keydown until the Bode data and the margins table have
// both changed and the browser has painted a frame (null for the table if it did not change)
window.__measure = (timeoutMs = 5000) => new Promise((resolve) => {
  const bode0 = window.__source('bode-mag').db[0];
  const table0 = window.__text('#margins-table');
  let t0 = null, tData = null, tTable = null;
  document.addEventListener('keydown', () => { t0 = performance.now(); }, { once: true, capture: true });
  const check = () => {
    const now = performance.now();
    if (t0 !== null) {
      if (tData === null && window.__source('bode-mag').db[0] !== bode0) tData = now - t0;
      if (tTable === null && window.__text('#margins-table') !== table0) tTable = now - t0;
      if ((tData !== null && tTable !== null) || now - t0 > timeoutMs) {
        requestAnimationFrame(() => resolve({ data: tData, table: tTable, painted: performance.now() - t0 }));
        return;
      }
    }
    requestAnimationFrame(check);
  };
  requestAnimationFrame(check);
});
"""


def free_port() -> int:
    """A TCP port that is free on 127.0.0.1 right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_server(
    env_id: str,
    spec: str | Path,
    tuning_dir: str | Path,
    port: int,
    extra: Sequence[str] = (),
    log: Path | None = None,
    timeout_s: float = 90.0,
) -> subprocess.Popen[bytes]:
    """Run ``pidlab tune ENV --ui`` in a subprocess and wait until it answers HTTP.

    Raises
    ------
    PidlabError
        The server exited or did not answer within ``timeout_s`` (the message carries the end
        of its log).
    """
    cmd = [sys.executable, "-m", "pidlab", "tune", env_id, "--ui", "--spec", str(spec)]
    cmd += ["--tuning-dir", str(tuning_dir), "--port", str(port), *extra]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    if log is not None:
        with open(log, "wb") as out:  # the child keeps its own handle
            proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env)
    else:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, env=env)
    url = f"http://localhost:{port}/"
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with urllib.request.urlopen(url, timeout=5) as r:
                if r.status == 200:
                    return proc
        except OSError:
            pass
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            tail = log.read_text(errors="replace")[-3000:] if log is not None else ""
            raise PidlabError(f"the tuner server did not start ({' '.join(cmd)}):\n{tail}")
        time.sleep(0.5)


def stop_server(proc: subprocess.Popen[bytes]) -> int:
    """Stop a server started by :func:`start_server` (SIGTERM, then SIGKILL after 20 s).

    Returns
    -------
    int
        Its exit code: 130 when it stopped cleanly (the code of every interrupted command),
        -9 when it had to be killed.
    """
    proc.terminate()
    try:
        return proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait()


DOCUMENT_READY = {
    "events": [
        {
            "kind": "MessageSent",
            "msg_type": "bokeh_event",
            "msg_data": {"type": "event", "name": "document_ready", "values": {"type": "map"}},
        }
    ]
}
"""What BokehJS sends once it has rendered a document (Panel then runs the page's ``onload``)."""


def _objects(node: Any) -> Iterator[dict[str, Any]]:
    """Every serialized Bokeh model (``{"type": "object", "id": ...}``) inside a message's content."""
    stack = [node]
    while stack:
        item = stack.pop()
        if isinstance(item, dict):
            if item.get("type") == "object" and "id" in item:
                yield item
            stack.extend(item.values())
        elif isinstance(item, list):
            stack.extend(item)


class TunerClient:
    """One tuner tab without a browser: what the page's JavaScript sends and receives, nothing drawn.

    :meth:`open` requests the page, opens its websocket, pulls the document and says it is
    ready, as BokehJS does, then waits for the tuner's margins table. :meth:`set_value` changes a
    widget's value as a browser would (the server does not know the difference), and
    :meth:`wait_for` waits for a message that holds a piece of text. Methods are coroutines on
    Tornado's (asyncio) loop.

    Parameters
    ----------
    url : str
        The tuner's page, e.g. ``http://localhost:5006/``.
    """

    def __init__(self, url: str) -> None:
        self.url = url
        self.ws: Any = None
        self.models: dict[str, dict[str, Any]] = {}  # css class -> the widget's model id and attributes
        self.status = 0
        self.pulled = ""  # the document as first pulled, before the page said it had loaded
        self.usable_s = math.nan
        self._t0 = 0.0

    async def open(self, timeout: float = 60.0) -> float:
        """Open the tab; the seconds from the page request until the whole tuner, plots too, arrived.

        :attr:`usable_s` is the time until its controls and numbers (the margins table) arrived.

        Raises
        ------
        TimeoutError
            The views did not arrive within ``timeout`` seconds.
        PidlabError
            The server sent its "busy" page instead (it serves as many tabs as it will).
        """
        import asyncio

        self._t0 = time.perf_counter()
        await asyncio.wait_for(self._open(), timeout)
        return time.perf_counter() - self._t0

    async def _open(self) -> None:
        from tornado.httpclient import AsyncHTTPClient, HTTPRequest
        from tornado.websocket import websocket_connect

        page = await AsyncHTTPClient().fetch(self.url, raise_error=False, request_timeout=120)
        self.status = page.code
        found = re.search(r'"token":\s*"([^"]+)"', page.body.decode("utf-8", "replace"))
        if found is None:
            raise PidlabError(f"{self.url} answered {page.code} without a Bokeh session")
        origin = self.url.rstrip("/")
        ws_url = origin.replace("http://", "ws://", 1) + "/ws"
        request = HTTPRequest(ws_url, headers={"Origin": origin}, request_timeout=120)
        self.ws = await websocket_connect(
            request, subprotocols=["bokeh", found.group(1)], max_message_size=200 * 2**20
        )
        await self.wait_for(msgtype="ACK")
        await self.send("PULL-DOC-REQ", {})
        seen = self.pulled = await self.wait_for(msgtype="PULL-DOC-REPLY")
        if "margins-table" not in seen:
            await self.send("PATCH-DOC", DOCUMENT_READY)
            seen = await self.wait_for_any("margins-table", "pidlab-busy")
            if "pidlab-busy" in seen:
                raise PidlabError(f"{self.url}: the tuner is busy (it serves as many tabs as it will)")
        self.usable_s = time.perf_counter() - self._t0
        if '"bode-mag"' not in seen:
            await self.wait_for('"bode-mag"')  # the plots' data sources: the plots have arrived

    async def send(self, msgtype: str, content: dict[str, Any]) -> None:
        """Send one Bokeh protocol message (no buffers)."""
        header = {"msgid": uuid.uuid4().hex, "msgtype": msgtype}
        for part in (header, {}, content):
            await self.ws.write_message(json.dumps(part))

    async def _receive(self) -> tuple[dict[str, Any], str]:
        """The next message: its header and its content's text (buffers are read and dropped)."""
        parts = []
        for _ in range(3):
            frame = await self.ws.read_message()
            if frame is None:
                raise PidlabError(f"{self.url}: the server closed the websocket")
            parts.append(frame)
        header = json.loads(parts[0])
        for _ in range(2 * int(header.get("num_buffers", 0))):
            await self.ws.read_message()
        text = parts[2] if isinstance(parts[2], str) else parts[2].decode("utf-8", "replace")
        if '"css_classes"' in text:
            self._remember(json.loads(text))
        return header, text

    def _remember(self, content: Any) -> None:
        for obj in _objects(content):
            attrs = obj.get("attributes", {})
            for css in attrs.get("css_classes", []) if isinstance(attrs, dict) else []:
                if isinstance(css, str) and css.startswith("pidlab-"):
                    self.models[css] = {"id": obj["id"], **attrs}

    async def wait_for(self, text: str = "", msgtype: str = "") -> str:
        """Read messages until one of type ``msgtype`` (any: "") holds ``text``; its content's text."""
        while True:
            header, content = await self._receive()
            if (not msgtype or header.get("msgtype") == msgtype) and text in content:
                return content

    async def wait_for_any(self, *texts: str) -> str:
        """Read messages until one holds one of ``texts``; its content's text."""
        while True:
            _, content = await self._receive()
            if any(t in content for t in texts):
                return content

    async def set_value(self, css_class: str, value: Any, attr: str = "value") -> None:
        """Set the value of the widget with CSS class ``css_class``, as its page would."""
        model = self.models[css_class]["id"]
        event = {"kind": "ModelChanged", "model": {"id": model}, "attr": attr, "new": value}
        await self.send("PATCH-DOC", {"events": [event]})

    def close(self) -> None:
        """Close the websocket (the tab is gone)."""
        if self.ws is not None:
            self.ws.close()
