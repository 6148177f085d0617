"""Files below every stage: atomic writes, JSON and TOML reading with one-line errors.

Every file pidlab writes goes through :func:`atomic_write_text` / :func:`atomic_write_bytes` (a
temporary file in the same folder, flushed, then renamed over the target), so a kill leaves either
the old file or the new one, never half of one.
"""

from __future__ import annotations

import errno
import io
import json
import os
import stat
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

from pidlab.checks import NAME_MAX_BYTES, clip, path_argument
from pidlab.errors import OutputError, PidlabError

if TYPE_CHECKING:
    from matplotlib.figure import Figure

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


def _writable(path: Path) -> bool:
    """Whether pidlab may change ``path``: the OS allows it and the mode has a write bit.

    The root user may write anything the OS lets it; pidlab still treats a file or folder without
    any write bit (``chmod a-w``) as read-only, for every user.
    """
    try:
        mode = path.stat().st_mode
    except OSError:
        return False
    return os.access(path, os.W_OK) and bool(mode & 0o222)


BOM = "\ufeff"
"""The byte order mark some editors put at the start of a UTF-8 file; pidlab reads past it."""

PATH_MAX_BYTES = 4096
"""Linux's limit on a whole path, in bytes (with its final NUL)."""


def _refusal(path: Path, reason: str, param: str | None) -> OutputError:
    """An :class:`OutputError` about ``path``: ``param=PATH: reason`` when a parameter named it."""
    head = f"{param}={clip(str(path), 200)!r}" if param else clip(str(path), 200)
    return OutputError(f"{head}: {reason}", param=param)


def _name_problem(path: Path) -> str | None:
    """Why the file system would refuse ``path``'s name (a NUL, a part over 255 bytes), or None."""
    text = str(path)
    if "\x00" in text:
        return "the path contains a NUL character"
    if any(len(part.encode("utf-8", "surrogateescape")) > NAME_MAX_BYTES for part in path.parts):
        return f"a part of the path is longer than {NAME_MAX_BYTES} bytes (file name too long)"
    if len(os.fsencode(text)) >= PATH_MAX_BYTES:
        return f"the path is longer than {PATH_MAX_BYTES - 1} bytes"
    return None


def _folder_problem(folder: Path) -> str | None:
    """Why no file can be written in ``folder`` (created with its parents if need be), or None."""
    problem = _name_problem(folder)
    if problem is not None:
        return problem
    try:
        return _existing_folder_problem(folder)
    except OSError as exc:  # the file system refused to even look (a loop of links, EACCES, ...)
        return exc.strerror or str(exc)


def _existing_folder_problem(folder: Path) -> str | None:
    if folder.exists() and not folder.is_dir():
        return f"{folder} is a file, not a folder"
    base = folder
    while not base.exists() and base != base.parent:
        base = base.parent
    if not base.is_dir():
        return f"{base} is a file, not a folder"
    if not (_writable(base) and os.access(base, os.X_OK)):
        return f"the folder {base} is read-only"
    return None


def check_output_folder(folder: str | Path, param: str | None = None) -> Path:
    """Refuse a folder that pidlab could not create or write in; nothing is written.

    Call it before long work, so that a bad output place fails at once.

    Parameters
    ----------
    folder : path
        The folder to create (with its parents) or to write in.
    param : str, optional
        The parameter that named it (the error message starts with ``param=``).

    Raises
    ------
    OutputError
        ``folder`` (or a part of its path) is a file, or the folder where it would be created
        is read-only.
    """
    folder = path_argument(folder, param or "folder", OutputError, what="a folder's path")
    problem = _folder_problem(folder)
    if problem is not None:
        raise _refusal(folder, f"cannot write there: {problem}", param)
    return folder


def check_output_file(path: str | Path, param: str | None = None) -> Path:
    """Refuse a file that pidlab could not write (or replace); nothing is written.

    Parameters
    ----------
    path : path
        The file to write; it may exist (it is replaced, keeping its mode) or not.
    param : str, optional
        The parameter that named it.

    Raises
    ------
    OutputError
        ``path`` is a folder, a read-only file, a device, a named pipe or a socket, or lies where
        no file can be created.
    """
    path = path_argument(path, param or "path", OutputError, what="a file's path")
    problem = _name_problem(path)
    if problem is not None:
        raise _refusal(path, f"cannot write there: {problem}", param)
    if path.is_dir():
        raise _refusal(path, "is a folder; give a file name", param)
    special = _special_kind(path)
    if special is not None:  # replacing it would remove a device or a pipe (/dev/null, as root)
        raise _refusal(path, f"is {special}, not a file; pidlab writes regular files only", param)
    if path.exists() and not _writable(path):
        reason = "the file is read-only; pidlab does not replace it (make it writable first)"
        raise _refusal(path, reason, param)
    problem = _folder_problem(path.parent)
    if problem is not None:
        raise _refusal(path, f"cannot write there: {problem}", param)
    return path


