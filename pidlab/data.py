"""Where pidlab's data folders are: the one place that locates them.

pidlab keeps what a user reads, edits and versions in three folders of TOML files, never in code:

- ``models/``: model cards (operating point, named states, termination limits, per-env facts such
  as the tuning template, the region method and the paper's published numbers);
- ``tuning/``: coach specs, one file per env and name;
- ``coach/``: training recipes and ``conditions.toml``.

Each folder has two layers, searched in this order:

1. the user's folder named by its environment variable (``PIDLAB_MODELS``, ``PIDLAB_TUNING``,
   ``PIDLAB_COACH``), when set: its files come first, and new files are written there;
2. the shipped folder: the source tree when pidlab runs from a checkout (an editable install),
   else the copy inside the installed package (``pidlab/_data/``, after ``pip install .``).

A project file (``pidlab.toml``, :mod:`pidlab.project`) sets these variables for the commands run
in its folder, unless they are set already.

A file the user's folder lacks is read from the shipped one (:func:`find_data_file`): a user
folder with only a card of their own robot still finds the shipped cards, recipes, specs and
``conditions.toml``. A user's file of the same name replaces the shipped one.
"""

from __future__ import annotations

import os
from pathlib import Path

FOLDERS = {"models": "PIDLAB_MODELS", "tuning": "PIDLAB_TUNING", "coach": "PIDLAB_COACH"}
"""Data folder -> the environment variable that overrides it."""

_PACKAGE = Path(__file__).resolve().parent


def shipped_dir(name: str) -> Path:
    """The data folder ``name`` that ships with pidlab: the checkout's, else the installed copy.

    Raises
    ------
    ValueError
        ``name`` is not one of :data:`FOLDERS` (a programming error, not bad user input).
    """
    if name not in FOLDERS:
        raise ValueError(f"name {name!r}: expected one of {', '.join(FOLDERS)}")
    source = _PACKAGE.parent / name
    if source.is_dir() and (_PACKAGE.parent / "pyproject.toml").is_file():
        return source
    return _PACKAGE / "_data" / name


def data_dirs(name: str) -> tuple[Path, ...]:
    """The layers of the data folder ``name``, first searched first: the user's (when set), the shipped one.

    Parameters
    ----------
    name : {"models", "tuning", "coach"}

    Returns
    -------
    tuple of Path
        One or two folders; the user's may not exist when its environment variable names a
        missing one.

    Raises
    ------
    ValueError
        ``name`` is not one of :data:`FOLDERS` (a programming error, not bad user input).
    """
    shipped = shipped_dir(name)
    override = os.environ.get(FOLDERS[name])
    if override and Path(override).resolve() != shipped.resolve():
        return (Path(override), shipped)
    return (shipped,)


def data_dir(name: str) -> Path:
    """The first layer of the data folder ``name``: where pidlab writes, and looks first.

    The user's folder when its environment variable is set, else the shipped one
    (:func:`data_dirs`).
    """
    return data_dirs(name)[0]


def find_data_file(name: str, relative: str) -> Path:
    """The file ``relative`` in the first layer of the data folder ``name`` that has it.

    A dangling symbolic link counts as present (reading it then says what is wrong). When no
    layer has the file, its path in the first layer (where pidlab would write it).
    """
    layers = data_dirs(name)
    for folder in layers:
        path = folder / relative
        if path.exists() or path.is_symlink():
            return path
    return layers[0] / relative


def data_files(name: str, pattern: str) -> list[Path]:
    """The files matching ``pattern`` in the data folder ``name``, a user's file hiding a shipped one.

    Sorted by file name.
    """
    found: dict[str, Path] = {}
    for folder in reversed(data_dirs(name)):
        found.update({p.name: p for p in folder.glob(pattern)})
    return [found[k] for k in sorted(found)]


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
    roots = [(name, folder) for name in FOLDERS for folder in data_dirs(name)]
    tree = source_root()
    for name, root in [*roots, *([("", tree)] if tree is not None else [])]:
        try:
            rel = p.relative_to(root.resolve()).as_posix()
        except ValueError:
            continue
        return f"{name}/{rel}" if name else rel
    return p.name
