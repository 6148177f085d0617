"""Takeover regions: where the agent acts freely, and the one question every consumer asks of them.

A coach spec's ``[bounds]`` table may hold three sets, in observation variables:

``ellipsoid``
    The **certified core**: the Lyapunov level set of :mod:`pidlab.region.roa`, checked in MuJoCo.
    As a takeover region it is shrunk to ``rho * level`` (room for one worst-case agent step).
``box``
    A box on a few variables (inside the core's projection, or the simulated recoverable box).
``rescue``
    A **rescue region** (:mod:`pidlab.region.rescue`): a lookup grid on two to four variables,
    cut by a guard box on others, whose cells hold the states from which the coach recovers in
    MuJoCo (after one agent step for the ``reactive`` trigger; from the state itself for the
    ``predictive`` one); or (``shape = "classifier"``, :mod:`pidlab.region.classifier`) a learned
    classifier over every variable that decides a rescue, validated the same way.

``[bounds] takeover = "rescue" | "box" | "ellipsoid"`` names the spec's takeover region (default:
the rescue region when there is one, else the box). :func:`load_region` returns it as an object
whose ``contains(obs)`` takes the env's observation vector: the coaching wrapper, the reports
and users ask the same object.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from pidlab.checks import shown
from pidlab.errors import CoachingError
from pidlab.lookup import LookupGrid, RescueClassifier, parse_rescue

KINDS = ("box", "ellipsoid", "rescue")
"""The shapes a takeover region can have."""


class Region(Protocol):
    """What every takeover region answers."""

    kind: str
    variables: tuple[str, ...]
    scale: float
    """Its width (1: as estimated); only a box or an ellipsoid is scaled, a rescue region stays at 1."""

    def contains(self, obs: np.ndarray) -> bool:
        """Whether the observation ``obs`` lies in the region (where the agent acts freely)."""
        ...

    def inner(self, fraction: float) -> Region:
        """The region shrunk to ``fraction`` of its size (a hand-back region), ``0 < fraction <= 1``."""
        ...


def observation_indices(
    names: tuple[str, ...] | list[str], observation_names: tuple[str, ...], where: str
) -> list[int]:
    """Columns of ``names`` in the observation; :class:`CoachingError` names an unknown one."""
    out = []
    for n in names:
        if n not in observation_names:
            valid = ", ".join(observation_names)
            raise CoachingError(f"{where}: {n!r} is not an observation variable; valid: {valid}")
        out.append(observation_names.index(n))
    return out


def checked_observation(obs: Any, size: int, inside: Callable[[Any], bool]) -> bool:
    """``inside(obs)`` for an observation of ``size`` numbers; else the error ``contains`` raises."""
    try:
        if len(obs) == size:
            return inside(obs)
    except (TypeError, IndexError, ValueError):
        pass
    raise _bad_observation(obs, size)


def _bad_observation(obs: Any, size: int) -> CoachingError:
    """Why ``obs`` is no observation of ``size`` numbers, as the error ``contains`` raises."""
    try:
        got = f"{len(obs)} entr{'y' if len(obs) == 1 else 'ies'}"
    except TypeError:
        got = type(obs).__name__
    return CoachingError(f"obs={shown(obs)}: expected the env's observation, {size} numbers (got {got})",
                         param="obs")  # fmt: skip


def _check_fraction(fraction: float, where: str) -> float:
    f = float(fraction)
    if not 0.0 < f <= 1.0 or not np.isfinite(f):
        raise CoachingError(f"{where}: {fraction!r}; expected a fraction in (0, 1]")
    return f


class BoxRegion:
    """Every listed variable within its range.

    Parameters
    ----------
    box : dict
        ``variable -> (low, high)``.
    observation_names : tuple of str
    scale : float
        Factor on the half-widths about the box's centre.
    """

    kind = "box"

    def __init__(self, box: dict[str, Any], observation_names: tuple[str, ...], scale: float = 1.0) -> None:
        self.box = {k: (float(v[0]), float(v[1])) for k, v in box.items()}
        self.variables = tuple(self.box)
        self.observation_names = observation_names
        idx = observation_indices(self.variables, observation_names, "bounds.box")
        lo = np.array([v[0] for v in self.box.values()])
        hi = np.array([v[1] for v in self.box.values()])
        self.center, self.half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        self._idx = idx
        self._size = len(observation_names)
        self.scale = scale

    @property
    def scale(self) -> float:
        """Factor on the half-widths."""
        return self._scale

    @scale.setter
    def scale(self, value: float) -> None:
        self._scale = float(value)
        # plain floats: for a handful of variables Python comparisons beat numpy on tiny arrays
        self._limits = [
            (i, float(c - h * self._scale), float(c + h * self._scale))
            for i, c, h in zip(self._idx, self.center, self.half, strict=True)
        ]

    def contains(self, obs: np.ndarray) -> bool:
        """Whether ``obs`` lies in the (scaled) box.

        Raises
        ------
        CoachingError
            ``obs`` is not an observation of the env (another length, not numbers).
        """
        inside = lambda o: all(lo <= o[i] <= hi for i, lo, hi in self._limits)  # noqa: E731
        return checked_observation(obs, self._size, inside)

    def inner(self, fraction: float) -> BoxRegion:
        """The box with its half-widths times ``fraction``."""
        scale = self._scale * _check_fraction(fraction, "hand-back")
        return BoxRegion(self.box, self.observation_names, scale)


class EllipsoidRegion:
    """``(y - center)' shape (y - center) <= rho * level * scale**2``.

    Parameters
    ----------
    ellipsoid : dict
        The ``[bounds.ellipsoid]`` table.
    observation_names : tuple of str
    scale : float
    certified : bool
        ``True``: the whole certified level ``level`` (the core); ``False``: ``rho * level``.
    """

    kind = "ellipsoid"

    def __init__(
        self, ellipsoid: dict[str, Any], observation_names: tuple[str, ...], scale: float = 1.0,
        certified: bool = False,
    ) -> None:  # fmt: skip
        self.ellipsoid = ellipsoid
        self.certified = certified
        self.variables = tuple(ellipsoid["variables"])
        self.observation_names = observation_names
        self.index = np.array(observation_indices(self.variables, observation_names, "bounds.ellipsoid"))
        self._size = len(observation_names)
        self.center = np.array(ellipsoid["center"], dtype=float)
        self.shape = np.array(ellipsoid["shape"], dtype=float)
        rho = 1.0 if certified else float(ellipsoid["rho"])
        self.threshold = rho * float(ellipsoid["level"])
        self.scale = float(scale)

    def contains(self, obs: np.ndarray) -> bool:
        """Whether ``obs`` lies in the (scaled) ellipsoid.

        Raises
        ------
        CoachingError
            ``obs`` is not an observation of the env (another length, not numbers).
        """
        try:
            x = np.asarray(obs, dtype=float)
        except (TypeError, ValueError):
            raise _bad_observation(obs, self._size) from None
        if x.shape != (self._size,):
            raise _bad_observation(obs, self._size)
        y = x[self.index] - self.center
        return bool(y @ self.shape @ y <= self.threshold * self.scale**2)

    def inner(self, fraction: float) -> EllipsoidRegion:
        """The ellipsoid with its semi-axes times ``fraction``."""
        f = self.scale * _check_fraction(fraction, "hand-back")
        return EllipsoidRegion(self.ellipsoid, self.observation_names, f, self.certified)


class GridRegion:
    """Membership in a :class:`LookupGrid`, bound to an env's observation layout.

    Parameters
    ----------
    grid : LookupGrid
    observation_names : tuple of str
    min_depth : int
        Only cells at least this deep count (0: every marked cell); see :meth:`inner`.
    """

    kind = "rescue"

    def __init__(self, grid: LookupGrid, observation_names: tuple[str, ...], min_depth: int = 0) -> None:
        self.grid = grid
        self.variables = grid.variables
        self.min_depth = int(min_depth)
        self.observation_names = observation_names
        self._depth = grid.depth()
        marked = self._depth > self.min_depth if self.min_depth > 0 else grid.table
        self._flat = [bool(v) for v in np.asarray(marked).ravel()]
        idx = observation_indices(grid.variables, observation_names, "bounds.rescue.variables")
        strides = np.cumprod((*grid.cells[1:], 1)[::-1])[::-1]
        self._axes = [
            (i, lo, hi, float(n) / (hi - lo), n, int(s))
            for i, lo, hi, n, s in zip(idx, grid.lower, grid.upper, grid.cells, strides, strict=True)
        ]
        gidx = observation_indices(tuple(grid.guard), observation_names, "bounds.rescue.guard")
        self._guard = [(i, lo, hi) for i, (lo, hi) in zip(gidx, grid.guard.values(), strict=True)]
        self._size = len(observation_names)
        self.scale = 1.0

    @property
    def trigger(self) -> str:
        """What the region was derived for: ``"predictive"`` or ``"reactive"``."""
        return self.grid.trigger

    @property
    def max_depth(self) -> int:
        """The deepest cell's depth."""
        return int(self._depth.max(initial=0))

    @property
    def centre_depth(self) -> int:
        """The depth of the cell holding the grid's centre (the operating point; 0 if unmarked)."""
        g = self.grid
        centre = (np.array(g.lower) + np.array(g.upper)) / 2.0
        return int(self._depth[tuple(g.cell_of(centre[None, :])[0])])

    def contains(self, obs: np.ndarray) -> bool:
        """Whether ``obs`` lies in the guard box and in a marked cell.

        Raises
        ------
        CoachingError
            ``obs`` is not an observation of the env (another length, not numbers).
        """
        return checked_observation(obs, self._size, self._contains)

    def _in_guard(self, obs: np.ndarray) -> bool:
        return all(lo <= obs[i] <= hi for i, lo, hi in self._guard)

    def _contains(self, obs: np.ndarray) -> bool:
        if not self._in_guard(obs):
            return False
        flat = 0
        for i, lo, hi, inv, n, stride in self._axes:
            x = float(obs[i])
            if not lo <= x <= hi:
                return False
            flat += min(int((x - lo) * inv), n - 1) * stride
        return self._flat[flat]

    def inner(self, fraction: float) -> GridRegion:
        """The cells deeper than ``(1 - fraction)`` of the deepest cell's depth.

        The depth asked is capped so that the operating point's own cell stays in: a coach that
        settles at its operating point always hands back, however thin the region is there.
        """
        f = _check_fraction(fraction, "hand-back")
        depth = min(int(np.floor((1.0 - f) * self.max_depth)), max(self.centre_depth - 1, 0))
        return GridRegion(self.grid, self.observation_names, max(depth, self.min_depth))


