"""How wrong the model predictor's forecast is, measured where the shield asks it.

:func:`measure_forecast` runs the env behind the exact predictive shield (the spec's rescue region,
the coach taking over at a veto and handing back at half the region) with an agent that acts
uniformly at random: the untrained agent of a training run's start, whose actions are the widest
the forecast must answer for. At every action put to the shield, the exact look-ahead (a copy of
the MuJoCo data) gives the true next observation and :class:`~pidlab.region.forecast.LinearForecast`
its forecast from the same joint state. With ``model = "learned"`` the first ``fit`` actions fit a
network to what the linear forecast misses (:mod:`pidlab.region.dynamics`), and the forecast is the
corrected one from then on. The next ``transitions`` set the margins (the largest
error per region variable); the next ``held_out`` check them: how many true next observations fall
outside the margins of their forecast (``escapes``), and how often the two predictors agree on a
veto (the model's asked of the margin box about its forecast, :func:`margin_region`: a lookup grid's
or a classifier's rescue region).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from pidlab.checks import integer
from pidlab.checks import seed as checked_seed
from pidlab.controller.spec import CoachSpec
from pidlab.errors import CoachingError
from pidlab.lookup import (
    AGREEMENT,
    LOG_LIMIT,
    MAX_WIDTH,
    MODELS,
    SCOPES,
    ForecastError,
    MarginScale,
    ResidualNet,
    region_digest,
)
from pidlab.plant.model import LoadedModel, load_model
from pidlab.region.dynamics import fit_error_scale, fit_residual
from pidlab.region.forecast import (
    ClassifierMarginRegion,
    MarginRegion,
    check_adaptive,
    check_bound,
    check_forecastable,
    check_pieces,
    in_domain,
    learned_forecast,
    margin_region,
    margin_variables,
)
from pidlab.region.takeover import Region, observation_indices, region_from_bounds
from pidlab.rl.coaching import CoachingWrapper
from pidlab.rl.predict import Predictor, forecast_of

MAX_TRANSITIONS = 1_000_000
"""The most actions :func:`measure_forecast` records per part (about an hour of Walker2d)."""

MIN_ADAPTIVE = 1000
"""The fewest transitions adaptive margins are fitted on (and in scope of them, the fewest kept)."""


def _record(
    spec: CoachSpec, loaded: LoadedModel, count: int, seed: int, tick: Callable[[], None]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``count`` transitions of a random agent behind the exact shield.

    Per transition: the true next observation, the linear forecast, and the linear model's inputs
    (the state's and the control's deviations).
    """
    env = CoachingWrapper(gym.make(spec.env_id), spec, mode="takeover", region="rescue", trigger="predictive",
                          handback=0.5, loaded=loaded, seed=seed)  # fmt: skip
    forecast, model = forecast_of(loaded), loaded.model
    truth: list[np.ndarray] = []
    guess: list[np.ndarray] = []
    inputs: list[np.ndarray] = []

    def listener(data: Any, action: Any, obs: np.ndarray) -> None:
        if len(truth) < count:
            z = forecast.inputs(model, data.qpos, data.qvel, data.act, action)
            truth.append(np.array(obs, dtype=float))
            guess.append(forecast.from_inputs(model, z))
            inputs.append(z)
            tick()

    lookahead = env.lookahead
    if not isinstance(lookahead, Predictor):
        raise CoachingError(f"{spec.name}: the exact shield has no exact look-ahead")  # never: predictive
    lookahead.listen(listener)
    rng = np.random.default_rng(seed)
    space: Any = env.action_space
    low, high = np.asarray(space.low, dtype=np.float64), np.asarray(space.high, dtype=np.float64)
    env.reset(seed=seed)
    while len(truth) < count:
        _, _, terminated, truncated, _ = env.step(rng.uniform(low, high).astype(space.dtype))
        if terminated or truncated:
            env.reset()
    env.close()
    return np.array(truth), np.array(guess), np.array(inputs)


