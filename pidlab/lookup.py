"""A boolean lookup table on a rectangular grid, and its TOML form: the data of a rescue region.

Also the data of the model predictor's measured forecast error (``[bounds.forecast]``,
:class:`ForecastError`): :mod:`pidlab.region.forecast` computes it, the spec reader checks it.

The rescue region of :mod:`pidlab.region.rescue` is stored in a coach spec's ``[bounds.rescue]``
table as a :class:`LookupGrid`; :mod:`pidlab.region.takeover` tests membership in it. The data
structure lives here, below every stage, because the spec reader of :mod:`pidlab.controller.spec`
checks the table too.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pidlab.errors import SpecError
from pidlab.provenance import digest

MODELS = ("linear", "learned")
"""The forecast models: the discrete linear model at the card's operating point, and that model
corrected by a network fitted on recorded transitions (:class:`ResidualNet`)."""

SCOPES = ("all", "domain")
"""Which recorded transitions set a forecast's margins: all of them, or those whose forecast lies in
the rescue region's domain box (the only ones whose error can decide a veto: a forecast whose
margin box lies in the region lies in that box). A table without ``scope`` used ``"all"``."""

BOUNDS = ("interval", "linear")
"""How the model predictor bounds a classifier's score over a forecast's margin box
(:func:`pidlab.region.relaxation.lowest_scores`): interval arithmetic, or a linear relaxation (tighter). A
``[bounds.forecast]`` table without ``bound`` was measured with ``"interval"``."""

SPLITS = 8
"""How many times the model predictor halves a margin box whose score bound is inconclusive
(:func:`pidlab.region.forecast.box_in_classifier`)."""

MAX_PIECES = 65_536
"""The largest cap on a model-predictor query's boxes per halving (``[bounds.forecast] pieces``);
with :data:`SPLITS` halvings no query asks more than ``2 ** SPLITS`` = 256 at once."""

TRIGGERS = ("reactive", "predictive")
"""What a rescue region was derived for: a check after the agent's step, or one before it."""

MAX_CELLS = 1_000_000
"""The largest lookup grid a spec may hold."""


@dataclass(frozen=True)
class LookupGrid:
    """A rescue region's data: a boolean lookup grid cut by a guard box.

    A state is in the region when every guard variable lies in its range and the grid cell of
    its grid variables is marked. Cells are half-open ``[lower + i h, lower + (i+1) h)``
    (the last one closed), ``h = (upper - lower) / cells``.

    Attributes
    ----------
    variables : tuple of str
        Grid variables (observation names).
    lower, upper : tuple of float
        The grid's domain.
    cells : tuple of int
        Cells per variable.
    table : ndarray of bool, shape ``cells``
        Marked cells.
    guard : dict
        ``variable -> (low, high)``: the other variables' ranges the estimate covered.
    trigger : {"reactive", "predictive"}
        What the region was derived for.
    action_fraction : float
        The agent step's size as a fraction of the action range (0 for ``predictive``).
    """

    variables: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    cells: tuple[int, ...]
    table: np.ndarray = field(compare=False, hash=False)
    guard: dict[str, tuple[float, float]] = field(default_factory=dict, compare=False, hash=False)
    trigger: str = "predictive"
    action_fraction: float = 0.0

    @property
    def widths(self) -> np.ndarray:
        """Cell widths, shape ``(k,)``."""
        return (np.array(self.upper) - np.array(self.lower)) / np.array(self.cells)

    def cell_of(self, points: np.ndarray) -> np.ndarray:
        """Cell indices of ``points`` (shape ``(n, k)``), ``-1`` rows for points outside the grid."""
        p = np.atleast_2d(np.asarray(points, dtype=float))
        lo, hi, n = np.array(self.lower), np.array(self.upper), np.array(self.cells)
        k = np.floor((p - lo) / self.widths).astype(int)
        k = np.where(p == hi, n - 1, k)
        outside = np.any((p < lo) | (p > hi) | ~np.isfinite(p), axis=1)
        k[outside] = -1
        return k

    def depth(self) -> np.ndarray:
        """Per cell, the distance in cells to the nearest unmarked cell or the grid's edge (0 outside)."""
        from scipy import ndimage

        padded = np.pad(self.table, 1, constant_values=False)
        d = ndimage.distance_transform_cdt(padded, metric="chessboard")
        return d[tuple(slice(1, -1) for _ in self.cells)].astype(int)

    def fraction_marked(self) -> float:
        """Share of the grid's cells that are marked."""
        return float(np.mean(self.table))

    def to_table(self) -> dict[str, Any]:
        """The ``[bounds.rescue]`` TOML table (rows of ``0``/``1`` along the last variable)."""
        rows = ["".join("1" if v else "0" for v in row) for row in self.table.reshape(-1, self.cells[-1])]
        return {
            "trigger": self.trigger,
            "action_fraction": float(self.action_fraction),
            "variables": list(self.variables),
            "lower": [float(v) for v in self.lower],
            "upper": [float(v) for v in self.upper],
            "cells": [int(v) for v in self.cells],
            "guard": {k: [float(v[0]), float(v[1])] for k, v in self.guard.items()},
            "rows": rows,
        }