class ClassifierRegion:
    """Membership in a :class:`~pidlab.lookup.RescueClassifier`, bound to an env's observation layout.

    Parameters
    ----------
    classifier : RescueClassifier
    observation_names : tuple of str
    fraction : float
        ``inner(fraction)``: the threshold moved from the validated one towards the operating point's
        score by ``1 - fraction`` (1: the validated region).
    operating_score : float, optional
        The score where the coach hands back (default: at the classifier's
        :meth:`~pidlab.lookup.RescueClassifier.anchor_point`, the domain box's centre, which the
        estimate puts at the operating point, unless the coach regulates to a point of its own).
    """

    kind = "rescue"
    trigger = "predictive"

    def __init__(
        self, classifier: RescueClassifier, observation_names: tuple[str, ...], fraction: float = 1.0,
        operating_score: float | None = None,
    ) -> None:  # fmt: skip
        self.classifier = classifier
        self.variables = classifier.variables
        self.observation_names = observation_names
        idx = observation_indices(classifier.variables, observation_names, "bounds.rescue.variables")
        self._idx = np.array(idx)
        self._size = len(observation_names)
        self._lo, self._hi = np.array(classifier.lower), np.array(classifier.upper)
        self._scale = 2.0 / (self._hi - self._lo)
        self._layers = classifier.layers
        if operating_score is None:
            operating_score = float(classifier.scores(classifier.anchor_point()[None, :])[0])
        self.operating_score = operating_score
        self.fraction = fraction
        self.scale = 1.0  # a rescue region is not scaled (a width schedule on one is refused)
        t = classifier.threshold
        self.threshold = t + (1.0 - fraction) * max(operating_score - t, 0.0)

    def _score(self, y: np.ndarray) -> float:
        h = (y - self._lo) * self._scale - 1.0
        last = len(self._layers) - 1
        for i, (w, b) in enumerate(self._layers):
            h = h @ w + b
            if i < last:
                h = np.tanh(h)
        return float(h[0])

    def _contains(self, obs: np.ndarray) -> bool:
        y = np.asarray(obs, dtype=float)[self._idx]
        if not (np.all(y >= self._lo) and np.all(y <= self._hi)):
            return False
        return self._score(y) >= self.threshold

    def contains(self, obs: np.ndarray) -> bool:
        """Whether ``obs`` lies in the domain box with a score of at least the threshold.

        Raises
        ------
        CoachingError
            ``obs`` is not an observation of the env (another length, not numbers).
        """
        return checked_observation(obs, self._size, self._contains)

    def inner(self, fraction: float) -> ClassifierRegion:
        """The region whose threshold lies ``1 - fraction`` of the way to the operating point's score."""
        f = self.fraction * _check_fraction(fraction, "hand-back")
        return ClassifierRegion(self.classifier, self.observation_names, f, self.operating_score)


