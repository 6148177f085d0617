"""How every benchmark script reads its command line and ends: bad input in one line and exit 2.

The ``pidlab`` commands print ``pidlab: error: ...`` and exit 2 on bad input (pidlab/cli/main.py);
the benchmark scripts do the same through this module:

- :class:`Parser` is :class:`argparse.ArgumentParser` with a one-line error (no usage block);
- :func:`count`, :func:`counts`, :func:`positive`, :func:`seconds` and :func:`names` are argument
  types that refuse a value before any work starts (a count below 1, a non-finite or negative
  number, a name not on the list);
- :func:`run` runs a script's ``main``: an error pidlab raises for bad input
  (:class:`pidlab.errors.PidlabError`) or a file that cannot be read or written (:class:`OSError`)
  becomes the script's one line and exit code 2, Ctrl-C (or SIGTERM) exit code 130. Any other
  exception is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import NoReturn

from pidlab.errors import PidlabError
from pidlab.interrupts import ignore_stops, sigterm_interrupts

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130


def _prog() -> str:
    """The running script's name, as argparse shows it."""
    return Path(sys.argv[0]).name or "benchmark"


def fail(message: str) -> NoReturn:
    """Print ``SCRIPT: error: MESSAGE`` on one line (line breaks shown escaped) and exit 2."""
    message = message.replace("\r", "\\r").replace("\n", "\\n")
    print(f"{_prog()}: error: {message}", file=sys.stderr)
    sys.exit(EXIT_BAD_INPUT)


class Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors take one line (``SCRIPT: error: ...``) and exit 2."""

    def error(self, message: str) -> NoReturn:
        fail(f"{message} (see {self.prog} --help)")


def count(text: str) -> int:
    """An argument type: a whole number of at least 1 (states, steps, repeats, workers)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a whole number >= 1") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a whole number >= 1")
    return value


def counts(text: str) -> list[int]:
    """An argument type: comma-separated whole numbers of at least 1 (``1,2``: worker counts)."""
    return [count(s.strip()) for s in text.split(",")]


def positive(text: str) -> float:
    """An argument type: a finite number above 0 (seconds, a standard deviation)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a finite number > 0") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a finite number > 0")
    return value


def seconds(text: str) -> float:
    """An argument type: a finite number of seconds, 0 or more."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a finite number of seconds >= 0") from None
    if not math.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a finite number of seconds >= 0")
    return value


def names(allowed: Iterable[str]) -> Callable[[str], str]:
    """An argument type: comma-separated names, each one of ``allowed`` and none twice.

    The value stays a string (the names joined by commas, spaces removed), as the scripts print it
    back in the command that made their page.
    """
    known = list(allowed)

    def parse(text: str) -> str:
        items = [s.strip() for s in text.split(",")]
        for item in items:
            if item not in known:
                raise argparse.ArgumentTypeError(f"{item!r}: expected names among {', '.join(known)}")
        if len(set(items)) != len(items):
            raise argparse.ArgumentTypeError(f"{text!r}: a name is given twice")
        return ",".join(items)

    return parse


def run(main: Callable[[], int | None]) -> NoReturn:
    """Run a script's ``main`` and exit with its code (0 for ``None``); bad input exits 2 in one line.

    SIGTERM stops a script as Ctrl-C does, once (:mod:`pidlab.interrupts`, as for ``pidlab``).
    """
    try:
        with sigterm_interrupts():
            code = main()
    except PidlabError as exc:
        fail(str(exc))
    except OSError as exc:
        where = f" {exc.filename!r}" if exc.filename else ""
        fail(f"cannot read or write{where}: {exc.strerror or exc}")
    except KeyboardInterrupt:
        print(f"{_prog()}: interrupted", file=sys.stderr)
        sys.exit(EXIT_INTERRUPTED)
    finally:
        ignore_stops()
    sys.exit(code or 0)
