"""The one place where the names and numbers a user gives are checked.

Every parser of pidlab (coach specs, recipes, conditions files, schedules, model cards, seeds, the
command line's vectors) hands each name and number it reads to one of these functions, so that
one rule holds everywhere and the message says what was expected.

Names
    A name that becomes part of a path (a spec's ``name``, a condition, an env id, a recipe's
    env) must follow :data:`NAME_RULE`: 1-64 letters, digits, ``.``, ``_`` or ``-``, starting with
    a letter or digit. It cannot climb out of its folder (no ``/``, no ``..``) and never makes a
    file name too long. :func:`path_under` builds a path from such names and checks that it
    stays under its root.
Numbers
    :func:`number` and :func:`integer` take a value as parsed (TOML, JSON, a Python argument):
    a bool is not a number (TOML's ``true`` is not 1), a number must be finite unless told
    otherwise, and must lie in its documented range; the message states the range. Seeds are
    integers in ``[0, 2**32 - 1]`` (:data:`SEED_MAX`, what NumPy and SB3 accept).

Each function raises the error class it is given (``SpecError``, ``RecipeError``, ...), with
``param`` set when the value is a Python argument, so that the command line names its flag.
A message is ``"{where} = {value}: expected {what}"``, or ``"{param}={value}: expected {what}"``.
"""

from __future__ import annotations

import math
import numbers
import os
import re
from pathlib import Path
from typing import Any, NoReturn, TypeVar

from pidlab.errors import ArgumentError, PidlabError

NAME_RULE = "1-64 letters, digits, '.', '_' or '-', starting with a letter or digit"
"""What a name that becomes part of a path may be (the web tuner's rule for spec names)."""

_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
_NAME_NO_DOT = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]{0,63}")

SEED_MAX = 2**32 - 1
"""The largest seed: NumPy's legacy seeding (and so SB3's) needs ``0 <= seed < 2**32``."""

MAX_SEEDS = 10_000
"""The most seeds one experiment or pipeline may ask for."""

MAX_SAMPLES = 10**7
"""The most simulated initial states one region estimate may ask for (``roa_samples``, ``--samples``)."""

NAME_MAX_BYTES = 255
"""The longest file name most file systems accept, in bytes."""


def shown(value: Any, limit: int = 40) -> str:
    """``repr(value)``, cut to ``limit`` characters (a 100,000-character name stays one short line)."""
    try:
        text = repr(value)
    except Exception:  # pragma: no cover - a repr that fails is still a bad value
        text = f"<{type(value).__name__}>"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def clip(text: str, limit: int = 80) -> str:
    """``text``, cut to ``limit`` characters with ``...`` (a path or name shown as given, unquoted)."""
    return text if len(text) <= limit else text[: limit - 3] + "..."


def fail(
    value: Any, where: str, expected: str, error: type[PidlabError] = PidlabError, param: str | None = None
) -> NoReturn:
    """Raise ``error``: ``"{where} = {value}: expected {expected}"`` (or ``"{param}={value}: ..."``).

    A command-line option (``where`` starting ``--``) is shown as it is typed: ``"--seed -1: ..."``.

    Raises
    ------
    PidlabError
        Always, of class ``error``.
    """
    if param is not None:
        raise error(f"{param}={shown(value)}: expected {expected}", param=param)
    sep = " " if where.startswith("--") else " = "
    raise error(f"{where}{sep}{shown(value)}: expected {expected}")


def _fmt(x: float) -> str:
    if isinstance(x, int):
        return str(x)
    return "inf" if x == math.inf else "-inf" if x == -math.inf else f"{x:g}"


def range_text(
    low: float | None = None, high: float | None = None, low_open: bool = False, high_open: bool = False
) -> str:
    """The range in words: ``in [0, 1]``, ``in (0, 1]``, ``>= 1``, ``> 0``, ``<= 5``, or ``""``."""
    if low is not None and high is not None:
        return f"in {'(' if low_open else '['}{_fmt(low)}, {_fmt(high)}{')' if high_open else ']'}"
    if low is not None:
        return f"{'>' if low_open else '>='} {_fmt(low)}"
    if high is not None:
        return f"{'<' if high_open else '<='} {_fmt(high)}"
    return ""


def _in_range(x: float, low: float | None, high: float | None, low_open: bool, high_open: bool) -> bool:
    if low is not None and (x <= low if low_open else x < low):
        return False
    return not (high is not None and (x >= high if high_open else x > high))


