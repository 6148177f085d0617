"""Coach specs: a versioned TOML schema for multi-loop PID coaches.

A coach spec lives in ``tuning/`` and is read by analysis, the tuner and the training wrapper.
:func:`save_spec` writes a canonical form; ``save(load(file))`` reproduces a canonical file
byte for byte and ``load(save(spec)) == spec``. Validation errors name the field and the
allowed values.

Schema ``pidlab.coach-spec/1``::

    schema = "pidlab.coach-spec/1"
    env_id = "InvertedPendulum-v5"
    name = "pidlab-robust"
    description = "..."

    [offset]                     # control added to the loops' output (e.g. the equilibrium
    slide = 0.0                  # control); default 0 for every actuator

    [[loop]]
    name = "pole"
    signal = "hinge_pos"         # observation variable measured
    setpoint = 0.0
    action = "reverse"           # reverse: e = setpoint - signal; direct: e = signal - setpoint
    kp = 20.0
    ki = 0.0                     # 1/s
    kd = 3.0                     # s
    rate_signal = "hinge_vel"    # optional: derivative from this measured rate, else from a
                                 # filtered difference of the signal
    tf = 0.0                     # derivative filter time constant, s (>= 0)
    anti_windup = "clamping"     # none | clamping | back-calculation
    tt = 0.0                     # back-calculation tracking time constant, s (> 0 when used)
    output_limits = [-inf, inf]  # clip of the loop's output (used by cascades)
    actuators = { slide = 1.0 }  # actuator -> weight; or:
    # feeds = "other_loop"       # cascade: the output shifts the setpoint of that loop

    [provenance]                 # free-form strings and numbers: how the spec was made
"""

from __future__ import annotations

import datetime
import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from pidlab.checks import as_table, check_name, number, shown, text
from pidlab.errors import SpecError
from pidlab.files import parse_toml, read_toml
from pidlab.lookup import coach_digest, is_classifier, parse_forecast, parse_rescue

SPEC_SCHEMA = "pidlab.coach-spec/1"
ACTIONS = ("reverse", "direct")
ANTI_WINDUP = ("none", "clamping", "back-calculation")


@dataclass(frozen=True)
class Loop:
    """One PID loop of a coach.

    Attributes
    ----------
    name : str
    signal : str
        Observation variable measured.
    setpoint : float
    action : {"reverse", "direct"}
        ``reverse``: error = setpoint - signal (output rises when the signal is low);
        ``direct``: error = signal - setpoint.
    kp, ki, kd : float
        Gains: ``u = kp e + ki * integral(e) + kd * de/dt``; ``ki`` in 1/s, ``kd`` in s.
    rate_signal : str or None
        Observation variable that measures the signal's rate; used for the derivative term
        (derivative on measurement) instead of a filtered difference.
    tf : float
        Derivative filter time constant, s.
    anti_windup : {"none", "clamping", "back-calculation"}
    tt : float
        Back-calculation tracking time constant, s.
    output_limits : tuple of float
        Clip of the loop's output.
    actuators : tuple of (str, float)
        Actuator names and weights the loop's output drives.
    feeds : str or None
        Name of the loop whose setpoint this loop's output shifts (cascade).
    """

    name: str
    signal: str
    setpoint: float = 0.0
    action: str = "reverse"
    kp: float = 0.0
    ki: float = 0.0
    kd: float = 0.0
    rate_signal: str | None = None
    tf: float = 0.0
    anti_windup: str = "clamping"
    tt: float = 0.0
    output_limits: tuple[float, float] = (-math.inf, math.inf)
    actuators: tuple[tuple[str, float], ...] = ()
    feeds: str | None = None

    def __post_init__(self) -> None:
        for key in ("setpoint", "kp", "ki", "kd", "tf", "tt"):
            object.__setattr__(self, key, float(getattr(self, key)))
        object.__setattr__(self, "output_limits", tuple(float(v) for v in self.output_limits))
        object.__setattr__(self, "actuators", tuple((str(a), float(w)) for a, w in self.actuators))

    @property
    def sign(self) -> float:
        """+1 for reverse action, -1 for direct action."""
        return 1.0 if self.action == "reverse" else -1.0


