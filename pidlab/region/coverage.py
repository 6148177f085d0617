"""Rescue coverage over the env's own termination domain, and how often a region claims too much.

A region estimate scores its coverage over its *own* domain: a lookup grid over the pole and its
rate, with the cart in a guard box, or the torso's pitch with the legs at the standing pose. That
says nothing about the states an agent actually visits, where the other variables move. This
module scores any spec's regions over a domain the caller names, the same for every coach:

1. **Domain.** A box about the operating point over observation variables (a joint's position,
   its sine, or its velocity); every variable not named stays at the operating point. A drawn
   state is dropped when the env's termination rule ends it or a limited joint lies outside its
   range: what remains is the env's own termination domain, cut by the box on the rates (no
   termination rule bounds them). A model that stands on a floor starts on it
   (:meth:`pidlab.region.simulate.Simulator.start`).
2. **Labels.** ``states`` states drawn uniformly there are simulated as a region estimate's probes
   are: the coach's real discrete law in MuJoCo, *rescued* when it brings the state into the
   spec's certified core (or, for a coach certified by simulation, survives the horizon) without a
   termination.
3. **Scores**, per region of the spec's ``[bounds]`` (rescue region, certified core, box):
   the **coverage** (share of the rescuable states the region holds) and the **false claims**
   (share of the region's states the coach does *not* rescue, with a 95 % Clopper-Pearson
   interval). A region with false claims lets an agent fall while the coach acts: the region
   tests fewer variables than decide a rescue. A spec with a forecast measurement
   (``[bounds.forecast]``) also scores its rescue region as the model predictor asks it
   (:data:`MODEL_KIND`).

Deterministic from ``seed``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import binomtest

from pidlab.checks import integer, number
from pidlab.checks import seed as check_seed
from pidlab.controller.spec import CoachSpec
from pidlab.errors import CoachingError, RegionError
from pidlab.linear.linearize import linearize
from pidlab.plant.model import LoadedModel
from pidlab.region.forecast import (
    ClassifierMarginRegion,
    check_adaptive,
    linear_forecast,
    margin_region,
    spec_forecast,
)
from pidlab.region.rescue import _Estimate, check_into, simulations, state_domain
from pidlab.region.takeover import region_from_bounds

Progress = Callable[[str, "float | None"], None]

MAX_STATES = 1_000_000
"""The most states one coverage measurement may simulate."""

MAX_DOMAIN_VARIABLES = 64
"""The most variables a coverage domain may span."""

MAX_DRAWS = 2000
"""Uniform draws per state kept, at most, before a domain is called empty (rejection sampling)."""

MAX_REGION_DRAWS = 50_000
"""The same for draws inside a region (``keep``), which are rejected before any simulator work."""

FIRST_DRAWS = 100_000
"""Uniform draws after which a domain (or region) that kept no state at all is called empty."""

REGION_KINDS = {"rescue": "rescue region", "ellipsoid": "certified core", "box": "box"}
"""The ``[bounds]`` regions scored, and their names in the tables."""
MODEL_KIND = "rescue region through the forecast's margins"
"""The name of the rescue region as the model predictor asks it (a spec with ``[bounds.forecast]``):
a state counts as inside when the whole box of the forecast's margins about it lies in the region,
i.e. when a forecast landing there would pass."""


@dataclass(frozen=True)
class DomainSettings:
    """The domain a coverage is measured over, and how many states.

    Attributes
    ----------
    variables : tuple of str
        Observation variables (a hinge or slide joint's position, its sine, or its velocity).
    half_range : tuple of float
        The box's half-widths about the operating point's observation.
    states : int
        States drawn and simulated.
    horizon_s : float
        Simulated time per rescue, s.
    seed : int
    into : {"core", "box"}
        Where a rescue ends (:data:`pidlab.region.rescue.RESCUE_ENDS`): the certified core (a coach
        certified by simulation: the horizon held), or the horizon held and ended in the
        recoverable box ``[bounds.box]``.
    """

    variables: tuple[str, ...]
    half_range: tuple[float, ...]
    states: int = 2000
    horizon_s: float = 3.0
    seed: int = 0
    into: str = "core"

    def __post_init__(self) -> None:
        """Refuse settings out of range at once (:class:`RegionError` naming the field)."""
        k = len(self.variables)
        if not 1 <= k <= MAX_DOMAIN_VARIABLES or len(self.half_range) != k or len(set(self.variables)) != k:
            raise RegionError(
                f"coverage domain: expected 1 to {MAX_DOMAIN_VARIABLES} distinct variables, a half-range each"
            )
        for name, h in zip(self.variables, self.half_range, strict=True):
            number(h, f"half-range of {name}", RegionError, low=0.0, low_open=True)
        integer(self.states, "states", RegionError, low=1, high=MAX_STATES, param="states")
        number(self.horizon_s, "horizon_s", RegionError, low=0.0, low_open=True, high=600.0, unit="s",
               param="horizon_s")  # fmt: skip
        check_seed(self.seed, "seed", RegionError, param="seed")
        check_into(self.into)


@dataclass(frozen=True)
class RegionScore:
    """One region scored on the domain's states.

    Attributes
    ----------
    kind : str
        ``rescue region``, ``certified core`` or ``box``.
    inside : int
        Domain states the region holds.
    held : int
        Of those, the ones the coach rescues.
    coverage : float
        ``held`` over the domain's rescuable states (0 when none is rescuable).
    false_claims : float
        Share of ``inside`` the coach does not rescue (nan when ``inside`` is 0).
    false_claims_ci : (float, float)
        Its 95 % Clopper-Pearson interval (nan when ``inside`` is 0).
    """

    kind: str
    inside: int
    held: int
    coverage: float
    false_claims: float
    false_claims_ci: tuple[float, float]


@dataclass(frozen=True)
class DomainCoverage:
    """How much of the domain the coach rescues, and how each of the spec's regions reads it.

    Attributes
    ----------
    env_id, spec_name : str
    settings : DomainSettings
    grounded : bool
        The starts were put on the floor.
    rescuable : int
        Domain states the coach rescues.
    scores : tuple of RegionScore
        Per region of the spec's ``[bounds]``.
    simulations : int
    elapsed_s : float
    reach, reach95 : tuple of float
        Per domain variable, the largest and the 95th percentile of the rescued states' distance
        from the operating point (nan when none is rescued): the box a classifier region's domain
        needs to hold every rescued state, or 95 % of them along each variable
        (:meth:`classifier_domain`). Empty for a measurement made before they were recorded.
    reused : int
        Of :attr:`simulations`, the outcomes read from a journal instead of simulated (a resumed
        run); not part of the figures (:meth:`to_dict` leaves it out).
    """

    env_id: str
    spec_name: str
    settings: DomainSettings
    grounded: bool
    rescuable: int
    scores: tuple[RegionScore, ...]
    simulations: int
    elapsed_s: float
    reach: tuple[float, ...] = ()
    reach95: tuple[float, ...] = ()
    reused: int = field(default=0, compare=False)

    def classifier_domain(self, share: str = "all") -> str:
        """``pidlab rescue-classifier --domain`` for a box about the rescued states (``all`` or ``95``).

        Each half-width is the rescued states' reach (:attr:`reach` or :attr:`reach95`) rounded up
        to two significant digits, capped at this domain's own; empty when none is rescued.
        """
        reach = self.reach if share == "all" else self.reach95
        if not reach or not np.all(np.isfinite(reach)):
            return ""
        pairs = zip(self.settings.variables, reach, self.settings.half_range, strict=True)
        return ",".join(f"{name}={min(_round_up(r), h):g}" for name, r, h in pairs)

    @property
    def rescuable_share(self) -> float:
        """Share of the domain's states the coach rescues."""
        return self.rescuable / self.settings.states

    def score(self, kind: str) -> RegionScore | None:
        """The score of region ``kind`` (a :data:`REGION_KINDS` value), or None."""
        return next((s for s in self.scores if s.kind == kind), None)

    def to_dict(self) -> dict[str, Any]:
        """Plain data (JSON)."""
        out = asdict(self)
        del out["reused"]
        out["settings"]["domain"] = dict(zip(self.settings.variables, self.settings.half_range, strict=True))
        out["rescuable_share"] = self.rescuable_share
        return out


def draw_states(
    est: _Estimate, n: int, keep: Callable[[np.ndarray], np.ndarray] | None = None, kept: str = "what is kept"
) -> np.ndarray:
    """``n`` states uniform in the estimate's domain that the env can be in (and that ``keep`` accepts).

    A state is dropped when the env's termination rule ends it or a limited joint lies outside its
    range; starts are on the floor when ``est.grounded``. ``kept`` names what ``keep`` accepts, for
    the error.

    Raises
    ------
    RegionError
        The domain (or ``keep``) leaves (almost) nothing of the box.
    """
    d, rng = est.domain, est.rng

    def candidates(m: int) -> np.ndarray:
        batch = rng.uniform(d.lower, d.upper, (m, len(d.grid_vars)))
        # cheap and vectorized: before the simulator's check of each state
        return batch if keep is None else batch[keep(batch)]

    most = (MAX_DRAWS if keep is None else MAX_REGION_DRAWS) * n
    why = (
        "lay in the region's domain (the termination rule or the joint ranges leave almost nothing of "
        "the box)"
        if keep is None
        else f"lay in {kept}"
    )
    return _possible_states(est, n, candidates, most, ("uniform draws", why))


NEAR_SCALES = (0.01, 0.5)
"""The smallest and largest box about a point that :func:`draw_near` draws in, as a fraction of the
domain's half-widths (log-uniform between them)."""


def draw_near(est: _Estimate, n: int, centres: np.ndarray) -> np.ndarray:
    """``n`` states the env can be in, drawn in boxes about ``centres`` (rows, in turn), in the domain.

    Each state's box is the domain's half-widths times a scale drawn log-uniform in
    :data:`NEAR_SCALES`, clipped to the domain. Uniform draws over a domain of many variables never
    come near one point (on Walker2d's 16 variables, none of 210,000 lay within 30 % of the
    half-widths of the posture in every variable); these do, at every distance.

    Raises
    ------
    RegionError
        The env can be in almost none of them (the termination rule or the joint ranges).
    """
    d, rng = est.domain, est.rng
    centres = np.atleast_2d(np.asarray(centres, dtype=float))
    half = (np.asarray(d.upper) - np.asarray(d.lower)) / 2.0
    lo, hi = np.log(NEAR_SCALES[0]), np.log(NEAR_SCALES[1])

    def candidates(m: int) -> np.ndarray:
        scale = np.exp(rng.uniform(lo, hi, (m, 1)))
        batch = centres[np.arange(m) % len(centres)] + scale * half * rng.uniform(-1.0, 1.0, (m, len(half)))
        return np.clip(batch, d.lower, d.upper)

    return _possible_states(
        est, n, candidates, MAX_DRAWS * n, ("draws near their centres", "were ones the env can be in")
    )


def _possible_states(
    est: _Estimate, n: int, candidates: Callable[[int], np.ndarray], most: int, said: tuple[str, str]
) -> np.ndarray:
    """``n`` states the env can be in, from ``candidates(m)``: those kept of ``m`` drawn.

    Raises
    ------
    RegionError
        More than ``most`` drawn, or none kept of the first :data:`FIRST_DRAWS`; ``said`` names the
        draws and what the kept states are.
    """
    d, sim = est.domain, est.pool.sim
    out: list[np.ndarray] = []
    drawn = 0
    while len(out) < n:
        if drawn > most or (drawn >= FIRST_DRAWS and not out):
            raise RegionError(f"after {drawn:,} {said[0]} only {len(out):,} of {n:,} states {said[1]}")
        m = max(n, 1000)
        batch = candidates(m)
        drawn += m
        alive = np.array([_possible(sim, d.to_plant(v, sim), est.grounded) for v in batch], dtype=bool)
        out.extend(batch[alive][: n - len(out)])
    return np.array(out).reshape(n, len(d.grid_vars))


def _possible(sim: Any, x: np.ndarray, grounded: bool) -> bool:
    """Whether the env can be in the state ``x``: within the joint ranges, not terminated."""
    obs = sim.start(x, grounded=grounded)
    return sim.within_limits() and not sim.terminated(obs)


def _score(kind: str, inside: np.ndarray, rescued: np.ndarray) -> RegionScore:
    n_in, held, rescuable = int(inside.sum()), int((inside & rescued).sum()), int(rescued.sum())
    if n_in:
        ci = binomtest(n_in - held, n_in).proportion_ci(0.95)
        false, bounds = (n_in - held) / n_in, (float(ci.low), float(ci.high))
    else:
        false, bounds = float("nan"), (float("nan"), float("nan"))
    return RegionScore(kind, n_in, held, held / rescuable if rescuable else 0.0, false, bounds)


def _through_margins(
    spec: CoachSpec, loaded: LoadedModel, names: tuple[str, ...], obs: np.ndarray
) -> np.ndarray:
    """Whether the box of the spec's forecast margins about each observation lies in its rescue region.

    Adaptive margins are those of a forecast made from the state itself with the operating point's
    control (:meth:`pidlab.region.forecast.LinearForecast.observed_inputs`).
    """
    region = region_from_bounds(spec.bounds, names, "rescue", spec.name)
    forecast = spec_forecast(spec.bounds, spec.name)  # a stale or incomplete measurement: one line
    check_adaptive(forecast.adaptive, region)
    try:
        shrunk = margin_region(region, forecast.margin, forecast.bound, forecast.pieces, forecast.adaptive)
    except CoachingError:  # the margins leave nothing of the region
        return np.zeros(len(obs), dtype=bool)
    if not isinstance(shrunk, ClassifierMarginRegion) or forecast.adaptive is None:
        return np.array([shrunk.contains(o) for o in obs], dtype=bool)
    linear = linear_forecast(linearize(loaded), loaded.require_card(), loaded.model)
    inputs = linear.observed_inputs(loaded.model, obs)
    return np.array([shrunk.contains(o, z) for o, z in zip(obs, inputs, strict=True)], dtype=bool)


def measure_domain_coverage(
    spec: CoachSpec,
    loaded: LoadedModel,
    settings: DomainSettings,
    workers: int | None = None,
    progress: Progress | None = None,
    journal: str | Path | None = None,
) -> DomainCoverage:
    """Score ``spec``'s regions over the domain of ``settings`` (see the module docstring).

    Parameters
    ----------
    spec : CoachSpec
        The coach; its certified core (``[bounds]``) is where a rescue ends.
    loaded : LoadedModel
        The model of ``spec.env_id``, with a model card.
    settings : DomainSettings
    workers : int, optional
        Worker processes for the simulations (default: the machine's cores).
    progress : callable, optional
        ``progress(stage, fraction)``.
    journal : path, optional
        A folder that keeps every simulation's outcome as it is found, so that the same measurement
        run again after a stop simulates only what it lacks (:mod:`pidlab.region.journal`).

    Raises
    ------
    RegionError
        A variable that is not a joint's position, sine or velocity; no certified core; a domain
        the termination rule leaves (almost) empty.
    """
    t0 = time.perf_counter()
    s = settings

    def domain_of(card: Any, model: LoadedModel, y_op: np.ndarray) -> Any:
        return state_domain(s.variables, s.half_range, card, model, y_op)

    with simulations(spec, loaded, s, domain_of, workers, progress, journal, s.into) as (est, _, _):
        states = draw_states(est, s.states)
        rescued, obs = est.rescued(states, "labelling")
        names = est.pool.sim.card.observation_names
        grounded = est.grounded
        sims = est.simulations
    reach, reach95 = _reach(states, est.domain, rescued)
    scores = []
    for key, kind in REGION_KINDS.items():
        if key not in (spec.bounds or {}):
            continue
        region = region_from_bounds(spec.bounds, names, key, spec.name)
        inside = np.array([region.contains(o) for o in obs], dtype=bool)
        scores.append(_score(kind, inside, rescued))
    if "rescue" in (spec.bounds or {}) and "forecast" in (spec.bounds or {}):
        scores.append(_score(MODEL_KIND, _through_margins(spec, loaded, names, obs), rescued))
    return DomainCoverage(
        str(spec.env_id), spec.name, s, grounded, int(rescued.sum()), tuple(scores), sims,
        round(time.perf_counter() - t0, 1), reach, reach95, est.reused,
    )  # fmt: skip


def _round_up(x: float) -> float:
    """``x`` >= 0 rounded up to two significant digits (0 stays 0)."""
    if x <= 0:
        return 0.0
    step = 10.0 ** (math.floor(math.log10(x)) - 1)
    return float(f"{math.ceil(round(x / step, 9)) * step:.2g}")


def _reach(
    states: np.ndarray, domain: Any, rescued: np.ndarray
) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Per variable, the largest and the 95th-percentile distance of a rescued state from the box's centre."""
    if not rescued.any():
        nan = (float("nan"),) * states.shape[1]
        return nan, nan
    away = np.abs(states[rescued] - 0.5 * (np.asarray(domain.lower) + np.asarray(domain.upper)))
    return tuple(float(v) for v in away.max(axis=0)), tuple(float(v) for v in np.quantile(away, 0.95, axis=0))
