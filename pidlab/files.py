"""Files below every stage: atomic writes, JSON and TOML reading with one-line errors.

Every file pidlab writes goes through :func:`atomic_write_text` / :func:`atomic_write_bytes` (a
temporary file in the same folder, flushed, then renamed over the target), so a kill leaves either
the old file or the new one, never half of one.
"""

from __future__ import annotations

import io
import json
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pidlab.errors import PidlabError

if TYPE_CHECKING:
    from matplotlib.figure import Figure

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (temporary file, fsync, rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    return path


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def write_json(path: str | Path, data: Any) -> Path:
    """Write ``data`` as indented JSON, atomically."""
    return atomic_write_text(path, json.dumps(data, indent=2, sort_keys=False) + "\n")


def read_json(path: str | Path) -> Any:
    """Read a JSON file."""
    return json.loads(Path(path).read_text(encoding="utf-8"))


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
    """Parse TOML ``text``; invalid TOML raises ``error`` naming ``where``."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{where}: not valid TOML: {exc}") from None


def read_toml(path: str | Path, what: str, error: type[PidlabError]) -> dict[str, Any]:
    """Read and parse the TOML file ``path`` (a ``what``, e.g. "recipe"), raising ``error`` on failure."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise error(f"cannot read {what} {str(path)!r}: {exc.strerror}") from None
    return parse_toml(text, str(path), error)