def _finite_list(value: Any, k: int | None, where: str) -> list[float]:
    ok = isinstance(value, list) and (k is None or len(value) == k)
    if ok and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value):
        out = [float(v) for v in value]
        if all(np.isfinite(out)):
            return out
    n = f"{k} " if k is not None else ""
    raise SpecError(f"{where}: expected a list of {n}finite numbers")


def _check_cells(value: Any, k: int, where: str) -> list[int]:
    ok = isinstance(value, list) and len(value) == k
    if not ok or not all(isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 10_000 for v in value):
        raise SpecError(f"{where}: expected {k} whole numbers in [1, 10000]")
    if int(np.prod(value)) > MAX_CELLS:
        raise SpecError(f"{where}: {int(np.prod(value))} cells; at most {MAX_CELLS}")
    return list(value)


def _check_rows(value: Any, cells: list[int], where: str) -> np.ndarray:
    n_rows = int(np.prod(cells[:-1]))
    ok = isinstance(value, list) and len(value) == n_rows
    if not ok or not all(isinstance(r, str) and len(r) == cells[-1] and set(r) <= {"0", "1"} for r in value):
        raise SpecError(f"{where}: expected {n_rows} strings of {cells[-1]} characters 0 or 1")
    flat = np.array([c == "1" for r in value for c in r], dtype=bool)
    return flat.reshape(cells)


def _check_guard(value: Any, grid_vars: list[str], where: str) -> dict[str, tuple[float, float]]:
    if not isinstance(value, dict):
        raise SpecError(f"{where}: expected a table of variable = [low, high]")
    out = {}
    for name, lim in value.items():
        lo, hi = _finite_list(lim, 2, f"{where}.{name}")
        if not lo <= hi:
            raise SpecError(f"{where}.{name}: [{lo}, {hi}]; expected low <= high")
        if name in grid_vars:
            raise SpecError(f"{where}.{name}: a grid variable cannot be a guard variable too")
        out[str(name)] = (lo, hi)
    return out


LOOKUP_FIELDS = ("trigger", "action_fraction", "variables", "lower", "upper", "cells", "guard", "rows",
                 "provenance")  # fmt: skip
"""The fields of a ``[bounds.rescue]`` table."""
FORECAST_FIELDS = ("model", "region", "transitions", "held_out", "escapes", "seed", "margins", "median",
                   "p99", "agreement", "network", "bound", "scope", "in_scope",
                   "held_out_in_scope", "pieces", "adaptive")  # fmt: skip
"""The fields of a ``[bounds.forecast]`` table."""


def _check_fields(t: Any, where: str, allowed: tuple[str, ...]) -> None:
    """``t`` is a table with no field but ``allowed``."""
    if not isinstance(t, dict):
        raise SpecError(f"{where}: expected a table")
    unknown = set(t) - set(allowed)
    if unknown:
        raise SpecError(f"{where}: unknown field(s) {sorted(unknown)}; allowed: {', '.join(sorted(allowed))}")


def _variables_box(t: dict[str, Any], where: str, most: int) -> tuple[list[str], list[float], list[float]]:
    """A rescue table's ``variables`` (1 to ``most`` distinct names) with their ``lower`` < ``upper``."""
    raw = t.get("variables")
    names: list[str] = list(raw) if isinstance(raw, list) else []
    if not all(isinstance(v, str) and v for v in names) or not 1 <= len(names) <= most:
        raise SpecError(f"{where}.variables: expected 1 to {most} observation variable names")
    if len(set(names)) != len(names):
        raise SpecError(f"{where}.variables: a variable is named twice")
    lower = _finite_list(t.get("lower"), len(names), f"{where}.lower")
    upper = _finite_list(t.get("upper"), len(names), f"{where}.upper")
    if not all(lo < hi for lo, hi in zip(lower, upper, strict=True)):
        raise SpecError(f"{where}: expected lower < upper for every variable")
    return names, lower, upper