def number(
    value: Any,
    where: str,
    error: type[PidlabError] = PidlabError,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
    finite: bool = True,
    unit: str = "",
    param: str | None = None,
) -> float:
    """``value`` as a float: a real number (not a bool), finite unless ``finite=False``, in range.

    Parameters
    ----------
    value : object
        As parsed (int, float, or anything else, which is refused).
    where : str
        What the value is, e.g. ``"spec.toml: loop 'pole'.kp"`` (unused when ``param`` is given).
    error : type of PidlabError
    low, high : float, optional
        Bounds of the range; ``low_open``/``high_open`` exclude them.
    finite : bool, default True
        False: ``inf`` and ``-inf`` are allowed (NaN never is).
    unit : str
        Shown after the range, e.g. ``"s"``.
    param : str, optional
        The Python parameter, when ``value`` is a function's argument.

    Raises
    ------
    PidlabError
        Of class ``error``, stating the expected kind and range.
    """
    span = range_text(low, high, low_open, high_open)
    kind = "a finite number" if finite else "a number (inf allowed, not nan)"
    expected = " ".join(p for p in (kind, span, f"({unit})" if unit else "") if p)
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        fail(value, where, expected, error, param)
    try:
        x = float(value)
    except (OverflowError, ValueError, TypeError):
        fail(value, where, expected, error, param)
    if math.isnan(x) or (finite and math.isinf(x)) or not _in_range(x, low, high, low_open, high_open):
        fail(value, where, expected, error, param)
    return x


def integer(
    value: Any,
    where: str,
    error: type[PidlabError] = PidlabError,
    *,
    low: int | None = None,
    high: int | None = None,
    param: str | None = None,
) -> int:
    """``value`` as an int: an integer (not a bool, not a float such as ``3.0``) in ``[low, high]``.

    Raises
    ------
    PidlabError
        Of class ``error``, stating the range.
    """
    expected = " ".join(p for p in ("an integer", range_text(low, high)) if p)
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        fail(value, where, expected, error, param)
    n = int(value)
    if not _in_range(n, low, high, False, False):
        fail(value, where, expected, error, param)
    return n


def seed(value: Any, where: str, error: type[PidlabError] = PidlabError, *, param: str | None = None) -> int:
    """A seed: an integer in ``[0, 2**32 - 1]`` (:data:`SEED_MAX`).

    Raises
    ------
    PidlabError
        Of class ``error``.
    """
    return integer(value, where, error, low=0, high=SEED_MAX, param=param)


def flag(value: Any, where: str, error: type[PidlabError] = PidlabError) -> bool:
    """``value`` when it is ``true`` or ``false`` (not 0, 1 or a string).

    Raises
    ------
    PidlabError
        Of class ``error``.
    """
    if not isinstance(value, bool):
        fail(value, where, "true or false", error)
    return value


def text(value: Any, where: str, error: type[PidlabError] = PidlabError, *, empty: bool = True) -> str:
    """``value`` when it is a string (non-empty unless ``empty``).

    Raises
    ------
    PidlabError
        Of class ``error``.
    """
    if not isinstance(value, str) or (not empty and not value):
        fail(value, where, "a string" if empty else "a non-empty string", error)
    return value


def as_table(
    value: Any, where: str, error: type[PidlabError] = PidlabError, what: str = "a table"
) -> dict[str, Any]:
    """``value`` when it is a table: a dict whose keys are strings (as TOML gives them).

    Raises
    ------
    PidlabError
        Of class ``error``: ``"{where}: expected {what}, got ..."``.
    """
    if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
        raise error(f"{where}: expected {what}, got {shown(value)}")
    return value


def check_name(
    value: Any,
    where: str,
    error: type[PidlabError] = PidlabError,
    *,
    param: str | None = None,
    dots: bool = True,
) -> str:
    """``value`` when it is a name of :data:`NAME_RULE` (the one rule for names in paths).

    Parameters
    ----------
    value : object
    where : str
        What the name is, e.g. ``"spec.toml: name"``.
    error : type of PidlabError
    param : str, optional
        The Python parameter, when ``value`` is a function's argument.
    dots : bool, default True
        False: ``.`` is not allowed either (python-control's signal names, e.g. loop names).

    Raises
    ------
    PidlabError
        Of class ``error``.
    """
    rule = _NAME if dots else _NAME_NO_DOT
    if not isinstance(value, str) or rule.fullmatch(value) is None:
        described = NAME_RULE if dots else NAME_RULE.replace("'.', ", "")
        fail(value, where, f"a name of {described}", error, param)
    return value