@dataclass(frozen=True)
class CoachSpec:
    """A multi-loop PID coach for one env.

    Attributes
    ----------
    env_id : str
    name : str
    description : str
    loops : tuple of Loop
    offset : tuple of (str, float)
        Control added to every command, per actuator.
    provenance : dict
        Free-form record of how the spec was made (tool, version, date, targets, achieved).
    bounds : dict or None
        Critical-state bounds (``[bounds]`` table, see :mod:`pidlab.region.bounds`): ``method``, an
        optional ``ellipsoid`` (``variables``, ``center``, ``shape``, ``level``, ``rho``), an
        optional ``box`` (variable -> ``[low, high]``) and their ``provenance``.
    """

    env_id: str
    name: str
    loops: tuple[Loop, ...]
    description: str = ""
    offset: tuple[tuple[str, float], ...] = ()
    provenance: dict[str, Any] = field(default_factory=dict, compare=True, hash=False)
    bounds: dict[str, Any] | None = field(default=None, compare=True, hash=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "offset", tuple((str(a), float(v)) for a, v in self.offset))

    def loop(self, name: str) -> Loop:
        """The loop called ``name``."""
        for lp in self.loops:
            if lp.name == name:
                return lp
        raise SpecError(f"no loop {name!r}; loops: {', '.join(lp.name for lp in self.loops)}")

    def order(self) -> tuple[Loop, ...]:
        """Loops in evaluation order: a loop that feeds another comes before it."""
        done: list[Loop] = []
        pending = list(self.loops)
        while pending:
            progressed = False
            for lp in list(pending):
                feeders = [o for o in self.loops if o.feeds == lp.name]
                if all(f in done for f in feeders):
                    done.append(lp)
                    pending.remove(lp)
                    progressed = True
            if not progressed:
                raise SpecError(f"cascade cycle among loops {', '.join(lp.name for lp in pending)}")
        return tuple(done)


def _num(value: Any, where: str, **kw: Any) -> float:
    return number(value, where, SpecError, **kw)


def _str(value: Any, where: str) -> str:
    return text(value, where, SpecError, empty=False)


def _table(value: Any, where: str, what: str) -> dict[str, Any]:
    return as_table(value, where, SpecError, what)


_TOML_SCALARS = (str, int, float, bool, datetime.date, datetime.time)


def _free_form(value: Any, where: str) -> dict[str, Any]:
    """A free-form table (``[provenance]``): anything TOML can hold, so that the spec saves again."""
    table = _table(value, where, "a table")
    stack: list[Any] = [table]
    seen: set[int] = set()
    while stack:
        item = stack.pop()
        if isinstance(item, (dict, list)):
            if id(item) in seen:  # shared (or, from Python, cyclic): checked once
                continue
            seen.add(id(item))
            if isinstance(item, dict):
                as_table(item, where, SpecError, "a table with string keys")
            stack.extend(item.values() if isinstance(item, dict) else item)
        elif not isinstance(item, _TOML_SCALARS):
            expected = "strings, numbers, booleans, dates, lists and tables"
            raise SpecError(f"{where}: {shown(item)} is not a TOML value; expected {expected}")
    return table


_LOOP_KEYS = {
    "name",
    "signal",
    "setpoint",
    "action",
    "kp",
    "ki",
    "kd",
    "rate_signal",
    "tf",
    "anti_windup",
    "tt",
    "output_limits",
    "actuators",
    "feeds",
}
_TOP_KEYS = {"schema", "env_id", "name", "description", "offset", "loop", "provenance", "bounds"}


def _choice(value: Any, where: str, allowed: tuple[str, ...]) -> str:
    if not isinstance(value, str) or value not in allowed:
        raise SpecError(f"{where}: {shown(value)}; allowed: {', '.join(allowed)}")
    return value


def _loop_dynamics(t: dict[str, Any], w: str) -> dict[str, Any]:
    """A loop's action, gains, derivative filter and anti-windup fields, checked."""
    action = _choice(t.get("action", "reverse"), f"{w}.action", ACTIONS)
    aw = _choice(t.get("anti_windup", "clamping"), f"{w}.anti_windup", ANTI_WINDUP)
    tf = _num(t.get("tf", 0.0), f"{w}.tf", low=0.0, unit="s")
    tt = _num(t.get("tt", 0.0), f"{w}.tt", low=0.0, unit="s")
    if aw == "back-calculation" and not tt > 0:
        raise SpecError(f"{w}.tt: back-calculation needs a tracking time constant > 0 s, got {tt}")
    gains = {key: _num(t.get(key, 0.0), f"{w}.{key}") for key in ("setpoint", "kp", "ki", "kd")}
    return {"action": action, "tf": tf, "anti_windup": aw, "tt": tt, **gains}


