"""Signals that stop a command: SIGTERM as Ctrl-C, once, and never lost.

A command stops on SIGINT (Ctrl-C) or SIGTERM by raising :class:`KeyboardInterrupt` in its main
thread, so its clean-up runs (:func:`sigterm_interrupts`). Two things Python does not do on its
own are done here:

- **A stop is asked for once.** A second SIGTERM while the command stops is ignored: ``timeout``
  and job controls signal the command and then its process group, and the second signal would
  break off the first one's clean-up, or land while Python shuts down and print a traceback.
  Once the command has ended, :func:`ignore_stops` ignores both signals for good.
- **A stop is never lost.** Python runs a signal's handler wherever the main thread is, also in a
  weak reference's callback or a ``__del__``, where an exception cannot propagate: Python prints
  it as "Exception ignored in ..." with a traceback and goes on. Such an interrupt is sent again
  from another thread, a few milliseconds later (:func:`redeliver_lost_interrupts`).

``pidlab train``, ``experiment`` and ``run`` install handlers of their own while they train (a
polite stop at the next step, a second signal stops at once).
"""

from __future__ import annotations

import contextlib
import functools
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

STOPPING = threading.Event()
"""Set once SIGTERM has raised :class:`KeyboardInterrupt` in the running command."""

RESEND_DELAY_S = 0.01
"""How soon an interrupt lost in a finalizer is sent again (:func:`redeliver_lost_interrupts`)."""


def _interrupt(signum: int, frame: Any) -> None:
    """SIGTERM stops a command as Ctrl-C does (clean-up runs, exit 130), once.

    A second SIGTERM while it stops changes nothing and is ignored: a job control that signals
    the command and then its process group (``timeout``, ``kill -- -PGID``) sends two, and the
    second one would break off the clean-up of the first.
    """
    if STOPPING.is_set():
        return
    STOPPING.set()
    raise KeyboardInterrupt


def _send_again() -> None:
    import _thread

    time.sleep(RESEND_DELAY_S)
    _thread.interrupt_main(signal.SIGTERM)  # nothing, once the command's handler is gone


def redeliver_lost_interrupts(unraisable: Any, previous: Callable[[Any], None]) -> None:
    """``sys.unraisablehook`` while a command runs: an interrupt that landed in a finalizer is sent again.

    Python runs a signal's handler wherever the main thread is, also inside a weak reference's
    callback or a ``__del__``; the :class:`KeyboardInterrupt` raised there cannot propagate, so
    Python would print it as "Exception ignored in ..." with a traceback, and the command would go
    on as if no one had asked it to stop. Instead SIGTERM (whose handler is :func:`_interrupt`)
    is sent again from another thread, so that it arrives after the finalizer.
    """
    if not isinstance(unraisable.exc_value, KeyboardInterrupt):
        previous(unraisable)
        return
    STOPPING.clear()  # that stop was lost
    try:
        threading.Thread(target=_send_again, name="pidlab-interrupt", daemon=True).start()
    except RuntimeError:  # Python is shutting down: the command has ended
        pass


@contextlib.contextmanager
def sigterm_interrupts() -> Iterator[None]:
    """While a command runs, SIGTERM raises :class:`KeyboardInterrupt` (main thread only).

    An interrupt raised inside a finalizer is not lost: :func:`redeliver_lost_interrupts`.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    STOPPING.clear()
    old = signal.signal(signal.SIGTERM, _interrupt)
    previous = sys.unraisablehook
    sys.unraisablehook = functools.partial(redeliver_lost_interrupts, previous=previous)
    try:
        yield
    finally:
        sys.unraisablehook = previous
        signal.signal(signal.SIGTERM, old)


def ignore_stops() -> None:
    """Ignore SIGINT and SIGTERM from now on (main thread only): the command has ended.

    A signal then would change nothing, and raised while Python shuts down it printed a traceback
    after the command's last line.
    """
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_IGN)