def is_name(value: Any) -> bool:
    """Whether ``value`` follows :data:`NAME_RULE`."""
    return isinstance(value, str) and _NAME.fullmatch(value) is not None


def path_under(
    root: str | Path, *parts: str, error: type[PidlabError] = PidlabError, param: str | None = None
) -> Path:
    """``root / part / ...``, checked to stay under ``root``; every part is one file name.

    A part may not be empty, ``.``, ``..``, hold a path separator or a NUL, or be longer than
    :data:`NAME_MAX_BYTES` bytes; the absolute, normalized path must lie under the absolute,
    normalized ``root``.

    Returns
    -------
    Path
        ``Path(root).joinpath(*parts)`` (relative when ``root`` is).

    Raises
    ------
    PidlabError
        Of class ``error``, naming the part.
    """
    for part in parts:
        bad = (
            not isinstance(part, str)
            or part in ("", ".", "..")
            or "/" in part
            or os.sep in part
            or "\0" in part
            or len(part.encode("utf-8", "surrogateescape")) > NAME_MAX_BYTES
        )
        if bad:
            expected = f"one file name of 1-{NAME_MAX_BYTES} bytes (no '/', not '..') under {root}"
            if param is not None:
                fail(part, param, expected, error, param)
            raise error(f"{shown(part)}: cannot be part of a path under {root}; expected {expected}")
    path = Path(root).joinpath(*parts)
    base = os.path.abspath(root)
    full = os.path.abspath(path)
    if os.path.commonpath([base, full]) != base:  # pragma: no cover - the parts were checked above
        raise error(f"{shown(str(path))}: leaves {root}; expected a path under it", param=param)
    return path


def exists(path: str | Path) -> bool:
    """Whether ``path`` exists; a name the file system refuses (too long, a NUL) never does.

    :meth:`pathlib.Path.exists` raises ``OSError: File name too long`` on a 100,000-character
    name; a command that asks whether a user's name is a file uses this instead.
    """
    try:
        return Path(path).exists()
    except (OSError, ValueError):
        return False


def is_file(path: str | Path) -> bool:
    """Whether ``path`` is a file (as :func:`exists`, a name the file system refuses is not)."""
    try:
        return Path(path).is_file()
    except (OSError, ValueError):
        return False


_NUMBER = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
"""A number as text: ASCII digits only (``float()`` also takes ``'١'`` and ``'１０'``, pidlab does not)."""


def float_text(text: str) -> float:
    """The number ``text`` writes with ASCII digits (``"1.5"``, ``"-2e-3"``), else NaN.

    Unlike ``float()``, it reads no Unicode digits (``"١"``), no ``"inf"``/``"nan"`` words and no
    underscores: the one reading of a number given as text (:func:`parse_vector`, recipes).
    """
    return float(text) if isinstance(text, str) and _NUMBER.fullmatch(text.strip()) else math.nan


def check_ascii_digits(
    value: str, where: str, error: type[PidlabError] = PidlabError, *, param: str | None = None
) -> str:
    """``value`` when every digit in it is one of ``0-9`` (the one rule for numbers given as text).

    Python's ``int()`` and ``float()`` read Arabic-Indic (``'١'``), full-width (``'１０'``) and other
    Unicode digits; pidlab reads only ASCII digits, everywhere a number comes as text.

    Raises
    ------
    PidlabError
        Of class ``error``, naming the character.
    """
    for ch in value:
        if ch.isdigit() and not ch.isascii():
            fail(value, where, f"numbers written with the digits 0-9 ({ch!r} is not one)", error, param)
    return value


def split_list(
    value: str, param: str, error: type[PidlabError] = PidlabError, *, what: str = "names", sep: str = ","
) -> list[str]:
    """The parts of comma-separated text such as ``--variables a,b``, stripped; an empty part is refused.

    ``"a,,b"``, ``"a,"`` and ``""`` are refused (an empty part would silently vanish).

    Raises
    ------
    PidlabError
        Of class ``error``, with ``param``.
    ArgumentError
        ``value`` is not a string (a ``TypeError`` too).
    """
    if not isinstance(value, str):
        fail(value, param, "a str", ArgumentError, param)
    parts = [part.strip() for part in value.split(sep)]
    if not all(parts):
        fail(value, param, f"comma-separated {what}, none of them empty", error, param)
    return parts


