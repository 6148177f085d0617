"""Rescue outcomes kept on disk as they are found, so that a long estimate resumes where it stopped.

A classifier region is fitted on tens of thousands of labelled states, each a MuJoCo simulation of
the coach (on Hopper and Walker2d, an hour or more of them). :class:`LabelJournal` keeps every
outcome the moment its chunk of simulations is done, one file per chunk, each written atomically
(a temporary file renamed into place). An estimate run again with the same command draws the same
states from its seed, finds their outcomes in the journal and simulates only the rest; the result
is the same as an uninterrupted run's.

An outcome is keyed by its start (the MuJoCo state, and the agent step before the rescue, if any),
inside a folder named by the digest of everything else that decides it (:func:`journal_key` of
:func:`pidlab.region.rescue.outcome_facts`: the coach's law and certified core, the env, the
compiled model and its card, the horizon, whether starts are put on the floor, where a rescue
ends, and the versions of pidlab, MuJoCo and Gymnasium). A journal of another coach or setting lies in another
folder and is never read. A chunk file that cannot be read (cut short, edited) is ignored: its
states are simulated again.
"""

from __future__ import annotations

import io
import shutil
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from pidlab.errors import RegionError
from pidlab.files import atomic_write_bytes, open_binary
from pidlab.provenance import digest

CHUNK = 2000
"""Simulations between two writes of the journal (a run stopped loses at most one chunk's work)."""

Outcome = tuple[bool, np.ndarray]
"""A simulation's outcome: rescued, and the start's observation."""

Start = tuple[np.ndarray, "np.ndarray | None"]
"""A simulation's start: the MuJoCo state, and the agent step before the rescue (or none)."""


def start_key(x: np.ndarray, kick: np.ndarray | None) -> bytes:
    """The journal's key of one start: the MuJoCo state ``x`` and the agent step ``kick`` (or none)."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    if kick is None:
        return b"-" + x.tobytes()
    return b"k" + x.tobytes() + np.ascontiguousarray(kick, dtype=np.float64).tobytes()


def journal_key(facts: dict[str, Any]) -> str:
    """The folder name of a journal: the digest of what decides an outcome besides its start."""
    return digest(facts, 16)


class LabelJournal:
    """The outcomes found so far, in ``folder`` (made on the first write).

    Parameters
    ----------
    folder : path
        This journal's own folder (one per :func:`journal_key`).

    Raises
    ------
    RegionError
        ``folder``, or the folder it lies in, exists and is not a folder.
    """

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        for path in (self.folder, self.folder.parent):
            if path.exists() and not path.is_dir():
                raise RegionError(f"{path}: the labels' journal must be a folder; move that file away")
        self._known: dict[bytes, Outcome] = {}
        self._written = 0
        self.loaded = 0
        self.skipped: list[str] = []
        for path in sorted(self.folder.glob("chunk-*.npz")):
            self._read(path)
        self.loaded = len(self._known)

    def __len__(self) -> int:
        return len(self._known)

    def _read(self, path: Path) -> None:
        """Take in one chunk file; one that cannot be read is left out (its states are simulated again)."""
        self._written = max(self._written, _number(path))
        try:
            with open_binary(path) as fh, np.load(fh, allow_pickle=False) as f:
                starts, kicks, kicked, ok, obs = (f[k] for k in ("starts", "kicks", "kicked", "ok", "obs"))
            if not (starts.ndim == kicks.ndim == obs.ndim == 2 and len(starts) == len(kicks) == len(kicked)
                    == len(ok) == len(obs)):  # fmt: skip
                raise ValueError("arrays of different lengths")
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            self.skipped.append(f"{path.name} ({exc})")
            return
        for x, k, has, rescued, o in zip(starts, kicks, kicked, ok, obs, strict=True):
            self._known[start_key(x, k if has else None)] = (bool(rescued), np.array(o, dtype=float))

    def get(self, start: Start) -> Outcome | None:
        """The outcome of ``start`` (``(x, kick)``), if the journal holds it."""
        return self._known.get(start_key(*start))

    def record(self, starts: list[Start], outcomes: list[Outcome]) -> None:
        """Keep ``outcomes`` of ``starts`` (``(x, kick)`` pairs): one chunk file, written atomically."""
        if not starts:
            return
        self.folder.mkdir(parents=True, exist_ok=True)
        self._written += 1
        width = max((0 if k is None else len(k) for _, k in starts), default=0)
        kicks = np.full((len(starts), width), np.nan)
        for row, (_, k) in zip(kicks, starts, strict=True):
            if k is not None:
                row[:] = k
        buf = io.BytesIO()
        np.savez(
            buf, starts=np.array([x for x, _ in starts], dtype=float), kicks=kicks,
            kicked=np.array([k is not None for _, k in starts]), ok=np.array([o[0] for o in outcomes]),
            obs=np.array([o[1] for o in outcomes], dtype=float),
        )  # fmt: skip
        atomic_write_bytes(self.folder / f"chunk-{self._written:06d}.npz", buf.getvalue())
        for (x, k), outcome in zip(starts, outcomes, strict=True):
            self._known[start_key(x, k)] = outcome

    def remove(self) -> None:
        """Delete the journal's folder (its outcomes have been used)."""
        shutil.rmtree(self.folder, ignore_errors=True)
        parent = self.folder.parent
        if parent.exists() and not any(parent.iterdir()):
            parent.rmdir()


def drop_journal(folder: str | Path | None) -> None:
    """Delete a command's journal folder (every coach's and setting's), its outcomes now in what it wrote.

    None (no journal was kept) does nothing.
    """
    if folder is not None:
        shutil.rmtree(folder, ignore_errors=True)


def _number(path: Path) -> int:
    """The chunk file's number (0 for a name that has none)."""
    stem = path.stem.removeprefix("chunk-")
    return int(stem) if stem.isdigit() else 0
