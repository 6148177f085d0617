"""Provenance: what a run, an experiment or a pipeline records so that it can be reproduced.

One record type serves all three (``run.json``, ``experiment.json``, ``pipeline.json``)::

    schema     what kind of record, versioned ("pidlab.run/1", "pidlab.experiment/1", ...)
    created    when the folder was started (local time, ISO 8601)
    command    the command line that started it
    versions   Python, the platform and the packages (:func:`package_versions`)
    git        pidlab's commit and whether its tree was dirty (:func:`git_state`)
    identity   what makes two folders the same (experiments, pipelines); absent for a run
    ...        the kind's own fields (a run's seed, an experiment's backend, a pipeline's stages)
    resumes    one entry per later session: at, command, versions, git and the kind's own fields

:func:`check_folder` is the one folder guard: it says whether a folder is new, holds this very
record (to resume), or must be refused. :func:`hold_lock` is the one lock: every command that writes
into a run, an experiment or a pipeline folder (or into a coach spec) holds it for as long as it
runs. :func:`digest` is the one digest of settings and specs.

Records written before this module (run.json with ``started``, experiment.json resumes keyed
``time``, pipeline.json without a top-level ``schema``) are read with the new names and written
back with them on the next write (:func:`record_from_dict`).
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import platform
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from importlib import metadata
from pathlib import Path
from typing import Any

from pidlab.checks import exists
from pidlab.errors import PidlabError
from pidlab.files import check_output_folder, make_folder, read_file, write_json

PACKAGES = (
    "pidlab",
    "numpy",
    "scipy",
    "torch",
    "stable-baselines3",
    "gymnasium",
    "mujoco",
    "control",
    "casadi",
    "tensorboard",
)
TIME_FORMAT = "%Y-%m-%dT%H:%M:%S%z"
LOCK_NAME = ".pidlab.lock"
"""The lock file :func:`hold_lock` keeps in a folder while a command works in it (holds its pid)."""
COMMON_FIELDS = ("schema", "created", "command", "versions", "git", "identity", "resumes")
RESUME_FIELDS = ("at", "command", "versions", "git")


def package_versions() -> dict[str, str]:
    """Versions of Python, the platform and the packages a run depends on."""
    out = {"python": sys.version.split()[0], "platform": platform.platform()}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def git_state(folder: str | Path | None = None) -> dict[str, Any]:
    """The git commit of pidlab's source tree and whether it has uncommitted changes.

    Returns ``{"sha": None, ...}`` outside a git checkout.
    """
    folder = Path(folder) if folder else Path(__file__).resolve().parents[1]

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(
                ["git", *args], cwd=folder, capture_output=True, text=True, timeout=10, check=False
            )
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    sha = git("rev-parse", "HEAD")
    status = git("status", "--porcelain", "--untracked-files=no") if sha else None
    return {"sha": sha, "dirty": bool(status) if status is not None else None}


def now() -> str:
    """The local time as records write it, e.g. ``2026-11-22T21:25:07+0000``."""
    return time.strftime(TIME_FORMAT)


def digest(data: Any, length: int | None = None) -> str:
    """SHA-256 (hex) of ``data``: the one digest of settings, specs and identities.

    Parameters
    ----------
    data : str, bytes or JSON-able
        A ``str`` is hashed as its UTF-8 text, ``bytes`` as they are, anything else as
        ``json.dumps(data, sort_keys=True, default=str)`` (so key order does not matter).
    length : int, optional
        Keep the first ``length`` hex digits (default: all 64).
    """
    if isinstance(data, bytes):
        raw = data
    elif isinstance(data, str):
        raw = data.encode("utf-8")
    else:
        raw = json.dumps(data, sort_keys=True, default=str).encode("utf-8")
    return hashlib.sha256(raw).hexdigest()[:length]


@dataclass(frozen=True)
class Resume:
    """One later session of a run, an experiment or a pipeline.

    ``versions`` is None in entries written before resumes recorded them; ``extra`` holds the
    kind's own fields (an experiment's ``backend``, a run's ``from_env_steps``).
    """

    at: str
    command: tuple[str, ...]
    versions: dict[str, str] | None
    git: dict[str, Any]
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """The entry as JSON writes it."""
        out: dict[str, Any] = {"at": self.at, "command": list(self.command)}
        if self.versions is not None:
            out["versions"] = dict(self.versions)
        return {**out, "git": dict(self.git), **self.extra}


@dataclass(frozen=True)
class Record:
    """What a run directory, an experiment or a pipeline folder records about itself.

    Attributes
    ----------
    schema : str
        E.g. ``"pidlab.experiment/1"``.
    created : str
        When it was started.
    command : tuple of str
    versions : dict
        :func:`package_versions` at the start.
    git : dict
        :func:`git_state` at the start.
    identity : dict or None
        What makes two folders the same (compared by :func:`check_folder`).
    extra : dict
        The kind's own fields, written beside the common ones.
    resumes : tuple of Resume
    """

    schema: str
    created: str
    command: tuple[str, ...]
    versions: dict[str, str]
    git: dict[str, Any]
    identity: dict[str, Any] | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    resumes: tuple[Resume, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """The record as JSON writes it (common fields first, resumes last)."""
        out: dict[str, Any] = {"schema": self.schema, "created": self.created, "command": list(self.command),
                               "versions": dict(self.versions), "git": dict(self.git)}  # fmt: skip
        if self.identity is not None:
            out["identity"] = self.identity
        return {**out, **self.extra, "resumes": [r.to_dict() for r in self.resumes]}

    def with_extra(self, **fields: Any) -> Record:
        """The same record with the kind's fields ``fields`` set (a value of None removes one)."""
        extra = {**self.extra, **fields}
        return replace(self, extra={k: v for k, v in extra.items() if v is not None})


