"""Worker processes that notice when the process that started them is gone."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable


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