def _check_options(transitions: int, held_out: int, seed: int, model: str, fit: int, width: int, epochs: int,
                   bound: str, scope: str, pieces: int | None, adaptive: int) -> None:  # fmt: skip
    integer(transitions, "transitions", CoachingError, low=1, high=MAX_TRANSITIONS, param="transitions")
    integer(adaptive, "adaptive", CoachingError, low=0, high=MAX_TRANSITIONS, param="adaptive")
    if 0 < adaptive < MIN_ADAPTIVE:
        raise CoachingError(
            f"adaptive={adaptive}: expected 0 (constant margins) or at least {MIN_ADAPTIVE} transitions "
            "to fit the error's scale on", param="adaptive",
        )  # fmt: skip
    integer(held_out, "held_out", CoachingError, low=0, high=MAX_TRANSITIONS, param="held_out")
    checked_seed(seed, "seed", CoachingError, param="seed")
    if model not in MODELS:
        raise CoachingError(f"model={model!r}: expected one of {', '.join(MODELS)}", param="model")
    if model == "learned":
        integer(fit, "fit", CoachingError, low=100, high=MAX_TRANSITIONS, param="fit")
    if model == "learned" or adaptive:
        integer(width, "width", CoachingError, low=2, high=MAX_WIDTH, param="width")
        integer(epochs, "epochs", CoachingError, low=1, high=10_000, param="epochs")
    check_bound(bound)
    check_pieces(pieces)
    if scope not in SCOPES:
        raise CoachingError(f"scope={scope!r}: expected one of {', '.join(SCOPES)}", param="scope")


def measure_forecast(
    spec: CoachSpec,
    loaded: LoadedModel | None = None,
    transitions: int = 5000,
    held_out: int = 5000,
    seed: int = 0,
    progress: Callable[[int, int], None] | None = None,
    model: str = "linear",
    fit: int = 30_000,
    width: int = 64,
    epochs: int = 100,
    bound: str = "linear",
    scope: str = "domain",
    pieces: int | None = None,
    adaptive: int = 0,
) -> ForecastError:
    """The forecast's error on the spec's rescue region, and what it does to the shield.

    Parameters
    ----------
    spec : CoachSpec
        A coach with a rescue region derived for the predictive trigger.
    loaded : LoadedModel, optional
        The env's model (default: loaded from the spec's env id).
    transitions, held_out : int
        Actions put to the shield that set the margins, then check them.
    seed : int
        Seeds the env's resets, the random agent and the network's fit.
    progress : callable, optional
        ``progress(done, total)`` after each recorded action.
    model : {"linear", "learned"}
        The linear forecast, or the linear forecast corrected by a network fitted on ``fit``
        actions recorded first (:func:`pidlab.region.dynamics.fit_residual`, ``width`` units per
        hidden layer, ``epochs`` passes); the margins are then measured on actions it never saw.
    bound : {"linear", "interval"}, pieces : int, optional
        How a classifier region's score is bounded over a margin box (:data:`pidlab.lookup.BOUNDS`),
        and the most boxes one query bounds at one halving (None: no cap;
        :func:`pidlab.region.forecast.box_in_classifier`), for the veto agreement and then by the
        shield (a lookup grid is asked exactly either way).
    scope : {"domain", "all"}
        Which transitions set the margins (and count as escapes): those whose forecast lies in the
        rescue region's domain box (:func:`pidlab.region.forecast.domain_box`), or all
        (:data:`pidlab.lookup.SCOPES`).
    adaptive : int
        0: constant margins. Else margins that depend on the state and the action
        (:class:`pidlab.lookup.MarginScale`): ``adaptive`` transitions recorded after the learned
        correction's and before those that set the margins fit a network to the log of the error
        (:func:`pidlab.region.dynamics.fit_error_scale`, ``width``, ``epochs``); the transitions that
        set the margins calibrate its factors, and the held-out ones are checked with the margins of
        each. A classifier rescue region only.

    Returns
    -------
    ForecastError
        Margins, error quantiles, escapes and veto agreement (and the network);
        ``to_table()`` is ``[bounds.forecast]``.

    Raises
    ------
    CoachingError
        Counts below 1 (``held_out`` below 0; ``fit`` below 100; ``adaptive`` neither 0 nor at least
        :data:`MIN_ADAPTIVE`) or above :data:`MAX_TRANSITIONS`, an unknown model or bound,
        ``pieces`` below 1 or for a lookup grid, adaptive margins for a lookup grid, no rescue
        region, a region over a variable no joint-state forecast gives, or no forecast in scope.
    """
    _check_options(transitions, held_out, seed, model, fit, width, epochs, bound, scope, pieces, adaptive)
    loaded = loaded if loaded is not None else load_model(spec.env_id)
    card = loaded.require_card()
    region = _rescue_region(spec, card)
    check_pieces(pieces, region)
    check_adaptive(adaptive, region)
    names = margin_variables(region)
    learned = (int(fit), width, epochs) if model == "learned" else None
    recorded = adaptive + transitions + held_out
    truth, guess, inputs, network = _forecasts(spec, loaded, names, recorded, learned, int(seed), progress)
    asked = _Asked(int(transitions), int(held_out), int(adaptive), (width, epochs, int(seed)), model, bound,
                   scope, pieces)  # fmt: skip
    return _measurement(spec, loaded, region, asked, (truth, guess, inputs), network)