def _kind_fields(fields: Mapping[str, Any], common: Sequence[str]) -> dict[str, Any]:
    clash = set(fields) & set(common)
    if clash:
        raise ValueError(f"extra fields {sorted(clash)} would overwrite the record's own")
    return dict(fields)


def new_record(
    schema: str,
    command: Sequence[str],
    *,
    identity: dict[str, Any] | None = None,
    extra: Mapping[str, Any] | None = None,
) -> Record:
    """A new record, started now, with this machine's versions and pidlab's git state.

    Parameters
    ----------
    schema : str
    command : sequence of str
        The command line to record.
    identity : dict, optional
        What makes two folders the same.
    extra : mapping, optional
        The kind's own fields (must not reuse a common field's name).
    """
    return Record(
        schema=schema,
        created=now(),
        command=tuple(command),
        versions=package_versions(),
        git=git_state(),
        identity=identity,
        extra=_kind_fields(extra or {}, COMMON_FIELDS),
    )


def add_resume(record: Record, command: Sequence[str], **extra: Any) -> Record:
    """``record`` with one more resume: now, ``command``, versions, git state and ``extra``."""
    entry = Resume(now(), tuple(command), package_versions(), git_state(), _kind_fields(extra, RESUME_FIELDS))
    return replace(record, resumes=(*record.resumes, entry))


def _resume_from_dict(data: Mapping[str, Any]) -> Resume:
    at = data.get("at", data.get("time", ""))  # "time": experiment.json and run.json before 2026-11
    extra = {k: v for k, v in data.items() if k not in (*RESUME_FIELDS, "time")}
    versions = data.get("versions")
    return Resume(str(at), tuple(data.get("command", ())), dict(versions) if versions is not None else None,
                  dict(data.get("git", {})), extra)  # fmt: skip