def parse_lookup(t: Any, where: str = "bounds.rescue") -> LookupGrid:
    """Read and check a ``[bounds.rescue]`` table.

    Raises
    ------
    SpecError
        A field missing, of the wrong type or out of range; the message names it.
    """
    _check_fields(t, where, LOOKUP_FIELDS)
    trigger = t.get("trigger")
    if trigger not in TRIGGERS:
        raise SpecError(f"{where}.trigger: {trigger!r}; expected one of {', '.join(TRIGGERS)}")
    frac = t.get("action_fraction")
    if isinstance(frac, bool) or not isinstance(frac, int | float) or not 0.0 <= frac <= 1.0:
        raise SpecError(f"{where}.action_fraction: {frac!r}; expected a number in [0, 1]")
    names, lower, upper = _variables_box(t, where, 4)
    k = len(names)
    cells = _check_cells(t.get("cells"), k, f"{where}.cells")
    table = _check_rows(t.get("rows"), cells, f"{where}.rows")
    guard = _check_guard(t.get("guard", {}), names, f"{where}.guard")
    grid = (tuple(names), tuple(lower), tuple(upper), tuple(cells))
    return LookupGrid(*grid, table, guard, trigger, float(frac))


# ----------------------------------------------------------------------------- the forecast's error


@dataclass(frozen=True)
class ForecastError:
    """How far the forecast missed, per region variable, on recorded transitions.

    Attributes
    ----------
    model : str
        The forecast model (:data:`MODELS`).
    variables : tuple of str
        The rescue region's variables (grid and guard).
    margins : tuple of float
        Per variable, the largest error over the transitions: the half-width of the box about a
        forecast that must lie in the region.
    median, p99 : tuple of float
        Per variable, the median and 99th percentile of the error.
    transitions : int
        How many transitions the margins were measured on.
    held_out : int
        How many further transitions checked them (and the agreement).
    escapes : int
        Held-out transitions whose true next observation lay outside the margins of the forecast.
    seed : int
        The recording's seed.
    agreement : dict
        Of the held-out actions put to both predictors (the model's: its margin box in the region):
        ``both`` vetoed, ``exact_only``, ``model_only``, ``neither``.
    region : str
        Digest of the ``[bounds.rescue]`` table measured on.
    network : ResidualNet or None
        The learned correction (``model = "learned"`` only), fitted on transitions before the
        ``transitions`` that set the margins.
    bound : str
        How a classifier region's score is bounded over a margin box (:data:`BOUNDS`); the
        agreement was measured with it. A lookup grid is asked cell by cell, exactly, either way.
    scope : str
        Which transitions set the margins (:data:`SCOPES`): all, or those whose forecast lies in the
        region's domain box.
    in_scope, held_out_in_scope : int or None
        Of ``transitions`` and ``held_out``, how many were in scope (the margins, quantiles and
        escapes are over those); None: all of them.
    pieces : int or None
        The most boxes one query of a classifier region may bound at one halving (a box whose next
        halving would ask more counts as unproven: the query's work is capped); None: no cap. The
        agreement was measured with it.
    adaptive : MarginScale or None
        Margins that depend on the state and the action (:meth:`margins_at`); the escapes and the
        agreement were measured with them. None: the constant ``margins``.
    """

    model: str
    variables: tuple[str, ...]
    margins: tuple[float, ...]
    median: tuple[float, ...]
    p99: tuple[float, ...]
    transitions: int
    held_out: int
    escapes: int
    seed: int
    agreement: dict[str, int]
    region: str
    network: ResidualNet | None = None
    bound: str = "interval"
    scope: str = "all"
    in_scope: int | None = None
    held_out_in_scope: int | None = None
    pieces: int | None = None
    adaptive: MarginScale | None = None

    @property
    def margin(self) -> dict[str, float]:
        """``variable -> margin``: the constant margins (with :attr:`adaptive`, the largest)."""
        return dict(zip(self.variables, self.margins, strict=True))

    def margins_at(self, inputs: np.ndarray) -> np.ndarray:
        """The margins of forecasts made from ``inputs`` (rows: the linear model's inputs), shape ``(n, k)``.

        The constant margins, or with :attr:`adaptive` its margins (never above the constant ones).
        """
        n = len(np.atleast_2d(inputs))
        if self.adaptive is None:
            return np.tile(np.array(self.margins), (n, 1))
        return self.adaptive.margins(inputs, np.array(self.margins))

    @property
    def veto_agreement(self) -> float:
        """Of the actions either predictor vetoes, the share both veto (1 when neither vetoes any)."""
        a = self.agreement
        either = a["both"] + a["exact_only"] + a["model_only"]
        return a["both"] / either if either else 1.0

    def to_table(self) -> dict[str, Any]:
        """The ``[bounds.forecast]`` table."""
        return {
            "model": self.model,
            "region": self.region,
            "transitions": self.transitions,
            "held_out": self.held_out,
            "escapes": self.escapes,
            "seed": self.seed,
            "margins": self.margin,
            "median": dict(zip(self.variables, self.median, strict=True)),
            "p99": dict(zip(self.variables, self.p99, strict=True)),
            "agreement": dict(self.agreement),
            "bound": self.bound,
            "scope": self.scope,
            **({"in_scope": self.in_scope} if self.in_scope is not None else {}),
            **({"held_out_in_scope": self.held_out_in_scope} if self.held_out_in_scope is not None else {}),
            **({"pieces": self.pieces} if self.pieces is not None else {}),
            **({"network": self.network.to_table()} if self.network is not None else {}),
            **({"adaptive": self.adaptive.to_table()} if self.adaptive is not None else {}),
        }