def _limits(value: Any, where: str, finite: bool) -> tuple[float, float]:
    """``[low, high]`` with ``low < high`` (infinite ends allowed unless ``finite``)."""
    if not isinstance(value, list) or len(value) != 2:
        raise SpecError(f"{where}: expected [low, high], got {shown(value)}")
    lo, hi = (_num(v, where, finite=finite) for v in value)
    if not lo < hi:
        raise SpecError(f"{where}: low ({lo}) must be below high ({hi})")
    return lo, hi


def _loop_output(t: dict[str, Any], w: str) -> dict[str, Any]:
    """Where a loop's output goes: its limits, and its actuators or the loop it feeds, checked."""
    limits = _limits(t.get("output_limits", [-math.inf, math.inf]), f"{w}.output_limits", finite=False)
    acts = _table(t.get("actuators", {}), f"{w}.actuators", "a table of actuator = weight")
    actuators = tuple((k, _num(v, f"{w}.actuators.{k}")) for k, v in acts.items())
    feeds = t.get("feeds")
    if feeds is not None:
        feeds = _str(feeds, f"{w}.feeds")
    if bool(actuators) == (feeds is not None):
        raise SpecError(f'{w}: give either actuators = {{...}} or feeds = "<loop>" (exactly one)')
    return {"output_limits": limits, "actuators": actuators, "feeds": feeds}


def _parse_loop(t: Any, i: int, where: str) -> Loop:
    """The ``i``-th ``[[loop]]`` table, checked."""
    w = f"{where}: loop[{i}]"
    t = _table(t, w, "a table")
    unknown = set(t) - _LOOP_KEYS
    if unknown:
        raise SpecError(f"{w}: unknown field(s) {sorted(unknown)}; allowed: {sorted(_LOOP_KEYS)}")
    lname = check_name(t.get("name"), f"{w}.name", SpecError, dots=False)
    w = f"{where}: loop {lname!r}"
    dynamics = _loop_dynamics(t, w)
    output = _loop_output(t, w)
    rate = t.get("rate_signal")
    if rate is not None:
        rate = _str(rate, f"{w}.rate_signal")
    return Loop(
        name=lname, signal=_str(t.get("signal"), f"{w}.signal"), rate_signal=rate, **dynamics, **output
    )


def _check_loop_names(loops: list[Loop], where: str) -> None:
    """Unique loop names; every ``feeds`` names another loop."""
    names = [lp.name for lp in loops]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise SpecError(f"{where}: loop names must be unique; repeated: {dupes}")
    for lp in loops:
        if lp.feeds is not None and lp.feeds not in names:
            raise SpecError(
                f"{where}: loop {lp.name!r}.feeds: no loop {shown(lp.feeds)}; loops: {', '.join(names)}"
            )
        if lp.feeds == lp.name:
            raise SpecError(f"{where}: loop {lp.name!r} feeds itself")


def parse_spec(data: dict[str, Any], where: str = "spec") -> CoachSpec:
    """Build a :class:`CoachSpec` from parsed TOML, checking types and values.

    Every number must be finite (``output_limits`` may be infinite) and in its range; ``name``
    and ``env_id`` follow :data:`pidlab.checks.NAME_RULE` (a run folder is named after them).
    Names (signals, actuators) are checked against the env by :func:`validate_against`.

    Raises
    ------
    SpecError
    """
    data = _table(data, where, "a table (parsed TOML)")
    unknown = set(data) - _TOP_KEYS
    if unknown:
        raise SpecError(f"{where}: unknown field(s) {sorted(unknown)}; allowed: {sorted(_TOP_KEYS)}")
    if data.get("schema") != SPEC_SCHEMA:
        raise SpecError(f"{where}: schema is {shown(data.get('schema'))}; expected {SPEC_SCHEMA!r}")
    env_id = check_name(data.get("env_id"), f"{where}: env_id", SpecError)
    name = check_name(data.get("name", "coach"), f"{where}: name", SpecError)
    offset_tbl = _table(data.get("offset", {}), f"{where}: offset", "a table of actuator = number")
    offset = tuple((k, _num(v, f"{where}: offset.{k}")) for k, v in offset_tbl.items())
    raw_loops = data.get("loop")
    if not isinstance(raw_loops, list) or not raw_loops:
        raise SpecError(f"{where}: expected at least one [[loop]] table")
    loops = [_parse_loop(t, i, where) for i, t in enumerate(raw_loops)]
    _check_loop_names(loops, where)
    provenance = _free_form(data.get("provenance", {}), f"{where}: provenance")
    bounds = data.get("bounds")
    if bounds is not None:
        _check_bounds(bounds, f"{where}: bounds")
    spec = CoachSpec(
        env_id=env_id,
        name=name,
        description=text(data.get("description", ""), f"{where}: description", SpecError),
        loops=tuple(loops),
        offset=offset,
        provenance=dict(provenance),
        bounds=bounds,
    )
    spec.order()  # raises on cascade cycles
    _check_fitted_for(spec, f"{where}: bounds.rescue.coach")
    return spec