def record_from_dict(data: Mapping[str, Any], schema: str) -> Record:
    """A record from its JSON, with the names of records written before this module migrated.

    ``started`` (old run.json) becomes ``created``, a resume's ``time`` becomes ``at``, and a
    record without ``schema`` (old run.json and pipeline.json) gets ``schema``. Every other field
    is kept as it was, in ``extra`` (an ``identity`` that is not a JSON object reads as None).

    Parameters
    ----------
    data : mapping
        The parsed JSON object.
    schema : str
        The schema of the kind of record expected (given to records that have none).
    """
    created = data.get("created", data.get("started", ""))
    extra = {k: v for k, v in data.items() if k not in (*COMMON_FIELDS, "started")}
    identity = data.get("identity")
    return Record(
        schema=str(data.get("schema", schema)),
        created=str(created),
        command=tuple(data.get("command", ())),
        versions=dict(data.get("versions", {})),
        git=dict(data.get("git", {})),
        identity=dict(identity) if isinstance(identity, Mapping) else None,
        extra=extra,
        resumes=tuple(_resume_from_dict(r) for r in data.get("resumes", ()) if isinstance(r, Mapping)),
    )


def _load(path: Path, schema: str) -> Record | str:
    """The record in ``path``, or why it is none (unreadable, damaged, not a JSON object)."""
    try:
        data = json.loads(read_file(path).decode("utf-8"))
    except OSError as exc:
        return f"unreadable: {exc.strerror or exc}"
    except UnicodeDecodeError:
        return "not UTF-8 text"
    except (ValueError, RecursionError) as exc:
        return f"damaged: not valid JSON: {exc}"
    if not isinstance(data, dict):
        return "not a JSON object"
    try:
        return record_from_dict(data, schema)
    except (TypeError, ValueError):
        return "damaged: a field of the wrong type"


def read_record(path: str | Path, schema: str, error: type[PidlabError] = PidlabError) -> Record:
    """Read a record file (migrating old field names, see :func:`record_from_dict`).

    Raises
    ------
    PidlabError
        Of class ``error``, in one line naming the file: it is unreadable, damaged (cut short,
        not JSON, not text) or holds no JSON object.
    """
    record = _load(Path(path), schema)
    if isinstance(record, str):
        raise error(f"{path}: not a pidlab record ({record})")
    return record


def write_record(path: str | Path, record: Record) -> Path:
    """Write ``record`` to ``path`` atomically, with the current field names."""
    return write_json(path, record.to_dict())


@dataclass(frozen=True)
class Refusals:
    """The caller's one-line messages for a folder :func:`check_folder` refuses.

    Attributes
    ----------
    not_a_folder : str
        The path exists and is a file.
    not_a_record : str
        The record file is unreadable or holds no JSON object.
    not_ours : str
        The folder holds files but no record file.
    another : callable
        ``another(record)``: the folder holds another run, experiment or pipeline; the message
        says what differs.
    """

    not_a_folder: str
    not_a_record: str
    not_ours: str
    another: Callable[[Record], str]


def check_folder(
    folder: str | Path,
    filename: str,
    schema: str,
    identity: dict[str, Any] | None,
    refusals: Refusals,
    error: type[PidlabError],
    param: str | None = None,
) -> Record | None:
    """The one folder guard: may ``folder`` hold this run, experiment or pipeline? Nothing is written.

    Parameters
    ----------
    folder : path
    filename : str
        The record's file in it, e.g. ``"experiment.json"``.
    schema : str
        The record's schema (records without one are taken as this kind's old records).
    identity : dict or None
        What the record must say to be this folder's (compared with ``Record.identity``).
    refusals : Refusals
        The caller's messages.
    error : type
        The caller's error class.
    param : str, optional
        The parameter that named the folder (the errors carry it).

    Returns
    -------
    Record or None
        The folder's record when it holds this very one (resume); None when the folder does
        not exist or is empty (new). A lock file (:data:`LOCK_NAME`) does not count: a folder
        that holds only the one a killed command left is empty.

    Raises
    ------
    PidlabError
        Of class ``error``, with one of ``refusals``' messages.
    OutputError
        The folder cannot be created or written (a file in its path, a read-only folder).
    """
    folder = Path(folder)
    if exists(folder) and not folder.is_dir():
        raise error(refusals.not_a_folder, param=param)
    check_output_folder(folder, param)  # a folder that cannot be made or written (or named): refused now
    path = folder / filename
    if path.exists():
        record = _load(path, schema)
        if isinstance(record, str):
            raise error(refusals.not_a_record, param=param)
        if record.schema != schema or record.identity != identity:
            raise error(refusals.another(record), param=param)
        return record
    if folder.exists() and any(p.name != LOCK_NAME for p in folder.iterdir()):
        raise error(refusals.not_ours, param=param)
    return None


