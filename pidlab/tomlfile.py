"""Reading TOML files (model cards, coach specs, recipes, run configs) with one-line errors."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from pidlab.errors import PidlabError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


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