def law_digest(spec: CoachSpec) -> str:
    """The digest of the spec's control law (env, loops, offset; not its name or bounds)."""
    plain = spec_to_dict(spec)
    return coach_digest(spec.env_id, plain["loop"], plain.get("offset", {}))


def _check_fitted_for(spec: CoachSpec, where: str) -> None:
    """A classifier rescue region must have been fitted for this spec's coach (not copied from another)."""
    rescue = (spec.bounds or {}).get("rescue")
    if rescue is None or not is_classifier(rescue):
        return
    want = law_digest(spec)
    if rescue["coach"] != want:
        raise SpecError(
            f"{where}: {rescue['coach']!r}: the classifier was fitted for another coach (this spec's law "
            f"is {want!r}); estimate it for this one: pidlab rescue-classifier SPEC --domain ... --write"
        )


def _check_ellipsoid(e: Any, where: str) -> None:
    """``[bounds.ellipsoid]``: distinct variables, a finite centre, a positive definite shape.

    Also a finite positive ``level`` and ``rho``.
    """
    e = _table(e, where, "a table")
    unknown = set(e) - {"variables", "center", "shape", "level", "rho"}
    if unknown:
        raise SpecError(
            f"{where}: unknown field(s) {sorted(unknown)}; allowed: variables, center, shape, level, rho"
        )
    names = e.get("variables")
    if not isinstance(names, list) or not names or not all(isinstance(v, str) and v for v in names):
        raise SpecError(f"{where}.variables: expected a list of observation variable names")
    if len(set(names)) != len(names):
        raise SpecError(f"{where}.variables: a variable is named twice")
    k = len(names)
    center = e.get("center")
    if not isinstance(center, list) or len(center) != k:
        raise SpecError(f"{where}.center: expected {k} numbers")
    [_num(v, f"{where}.center") for v in center]
    shape = e.get("shape")
    square = isinstance(shape, list) and len(shape) == k
    if not square or not all(isinstance(r, list) and len(r) == k for r in shape):
        raise SpecError(f"{where}.shape: expected a {k} x {k} matrix")
    P = np.array([[_num(v, f"{where}.shape") for v in r] for r in shape])
    scale = float(np.max(np.abs(P))) or 1.0
    if not np.allclose(P, P.T, rtol=1e-9, atol=1e-12 * scale):
        raise SpecError(f"{where}.shape: expected a symmetric matrix")
    with np.errstate(all="ignore"):
        eig = np.linalg.eigvalsh(P / scale)
    if not (np.all(np.isfinite(eig)) and eig.min() > 0):
        raise SpecError(f"{where}.shape: expected a positive definite matrix (an ellipsoid)")
    for key in ("level", "rho"):
        _num(e.get(key), f"{where}.{key}", low=0.0, low_open=True)


