"""Helpers shared by the tests: the repository's folders and the in-process command line.

Fixtures live in ``conftest.py``; everything a test imports lives here (no test imports from
``conftest``).
"""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
"""The checkout."""
TUNING = ROOT / "tuning"
MODELS = ROOT / "models"
COACH = ROOT / "coach"
DATA = Path(__file__).resolve().parent / "data"
"""Test data: MJCF files and the bad-input corpus."""
PAPER_ENVS = ("InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Hopper-v5", "Walker2d-v5")


def cli_in_process(*args: str) -> tuple[int, str]:
    """Run the ``pidlab`` command line in this process: (exit code, stderr).

    The parametrized bad-input tests use it (a subprocess costs ~5 s of imports each); one
    case per verb still runs the real ``pidlab`` executable.
    """
    from typer.testing import CliRunner

    from pidlab.cli import app

    result = CliRunner().invoke(app, list(args))
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise result.exception
    return result.exit_code, result.stderr