def make_folder(folder: str | Path, param: str | None = None) -> Path:
    """Create ``folder`` and its parents (the one way pidlab makes a folder); returns it.

    Raises
    ------
    OutputError
        As :func:`check_output_folder`, or the OS refused (the reason in one line).
    """
    folder = check_output_folder(folder, param)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise _refusal(folder, f"cannot create the folder: {exc.strerror or exc}", param) from None
    return folder


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (temporary file, fsync, rename).

    A file that is replaced keeps its mode. On any failure (or an interrupt) the temporary file
    is removed and the old file, if any, is left as it was.

    Raises
    ------
    OutputError
        ``path`` is a folder or a read-only file, its folder cannot be made or written, or the
        write itself failed (no space left, name too long, ...).
    """
    path = check_output_file(path)
    make_folder(path.parent)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    replaced = False
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        if path.exists():
            os.chmod(tmp, stat.S_IMODE(path.stat().st_mode))
        os.replace(tmp, path)
        replaced = True
    except OSError as exc:
        refusal = _refusal(path, f"cannot write the file: {exc.strerror or exc}", None)
        refusal.errno = exc.errno  # a full disk stays recognizable (ENOSPC) to the callers that resume
        raise refusal from None
    finally:
        if not replaced:
            tmp.unlink(missing_ok=True)
    return path


def atomic_create_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically, only if no file is there: never replaces one.

    The text is written to a temporary file, then hard-linked to ``path``, which fails when a file
    appeared there in the meantime (another command's).

    Raises
    ------
    FileExistsError
        ``path`` exists (nothing was written).
    OutputError
        As :func:`atomic_write_bytes`.
    """
    path = check_output_file(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.new")
    atomic_write_text(tmp, text)
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise
    except OSError as exc:  # a file system without hard links, a full directory, ...
        raise _refusal(path, f"cannot write the file: {exc.strerror or exc}", None) from None
    finally:
        tmp.unlink(missing_ok=True)
    return path


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def write_json(path: str | Path, data: Any) -> Path:
    """Write ``data`` as indented JSON, atomically."""
    return atomic_write_text(path, json.dumps(data, indent=2, sort_keys=False) + "\n")


def read_json(path: str | Path) -> Any:
    """Read a JSON file (trusted: one pidlab wrote; see :func:`load_json` for one a user may have damaged)."""
    return json.loads(Path(path).read_text(encoding="utf-8"))


MAX_TEXT_BYTES = 64 * 2**20
"""The largest text file pidlab reads (a spec, recipe, record or run log is far smaller): a larger
one is refused in one line instead of being read into memory."""

_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a named pipe"), (stat.S_ISCHR, "a device"),
          (stat.S_ISBLK, "a device"), (stat.S_ISSOCK, "a socket"))  # fmt: skip


def _kind(mode: int) -> str:
    """What a file of ``mode`` that is no regular file is, in words."""
    return next((name for test, name in _KINDS if test(mode)), "no regular file")


def _special_kind(path: Path) -> str | None:
    """What ``path`` is when it exists and is neither a regular file nor a folder (a pipe, ...)."""
    try:
        mode = path.stat().st_mode
    except (OSError, ValueError):
        return None
    return None if stat.S_ISREG(mode) or stat.S_ISDIR(mode) else _kind(mode)


def open_regular(path: str | Path, limit: int | None = None) -> int:
    """A read-only descriptor of the regular file ``path``, examined before any read.

    A named pipe, a device (``/dev/zero``, ``/dev/stdin``) or a socket would block a read or never
    end it: it is refused without a read, as is a folder, or a file over ``limit`` bytes. The file
    is opened without blocking, then examined, so what is examined is what is read.

    Raises
    ------
    OSError
        As :func:`os.open`; or ``EINVAL`` (no regular file) or ``EFBIG`` (over ``limit``), whose
        ``strerror`` says why in words.
    """
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise OSError(errno.EINVAL, f"it is {_kind(info.st_mode)}; expected a regular file")
        if limit is not None and info.st_size > limit:
            raise OSError(errno.EFBIG, f"it holds {info.st_size:,} bytes; expected at most {limit:,}")
    except BaseException:
        os.close(fd)
        raise
    return fd