def takeover_kind(bounds: dict[str, Any] | None) -> str | None:
    """The takeover region a ``[bounds]`` table names (``None`` without bounds)."""
    if not bounds:
        return None
    if "takeover" in bounds:
        return str(bounds["takeover"])
    if "rescue" in bounds:
        return "rescue"
    return "box" if "box" in bounds else "ellipsoid" if "ellipsoid" in bounds else None


def region_from_bounds(
    bounds: dict[str, Any] | None, observation_names: tuple[str, ...], kind: str | None = None,
    name: str = "spec",
) -> Region:  # fmt: skip
    """The region ``kind`` (default: the takeover one) of a ``[bounds]`` table.

    Raises
    ------
    CoachingError
        ``kind`` unknown, or the table has no such region.
    """
    if kind is None:
        kind = takeover_kind(bounds)
        if kind is None:
            raise CoachingError(
                f"{name}: the spec has no [bounds], so no takeover region; "
                "run `pidlab bounds SPEC --write` (and `pidlab rescue SPEC --write`) first"
            )
    elif kind not in KINDS:
        raise CoachingError(f"kind={shown(kind)}: expected one of {', '.join(KINDS)}", param="kind")
    if kind not in KINDS:  # the spec's [bounds] takeover names no shape (a spec file checks this)
        raise CoachingError(f"{name}: [bounds] takeover = {shown(kind)}: expected one of {', '.join(KINDS)}")
    b = bounds or {}
    if kind not in b:
        hint = {
            "rescue": "run `pidlab rescue SPEC --write`",
            "ellipsoid": "its bounds come from a simulated recoverable box (contacts), which has no "
            'ellipsoid; use region = "box"'
            if b.get("box")
            else "run `pidlab bounds SPEC --write`",
            "box": "run `pidlab bounds SPEC --write`",
        }[kind]
        raise CoachingError(f"{name}: the spec has no [bounds.{kind}]; {hint}")
    if kind == "box":
        return BoxRegion(b["box"], observation_names)
    if kind == "ellipsoid":
        return EllipsoidRegion(b["ellipsoid"], observation_names)
    rescue = parse_rescue(b["rescue"])
    if isinstance(rescue, RescueClassifier):
        return ClassifierRegion(rescue, observation_names)
    return GridRegion(rescue, observation_names)


