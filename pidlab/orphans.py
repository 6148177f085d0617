"""Worker processes that notice when the process that started them is gone.

A pool worker whose parent was killed (SIGKILL, or SIGTERM without cleanup) is re-parented and
would otherwise go on: take the next task queued in its pipe, hold its files, keep the pool's
resource tracker alive. :func:`stop_with_parent` makes it stop within seconds instead;
:func:`watch_parent` is the portable, polling part of it.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import threading
import time
from collections.abc import Callable

PR_SET_PDEATHSIG = 1
"""Linux ``prctl`` option: the signal the kernel sends a process when its parent dies."""

ORPHAN_GRACE_S = 3.0
"""How long an orphaned worker may go on (to finish a quick checkpoint) before it exits."""


def watch_parent(on_orphan: Callable[[], None], period_s: float = 1.0) -> None:
    """Call ``on_orphan`` (once, from a daemon thread) when this process's parent changes.

    A worker of a pool whose parent was killed (SIGKILL, or SIGTERM without cleanup) is
    re-parented; this notices within ``period_s`` and lets the worker stop instead of lingering.
    """
    parent = os.getppid()

    def watch() -> None:
        while True:
            time.sleep(period_s)
            if os.getppid() != parent:
                on_orphan()
                return

    threading.Thread(target=watch, daemon=True, name="pidlab-orphan-watch").start()


def signal_on_parent_death(signum: int) -> bool:
    """Ask the kernel to send ``signum`` to this process the moment its parent dies.

    Linux only (``prctl(PR_SET_PDEATHSIG)``); returns False where it is not available. The
    "parent" is the thread that started this process: start workers from a thread that lives
    as long as its process (the main thread).
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return int(libc.prctl(PR_SET_PDEATHSIG, int(signum), 0, 0, 0)) == 0
    except (OSError, AttributeError):
        return False


def stop_with_parent(
    parent: int,
    on_orphan: Callable[[], None],
    *,
    grace_s: float = ORPHAN_GRACE_S,
    period_s: float = 0.25,
) -> None:
    """Make this worker stop when ``parent`` (the pid that started it) dies.

    On Linux the kernel sends SIGTERM at once (the worker's SIGTERM handler decides: an idle
    worker exits, a busy one stops its work with a quick checkpoint); elsewhere a thread that
    polls every ``period_s`` calls ``on_orphan`` instead. Either way the process exits
    ``grace_s`` seconds after the parent is gone, whatever it is doing.

    Parameters
    ----------
    parent : int
        The pid of the process that started this one (``os.getpid()`` there, passed along: by
        the time this runs, the parent may already be gone).
    on_orphan : callable
        Asks the work in progress to stop (e.g. ``os.kill(os.getpid(), signal.SIGTERM)``).
    grace_s, period_s : float
    """
    by_kernel = signal_on_parent_death(signal.SIGTERM)
    if os.getppid() != parent:  # gone before prctl: no signal will come
        on_orphan()
        by_kernel = True

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(period_s)
        if not by_kernel:
            on_orphan()
        time.sleep(grace_s)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="pidlab-orphan-stop").start()


def orphaned(parent: int | None) -> bool:
    """Whether this process was started by ``parent`` and ``parent`` is gone (False for None)."""
    return parent is not None and os.getppid() != parent
