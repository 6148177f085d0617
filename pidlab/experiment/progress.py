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
from dataclasses import dataclass
from pathlib import Path

from pidlab.errors import PidlabError
from pidlab.provenance import lock_holder
from pidlab.rl.rundir import checkpoint_folders, finished_summary, read_state

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


RUN_STATES = ("finished", "under way", "not started", "damaged")
"""What :func:`run_progress` finds a run to be."""


@dataclass(frozen=True)
class RunProgress:
    """Where one run of a sweep stands, read from its folder; nothing is written.

    Attributes
    ----------
    state : str
        One of :data:`RUN_STATES`: ``finished`` (its summary says it completed its budget),
        ``under way`` (a checkpoint, a logged episode, or a process training it now), ``not
        started``, or ``damaged`` (its summary or newest checkpoint cannot be read; ``problem``
        says what, as its resume does).
    checkpointed : int
        Env steps of the newest checkpoint that reads (its budget once finished): where a resume
        starts, falling back past a damaged one as a resume does.
    logged : int
        Env steps its ``episodes.csv`` has reached (:func:`logged_env_steps`), at most its budget.
    training : bool
        A process holds the run's lock now (:func:`pidlab.provenance.lock_holder`).
    problem : str
        For a damaged run, the first line of what is wrong.
    """

    state: str
    checkpointed: int
    logged: int
    training: bool
    problem: str = ""


def run_progress(run_dir: Path, budget: int) -> RunProgress:
    """Where the run in ``run_dir`` stands against its ``budget`` of env steps.

    Parameters
    ----------
    run_dir : Path
        The run directory (it need not exist yet).
    budget : int
        The run's budget in env steps.

    Returns
    -------
    RunProgress
    """
    training = lock_holder(run_dir) is not None if run_dir.is_dir() else False
    logged = min(budget, logged_env_steps(run_dir))
    summary_problem = ""
    try:
        if finished_summary(run_dir, budget) is not None:
            return RunProgress("finished", budget, budget, training)
    except (PidlabError, OSError) as exc:
        summary_problem = _first_line(exc)
    checkpointed, problem = _resume_point(run_dir)
    problem = summary_problem or problem
    if problem:
        return RunProgress("damaged", min(checkpointed, budget), logged, training, problem)
    state = "under way" if checkpointed or logged or training else "not started"
    return RunProgress(state, min(checkpointed, budget), logged, training)


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


def _resume_point(run_dir: Path) -> tuple[int, str]:
    """Env steps of the newest checkpoint that reads, and what is wrong with the newest if it does not.

    A resume does the same: it falls back past a damaged checkpoint to the previous one.
    """
    problem = ""
    for folder in reversed(checkpoint_folders(run_dir)):
        try:
            return read_state(folder)["env_steps"], problem
        except (PidlabError, OSError) as exc:
            problem = problem or _first_line(exc)
    return 0, problem