def open_binary(path: str | Path, limit: int | None = None) -> BinaryIO:
    """The regular file ``path`` opened for reading bytes (:func:`open_regular`), as a file object.

    Raises
    ------
    OSError
        As :func:`open_regular`.
    """
    return os.fdopen(open_regular(path, limit), "rb")


def read_file(path: str | Path, limit: int = MAX_TEXT_BYTES) -> bytes:
    """The bytes of the regular file ``path``: at most ``limit``, never from a pipe or a device.

    Raises
    ------
    OSError
        As :func:`open_regular`, or the read failed, or the file grew past ``limit`` as it was read.
    """
    with open_binary(path, limit) as fh:
        data = fh.read(limit + 1)
    if len(data) > limit:
        raise OSError(errno.EFBIG, f"it grew past {limit:,} bytes as it was read")
    return data


def read_text(path: str | Path, what: str, error: type[PidlabError]) -> str:
    """The UTF-8 text of ``path`` (a ``what``, e.g. "recipe"), or ``error`` in one line naming the file.

    A UTF-8 byte order mark at the start (as some Windows editors write) is dropped.

    Raises
    ------
    PidlabError
        Of class ``error``: ``path`` is no path (``None``, an empty string: ``param`` is
        ``"path"``, the parameter of every ``load_*`` function that reads a file), the file
        cannot be read (missing, a folder, no permission, a loop of symbolic links), is no
        regular file (a named pipe, a device), is larger than :data:`MAX_TEXT_BYTES`, or is not
        UTF-8 text (binary, UTF-16, a stray latin-1 byte).
    """
    path = path_argument(path, "path", error, what=f"the path of a {what} file")
    try:
        data = read_file(path)
    except OSError as exc:
        raise error(f"cannot read {what} {clip(str(path), 200)!r}: {exc.strerror or exc}") from None
    try:
        return data.decode("utf-8").removeprefix(BOM)
    except UnicodeDecodeError as exc:
        raise error(
            f"{clip(str(path), 200)}: the {what} is not UTF-8 text "
            f"(byte 0x{data[exc.start]:02x} at offset {exc.start}); save it as UTF-8"
        ) from None


def load_json(path: str | Path, what: str, error: type[PidlabError]) -> Any:
    """Read a JSON file that may be damaged (cut short, not JSON, not text): ``error`` in one line.

    Raises
    ------
    PidlabError
        Of class ``error``, naming the file.
    """
    text = read_text(path, what, error)
    try:
        return json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise error(f"{clip(str(path), 200)}: the {what} is damaged (not valid JSON: {exc})") from None


def save_figure(fig: Figure, path: str | Path, dpi: int = 110) -> Path:
    """Write a matplotlib figure as PNG, atomically, and close it (the one way pidlab saves figures).

    Works for a bare :class:`~matplotlib.figure.Figure` (what pidlab's ``plot_*`` functions make)
    and for a figure made through pyplot, which is also removed from pyplot's list of open figures.
    Neither imports pyplot nor chooses a backend.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
    path : path
        The PNG file; its folder is created.
    dpi : int
    """
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    pyplot = sys.modules.get("matplotlib.pyplot")
    if pyplot is not None:  # a figure pyplot manages: let it go (a no-op for a bare Figure)
        pyplot.close(fig)
    return atomic_write_bytes(path, buf.getvalue())


def parse_toml(text: str, where: str, error: type[PidlabError]) -> dict[str, Any]:
    """Parse TOML ``text``; invalid TOML raises ``error`` naming ``where``.

    The one TOML parser of pidlab: a syntax error, a NUL or control character, or nesting deep
    enough to exhaust Python's recursion limit all become one line. A leading byte order mark
    (U+FEFF, which TOML does not allow) is dropped.
    """
    if not isinstance(text, str):
        raise TypeError(f"text: expected str, got {type(text).__name__}")
    try:
        return tomllib.loads(text.removeprefix(BOM))
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{where}: not valid TOML: {exc}") from None
    except RecursionError:
        raise error(f"{where}: not valid TOML: nested too deeply") from None


def read_toml(path: str | Path, what: str, error: type[PidlabError]) -> dict[str, Any]:
    """Read and parse the TOML file ``path`` (a ``what``, e.g. "recipe"), raising ``error`` on failure."""
    return parse_toml(read_text(path, what, error), clip(str(path), 200), error)