LOG_LIMIT = 30.0
"""The log error scale a :class:`MarginScale` network may give is clipped to ``+-LOG_LIMIT``."""


@dataclass(frozen=True)
class MarginScale:
    """Margins that depend on where a forecast is made: a calibrated multiple of a predicted error scale.

    A network (:class:`ResidualNet`, same inputs as the forecast) predicts the log of the
    forecast's error per variable, ``sigma(z)``; a forecast's margins are ``factors * sigma(z)``,
    and never more than the constant margins. ``factors`` are the largest ratio
    ``error / sigma`` over the transitions that set the constant margins (normalized conformal
    calibration), so on those transitions no error exceeds its margin, as with constant margins,
    while a forecast made where the error is small gets a small box.

    Attributes
    ----------
    network : ResidualNet
        ``network.correction(z)`` is ``log sigma(z)`` (clipped to :data:`LOG_LIMIT`).
    factors : tuple of float
        Per variable (the network's), the calibrated multiple.
    transitions : int
        The transitions recorded for the network's fit (before those that set the margins).
    """

    network: ResidualNet
    factors: tuple[float, ...]
    transitions: int

    def margins(self, inputs: np.ndarray, ceiling: np.ndarray) -> np.ndarray:
        """Per row of ``inputs``, the margins: ``factors * sigma``, at most ``ceiling``, shape ``(n, k)``.

        A row the network cannot score (not finite) gets the ceiling.
        """
        log = np.clip(self.network.correction(inputs), -LOG_LIMIT, LOG_LIMIT)
        return np.fmin(np.asarray(ceiling, dtype=float), np.array(self.factors) * np.exp(log))

    def to_table(self) -> dict[str, Any]:
        """The ``[bounds.forecast.adaptive]`` table."""
        return {
            "transitions": int(self.transitions),
            "factors": dict(zip(self.network.variables, self.factors, strict=True)),
            "network": self.network.to_table(),
        }


ADAPTIVE_FIELDS = ("transitions", "factors", "network")
"""The fields of a ``[bounds.forecast.adaptive]`` table."""


def parse_adaptive(t: Any, names: tuple[str, ...], where: str = "bounds.forecast.adaptive") -> MarginScale:
    """Read and check a ``[bounds.forecast.adaptive]`` table (over the margins' variables ``names``).

    Raises
    ------
    SpecError
        A field missing, of the wrong type or out of range; the message names it.
    """
    _check_fields(t, where, ADAPTIVE_FIELDS)
    n = t.get("transitions")
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise SpecError(f"{where}.transitions: {n!r}; expected an integer >= 1")
    factors = _per_variable(t.get("factors"), f"{where}.factors", names)
    network = parse_residual(t.get("network"), f"{where}.network", names)
    return MarginScale(network, tuple(factors[v] for v in names), n)


AGREEMENT = ("both", "exact_only", "model_only", "neither")


def valid_pieces(pieces: Any) -> bool:
    """Whether ``pieces`` caps a query's boxes: None (no cap), or an integer in [1, :data:`MAX_PIECES`]."""
    if pieces is None:
        return True
    return not isinstance(pieces, bool) and isinstance(pieces, int) and 1 <= pieces <= MAX_PIECES


def region_digest(rescue: dict[str, Any]) -> str:
    """The digest that ties a forecast's measurement to the ``[bounds.rescue]`` table it was made on."""
    return digest(rescue, 16)


