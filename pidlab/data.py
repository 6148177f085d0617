"""Where pidlab's data folders are: the one place that locates them.

pidlab keeps what a user reads, edits and versions in three folders of TOML files, never in code:

- ``models/``: model cards (operating point, named states, termination limits, per-env facts such
  as the tuning template, the region method and the paper's published numbers);
- ``tuning/``: coach specs, one file per env and name;
- ``coach/``: training recipes and ``conditions.toml``.

Each folder is found, in this order, at:

1. the folder named by its environment variable (``PIDLAB_MODELS``, ``PIDLAB_TUNING``,
   ``PIDLAB_COACH``), when set;
2. the source tree, when pidlab runs from a checkout (an editable install);
3. the copy shipped inside the installed package (``pidlab/_data/``), after ``pip install .``.
"""

from __future__ import annotations

import os
from pathlib import Path

FOLDERS = {"models": "PIDLAB_MODELS", "tuning": "PIDLAB_TUNING", "coach": "PIDLAB_COACH"}
"""Data folder -> the environment variable that overrides it."""

_PACKAGE = Path(__file__).resolve().parent


def data_dir(name: str) -> Path:
    """The data folder ``name`` (``"models"``, ``"tuning"`` or ``"coach"``).

    Parameters
    ----------
    name : {"models", "tuning", "coach"}

    Returns
    -------
    Path
        The folder; it may not exist when an environment variable names a missing one.

    Raises
    ------
    ValueError
        ``name`` is not one of :data:`FOLDERS` (a programming error, not bad user input).
    """
    if name not in FOLDERS:
        raise ValueError(f"name {name!r}: expected one of {', '.join(FOLDERS)}")
    override = os.environ.get(FOLDERS[name])
    if override:
        return Path(override)
    source = _PACKAGE.parent / name
    if source.is_dir() and (_PACKAGE.parent / "pyproject.toml").is_file():
        return source
    return _PACKAGE / "_data" / name


def models_dir() -> Path:
    """The folder of model cards (see :func:`data_dir`)."""
    return data_dir("models")


def tuning_dir() -> Path:
    """The folder of coach specs (see :func:`data_dir`)."""
    return data_dir("tuning")


def coach_dir() -> Path:
    """The folder of recipes and the conditions file (see :func:`data_dir`)."""
    return data_dir("coach")


def source_root() -> Path | None:
    """Pidlab's source tree when it runs from a checkout, else None (an installed copy)."""
    root = _PACKAGE.parent
    return root if (root / "pyproject.toml").is_file() and (root / "pidlab").is_dir() else None


def portable_name(path: str | Path) -> str:
    """How a record names a data file, the same on every machine: never the writer's absolute path.

    A file inside one of the data folders is named relative to it (``tuning/Hopper-v5.paper.toml``),
    a file of the source tree relative to its root; any other file by its name alone (the record
    identifies it by its digest). An empty path stays empty.

    Parameters
    ----------
    path : path
        The file (absolute or relative to the working directory).

    Returns
    -------
    str
        A POSIX path relative to a data folder or to the source tree, or the file's name.
    """
    if str(path) == "":
        return ""
    p = Path(path).resolve()
    roots = [(name, data_dir(name)) for name in FOLDERS]
    tree = source_root()
    for name, root in [*roots, *([("", tree)] if tree is not None else [])]:
        try:
            rel = p.relative_to(root.resolve()).as_posix()
        except ValueError:
            continue
        return f"{name}/{rel}" if name else rel
    return p.name