def load_region(spec: Any, kind: str | None = None) -> Region:
    """The takeover region of a coach spec, whatever its shape.

    Parameters
    ----------
    spec : CoachSpec or str or Path
        A spec, or the path of a spec file.
    kind : {"box", "ellipsoid", "rescue"}, optional
        Another of the spec's regions (default: the one ``[bounds] takeover`` names).

    Returns
    -------
    Region
        ``region.contains(obs)`` takes the env's observation vector.

    Raises
    ------
    CoachingError
        The spec has no such region, or its env has no model card.
    SpecError
        The spec file cannot be read.

    Examples
    --------
    >>> region = pidlab.load_region("tuning/InvertedPendulum-v5.pidlab-robust.toml")  # doctest: +SKIP
    >>> region.contains(env.reset(seed=0)[0])  # doctest: +SKIP
    True
    """
    from pidlab.controller.spec import CoachSpec, load_spec
    from pidlab.plant.card import find_card

    if isinstance(spec, str | Path):
        spec = load_spec(spec)
    if not isinstance(spec, CoachSpec):
        raise CoachingError(f"spec={shown(spec)}: expected a CoachSpec or a spec file's path", param="spec")
    card = find_card(spec.env_id)
    if card is None:
        raise CoachingError(f"{spec.name}: {spec.env_id} has no model card, so its observation is unknown")
    return region_from_bounds(spec.bounds, card.observation_names, kind, spec.name)
