"""Driving the tuner from outside: start a server, and the JavaScript that reads the page.

Used by the browser tests and by ``benchmarks/tuner_latency.py``. The page is read through
Bokeh's own document (``Bokeh.documents[0]``: the plots' data sources by name) and through the
DOM; Bokeh and Panel render every widget and pane inside a shadow root, so the helpers search
through shadow roots.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Sequence
from pathlib import Path

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