def _check_bounds(b: Any, where: str) -> None:
    b = _table(b, where, "a table")
    unknown = set(b) - {"method", "ellipsoid", "box", "rescue", "takeover", "forecast", "provenance"}
    if unknown:
        raise SpecError(
            f"{where}: unknown field(s) {sorted(unknown)}; "
            "allowed: method, ellipsoid, box, rescue, takeover, forecast, provenance"
        )
    _str(b.get("method"), f"{where}.method")
    _free_form(b.get("provenance", {}), f"{where}.provenance")
    if "ellipsoid" in b:
        _check_ellipsoid(b["ellipsoid"], f"{where}.ellipsoid")
    if "box" in b:
        box = _table(b["box"], f"{where}.box", "a table of variable = [low, high]")
        for name, lim in box.items():
            _limits(lim, f"{where}.box.{name}", finite=True)
    if "rescue" in b:
        parse_rescue(b["rescue"], f"{where}.rescue")
    if "forecast" in b:
        if "rescue" not in b:
            raise SpecError(f"{where}.forecast: the forecast's error is measured on a rescue region; "
                            "the table has no [bounds.rescue]")  # fmt: skip
        parse_forecast(b["forecast"], f"{where}.forecast")
    if "takeover" in b:
        kind = _choice(b["takeover"], f"{where}.takeover", ("box", "ellipsoid", "rescue"))
        if kind not in b:
            raise SpecError(f"{where}.takeover: {kind!r}, but the table has no [bounds.{kind}]")


def bound_variables(spec: CoachSpec) -> list[str]:
    """Observation variables the spec's bounds mention."""
    if not spec.bounds:
        return []
    names = list(spec.bounds.get("ellipsoid", {}).get("variables", []))
    names += [n for n in spec.bounds.get("box", {}) if n not in names]
    rescue = spec.bounds.get("rescue", {})
    names += [n for n in (*rescue.get("variables", []), *rescue.get("guard", {})) if n not in names]
    names += [n for n in spec.bounds.get("forecast", {}).get("margins", {}) if n not in names]
    return names


def validate_against(
    spec: CoachSpec,
    observation_names: tuple[str, ...],
    actuator_names: tuple[str, ...],
    ctrlrange: dict[str, tuple[float, float]] | None = None,
    where: str = "spec",
) -> None:
    """Check every signal and actuator name, and offsets against ``ctrlrange``.

    Raises
    ------
    SpecError
        Naming the field and listing the valid names.
    """
    obs = ", ".join(observation_names)
    for name in bound_variables(spec):
        if name not in observation_names:
            raise SpecError(
                f"{where}: bounds: {shown(name)} is not an observation variable of {spec.env_id}; "
                f"valid names: {obs}"
            )
    for lp in spec.loops:
        for key in ("signal", "rate_signal"):
            name = getattr(lp, key)
            if name is not None and name not in observation_names:
                raise SpecError(
                    f"{where}: loop {lp.name!r}.{key}: {shown(name)} is not an observation variable of "
                    f"{spec.env_id}; valid names: {obs}"
                )
        for act, _ in lp.actuators:
            if act not in actuator_names:
                raise SpecError(
                    f"{where}: loop {lp.name!r}.actuators: no actuator {shown(act)} in {spec.env_id}; "
                    f"actuators: {', '.join(actuator_names)}"
                )
    for act, value in spec.offset:
        if act not in actuator_names:
            raise SpecError(
                f"{where}: offset.{act}: no such actuator; actuators: {', '.join(actuator_names)}"
            )
        if ctrlrange and act in ctrlrange:
            lo, hi = ctrlrange[act]
            if not lo <= value <= hi:
                raise SpecError(
                    f"{where}: offset.{act} = {value} is outside the actuator's ctrlrange [{lo}, {hi}]"
                )


def spec_to_dict(spec: CoachSpec) -> dict[str, Any]:
    """Canonical plain-data form of a spec (the TOML document)."""
    loops = []
    for lp in spec.loops:
        t: dict[str, Any] = {
            "name": lp.name,
            "signal": lp.signal,
            "setpoint": lp.setpoint,
            "action": lp.action,
            "kp": lp.kp,
            "ki": lp.ki,
            "kd": lp.kd,
        }
        if lp.rate_signal is not None:
            t["rate_signal"] = lp.rate_signal
        t.update(
            {
                "tf": lp.tf,
                "anti_windup": lp.anti_windup,
                "tt": lp.tt,
                "output_limits": [lp.output_limits[0], lp.output_limits[1]],
            }
        )
        if lp.feeds is not None:
            t["feeds"] = lp.feeds
        else:
            t["actuators"] = dict(lp.actuators)
        loops.append(t)
    out: dict[str, Any] = {
        "schema": SPEC_SCHEMA,
        "env_id": spec.env_id,
        "name": spec.name,
        "description": spec.description,
    }
    if spec.offset:
        out["offset"] = dict(spec.offset)
    out["loop"] = loops
    if spec.provenance:
        out["provenance"] = spec.provenance
    if spec.bounds:
        out["bounds"] = spec.bounds
    return out