def parse_forecast(t: Any, where: str = "bounds.forecast") -> ForecastError:
    """Read and check a ``[bounds.forecast]`` table.

    Raises
    ------
    SpecError
        A field missing, of the wrong type or out of range; the message names it.
    """
    _check_fields(t, where, FORECAST_FIELDS)
    if t.get("model") not in MODELS:
        raise SpecError(f"{where}.model: {t.get('model')!r}; expected one of {', '.join(MODELS)}")
    if not isinstance(t.get("region"), str) or not t["region"]:
        raise SpecError(f"{where}.region: expected the digest of the rescue region it was measured on")
    counts = {}
    for key, low in (("transitions", 1), ("held_out", 0), ("escapes", 0), ("seed", 0)):
        v = t.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or v < low:
            raise SpecError(f"{where}.{key}: {v!r}; expected an integer >= {low}")
        counts[key] = v
    if counts["escapes"] > counts["held_out"]:
        raise SpecError(f"{where}.escapes: {counts['escapes']} of {counts['held_out']} held-out transitions")
    margins = _per_variable(t.get("margins"), f"{where}.margins", None)
    names = tuple(margins)
    median = _per_variable(t.get("median"), f"{where}.median", names)
    p99 = _per_variable(t.get("p99"), f"{where}.p99", names)
    agreement = t.get("agreement")
    if not isinstance(agreement, dict) or set(agreement) != set(AGREEMENT) or not all(
        isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in agreement.values()
    ):  # fmt: skip
        raise SpecError(f"{where}.agreement: expected counts >= 0 of {', '.join(AGREEMENT)}")
    if sum(agreement.values()) != counts["held_out"]:
        raise SpecError(f"{where}.agreement: the counts add up to {sum(agreement.values())}, "
                        f"not to the {counts['held_out']} held-out transitions")  # fmt: skip
    network = _network_of(t, where, names)
    bound = t.get("bound", "interval")
    if bound not in BOUNDS:
        raise SpecError(f"{where}.bound: {bound!r}; expected one of {', '.join(BOUNDS)}")
    scope, in_scope, held_in = _scope_of(t, where, counts)
    pieces = t.get("pieces")
    if not valid_pieces(pieces):
        raise SpecError(
            f"{where}.pieces: {pieces!r}; expected an integer in [1, {MAX_PIECES}] (or no pieces: no cap)"
        )
    adaptive = parse_adaptive(t["adaptive"], names, f"{where}.adaptive") if "adaptive" in t else None
    return ForecastError(
        network=network, bound=bound, scope=scope, in_scope=in_scope, held_out_in_scope=held_in,
        pieces=pieces, adaptive=adaptive,
        model=t["model"], variables=names, margins=tuple(margins.values()),
        median=tuple(median[n] for n in names),
        p99=tuple(p99[n] for n in names), transitions=counts["transitions"], held_out=counts["held_out"],
        escapes=counts["escapes"], seed=counts["seed"],
        agreement={k: int(agreement[k]) for k in AGREEMENT}, region=t["region"],
    )  # fmt: skip


def _scope_of(t: dict[str, Any], where: str, counts: dict[str, int]) -> tuple[str, int | None, int | None]:
    """A forecast table's ``scope`` and its in-scope counts (at most the counts they are of)."""
    scope = t.get("scope", "all")
    if scope not in SCOPES:
        raise SpecError(f"{where}.scope: {scope!r}; expected one of {', '.join(SCOPES)}")
    found: list[int | None] = []
    for key, of, low in (("in_scope", "transitions", 1), ("held_out_in_scope", "held_out", 0)):
        v = t.get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or not low <= v <= counts[of]):
            raise SpecError(f"{where}.{key}: {v!r}; expected an integer in [{low}, {of} = {counts[of]}]")
        found.append(v)
    if any((scope == "domain") != (v is not None) for v in found):
        raise SpecError(
            f"{where}.in_scope: scope 'domain' needs in_scope and held_out_in_scope; scope 'all' has neither"
        )
    if counts["escapes"] > (counts["held_out"] if found[1] is None else found[1]):
        raise SpecError(f"{where}.escapes: {counts['escapes']} of {found[1]} held-out transitions in scope")
    return scope, found[0], found[1]


def _network_of(t: dict[str, Any], where: str, names: tuple[str, ...]) -> ResidualNet | None:
    """The ``network`` of a forecast table, over ``names``: needed for ``model = "learned"``, else refused."""
    learned = t["model"] == "learned"
    if ("network" in t) != learned:
        need = "a learned model needs its network" if learned else "only model = 'learned' has a network"
        raise SpecError(f"{where}.network: {need}")
    return parse_residual(t["network"], f"{where}.network", names) if learned else None


