"""A project folder: ``pidlab.toml`` says where your own robot's files are, for every command run there.

``pidlab init`` writes it beside the scaffold it writes. Schema ``pidlab.project/1``::

    schema = "pidlab.project/1"
    gym_packages = ["mycartpole_v0_env"]  # modules that register your envs (found in this folder)
    models = "models"                     # your model cards, searched before the shipped ones
    tuning = "tuning"                     # your coach specs
    coach = "coach"                       # your recipes (conditions.toml falls back to the shipped one)

Every field but ``schema`` is optional; folders are relative to the project folder. A ``pidlab``
command run in a folder that holds ``pidlab.toml`` applies it first (:func:`apply_project`):

- the folder goes at the end of the module search path, so that its modules are found and a file
  there named like an installed package (``control.py``) does not hide the package; it is named
  in ``PIDLAB_PROJECT`` for the processes pidlab starts, which put it at the end of theirs
  before they import a module that registers envs (:func:`pidlab.plant.envs.import_module`);
- each data folder becomes ``PIDLAB_MODELS``, ``PIDLAB_TUNING`` or ``PIDLAB_COACH``, unless that
  variable is set already (the environment wins, see :mod:`pidlab.data`);
- ``gym_packages`` join ``PIDLAB_GYM_PACKAGES`` (imported when an env id is not registered yet,
  see :mod:`pidlab.plant.envs`).

Only the current folder is looked at, not its parents. From Python, the same is
``apply_project(load_project("pidlab.toml"))``.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from pathlib import Path

from pidlab.checks import as_table, clip, shown, text
from pidlab.data import FOLDERS
from pidlab.errors import ProjectError
from pidlab.files import read_toml

PROJECT_FILE = "pidlab.toml"
"""The project file's name."""

PROJECT_SCHEMA = "pidlab.project/1"

_FIELDS = {"schema", "gym_packages", *FOLDERS}


@dataclass(frozen=True)
class Project:
    """A parsed project file.

    Attributes
    ----------
    root : Path
        The project folder (absolute).
    gym_packages : tuple of str
        Modules that register the project's envs.
    folders : tuple of (str, Path)
        Data folder name (``models``, ``tuning``, ``coach``) -> its absolute path, for those given.
    """

    root: Path
    gym_packages: tuple[str, ...]
    folders: tuple[tuple[str, Path], ...]


def find_project(folder: str | Path = ".") -> Path | None:
    """The project file of ``folder`` (only there, not in its parents), or None."""
    path = Path(folder) / PROJECT_FILE
    return path if os.path.lexists(path) else None


def load_project(path: str | Path) -> Project:
    """Read and check the project file ``path``.

    Raises
    ------
    ProjectError
        One line: an unreadable file, bad TOML, a wrong schema, an unknown field, a module list
        that is no list of module names, or a folder that is no non-empty string or is a file.
    """
    data = read_toml(path, "project file", ProjectError)
    where = str(path)
    as_table(data, where, ProjectError, "a table (parsed TOML)")
    if data.get("schema") != PROJECT_SCHEMA:
        raise ProjectError(f"{where}: schema is {shown(data.get('schema'))}; expected {PROJECT_SCHEMA!r}")
    unknown = sorted(set(data) - _FIELDS)
    if unknown:
        raise ProjectError(
            f"{where}: unknown field(s) {[clip(k, 40) for k in unknown[:10]]}; "
            f"allowed: {', '.join(sorted(_FIELDS))}"
        )
    modules = data.get("gym_packages", [])
    if not isinstance(modules, list) or not all(_is_module(m) for m in modules):
        raise ProjectError(
            f"{where}: gym_packages is {shown(modules, 80)}; "
            'expected a list of module names, e.g. ["my_robots"]'
        )
    root = Path(os.path.abspath(Path(path).parent))
    folders = []
    for name in FOLDERS:
        if name in data:
            rel = text(data[name], f"{where}: {name}", ProjectError, empty=False)
            if "\0" in rel:
                raise ProjectError(f"{where}: {name} is {shown(rel, 80)}; expected a folder's path")
            full = Path(os.path.normpath(root / rel))
            if os.path.exists(full) and not os.path.isdir(full):
                raise ProjectError(f"{where}: {name} = {shown(rel, 80)} is a file; expected a folder")
            folders.append((name, full))
    return Project(root, tuple(modules), tuple(folders))


def _is_module(name: object) -> bool:
    from pidlab.plant.envs import MODULE_NAME

    return isinstance(name, str) and MODULE_NAME.fullmatch(name) is not None


PROJECT_VAR = "PIDLAB_PROJECT"
"""The environment variable that names the project folder for the processes pidlab starts."""


def apply_project(project: Project) -> None:
    """Make this process, and the processes it starts, see ``project`` (see the module docstring)."""
    from pidlab.plant.envs import GYM_PACKAGES_VAR, gym_packages

    root = str(project.root)
    if root not in sys.path:
        sys.path.append(root)
    os.environ[PROJECT_VAR] = root
    for name, folder in project.folders:
        if not os.environ.get(FOLDERS[name]):  # a variable set by the user wins
            os.environ[FOLDERS[name]] = str(folder)
    known = list(gym_packages())
    extra = [m for m in project.gym_packages if m not in known]
    if extra:
        os.environ[GYM_PACKAGES_VAR] = ",".join([*known, *extra])