@dataclass(frozen=True)
class _Asked:
    """What :func:`measure_forecast` was asked: counts, the scale network's fit, the model and its proof."""

    transitions: int
    held_out: int
    adaptive: int
    fit: tuple[int, int, int]
    """Width, epochs and seed of a network's fit."""
    model: str
    bound: str
    scope: str
    pieces: int | None


def _measurement(
    spec: CoachSpec, loaded: LoadedModel, region: Region, a: _Asked,
    data: tuple[np.ndarray, np.ndarray, np.ndarray], network: ResidualNet | None,
) -> ForecastError:  # fmt: skip
    """:func:`measure_forecast` of recorded ``data``: true next observations, forecasts, inputs."""
    card = loaded.require_card()
    truth, guess, inputs = data
    names = margin_variables(region)
    cols = observation_indices(names, card.observation_names, "bounds.rescue")
    err = np.abs(truth[:, cols] - guess[:, cols])
    scoped = in_domain(region, guess[:, cols]) if a.scope == "domain" else np.ones(len(err), dtype=bool)
    n, t = a.adaptive, a.transitions
    first = (err[:n], inputs[:n], scoped[:n])
    scale = _error_scale(spec.name, *first, names, a.fit, forecast_of(loaded).blind) if n else None
    err, inputs, scoped = err[n:], inputs[n:], scoped[n:]
    fitted, check = _in_scope(spec.name, err, scoped, t)
    margins = fitted.max(axis=0)
    found = _calibrated(scale, fitted, inputs[:t][scoped[:t]], n) if scale is not None else None
    ceiling = margins if found is None else found.margins(inputs[t:][scoped[t:]], margins)
    held = truth[n + t :], guess[n + t :], inputs[t:]
    agreement = _agreement(region, dict(zip(names, margins, strict=True)), (a.bound, a.pieces, found),
                           card.observation_names, *held)  # fmt: skip
    counted = {"in_scope": len(fitted), "held_out_in_scope": len(check)} if a.scope == "domain" else {}
    return ForecastError(
        model=a.model, variables=names, margins=tuple(float(m) for m in margins),
        median=tuple(float(v) for v in np.median(fitted, axis=0)),
        p99=tuple(float(v) for v in np.quantile(fitted, 0.99, axis=0)), transitions=t,
        held_out=a.held_out, escapes=int(np.any(check > ceiling, axis=1).sum()), seed=a.fit[2],
        agreement=agreement, region=region_digest((spec.bounds or {})["rescue"]), network=network,
        bound=a.bound, scope=a.scope, pieces=a.pieces, adaptive=found, **counted,
    )  # fmt: skip


def _error_scale(
    name: str, err: np.ndarray, inputs: np.ndarray, scoped: np.ndarray, names: tuple[str, ...],
    fit: tuple[int, int, int], blind: tuple[int, ...],
) -> ResidualNet:  # fmt: skip
    """The network of adaptive margins, fitted on the in-scope transitions recorded for it.

    Raises
    ------
    CoachingError
        Fewer than :data:`MIN_ADAPTIVE` of them are in scope.
    """
    if scoped.sum() < MIN_ADAPTIVE:
        raise CoachingError(
            f"{name}: {int(scoped.sum()):,} of the {len(err):,} transitions recorded for adaptive margins "
            f"lie in the rescue region's domain box; at least {MIN_ADAPTIVE:,} are needed: record more "
            "(adaptive)",
            param="adaptive",
        )  # fmt: skip
    return fit_error_scale(inputs[scoped], err[scoped], names, *fit, blind=blind)


def _calibrated(network: ResidualNet, errors: np.ndarray, inputs: np.ndarray, recorded: int) -> MarginScale:
    """Adaptive margins whose factors cover every error of the transitions that set the margins.

    Per variable, the factor is the largest ``error / sigma`` over them (normalized conformal
    calibration, :class:`pidlab.lookup.MarginScale`).
    """
    sigma = np.exp(np.clip(network.correction(inputs), -LOG_LIMIT, LOG_LIMIT))
    factors = (errors / sigma).max(axis=0)
    return MarginScale(network, tuple(float(f) for f in factors), int(recorded))