@dataclass(frozen=True)
class ResidualNet:
    """A learned correction of the linear forecast, added to its forecast of ``variables``.

    Its inputs are the linear model's: the state's tangent-space deviation from the operating point
    (``2 nv + na`` entries) and the control's (``nu``), standardized as
    ``(inputs - input_mean) / input_scale``; ``tanh`` hidden layers and a linear output, times
    ``output_scale``, give the correction per variable. The ``blind`` inputs are set to 0 first: the
    positions the observation leaves out (a walker's forward position), which the dynamics do not
    depend on and which grow without bound as the robot moves
    (:func:`pidlab.region.forecast.blind_inputs`).

    Attributes
    ----------
    variables : tuple of str
        The observation variables it corrects (the rescue region's).
    input_mean, input_scale, output_scale : tuple of float
    layers : tuple of (ndarray, ndarray)
        ``(weights, bias)`` per layer; weights of shape ``(inputs, outputs)``.
    fitted : int
        The transitions it was fitted on.
    blind : tuple of int
        Inputs set to 0 before the network (ascending). A table without ``blind`` read every input.
    """

    variables: tuple[str, ...]
    input_mean: tuple[float, ...]
    input_scale: tuple[float, ...]
    output_scale: tuple[float, ...]
    layers: tuple[tuple[np.ndarray, np.ndarray], ...] = field(compare=False, hash=False)
    fitted: int = 0
    blind: tuple[int, ...] = ()

    @property
    def inputs(self) -> int:
        """How many inputs it takes."""
        return len(self.input_mean)

    def correction(self, inputs: np.ndarray) -> np.ndarray:
        """The correction of each row of ``inputs`` (shape ``(n, inputs)``), shape ``(n, len(variables))``."""
        x = np.array(np.atleast_2d(np.asarray(inputs, dtype=float)))
        x[:, list(self.blind)] = 0.0
        h = tanh_forward(self.layers, (x - np.array(self.input_mean)) / np.array(self.input_scale))
        return h * np.array(self.output_scale)

    def to_table(self) -> dict[str, Any]:
        """The ``[bounds.forecast.network]`` table."""
        return {
            "variables": list(self.variables),
            "fitted": int(self.fitted),
            "input_mean": [float(v) for v in self.input_mean],
            "input_scale": [float(v) for v in self.input_scale],
            "output_scale": [float(v) for v in self.output_scale],
            **({"blind": list(self.blind)} if self.blind else {}),
            "layers": layers_table(self.layers),
        }


RESIDUAL_FIELDS = ("variables", "fitted", "input_mean", "input_scale", "output_scale", "blind", "layers")
"""The fields of a ``[bounds.forecast.network]`` table."""
MAX_RESIDUAL_INPUTS = 1000
"""The most inputs a learned forecast may take (``2 nv + na + nu``)."""


def parse_residual(
    t: Any, where: str = "bounds.forecast.network", variables: tuple[str, ...] | None = None
) -> ResidualNet:
    """Read and check a ``[bounds.forecast.network]`` table (over exactly ``variables``, when given).

    Raises
    ------
    SpecError
        A field missing, of the wrong type or out of range; the message names it.
    """
    _check_fields(t, where, RESIDUAL_FIELDS)
    raw = t.get("variables")
    names = list(raw) if isinstance(raw, list) else []
    if not names or not all(isinstance(n, str) and n for n in names) or len(set(names)) != len(names):
        raise SpecError(f"{where}.variables: expected distinct observation variable names")
    fitted = t.get("fitted")
    if isinstance(fitted, bool) or not isinstance(fitted, int) or fitted < 1:
        raise SpecError(f"{where}.fitted: {fitted!r}; expected an integer >= 1")
    mean = _finite_list(t.get("input_mean"), None, f"{where}.input_mean")
    if not 1 <= len(mean) <= MAX_RESIDUAL_INPUTS:
        raise SpecError(f"{where}.input_mean: expected 1 to {MAX_RESIDUAL_INPUTS} numbers")
    scale = _finite_list(t.get("input_scale"), len(mean), f"{where}.input_scale")
    out = _finite_list(t.get("output_scale"), len(names), f"{where}.output_scale")
    if min(scale) <= 0 or min(out) <= 0:
        raise SpecError(f"{where}: input_scale and output_scale must be > 0")
    layers = _check_layers(t.get("layers"), len(mean), f"{where}.layers", outputs=len(names))
    blind = t.get("blind", [])
    if not isinstance(blind, list) or not all(
        isinstance(k, int) and not isinstance(k, bool) and 0 <= k < len(mean) for k in blind
    ) or blind != sorted(set(blind)):  # fmt: skip
        raise SpecError(f"{where}.blind: expected ascending distinct input indices in [0, {len(mean) - 1}]")
    if variables is not None and tuple(names) != variables:
        raise SpecError(f"{where}.variables: expected the margins' variables {', '.join(variables)}")
    return ResidualNet(tuple(names), tuple(mean), tuple(scale), tuple(out), layers, fitted, tuple(blind))