# --------------------------------------------------------------------------- the lock

_HELD: dict[Path, int] = {}  # lock file -> how many blocks of this process hold it
_HELD_GUARD = threading.Lock()


def _lock_file(target: Path) -> Path:
    """The file to flock for ``target``: a file itself, a folder's :data:`LOCK_NAME`."""
    return target if target.is_file() else target / LOCK_NAME


def _flock_pid(st: os.stat_result) -> int | None:
    """The pid holding a flock on the file of ``st``, from /proc/locks (Linux); None when none is seen."""
    key = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    try:
        with open("/proc/locks", encoding="ascii", errors="replace") as fh:
            for line in fh:
                parts = line.split()
                if len(parts) > 5 and parts[1] == "FLOCK" and parts[5] == key and parts[4].isdigit():
                    return int(parts[4])
    except OSError:
        pass
    return None


def lock_holder(target: str | Path) -> int | None:
    """The pid of the process that holds the lock of ``target`` now, or None.

    Read from /proc/locks: nothing is opened for writing, created or locked, so it can be asked
    while a sweep works in the folder. Where /proc/locks is missing (not Linux) it says None.
    """
    try:
        return _flock_pid(os.stat(_lock_file(Path(target))))
    except OSError:
        return None


def _holder(fd: int) -> int | None:
    """The pid holding the flock on ``fd``'s file: from /proc/locks (Linux), else from the file."""
    pid = _flock_pid(os.fstat(fd))
    if pid is not None:
        return pid
    try:
        text = os.pread(fd, 32, 0).decode("ascii", errors="replace").strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


@dataclass(frozen=True)
class _Found:
    """A lock file as this command found it (a killed command's): put back when the command fails.

    A refused command changes nothing, the lock file a killed command left included.
    """

    data: bytes
    times_ns: tuple[int, int]


def _open_lock(path: Path, folder_lock: bool) -> tuple[int, bool]:
    """Open the lock file ``path`` (a folder's is created when missing): (fd, whether it was created)."""
    if not folder_lock:
        return os.open(path, os.O_RDONLY), False
    for _ in range(3):
        try:
            return os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644), True
        except FileExistsError:
            pass
        try:
            return os.open(path, os.O_RDWR), False
        except FileNotFoundError:  # removed in between (its holder ended): create it
            continue
    return os.open(path, os.O_RDWR | os.O_CREAT, 0o644), False  # e.g. a dangling symlink


def _try_flock(path: Path, folder_lock: bool) -> tuple[int, bool, _Found | None]:
    """Open ``path`` and try to flock it: (fd, True, found) when this process now holds it.

    ``found`` is the lock file as it was when this process did not create it (a killed
    command's), else None. A lock taken on a file that was meanwhile unlinked or replaced (its
    holder removed it on release, or a file target was rewritten) is not the lock of ``path``:
    (-1, True, None) says "try again". (fd, False, None): another process holds it; the caller
    closes ``fd``.
    """
    fd, created = _open_lock(path, folder_lock)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return fd, False, None
    held = os.fstat(fd)
    try:
        there = os.stat(path)
        same = (there.st_dev, there.st_ino) == (held.st_dev, held.st_ino)
    except FileNotFoundError:
        same = False
    if not same:
        os.close(fd)
        return -1, True, None
    if not folder_lock or created:
        return fd, True, None
    return fd, True, _Found(os.pread(fd, held.st_size, 0), (held.st_atime_ns, held.st_mtime_ns))