def _errors(
    name: str, region: Region, truth: np.ndarray, guess: np.ndarray, transitions: int, scope: str
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_in_scope` of the forecast's absolute errors (``truth``, ``guess``: the region's variables)."""
    err = np.abs(truth - guess)
    scoped = in_domain(region, guess) if scope == "domain" else np.ones(len(err), dtype=bool)
    return _in_scope(name, err, scoped, transitions)


def _forecasts(
    spec: CoachSpec,
    loaded: LoadedModel,
    names: tuple[str, ...],
    count: int,
    learned: tuple[int, int, int] | None,
    seed: int,
    progress: Callable[[int, int], None] | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, ResidualNet | None]:
    """``count`` recorded transitions: true next observations, forecasts, inputs, the learned correction.

    With ``learned = (fit, width, epochs)``, ``fit`` transitions are recorded first and the
    correction fitted on them (:func:`pidlab.region.dynamics.fit_residual`); the forecasts returned
    are corrected by it, on transitions it never saw.
    """
    card = loaded.require_card()
    first = learned[0] if learned is not None else 0
    total, done = first + count, [0]

    def tick() -> None:
        done[0] += 1
        if progress is not None:
            progress(done[0], total)

    truth, guess, inputs = _record(spec, loaded, total, seed, tick)
    if learned is None:
        return truth, guess, inputs, None
    cols = observation_indices(names, card.observation_names, "bounds.rescue")
    missed = truth[:first, cols] - guess[:first, cols]
    blind = forecast_of(loaded).blind
    network = fit_residual(inputs[:first], missed, names, learned[1], learned[2], seed, blind)
    guess = learned_forecast(forecast_of(loaded), network, card).correct(guess, inputs)
    return truth[first:], guess[first:], inputs[first:], network


def _in_scope(
    name: str, err: np.ndarray, scoped: np.ndarray, transitions: int
) -> tuple[np.ndarray, np.ndarray]:
    """The errors in scope of the transitions that set the margins, and of the held-out ones.

    Raises
    ------
    CoachingError
        No transition that sets the margins is in scope.
    """
    fitted, check = err[:transitions][scoped[:transitions]], err[transitions:][scoped[transitions:]]
    if not len(fitted):
        raise CoachingError(
            f"{name}: no forecast of the {transitions:,} transitions lies in the rescue region's domain box; "
            "record more (transitions) or set scope 'all'", param="transitions",
        )  # fmt: skip
    return fitted, check


def _rescue_region(spec: CoachSpec, card: Any) -> Region:
    """The spec's rescue region, refused when it has none or tests a variable no forecast gives."""
    if (spec.bounds or {}).get("rescue") is None:
        raise CoachingError(
            f"{spec.name}: the spec has no rescue region; run `pidlab rescue SPEC --write` first"
        )
    region = region_from_bounds(spec.bounds, card.observation_names, "rescue", spec.name)
    check_forecastable(card, margin_variables(region), f"{spec.name}: pidlab forecast")
    return region


def _agreement(
    region: Region,
    margins: dict[str, float],
    proof: tuple[str, int | None, MarginScale | None],
    names: tuple[str, ...],
    truth: np.ndarray,
    guess: np.ndarray,
    inputs: np.ndarray,
) -> dict[str, int]:
    """Veto by veto: the exact look-ahead's state in the region, the forecast's margin box in it.

    ``proof``: the score bound, the cap on a query's boxes and the adaptive margins
    (:func:`margin_region`); ``inputs``: each forecast's (for adaptive margins).
    """
    try:
        shrunk: MarginRegion | ClassifierMarginRegion | None = margin_region(region, margins, *proof)
    except CoachingError:  # nothing fits: the model vetoes every action
        shrunk = None
    counts = dict.fromkeys(AGREEMENT, 0)
    for t, g, z in zip(truth, guess, inputs, strict=True):
        exact = not region.contains(t)
        if shrunk is None:
            model = True
        elif isinstance(shrunk, ClassifierMarginRegion):
            model = not shrunk.contains(g, z)
        else:
            model = not shrunk.contains(g)
        key = "both" if exact and model else "exact_only" if exact else "model_only" if model else "neither"
        counts[key] += 1
    return counts