def _per_variable(value: Any, where: str, names: tuple[str, ...] | None) -> dict[str, float]:
    """A ``variable = number >= 0`` table (with exactly ``names``, when given)."""
    ok = isinstance(value, dict) and bool(value) and all(
        isinstance(k, str) and isinstance(v, int | float) and not isinstance(v, bool)
        and bool(np.isfinite(v)) and v >= 0
        for k, v in value.items()
    )  # fmt: skip
    if not ok or (names is not None and tuple(value) != names):
        expected = f"the variables {', '.join(names)}" if names else "observation variables"
        raise SpecError(f"{where}: expected a table of {expected} = finite numbers >= 0")
    return {k: float(v) for k, v in value.items()}


# ----------------------------------------------------------------------------- a learned rescue region

CLASSIFIER_FIELDS = ("shape", "trigger", "action_fraction", "variables", "lower", "upper", "layers",
                     "threshold", "coach", "anchor", "provenance")  # fmt: skip
"""The fields of a ``[bounds.rescue]`` table whose region is a classifier (``shape = "classifier"``)."""

MAX_CLASSIFIER_VARIABLES = 24
"""The most state variables a classifier region may test."""

MAX_WIDTH = 512
"""The widest hidden layer a classifier region may hold."""


def tanh_forward(layers: tuple[tuple[np.ndarray, np.ndarray], ...], h: np.ndarray) -> np.ndarray:
    """A spec's small network on the rows of ``h``: ``tanh`` after every layer but the last."""
    for i, (w, b) in enumerate(layers):
        h = h @ w + b
        if i < len(layers) - 1:
            h = np.tanh(h)
    return h


def layers_table(layers: tuple[tuple[np.ndarray, np.ndarray], ...]) -> list[dict[str, Any]]:
    """A network's layers as TOML tables (``weights`` rows per input, ``bias``)."""
    return [{"weights": w.tolist(), "bias": b.tolist()} for w, b in layers]


@dataclass(frozen=True)
class RescueClassifier:
    """A rescue region's data as a classifier: a small network scores a state, a threshold decides.

    A state is in the region when every variable lies in the domain box and the score
    :meth:`scores` gives it is at least ``threshold``. The network takes the variables scaled to
    [-1, 1] over the domain box, has ``tanh`` hidden layers and one linear output.

    Attributes
    ----------
    variables : tuple of str
        The observation variables it tests (every one that decides a rescue).
    lower, upper : tuple of float
        The domain box it was fitted on; states outside it are outside the region.
    layers : tuple of (ndarray, ndarray)
        ``(weights, bias)`` per layer; weights of shape ``(inputs, outputs)``.
    threshold : float
        The validated score threshold.
    coach : str
        Digest of the coach it was fitted for (:func:`coach_digest`): a table copied from another
        spec is refused.
    trigger : {"predictive"}
        What the region was derived for (the state is tested before the agent's step runs).
    action_fraction : float
        0 (no agent step is allowed for).
    anchor : tuple of float or None
        Where the coach hands back: the state its law regulates to, which the region must hold and
        toward whose score the hand-back region tightens (:meth:`anchor_point`). None: the domain
        box's centre, the operating point (a coach designed elsewhere, such as the ``balance``
        preset's posture, names its own).
    """

    variables: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    layers: tuple[tuple[np.ndarray, np.ndarray], ...] = field(compare=False, hash=False)
    threshold: float = 0.0
    coach: str = ""
    trigger: str = "predictive"
    action_fraction: float = 0.0
    anchor: tuple[float, ...] | None = None

    def anchor_point(self) -> np.ndarray:
        """Where the coach hands back, shape ``(k,)``: :attr:`anchor`, else the domain box's centre."""
        if self.anchor is not None:
            return np.array(self.anchor, dtype=float)
        return (np.array(self.lower, dtype=float) + np.array(self.upper, dtype=float)) / 2.0

    def scaled(self, points: np.ndarray) -> np.ndarray:
        """``points`` (shape ``(n, k)``) scaled to [-1, 1] over the domain box."""
        lo, hi = np.array(self.lower), np.array(self.upper)
        return 2.0 * (np.atleast_2d(np.asarray(points, dtype=float)) - lo) / (hi - lo) - 1.0

    def scores(self, points: np.ndarray) -> np.ndarray:
        """The network's score of each row of ``points`` (shape ``(n, k)``), shape ``(n,)``."""
        return tanh_forward(self.layers, self.scaled(points))[:, 0]

    def inside(self, points: np.ndarray, threshold: float | None = None) -> np.ndarray:
        """Whether each row of ``points`` is in the domain box with a score of at least the threshold."""
        p = np.atleast_2d(np.asarray(points, dtype=float))
        boxed = np.all((p >= np.array(self.lower)) & (p <= np.array(self.upper)), axis=1)
        t = self.threshold if threshold is None else float(threshold)
        return boxed & (self.scores(p) >= t)

    def to_table(self) -> dict[str, Any]:
        """The ``[bounds.rescue]`` TOML table."""
        return {
            "shape": "classifier",
            "trigger": self.trigger,
            "action_fraction": float(self.action_fraction),
            "variables": list(self.variables),
            "lower": [float(v) for v in self.lower],
            "upper": [float(v) for v in self.upper],
            "layers": layers_table(self.layers),
            "threshold": float(self.threshold),
            "coach": self.coach,
        } | ({} if self.anchor is None else {"anchor": [float(v) for v in self.anchor]})