def parse_vector(
    value: str, param: str, error: type[PidlabError] = PidlabError, *, length: int | None = None
) -> list[float]:
    """Finite numbers from comma- (or semicolon-) separated text, as ``--qpos 0,0.1`` gives them.

    Every part must be a number written with ASCII digits (``1.5``, ``-2e-3``); an empty part
    (``0,,0``) is refused, not skipped.

    Raises
    ------
    PidlabError
        Of class ``error``, with ``param``: a part that is not a finite number, or (when
        ``length`` is given) the wrong number of parts.
    ArgumentError
        ``value`` is not a string (a ``TypeError`` too).
    """
    if not isinstance(value, str):
        fail(value, param, "a str", ArgumentError, param)
    check_ascii_digits(value, param, error, param=param)
    out = []
    for part in split_list(value.replace(";", ","), param, error, what="numbers (e.g. 0,0.1)"):
        x = float_text(part)
        if not math.isfinite(x):
            bad = shown(part, 20)
            expected = f"comma-separated numbers, e.g. 0,0.1; {bad} is not a finite number"
            fail(value, param, expected, error, param)
        out.append(x)
    if length is not None and len(out) != length:
        fail(value, param, f"{length} comma-separated numbers, got {len(out)}", error, param)
    return out


def path_argument(
    value: Any, param: str, error: type[PidlabError] = PidlabError, *, what: str = "a path"
) -> Path:
    """``value`` as a :class:`~pathlib.Path`: a ``str`` or path-like object, not empty or blank.

    ``Path("")`` is ``.``, the current folder: an empty string is refused here instead of being
    read as "here".

    Raises
    ------
    PidlabError
        Of class ``error``, with ``param``.
    """
    if not isinstance(value, (str, os.PathLike)):
        fail(value, param, f"{what} (a str or pathlib.Path)", error, param)
    raw = os.fspath(value)
    if not isinstance(raw, str) or not raw.strip():
        fail(value, param, f"{what} (a str or pathlib.Path), not an empty one", error, param)
    return Path(raw)


def boolean(value: Any, param: str, error: type[PidlabError] = PidlabError) -> bool:
    """``value`` when it is ``True`` or ``False`` (a Python argument; not 0, 1 or a string).

    Raises
    ------
    PidlabError
        Of class ``error``, with ``param``.
    """
    if not isinstance(value, bool):
        fail(value, param, "True or False", error, param)
    return value


def strings(
    value: Any,
    param: str,
    error: type[PidlabError] = PidlabError,
    *,
    what: str = "strings",
    empty: bool = True,
) -> list[str]:
    """``value`` as a list of non-empty strings: a list or tuple, never one string (its characters).

    Raises
    ------
    PidlabError
        Of class ``error``, with ``param``: one string where a list is expected (``envs="Hopper-v5"``
        instead of ``["Hopper-v5"]``), another type, an entry that is not a non-empty string, or
        (unless ``empty``) no entry at all.
    """
    if isinstance(value, str):
        fail(value, param, f"a list of {what}, e.g. [{value!r}], not one string", error, param)
    if not isinstance(value, (list, tuple)):
        fail(value, param, f"a list of {what}", error, param)
    if not empty and not value:
        fail(value, param, f"a list of at least one of {what}", error, param)
    for item in value:
        if not isinstance(item, str) or not item.strip():
            expected = f"a list of {what} (each a non-empty str; {shown(item, 20)} is not)"
            fail(value, param, expected, error, param)
    return list(value)


T = TypeVar("T")

_LOADERS = {"CoachSpec": "pidlab.load_spec(path)", "LoadedModel": "pidlab.load_model(env_id)",
            "Recipe": "pidlab.load_recipe(path)"}  # fmt: skip
"""What reads each object from a file or name, for the hint when a path or name is given instead."""


def instance(value: Any, kind: type[T], param: str, error: type[PidlabError] = ArgumentError) -> T:
    """``value`` when it is a ``kind`` (a function's argument); else ``error`` naming ``param``.

    A path or name given where a loaded object is expected gets a hint: ``spec='a.toml': expected
    a CoachSpec; read it with pidlab.load_spec(path)``.

    Raises
    ------
    PidlabError
        Of class ``error`` (default :class:`~pidlab.errors.ArgumentError`, a ``TypeError`` too).
    """
    if not isinstance(value, kind):
        loader = _LOADERS.get(kind.__name__)
        hint = f"; read it with {loader}" if loader and isinstance(value, (str, os.PathLike)) else ""
        fail(value, param, f"a {kind.__name__}{hint}", error, param)
    return value
