"""How far a sweep has come, in env steps: read from its runs' logs while they train.

A sweep of SAC runs can spend hours in one run; counting finished runs alone shows nothing for
that long. Each run appends a row to its ``episodes.csv`` at the end of every training episode,
flushed at once (:class:`pidlab.rl.rundir.CsvLog`), and the row holds ``env_steps_so_far``. Its
last complete row is the run's progress; a finished run (``summary.json``) counts its whole budget.

Reading progress never fails a sweep: a log that is missing, empty or damaged counts as no
progress, and the run's own resume or report says what is wrong with it.
"""

from __future__ import annotations

import os
from pathlib import Path

from pidlab.errors import PidlabError
from pidlab.rl.rundir import finished_summary

TAIL_BYTES = 4096
"""How much of the end of ``episodes.csv`` is read: several rows of the widest log."""
STEPS_COLUMN = "env_steps_so_far"


def _last_complete_row(path: Path) -> tuple[str, str] | None:
    """The header and the last newline-terminated row after it, or None (also for a pipe or folder)."""
    if not path.is_file():
        return None
    with path.open("rb") as fh:
        header = fh.readline(TAIL_BYTES)  # a damaged log without newlines is not read whole
        fh.seek(0, os.SEEK_END)
        size = fh.tell()
        start = max(len(header), size - TAIL_BYTES)
        fh.seek(start)
        tail = fh.read()
    lines = tail.split(b"\n")[:-1]  # what follows the last newline is a row being written
    if start > len(header):
        lines = lines[1:]  # the read began inside a row
    if not header.endswith(b"\n") or not lines or not lines[-1].strip():
        return None
    return header.decode("utf-8", "replace").strip(), lines[-1].decode("utf-8", "replace")


def logged_env_steps(run_dir: Path) -> int:
    """The env steps a run's ``episodes.csv`` has reached: its last complete row's, else 0.

    Parameters
    ----------
    run_dir : Path
        A run directory (:mod:`pidlab.rl.train`).

    Returns
    -------
    int
        ``env_steps_so_far`` of the last complete row; 0 when the log is missing, holds no row, or
        the row is not a whole non-negative number.
    """
    try:
        found = _last_complete_row(run_dir / "episodes.csv")
    except OSError:
        return 0
    if found is None:
        return 0
    header, row = found
    columns = header.split(",")
    fields = row.split(",")
    if STEPS_COLUMN not in columns or len(fields) != len(columns):
        return 0
    text = fields[columns.index(STEPS_COLUMN)].strip()
    return int(text) if text.isdigit() else 0


def steps_done(run_dir: Path, budget: int) -> int:
    """A run's progress in env steps, within ``[0, budget]``: its budget once it has finished.

    Parameters
    ----------
    run_dir : Path
        The run directory.
    budget : int
        The run's budget in env steps.

    Returns
    -------
    int
    """
    try:
        if finished_summary(run_dir, budget) is not None:
            return budget
    except (PidlabError, OSError):
        pass
    return min(budget, logged_env_steps(run_dir))