def coach_digest(env_id: str, loops: Any, offset: Any) -> str:
    """The digest of a coach's law (env, loops and offset; not its name): what a region is fitted for."""
    return digest({"env_id": env_id, "loops": loops, "offset": offset}, 16)


def is_classifier(t: Any) -> bool:
    """Whether a ``[bounds.rescue]`` table holds a classifier region (else a lookup grid)."""
    return isinstance(t, dict) and "shape" in t


def _check_layers(
    value: Any, k: int, where: str, outputs: int = 1
) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    if not isinstance(value, list) or not 2 <= len(value) <= 4:
        raise SpecError(f"{where}: expected 2 to 4 layers, each a table of weights and bias")
    out, inputs = [], k
    for i, layer in enumerate(value):
        here = f"{where}[{i}]"
        _check_fields(layer, here, ("weights", "bias"))
        rows = layer.get("weights")
        if not isinstance(rows, list) or len(rows) != inputs:
            raise SpecError(f"{here}.weights: expected {inputs} rows (one per input)")
        bias = _finite_list(layer.get("bias"), None, f"{here}.bias")
        width = len(bias)
        last = i == len(value) - 1
        if (last and width != outputs) or not 1 <= width <= MAX_WIDTH:
            want = f"{outputs} output{'s' if outputs != 1 else ''}" if last else f"1 to {MAX_WIDTH} units"
            raise SpecError(f"{here}.bias: {width} entries; expected {want}")
        w = np.array([_finite_list(r, width, f"{here}.weights[{j}]") for j, r in enumerate(rows)])
        out.append((w, np.array(bias)))
        inputs = width
    return tuple(out)


def parse_classifier(t: Any, where: str = "bounds.rescue") -> RescueClassifier:
    """Read and check a ``[bounds.rescue]`` table of ``shape = "classifier"``.

    Raises
    ------
    SpecError
        A field missing, of the wrong type or out of range; the message names it.
    """
    _check_fields(t, where, CLASSIFIER_FIELDS)
    if t.get("shape") != "classifier":
        raise SpecError(f"{where}.shape: {t.get('shape')!r}; expected 'classifier' (no shape: a lookup grid)")
    if t.get("trigger") != "predictive":
        raise SpecError(f"{where}.trigger: {t.get('trigger')!r}; a classifier region is for 'predictive'")
    frac = t.get("action_fraction")
    if isinstance(frac, bool) or not isinstance(frac, int | float) or frac != 0:
        raise SpecError(f"{where}.action_fraction: {frac!r}; expected 0 (predictive)")
    names, lower, upper = _variables_box(t, where, MAX_CLASSIFIER_VARIABLES)
    layers = _check_layers(t.get("layers"), len(names), f"{where}.layers")
    threshold = t.get("threshold")
    if isinstance(threshold, bool) or not isinstance(threshold, int | float) or not np.isfinite(threshold):
        raise SpecError(f"{where}.threshold: {threshold!r}; expected a finite number")
    if not isinstance(t.get("coach"), str) or not t["coach"]:
        raise SpecError(f"{where}.coach: expected the digest of the coach the classifier was fitted for")
    anchor = _anchor(t.get("anchor"), lower, upper, f"{where}.anchor")
    return RescueClassifier(tuple(names), tuple(lower), tuple(upper), layers, float(threshold), t["coach"],
                            anchor=anchor)  # fmt: skip


def _anchor(value: Any, lower: Any, upper: Any, where: str) -> tuple[float, ...] | None:
    """An optional hand-back point: one finite number per variable, inside the domain box."""
    if value is None:
        return None
    point = _finite_list(value, len(lower), where)
    if not all(lo <= v <= hi for v, lo, hi in zip(point, lower, upper, strict=True)):
        raise SpecError(f"{where}: {point}; expected a point inside the domain box (lower .. upper)")
    return tuple(float(v) for v in point)


def parse_rescue(t: Any, where: str = "bounds.rescue") -> LookupGrid | RescueClassifier:
    """Read and check a ``[bounds.rescue]`` table: a classifier when it names a shape, else a lookup grid."""
    return parse_classifier(t, where) if is_classifier(t) else parse_lookup(t, where)
