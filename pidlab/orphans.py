"""Worker processes that notice when the process that started them is gone.

A pool worker whose parent was killed (SIGKILL, or SIGTERM without cleanup) is re-parented and
would otherwise go on: take the next task queued in its pipe, hold its files, keep the pool's
resource tracker alive. :func:`stop_with_parent` makes it stop within seconds instead;
:func:`watch_parent` is the portable, polling part of it.

A parent's death is handled once. The kernel's death signal (``prctl(PR_SET_PDEATHSIG)``) is
sent whenever the *thread* that started the worker ends, and again each time the worker is
handed to another thread of the dying parent: a worker of a multi-threaded parent killed with
SIGKILL gets it several times, milliseconds apart. So the kernel sends
:data:`PARENT_DEATH_SIGNAL`, not the worker's stop signal, and its handler (like the polling
thread) asks the work to stop only the first time: a busy worker stops with a checkpoint and
is not interrupted again by the same death ("a second signal stops at once" stays a user's).
"""

from __future__ import annotations

import ctypes
import itertools
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

PARENT_DEATH_SIGNAL = signal.SIGUSR1
"""The signal the kernel sends a worker of :func:`stop_with_parent` when its parent dies (maybe
several times); its handler turns the first into one call of ``on_orphan``. Its default action
ends the process, so a process that lost the handler still does not outlive its parent."""

_PARENT_GONE = [False]
"""Set (once) in a worker of :func:`stop_with_parent` when its parent died (a plain flag: a
signal handler must not wait on a lock its own thread may hold)."""


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


class _Once:
    """``on_orphan`` called at most once, from the signal handler or the polling thread."""

    def __init__(self, on_orphan: Callable[[], None]) -> None:
        self._on_orphan = on_orphan
        self._calls = itertools.count()  # next() is atomic: no lock a nested handler could wait on

    def __call__(self, *_: object) -> None:
        _PARENT_GONE[0] = True
        if next(self._calls) == 0:
            self._on_orphan()


def stop_with_parent(
    parent: int,
    on_orphan: Callable[[], None],
    *,
    grace_s: float = ORPHAN_GRACE_S,
    period_s: float = 0.25,
) -> None:
    """Make this worker stop when ``parent`` (the pid that started it) dies: ``on_orphan`` once.

    On Linux the kernel signals the death at once (:data:`PARENT_DEATH_SIGNAL`, from the main
    thread's handler); elsewhere a thread that polls every ``period_s`` notices. Either way
    ``on_orphan`` is called once, however often the kernel signals, and the process exits
    ``grace_s`` seconds after the parent is gone, whatever it is doing.

    Parameters
    ----------
    parent : int
        The pid of the process that started this one (``os.getpid()`` there, passed along: by
        the time this runs, the parent may already be gone).
    on_orphan : callable
        Asks the work in progress to stop (e.g. ``os.kill(os.getpid(), signal.SIGTERM)``: a busy
        worker stops with a checkpoint, an idle one exits).
    grace_s, period_s : float

    Notes
    -----
    Call it from the main thread (the signal handler is installed there; from another thread
    only the polling thread watches). The "parent" of the kernel's signal is the thread that
    started this process: start workers from a thread that lives as long as its process.
    """
    once = _Once(on_orphan)
    if threading.current_thread() is threading.main_thread():
        signal.signal(PARENT_DEATH_SIGNAL, once)
        signal_on_parent_death(PARENT_DEATH_SIGNAL)
    if os.getppid() != parent:  # gone before prctl: no signal will come
        once()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(period_s)
        once()  # a no-op when the kernel's signal came first
        time.sleep(grace_s)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="pidlab-orphan-stop").start()


def orphaned(parent: int | None) -> bool:
    """Whether this process was started by ``parent`` and ``parent`` is gone (False for None).

    True from the parent's death on: its death signal may come while the dying parent's last
    threads still adopt this process (``os.getppid()`` then still names it).
    """
    return parent is not None and (_PARENT_GONE[0] or os.getppid() != parent)