def dumps_spec(spec: CoachSpec) -> str:
    """The canonical TOML text of ``spec``."""
    return tomli_w.dumps(spec_to_dict(spec), multiline_strings=False)


def loads_spec(text: str, where: str = "spec") -> CoachSpec:
    """Parse TOML text into a spec.

    Raises
    ------
    SpecError
    """
    return parse_spec(parse_toml(text, where, SpecError), where)


def load_spec(path: str | Path) -> CoachSpec:
    """Read a spec file.

    Raises
    ------
    SpecError
        Unreadable file, invalid TOML or an invalid field.
    """
    return parse_spec(read_toml(path, "coach spec", SpecError), str(path))


def save_spec(spec: CoachSpec, path: str | Path) -> Path:
    """Write ``spec`` atomically (temporary file, then rename) in canonical form."""
    from pidlab.checks import instance
    from pidlab.files import atomic_write_text

    return atomic_write_text(path, dumps_spec(instance(spec, CoachSpec, "spec")))


# --------------------------------------------------------------------------- writing spec files
#
# One rule for every command that writes a spec (``tune --auto -o``, ``bounds --write``,
# ``rescue --write``, the tuner's Save): it holds the spec's lock while it works on an existing
# file, it keeps every table it does not own, and it never replaces a file it did not open for
# editing unless it was asked to (``force``). A refusal changes nothing.


@contextmanager
def writing_spec(
    path: str | Path, *, force: bool = False, param: str = "path"
) -> Iterator[Callable[[CoachSpec], Path]]:
    """Write a new spec file: refused before any work when the file exists, unless ``force``.

    With ``force`` and an existing file, the file's lock is held for the whole block, so that
    ``bounds --write`` or ``rescue --write`` on it is refused meanwhile (and the reverse). The
    function the block receives writes the spec: replacing the file (``force``), else creating it
    only if no file appeared there in the meantime.

    Parameters
    ----------
    path : path
        The spec file to write.
    force : bool
        Replace an existing file (the whole spec: its bounds and rescue region go with it).
    param : str
        The parameter that named ``path`` (in messages).

    Yields
    ------
    callable
        ``write(spec) -> Path``.

    Raises
    ------
    SpecError
        The file exists and ``force`` is not given, another command holds its lock, or a file
        appeared at ``path`` while the block worked. Nothing was written then.
    OutputError
        ``path`` cannot be written (a folder, read-only, ...).
    """
    from pidlab.files import atomic_create_text, atomic_write_text, check_output_file
    from pidlab.provenance import hold_lock

    target = check_output_file(path, param)
    if target.exists() and not force:
        raise SpecError(
            f"{param}={target}: the file exists; replace it with force (--force), or write another file",
            param=param,
        )

    def write(spec: CoachSpec) -> Path:
        text = dumps_spec(spec)
        if force:
            return atomic_write_text(target, text)
        try:
            return atomic_create_text(target, text)
        except FileExistsError:
            raise SpecError(
                f"{param}={target}: another command created the file meanwhile; nothing was written "
                "(run again with force (--force) to replace it, or write another file)",
                param=param,
            ) from None

    with hold_lock(target, SpecError, param=param) if target.is_file() else nullcontext():
        yield write


@contextmanager
def editing_spec(path: str | Path, write: bool = True) -> Iterator[CoachSpec]:
    """The spec at ``path``, read under its lock when the block will rewrite it (``write``).

    The spec is read after the lock is taken, so a command that rewrote it just before is seen;
    the lock is held to the end of the block, so no other command rewrites it meanwhile.

    Raises
    ------
    SpecError
        The spec cannot be read, or another command holds its lock (nothing was changed).
    OutputError
        ``write`` and the file cannot be replaced (read-only, ...).
    """
    from pidlab.files import check_output_file
    from pidlab.provenance import hold_lock

    if not write:
        yield load_spec(path)
        return
    if not isinstance(path, (str, Path)) or not str(path):
        load_spec(path)  # the one message for what is no path
    check_output_file(path, "write")  # a folder, a read-only file: refused before the work
    if not Path(path).is_file():
        load_spec(path)  # the one message for a path that is no spec file
    with hold_lock(path, SpecError):
        yield load_spec(path)