def _acquire(path: Path, folder_lock: bool, shown: str, error: type[PidlabError], param: str | None,
             wait_s: float) -> tuple[int, _Found | None]:  # fmt: skip
    """Flock ``path`` for this process (waiting up to ``wait_s`` seconds): its fd, and the file found."""
    deadline = time.monotonic() + wait_s
    while True:
        try:
            fd, mine, found = _try_flock(path, folder_lock)
        except OSError as exc:
            reason = exc.strerror or exc
            raise error(f"{shown}: cannot take its lock {path.name}: {reason}", param=param) from None
        if mine and fd >= 0:
            return fd, found
        if not mine:
            pid = _holder(fd)
            os.close(fd)
            if time.monotonic() >= deadline:
                by = f" (pid {pid})" if pid is not None else ""
                raise error(
                    f"{shown}: in use by another pidlab command{by}; nothing was changed. "
                    "Wait for it to end (or stop it), then run this again",
                    param=param,
                )
            time.sleep(0.1)


def _release(fd: int, path: Path, folder_lock: bool, found: _Found | None) -> None:
    """Release the lock on ``fd``; a folder's lock file is removed, or (``found``) put back as it was."""
    if not folder_lock:
        pass
    elif found is None:
        path.unlink(missing_ok=True)  # before the release: a waiter then retries on a new file
    else:
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, found.data, 0)
            os.utime(fd, ns=found.times_ns)
        except OSError:
            pass  # the lock file of a killed command: nobody reads more than its name
    os.close(fd)


def _remove_empty(folders: Sequence[Path]) -> None:
    """Remove ``folders`` (deepest first) while they are empty."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            break


def _missing_folders(folder: Path) -> list[Path]:
    """``folder`` and those of its parents that do not exist, deepest first."""
    missing = []
    while not folder.exists() and folder != folder.parent:
        missing.append(folder)
        folder = folder.parent
    return missing


@contextmanager
def hold_lock(
    target: str | Path,
    error: type[PidlabError],
    *,
    param: str | None = None,
    wait_s: float = 0.0,
) -> Iterator[Path]:
    """Hold the exclusive lock of a folder (or of a file) for the duration of the block.

    Every command that writes into a run, an experiment or a pipeline folder, or rewrites a
    coach spec, holds it from its first write to its end, so two commands never work in one
    folder. It is an ``fcntl.flock``: the OS releases it when its process ends in any way
    (SIGKILL too), so a lock is never left behind by a killed command.

    A folder's lock is the file :data:`LOCK_NAME` in it (created, with the folder and its
    parents, when missing; it holds the pid of its holder and is removed on release). The folder
    guard :func:`check_folder` ignores it, and folders this call created are removed again when
    they are still empty at the end. A block that ends with an exception (a refusal) leaves the
    lock file as it found it: a killed command's file is put back, bytes and times, not removed.
    A file's lock is the file itself (nothing is created).
    Within one process the lock is re-entrant: a block inside a block that holds it is a no-op.

    Parameters
    ----------
    target : path
        The folder (existing or not) or the existing file to lock.
    error : type
        The caller's error class.
    param : str, optional
        The parameter that named ``target`` (the message then starts with ``param=``).
    wait_s : float
        How long to wait for another process to release it (default: not at all).

    Yields
    ------
    Path
        The lock file.

    Raises
    ------
    PidlabError
        Of class ``error``, in one line: another process holds the lock (its pid, where known),
        or the lock cannot be taken (a read-only folder, ...). Nothing was changed then.
    OutputError
        The folder cannot be created, or is read-only.
    """
    target = Path(target).resolve()
    shown = f"{param}={target}" if param else str(target)
    created = [] if target.is_file() else _missing_folders(target)
    if not target.is_file():
        check_output_folder(target, param)  # a read-only folder gets no lock file either
    if created:
        make_folder(target, param)
    path = _lock_file(target)
    with _HELD_GUARD:
        depth = _HELD.get(path, 0)
        _HELD[path] = depth + 1
    fd, found, failed = -1, None, False
    try:
        if depth == 0:
            fd, found = _acquire(path, path != target, shown, error, param, wait_s)
            if path != target:
                os.ftruncate(fd, 0)
                os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
        yield path
    except BaseException:
        failed = True
        raise
    finally:
        with _HELD_GUARD:
            _HELD[path] -= 1
            if _HELD[path] == 0:
                del _HELD[path]
        if fd >= 0:
            _release(fd, path, path != target, found if failed else None)
        _remove_empty(created)
